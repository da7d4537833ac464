"""Gaussian splat models, spherical harmonics and rendering (the ``mlx3d.splatting`` API).

The rendering names are re-exported from ``mlx3d.render`` on first use (the
renderer itself imports ``mlx3d.splatting.sh``, so an eager import would be a
cycle). They keep the original mlx3D library's names, signatures, defaults and
dict/tuple results; our additions are keyword-only arguments and extra keys.
"""

from .model import GaussianModel, merge
from .ops import merge_splats, resize_sh_rest, transform_splats
from .sh import (
    C0,
    MAX_SH_DEGREE,
    eval_sh,
    num_sh_bases,
    rgb_to_sh,
    rotate_sh,
    sh_basis,
    sh_degree_from_bases,
    sh_rotation,
    sh_to_rgb,
)

_RENDER_NAMES = (
    "TILE_SIZE",
    "bin_gaussians",
    "project_gaussians",
    "project_gaussians_ut",
    "quat_scale_to_cov3d",
    "rasterize",
    "rasterize_depth",
    "rasterize_features",
    "render_gaussian_depth",
    "render_gaussian_features",
    "render_gaussians",
    "render_gaussians_reference",
)


_TRAINER_NAMES = ("GaussianTrainer", "TrainerConfig")  # the original's defaults (mlx3d.splatting.trainer)


def __getattr__(name):
    if name in _RENDER_NAMES:
        from .. import render

        return getattr(render, name)
    if name in _TRAINER_NAMES:
        from . import trainer

        return getattr(trainer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = list(_RENDER_NAMES) + list(_TRAINER_NAMES) + [
    "C0",
    "MAX_SH_DEGREE",
    "GaussianModel",
    "eval_sh",
    "merge",
    "merge_splats",
    "num_sh_bases",
    "resize_sh_rest",
    "rgb_to_sh",
    "rotate_sh",
    "sh_basis",
    "sh_degree_from_bases",
    "sh_rotation",
    "sh_to_rgb",
    "transform_splats",
]
