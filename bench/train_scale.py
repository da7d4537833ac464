"""A training step at real-capture sizes: time per step for 1 and 2 threads, peak memory, where the time goes.

The real garden SfM points and first camera of ``shared/data/test_garden.npz``
(648x420; ``--scale 2`` for 1296x840), Gaussians from ``from_points`` (SH
degree 3, active), and ``GaussianTrainer.step`` (vanilla, no density control
inside the timed steps) against a target rendered from the second camera.
``--gaussians`` above the 138,766 points repeats them with a seeded jitter of
a tenth of their 3-NN spacing. Each case runs in a fresh process (its own peak
RSS) that times every thread count, alternating them step by step
(``set_num_threads``; the order reversed every round), so that a shared
machine's slow and fast phases fall on all of them alike and the speed-up is
a ratio within one run. Each thread count also gets the cores it kept busy
(CPU time over wall time of its steps): below the thread count, the rest is
serial work or waiting; and, on Linux, how long per step the process's
threads were ready to run but waited for a core (the scheduler's run-queue
delay, ``/proc/self/task/*/schedstat``): on a shared or virtual machine, time
the machine did not give, which no change here can win back.

``--profile`` also times each stage of the step on its own, forward and
backward, through the same public functions the step calls (projection,
SH evaluation, tile binning, the rasterizer, the loss, Adam, the density
statistics), so the table says where the time goes and which stages use the
second core. Memory bandwidth (a numpy triad on 256 MB arrays, one core) gives
the bytes-moved floor of the per-Gaussian stages.

``--cache-limit GB`` sets ``TrainerConfig.cache_limit_gb`` (MLX's buffer
cache) in each case, to weigh buffer reuse against peak RSS.

    python bench/train_scale.py                          # the four cases of the scale table
    python bench/train_scale.py --cases 138766:1 --threads 1,2 --profile --markdown bench/out/train_scale.md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from common import LoadSampler, emit, machine_line, median_ms, peak_rss_mb  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
GARDEN = os.path.join(HERE, "..", "..", "shared", "data", "test_garden.npz")
CASES = "138766:1,1000000:2"  # gaussians:scale
PARAMS_PER_GAUSSIAN = 59  # means 3, quats 4, scales 3, opacity 1, SH 16x3


def _waiting_ms():
    """Milliseconds this process's threads have been ready to run but waited for a core (Linux), else None."""
    total = 0
    try:
        for task in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{task}/schedstat") as f:
                    total += int(f.read().split()[1])
            except FileNotFoundError:  # a thread that just ended
                pass
    except OSError:
        return None
    return total / 1e6


