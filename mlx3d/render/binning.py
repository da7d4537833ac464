"""Tile binning: which Gaussians touch which 16x16 tile, front to back.

A Gaussian with radius r > 0 and centre (mx, my) covers the tiles
``floor((mx ± r) / tile)`` × ``floor((my ± r) / tile)`` clipped to the image
(inclusive). Intersections are sorted by tile id (row-major), then depth, then
Gaussian index, with one 64-bit key sort. Not differentiable (indices only).
"""

from __future__ import annotations

from typing import NamedTuple

import mlx.core as mx
import numpy as np

TILE_SIZE = 16


class Bins(NamedTuple):
    """tile_offsets (tiles_y*tiles_x + 1,) int32 and flatten_ids (M,) int32, as mx arrays;
    intersections of tile t are ``flatten_ids[tile_offsets[t]:tile_offsets[t+1]]``."""

    tile_offsets: mx.array
    flatten_ids: mx.array
    tiles_x: int
    tiles_y: int
    tile_size: int


def _depth_key(depths: np.ndarray) -> np.ndarray:
    """uint32 keys that sort like the float32 depths (IEEE-754 order trick)."""
    bits = np.ascontiguousarray(depths, dtype=np.float32).view(np.uint32)
    return np.where(bits & 0x80000000, ~bits, bits | 0x80000000).astype(np.uint64)


def bin_gaussians(means2d, radii, depths, width: int, height: int, tile_size: int = TILE_SIZE) -> Bins:
    """Bin projected Gaussians into tiles. means2d (N,2), radii (N,) (0 = culled), depths (N,)."""
    if tile_size < 1:
        raise ValueError(f"tile_size must be >= 1, got {tile_size}")
    tiles_x = -(-int(width) // tile_size)
    tiles_y = -(-int(height) // tile_size)
    m = np.asarray(mx.stop_gradient(means2d) if isinstance(means2d, mx.array) else means2d, dtype=np.float64)
    r = np.asarray(radii).astype(np.float64)
    d = np.asarray(mx.stop_gradient(depths) if isinstance(depths, mx.array) else depths, dtype=np.float32)
    live = np.flatnonzero(r > 0)
    x0 = np.clip(np.floor((m[live, 0] - r[live]) / tile_size), 0, tiles_x).astype(np.int64)
    x1 = np.clip(np.floor((m[live, 0] + r[live]) / tile_size) + 1, 0, tiles_x).astype(np.int64)
    y0 = np.clip(np.floor((m[live, 1] - r[live]) / tile_size), 0, tiles_y).astype(np.int64)
    y1 = np.clip(np.floor((m[live, 1] + r[live]) / tile_size) + 1, 0, tiles_y).astype(np.int64)
    w, h = np.maximum(x1 - x0, 0), np.maximum(y1 - y0, 0)
    counts = w * h
    total = int(counts.sum())
    num_tiles = tiles_x * tiles_y
    if total == 0:
        return Bins(mx.zeros(num_tiles + 1, dtype=mx.int32), mx.zeros(0, dtype=mx.int32), tiles_x, tiles_y, tile_size)
    # one row per intersection: which Gaussian, and its index within that Gaussian's tile rectangle
    owner = np.repeat(np.arange(live.size), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    tx = x0[owner] + local % w[owner]
    ty = y0[owner] + local // w[owner]
    tile = (ty * tiles_x + tx).astype(np.uint64)
    order = np.argsort((tile << np.uint64(32)) | _depth_key(d[live])[owner], kind="stable")
    flatten_ids = live[owner[order]].astype(np.int32)
    offsets = np.searchsorted(tile[order], np.arange(num_tiles + 1, dtype=np.uint64)).astype(np.int32)
    return Bins(mx.array(offsets), mx.array(flatten_ids), tiles_x, tiles_y, tile_size)
