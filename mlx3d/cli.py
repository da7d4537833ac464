"""The ``mlx3d`` command line: inspect, convert, compact, clean, transform, merge, solve cameras, train, evaluate and benchmark.

Every command reads any splat file format :func:`mlx3d.io.read_splats` reads
(recognised by content) and writes the format its output's extension names.

Exit codes: 0 success, 1 bad input or failed work (the message says what),
2 bad command-line usage, 130 cancelled with Ctrl+C. Outputs are written
atomically: a failed or cancelled run never leaves a partial file.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings

import numpy as np

from .errors import Mlx3dError
from .io.ply import NORMAL_NAMES
from .io.codec import sigmoid
from .io.formats import FORMATS, format_for_path
from .progress import ProgressLine, StageProgressLine, step

#: The writable extensions, for help texts.
FORMAT_HELP = " ".join(ext for f in FORMATS if f.writer for ext in f.extensions if ext.startswith("."))

#: Commands whose splat output is checked (extension, directory) before any work.
_OUTPUTS = {"convert": "output", "compact": "output", "clean": "output", "transform": "output", "merge": "output", "train": "out"}


def _stats(values: np.ndarray) -> dict:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return {"min": None, "median": None, "mean": None, "max": None}
    return {"min": float(finite.min()), "median": float(np.median(finite)), "mean": float(finite.mean()), "max": float(finite.max())}


def splat_summary(path: str) -> dict:
    """Facts about a splat file: format, count, SH degree, bounds, opacity/scale statistics, extras."""
    from .io import detect_format, read_splats

    fmt = detect_format(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        arrays = read_splats(path, format=fmt.name, nonfinite="keep")
    finite_means = arrays.means[np.isfinite(arrays.means).all(axis=1)]
    lo = finite_means.min(axis=0).tolist() if finite_means.size else None
    hi = finite_means.max(axis=0).tolist() if finite_means.size else None
    return {
        "file": os.fspath(path),
        "format": fmt.name,
        "bytes": os.path.getsize(path),
        "splats": arrays.count,
        "sh_degree": arrays.sh_degree,
        "bounds_min": lo,
        "bounds_max": hi,
        "opacity": _stats(sigmoid(arrays.opacities)),
        "scale_max_axis": _stats(np.exp(arrays.scales.max(axis=1).astype(np.float64))),
        "normals": all(name in arrays.extra for name in NORMAL_NAMES),
        "extra": {name: str(values.dtype) for name, values in arrays.extra.items() if name not in NORMAL_NAMES},
        "nonfinite_rows": arrays.nonfinite_rows,
    }


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.4g}"


def _print_summary(s: dict) -> None:
    def vec(v):
        return "-" if v is None else "  ".join(f"{c:.4g}" for c in v)

    rows = [
        ("file", s["file"]),
        ("format", s["format"]),
        ("size", f"{s['bytes'] / 1e6:.2f} MB"),
        ("splats", f"{s['splats']:,}"),
        ("SH degree", str(s["sh_degree"])),
        ("bounds min", vec(s["bounds_min"])),
        ("bounds max", vec(s["bounds_max"])),
        ("opacity", "  ".join(f"{k} {_fmt(v)}" for k, v in s["opacity"].items())),
        ("scale (max axis)", "  ".join(f"{k} {_fmt(v)}" for k, v in s["scale_max_axis"].items())),
        ("normals (nx ny nz)", "yes" if s["normals"] else "no"),
        ("extra properties", ", ".join(f"{k} ({t})" for k, t in s["extra"].items()) or "none"),
        ("non-finite rows", str(s["nonfinite_rows"])),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")


def _load(path: str, nonfinite: str):
    from .splatting import GaussianModel

    with step(f"reading {path}"):
        model = GaussianModel.load(path, nonfinite=nonfinite)
    print(f"{path}: {len(model):,} splats, SH degree {model.sh_degree}")
    return model


def _save(model, path: str) -> None:
    with step(f"writing {path}"):
        model.save(path)
    print(f"{path}: {len(model):,} splats, SH degree {model.sh_degree}, {os.path.getsize(path) / 1e6:.2f} MB")


def _plan_camera(args, model):
    """The camera ``info --plan`` plans for: the dataset's first training view, or one looking at the model."""
    from .cameras import Camera

    if args.data:
        from .datasets import load_dataset

        dataset = load_dataset(args.data)
        return dataset.frames[(dataset.train or [0])[0]].camera, f"training view 1 of {args.data}"
    means = np.array(model.means)
    centre = means.mean(0) if len(means) else np.zeros(3)
    radius = float(np.linalg.norm(means - centre, axis=1).max()) if len(means) else 1.0
    eye = centre + 2.5 * max(radius, 1e-6) * np.array([0.0, -1.0, 0.5])
    kw = {"focal": 256 / (2.2 * max(radius, 1e-6))} if args.camera == "orthographic" else {"fov": 50.0}
    if args.camera in ("opencv", "fisheye"):
        kw["dist"] = (0.05, 0.01, 0.0, 0.0) if args.camera == "fisheye" else (0.05, 0.01, 0.0, 0.0, 0.0)
    return Camera.look_at(eye=eye, at=centre, up=(0, 0, 1), width=256, height=256, model=args.camera, **kw), f"a 256x256 {args.camera} camera"


