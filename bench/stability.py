"""Long-run stability: train each method for many steps and check everything stays finite.

    python bench/stability.py DATA_DIR [--steps 30000] [--methods vanilla,mcmc,2dgs]
                              [--every 1000] [--max-gaussians 100000] [--jobs N] [--markdown PATH]

Each method trains in its own process on DATA_DIR (``make demo`` writes the
demo scene to ``demo_out/dataset``), white background. Every ``--every``
steps the child reports the mean loss, the training PSNR, the Gaussian count,
the largest |value| of every raw parameter and the extreme scales, and checks
that all parameters and Adam moments are finite (the trainer itself stops
with ``TrainingError`` on a non-finite loss or gradient). The table lists the
last report of each method and whether it finished; the exit code is 1 when
any method did not. ``--jobs N`` trains N methods at once, splitting the
cores between them (``MLX3D_NUM_THREADS``); on a small machine several
one-thread processes get through more steps than one process on all cores.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time

from common import emit, peak_rss_mb  # bench/ is on sys.path when run as a script


def _child(data: str, method: str, steps: int, every: int, max_gaussians: int) -> None:
    import mlx.core as mx
    import numpy as np

    from mlx3d.datasets import load_dataset
    from mlx3d.splatting import GaussianModel
    from mlx3d.training import GaussianTrainer, TrainerConfig, TrainingError
    from mlx3d.training.evaluate import BACKGROUNDS

    dataset = load_dataset(data)
    model = GaussianModel.from_points(dataset.points, dataset.point_colors, sh_degree=3)
    config = TrainerConfig(method=method, steps=steps, max_gaussians=max_gaussians, background=BACKGROUNDS["white"])
    trainer = GaussianTrainer(model, config, scene_extent=dataset.scene_extent())
    t0, losses = time.perf_counter(), []

    def report(status: str) -> None:
        params = {k: np.array(v) for k, v in trainer.model.params.items()}
        moments = [np.array(m) for m in list(trainer.optimizer.m.values()) + list(trainer.optimizer.v.values())]
        finite = all(np.isfinite(v).all() for v in params.values()) and all(np.isfinite(m).all() for m in moments)
        scales = np.exp(params["scales"]) if params["scales"].size else np.zeros(1)
        row = {
            "method": method, "step": trainer.step_count, "status": status if finite else "non-finite state", "seconds": time.perf_counter() - t0,
            "loss": float(np.mean(losses[-every:])) if losses else float("nan"), "psnr": last.get("psnr", float("nan")),
            "gaussians": len(trainer.model), "max_abs": {k: float(np.abs(v).max()) if v.size else 0.0 for k, v in params.items()},
            "scale_min": float(scales.min()), "scale_max": float(scales.max()), "peak_mb": peak_rss_mb(),
        }
        print(json.dumps(row), flush=True)
        if not finite:
            sys.exit(1)

    last = {}
    try:
        for _ in range(steps // every):
            for info in trainer.fit(dataset, steps=every):
                losses.append(info["loss"])
                last = info
            report("running" if trainer.step_count < steps else "finished")
    except TrainingError as exc:
        report(f"stopped: {exc}")
        sys.exit(1)
    mx.clear_cache()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", metavar="DATA_DIR")
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--methods", default="vanilla,mcmc,2dgs")
    parser.add_argument("--every", type=int, default=1000)
    parser.add_argument("--max-gaussians", type=int, default=100_000)
    parser.add_argument("--jobs", type=int, default=1, help="methods trained at once (default 1)")
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--child", metavar="METHOD", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.data, args.child, args.steps, args.every, args.max_gaussians)
        return 0
    methods = args.methods.split(",")
    jobs = max(1, min(args.jobs, len(methods)))
    env = dict(os.environ, MLX3D_NUM_THREADS=str(max(1, (os.cpu_count() or 1) // jobs))) if jobs > 1 else None
    rows, status, slots = {}, {}, threading.Semaphore(jobs)

    def run(method: str) -> None:
        with slots:
            cmd = [sys.executable, __file__, args.data, "--child", method, "--steps", str(args.steps), "--every", str(args.every), "--max-gaussians", str(args.max_gaussians)]
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env)
            last = None
            for line in proc.stdout:
                last = json.loads(line)
                print(f"{method}: step {last['step']:,} loss {last['loss']:.4f} PSNR {last['psnr']:.2f} Gaussians {last['gaussians']:,} ({last['status']}, {last['seconds']:.0f} s)", file=sys.stderr, flush=True)
            status[method] = proc.wait() == 0 and last is not None and last["status"] == "finished"
            rows[method] = last or {"method": method, "status": "no report"}

    threads = [threading.Thread(target=run, args=(m,)) for m in methods]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    failed = not all(status.get(m, False) for m in methods)
    rows = [rows.get(m, {"method": m, "status": "no report"}) for m in methods]
    lines = [
        f"Stability on {os.path.basename(os.path.abspath(args.data))} ({platform.machine()}, {os.cpu_count()} cores): {args.steps:,} steps per method, "
        f"at most {args.max_gaussians:,} Gaussians, {jobs} at a time",
        "",
        "| method | status | steps | time (s) | loss | train PSNR (dB) | Gaussians | largest coordinate | scale min | scale max | peak RSS (MB) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "step" not in r:
            lines.append(f"| {r['method']} | {r['status']} | | | | | | | | | |")
            continue
        lines.append(
            f"| {r['method']} | {r['status']} | {r['step']:,} | {r['seconds']:.0f} | {r['loss']:.4f} | {r['psnr']:.2f} | {r['gaussians']:,} | "
            f"{r['max_abs']['means']:.3g} | {r['scale_min']:.2e} | {r['scale_max']:.2e} | {r['peak_mb']:.0f} |"
        )
    emit("\n".join(lines) + "\n", args.markdown)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
