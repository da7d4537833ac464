"""What accuracy costs on this machine: ``mlx3d bench accuracy`` (and the add-on's "Benchmark this machine").

``run_accuracy(out_dir, mode)`` measures a fixed set of configurations on the
built-in scene (``mlx3d.report.scene``) and writes ``README.md`` (the report),
PNG plots and ``results.json`` into ``out_dir``:

1. **scene**: the ground truth is rendered into a nerfstudio dataset (in a
   temporary folder, or ``out_dir/dataset`` with ``keep_data``) and loaded with
   ``load_dataset``, so training takes the same path as ``mlx3d train``;
2. **training**: one configuration per setting, changing one factor at a time
   from the baseline (MCMC, the middle Gaussian budget, SH degree 3, EWA, no
   antialias, full-size images): method, Gaussian budget, SH degree,
   projection, antialias, image scale. Every configuration trains the same
   number of steps with the same schedule, scaled to that number (see
   ``schedule``), and is evaluated on the held-out views at checkpoints;
   evaluation time is not training time. The configurations train in turn, one
   segment (up to the next checkpoint) each, so load from other processes on
   a shared machine falls on all of them alike;
3. **rendering**: the baseline's trained model compacted to 100/50/25% of its
   Gaussians at SH degree 3/1/0, with EWA and with UT projection, rendered from
   every held-out view several times (after a warm-up): median and quartiles
   of the milliseconds per view, and held-out PSNR;
4. **effects on demand**: the time of a training step and of a render with an
   optional stage on and with it skipped, measured in adjacent pairs on the
   trained model (the saving is the median paired difference), with the
   stages that ran (``info["stages"]``, ``out["stages"]``);
5. **Pareto tables**: for time budgets, the most accurate configuration and
   checkpoint (training) or model (rendering) that fits.

Modes: ``quick`` (a few minutes), ``full`` (the committed report, under an hour
on 2 cores) and ``tiny`` (seconds; for tests). Timings are wall-clock seconds
of this process; the report records the machine and its load.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import platform
import shutil
import signal
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from . import plot as plt
from .scene import BACKGROUND, SceneSpec, write_dataset
from .stats import budget_table, format_spread, pareto_front, summary

REPORT_NAME = "README.md"
PLOTS = {
    "train_psnr": "train_psnr_vs_time.png",
    "train_ssim": "train_ssim_vs_time.png",
    "render": "render_ms_vs_psnr.png",
    "effects": "effects.png",
    "views": "heldout_view.png",
}


@dataclass(frozen=True)
class Mode:
    """Sizes of a benchmark run."""

    name: str
    scene: SceneSpec
    steps: int  # training steps per configuration
    checkpoints: int  # evaluations per configuration (evenly spaced in steps)
    budgets: tuple  # Gaussian budgets (low, baseline, high)
    render_repeats: int  # timed renders per held-out view and model (after one warm-up)
    effect_repeats: int  # timed training steps per effect and side (renders: render_repeats per held-out view)

    def describe(self) -> str:
        return (
            f"{self.name}: {self.steps:,} training steps per configuration, evaluated at {self.checkpoints} checkpoints; "
            f"Gaussian budgets {', '.join(_count(b) for b in self.budgets)}; {self.render_repeats} timed renders per view and model; "
            f"{self.effect_repeats} timed training steps per effect and side"
        )


MODES = {
    "tiny": Mode("tiny", SceneSpec(image_size=32, num_views=12, num_points=300, spacing=0.05), steps=16, checkpoints=2,
                 budgets=(400, 600, 900), render_repeats=2, effect_repeats=2),
    "quick": Mode("quick", SceneSpec(image_size=64, num_views=24, num_points=1000), steps=300, checkpoints=6,
                  budgets=(2000, 5000, 10000), render_repeats=5, effect_repeats=16),
    "full": Mode("full", SceneSpec(image_size=128, num_views=64, num_points=5000), steps=800, checkpoints=8,
                 budgets=(10000, 30000, 100000), render_repeats=10, effect_repeats=30),
}


def _count(n: int) -> str:
    return f"{n // 1000}k" if n >= 1000 and n % 1000 == 0 else f"{n:,}"


# ------------------------------------------------------------------ the machine
def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo, macOS sysctl), else platform.processor()."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    if sys.platform == "darwin":
        import subprocess

        with contextlib.suppress(Exception):
            return subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True, timeout=5).stdout.strip()
    return platform.processor() or "unknown"


def memory_gb() -> float | None:
    """Total memory in GB (Linux /proc/meminfo; None elsewhere)."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) / 1024**2
    return None


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MB."""
    with contextlib.suppress(OSError):
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 / (1024.0 if sys.platform == "darwin" else 1.0)


def load_average():
    with contextlib.suppress(OSError, AttributeError):
        return os.getloadavg()[0]
    return None


def machine_info() -> dict:
    """Platform, CPU, cores, memory, Python, MLX and the render backend."""
    import mlx.core as mx

    from ..render.pipeline import resolve_backend
    from ..render.raster_cpu import get_num_threads

    backend = resolve_backend("auto")
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "memory_gb": memory_gb(),
        "python": platform.python_version(),
        "mlx": mx.__version__,
        "mlx_device": str(mx.default_device()),
        "backend": backend,
        "raster_threads": get_num_threads() if backend == "cpu" else None,
    }


# ------------------------------------------------------------------ configurations
@dataclass(frozen=True)
class TrainCase:
    """One training configuration: the baseline with one factor changed."""

    name: str
    factor: str  # 'baseline', 'method', 'budget', 'SH degree', 'projection', 'antialias', 'image scale'
    budget: int
    method: str = "mcmc"
    sh_degree: int = 3
    projection: str = "ewa"
    antialias: bool = False
    scale: float = 1.0

    def settings(self) -> str:
        parts = [self.method, f"{_count(self.budget)} Gaussians", f"SH {self.sh_degree}", self.projection.upper()]
        if self.antialias:
            parts.append("antialias")
        if self.scale != 1.0:
            parts.append(f"images x{self.scale:g}")
        return ", ".join(parts)


def train_cases(mode: Mode) -> list:
    """The baseline and its one-factor variations."""
    low, mid, high = mode.budgets
    base = TrainCase("baseline", "baseline", mid)
    return [
        base,
        replace(base, name="vanilla", factor="method", method="vanilla"),
        replace(base, name=f"budget {_count(low)}", factor="budget", budget=low),
        replace(base, name=f"budget {_count(high)}", factor="budget", budget=high),
        replace(base, name="SH 0", factor="SH degree", sh_degree=0),
        replace(base, name="SH 1", factor="SH degree", sh_degree=1),
        replace(base, name="UT", factor="projection", projection="ut"),
        replace(base, name="antialias", factor="antialias", antialias=True),
        replace(base, name="images x0.5", factor="image scale", scale=0.5),
    ]


def schedule(steps: int, initial: int, budget: int) -> dict:
    """The training schedule laid out over ``steps`` (3DGS's is laid out over 30,000).

    SH degree up every 10% of the steps; densification (vanilla) or relocation
    and growth (MCMC) every 2.5% of the steps from 10% to 60%, no opacity reset;
    MCMC grows by the factor that reaches the budget at the last growth event
    (at least the default 5% per event).
    """
    every = max(steps // 40, 1)
    start, until = steps // 10, int(steps * 0.6)
    events = max(sum(1 for s in range(start + 1, until + 1) if s % every == 0), 1)
    growth = max((budget / max(initial, 1)) ** (1.0 / events) - 1.0, 0.05)
    return {
        "sh_increase_every": max(steps // 10, 1), "densify_from": start, "densify_until": until, "densify_every": every,
        "opacity_reset_every": 0, "mcmc_growth": round(growth, 4),
    }


def trainer_config(case: TrainCase, steps: int, initial: int, seed: int):
    from ..training import TrainerConfig

    return TrainerConfig(
        method=case.method, steps=steps, max_gaussians=case.budget, background=BACKGROUND, antialias=case.antialias,
        projection=case.projection, seed=seed, **schedule(steps, initial, case.budget),
    )


# ------------------------------------------------------------------ measuring
class Cancelled(KeyboardInterrupt):
    """Raised when ``should_stop`` asks to stop (handled like Ctrl+C)."""


class _Progress:
    """Adds up the work done (in thousandths of the run) and passes (done, 1000, what) on; samples the load average.

    ``tick(what, share)`` reports one piece of work worth ``share`` thousandths;
    ``should_stop()`` is polled on every report.
    """

    total = 1000

    def __init__(self, callback, should_stop):
        self.done, self.callback, self.should_stop = 0.0, callback, should_stop
        self.loads = []

    def __call__(self, what: str, share: float) -> None:
        if self.should_stop is not None and self.should_stop():
            raise Cancelled("cancelled")
        self.done = min(self.done + share, self.total)
        load = load_average()
        if load is not None:
            self.loads.append(load)
        if self.callback is not None:
            self.callback(int(round(self.done)), self.total, what)


#: PSNR differences up to this (dB, the precision the report shows) are ties in the budget tables: the cheaper wins.
PSNR_TIE_DB = 0.01

# Shares of the run (thousandths) by phase, roughly as the time goes.
SHARES = {"scene": 20, "training": 880, "rendering": 40, "effects": 60}


def _eval_views(model, dataset, cameras=None):
    """Held-out PSNR and SSIM (means over the test views), rendered on the report's white background."""
    import mlx.core as mx

    from ..training.metrics import psnr, ssim

    ps, ss = [], []
    for k, i in enumerate(dataset.test):
        target, _ = dataset.load_image(i, background=BACKGROUND)
        cam = dataset.frames[i].camera if cameras is None else cameras[k]
        image = mx.clip(model.render(cam, background=BACKGROUND)["image"], 0.0, 1.0)
        ref = mx.array(target)
        ps.append(float(psnr(image, ref)))
        ss.append(float(ssim(image, ref)))
    return float(np.mean(ps)), float(np.mean(ss))


SCHEDULE_EVENTS = {"sh_up", "densify", "reset_opacity", "relocate", "grow"}


class _TrainRun:
    """One configuration being trained in segments."""

    def __init__(self, case: TrainCase, dataset, steps: int, seed: int):
        from ..splatting import GaussianModel
        from ..training import GaussianTrainer

        self.case, self.dataset = case, dataset
        model = GaussianModel.from_points(dataset.points, dataset.point_colors, sh_degree=case.sh_degree)
        self.initial = len(model)
        self.config = trainer_config(case, steps, self.initial, seed)
        self.trainer = GaussianTrainer(model, self.config, scene_extent=dataset.scene_extent())
        self.seconds = 0.0
        self.step_seconds = []
        self.curve = []
        self.extra_bytes = 0  # the most a segment allocated on top of what was held when it started
        self.stages = None

    def train_to(self, step: int) -> None:
        import mlx.core as mx

        todo = step - self.trainer.step_count
        if todo <= 0:
            return
        mx.eval(*self.trainer.model.params.values())
        held = mx.get_active_memory()
        mx.reset_peak_memory()
        t0 = last = time.perf_counter()

        def progress(done, total, info):
            nonlocal last
            now = time.perf_counter()
            self.step_seconds.append(now - last)
            last = now
            if info["step"] > self.config.steps // 2 and not set(info["stages"]) & SCHEDULE_EVENTS:
                self.stages = tuple(info["stages"])  # a step without schedule events, late in training

        self.trainer.fit(self.dataset, steps=todo, progress=progress)
        mx.eval(*self.trainer.model.params.values())
        self.seconds += time.perf_counter() - t0
        self.extra_bytes = max(self.extra_bytes, mx.get_peak_memory() - held)

    def state_bytes(self) -> int:
        """Bytes of the model's parameters and the optimizer's two moments of each."""
        return 3 * sum(v.nbytes for v in self.trainer.model.params.values())

    def checkpoint(self, eval_dataset) -> dict:
        p, s = _eval_views(self.trainer.model, eval_dataset)
        point = {"step": self.trainer.step_count, "seconds": self.seconds, "psnr": p, "ssim": s, "gaussians": len(self.trainer.model)}
        self.curve.append(point)
        return point

    def result(self) -> dict:
        last = self.curve[-1]
        return {
            "name": self.case.name, "factor": self.case.factor, "settings": self.case.settings(), "case": asdict(self.case),
            "steps": last["step"], "seconds": self.seconds, "steps_per_second": last["step"] / max(self.seconds, 1e-9),
            "gaussians": last["gaussians"], "initial_gaussians": self.initial, "psnr": last["psnr"], "ssim": last["ssim"],
            "state_mb": self.state_bytes() / 1e6, "memory_mb": (self.state_bytes() + self.extra_bytes) / 1e6, "step_ms": summary([1000 * s for s in self.step_seconds]),
            "image_size": [self.dataset.frames[0].camera.width, self.dataset.frames[0].camera.height],
            "curve": list(self.curve), "stages": list(self.stages or ()),
        }


def ply_megabytes(count: int, sh_degree: int) -> float:
    """Size of a standard 3DGS PLY of ``count`` splats: (14 + 3·(degree+1)²) float32 per splat (normals included)."""
    return count * 4 * (14 + 3 * (sh_degree + 1) ** 2) / 1e6


def _time_renders(models: list, cameras: list, repeats: int, progress, label: str) -> list:
    """{ms: [...], image: first render per camera} per (model, kwargs); repeats run in alternation over the models."""
    import mlx.core as mx

    out = [{"ms": [], "images": []} for _ in models]
    for k, (model, kwargs) in enumerate(models):  # warm-up, and the images for PSNR
        for cam in cameras:
            image = mx.clip(model.render(cam, background=BACKGROUND, **kwargs)["image"], 0.0, 1.0)
            mx.eval(image)
            out[k]["images"].append(image)
    for r in range(repeats):
        order = range(len(models)) if r % 2 == 0 else range(len(models) - 1, -1, -1)  # drifting load falls on all alike
        for k in order:
            model, kwargs = models[k]
            for cam in cameras:
                t0 = time.perf_counter()
                mx.eval(model.render(cam, background=BACKGROUND, **kwargs)["image"])
                out[k]["ms"].append(1000 * (time.perf_counter() - t0))
        progress(f"{label}: timing renders {r + 1}/{repeats}", SHARES["rendering"] / repeats)
    return out


@dataclass(frozen=True)
class Effect:
    """An optional stage, measured with it on and with it skipped: training settings (``TrainerConfig``
    fields) and render options for each side, and the active SH degree of each side."""

    name: str
    short: str
    train_on: dict
    train_off: dict = field(default_factory=dict)
    render_on: dict | None = None
    render_off: dict | None = None
    degree_on: int = 3
    degree_off: int = 3


EFFECTS = (
    Effect("D-SSIM loss term (weight 0.2 vs 0)", "D-SSIM loss term", {"lambda_dssim": 0.2}, {"lambda_dssim": 0.0}),
    Effect("depth, depth² and normal channels with their losses (2DGS regularisers)", "geometry channels and losses",
           {"lambda_2d_depth_variance": 100.0, "lambda_2d_normal_consistency": 0.05, "geometry_from": 0}, {},
           {"render_depth_variance": True, "render_normals": True}, {}),
    Effect("antialias compensation", "antialias compensation", {"antialias": True}, {}, {"antialias": True}, {}),
    Effect("UT projection on a pinhole camera (EWA when skipped)", "UT projection (pinhole camera)", {"projection": "ut"},
           {"projection": "auto"}, {"projection": "ut"}, {"projection": "auto"}),
    Effect("SH colour up to degree 3 (degree 0 when skipped)", "SH degree 3 (vs 0)", {}, {}, {"sh_degree": 3}, {"sh_degree": 0},
           degree_off=0),
    Effect("MCMC opacity and scale regularisers and SGLD noise", "MCMC regularisers and noise", {"method": "mcmc"},
           {"method": "mcmc", "mcmc_opacity_reg": 0.0, "mcmc_scale_reg": 0.0, "mcmc_noise_lr": 0.0}),
    Effect("bilateral colour grid", "bilateral colour grid", {"bilateral_grid": True}, {}),
)


def _effect_trainer(model, dataset, settings: dict, degree: int, seed: int):
    from ..training import GaussianTrainer, TrainerConfig

    kw = dict(method="vanilla", steps=10**6, background=BACKGROUND, densify_from=10**9, sh_increase_every=0, seed=seed)
    kw.update(settings)
    trainer = GaussianTrainer(model.copy(), TrainerConfig(**kw), scene_extent=dataset.scene_extent(), num_images=len(dataset.frames))
    trainer.active_sh_degree = degree
    return trainer


def _measure_effect(effect, model, dataset, repeats: int, render_repeats: int, seed: int) -> dict:
    """Training steps (and renders) with the effect on and off, in adjacent pairs whose order alternates.

    Each pair's difference (on - off) is measured within a second, so load that
    drifts on a shared machine mostly cancels in it; the saving reported is the
    median of these paired differences, with their 25-75% range.
    """
    import mlx.core as mx

    trainers = [_effect_trainer(model, dataset, effect.train_on, effect.degree_on, seed),
                _effect_trainer(model, dataset, effect.train_off, effect.degree_off, seed)]
    train_ids = dataset.train
    times = [[], []]
    stages = [None, None]
    for r in range(repeats + 2):  # two warm-up steps per side
        index = train_ids[r % len(train_ids)]
        target, _ = dataset.load_image(index, background=BACKGROUND)
        camera = dataset.frames[index].camera
        for side in ((0, 1) if r % 2 == 0 else (1, 0)):
            t0 = time.perf_counter()
            info = trainers[side].step(camera, target, background=BACKGROUND, image_index=index)
            mx.eval(*trainers[side].model.params.values())
            if r >= 2:
                times[side].append(1000 * (time.perf_counter() - t0))
            stages[side] = info["stages"]
    result = {
        "name": effect.name, "train_on_ms": summary(times[0]), "train_off_ms": summary(times[1]),
        "train_saved_ms": summary([a - b for a, b in zip(*times)]),
        "train_stages_on": [s for s in stages[0] if s not in stages[1]], "train_stages_off": [s for s in stages[1] if s not in stages[0]],
        "render_on_ms": None, "render_off_ms": None, "render_saved_ms": None, "render_stages_on": [], "render_stages_off": [],
    }
    if effect.render_on is not None:
        options = (effect.render_on, effect.render_off or {})
        cams = [dataset.frames[i].camera for i in dataset.test]
        rtimes, rstages = [[], []], [None, None]
        for r in range(render_repeats + 1):  # one warm-up round
            for k, cam in enumerate(cams):
                for side in ((0, 1) if (r + k) % 2 == 0 else (1, 0)):
                    t0 = time.perf_counter()
                    out = model.render(cam, background=BACKGROUND, **options[side])
                    mx.eval(out["image"], *(out[c] for c in ("depth", "depth_variance", "normals") if c in out))
                    if r >= 1:
                        rtimes[side].append(1000 * (time.perf_counter() - t0))
                    rstages[side] = out["stages"]
        result.update(
            render_on_ms=summary(rtimes[0]), render_off_ms=summary(rtimes[1]), render_saved_ms=summary([a - b for a, b in zip(*rtimes)]),
            render_stages_on=[s for s in rstages[0] if s not in rstages[1]], render_stages_off=[s for s in rstages[1] if s not in rstages[0]],
        )
    return result


def _views_image(panels: list, labels: list, scale: int):
    """Images side by side, each scaled up ``scale`` times (nearest), with a label above each."""
    from PIL import Image, ImageDraw

    tiles = [Image.fromarray((np.clip(np.asarray(p), 0, 1) * 255).round().astype(np.uint8)) for p in panels]
    w, h = tiles[0].width * scale, tiles[0].height * scale
    pad, head = 8, 26
    canvas = Image.new("RGB", (len(tiles) * (w + pad) + pad, h + head + pad), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    label_font = plt.font(14)
    for k, (tile, text) in enumerate(zip(tiles, labels)):
        x = pad + k * (w + pad)
        canvas.paste(tile.resize((w, h), Image.Resampling.NEAREST), (x, head))
        draw.text((x, 5), text, font=label_font, fill=plt.INK)
    return canvas


# ------------------------------------------------------------------ the run
def measure(mode: Mode, data_dir: str, seed: int = 0, progress=None, should_stop=None) -> dict:
    """Run every measurement of ``mode`` (dataset in ``data_dir``); returns the results (JSON-ready) and images."""
    import mlx.core as mx

    from ..datasets import load_dataset
    from ..training.metrics import psnr, ssim

    cases = train_cases(mode)
    spec = replace(mode.scene, seed=seed)
    tick = _Progress(progress, should_stop)
    started = time.perf_counter()
    timings = {}
    date = datetime.datetime.now(datetime.timezone.utc).astimezone().strftime("%Y-%m-%d %H:%M %Z")

    # 1. scene
    t0 = time.perf_counter()
    truth = write_dataset(data_dir, spec, progress=lambda done, n: tick(f"scene: rendering view {done}/{n}", SHARES["scene"] / n))
    full = load_dataset(data_dir)
    half = load_dataset(data_dir, factor=2)
    timings["scene"] = time.perf_counter() - t0

    # 2. training, in turns
    t0 = time.perf_counter()
    runs = [_TrainRun(case, half if case.scale == 0.5 else full, mode.steps, seed) for case in cases]
    initial_psnr, initial_ssim = _eval_views(runs[0].trainer.model, full)
    marks = [round(mode.steps * (k + 1) / mode.checkpoints) for k in range(mode.checkpoints)]
    for mark in marks:
        for run in runs:
            run.train_to(mark)
            point = run.checkpoint(full)
            tick(f"train '{run.case.name}': step {mark:,}/{mode.steps:,}, {point['psnr']:.2f} dB, {run.seconds:.0f} s",
                 SHARES["training"] / (len(runs) * len(marks)))
    train = [run.result() for run in runs]
    for run, row in zip(runs, train):
        if run.case.scale != 1.0:  # also at the resolution it trained at
            row["psnr_own_resolution"], row["ssim_own_resolution"] = _eval_views(run.trainer.model, run.dataset)
    timings["training"] = time.perf_counter() - t0

    # 3. rendering: compaction x SH degree (EWA), UT, and the ground truth
    t0 = time.perf_counter()
    trained = runs[0].trainer.model
    models, rows = [], []
    for projection in ("ewa", "ut"):
        for fraction in (1.0, 0.5, 0.25):
            for degree in ((3, 1, 0) if projection == "ewa" else (3,)):
                keep = None if fraction == 1.0 else max(int(round(fraction * len(trained))), 1)
                model = trained.compact(max_gaussians=keep, target_sh_degree=degree)
                models.append((model, {"projection": projection}))
                rows.append({"name": f"{int(fraction * 100)}%, SH {degree}, {projection.upper()}", "fraction": fraction,
                             "sh_degree": degree, "projection": projection, "gaussians": len(model)})
    models.append((truth, {"projection": "ewa"}))
    rows.append({"name": "ground truth scene", "fraction": None, "sh_degree": truth.sh_degree, "projection": "ewa", "gaussians": len(truth)})
    cams = [full.frames[i].camera for i in full.test]
    targets = [mx.array(full.load_image(i, background=BACKGROUND)[0]) for i in full.test]
    timed = _time_renders(models, cams, mode.render_repeats, tick, "render")
    for row, t in zip(rows, timed):
        row["ms"] = summary(t["ms"])
        row["ms_median"] = row["ms"]["median"]
        row["psnr"] = float(np.mean([float(psnr(im, ref)) for im, ref in zip(t["images"], targets)]))
        row["ssim"] = float(np.mean([float(ssim(im, ref)) for im, ref in zip(t["images"], targets)]))
        row["ply_mb"] = ply_megabytes(row["gaussians"], row["sh_degree"])
    smallest = next(k for k, r in enumerate(rows) if r["fraction"] == 0.25 and r["sh_degree"] == 0)
    sh0 = next(run for run in runs if run.case.sh_degree == 0)
    views = {
        "ground truth": np.array(targets[0]),
        f"baseline ({len(trained):,} Gaussians)": np.array(timed[0]["images"][0]),
        f"baseline at 25%, SH 0 ({rows[smallest]['gaussians']:,})": np.array(timed[smallest]["images"][0]),
        f"trained at SH 0 ({len(sh0.trainer.model):,})": np.array(mx.clip(sh0.trainer.model.render(cams[0], background=BACKGROUND)["image"], 0, 1)),
    }
    timings["rendering"] = time.perf_counter() - t0

    # 4. effects on demand
    t0 = time.perf_counter()
    effects = []
    for effect in EFFECTS:
        effects.append(_measure_effect(effect, trained, full, mode.effect_repeats, mode.render_repeats, seed))
        tick(f"effects: {effect.short}", SHARES["effects"] / len(EFFECTS))
    timings["effects"] = time.perf_counter() - t0

    # 5. Pareto choices
    base_seconds = train[0]["seconds"]
    points = [dict(p, name=row["name"]) for row in train for p in row["curve"]]
    train_budgets = [f * base_seconds for f in (0.1, 0.25, 0.5, 1.0, 2.0, 4.0)]
    base_ms = rows[0]["ms_median"]
    render_budgets = [f * base_ms for f in (0.25, 0.5, 0.75, 1.0, 1.5)]
    candidates = [r for r in rows if r["fraction"] is not None]
    timings["total"] = time.perf_counter() - started

    return {
        "mode": mode.name, "mode_description": mode.describe(), "seed": seed, "date": date, "machine": machine_info(),
        "load": summary(tick.loads), "peak_rss_mb": peak_rss_mb(), "timings": timings,
        "scene": {"description": spec.describe(), "ground_truth_gaussians": len(truth), "initial_points": len(full.points),
                  "training_views": len(full.train), "heldout_views": len(full.test), "image_size": spec.image_size,
                  "initial_psnr": initial_psnr, "initial_ssim": initial_ssim},
        "schedule": schedule(mode.steps, runs[0].initial, mode.budgets[1]),
        "train": train,
        "render": rows,
        "effects": effects,
        "pareto_train": [{"budget": b, "best": best} for b, best in budget_table(points, train_budgets, "seconds", "psnr", PSNR_TIE_DB)],
        "pareto_train_front": pareto_front(points, "seconds", "psnr"),
        "pareto_render": [{"budget": b, "best": best} for b, best in budget_table(candidates, render_budgets, "ms_median", "psnr", PSNR_TIE_DB)],
        "_images": views,
    }


# ------------------------------------------------------------------ the report
def _table(headers: list, rows: list, align: str) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---:" if a == "r" else "---" for a in align) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _machine_line(results: dict) -> str:
    m = results["machine"]
    memory = f", {m['memory_gb']:.0f} GB memory" if m.get("memory_gb") else ""
    text = f"{m['cpu']} ({m['machine']}, {m['cores']} cores{memory}), {m['platform']}; Python {m['python']}, MLX {m['mlx']} ({m['mlx_device']}), render backend {m['backend']}"
    if m.get("raster_threads"):
        text += f" with {m['raster_threads']} threads"
    if _shared(results):
        text += "; a **shared machine**: other jobs ran during the measurement (see the load)"
    return text


def _shared(results: dict) -> bool:
    """Whether other processes kept the machine busy: the median 1-minute load exceeded half the cores plus one."""
    load, cores = results["load"], results["machine"]["cores"] or 1
    return bool(load["n"]) and load["median"] > 0.5 * cores + 1


def _load_line(results: dict) -> str:
    load, cores = results["load"], results["machine"]["cores"] or 1
    if not load["n"]:
        return "load average not available"
    text = f"1-minute load average during the run: median {load['median']:.1f}, range {load['min']:.1f}-{load['max']:.1f} on {cores} cores"
    if _shared(results):
        text += (" - other processes were running, so absolute times are slower than on an idle machine, and noisier; "
                 "configurations were measured in alternation, so their ratios hold better than their absolute values")
    return text


def _fmt_seconds(s: float) -> str:
    return f"{s:.0f}" if s >= 100 else f"{s:.1f}" if s >= 1 else f"{s:.2f}"


def _duration(s: float) -> str:
    m, sec = divmod(int(round(s)), 60)
    return f"{m} min {sec} s" if m else f"{sec} s"


def _figures(results: dict) -> dict:
    """PNG bytes of every plot and image of the report."""
    note = f"{results['machine']['cpu']}, {results['machine']['cores']} cores, MLX {results['machine']['mlx']} ({results['machine']['backend']}); {results['mode']} mode, {results['date']}"
    train = results["train"]

    def series(key):
        return [plt.Series(r["name"], [p["seconds"] for p in r["curve"]], [p[key] for p in r["curve"]]) for r in train]

    out = {
        PLOTS["train_psnr"]: plt.plot(series("psnr"), title=f"Held-out PSNR against training time ({train[0]['steps']:,} steps per configuration)",
                                      xlabel="training wall time (s, log scale)", ylabel="held-out PSNR (dB)", log_x=True, note=note),
        PLOTS["train_ssim"]: plt.plot(series("ssim"), title=f"Held-out SSIM against training time ({train[0]['steps']:,} steps per configuration)",
                                      xlabel="training wall time (s, log scale)", ylabel="held-out SSIM", log_x=True, note=note),
    }
    groups = {}
    for row in results["render"]:
        key = "ground truth scene" if row["fraction"] is None else f"{row['projection'].upper()}, SH {row['sh_degree']}"
        groups.setdefault(key, []).append(row)
    render_series = []
    for i, (key, rows) in enumerate(groups.items()):
        render_series.append(plt.Series(  # the first series' points are labelled with their share and count of Gaussians
            key + ("" if key.startswith("ground") else " (100/50/25% of the Gaussians)"), [r["ms"]["median"] for r in rows], [r["psnr"] for r in rows],
            xerr=[(r["ms"]["p25"], r["ms"]["p75"]) for r in rows],
            labels=[f"{r['fraction']:.0%} ({r['gaussians']:,})" for r in rows] if i == 0 else None, line=len(rows) > 1,
        ))
    truth = [s for s in render_series if s.label.startswith("ground")]
    shown = [s for s in render_series if not s.label.startswith("ground")]
    out[PLOTS["render"]] = plt.plot(
        shown, title="Render time against held-out PSNR (trained baseline, compacted)", xlabel="render time per view (ms, median; bars: 25-75%)",
        ylabel="held-out PSNR (dB)", note=note + (f"; ground truth scene: {truth[0].x[0]:.1f} ms" if truth else ""),
    )
    effects = results["effects"]
    out[PLOTS["effects"]] = plt.barh(
        [f"{k}. {_short_effect(e['name'])}" for k, e in enumerate(effects, start=1)],
        {"effect on": [e["train_on_ms"]["median"] for e in effects], "skipped": [e["train_off_ms"]["median"] for e in effects]},
        title="Effects on demand: a training step with each optional stage on and skipped", xlabel="training step time (ms, median)", note=note,
    )
    images = results.get("_images")
    if images:
        out[PLOTS["views"]] = _views_image(list(images.values()), list(images.keys()), max(1, 256 // results["scene"]["image_size"]))
    return {name: plt.png_bytes(image) for name, image in out.items()}


def _short_effect(name: str) -> str:
    return next((e.short for e in EFFECTS if e.name == name), name)


def render_markdown(results: dict) -> str:
    """The report (markdown) of ``measure``'s results."""
    t = results["timings"]
    train, render, effects = results["train"], results["render"], results["effects"]
    base = train[0]
    scene = results["scene"]
    lines = [
        "# What accuracy costs on this machine",
        "",
        f"`mlx3d bench accuracy{' --quick' if results['mode'] == 'quick' else ''}` - {results['mode']} mode, {results['date']}, "
        f"{_duration(t['total'])} in all (scene {_duration(t['scene'])}, training {_duration(t['training'])}, rendering {_duration(t['rendering'])}, "
        f"effects {_duration(t['effects'])}); seed {results['seed']}. Every number below comes from this one run on this one machine.",
        "",
        f"- **Machine:** {_machine_line(results)}.",
        f"- **Load:** {_load_line(results)}. Peak memory of the process: {results['peak_rss_mb']:.0f} MB.",
        f"- **Mode:** {results['mode_description']}.",
        f"- **Scene:** the built-in scene (`mlx3d.report.scene`): a checker ground, a striped sphere whose colour changes with the view "
        f"(SH bands 1 and 3) and a cube with a view-dependent top (band 2), {scene['ground_truth_gaussians']:,} ground-truth Gaussians "
        f"rendered by mlx3d into {scene['description']}. The initial model scores {scene['initial_psnr']:.2f} dB.",
        "",
        "**How to read it.** Each training configuration is the baseline with one setting changed; its curve shows the held-out PSNR "
        "reached after a given training time, so a curve above and to the left of another buys more accuracy for the same time. "
        "The rendering plot shows how much render time each drop in accuracy saves. The Pareto tables answer the question directly: "
        "given this much time, which setting is best. The effects table shows what an optional stage costs when it runs and what skipping "
        "it saves. Timings are medians; spreads are the 25-75% range of repeated measurements.",
        "",
        f"![Held-out views]({PLOTS['views']})",
        "",
        "## Training: accuracy against time",
        "",
        f"Baseline: **{base['settings']}**, {base['steps']:,} steps. Every configuration trains the same number of steps with the "
        "same schedule; the held-out views are evaluated at the checkpoints (evaluation time is not counted). "
        f"Schedule, laid out over the {base['steps']:,} steps: " + _schedule_text(results["schedule"]) + ".",
        "",
        f"![Held-out PSNR against training time]({PLOTS['train_psnr']})",
        "",
        f"![Held-out SSIM against training time]({PLOTS['train_ssim']})",
        "",
    ]
    rows = []
    for r in train:
        size = f"{r['image_size'][0]}x{r['image_size'][1]}"
        rows.append([
            r["name"], r["settings"], size, f"{r['steps']:,}", _fmt_seconds(r["seconds"]), f"{r['steps_per_second']:.1f}",
            format_spread(r["step_ms"], digits=0), f"{r['gaussians']:,}", f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['memory_mb']:.0f}",
        ])
    lines += [
        _table(["configuration", "settings", "images", "steps", "train time (s)", "steps/s", "ms per step (25-75%)", "Gaussians",
                "held-out PSNR (dB)", "held-out SSIM", "MLX memory (MB)"], rows, "llrrrrrrrrr"),
        "",
        "MLX memory is what that configuration needs from MLX's allocator: its parameters and Adam moments at the end, plus the most "
        "that one of its training segments allocated on top of what was already held (the process holds every configuration at once; "
        f"its own peak resident memory was {results['peak_rss_mb']:.0f} MB).",
    ]
    for r in train:
        if "psnr_own_resolution" in r:
            lines += ["", f"'{r['name']}' trains on images at {r['image_size'][0]}x{r['image_size'][1]} and is evaluated here at the full "
                      f"{scene['image_size']}x{scene['image_size']} on the same held-out views as the others; at its own resolution it scores "
                      f"{r['psnr_own_resolution']:.2f} dB PSNR, {r['ssim_own_resolution']:.4f} SSIM."]
    lines += ["", "## Rendering: time against accuracy", "",
              f"The trained baseline ({render[0]['gaussians']:,} Gaussians) compacted with `GaussianModel.compact` to 100/50/25% of its "
              "Gaussians (the most important kept) and SH degree 3/1/0, rendered from every held-out view with EWA and with UT projection; "
              "the ground-truth scene is rendered for comparison (its PSNR is only limited by the 8-bit images).", "",
              f"![Render time against PSNR]({PLOTS['render']})", ""]
    rows = [[r["name"], f"{r['gaussians']:,}", format_spread(r["ms"], digits=2), f"{r['ms']['min']:.2f}-{r['ms']['max']:.2f}",
             f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['ply_mb']:.2f}"] for r in render]
    lines += [_table(["model", "Gaussians", "ms per view, median (25-75%)", "min-max (ms)", "held-out PSNR (dB)", "held-out SSIM", "PLY size (MB)"],
                     rows, "lrrrrrr"), ""]

    lines += ["## Best configuration for a time budget", "",
              f"Training: for each budget (a fraction of the baseline's {_fmt_seconds(base['seconds'])} s), the configuration and checkpoint "
              f"with the best held-out PSNR among all that trained for at most that long (within {PSNR_TIE_DB} dB, the faster).", ""]
    rows = []
    for entry in results["pareto_train"]:
        b, best = entry["budget"], entry["best"]
        label = f"{b / base['seconds']:.0%} ({_fmt_seconds(b)} s)"
        rows.append([label, "none fits"] + [""] * 4 if best is None else
                    [label, best["name"], f"{best['step']:,}", _fmt_seconds(best["seconds"]), f"{best['psnr']:.2f}", f"{best['ssim']:.4f}"])
    lines += [_table(["time budget", "best configuration", "at step", "train time (s)", "held-out PSNR (dB)", "held-out SSIM"], rows, "llrrrr"), ""]
    front = results["pareto_train_front"]
    lines += ["Every checkpoint that no other beats on both time and PSNR (the Pareto front): " +
              ", ".join(f"{p['name']} @ {p['step']:,} ({_fmt_seconds(p['seconds'])} s, {p['psnr']:.2f} dB)" for p in front) + ".", ""]
    base_ms = render[0]["ms"]["median"]
    lines += [f"Rendering: for each budget (a fraction of the uncompacted baseline's {base_ms:.2f} ms per view), the compacted model with the "
              f"best held-out PSNR whose median render time fits (within {PSNR_TIE_DB} dB, the faster).", ""]
    rows = []
    for entry in results["pareto_render"]:
        b, best = entry["budget"], entry["best"]
        label = f"{b / base_ms:.0%} ({b:.2f} ms)"
        rows.append([label, "none fits", "", "", ""] if best is None else
                    [label, best["name"], f"{best['gaussians']:,}", f"{best['ms']['median']:.2f}", f"{best['psnr']:.2f}"])
    lines += [_table(["time budget", "best model", "Gaussians", "ms per view", "held-out PSNR (dB)"], rows, "llrrr"), ""]

    lines += ["## Effects on demand: what skipping a stage saves", "",
              "A training step and a render with an optional stage on, and with it skipped as the step plan (`mlx3d.training.plan.step_plan`) "
              f"and the render plan (`plan_render`) skip it when it is not needed: on the trained baseline model ({render[0]['gaussians']:,} Gaussians, "
              f"{scene['image_size']}x{scene['image_size']}), {effects[0]['train_on_ms']['n']} training steps per side and "
              f"{_render_count(effects)} renders per side (every held-out view, repeatedly), on and off in adjacent pairs. "
              "Times are medians (25-75%); the time saved is the median of the paired differences, which cancels most of the drift of a "
              "shared machine's load, with its 25-75% range; a saving whose range includes zero is marked *within noise*. "
              "'Stages' are those that ran only with the effect on (instead of the ones in brackets), as the trainer and renderer report them.", "",
              f"![Effects on demand]({PLOTS['effects']})", ""]
    rows = []
    for k, e in enumerate(effects, start=1):
        stages = ", ".join(e["train_stages_on"] + [s for s in e["render_stages_on"] if s not in e["train_stages_on"]]) or "-"
        instead = e["train_stages_off"] + [s for s in e["render_stages_off"] if s not in e["train_stages_off"]]
        if instead:
            stages += f" (instead of {', '.join(instead)})"
        row = [str(k), e["name"], stages, format_spread(e["train_on_ms"], digits=1), format_spread(e["train_off_ms"], digits=1),
               _saved(e["train_saved_ms"], e["train_on_ms"], 1)]
        if e["render_on_ms"] is not None:
            row += [format_spread(e["render_on_ms"], digits=2), format_spread(e["render_off_ms"], digits=2), _saved(e["render_saved_ms"], e["render_on_ms"], 2)]
        else:
            row += ["-", "-", "-"]
        rows.append(row)
    lines += [_table(["#", "effect", "stages", "training step, on (ms)", "skipped (ms)", "saved per step (ms)", "render, on (ms)", "skipped (ms)",
                      "saved per render (ms)"], rows, "lllrrrrrr"), ""]

    lines += ["## What each configuration runs", "",
              "The stages of a training step late in training (one without schedule events; `info[\"stages\"]`): the baseline's, and what the others change.", ""]
    base_stages = base["stages"]
    rows = [[base["name"], " -> ".join(base_stages)]]
    for r in train[1:]:
        added = [s for s in r["stages"] if s not in base_stages]
        removed = [s for s in base_stages if s not in r["stages"]]
        change = ", ".join([f"+{s}" for s in added] + [f"-{s}" for s in removed]) or "same stages"
        rows.append([r["name"], change])
    lines += [_table(["configuration", "stages"], rows, "ll"), "",
              "`results.json` holds every number of this report, the checkpoints of each curve included.", ""]
    return "\n".join(lines)


def _render_count(effects: list) -> int:
    return next((e["render_on_ms"]["n"] for e in effects if e["render_on_ms"] is not None), 0)


def _saved(saved: dict, on: dict, digits: int) -> str:
    """``'12.3 (10.1-14.0), 21%'``: the median paired saving, its 25-75% range and its share of the time with the effect on."""
    if saved is None or not saved["n"]:
        return "-"
    text = f"{format_spread(saved, digits=digits)}, {saved['median'] / on['median']:.0%}"
    return text + (" *within noise*" if saved["p25"] <= 0 <= saved["p75"] else "")


def _schedule_text(s: dict) -> str:
    return (f"SH degree up every {s['sh_increase_every']:,} steps, density control (vanilla: clone/split/prune; MCMC: relocate and grow) "
            f"every {s['densify_every']:,} steps from step {s['densify_from']:,} to {s['densify_until']:,}, no opacity reset, "
            f"MCMC growth to the budget by the last event (baseline: {s['mcmc_growth']:.1%} per event), other settings `TrainerConfig` defaults")


@contextlib.contextmanager
def _sigint_deferred():
    """Hold Ctrl+C back while the report's files are put in place (POSIX main thread), so they change together."""
    can = hasattr(signal, "pthread_sigmask") and _in_main_thread()
    if can:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if can:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _in_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def write_report(results: dict, out_dir) -> list:
    """Write ``README.md``, the PNGs and ``results.json`` into ``out_dir`` (each atomically, all at the end); returns the paths."""
    from ..io.atomic import atomic_write

    files = _figures(results)
    public = {k: v for k, v in results.items() if not k.startswith("_")}
    files["results.json"] = (json.dumps(public, indent=1, default=float) + "\n").encode()
    files[REPORT_NAME] = render_markdown(results).encode()
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    with _sigint_deferred():
        for name, data in files.items():  # the report last
            path = os.path.join(out_dir, name)
            with atomic_write(path) as f:
                f.write(data)
            paths.append(path)
    return paths


def run_accuracy(out_dir, mode: str | Mode = "quick", seed: int = 0, progress=None, should_stop=None, keep_data: bool = False) -> dict:
    """Measure and write the report into ``out_dir``; returns {'results', 'paths', 'report'}.

    progress(done, total, what) follows the work; should_stop() is polled to
    cancel (raises ``Cancelled``, a KeyboardInterrupt). Cancelled or failed runs
    write nothing into ``out_dir`` (a kept dataset may stay).
    """
    mode = MODES[mode] if isinstance(mode, str) else mode
    out_dir = os.path.abspath(os.fspath(out_dir))
    if keep_data:
        data_dir, tmp = os.path.join(out_dir, "dataset"), None
    else:
        tmp = tempfile.mkdtemp(prefix="mlx3d-accuracy-")
        data_dir = os.path.join(tmp, "dataset")
    try:
        results = measure(mode, data_dir, seed, progress, should_stop)
        paths = write_report(results, out_dir)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return {"results": results, "paths": paths, "report": os.path.join(out_dir, REPORT_NAME)}


__all__ = ["MODES", "Mode", "TrainCase", "Cancelled", "machine_info", "measure", "render_markdown", "run_accuracy", "schedule",
           "train_cases", "write_report"]