def _print_plan(args, path: str) -> None:
    from .render import plan_render
    from .training import TrainerConfig
    from .training.plan import active_sh_degree, step_plan

    model = _load(path, "keep")
    camera, where = _plan_camera(args, model)
    config = TrainerConfig(method=args.method, antialias=args.antialias, projection=args.projection, bilateral_grid=args.bilateral_grid)
    render = plan_render(camera, sh=model.sh[:0], sh_degree=model.sh_degree, projection=args.projection, antialias=args.antialias)
    step = max(args.step, 1)
    active = active_sh_degree(config, step - 1, model.sh_degree)
    train = step_plan(config, camera, active, step - 1)
    print(f"camera:              {where}")
    print(f"render:              {' -> '.join(render.stages)}")
    print(f"training step {step:,} ({args.method}, SH degree {active}): {' -> '.join(train.stages)}")
    print(f"not run:             {', '.join(train.skipped)}")


def cmd_info(args) -> None:
    if args.plan:
        for path in args.files:
            _print_plan(args, path)
        return
    for path in args.files:
        summary = splat_summary(path)
        if args.json:
            print(json.dumps(summary, indent=2))
        else:
            _print_summary(summary)


def cmd_convert(args) -> None:
    from .io import read_splats, write_splats

    with step(f"reading {args.input}"):
        splats = read_splats(args.input, sh_degree=args.sh_degree, nonfinite=args.nonfinite)
    options = {name: value for name, value in (("version", args.spz_version), ("level", args.ksplat_level)) if value is not None}
    with step(f"writing {args.output}"):
        fmt = write_splats(args.output, splats, **options)
    size_in, size_out = os.path.getsize(args.input), os.path.getsize(args.output)
    print(f"convert: {splats.count:,} splats, SH degree {splats.sh_degree}, {size_in / 1e6:.2f} MB -> "
          f"{args.output} ({fmt.description}, {size_out / 1e6:.2f} MB)")


def cmd_compact(args) -> None:
    model = _load(args.input, args.nonfinite)
    out = model.compact(min_opacity=args.min_opacity, max_gaussians=args.max_gaussians, target_sh_degree=args.sh_degree)
    print(f"compact: {len(model):,} -> {len(out):,} splats, SH degree {model.sh_degree} -> {out.sh_degree}")
    _save(out, args.output)


def cmd_clean(args) -> None:
    from .floaters import radius_outliers, statistical_outliers

    model = _load(args.input, args.nonfinite)
    points = np.array(model.means, dtype=np.float32)
    progress = ProgressLine("neighbour search")
    if args.radius is not None:
        result = radius_outliers(points, radius=args.radius, min_neighbours=args.min_neighbours, progress=progress)
        rule = f"fewer than {args.min_neighbours} neighbours within radius {args.radius}"
    else:
        result = statistical_outliers(points, k=args.stat_k, std_ratio=args.stat_std, progress=progress)
        rule = f"mean distance to {args.stat_k} nearest neighbours > {result.threshold:.4g} (mean + {args.stat_std} std)"
    print(f"clean: removed {result.removed:,} of {len(model):,} splats ({rule})")
    _save(model.copy().select(result.keep), args.output)


def cmd_transform(args) -> None:
    from .transforms import compose_affine

    if len(args.scale) not in (1, 3):
        raise Mlx3dError(f"--scale takes 1 or 3 values, got {len(args.scale)}")
    matrix = compose_affine(args.scale if len(args.scale) == 3 else args.scale[0], args.rotate_deg, args.translate)
    model = _load(args.input, args.nonfinite)
    with step("transforming"):
        out = model.transform(matrix)
    _save(out, args.output)


