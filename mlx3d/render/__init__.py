"""The differentiable Gaussian renderer: projection, tile binning, rasterization.

The public functions keep the original mlx3D names, signatures, defaults and
dict/tuple results (``mlx3d.splatting`` re-exports them): ``project_gaussians``
/ ``project_gaussians_ut`` -> dict, ``bin_gaussians`` -> ``(sorted_ids,
tile_ranges, tiles_x, tiles_y)``, ``rasterize_features`` / ``rasterize_depth``
/ ``rasterize`` -> dict, ``render_gaussians`` / ``render_gaussian_features`` /
``render_gaussian_depth`` / ``render_gaussians_reference`` -> dict. Their
additions are keyword-only. The renderer's own stages work on the structured
forms ``Projection`` (``project_ewa``, ``project_ut``) and ``Bins``
(``bin_tiles``, ``composite``). Rasterizer backends: 'cpu' (C++ MLX
primitive, threaded over tiles), 'metal' (Apple GPUs), 'reference' (pure MLX,
the test oracle); 'auto' takes Metal when available. ``Surface`` is a
per-pixel layer (e.g. a mesh render with depth) that ``render_gaussians``
composites with the splats in depth order. Conventions (pixel
centres at +0.5, OpenCV camera axes) are in docs/reference/conventions.md.
"""

from .binning import TILE_SIZE, Bins, bin_gaussians, bin_tiles, bins_from_ranges
from .geometry_channels import facing_normals
from .pipeline import (
    RenderPlan,
    plan_render,
    render_gaussian_depth,
    render_gaussian_features,
    render_gaussian_median_depth,
    render_gaussians,
    render_gaussians_reference,
)
from .projection import Projection, project_ewa, project_gaussians, project_gaussians_ut, project_ut, quat_scale_to_cov3d
from .rasterize import composite, composite_features, rasterize, rasterize_depth, rasterize_features, resolve_backend
from .surface import Surface

__all__ = [
    "TILE_SIZE",
    "Bins",
    "Projection",
    "RenderPlan",
    "Surface",
    "bin_gaussians",
    "bin_tiles",
    "bins_from_ranges",
    "composite",
    "composite_features",
    "facing_normals",
    "plan_render",
    "project_ewa",
    "project_gaussians",
    "project_gaussians_ut",
    "project_ut",
    "quat_scale_to_cov3d",
    "rasterize",
    "rasterize_depth",
    "rasterize_features",
    "render_gaussian_depth",
    "render_gaussian_features",
    "render_gaussian_median_depth",
    "render_gaussians",
    "render_gaussians_reference",
    "resolve_backend",
]
