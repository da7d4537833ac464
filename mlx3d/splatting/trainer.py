"""``mlx3d.splatting.TrainerConfig`` and ``GaussianTrainer``: the trainer with the original mlx3D's defaults.

The same trainer and fields as :mod:`mlx3d.training.trainer`; only the
defaults differ, so that a script written for the original mlx3D trains the
way it did there:

- MCMC as the original runs it: at most 2% of the Gaussians relocated per
  event (those below opacity 0.01), copies jittered by 0.25 of their scale,
  isotropic position noise ``0.01 · extent · sqrt(means lr)`` on every
  Gaussian, no opacity/scale regularisers, no growth (the count stays fixed).
  ``mlx3d.training.TrainerConfig`` defaults to the 3DGS-MCMC paper instead
  (every dead Gaussian relocated, no jitter, opacity-gated noise, the
  regularisers, growth to a budget).
- ``densify_until=15000`` and ``lr_means_max_steps=30000`` for every method.
  ``projection`` stays ``'auto'``, as in ``render_gaussians``: EWA for every
  pinhole camera (the original's ``'ewa'``), the unscented transform for
  distorted, fisheye and orthographic cameras, which EWA cannot draw.
- 2DGS: thickness 1e-4 of the extent and no geometry regularisers unless
  their weights are set (``geometry_min_alpha=0.05``, from step 0).
"""

from __future__ import annotations

from collections.abc import MutableMapping
from dataclasses import dataclass

import mlx.core as mx
import numpy as np

from ..training.plan import step_plan
from ..training.trainer import GaussianTrainer as _GaussianTrainer
from ..training.trainer import TrainerConfig as _TrainerConfig

__all__ = ["GaussianTrainer", "TrainerConfig"]


@dataclass
class TrainerConfig(_TrainerConfig):
    """:class:`mlx3d.training.TrainerConfig` with the original mlx3D's defaults (see the module)."""

    lr_means_max_steps: int | None = 30_000
    densify_until: int | None = 15_000
    mcmc_min_opacity: float = 0.01
    mcmc_relocate_frac: float = 0.02
    mcmc_jitter_scale: float = 0.25
    mcmc_noise_scale: float = 0.01
    mcmc_noise_lr: float = 0.0
    mcmc_growth: float = 0.0
    mcmc_opacity_reg: float = 0.0
    mcmc_scale_reg: float = 0.0
    two_d_thickness: float = 1e-4
    lambda_2d_depth_variance: float | None = 0.0
    lambda_2d_normal_consistency: float | None = 0.0
    geometry_min_alpha: float = 0.05
    geometry_from: int = 0
    cache_limit_gb: float | None = 2.0


class _Moments(MutableMapping):
    """``{'m': ..., 'v': ...}`` of one parameter, read from and written to the trainer's Adam."""

    def __init__(self, adam, name: str):
        self._slots = {"m": adam.m, "v": adam.v}
        self._name = name

    def __getitem__(self, slot):
        return self._slots[slot][self._name]

    def __setitem__(self, slot, value):
        self._slots[slot][self._name] = value

    def __delitem__(self, slot):
        raise TypeError("Adam moments cannot be removed")

    def __iter__(self):
        return iter(self._slots)

    def __len__(self):
        return 2


class _AdamState(MutableMapping):
    """The original's ``optimizer.state`` of one parameter: ``state[name]`` its moments, ``state['step']``.

    Our parameters share one Adam and so one step count: setting ``'step'`` sets it for all.
    """

    def __init__(self, adam, name: str):
        self._adam, self._name = adam, name

    def _keys(self):
        return ["step", "learning_rate"] + ([self._name] if self._name in self._adam.m else [])

    def __getitem__(self, key):
        if key == "step":
            return mx.array(self._adam.step_count, dtype=mx.uint64)
        if key == "learning_rate":
            return mx.array(self._adam.lrs.get(self._name, 0.0))
        if key == self._name and key in self._adam.m:
            return _Moments(self._adam, key)
        raise KeyError(key)

    def __setitem__(self, key, value):
        if key == "step":
            self._adam.step_count = int(value)
        elif key == self._name:
            self._adam.m[key], self._adam.v[key] = value["m"], value["v"]
        else:
            raise KeyError(key)

    def __delitem__(self, key):
        raise TypeError("Adam state entries cannot be removed")

    def __iter__(self):
        return iter(self._keys())

    def __len__(self):
        return len(self._keys())


class _AdamView:
    """One parameter's view of the trainer's Adam, with the original's per-parameter optimizer attributes."""

    def __init__(self, adam, name: str):
        self._adam, self._name = adam, name

    @property
    def learning_rate(self) -> mx.array:
        return mx.array(self._adam.lrs.get(self._name, 0.0))

    @property
    def state(self) -> _AdamState:
        return _AdamState(self._adam, self._name)

    def init(self, params: dict) -> None:
        """Zero moments for the parameters in ``params`` that have none yet."""
        for name, value in params.items():
            if name not in self._adam.m:
                self._adam.m[name], self._adam.v[name] = mx.zeros_like(value), mx.zeros_like(value)


class GaussianTrainer(_GaussianTrainer):
    """:class:`mlx3d.training.GaussianTrainer` whose config defaults to this module's :class:`TrainerConfig`.

    It also has the original's entry points into a step, for scripts that inspect
    training: ``optimizers`` (per-parameter views of the one Adam), ``_render_loss``
    and ``_resize_optimizer_states_after_densify``.
    """

    def __init__(self, model, config: _TrainerConfig | None = None, scene_extent: float = 1.0, num_images: int | None = None):
        super().__init__(model, config if config is not None else TrainerConfig(), scene_extent, num_images)

    @property
    def optimizers(self) -> dict:
        """``{name: optimizer}`` as in the original: ``.state[name]['m'|'v']``, ``.state['step']``, ``.learning_rate``."""
        return {name: _AdamView(self.optimizer, name) for name in self.learning_rates()}

    def _render_loss(self, params, means2d_probe, camera, target, background):
        """``(loss, (image, radii, {'depth_variance', 'normal_consistency'}))`` of the next step, differentiable
        w.r.t. ``params`` and ``means2d_probe`` ((N, 2) zeros: its gradient is the screen-space one)."""
        degree = min(self.active_sh_degree, self.model.sh_degree)
        plan = step_plan(self.config, camera, degree, self.step_count)
        bg = tuple(np.asarray(background, dtype=np.float64).reshape(3))
        loss, out = self._loss(params, means2d_probe, None, camera, mx.array(target, dtype=mx.float32), None, bg, plan, degree)
        zero = mx.array(0.0)
        metrics = {"depth_variance": out.get("depth_variance_loss", zero), "normal_consistency": out.get("normal_loss", zero)}
        return loss, (out["image"], out["radii"], metrics)

    def _resize_optimizer_states_after_densify(self, result: dict) -> None:
        """Keep the Adam moments of rows ``result['_keep_idx']`` and append ``result['_new_count']`` zero rows."""
        keep = result.get("_keep_idx")
        if keep is None:
            return
        self.optimizer.select(np.asarray(keep))
        if int(result.get("_new_count", 0)):
            self.optimizer.append(int(result["_new_count"]))