def cmd_merge(args) -> None:
    from .splatting import merge

    models = [_load(path, args.nonfinite) for path in args.inputs]
    out = merge(models, sh_degree=args.sh_degree)
    print(f"merge: {len(models)} files -> {len(out):,} splats, SH degree {out.sh_degree}")
    _save(out, args.output)


class TrainProgress:
    """Progress line for training: step, loss, PSNR, Gaussians, steps/s, ETA (about every 2%)."""

    def __init__(self, stream=None):
        import time

        self.stream = stream if stream is not None else sys.stderr
        self.start = time.perf_counter()  # made just before the first step

    def __call__(self, done: int, total: int, info: dict) -> None:
        import time

        now = time.perf_counter()
        every = max(total // 50, 1)
        if done % every and done != total:
            return
        rate = done / max(now - self.start, 1e-9)
        eta = (total - done) / max(rate, 1e-9)
        print(
            f"step {info['step']:>6} ({done}/{total})  loss {info['loss']:.4f}  PSNR {info['psnr']:5.2f} dB  "
            f"{info['num_gaussians']:,} Gaussians  {rate:.1f} steps/s  ETA {eta:.0f} s",
            file=self.stream,
            flush=True,
        )


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_float(text: str) -> float:
    value = float(text)
    if not value >= 0:  # NaN too
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


def _background_arg(text: str):
    from .training.evaluate import BACKGROUNDS

    return text if text == "random" else BACKGROUNDS[text]


def _solve(source: str, out: str, args):
    """Solve the cameras of photos or a video into the dataset ``out`` and print what was solved."""
    from .sfm import solve_capture

    result = solve_capture(source, out, matching=args.matching, max_image_size=args.max_image_size,
                           min_registered=args.min_registered, fps=args.fps, blur_ratio=args.blur_ratio,
                           progress=StageProgressLine("poses"), verbose=args.verbose_sfm)
    print(f"poses: {result.summary()}")
    if result.unregistered:
        print(f"poses: not placed, left out of the dataset: {', '.join(result.unregistered)}")
    print(f"poses: wrote the dataset {out} ({sum(result.seconds.values()):.1f} s)")
    return result


def cmd_poses(args) -> None:
    _solve(args.photos, args.out, args)


def _train_data(args) -> str:
    """The dataset to train on: ``args.data`` itself, or, for photos without poses or a video, the dataset
    solved from them into ``--poses-out`` (default: ``<OUT stem>_poses`` beside OUT; reused when it holds one)."""
    from .datasets import detect_format
    from .sfm import needs_solve, poses_folder

    if not needs_solve(args.data):
        return args.data
    out = poses_folder(args.out, args.poses_out)
    if os.path.isdir(out) and any(os.scandir(out)):
        detect_format(out)  # an earlier solve: a clear error when it holds something else
        print(f"{args.data}: photos without poses; using the cameras solved earlier in {out}")
        return out
    print(f"{args.data}: photos without poses; solving the cameras into {out}")
    _solve(args.data, out, args)
    return out


def _ranks(args):
    """The ranks of a distributed run (``--distributed``, or started by mlx.launch or mpirun), or None."""
    from .training.distributed import init, launched

    if not (args.distributed or launched()):
        return None
    ranks = init(args.backend)
    return ranks if ranks.size > 1 else None


def cmd_train(args) -> None:
    import contextlib

    ranks = _ranks(args)
    if ranks is not None and ranks.rank != 0:  # rank 0 alone reports; errors still reach stderr (main prints them)
        with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            _train(args, ranks)
        return
    if ranks is not None:
        print(f"training on {ranks.size} ranks, {args.batch_size} views per step")
    _train(args, ranks)


def _train(args, ranks) -> None:
    import signal
    from dataclasses import replace

    from .datasets import load_dataset
    from .training import GaussianTrainer, TrainerConfig
    from .training.evaluate import evaluate
    from .training.initial import initial_state

    data = args.data if ranks is not None else _train_data(args)
    with step(f"loading {data}"):
        dataset = load_dataset(data, factor=args.factor)
    print(f"{data}: {len(dataset.train)} training and {len(dataset.test)} test views")
    out_dir = os.path.dirname(os.path.abspath(args.out))
    config = TrainerConfig(
        method=args.method, steps=args.steps, max_gaussians=args.max_gaussians, background=args.background,
        seed=args.seed, checkpoint_every=args.checkpoint_every, checkpoint_dir=out_dir,
        bilateral_grid={"on": True, "off": False}.get(args.bilateral_grid, "auto"),
        init_random_points=args.random_points, init_background_points=args.background_points,
        opaque_background=None if args.opaque_background == "same" else args.opaque_background, batch_size=args.batch_size,
        lambda_sparse_depth=args.sparse_depth,
    )
    if args.sparse_depth and dataset.observations is None:
        raise ValueError(f"--sparse-depth needs the points a solve placed and the photos that observe them (a COLMAP "
                         f"model, as `mlx3d poses` writes); {data} has none")
    if args.steps_scaler != 1.0:
        config = config.scale_steps(args.steps_scaler)
        print(f"steps scaled by {args.steps_scaler:g}: {config.steps:,} steps")
    if ranks is not None and args.batch_size < ranks.size:
        raise ValueError(f"--batch-size {args.batch_size} is smaller than the {ranks.size} ranks: each rank renders at least one view per step")
    writer = ranks is None or ranks.rank == 0
    if args.resume:
        # the run's own settings, with its defaults as they were resolved; the command line sets how long it runs
        stored = GaussianTrainer.checkpoint_config(args.resume)
        if stored is not None:
            config = replace(stored, steps=config.steps, checkpoint_every=config.checkpoint_every, checkpoint_dir=out_dir,
                             batch_size=config.batch_size)
        trainer = GaussianTrainer.load_checkpoint(args.resume, config, ranks=ranks)
        print(f"resumed at step {trainer.step_count} from {args.resume}")
    else:
        with step("building the initial model"):
            start = initial_state(dataset, config, sh_degree=args.sh_degree, progress=ProgressLine("plane sweep"))
        for note in start.notes:
            print(note)
        model = start.model
        if ranks is not None:  # every rank starts from rank 0's model
            from .splatting import GaussianModel

            model = GaussianModel(ranks.broadcast(model.params, "the initial model"))
        trainer = GaussianTrainer(model, start.config, scene_extent=dataset.scene_extent(), ranks=ranks)
    remaining = max(trainer.config.steps - trainer.step_count, 0)
    interrupted = []
    previous = None
    if ranks is not None:  # Ctrl+C: every rank stops after the same step (see fit), then rank 0 saves
        previous = signal.signal(signal.SIGINT, lambda *_: interrupted.append(True))
    try:
        history = trainer.fit(dataset, steps=remaining, progress=TrainProgress() if writer else None,
                              should_stop=(lambda: bool(interrupted)) if ranks is not None else None)
        if len(history) < remaining:  # a rank was interrupted: every rank stopped after the same step
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        if writer:
            trainer.model.save(args.out)
        trainer.save_checkpoint(os.path.join(out_dir, "checkpoint.npz"))
        print(f"cancelled at step {trainer.step_count}: saved {args.out} and a checkpoint to resume from", file=sys.stderr)
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    if not writer:
        return
    _save(trainer.model, args.out)
    if args.eval and dataset.test:
        background = (0.0, 0.0, 0.0) if args.background == "random" else _background_arg(args.background)
        report = evaluate(trainer.model, dataset, "test", background, out_dir=os.path.splitext(args.out)[0] + "_eval")
        print(f"held-out views: PSNR {report['psnr']:.2f} dB, SSIM {report['ssim']:.4f}, "
              f"colour-corrected PSNR {report['cc_psnr']:.2f} dB, SSIM {report['cc_ssim']:.4f} ({len(report['views'])} views)")
        print(_worst_line(report))


def cmd_mesh(args) -> None:
    from .meshing import DEFAULT_TRIM

    model = _load(args.model, args.nonfinite)
    resolution = args.resolution or 128
    cameras = None
    if args.data:
        from .datasets import load_dataset

        dataset = load_dataset(args.data, factor=args.factor)
        cameras = [dataset.frames[i].camera for i in dataset.train]
    if args.method == "fusion":
        where = f"{len(cameras)} training views" if cameras else "60 views around the model"
        with step(f"fusing the depth of {where} at resolution {resolution}"):
            bounds = None if args.bounds is None else np.reshape(args.bounds, (2, 3))
            mesh = model.fused_mesh(cameras, resolution=resolution, voxel_size=args.voxel_size, truncation=args.truncation,
                                    cleanup=args.cleanup, progress=ProgressLine("meshing"), bounds=bounds)
    else:
        trim = DEFAULT_TRIM if args.trim is None else args.trim
        centres = None if cameras is None else [camera.center for camera in cameras]
        with step(f"extracting a mesh at resolution {resolution}"):
            mesh = model.surface_mesh(
                resolution=resolution, padding=args.padding, min_opacity=args.min_opacity, max_points=args.max_points,
                orient_towards=centres, trim=trim, progress=ProgressLine("meshing"),
            )
        if args.cleanup:
            from .meshing import keep_large_components

            mesh = keep_large_components(mesh, args.cleanup)
    if args.faces:
        from .meshing import simplify

        with step(f"simplifying {len(mesh.faces):,} faces to at most {args.faces:,}"):
            mesh = simplify(mesh, args.faces)
    mesh.save_ply(args.out)
    print(f"wrote {args.out}: {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces, area {mesh.area():.4g}, watertight {mesh.is_watertight()}")


def _worst_line(report: dict) -> str:
    """The held-out view with the lowest PSNR, and the one with the lowest colour-corrected PSNR."""
    worst, cc = report["worst"], report["cc_worst"]
    return (f"worst view: {worst['name']} PSNR {worst['psnr']:.2f} dB (colour-corrected {worst['cc_psnr']:.2f} dB); "
            f"worst colour-corrected: {cc['name']} {cc['cc_psnr']:.2f} dB")


def cmd_eval(args) -> None:
    from .datasets import load_dataset
    from .splatting import GaussianModel
    from .training.evaluate import evaluate

    model = GaussianModel.load(args.model)
    dataset = load_dataset(args.data, factor=args.factor)
    report = evaluate(model, dataset, args.split, _background_arg(args.background), out_dir=args.out, progress=ProgressLine("evaluating"))

    def row(name, m):
        return f"{name:<32} PSNR {m['psnr']:6.2f} dB  SSIM {m['ssim']:.4f}  CC-PSNR {m['cc_psnr']:6.2f} dB  CC-SSIM {m['cc_ssim']:.4f}"

    for view in report["views"]:
        print(row(view["name"], view))
    print(row("mean", report) + f"  ({report['seconds_per_view'] * 1000:.0f} ms per view)")
    print(_worst_line(report))
    if args.out:
        print(f"side-by-side renders and metrics.json in {args.out}")


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def cmd_bench(args) -> None:
    import signal

    from .report.accuracy import MODES, run_accuracy

    # SIGINT and SIGTERM cancel like Ctrl+C (nothing is written), also when started with SIGINT ignored
    # (a background job, or a child of Blender: the add-on stops the benchmark this way).
    if _in_main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _interrupt)
    mode = "tiny" if args.tiny else "quick" if args.quick else "full"
    line = ProgressLine(f"bench {args.benchmark}")

    def progress(done: int, total: int, what: str) -> None:
        line.label = f"bench {args.benchmark} [{what}]"
        line(done, total)

    print(f"bench {args.benchmark}: {MODES[mode].describe()}; writing into {args.out}", file=sys.stderr, flush=True)
    result = run_accuracy(args.out, mode, seed=args.seed, progress=progress, keep_data=args.keep_data)
    seconds = result["results"]["timings"]["total"]
    print(f"bench {args.benchmark}: finished in {seconds / 60:.1f} min; report in {result['report']} with {len(result['paths']) - 1} more files")


