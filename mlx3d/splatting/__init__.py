"""Gaussian splat models and spherical harmonics (the ``mlx3d.splatting`` API)."""

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

__all__ = [
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
