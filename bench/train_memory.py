"""Peak memory and time per step of training at a given Gaussian count and image size.

Each method runs in a fresh subprocess (so that its peak RSS is its own): N
random Gaussians in a cube (``GaussianModel.from_points``), eight 256x256
views on a ring, targets rendered from a quarter of the points, and
``GaussianTrainer.step`` for ``--steps`` steps with density control every 20
steps (MCMC capped at N, vanilla uncapped). Target: peak RSS < 1 GB at 200k
Gaussians, 256x256.

    python bench/train_memory.py                          # 200k Gaussians, 256², vanilla and mcmc
    python bench/train_memory.py --gaussians 500000 --size 512 --markdown bench/out/train_memory.md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from common import emit, peak_rss_mb  # bench/ is on sys.path when run as a script

TARGET_MB = 1024.0


def child(args) -> None:
    import mlx.core as mx
    import numpy as np

    from mlx3d.cameras import Camera
    from mlx3d.splatting import GaussianModel
    from mlx3d.training import GaussianTrainer, TrainerConfig

    rng = np.random.default_rng(0)
    n, size = args.gaussians, args.size
    points = (rng.normal(size=(n, 3)) * 0.6).astype(np.float32)
    colours = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    cams = [Camera.look_at(eye=(4 * np.cos(a), 4 * np.sin(a), 1.0), at=(0, 0, 0), up=(0, 0, 1), width=size, height=size, hfov=50)
            for a in angles]
    truth = GaussianModel.from_points(points[: n // 4], colours[: n // 4])
    targets = [mx.clip(truth.render(c, background=(1, 1, 1))["image"], 0, 1) for c in cams]
    mx.eval(targets)
    del truth
    config = TrainerConfig(method=args.child, steps=args.steps, densify_from=10, densify_every=20, background="white",
                           max_gaussians=n if args.child == "mcmc" else None)
    trainer = GaussianTrainer(GaussianModel.from_points(points, colours), config, scene_extent=4.0)
    trainer.step(cams[0], targets[0])  # warm-up (first-call allocations count in the peak, not in the time)
    t0 = time.perf_counter()
    for i in range(1, args.steps):
        info = trainer.step(cams[i % 8], targets[i % 8])
    seconds = (time.perf_counter() - t0) / max(args.steps - 1, 1)
    print(json.dumps({"method": args.child, "gaussians": info["num_gaussians"], "s_per_step": seconds, "peak_mb": peak_rss_mb()}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=200_000)
    parser.add_argument("--size", type=int, default=256, help="image width and height in pixels")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--methods", default="vanilla,mcmc")
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child(args)
    rows = []
    load = os.getloadavg()[0]
    for method in args.methods.split(","):
        cmd = [sys.executable, __file__, "--child", method, "--gaussians", str(args.gaussians), "--size", str(args.size),
               "--steps", str(args.steps)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    load = max(load, os.getloadavg()[0])
    from mlx3d.report.accuracy import machine_info

    m = machine_info()
    threads = os.environ.get("MLX3D_NUM_THREADS", "all")
    lines = [f"Training memory: {args.gaussians:,} initial Gaussians, {args.size}x{args.size} images, {args.steps} steps; "
             f"{m['cpu']} ({m['machine']}, {m['cores']} cores), threads {threads}, 1-minute load average up to {load:.1f}", "",
             "| method | Gaussians at the end | s per step | peak RSS (MB) | of the 1 GB target |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {r['method']} | {r['gaussians']:,} | {r['s_per_step']:.3f} | {r['peak_mb']:.0f} | {r['peak_mb'] / TARGET_MB:.0%} |" for r in rows]
    emit("\n".join(lines), args.markdown)


if __name__ == "__main__":
    main()
