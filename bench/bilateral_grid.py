"""Benchmark the per-image bilateral grid's share of a training step.

    python bench/bilateral_grid.py [--gaussians 20000] [--size 256] [--images 64] [--threads 1]
                                   [--repeat 30] [--markdown PATH]

Builds the synthetic scene of ``mlx3d.report.scene``: an initial model of
``--gaussians`` Gaussians (``GaussianModel.from_points`` on noisy samples of
the ground truth, SH degree 3), ``--size``² cameras on its rings and the
ground truth's renders as targets, and times ``GaussianTrainer.step``
(vanilla) without the grid and with ``bilateral_grid=True`` (``--images``
grids, the step's image index cycling over them: the stepped image's grid is
sliced, its TV is in the loss and ``GridAdam`` updates it alone). The two
alternate step by step, so machine load hits them alike; the table gives the
median ms per step of each and the grid's share of the step with the grid
((grid - plain) / grid).

A breakdown of the grid's own work follows, timed the same interleaved way on
the rendered image: slicing forward, slicing forward + backward of one
image's grid (gradient to the grid and the image), its TV loss with its
gradient, ``GridAdam``'s catch-up and update, and, for comparison, the
MLX-graph formulations that ``apply_grid_reference`` and
``total_variation_reference`` keep (MLX's own gradients: a scatter-add per
gather).

The render threads default to 1 (``MLX3D_NUM_THREADS``), and so do numpy's
BLAS threads (``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, which the grid's
numpy kernels use), so that the numbers do not depend on how many cores the
machine lends the run.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

from common import LoadSampler, emit, machine_line, peak_rss_mb  # bench/ is on sys.path when run as a script

BACKGROUND = (1.0, 1.0, 1.0)  # the scene's targets are composited on white
VARIANTS = ("plain", "grid")


def _median_ms(xs) -> float:
    return statistics.median(xs) * 1000.0


def _scene(n: int, size: int, views: int):
    """The built-in synthetic scene (``mlx3d.report.scene``): an initial model of ``n`` Gaussians
    (``from_points`` on noisy samples of the ground truth), cameras on its rings, ground-truth targets."""
    import mlx.core as mx

    from mlx3d.report import scene
    from mlx3d.splatting import GaussianModel

    truth = scene.ground_truth()
    points, colours = scene.initial_points(truth, n, 0.03, seed=0)
    cams = scene.cameras(views, size)
    targets = [mx.array(scene.render_view(truth, c)) for c in cams]
    return (lambda: GaussianModel.from_points(points, colours, sh_degree=3)), cams, targets


def _interleaved(fns: dict, rounds: int, warmup: int, before=None) -> dict:
    """Median seconds of each callable, calling them in rotating order each round."""
    import mlx.core as mx

    names = list(fns)
    times = {k: [] for k in names}
    for i in range(warmup + rounds):
        shift = i % len(names)
        for name in names[shift:] + names[:shift]:
            if before is not None:
                before(name, i)
            t0 = time.perf_counter()
            out = fns[name](i)
            if out is not None:
                mx.eval(*out)
            if i >= warmup:
                times[name].append(time.perf_counter() - t0)
    return times


def run(args) -> dict:
    import mlx.core as mx
    import numpy as np

    from mlx3d import native
    from mlx3d.render import render_gaussians
    from mlx3d.render.raster_cpu import get_num_threads
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.bilateral_grid import BilateralGrid, GridAdam, apply_grid_reference, total_variation_reference

    native.core()  # import (and, for editable installs, rebuild) outside the timing
    make_model, cams, targets = _scene(args.gaussians, args.size, min(args.images, 8))
    trainers = {}
    for variant in VARIANTS:
        config = TrainerConfig(steps=30_000, bilateral_grid=variant != "plain", background=BACKGROUND, densify_from=10**9,
                               sh_increase_every=0)
        trainers[variant] = GaussianTrainer(make_model(), config, num_images=args.images)

    # Whole steps, the variants alternating step by step.
    def step(variant):
        def go(i):
            k = i % len(cams)
            trainers[variant].step(cams[k], targets[k], image_index=i % args.images)

        return go

    times = _interleaved({v: step(v) for v in VARIANTS}, args.repeat, args.warmup)

    # The grid's own work, on the rendered image, with the trainer's grid and optimizer.
    trainer = trainers["grid"]
    bg = trainer.bilateral
    p = trainer.model.params
    sh = mx.concatenate([p["sh_dc"], p["sh_rest"]], axis=1)
    image = render_gaussians(cams[0], p["means"], p["quats"], mx.exp(p["scales"]), mx.sigmoid(p["opacities"]), sh=sh, sh_degree=0,
                             background=BACKGROUND)["image"]
    mx.eval(image)
    rng = np.random.default_rng(1)
    wts = mx.array(rng.standard_normal(image.shape).astype(np.float32))
    lam = trainer.config.lambda_bilateral_tv
    # Grids away from the identity (the TV's gradient is 0 there), as after some training.
    bg.params = bg.params + mx.array(rng.standard_normal(bg.params.shape).astype(np.float32) * 1e-2)
    mx.eval(bg.params)

    def slice_fwd(i):
        return [bg.apply(image, i, compiled=False)]

    def slice_fwd_bwd_graph(i):
        def f(grid, img):
            return mx.sum(apply_grid_reference(grid, img) * wts)

        return list(mx.value_and_grad(f, argnums=(0, 1))(bg.params[i % bg.num_images], image)[1])

    def tv_graph(i):
        return list(mx.value_and_grad(lambda g: lam * total_variation_reference(g))(bg.params[i % bg.num_images]))

    # A copy of the grids for GridAdam to write into.
    own = BilateralGrid(bg.num_images, bg.grid_shape)
    own.params = mx.array(np.array(bg.params))
    grid_adam = GridAdam(trainer.config.bilateral_grid_lr)
    one_grad = mx.array(rng.standard_normal(bg.params.shape[1:]).astype(np.float32) * 1e-3)

    def slice_fwd_bwd_one(i):
        def f(grid, img):
            return mx.sum(bg.apply(img, i, grid) * wts)

        return list(mx.value_and_grad(f, argnums=(0, 1))(bg.params[i % bg.num_images], image)[1])

    def tv_one(i):
        return list(mx.value_and_grad(lambda g: lam * bg.tv_loss(g))(bg.params[i % bg.num_images]))

    def grid_adam_step(i):
        grid_adam.current(own, i)
        grid_adam.update(own, i, one_grad)
        return [own.params]

    parts = {
        "slice forward": slice_fwd,
        "slice forward+backward, this image's grid": slice_fwd_bwd_one,
        "TV loss + gradient, this image's grid": tv_one,
        "GridAdam current + update, this image's grid": grid_adam_step,
        "slice forward+backward, MLX graph (reference)": slice_fwd_bwd_graph,
        "TV loss + gradient, MLX graph (reference)": tv_graph,
    }
    part_times = _interleaved(parts, args.repeat, args.warmup)

    plain = _median_ms(times["plain"])
    steps = {v: _median_ms(times[v]) for v in VARIANTS}
    return {
        "steps": steps,
        "share": {v: (steps[v] - plain) / steps[v] for v in VARIANTS if v != "plain"},
        "parts": {k: _median_ms(v) for k, v in part_times.items()},
        "threads": get_num_threads(),
        "peak_rss_mb": peak_rss_mb(),
    }


def _machine_line(threads: int, load: LoadSampler) -> str:
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    note = "; the interleaved comparisons hold better than the absolute times"
    load_line = load.line(os.cpu_count() or 0, 1.5, note)  # 1.5: this benchmark keeps one core busy
    return machine_line(f", {threads} render thread(s), numpy BLAS threads {blas}; {load_line}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=20_000)
    parser.add_argument("--size", type=int, default=256, help="image side in pixels")
    parser.add_argument("--images", type=int, default=64, help="number of training images (grids)")
    parser.add_argument("--threads", type=int, default=1, help="MLX3D_NUM_THREADS (and numpy's BLAS threads) (0: all cores)")
    parser.add_argument("--repeat", type=int, default=30, help="timed steps per variant")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--markdown", metavar="PATH")
    args = parser.parse_args()
    if args.threads > 0:  # before numpy is imported
        for var in ("MLX3D_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
            os.environ[var] = str(args.threads)
    load = LoadSampler(every=3.0)
    load.start()
    r = run(args)
    load.stop.set()
    load.join()
    steps, share = r["steps"], r["share"]
    lines = [
        f"Bilateral grid cost in a vanilla training step: {args.gaussians:,} Gaussians, {args.size}x{args.size}, "
        f"{args.images} grids of 16x16x8; median of {args.repeat} steps per variant, interleaved",
        "",
        _machine_line(r["threads"], load),
        "",
        "| step | ms/step | steps/s | grid's share of the step |",
        "|---|---:|---:|---:|",
        f"| without grid | {steps['plain']:.1f} | {1000 / steps['plain']:.2f} | |",
        f"| with grid (this image's grid sliced, its TV, GridAdam) | {steps['grid']:.1f} | {1000 / steps['grid']:.2f} "
        f"| {100 * share['grid']:.1f}% |",
        "",
        "| grid part (alone, interleaved) | ms |",
        "|---|---:|",
    ]
    lines += [f"| {k} | {v:.2f} |" for k, v in r["parts"].items()]
    lines += ["", f"Peak RSS {r['peak_rss_mb']:.0f} MB; Python {platform.python_version()}, {sys.platform}."]
    emit("\n".join(lines) + "\n", args.markdown)


if __name__ == "__main__":
    main()