def _alternating(fn, threads: list, repeats: int) -> dict:
    """{threads: (median ms, cores busy, ms waiting for a core per call or None)} of fn, the thread counts taking
    turns (order reversed every round)."""
    from mlx3d.render.raster_cpu import set_num_threads

    wall = {t: [] for t in threads}
    cpu = {t: 0.0 for t in threads}
    waited = {t: 0.0 for t in threads}
    for t in threads:  # warm-up at each thread count
        set_num_threads(t)
        fn()
    for r in range(repeats):
        for t in threads if r % 2 == 0 else threads[::-1]:
            set_num_threads(t)
            w0, c0, t0 = _waiting_ms(), os.times(), time.perf_counter()
            fn()
            t1, c1, w1 = time.perf_counter(), os.times(), _waiting_ms()
            wall[t].append(t1 - t0)
            cpu[t] += (c1.user - c0.user) + (c1.system - c0.system)
            waited[t] = None if w0 is None or waited[t] is None else waited[t] + (w1 - w0)
    set_num_threads(None)
    return {t: (1000.0 * sorted(w)[len(w) // 2], cpu[t] / sum(w), None if waited[t] is None else waited[t] / repeats)
            for t, w in wall.items()}


def _setup(n: int, scale: float):
    import mlx.core as mx
    import numpy as np

    from mlx3d.cameras import Camera
    from mlx3d.splatting import GaussianModel

    data = np.load(GARDEN)
    points, colours = data["means3d"].astype(np.float32), data["colors"]
    rng = np.random.default_rng(0)
    if n > len(points):
        from mlx3d.neighbors import mean_knn_distance

        spacing = np.asarray(mean_knn_distance(points, 3))[:, None]
        reps = -(-n // len(points))
        points = np.concatenate([points] + [points + rng.normal(0, 1, points.shape).astype(np.float32) * 0.1 * spacing for _ in range(reps - 1)])[:n]
        colours = np.tile(colours, (reps, 1))[:n]
    elif n < len(points):
        keep = np.sort(rng.choice(len(points), n, replace=False))
        points, colours = points[keep], colours[keep]
    w, h = int(data["width"]), int(data["height"])
    cams = [Camera(width=w, height=h, fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), viewmat=v).scaled(scale)
            for v, k in zip(data["viewmats"], data["Ks"])]
    model = GaussianModel.from_points(points, colours, sh_degree=3, initial_opacity=0.5)
    sh = np.array(model.params["sh_rest"])
    model.params["sh_rest"] = mx.array(rng.normal(0, 0.05, sh.shape).astype(np.float32))  # degree 3 does real work
    target = mx.clip(model.render(cams[1], background=(0, 0, 0))["image"], 0, 1)
    mx.eval(target)
    return model, cams[0], target


def _profile(trainer, camera, target, threads: list, repeats: int) -> tuple:
    """({threads: {stage: ms}}, tile entries): each stage on its own (forward and backward where it has one)."""
    import mlx.core as mx
    import numpy as np

    from mlx3d.render.binning import bin_tiles
    from mlx3d.render.projection import project_ewa
    from mlx3d.render.rasterize import composite
    from mlx3d.render.sh_color import sh_colors
    from mlx3d.training.adam import all_finite
    from mlx3d.training.metrics import photometric_loss

    p = trainer.model.params
    means, quats, scales, opac = p["means"], p["quats"], mx.exp(p["scales"]), mx.sigmoid(p["opacities"])
    proj = project_ewa(camera, means, quats, scales)
    bins = bin_tiles(proj.means2d, proj.radii, proj.depths, camera.width, camera.height, conics=proj.conics, opacities=opac)
    rgb = sh_colors((p["sh_dc"], p["sh_rest"]), means, camera.center, 3, "cpu")
    mx.eval(proj.means2d, proj.conics, rgb)
    image = composite(proj.means2d, proj.conics, rgb, opac, bins, camera.width, camera.height, mx.zeros(3), "cpu")[0]
    mx.eval(image)
    rng = np.random.default_rng(1)

    def cot(a):
        return mx.array(rng.normal(0, 1, a.shape).astype(np.float32))

    # cotangents drawn once, outside the timed functions
    def project(m, q, s):
        out = project_ewa(camera, m, q, s)
        return out.means2d, out.conics, out.depths
    proj_cots = [cot(o) for o in project(means, quats, scales)]
    rgb_cot, image_cot = cot(rgb), cot(image)
    mx.eval(proj_cots, rgb_cot, image_cot)

    def projection():
        mx.eval(mx.vjp(project, [means, quats, scales], proj_cots))

    def sh_eval():
        def f(dc, rest, m):
            return sh_colors((dc, rest), m, camera.center, 3, "cpu")
        mx.eval(mx.vjp(f, [p["sh_dc"], p["sh_rest"], means], [rgb_cot]))

    def binning():
        b = bin_tiles(proj.means2d, proj.radii, proj.depths, camera.width, camera.height, conics=proj.conics, opacities=opac)
        mx.eval(b.flatten_ids, b.tile_offsets)

    def raster_forward():
        mx.eval(composite(proj.means2d, proj.conics, rgb, opac, bins, camera.width, camera.height, mx.zeros(3), "cpu")[0])

    def raster_both():
        def f(m2, c, r, o):
            return composite(m2, c, r, o, bins, camera.width, camera.height, mx.zeros(3), "cpu")[0]
        mx.eval(mx.vjp(f, [proj.means2d, proj.conics, rgb, opac], [image_cot]))

    def loss():
        mx.eval(mx.value_and_grad(lambda im: photometric_loss(im, target, 0.2, backend="cpu"))(image))

    grads = {k: cot(v) for k, v in p.items()}

    def adam():  # the finiteness check, then the update (moments drift; p stays held here, so p' is fresh, unlike in the step)
        mx.eval(all_finite(grads.values()))
        mx.eval(trainer.optimizer.update(p, grads), trainer.optimizer.m, trainer.optimizer.v)
        trainer.optimizer.step_count -= 1

    grad2d = cot(proj.means2d)
    mx.eval(grad2d)

    visible = proj.radii > 0
    mx.eval(visible)

    def stats():  # what GaussianTrainer.step adds to the density statistics
        trainer.add_screen_statistics(camera, visible, grad2d, proj.radii)

    stages = {
        "projection (fwd+bwd)": projection,
        "SH degree 3 (fwd+bwd)": sh_eval,
        "tile binning": binning,
        "rasterizer forward": raster_forward,
        "rasterizer fwd+bwd": raster_both,
        "loss L1+D-SSIM (fwd+bwd)": loss,
        "Adam (59 params)": adam,
        "density statistics": stats,
    }
    out = {t: {} for t in threads}
    for name, fn in stages.items():
        for t, (ms, *_) in _alternating(fn, threads, repeats).items():
            out[t][name] = ms
    return out, int(bins.flatten_ids.size)


def _bandwidth_gbs() -> float:
    """Sustained bytes/s of c = a + b on 256 MB float32 arrays (numpy, one core): 3 arrays moved."""
    import numpy as np

    n = 64 * 1024 * 1024
    a, b, c = np.ones(n, np.float32), np.ones(n, np.float32), np.empty(n, np.float32)
    ms = median_ms(lambda: np.add(a, b, out=c), 5)
    return 3 * 4 * n / (ms / 1000.0) / 1e9


def child(args) -> None:
    """One case in this process: every thread count, alternating; prints one JSON result per thread count."""
    import mlx.core as mx

    from mlx3d.training import GaussianTrainer, TrainerConfig

    threads = _thread_counts(args.threads)
    model, camera, target = _setup(args.gaussians, args.scale)
    # vanilla during densification (its statistics gathered), with no densification inside the timed steps
    config = TrainerConfig(steps=10**6, densify_from=10**5, densify_until=10**6, sh_increase_every=0, cache_limit_gb=args.cache_limit)
    trainer = GaussianTrainer(model, config, scene_extent=5.0)
    trainer.active_sh_degree = 3
    trainer.step(camera, target)  # warm-up: Adam moments, compilation (then one more per thread count)
    steps = _alternating(lambda: trainer.step(camera, target), threads, args.steps)
    peak = peak_rss_mb()
    stages, entries = _profile(trainer, camera, target, threads, max(3, args.steps)) if args.profile else (None, None)
    bandwidth = _bandwidth_gbs() if args.profile else None
    results = []
    for t in threads:
        r = {"gaussians": len(trainer.model), "width": camera.width, "height": camera.height, "threads": t,
             "ms_per_step": steps[t][0], "cores_busy": steps[t][1], "waiting_ms": steps[t][2], "peak_mb": peak}
        if stages:
            r["stages"] = dict(stages[t], **{"tile entries": entries})
            r["bandwidth_gbs"] = bandwidth
        results.append(r)
    mx.clear_cache()
    print(json.dumps(results))


def _thread_counts(text: str) -> list:
    counts = [int(t) for t in text.split(",") if t]
    if not counts or min(counts) < 1 or len(set(counts)) != len(counts):
        raise ValueError(f"--threads takes distinct positive integers, got {text!r}")
    return counts


def _run(gaussians: int, scale: float, args) -> list:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--gaussians", str(gaussians), "--scale", str(scale),
           "--threads", args.threads, "--steps", str(args.steps)] + (["--profile"] if args.profile else [])
    if args.cache_limit is not None:
        cmd += ["--cache-limit", str(args.cache_limit)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"case {gaussians}:{scale} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=CASES, help=f"comma-separated GAUSSIANS:SCALE (default {CASES}; scale 1 = 648x420)")
    parser.add_argument("--threads", default="1,2", help="comma-separated thread counts, timed in turns in one process (default 1,2)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per case (median reported; default 5)")
    parser.add_argument("--profile", action="store_true", help="also time each stage of the step on its own")
    parser.add_argument("--cache-limit", type=float, metavar="GB",
                        help="TrainerConfig.cache_limit_gb: MLX's buffer cache limit (default: MLX's own, 32 MB on Linux)")
    parser.add_argument("--markdown", metavar="PATH", help="also write the tables here")
    parser.add_argument("--json", metavar="PATH", help="also write the raw results here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--gaussians", type=int, default=138_766, help=argparse.SUPPRESS)
    parser.add_argument("--scale", type=float, default=1.0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    if not os.path.exists(GARDEN):
        raise SystemExit(f"{GARDEN} not found (the garden SfM points and cameras)")
    if args.steps < 1:
        parser.error("--steps must be at least 1")
    try:
        cases = [(int(g), float(s)) for g, s in (c.split(":") for c in args.cases.split(",") if c)]
        threads = _thread_counts(args.threads)
    except ValueError:
        parser.error("--cases takes GAUSSIANS:SCALE pairs and --threads distinct positive integers")
    results = []
    load = LoadSampler()
    load.start()
    for gaussians, scale in cases:
        for r in _run(gaussians, scale, args):
            results.append(r)
            print(f"{r['gaussians']:,} Gaussians {r['width']}x{r['height']} {r['threads']} thread(s): {r['ms_per_step']:,.0f} ms/step, "
                  f"{r['cores_busy']:.2f} cores busy, peak {r['peak_mb']:,.0f} MB", file=sys.stderr, flush=True)
    load.stop.set()
    load.join()
    cores = os.cpu_count() or 1
    lines = [f"Machine: {machine_line()}. Load: {load.line(cores, max(threads) + 0.5 * cores)}.", "",
             f"Median of {args.steps} steps per thread count after warm-up steps, vanilla, SH degree 3 active; the thread counts "
             "take turns step by step in one process per case (so peak RSS is the case's).", "",
             "| Gaussians | image | threads | ms per step | speed-up vs 1 thread | cores busy | waiting for a core (ms/step) | peak RSS (MB) |",
             "|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        one = next((x for x in results if x["gaussians"] == r["gaussians"] and x["width"] == r["width"] and x["threads"] == 1), None)
        speedup = f"{one['ms_per_step'] / r['ms_per_step']:.2f}" if one else ""
        waiting = "" if r.get("waiting_ms") is None else f"{r['waiting_ms']:.1f}"
        lines.append(f"| {r['gaussians']:,} | {r['width']}x{r['height']} | {r['threads']} | {r['ms_per_step']:,.0f} | {speedup} | "
                     f"{r['cores_busy']:.2f} | {waiting} | {r['peak_mb']:,.0f} |")
    if args.profile:
        for key in sorted({(r["gaussians"], r["width"], r["height"]) for r in results}):
            rows = [r for r in results if (r["gaussians"], r["width"], r["height"]) == key]
            names = [k for k in rows[0]["stages"] if k != "tile entries"]
            bw = rows[0]["bandwidth_gbs"]
            floor = 7 * 4 * PARAMS_PER_GAUSSIAN * key[0] / (bw * 1e9) * 1000.0  # Adam: read p, g, m, v; write p, m, v
            lines += ["", f"Stages at {key[0]:,} Gaussians, {key[1]}x{key[2]} ({rows[0]['stages']['tile entries']:,} tile entries; "
                      f"memory bandwidth {bw:.1f} GB/s on one core, so Adam's 7 x 59 floats per Gaussian take at least {floor:.0f} ms):", "",
                      "| stage | " + " | ".join(f"{r['threads']} thread(s) ms" for r in rows) + " | share of the step (1 thread) |",
                      "|---|" + "---:|" * (len(rows) + 1)]
            for name in names:
                share = rows[0]["stages"][name] / rows[0]["ms_per_step"] if "forward" not in name or "bwd" in name else None
                lines.append(f"| {name} | " + " | ".join(f"{r['stages'][name]:,.1f}" for r in rows) + f" | {'' if share is None else f'{share:.0%}'} |")
            def rest(r):  # the step minus its stages timed on their own (the forward-only row is inside fwd+bwd)
                return r["ms_per_step"] - sum(v for k, v in r["stages"].items() if k in names and ("forward" not in k or "bwd" in k))
            lines.append("| everything else (MLX ops between the stages, numpy, Python) | " + " | ".join(f"{rest(r):,.1f}" for r in rows)
                         + f" | {rest(rows[0]) / rows[0]['ms_per_step']:.0%} |")
            lines.append("| whole step | " + " | ".join(f"{r['ms_per_step']:,.1f}" for r in rows) + " | 100% |")
    emit("\n".join(lines) + "\n", args.markdown)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
