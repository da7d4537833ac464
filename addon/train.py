"""Train Gaussians on a dataset inside Blender: ``TrainSession`` and ``train_dataset``.

A dataset is a folder ``mlx3d.datasets.load_dataset`` reads (COLMAP,
NeRF-synthetic or nerfstudio; a folder written by ``capture`` is both COLMAP
and nerfstudio). Training starts from ``mlx3d.training.initial.initial_state``
(the dataset's points, or random ones when it has none; the method's initial
opacity and scale; MCMC's default budget) and runs ``mlx3d.training.GaussianTrainer``;
views are drawn at random from the training split by ``GaussianTrainer.fit``,
which also composites each target on the colour the render uses.

The result is a splat object (see ``splat_object``) with an identity
transform: dataset cameras are in world coordinates, so the Gaussians are
too. Its custom property ``mlx3d_training`` records the dataset, method, step,
loss and PSNR of the state it holds.

``TrainSession`` splits the work so the modal operator can run a few steps per
timer tick: ``step(n, max_seconds=...)`` trains (and refreshes the object every
``update_every`` steps), ``status()`` reports progress and ``finish()`` writes
the final (or, after a cancel or an error, the last good) state into the
object. ``train_dataset`` runs a session to the end for scripts and the
headless command.
"""

from __future__ import annotations

import math
import operator
import os
import sys
import time
from collections import deque

import mlx.core as mx
import numpy as np

from mlx3d.datasets import Dataset, load_dataset
from mlx3d.io import write_splat_ply
from mlx3d.splatting import GaussianModel
from mlx3d.training import GaussianTrainer, TrainerConfig
from mlx3d.training.initial import initial_state
from mlx3d.training.metrics import psnr

from .splat_object import create_splat_object, replace_splats

METHODS = ("vanilla", "mcmc", "2dgs")
METHOD_ITEMS = [
    ("vanilla", "Vanilla 3DGS", "3D Gaussian Splatting with adaptive density control (clone, split, prune)"),
    ("mcmc", "3DGS-MCMC", "Relocation of dead Gaussians, growth to the cap and SGLD noise (set Max Gaussians)"),
    ("2dgs", "2DGS surfels", "Flat Gaussians with depth and normal regularisers: the best input for Extract Mesh"),
]
BACKGROUNDS = ("black", "white", "random")
BACKGROUND_ITEMS = [
    ("black", "Black", "Render and composite transparent target pixels on black"),
    ("white", "White", "Render and composite transparent target pixels on white"),
    ("random", "Random", "A new random colour every step (discourages Gaussians from painting the background)"),
]
DEFAULT_NAME = "Trained splats"
INFO_KEY = "mlx3d_training"
LOSS_WINDOW = 10  # steps averaged for the reported loss and PSNR


class TrainError(ValueError):
    """Training cannot start or go on (bad dataset, bad option); the message says why."""


def _positive_int(value, name) -> int:
    if isinstance(value, bool):
        raise TrainError(f"{name} must be a positive integer, got {value!r}")
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise TrainError(f"{name} must be a positive integer, got {value!r}") from None
    if v != value or v < 1:
        raise TrainError(f"{name} must be a positive integer, got {value!r}")
    return v


def format_duration(seconds) -> str:
    """``H:MM:SS`` or ``M:SS``; ``--:--`` when unknown."""
    if seconds is None or not math.isfinite(seconds):
        return "--:--"
    s = int(round(seconds))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def format_status(status: dict) -> str:
    """One line: step, loss, PSNR, Gaussian count, steps/s and ETA of a ``TrainSession.status()``."""
    loss = "-" if status["loss"] is None else f"{status['loss']:.4f}"
    quality = "-" if status["psnr"] is None else f"{status['psnr']:.2f} dB"
    rate = "-" if status["steps_per_second"] is None else f"{status['steps_per_second']:.1f}"
    return (
        f"step {status['step']:,}/{status['steps']:,}  loss {loss}  PSNR {quality}  "
        f"{status['num_gaussians']:,} Gaussians  {rate} steps/s  ETA {format_duration(status['eta_seconds'])}"
    )


def _alive(obj) -> bool:
    """False when the Blender object was deleted (its Python reference is stale)."""
    if obj is None:
        return False
    try:
        obj.name
    except ReferenceError:
        return False
    return True


