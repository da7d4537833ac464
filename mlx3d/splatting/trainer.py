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

from dataclasses import dataclass

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


class GaussianTrainer(_GaussianTrainer):
    """:class:`mlx3d.training.GaussianTrainer` whose config defaults to this module's :class:`TrainerConfig`."""

    def __init__(self, model, config: _TrainerConfig | None = None, scene_extent: float = 1.0, num_images: int | None = None):
        super().__init__(model, config if config is not None else TrainerConfig(), scene_extent, num_images)
