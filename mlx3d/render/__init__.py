"""The differentiable Gaussian renderer: projection, tile binning, rasterization.

One entry, ``render_gaussians``; ``rasterize_features`` picks the rasterizer
backend: 'cpu' (C++ MLX primitive, threaded over tiles), 'metal' (Apple
GPUs), 'reference' (pure MLX, the test oracle); 'auto' takes Metal when
available. Conventions (pixel centres at +0.5, OpenCV camera axes) are in the
README.
"""

from .binning import TILE_SIZE, Bins, bin_gaussians
from .geometry_channels import facing_normals
from .pipeline import (
    RenderPlan,
    plan_render,
    rasterize_features,
    render_gaussian_depth,
    render_gaussian_features,
    render_gaussians,
    resolve_backend,
)
from .projection import Projection, project_gaussians, project_gaussians_ut, quat_scale_to_cov3d

__all__ = [
    "TILE_SIZE",
    "Bins",
    "Projection",
    "RenderPlan",
    "bin_gaussians",
    "facing_normals",
    "plan_render",
    "project_gaussians",
    "project_gaussians_ut",
    "quat_scale_to_cov3d",
    "rasterize_features",
    "render_gaussian_depth",
    "render_gaussian_features",
    "render_gaussians",
    "resolve_backend",
]