class TrainSession:
    """One training run, in steps: ``step()`` until ``done``, then ``finish()``.

    data: a dataset folder (or a ``transforms*.json`` path), or a loaded ``Dataset``.
    method: one of ``METHODS`` (see ``TrainerConfig``); steps: total training steps
    (the learning-rate and density schedules are laid out over them);
    max_gaussians: cap on the number of Gaussians (None: no cap for vanilla and
    2dgs, ``mlx3d.training.initial.mcmc_budget`` for mcmc; initial points
    beyond it are subsampled, seeded); sh_degree: SH degree of the model (the
    active degree grows every ``sh_increase_every`` steps); background:
    ``'black'``, ``'white'``, ``'random'`` or (r, g, b), the colour renders
    and targets are composited on; update_every: steps between refreshes of
    the scene object (0: only ``update_object()``/``finish()``); name: of the
    splat object (Blender appends .001 when taken); seed: of the initial
    scales, the view order and the random backgrounds; collection: where the
    object goes (default: the active collection).

    trainer_overrides: further ``TrainerConfig`` fields, e.g.
    ``densify_from=10, densify_every=20, densify_grad_threshold=1e-7`` for a short run
    in which densification fires, or ``sh_increase_every``, learning rates,
    ``checkpoint_every``/``checkpoint_dir``.

    The constructor loads the dataset and builds the model and trainer without
    touching the scene; bad input raises ``TrainError`` or the dataset's
    ``DatasetError`` (both ``ValueError``), naming the file. ``start_progress(done,
    total)`` follows the initial model's plane sweep (opaque photos without points).
    """

    def __init__(self, data, *, steps, method="vanilla", max_gaussians=None, sh_degree=3, background="black",
                 update_every=100, name=DEFAULT_NAME, seed=0, collection=None, start_progress=None, **trainer_overrides):
        if method not in METHODS:
            raise TrainError(f"method {method!r} is not available; choose one of {', '.join(METHODS)}")
        steps = _positive_int(steps, "steps")
        if max_gaussians is not None:
            max_gaussians = _positive_int(max_gaussians, "max_gaussians")
        if isinstance(sh_degree, bool) or sh_degree not in (0, 1, 2, 3):
            raise TrainError(f"sh_degree must be 0, 1, 2 or 3, got {sh_degree!r}")
        if isinstance(background, str):
            if background not in BACKGROUNDS:
                raise TrainError(f"background must be one of {', '.join(BACKGROUNDS)} or (r, g, b), got {background!r}")
        else:
            try:
                background = tuple(float(c) for c in background)
            except (TypeError, ValueError):
                raise TrainError(f"background must be one of {', '.join(BACKGROUNDS)} or (r, g, b), got {background!r}") from None
            if len(background) != 3 or not all(0.0 <= c <= 1.0 for c in background):
                raise TrainError(f"background (r, g, b) must be three numbers in [0, 1], got {background!r}")
        try:
            every = -1 if isinstance(update_every, bool) else operator.index(update_every)
        except TypeError:
            every = -1
        if every < 0:
            raise TrainError(f"update_every must be a non-negative integer (0: only at the end), got {update_every!r}")

        if isinstance(data, Dataset):
            dataset = data
        else:
            if data is None or not os.fspath(data):
                raise TrainError("choose a dataset folder (COLMAP, NeRF-synthetic or nerfstudio, e.g. one made by Capture Dataset)")
            dataset = load_dataset(os.path.abspath(os.fspath(data)))
        where = str(dataset.root) if dataset.root is not None else "the dataset"
        if not dataset.train:
            raise TrainError(f"{where}: the dataset has no training views")
        try:
            config = TrainerConfig(method=method, steps=steps, max_gaussians=max_gaussians, background=background, seed=seed, **trainer_overrides)
        except TypeError as exc:
            known = ", ".join(f for f in TrainerConfig.__dataclass_fields__)
            raise TrainError(f"bad trainer setting ({exc}); TrainerConfig fields are: {known}") from None
        except ValueError as exc:
            raise TrainError(f"bad trainer setting: {exc}") from None
        start = initial_state(dataset, config, sh_degree=sh_degree, progress=start_progress)

        self.dataset = dataset
        self.where = where
        self.name = name
        self.collection = collection
        self.update_every = every
        self.notes: list = list(start.notes)
        self.trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
        self.object = None
        self.object_step = None  # training step of the state the object holds
        self.losses: list = []
        self.psnrs: list = []
        self._times: deque = deque(maxlen=50)  # (step, perf_counter) of recent steps, for the rate
        self.t_start = None
        self.error = None
        self._finished = None

    # -- state
    @property
    def model(self) -> GaussianModel:
        return self.trainer.model

    @property
    def config(self) -> TrainerConfig:
        return self.trainer.config

    @property
    def steps(self) -> int:
        return self.config.steps

    @property
    def step_count(self) -> int:
        return self.trainer.step_count

    @property
    def done(self) -> bool:
        return self.trainer.step_count >= self.config.steps

    # -- training
    def _after_step(self, done, total, info) -> None:
        self.losses.append(info["loss"])
        self.psnrs.append(info["psnr"])
        self._times.append((info["step"], time.perf_counter()))
        if self.update_every and info["step"] % self.update_every == 0:
            self.update_object()

    def step(self, n: int = 1, *, max_seconds: float | None = None) -> int:
        """Run up to ``n`` training steps (fewer at the end, or once ``max_seconds`` have passed; at least one).

        The scene object is refreshed after every step that is a multiple of
        ``update_every``. Returns the number of steps run. A ``TrainingError``
        (NaN/Inf) or a ``DatasetError`` (an unreadable image) propagates with
        the model at the last completed step.
        """
        if self._finished is not None:
            raise TrainError("this training session has finished")
        n = min(int(n), self.config.steps - self.trainer.step_count)
        if n <= 0:
            return 0
        if self.t_start is None:
            self.t_start = time.perf_counter()
            self._times.append((self.trainer.step_count, self.t_start))
        before = self.trainer.step_count
        should_stop = None
        if max_seconds is not None:
            deadline = time.perf_counter() + max_seconds
            should_stop = lambda: self.trainer.step_count > before and time.perf_counter() >= deadline  # noqa: E731
        try:
            self.trainer.fit(self.dataset, n, progress=self._after_step, should_stop=should_stop)
        except Exception as exc:
            self.error = str(exc)
            raise
        return self.trainer.step_count - before

    def run(self, progress=None, should_stop=None) -> None:
        """Train to the end. ``progress(done, total, status)`` after each step; ``should_stop()`` polled to stop early."""
        while not self.done:
            if should_stop is not None and should_stop():
                break
            self.step(1)
            if progress is not None:
                progress(self.trainer.step_count, self.config.steps, self.status())

    def status(self) -> dict:
        """step, steps, loss and psnr (means of the last ``LOSS_WINDOW`` steps), initial_loss (of the first),
        num_gaussians, steps_per_second, eta_seconds and elapsed_seconds (None where not known yet)."""
        step, steps = self.trainer.step_count, self.config.steps
        rate = None
        if len(self._times) >= 2:
            (s0, t0), (s1, t1) = self._times[0], self._times[-1]
            if t1 > t0 and s1 > s0:
                rate = (s1 - s0) / (t1 - t0)
        window = lambda values: float(np.mean(values)) if values else None  # noqa: E731
        return {
            "step": step,
            "steps": steps,
            "loss": window(self.losses[-LOSS_WINDOW:]),
            "psnr": window(self.psnrs[-LOSS_WINDOW:]),
            "initial_loss": window(self.losses[:LOSS_WINDOW]),
            "num_gaussians": len(self.model),
            "steps_per_second": rate,
            "eta_seconds": (steps - step) / rate if rate else (0.0 if step >= steps else None),
            "elapsed_seconds": 0.0 if self.t_start is None else time.perf_counter() - self.t_start,
        }

    def evaluate(self, split: str = "test") -> float | None:
        """Mean PSNR (dB) of renders against the ``split`` views (None when it has none).

        Targets are composited on the training background ('random' uses black).
        """
        indices = self.dataset.split(split) if split in self.dataset.splits else []
        if not indices:
            return None
        c = self.config
        bg = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "random": (0.0, 0.0, 0.0)}.get(c.background, c.background)
        bg = tuple(float(v) for v in bg)
        degree = min(self.trainer.active_sh_degree, self.model.sh_degree)
        values = []
        for i in indices:
            target, weight = self.dataset.load_image(i, background=bg)
            out = self.model.render(self.dataset.frames[i].camera, background=bg, antialias=c.antialias, projection=c.projection, sh_degree=degree)
            mask = None if weight is None else mx.array(weight)
            values.append(float(psnr(mx.clip(out["image"], 0, 1), mx.array(target), mask)))
        return float(np.mean(values))

    # -- the scene
    def _record(self) -> dict:
        status = self.status()
        record = {
            "dataset": self.where, "method": self.config.method, "step": status["step"], "steps": status["steps"],
            "num_gaussians": status["num_gaussians"], "sh_degree": self.model.sh_degree,
            "background": self.config.background if isinstance(self.config.background, str) else "custom",
        }
        for key in ("loss", "initial_loss", "psnr"):
            if status[key] is not None:
                record[key] = status[key]
        return record

    def update_object(self):
        """Write the current model into the splat object (created on first use, identity transform); returns it."""
        arrays = self.model.to_arrays()
        if _alive(self.object):
            replace_splats(self.object, arrays)
        else:  # first update, or the user deleted the object meanwhile
            self.object, _ = create_splat_object(self.name, arrays, collection=self.collection)
        self.object[INFO_KEY] = self._record()
        self.object_step = self.trainer.step_count
        return self.object

    def finish(self, cancelled: bool = False, error: str | None = None, evaluate: bool = False):
        """Write the final state into the object; returns (object, messages).

        After ``error`` (or a cancel) the object holds the last completed step.
        The first message is the summary (the error first when there is one);
        evaluate: add the mean PSNR on the held-out test views.
        """
        if self._finished is not None:
            return self._finished
        error = error or None
        obj = self.update_object()
        status = self.status()
        step, steps = status["step"], status["steps"]
        if step == 0:
            done = "training stopped before the first step" if (cancelled or error) else "no training steps run"
            summary = f"{done}; '{obj.name}' holds the {status['num_gaussians']:,} initial Gaussians"
        else:
            if step < steps:
                head = f"trained {step:,} of {steps:,} steps" + (" (cancelled)" if cancelled and not error else "")
            else:
                head = f"trained {steps:,} steps"
            summary = (
                f"{head} ({self.config.method}) on {len(self.dataset.train)} views of {self.where} in "
                f"{format_duration(status['elapsed_seconds'])}: {status['num_gaussians']:,} Gaussians, "
                f"loss {status['initial_loss']:.4f} -> {status['loss']:.4f}, PSNR {status['psnr']:.2f} dB; result in '{obj.name}'"
            )
        messages = [summary] + list(self.notes)
        if error:
            messages.insert(0, f"training stopped at step {step + 1:,} of {steps:,}: {error}; kept the last good state (step {step:,}) in '{obj.name}'")
        elif evaluate:
            value = self.evaluate("test")
            if value is not None:
                n = len(self.dataset.test)
                messages.append(f"test PSNR {value:.2f} dB on {n} held-out view{'' if n == 1 else 's'}")
        self._finished = (obj, messages)
        return self._finished


