"""Tile binning: which Gaussians touch which 16x16 tile, front to back.

A Gaussian with radius r > 0 and centre (mx, my) covers the tiles
``floor((mx ± r) / tile)`` × ``floor((my ± r) / tile)`` clipped to the image
(inclusive). Intersections are sorted by tile id (row-major), then depth, then
Gaussian index (C++ in ``mlx3d._core.bin_tiles``). Not differentiable.

Given ``conics`` and ``opacities``, each axis' half-extent is tightened to the
box of the ellipse where the Gaussian can reach alpha = 1/255,
``dᵀ Σ⁻¹ d ≤ 2 ln(255 o)``, i.e. ``sqrt(2 ln(255 o) Σxx)`` (+1 px for
rounding), never beyond r. Outside it every pixel would skip the Gaussian
anyway, so the image is unchanged while the rasterizer visits fewer entries;
a Gaussian with 255·o ≤ 1 touches no tile.
"""

from __future__ import annotations

from typing import NamedTuple

import mlx.core as mx
import numpy as np

from .. import native

TILE_SIZE = 16
_ROUNDING_MARGIN = 1.0  # pixels


class Bins(NamedTuple):
    """tile_offsets (tiles_y*tiles_x + 1,) int32 and flatten_ids (M,) int32, as mx arrays;
    intersections of tile t are ``flatten_ids[tile_offsets[t]:tile_offsets[t+1]]``."""

    tile_offsets: mx.array
    flatten_ids: mx.array
    tiles_x: int
    tiles_y: int
    tile_size: int


def _np(a, dtype):
    return np.ascontiguousarray(np.asarray(mx.stop_gradient(a) if isinstance(a, mx.array) else a), dtype=dtype)


def tile_extents(radii, conics=None, opacities=None) -> np.ndarray:
    """(N,2) float32 half-extents in pixels used for binning (see the module docstring)."""
    r = _np(radii, np.float64)
    if conics is None or opacities is None:
        return np.ascontiguousarray(np.stack([r, r], axis=1), dtype=np.float32)
    con = _np(conics, np.float64)
    o = _np(opacities, np.float64)
    det = con[:, 0] * con[:, 2] - con[:, 1] ** 2
    k = 2.0 * np.log(np.maximum(255.0 * o, 1e-30))
    live = (r > 0) & (det > 0) & (k > 0)
    inv = np.where(live, 1.0 / np.where(live, det, 1.0), 0.0)
    ext = np.sqrt(np.maximum(k, 0.0)[:, None] * np.stack([con[:, 2] * inv, con[:, 0] * inv], axis=1)) + _ROUNDING_MARGIN
    ext = np.minimum(ext, r[:, None])
    return np.ascontiguousarray(np.where(live[:, None], ext, 0.0), dtype=np.float32)


def bin_gaussians(means2d, radii, depths, width: int, height: int, tile_size: int = TILE_SIZE, conics=None, opacities=None) -> Bins:
    """Bin projected Gaussians into tiles. means2d (N,2), radii (N,) (0 = culled), depths (N,);
    with ``conics`` (N,3) and ``opacities`` (N,) the extents are tightened (same image)."""
    if tile_size < 1:
        raise ValueError(f"tile_size must be >= 1, got {tile_size}")
    tiles_x = -(-int(width) // tile_size)
    tiles_y = -(-int(height) // tile_size)
    extents = tile_extents(radii, conics, opacities)
    offsets, ids = native.core().bin_tiles(_np(means2d, np.float32).reshape(-1, 2), extents, _np(depths, np.float32).reshape(-1), int(width), int(height), tile_size)
    return Bins(mx.array(offsets), mx.array(ids), tiles_x, tiles_y, tile_size)