def _in_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def cmd_demo(args) -> None:
    from .demo import run_demo

    run_demo(args.out)


def add_solving_arguments(p) -> None:
    """The options of a camera solve (``mlx3d poses``, ``mlx3d train PHOTOS``, ``blender_splat.py poses|train``)."""
    from .sfm import MATCHING
    from .sfm.solve import MIN_REGISTERED
    from .sfm.video import DEFAULT_BLUR_RATIO, DEFAULT_FPS

    g = p.add_argument_group("solving cameras (photos without poses, or a video)")
    g.add_argument("--matching", choices=MATCHING, default="auto",
                   help="image pairs to match: every pair (exhaustive), neighbours in name order (sequential), or "
                        "auto (default): exhaustive up to 100 photos, sequential for more and for videos")
    g.add_argument("--max-image-size", type=_positive_int, default=1600, metavar="PX",
                   help="find features on photos scaled to at most PX pixels on the longer side (default 1600)")
    g.add_argument("--min-registered", type=float, default=MIN_REGISTERED, metavar="F",
                   help=f"fail unless at least this fraction of the photos is placed (default {MIN_REGISTERED})")
    g.add_argument("--fps", type=float, default=None, metavar="N",
                   help=f"video: frames taken per second (the sharpest of each 1/N s; default {DEFAULT_FPS:g})")
    g.add_argument("--blur-ratio", type=float, default=None, metavar="R",
                   help=f"video: drop frames less sharp than R times the median (default {DEFAULT_BLUR_RATIO:g}; 0 keeps all)")
    g.add_argument("--verbose-sfm", action="store_true", help="print COLMAP's own log")