class StatusPrinter:
    """``progress(done, total, status)`` printing a status line each time another ``fraction`` of the steps is done."""

    def __init__(self, stream=None, fraction: float = 0.05, label: str = "train"):
        self.stream = stream if stream is not None else sys.stderr
        self.fraction = fraction
        self.label = label
        self._next = None

    def __call__(self, done, total, status) -> None:
        if self._next is None:
            self._next = max(1, math.ceil(total * self.fraction))
        if done < self._next and done < total:
            return
        while self._next <= done:
            self._next += max(1, math.ceil(total * self.fraction))
        self.stream.write(f"{self.label}: {100.0 * done / total:5.1f}%  {format_status(status)}\n")
        self.stream.flush()


def _check_output(path) -> str:
    """The absolute output path, refused before training when its folder is missing or it is a folder."""
    out = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(out)
    if not os.path.isdir(folder):
        raise TrainError(f"cannot write {out}: folder {folder} does not exist")
    if os.path.isdir(out):
        raise TrainError(f"cannot write {out}: it is a folder")
    if not os.access(folder, os.W_OK):
        raise TrainError(f"cannot write {out}: folder {folder} is not writable")
    return out


def train_dataset(data, *, steps, method="vanilla", out_ply=None, max_gaussians=None, sh_degree=3, background="black",
                  update_every=0, name=DEFAULT_NAME, seed=0, collection=None, progress=None, should_stop=None, **trainer_overrides):
    """Train on a dataset to the end into a splat object; optionally write it as a 3DGS PLY. Returns (object, messages).

    Arguments as ``TrainSession`` (``update_every`` defaults to 0: the object
    is written once, at the end); out_ply: file to write the model to
    (atomically; its folder is checked before training); progress:
    ``progress(done, total, status)`` after each step (``StatusPrinter``
    prints one); should_stop: polled before each step, stops early and keeps
    (and writes) the result so far. Messages: the summary, caveats, the test
    PSNR when the dataset holds out views, the file written. A NaN/Inf loss
    or an unreadable image raises with the object at the last good step.
    """
    out = _check_output(out_ply) if out_ply else None
    session = TrainSession(data, steps=steps, method=method, max_gaussians=max_gaussians, sh_degree=sh_degree, background=background,
                           update_every=update_every, name=name, seed=seed, collection=collection, **trainer_overrides)
    try:
        session.run(progress=progress, should_stop=should_stop)
    except (ValueError, OSError, RuntimeError) as exc:
        _, messages = session.finish(error=str(exc))
        raise TrainError(messages[0]) from exc
    obj, messages = session.finish(cancelled=not session.done, evaluate=True)
    if out:
        arrays = session.model.to_arrays()
        write_splat_ply(out, arrays)
        messages.append(f"wrote {arrays.count:,} Gaussians (SH degree {arrays.sh_degree}) to {out}")
    return obj, messages
