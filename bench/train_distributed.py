"""Data-parallel training: 2 ranks x 1 thread against 1 rank x 2 threads, communication, a projection to N machines.

    python bench/train_distributed.py [--cases 138766:1,1000000:2] [--steps 5]
                                      [--scene bench_data/scenes/outdoor --scene-steps 3000]
                                      [--markdown docs/benchmarks/train_distributed.md]

**Step time.** Per case (Gaussians : image scale, on the garden scene of
``bench/train_scale.py``: its SfM points and cameras, 648x420 at scale 1), a
training step at batch size 2 (two views: the first two garden cameras, each
against a target rendered from the next), vanilla, SH degree 3, no density
control in the timed steps:

- *1 rank x 2 threads*: one process renders both views, the CPU kernels on
  2 threads;
- *2 ranks x 1 thread*: two processes with the ring backend on localhost,
  one view each, 1 thread each, the gradients summed by
  ``mx.distributed.all_sum`` over TCP. The ranks are started directly with
  the environment ``mlx.launch`` gives them (``MLX_RANK``, ``MLX_HOSTFILE``),
  and once more under ``mlx.launch`` itself: its output loop keeps about a
  core busy while the ranks run, which on a machine with few cores slows
  the ranks.

Each takes the median of ``--steps`` steps after a warm-up step. For the ranks
the table also gives the time inside the all-sum per step (rank 0's; it
includes waiting for the slower rank) and the payload each rank sends per
step (the flat float32 buffer of 59 gradients per Gaussian, plus the losses;
a ring all-reduce moves 2 (W-1)/W of it over each link).

**Projection.** From those numbers, the step time on N machines with one view
each (batch N): ``t(N) = t_view + t_comm(N)``, where ``t_view`` is the 2-rank
run's step time less its all-sum time (one view on one core: on the users'
machines it is their own per-view time, so the table is a ratio to it), and
``t_comm(N) = 2 (N - 1) / N * payload / bandwidth + 2 (N - 1) * latency``
(ring all-reduce). Links: 10 Gb/s Ethernet at 1.0 GB/s effective and 50 us per
hop; Thunderbolt 5 (80 Gb/s) at 6 GB/s effective and 10 us per hop. Views per
second ``N / t(N)`` against one machine's ``1 / t_view`` is the speed-up.

**Equivalence on a scene** (``--scene``): ``mlx3d train --batch-size 2
--steps-scaler 0.5`` in one process and on 2 ranks, held-out PSNR and worst
view of each, and whether the two output files are byte-identical.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time

from common import LoadSampler, emit, machine_line  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
CASES = "138766:1,1000000:2"
LINKS = {"10 Gb/s Ethernet": (1.0e9, 50e-6), "Thunderbolt 5": (6.0e9, 10e-6)}  # effective bytes/s, seconds per hop
MACHINES = (1, 2, 4, 8)


def _views(n: int, scale: float):
    """(model, [(camera, target)] x 2) of the garden case."""
    import mlx.core as mx
    import numpy as np

    sys.path.insert(0, HERE)
    from train_scale import GARDEN, _setup

    from mlx3d.cameras import Camera

    model, camera, _ = _setup(n, scale)
    data = np.load(GARDEN)
    w, h = int(data["width"]), int(data["height"])
    cams = [Camera(width=w, height=h, fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), viewmat=v).scaled(scale)
            for v, k in zip(data["viewmats"], data["Ks"])]
    views = []
    for i in range(2):
        target = mx.clip(model.render(cams[i + 1], background=(0, 0, 0))["image"], 0, 1)
        mx.eval(target)
        views.append((cams[i], target))
    return model, views


def child(args) -> None:
    """One timing run in this process (``--child single``) or this rank (``--child ranks``); prints JSON."""
    from mlx3d.render.raster_cpu import set_num_threads
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.distributed import init
    from mlx3d.training.trainer import TrainingView

    ranks = init("ring") if args.child == "ranks" else None
    set_num_threads(1 if ranks is not None else 2)
    model, views = _views(args.gaussians, args.scale)
    config = TrainerConfig(steps=10**6, densify_from=10**5, densify_until=10**6, sh_increase_every=0, batch_size=2)
    trainer = GaussianTrainer(model, config, scene_extent=5.0, ranks=ranks)
    mine = [TrainingView(c, t, background=(0.0, 0.0, 0.0), image_index=i) for i, (c, t) in enumerate(views)]
    if ranks is not None:
        mine = [mine[p] for p in ranks.positions(2)]
    trainer.step_batch(mine, [0, 1])  # warm-up
    times, comm, sent = [], [], []
    for _ in range(args.steps):
        c0, b0 = (ranks.seconds, ranks.bytes_sent) if ranks else (0.0, 0)
        t0 = time.perf_counter()
        trainer.step_batch(mine, [0, 1])
        times.append(time.perf_counter() - t0)
        if ranks:
            comm.append(ranks.seconds - c0)
            sent.append(ranks.bytes_sent - b0)
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    if ranks is None or ranks.rank == 0:
        print(json.dumps({"step_s": med(times), "comm_s": med(comm) if comm else 0.0, "bytes": med(sent) if sent else 0,
                          "gaussians": len(trainer.model)}), flush=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ranks(cmd: list, launcher: bool, env=None, cwd=None) -> str:
    """Output of ``cmd`` run as 2 ring ranks on localhost: under mlx.launch, or started directly with its environment."""
    env = dict(os.environ if env is None else env)
    if launcher:
        launch = os.path.join(os.path.dirname(sys.executable), "mlx.launch")
        done = subprocess.run([launch, "--backend", "ring", "-n", "2", "--hosts", "127.0.0.1", "--starting-port", str(_free_port()),
                               "--"] + cmd, capture_output=True, text=True, env=env, cwd=cwd)
        return done.stdout + done.stderr
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        f.write(json.dumps([[f"127.0.0.1:{_free_port()}"], [f"127.0.0.1:{_free_port()}"]]))
    try:
        procs = [subprocess.Popen(cmd, env=dict(env, MLX_RANK=str(r), MLX_HOSTFILE=f.name), cwd=cwd, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True) for r in range(2)]
        return "".join(p.communicate()[0] for p in procs)
    finally:
        os.unlink(f.name)


def _last_json(text: str) -> dict:
    lines = [line for line in text.splitlines() if line.startswith("{")]
    if not lines:
        raise RuntimeError(f"no result in:\n{text[-3000:]}")
    return json.loads(lines[-1])


def run_case(n: int, scale: float, steps: int) -> dict:
    base = [sys.executable, os.path.abspath(__file__), "--gaussians", str(n), "--scale", str(scale), "--steps", str(steps), "--child"]
    single = subprocess.run(base + ["single"], capture_output=True, text=True, check=True)
    return {"gaussians": n, "scale": scale, "single": _last_json(single.stdout), "ranks": _last_json(_ranks(base + ["ranks"], False)),
            "launched": _last_json(_ranks(base + ["ranks"], True))}


def projection(case: dict) -> list:
    """[(link, N, step s, views/s speed-up)] from a case's 2-rank numbers."""
    r = case["ranks"]
    t_view = r["step_s"] - r["comm_s"]
    rows = []
    for link, (bandwidth, latency) in LINKS.items():
        for n in MACHINES:
            t_comm = 2 * (n - 1) / n * r["bytes"] / bandwidth + 2 * (n - 1) * latency
            t = t_view + t_comm
            rows.append((link, n, t, (n / t) / (1 / t_view)))
    return rows