def build_parser() -> argparse.ArgumentParser:
    from .training.trainer import METHODS

    parser = argparse.ArgumentParser(prog="mlx3d", description="3D Gaussian Splatting tools on MLX.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name, func, help_text):
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(func=func)
        return p

    def reading(p):
        p.add_argument("--nonfinite", choices=("error", "drop", "keep"), default="error", help="rows with NaN/Inf: fail (default), drop them, or keep them")

    p = add("info", cmd_info, "Summarise splat files: format, count, SH degree, bounds, opacity and scale statistics, extra properties.")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--plan", action="store_true", help="print the stages a render and a training step run for this file (effects on demand)")
    p.add_argument("--data", metavar="DATA_DIR", help="--plan: use this dataset's first training camera")
    p.add_argument("--camera", choices=("pinhole", "opencv", "fisheye", "orthographic"), default="pinhole", help="--plan: camera model without --data")
    p.add_argument("--method", choices=METHODS, default="vanilla", help="--plan: training method")
    p.add_argument("--step", type=int, default=1, help="--plan: which training step (schedules start losses and events on their steps)")
    p.add_argument("--projection", choices=("auto", "ewa", "ut"), default="auto", help="--plan: projection")
    p.add_argument("--antialias", action="store_true", help="--plan: with antialias compensation")
    p.add_argument("--bilateral-grid", action="store_true", help="--plan: with the bilateral grid")

    p = add("convert", cmd_convert, f"Convert a splat file to another format: the output's extension picks it ({FORMAT_HELP}); the input's is recognised by its content.")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--sh-degree", type=int, default=None, choices=(0, 1, 2, 3), metavar="D", help="write SH degree D (cut, or padded with zeros)")
    p.add_argument("--spz-version", type=int, default=None, choices=(2, 3, 4), help="SPZ output: the version to write (default 4)")
    p.add_argument("--ksplat-level", type=int, default=None, choices=(0, 1, 2), help=".ksplat output: compression level (default 0, float32)")
    reading(p)

    p = add("compact", cmd_compact, "Keep the most important splats and/or truncate SH (importance = opacity * max scale^2).")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--max-gaussians", type=int, default=None, metavar="N", help="keep at most N splats")
    p.add_argument("--min-opacity", type=float, default=0.0, metavar="X", help="drop splats with opacity below X (0..1)")
    p.add_argument("--sh-degree", type=int, default=None, choices=(0, 1, 2, 3), metavar="D", help="truncate SH to degree D")
    reading(p)

    p = add("clean", cmd_clean, "Remove floaters: statistical outliers (default) or radius outliers.")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--stat-k", type=int, default=25, help="neighbours for the statistical rule (default 25)")
    p.add_argument("--stat-std", type=float, default=10.5, help="standard deviations above the mean distance (default 10.5)")
    p.add_argument("--radius", type=float, default=None, metavar="R", help="use the radius rule with this radius (scene units)")
    p.add_argument("--min-neighbours", type=int, default=None, metavar="M", help="radius rule: minimum neighbours within R")
    reading(p)

    p = add("transform", cmd_transform, "Scale, rotate (Euler XYZ, degrees) and translate a splat file; SH colour rotates too.")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--scale", type=float, nargs="+", default=[1.0], metavar="S", help="uniform scale S, or three factors SX SY SZ")
    p.add_argument("--rotate-deg", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("RX", "RY", "RZ"))
    p.add_argument("--translate", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"))
    reading(p)

    p = add("merge", cmd_merge, "Merge splat files into one (SH padded to the highest degree unless --sh-degree).")
    p.add_argument("output", metavar="OUT")
    p.add_argument("inputs", nargs="+", metavar="IN")
    p.add_argument("--sh-degree", type=int, default=None, choices=(0, 1, 2, 3), metavar="D")
    reading(p)

    p = add("mesh", cmd_mesh, "Extract a triangle mesh (PLY with vertex colours): by fusing the depth the splats render "
            "from the training views (--method fusion) or by Poisson reconstruction from the Gaussians as oriented discs. "
            "A model trained with `mlx3d train --method 2dgs` gives the closest mesh.")
    p.add_argument("model", metavar="MODEL")
    p.add_argument("--out", required=True, metavar="MESH.ply")
    p.add_argument("--method", choices=("fusion", "poisson"), default="fusion",
                   help="fusion: depth maps into a signed distance volume, unseen space left empty (default); "
                        "poisson: a closed surface through the Gaussians' discs")
    p.add_argument("--data", metavar="DATA_DIR", help="the dataset trained on: fusion renders its training views "
                   "(default: 60 views around the model); poisson turns each normal towards the nearest of its cameras")
    p.add_argument("--factor", type=float, default=1, help="with --data: its cameras this many times smaller, as "
                   "trained with `mlx3d train --factor` (fusion renders its depth at that size; default 1)")
    p.add_argument("--resolution", type=int, default=None,
                   help="voxels along the largest side (default 128; poisson's memory grows with its cube)")
    p.add_argument("--voxel-size", type=float, default=None, metavar="LENGTH", help="fusion: voxel size in scene units (instead of --resolution)")
    p.add_argument("--truncation", type=float, default=None, metavar="LENGTH", help="fusion: signed distance truncation in scene units (default 4 voxels)")
    p.add_argument("--bounds", type=float, nargs=6, default=None, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="fusion: the box to mesh, in scene units (default: the surfaces the views share)")
    p.add_argument("--cleanup", type=float, default=0.01, metavar="FRACTION",
                   help="drop pieces of fewer faces than this fraction of the largest piece's (default 0.01; 0 keeps all)")
    p.add_argument("--faces", type=int, default=0, metavar="N",
                   help="at most N triangles, by quadric vertex clustering (default 0: as extracted)")
    p.add_argument("--padding", type=float, default=0.1, help="poisson: grid margin, as a fraction of the bounding box's largest side")
    p.add_argument("--min-opacity", type=float, default=0.01, help="poisson: ignore Gaussians below this opacity")
    p.add_argument("--max-points", type=int, default=200_000, help="poisson: keep the N largest opaque discs (default 200000)")
    p.add_argument("--trim", type=float, default=None, metavar="VOXELS", help="poisson: drop faces farther than this from every disc centre (0: keep all)")
    reading(p)

    p = add("poses", cmd_poses, "Solve the cameras of a folder of photos (or a video) with COLMAP (pycolmap) and write a "
            "dataset that `mlx3d train` reads, set upright: +Z up, the scene at the origin.")
    p.add_argument("photos", metavar="PHOTOS", help="a folder of photos, or a video file")
    p.add_argument("--out", required=True, metavar="DIR", help="the dataset folder to write (new, or empty)")
    add_solving_arguments(p)

    p = add("train", cmd_train, "Train Gaussians on a dataset (COLMAP, NeRF-synthetic or nerfstudio folder), or on a "
            "folder of photos or a video whose cameras are solved first (as `mlx3d poses`), and write a splat file.")
    p.add_argument("data", metavar="DATA_DIR", help="a dataset folder, or photos without poses, or a video")
    p.add_argument("--poses-out", metavar="DIR", help="where cameras solved from photos go (default: OUT's name + _poses, "
                   "beside OUT; an earlier solve there is reused)")
    add_solving_arguments(p)
    p.add_argument("--out", required=True, metavar="OUT")
    p.add_argument("--method", choices=METHODS, default="vanilla", help="vanilla, mcmc or 2dgs (surfels, for mesh extraction)")
    p.add_argument("--steps", type=int, default=30000)
    p.add_argument("--max-gaussians", type=int, default=None, metavar="N", help="vanilla: stop growth at N; mcmc: grow to N (default: one per pixel of a training image, at least twice the initial count)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), default=3)
    p.add_argument("--background", choices=("black", "white", "random"), default="black", help="colour behind images with alpha")
    p.add_argument("--factor", type=float, default=1, help="image downscale factor (uses images_N when present)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="N", help="write checkpoint.npz next to OUT every N steps")
    p.add_argument("--resume", metavar="CHECKPOINT.npz", help="continue from a checkpoint")
    p.add_argument("--eval", action="store_true", help="evaluate the held-out views at the end")
    p.add_argument("--bilateral-grid", nargs="?", choices=("auto", "on", "off"), const="on", default="auto",
                   help="a per-photo colour grid that absorbs exposure and white-balance differences: 'auto' (default) "
                        "turns it on when the solve shows the photos' exposure varies; --bilateral-grid alone: on")
    p.add_argument("--random-points", type=int, default=100_000, metavar="N",
                   help="a dataset without points starts from N random points in a cube around what the cameras look at (default 100000)")
    p.add_argument("--background-points", type=int, default=None, metavar="N",
                   help="N points on a far sphere seed a backdrop (default: vanilla and mcmc on opaque photos; 0: none)")
    p.add_argument("--sparse-depth", type=_non_negative_float, default=0.0, metavar="WEIGHT",
                   help="the solve's sparse points as depth: WEIGHT x the L1 error of inverse depth at every point a photo "
                        "observes (default 0: off; e.g. 0.01); needs a COLMAP model's points")
    p.add_argument("--batch-size", type=_positive_int, default=1, metavar="N",
                   help="views per step (default 1); the learning rates scale by sqrt(N) as in gsplat. With several ranks, "
                        "the batch is shared between them")
    p.add_argument("--steps-scaler", type=float, default=1.0, metavar="F",
                   help="multiply the step counts (run length, schedules, checkpoint interval) by F, e.g. 1/N with --batch-size N")
    p.add_argument("--distributed", action="store_true",
                   help="train with the other processes of an mlx.launch or mpirun job (detected when launched by them)")
    p.add_argument("--backend", choices=("any", "ring", "jaccl", "mpi", "nccl"), default="any",
                   help="distributed backend (default any: the one the launcher set up)")
    p.add_argument("--opaque-background", choices=("auto", "random", "black", "white", "same"), default="auto",
                   help="behind training renders when the photos are opaque (no alpha): random (a colour per step, so the "
                        "model cannot go transparent), a fixed colour, or same: --background; auto (default): random when "
                        "the run seeds a backdrop (vanilla and mcmc on opaque photos, --background-points), else same")

    p = add("eval", cmd_eval, "PSNR and SSIM of a splat file on a dataset's held-out views, plain and colour-corrected (CC: after the best affine colour map per view); the worst view; side-by-side renders.")
    p.add_argument("model", metavar="MODEL")
    p.add_argument("--data", required=True, metavar="DATA_DIR")
    p.add_argument("--split", default="test")
    p.add_argument("--out", metavar="DIR", help="write renders/*.png (ground truth | render) and metrics.json here")
    p.add_argument("--background", choices=("black", "white"), default="black")
    p.add_argument("--factor", type=float, default=1)

    p = add("bench", cmd_bench, "Measure on this machine what accuracy costs: training and rendering configurations on the built-in scene, written as a markdown report with plots.")
    p.add_argument("benchmark", choices=("accuracy",), help="accuracy: held-out PSNR/SSIM against time and memory for training and rendering settings")
    p.add_argument("--quick", action="store_true", help="small sizes (a few minutes on 2 cores) instead of the full run (under an hour)")
    p.add_argument("--out", default=os.path.join("bench", "out", "accuracy"), metavar="DIR", help="output folder for README.md, the PNG plots and results.json (default bench/out/accuracy)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene, the initial points and training (default 0)")
    p.add_argument("--keep-data", action="store_true", help="keep the rendered dataset in DIR/dataset (default: a temporary folder)")
    p.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)  # seconds-long run for tests

    p = add("demo", cmd_demo, "Run the built-in end-to-end demo on a generated scene.")
    p.add_argument("--out", default="demo_out", metavar="DIR", help="output folder (default demo_out)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "clean":
        if (args.radius is None) != (args.min_neighbours is None):
            parser.error("clean: --radius and --min-neighbours go together")
    try:
        if args.command in _OUTPUTS:  # a wrong extension or an unmakeable folder fails before any work
            output = getattr(args, _OUTPUTS[args.command])
            format_for_path(output, writable=True)
            os.makedirs(os.path.dirname(os.path.abspath(output)), exist_ok=True)
        with warnings.catch_warnings():
            # What was dropped or kept (extras a format cannot store, NaN rows) as one line each.
            warnings.showwarning = lambda message, *rest, **kw: print(
                f"mlx3d {args.command}: warning: {message}", file=sys.stderr, flush=True)
            args.func(args)
    except KeyboardInterrupt:
        print("mlx3d: cancelled", file=sys.stderr)
        return 130
    except (Mlx3dError, ValueError, OSError) as exc:
        print(f"mlx3d {args.command}: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
