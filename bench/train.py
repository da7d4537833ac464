"""Benchmark training per scene and method: held-out PSNR, SSIM and CC-PSNR (mean and worst view), Gaussians, steps/s, memory.

    python bench/train.py DATA_DIR [DATA_DIR ...] [--suite DIR] [--methods vanilla,mcmc]
                          [--steps N | --milestones 1000,3000,7000] [--variants plain,grid | --bilateral-grid]
                          [--max-gaussians N] [--grid-lr LR] [--random-points N] [--background white|black] [--jobs N]
                          [--out bench/out/train] [--markdown PATH]

Every DATA_DIR is a dataset folder ``mlx3d.datasets.load_dataset`` reads, its
folder name the scene's name; ``--suite DIR`` adds every dataset folder in
DIR (``bench/scenes.py`` generates the benchmark set into ``bench_data/``).
The single-scene numbers of docs/benchmarks/training.md use the captured demo scene (``make demo``
writes it to ``demo_out/dataset``: 256², about 70 training and 10 held-out
views).

Each scene x method x variant trains in a fresh process and is evaluated on
the held-out views at every milestone (``--steps N`` is one milestone);
evaluation time is not counted in the train time or steps/s. Variants:
``plain``, and ``grid`` with the per-image bilateral grid (``--bilateral-grid``
adds it beside ``plain``). ``--max-gaussians`` is passed to the trainer only
when given (otherwise each method's own default: vanilla grows without a cap,
MCMC grows to ``mlx3d.training.initial.mcmc_budget``). Every run starts from
``mlx3d.training.initial.initial_state``, as ``mlx3d train`` does (a scene
without points from ``--random-points`` random ones). ``--jobs N`` trains N runs at once, splitting
the cores between them (``MLX3D_NUM_THREADS``), which changes steps/s.

Per run the table gives the held-out PSNR, SSIM and colour-corrected PSNR
(CC-PSNR: after the affine colour map that best fits each render to its photo,
see ``mlx3d.training.colour``) as the mean over the views and the worst view,
the final number of Gaussians, steps/s, peak resident memory and train time.
The worst held-out view (lowest PSNR) of every run is saved as a side-by-side
PNG (ground truth | render) in the output folder, with ``results.json``
(every row with its per-view metrics, the machine and its load average during
the run) and each run's trained model as ``<scene>_<method>_<variant>.ply``.

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
import threading
import time

from common import LoadSampler, emit, held_out_metrics, machine_line, peak_rss_mb, train_to_milestones  # bench/ is on sys.path when run as a script

VARIANTS = ("plain", "grid")


# ------------------------------------------------------------------ one run (child process)
def _child(args) -> None:
    from mlx3d.datasets import load_dataset
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.evaluate import BACKGROUNDS, render_view, save_side_by_side
    from mlx3d.training.initial import initial_state

    scene, method, variant = args.scene, args.child, args.variant
    label = f"{scene} {method} {variant}"
    milestones = _milestones(args)
    background = BACKGROUNDS[args.background]
    dataset = load_dataset(args.data[0])
    config = TrainerConfig(method=method, steps=milestones[-1], max_gaussians=args.max_gaussians, background=background,
                           bilateral_grid=variant == "grid", init_random_points=args.random_points,
                           opaque_background=None if args.opaque_background == "same" else args.opaque_background,
                           **({"bilateral_grid_lr": args.grid_lr} if args.grid_lr is not None else {}))
    start = initial_state(dataset, config)
    for note in start.notes:
        print(f"[{label}] {note}", file=sys.stderr, flush=True)
    trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
    for milestone, trained in train_to_milestones(trainer, dataset, milestones, label):
        row = {"scene": scene, "method": method, "variant": variant, "steps": milestone, "seconds": trained,
               "steps_per_s": milestone / max(trained, 1e-9), "gaussians": len(trainer.model)}
        if dataset.test:
            report = held_out_metrics(trainer.model, dataset, background)
            row.update(report)
            if milestone == milestones[-1]:
                index = next(i for i in dataset.test if dataset.frames[i].name == report["worst_view"])
                target, image = render_view(trainer.model, dataset, index, background)
                os.makedirs(args.out, exist_ok=True)
                row["worst_png"] = os.path.join(args.out, f"{scene}_{method}_{variant}_worst.png")
                save_side_by_side(row["worst_png"], target, image)
        if milestone == milestones[-1]:  # the trained model, to re-evaluate or inspect without training again
            os.makedirs(args.out, exist_ok=True)
            row["ply"] = os.path.join(args.out, f"{scene}_{method}_{variant}.ply")
            trainer.model.save_ply(row["ply"])
        row["peak_rss_mb"] = peak_rss_mb()
        print(json.dumps(row), flush=True)


# ------------------------------------------------------------------ the machine
def _machine_line(jobs: int) -> str:
    cores = os.cpu_count() or 1
    threads = max(1, cores // jobs)
    return machine_line("; one run at a time" if jobs == 1 else f"; {jobs} runs at a time, {threads} thread{'s' if threads > 1 else ''} each")


# ------------------------------------------------------------------ driver
def _milestones(args) -> list[int]:
    if args.steps is not None:
        return [args.steps]
    return sorted({int(m) for m in args.milestones.split(",")})


def _scenes(args) -> list[tuple[str, str]]:
    """(name, folder) of every scene: the DATA_DIRs, then the dataset folders of --suite (sorted by name)."""
    from mlx3d.datasets.detect import detect_format

    folders = list(args.data)
    if args.suite:
        for name in sorted(os.listdir(args.suite)):
            path = os.path.join(args.suite, name)
            if not os.path.isdir(path):
                continue
            try:
                detect_format(path)
            except Exception:
                print(f"--suite: skipping {path} (not a dataset folder)", file=sys.stderr)
                continue
            folders.append(path)
    scenes, seen = [], set()
    for folder in folders:
        name = os.path.basename(os.path.normpath(os.path.abspath(folder)))
        while name in seen:
            name += "'"
        seen.add(name)
        scenes.append((name, folder))
    return scenes


def _cell(row: dict, key: str, fmt: str) -> str:
    return "" if row.get(key) is None else format(row[key], fmt)


def _table(rows: list, header: str) -> str:
    lines = [
        header, "",
        "| scene | method | variant | steps | PSNR mean (dB) | PSNR worst | SSIM mean | SSIM worst | CC-PSNR mean (dB) | CC-PSNR worst | Gaussians | steps/s | peak RSS (MB) | train time (s) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['method']} | {r['variant']} | failed: {r['error']} | | | | | | | | | | |")
            continue
        lines.append(
            f"| {r['scene']} | {r['method']} | {r['variant']} | {r['steps']:,} | {_cell(r, 'psnr', '.2f')} | {_cell(r, 'psnr_worst', '.2f')} | "
            f"{_cell(r, 'ssim', '.4f')} | {_cell(r, 'ssim_worst', '.4f')} | {_cell(r, 'cc_psnr', '.2f')} | {_cell(r, 'cc_psnr_worst', '.2f')} | "
            f"{r['gaussians']:,} | {r['steps_per_s']:.2f} | {r['peak_rss_mb']:.0f} | {r['seconds']:{'.0f' if r['seconds'] >= 100 else '.1f'}} |"
        )
    worst = [r for r in rows if r.get("worst_png")]
    if worst:
        lines += ["", "Worst held-out view of each run (ground truth | render):", ""]
        lines += [f"- {r['scene']} {r['method']} {r['variant']}: {r['worst_view']}, {r['psnr_worst']:.2f} dB "
                  f"(CC {r['cc_psnr_worst']:.2f} dB on {r['cc_worst_view']}) - `{r['worst_png']}`" for r in worst]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="*", metavar="DATA_DIR", help="dataset folders, one scene each (the folder name is the scene's)")
    parser.add_argument("--suite", metavar="DIR", help="also every dataset folder in DIR (e.g. bench_data)")
    parser.add_argument("--methods", default="vanilla,mcmc", help="comma-separated: vanilla, mcmc, 2dgs (default vanilla,mcmc)")
    parser.add_argument("--steps", type=int, default=None, metavar="N", help="train N steps (one milestone; replaces --milestones)")
    parser.add_argument("--milestones", default="1000,3000,7000", help="evaluate after these steps (default 1000,3000,7000)")
    parser.add_argument("--variants", default="plain", help="comma-separated: plain, grid (with the bilateral grid); default plain")
    parser.add_argument("--bilateral-grid", action="store_true", help="also run every method with the bilateral grid (adds the grid variant)")
    parser.add_argument("--max-gaussians", type=int, default=None, metavar="N", help="Gaussian cap passed to the trainer (default: the method's own)")
    parser.add_argument("--grid-lr", type=float, default=None, metavar="LR", help="the bilateral grids' learning rate (default: the trainer's)")
    parser.add_argument("--random-points", type=int, default=100_000, metavar="N",
                        help="scenes without points start from N random ones (default 100000, as the 3DGS reference)")
    parser.add_argument("--background", choices=("black", "white"), default="white", help="colour behind the renders and images with alpha (default white)")
    parser.add_argument("--opaque-background", choices=("auto", "random", "same"), default="auto",
                        help="behind training renders of opaque photos: auto (the trainer's default), random, or the same as --background")
    parser.add_argument("--jobs", type=int, default=1, help="runs trained at once, the cores split between them (default 1)")
    parser.add_argument("--out", default=os.path.join("bench", "out", "train"), metavar="DIR", help="worst-view PNGs and results.json (default bench/out/train)")
    parser.add_argument("--markdown", metavar="PATH", help="also write the table here")
    parser.add_argument("--child", metavar="METHOD", help=argparse.SUPPRESS)
    parser.add_argument("--scene", help=argparse.SUPPRESS)
    parser.add_argument("--variant", default="plain", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        try:
            _child(args)
        except (ValueError, OSError) as exc:  # a bad scene: one clear line (the parent puts it in the table)
            print(f"error: {exc}", file=sys.stderr)
            return 1
        return 0

    methods = [m for m in args.methods.split(",") if m]
    variants = [v for v in args.variants.split(",") if v]
    if args.bilateral_grid and "grid" not in variants:
        variants.append("grid")
    from mlx3d.training.trainer import METHODS

    for m in methods:
        if m not in METHODS:
            parser.error(f"unknown method {m!r}; use {', '.join(METHODS)}")
    for v in variants:
        if v not in VARIANTS:
            parser.error(f"unknown variant {v!r}; use {', '.join(VARIANTS)}")
    if args.steps is not None and args.steps < 1:
        parser.error("--steps must be at least 1")
    try:
        milestones = _milestones(args)
    except ValueError:
        parser.error(f"--milestones takes comma-separated step counts, got {args.milestones!r}")
    if not milestones or milestones[0] < 1:
        parser.error("milestones must be at least 1")
    scenes = _scenes(args)
    if not scenes:
        parser.error("no scenes: give DATA_DIRs or --suite DIR")

    # Scenes that cannot be loaded fail once here instead of once per method and variant.
    from mlx3d.datasets import load_dataset

    refused = {}
    for scene, folder in scenes:
        try:
            refused[scene] = None if load_dataset(folder).train else "no training views"
        except (ValueError, OSError) as exc:
            refused[scene] = str(exc)
        if refused[scene]:
            print(f"{scene}: {refused[scene]}", file=sys.stderr)
    runs = [(scene, folder, method, variant) for scene, folder in scenes if not refused[scene] for method in methods for variant in variants]
    jobs = max(1, min(args.jobs, len(runs) or 1))
    env = dict(os.environ, MLX3D_NUM_THREADS=str(max(1, (os.cpu_count() or 1) // jobs))) if jobs > 1 else None
    results, slots, failed = {}, threading.Semaphore(jobs), []
    load = LoadSampler()
    load.start()
    started = time.perf_counter()

    def run(key) -> None:
        scene, folder, method, variant = key
        with slots:
            cmd = [sys.executable, os.path.abspath(__file__), folder, "--child", method, "--scene", scene, "--variant", variant,
                   "--background", args.background, "--opaque-background", args.opaque_background, "--out", args.out]
            cmd += ["--steps", str(args.steps)] if args.steps is not None else ["--milestones", args.milestones]
            if args.max_gaussians is not None:
                cmd += ["--max-gaussians", str(args.max_gaussians)]
            cmd += ["--random-points", str(args.random_points)]
            if args.grid_lr is not None:
                cmd += ["--grid-lr", str(args.grid_lr)]
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            rows, tail = [], []

            def drain_stderr() -> None:  # pass progress on, keep the end for the error message
                for line in proc.stderr:
                    sys.stderr.write(line)
                    tail[:] = (tail + [line.rstrip()])[-20:]

            reader = threading.Thread(target=drain_stderr, daemon=True)
            reader.start()
            for line in proc.stdout:
                rows.append(json.loads(line))
                r = rows[-1]
                psnr = f"PSNR {r['psnr']:.2f} (worst {r['psnr_worst']:.2f}) CC-PSNR {r['cc_psnr']:.2f}" if "psnr" in r else "no held-out views"
                print(f"{scene} {method} {variant}: step {r['steps']:,} {psnr}, {r['gaussians']:,} Gaussians, "
                      f"{r['steps_per_s']:.2f} steps/s", file=sys.stderr, flush=True)
            code = proc.wait()
            reader.join()
            if code != 0:
                message = next((t for t in reversed(tail) if t and not t.startswith(" ")), f"exit code {code}").removeprefix("error: ")
                rows.append({"scene": scene, "method": method, "variant": variant, "error": message.replace("|", "/")})
                failed.append(key)
            results[key] = rows

    threads = [threading.Thread(target=run, args=(key,)) for key in runs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    load.stop.set()
    load.join()
    elapsed = time.perf_counter() - started
    rows = []
    for scene, _ in scenes:
        if refused[scene]:
            rows.append({"scene": scene, "method": "all", "variant": "all", "error": refused[scene].replace("|", "/")})
        rows += [r for key in runs if key[0] == scene for r in results.get(key, [])]
    cores = os.cpu_count() or 1
    steps = f"{milestones[-1]:,} steps" if len(milestones) == 1 else f"milestones {', '.join(f'{m:,}' for m in milestones)}"
    cap = f"cap {args.max_gaussians:,} Gaussians" if args.max_gaussians is not None else "each method's default Gaussian budget"
    header = "\n".join([
        f"Training on {', '.join(s for s, _ in scenes)}: {steps}, {args.background} background ({args.opaque_background} behind opaque photos), {cap}; {len(runs)} run{'s' if len(runs) != 1 else ''} in {elapsed / 60:.1f} min",
        "",
        f"Machine: {_machine_line(jobs)}.",
        "",
        f"Load: {load.line(cores, jobs + 0.5 * cores)}.",
    ])
    table = _table(rows, header)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump({"machine": _machine_line(jobs), "platform": platform.platform(), "load": load.summary(), "jobs": jobs,
                   "milestones": milestones, "background": args.background, "opaque_background": args.opaque_background, "max_gaussians": args.max_gaussians, "grid_lr": args.grid_lr,
                   "seconds": elapsed, "rows": rows}, f, indent=2)
    emit(table, args.markdown)
    return 1 if failed or any(refused.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