def scene_equivalence(scene: str, steps: int, folder: str) -> dict:
    """Held-out PSNR of mlx3d train --batch-size 2 in one process and on 2 ranks, and whether the files are equal
    (the models and side-by-side renders of the held-out views go to ``folder``)."""
    folder = os.path.abspath(folder)
    os.makedirs(folder, exist_ok=True)
    name_of = os.path.basename(os.path.normpath(scene))
    common = ["-m", "mlx3d", "train", os.path.abspath(scene), "--batch-size", "2", "--steps", str(steps), "--steps-scaler", "0.5",
              "--random-points", "20000", "--eval"]
    runs, files = {}, []
    for name, ranks in (("1 rank x 2 threads", 1), ("2 ranks x 1 thread", 2)):
        path = os.path.join(folder, f"{name_of}_{ranks}rank.ply")
        cmd = [sys.executable] + common + ["--out", path]
        env = dict(os.environ, MLX3D_NUM_THREADS=str(3 - ranks))
        t0 = time.perf_counter()
        if ranks == 1:
            done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=folder)
            text = done.stdout + done.stderr
        else:
            text = _ranks(cmd, False, env=env, cwd=folder)
        seconds = time.perf_counter() - t0
        psnr = [line for line in text.splitlines() if line.startswith("held-out views:")]
        worst = [line for line in text.splitlines() if line.startswith("worst view:")]
        if not psnr or not os.path.exists(path):
            raise RuntimeError(f"{name} failed:\n{text[-3000:]}")
        runs[name] = {"psnr": float(psnr[0].split("PSNR ")[1].split(" dB")[0]), "worst": worst[0], "seconds": seconds}
        with open(path, "rb") as f:
            files.append(f.read())
    return {"scene": name_of, "steps": steps // 2, "runs": runs, "identical": files[0] == files[1]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default=CASES, help=f"comma-separated GAUSSIANS:SCALE (default {CASES}; scale 1 = 648x420)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per run (median; default 5)")
    parser.add_argument("--scene", metavar="DATA_DIR", help="also train this scene both ways and compare held-out PSNR")
    parser.add_argument("--scene-steps", type=int, default=3000, help="views per run of --scene, over 2 (default 3000: 1500 steps of 2)")
    parser.add_argument("--out", default=os.path.join("bench", "out", "train_distributed"), metavar="DIR",
                        help="--scene: the trained models and their held-out renders (default bench/out/train_distributed)")
    parser.add_argument("--markdown", metavar="PATH", help="also write the tables here")
    parser.add_argument("--child", choices=("single", "ranks"), help=argparse.SUPPRESS)
    parser.add_argument("--gaussians", type=int, default=138_766, help=argparse.SUPPRESS)
    parser.add_argument("--scale", type=float, default=1.0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    load = LoadSampler()
    load.start()
    cases = []
    for spec in args.cases.split(","):
        g, s = spec.split(":")
        cases.append(run_case(int(g), float(s), args.steps))
        print(f"case {spec} done", file=sys.stderr, flush=True)
    scene = scene_equivalence(args.scene, args.scene_steps, args.out) if args.scene else None
    load.stop.set()
    load.join()

    lines = ["# Data-parallel training: ranks against threads", "", machine_line() + f", {time.strftime('%Y-%m-%d')}", "",
             load.line(os.cpu_count() or 1, 3.5), "",  # its own: 2 ranks, and mlx.launch's loop (about 1.3 cores) in one run
             f"Batch size 2, vanilla, SH degree 3, median of {args.steps} steps after a warm-up step "
             "(`python bench/train_distributed.py`).", "",
             "| Gaussians | image | 1 rank x 2 threads (s/step) | 2 ranks x 1 thread (s/step) | ratio | all-sum (s/step) "
             "| sent per rank per step | 2 ranks under mlx.launch (s/step) |",
             "|---:|---|---:|---:|---:|---:|---:|---:|"]
    for c in cases:
        w, h = int(round(648 * c["scale"])), int(round(420 * c["scale"]))
        one, two = c["single"], c["ranks"]
        lines.append(f"| {c['gaussians']:,} | {w}x{h} | {one['step_s']:.3f} | {two['step_s']:.3f} | {two['step_s'] / one['step_s']:.2f} "
                     f"| {two['comm_s']:.3f} | {two['bytes'] / 1e6:.1f} MB ({two['bytes'] / c['gaussians']:.0f} B per Gaussian) "
                     f"| {c['launched']['step_s']:.3f} |")
    rates = ", ".join(f"{c['ranks']['bytes'] / c['ranks']['comm_s'] / 1e9:.2f} GB/s" for c in cases if c["ranks"]["comm_s"] > 0)
    lines += ["", "Ratio: 2 ranks' step time over 1 rank's (below 1: the ranks are faster), the ranks started directly. "
              "The all-sum time is rank 0's, waiting for the other rank included. Over loopback the all-sum moved "
              f"{rates} (payload over all-sum time): both ranks' TCP traffic and sums run on the same 2 cores that render, "
              "so on this machine the ranks lose what they gain; on separate machines the link and its rate decide (below).", ""]
    lines += ["## Projection to N machines (one view each, batch N)", "",
              "t(N) = t_view + 2 (N-1)/N x payload / bandwidth + 2 (N-1) x latency; t_view = the 2-rank step time less its "
              "all-sum time. Assumed links: " + "; ".join(f"{k}: {b / 1e9:.0f} GB/s effective, {lat * 1e6:.0f} us per hop"
                                                           for k, (b, lat) in LINKS.items()) + ".", ""]
    for c in cases:
        lines += [f"**{c['gaussians']:,} Gaussians** (t_view {c['ranks']['step_s'] - c['ranks']['comm_s']:.3f} s on one core here; "
                  f"payload {c['ranks']['bytes'] / 1e6:.1f} MB)", "", "| link | machines | s/step | views/s vs one machine |", "|---|---:|---:|---:|"]
        lines += [f"| {link} | {n} | {t:.3f} | {speedup:.2f}x |" for link, n, t, speedup in projection(c)]
        lines.append("")
    if scene:
        lines += [f"## Equivalence on `{scene['scene']}`", "",
                  f"`mlx3d train --batch-size 2 --steps-scaler 0.5 --steps {2 * scene['steps']}` ({scene['steps']} steps of 2 views), "
                  "`--random-points 20000`, held-out views:", "", "| run | PSNR | worst view | wall time |", "|---|---:|---|---:|"]
        for name, r in scene["runs"].items():
            lines.append(f"| {name} | {r['psnr']:.2f} dB | {r['worst']} | {r['seconds']:.0f} s |")
        lines += ["", f"Output files byte-identical: {'yes' if scene['identical'] else 'no'}.", ""]
    emit("\n".join(lines) + "\n", args.markdown)


if __name__ == "__main__":
    main()
