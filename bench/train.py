"""Benchmark training: steps/s, peak memory and held-out PSNR/SSIM at milestones.

    python bench/train.py DATA_DIR [--milestones 1000,3000,7000] [--methods vanilla,mcmc]
                          [--max-gaussians 100000] [--markdown PATH]

DATA_DIR is any dataset folder ``mlx3d.datasets.load_dataset`` reads; the
README's numbers use the captured demo scene (``make demo`` writes it to
``demo_out/dataset``: 256², about 70 training and 10 held-out views). Each
method trains in a fresh process; evaluation time is not counted in steps/s.
Anchor (OpenSplat 1.1.5, CPU mode, same machine, a similar scene): 2.8 steps/s
on average over 2000 steps (0.44 s/step at 32k Gaussians), 3.6 GB peak, 28.1 dB
after 1000 and 31.3 dB after 2000 steps on a held-out view.
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


def _child(data: str, method: str, milestones: list[int], max_gaussians: int | None, background: str) -> None:
    from mlx3d.datasets import load_dataset
    from mlx3d.splatting import GaussianModel
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.evaluate import BACKGROUNDS, evaluate

    dataset = load_dataset(data)
    model = GaussianModel.from_points(dataset.points, dataset.point_colors, sh_degree=3)
    config = TrainerConfig(method=method, steps=milestones[-1], max_gaussians=max_gaussians, background=BACKGROUNDS[background])
    trainer = GaussianTrainer(model, config, scene_extent=dataset.scene_extent())
    rows, trained, done = [], 0.0, 0
    for milestone in milestones:
        t0 = time.perf_counter()
        trainer.fit(dataset, steps=milestone - done)
        trained += time.perf_counter() - t0
        done = milestone
        report = evaluate(trainer.model, dataset, "test", BACKGROUNDS[background])
        rows.append({"steps": milestone, "seconds": trained, "steps_per_s": milestone / trained, "gaussians": len(trainer.model),
                     "psnr": report["psnr"], "ssim": report["ssim"], "peak_mb": peak_rss_mb()})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print(json.dumps(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", metavar="DATA_DIR")
    parser.add_argument("--milestones", default="1000,3000,7000")
    parser.add_argument("--methods", default="vanilla,mcmc")
    parser.add_argument("--max-gaussians", type=int, default=100_000)
    parser.add_argument("--background", choices=("black", "white"), default="white")
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--child", metavar="METHOD", help=argparse.SUPPRESS)
    args = parser.parse_args()
    milestones = sorted(int(m) for m in args.milestones.split(","))
    if args.child:
        _child(args.data, args.child, milestones, args.max_gaussians, args.background)
        return
    results = {}
    for method in args.methods.split(","):
        cmd = [sys.executable, __file__, args.data, "--child", method, "--milestones", args.milestones, "--max-gaussians", str(args.max_gaussians), "--background", args.background]
        out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=True)
        results[method] = json.loads(out.stdout.strip().splitlines()[-1])
    lines = [
        f"Training on {os.path.basename(os.path.abspath(args.data))} ({platform.machine()}, {os.cpu_count()} cores; cap {args.max_gaussians:,} Gaussians)",
        "",
        "| method | steps | train time (s) | steps/s | Gaussians | held-out PSNR (dB) | held-out SSIM | peak RSS (MB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for method, rows in results.items():
        for r in rows:
            lines.append(f"| {method} | {r['steps']:,} | {r['seconds']:.0f} | {r['steps_per_s']:.2f} | {r['gaussians']:,} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['peak_mb']:.0f} |")
    emit("\n".join(lines) + "\n", args.markdown)


if __name__ == "__main__":
    main()
