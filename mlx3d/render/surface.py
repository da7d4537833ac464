"""A surface layer composited with the splats: an external render (e.g. of meshes) with its depth.

``Surface(color, alpha, depth)`` holds, per pixel, the premultiplied colour
(H,W,C), the alpha (H,W) in [0,1] and the camera z (H,W) of the surface, in
the camera's units, +inf where there is none. ``render_gaussians(...,
surface=...)`` composites it in depth order with exact occlusion, in the one
rasterization pass: per pixel, front to back over its Gaussians, just before
the first Gaussian whose depth is >= the surface's (after the last if none)
and unless the pixel has already stopped,

    accum += T * color;   T *= 1 - alpha;   stop if T < 1e-4,

then the Gaussians behind go on with the reduced T (a semi-transparent
surface or an anti-aliased edge shows them); the background is added with
the final T as without a surface.

Two paths, visible in the render's stages:

- ``surface_behind``: no finite depth anywhere, so the surface is a
  background image: the plain rasterizer (any backend), then
  ``image = accum + T * (color + (1 - alpha) * background)``;
- ``+surface_depth_test``: the rasterizer with the depth test: the CPU
  kernel (``raster_cpu.rasterize_cpu_surface``), the Metal kernel
  (``raster_metal.rasterize_metal_surface``), the MLX tiles
  (``raster_mlx.rasterize_mlx_surface``) or, for backend 'reference', the
  pure-MLX oracle in ``raster_reference``.

Forward-only: differentiating a depth-tested composite raises.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import mlx.core as mx
import numpy as np

from .binning import Bins
from .raster_cpu import _float32

__all__ = ["Surface", "surface_mode", "surface_stages", "composite_surface"]

BEHIND = "behind"
DEPTH_TEST = "depth_test"


@dataclass(frozen=True)
class Surface:
    """Per-pixel surface layer: color (H,W,C) premultiplied, alpha (H,W) in [0,1],
    depth (H,W) camera z (>= 0, +inf where empty). Converted to float32 mx arrays
    and validated on construction (ValueError naming the field)."""

    color: mx.array
    alpha: mx.array
    depth: mx.array

    def __post_init__(self):
        for name in ("color", "alpha", "depth"):
            object.__setattr__(self, name, _float32(getattr(self, name), f"Surface.{name}"))
        if self.color.ndim != 3:
            raise ValueError(f"Surface.color must have shape (H, W, C), got {tuple(self.color.shape)}")
        hw = tuple(self.color.shape[:2])
        for name in ("alpha", "depth"):
            if tuple(getattr(self, name).shape) != hw:
                raise ValueError(f"Surface.{name} must have shape (H, W) = {hw} as color, got {tuple(getattr(self, name).shape)}")
        color, alpha, depth = (np.asarray(a) for a in (self.color, self.alpha, self.depth))
        for name, a in (("color", color), ("alpha", alpha), ("depth", depth)):
            if np.isnan(a).any():
                raise ValueError(f"Surface.{name} contains NaN at {np.isnan(a).sum()} values")
        if not np.isfinite(color).all():
            raise ValueError("Surface.color must be finite")
        if alpha.size and not (alpha.min() >= 0.0 and alpha.max() <= 1.0):
            raise ValueError(f"Surface.alpha must lie in [0, 1], got values in [{alpha.min()}, {alpha.max()}]")
        if depth.size and depth.min() < 0.0:
            raise ValueError(f"Surface.depth must be >= 0 (camera z; +inf where empty), got a minimum of {depth.min()}")

    @cached_property
    def has_depth(self) -> bool:
        """Whether any pixel has a finite depth (else the surface is a background image)."""
        return bool(np.isfinite(np.asarray(self.depth)).any())

    def check_camera(self, camera, channels: int = 3) -> None:
        """Raises ValueError unless the layer is (camera.height, camera.width) with ``channels`` colour channels."""
        want = (int(camera.height), int(camera.width), int(channels))
        if tuple(self.color.shape) != want:
            raise ValueError(f"Surface.color must have shape (H, W, C) = {want} for this camera, got {tuple(self.color.shape)}")


def surface_mode(surface: Surface | None, camera, channels: int = 3) -> str | None:
    """None without a surface, else 'behind' (no finite depth) or 'depth_test'; checks it against ``camera``."""
    if surface is None:
        return None
    if not isinstance(surface, Surface):
        raise ValueError(f"surface must be a mlx3d.render.Surface, got {type(surface).__name__}")
    surface.check_camera(camera, channels)
    return DEPTH_TEST if surface.has_depth else BEHIND


def surface_stages(mode: str | None, backend: str, raster_stage: str) -> tuple:
    """The stage names of the rasterization for a surface ``mode`` (see the module docstring)."""
    if mode is None:
        return (raster_stage,)
    if mode == BEHIND:
        return (raster_stage, "surface_behind")
    return (raster_stage + "+surface_depth_test",)


def _depth_tested(means2d, conics, features, opacities, depths, bins: Bins, width: int, height: int, surface: Surface, backend: str):
    """(accum, alpha, last) of the depth-tested composite on ``backend``'s rasterizer."""
    args = (means2d, conics, features, opacities, bins.tile_offsets, bins.flatten_ids)
    if backend == "reference":
        from .raster_reference import rasterize_reference

        return rasterize_reference(*args, width, height, bins.tile_size, depths=depths, surface=surface)
    if backend == "cpu":
        from .raster_cpu import rasterize_cpu_surface as rasterize_surface
    elif backend == "metal":
        from .raster_metal import rasterize_metal_surface as rasterize_surface
    else:
        from .raster_mlx import rasterize_mlx_surface as rasterize_surface
    return rasterize_surface(*args, depths, surface.color, surface.alpha, surface.depth, width, height, bins.tile_size)


def composite_surface(
    means2d, conics, features, opacities, depths, bins: Bins, width: int, height: int, surface: Surface, mode: str, background=None,
    backend: str = "cpu",
):
    """Composite Gaussians and ``surface`` (``mode`` from ``surface_mode``), then ``background`` (C,) or None.

    depths (N,): the Gaussians' camera z (the binning's sort key); backend: a
    resolved backend ('cpu', 'metal', 'mlx', 'reference'). Returns ``(image (H,W,C),
    alpha (H,W) = 1 - final T including the surface, last (H,W) int32)``.
    """
    if mode == BEHIND:
        from .rasterize import composite

        accum, alpha, last = composite(means2d, conics, features, opacities, bins, width, height, None, backend)
        T = (1.0 - alpha)[..., None]
        behind = surface.color if background is None else surface.color + (1.0 - surface.alpha)[..., None] * background
        return accum + T * behind, 1.0 - T[..., 0] * (1.0 - surface.alpha), last
    accum, alpha, last = _depth_tested(means2d, conics, features, opacities, depths, bins, width, height, surface, backend)
    if background is not None:
        accum = accum + (1.0 - alpha)[..., None] * background
    return accum, alpha, last
