"""Benchmark the renderer: scenes x rasterizer paths, forward and forward+backward.

Scenes (seeded random Gaussians in front of a pinhole camera):
  sparse-10k   10,000 splats at 512x512
  hd-100k     100,000 splats at 1280x720
  dense-20k    20,000 splats at 256x256 (a few hundred contributions per pixel)
  mem-100k    100,000 splats at 512x512 (the memory target)
Paths: reference (pure MLX), cpu kernel with 1 thread, cpu kernel with all threads.
Each (scene, path) runs in a fresh process: median of --repeat timings after a
warm-up, and the peak resident memory of the process. Targets on a 2-core
machine: hd-100k forward <= 150 ms; dense-20k forward+backward <= 200 ms; the
cpu kernel >= 5x faster than the reference; mem-100k forward+backward peak <= 300 MB.

    python bench/render.py [--quick] [--repeat 5] [--markdown PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

from common import emit, peak_rss_mb  # bench/ is on sys.path when run as a script

SCENES = {
    "sparse-10k": (10_000, 512, 512, (0.01, 0.05)),
    "hd-100k": (100_000, 1280, 720, (0.003, 0.02)),
    "dense-20k": (20_000, 256, 256, (0.03, 0.12)),
    "mem-100k": (100_000, 512, 512, (0.003, 0.02)),
}
PATHS = ("reference", "cpu-1", "cpu-all")
REFERENCE_SCENES = ("sparse-10k", "dense-20k")  # the reference path is too slow for the large ones


def _make_scene(name):
    import mlx.core as mx
    import numpy as np

    from mlx3d.cameras import Camera

    n, width, height, (s_lo, s_hi) = SCENES[name]
    rng = np.random.default_rng(0)
    cam = Camera.look_at(eye=(0.0, -3.0, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=width, height=height, hfov=60.0)
    arrays = {
        "means": rng.uniform(-1.0, 1.0, (n, 3)),
        "quats": rng.normal(size=(n, 4)),
        "scales": np.exp(rng.uniform(np.log(s_lo), np.log(s_hi), (n, 3))),
        "opacities": rng.uniform(0.05, 0.9, n),
        "colors": rng.uniform(0, 1, (n, 3)),
    }
    return cam, {k: mx.array(v.astype(np.float32)) for k, v in arrays.items()}


def _child(scene: str, path: str, repeat: int) -> None:
    import mlx.core as mx
    import numpy as np

    from mlx3d.render import render_gaussians

    if path.startswith("cpu"):
        from mlx3d.render.raster_cpu import set_num_threads

        set_num_threads(1 if path == "cpu-1" else 0)
    backend = "reference" if path == "reference" else "cpu"
    cam, s = _make_scene(scene)
    names = ("means", "quats", "scales", "opacities", "colors")

    inputs = [s[k] for k in names]

    def loss(*args):
        return render_gaussians(cam, *args[:4], colors=args[4], backend=backend)["image"].sum()

    grad_fn = mx.value_and_grad(loss, argnums=tuple(range(5)))

    def run_forward():
        return [render_gaussians(cam, *inputs[:4], colors=inputs[4], backend=backend)["image"]]

    def run_backward():
        value, grads = grad_fn(*inputs)
        return [value, *grads]

    def timed(run):
        times = []
        for i in range(repeat + 1):  # the first run warms up
            t0 = time.perf_counter()
            mx.eval(*run())
            if i:
                times.append(time.perf_counter() - t0)
        return float(np.median(times)) * 1000, float(np.std(times)) * 1000

    fwd_ms, fwd_sd = timed(run_forward)
    bwd_ms, bwd_sd = timed(run_backward)
    out = render_gaussians(cam, *inputs[:4], colors=inputs[4], backend=backend)
    from mlx3d.render import bin_gaussians

    sorted_ids, *_ = bin_gaussians(out["means2d"], out["radii"], out["depths"], cam.width, cam.height, conics=out["conics"], opacities=inputs[3])
    per_pixel = sorted_ids.size * 256 / (cam.width * cam.height)
    print(json.dumps({"fwd_ms": fwd_ms, "fwd_sd": fwd_sd, "bwd_ms": bwd_ms, "bwd_sd": bwd_sd, "peak_mb": peak_rss_mb(), "per_pixel": per_pixel}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only sparse-10k and dense-20k")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], args.child[1], args.repeat)
        return
    scenes = ["sparse-10k", "dense-20k"] if args.quick else list(SCENES)
    rows = []
    for scene in scenes:
        for path in PATHS:
            if path == "reference" and scene not in REFERENCE_SCENES:
                continue
            env = dict(os.environ, MALLOC_MMAP_MAX_="0") if path == "reference" else None
            res = subprocess.run([sys.executable, __file__, "--child", scene, path, "--repeat", str(args.repeat)], capture_output=True, text=True, env=env)
            if res.returncode != 0:
                print(res.stderr[-2000:], file=sys.stderr)
                rows.append((scene, path, None))
                continue
            r = json.loads(res.stdout.strip().splitlines()[-1])
            rows.append((scene, path, r))
            print(f"{scene:11s} {path:9s} fwd {r['fwd_ms']:8.1f} ms  fwd+bwd {r['bwd_ms']:8.1f} ms  peak {r['peak_mb']:6.0f} MB  {r['per_pixel']:.0f} contrib/px", file=sys.stderr)

    def get(scene, path, key):
        for s, p, r in rows:
            if s == scene and p == path and r:
                return r[key]
        return None

    n_cores = os.cpu_count()
    lines = [
        f"Renderer on {platform.machine()}, {n_cores} cores, Python {platform.python_version()} (median of {args.repeat}; one process per row)",
        "",
        "| scene | splats | image | path | forward (ms) | forward+backward (ms) | peak RSS (MB) | tile entries/pixel |",
        "|---|---:|---|---|---:|---:|---:|---:|",
    ]
    for scene, path, r in rows:
        n, w, h, _ = SCENES[scene]
        if r is None:
            lines.append(f"| {scene} | {n:,} | {w}x{h} | {path} | failed | | | |")
            continue
        lines.append(f"| {scene} | {n:,} | {w}x{h} | {path} | {r['fwd_ms']:.1f} ± {r['fwd_sd']:.1f} | {r['bwd_ms']:.1f} ± {r['bwd_sd']:.1f} | {r['peak_mb']:.0f} | {r['per_pixel']:.0f} |")
    lines.append("")
    checks = []
    hd = get("hd-100k", "cpu-all", "fwd_ms")
    if hd is not None:
        checks.append(f"hd-100k forward (all threads): {hd:.0f} ms (target <= 150)")
    dense = get("dense-20k", "cpu-all", "bwd_ms")
    if dense is not None:
        checks.append(f"dense-20k forward+backward (all threads): {dense:.0f} ms (target <= 200)")
    for scene in REFERENCE_SCENES:
        ref, cpu = get(scene, "reference", "bwd_ms"), get(scene, "cpu-all", "bwd_ms")
        if ref and cpu:
            checks.append(f"{scene}: cpu kernel {ref / cpu:.1f}x faster than the reference, forward+backward (target >= 5)")
    mem = get("mem-100k", "cpu-all", "peak_mb")
    if mem is not None:
        checks.append(f"mem-100k forward+backward peak RSS: {mem:.0f} MB (target <= 300)")
    lines += [f"- {c}" for c in checks]
    table = "\n".join(lines) + "\n"
    emit(table, args.markdown)


if __name__ == "__main__":
    main()
