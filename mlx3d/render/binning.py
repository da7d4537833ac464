"""Tile binning: which Gaussians touch which 16x16 tile, front to back.

A Gaussian with radius r > 0 and centre (mx, my) covers the tiles
``floor((mx ± r) / tile)`` × ``floor((my ± r) / tile)`` clipped to the image
(inclusive). Intersections are sorted by tile id (row-major), then depth, then
Gaussian index (C++ in ``mlx3d._core.bin_tiles``, threaded; the result does not
depend on the thread count). Not differentiable.

Given ``conics`` and ``opacities``, each axis' half-extent is tightened to the
box of the ellipse where the Gaussian can reach alpha = 1/255,
``dᵀ Σ⁻¹ d ≤ 2 ln(255 o)``, i.e. ``sqrt(2 ln(255 o) Σxx)`` (+1 px for
rounding), never beyond r (computed in the C++ binning; ``tile_extents``
returns them). Outside it every pixel would skip the Gaussian
anyway, so the image is unchanged while the rasterizer visits fewer entries;
a Gaussian with 255·o ≤ 1 touches no tile.

Two forms of the result: ``bin_tiles`` returns ``Bins`` (the renderer's
``tile_offsets`` (tiles + 1,) and ``flatten_ids``); the public
``bin_gaussians`` returns the original mlx3D tuple ``(sorted_ids,
tile_ranges, tiles_x, tiles_y)`` with ``tile_ranges`` (tiles, 2) [start, end)
rows. ``bins_from_ranges`` turns the tuple back into ``Bins``.
"""

from __future__ import annotations

from typing import NamedTuple

import mlx.core as mx
import numpy as np

from .. import native

TILE_SIZE = 16


class Bins(NamedTuple):
    """tile_offsets (tiles_y*tiles_x + 1,) int32 and flatten_ids (M,) int32, as mx arrays;
    intersections of tile t are ``flatten_ids[tile_offsets[t]:tile_offsets[t+1]]``."""

    tile_offsets: mx.array
    flatten_ids: mx.array
    tiles_x: int
    tiles_y: int
    tile_size: int


def tile_extents(radii, conics=None, opacities=None) -> np.ndarray:
    """(N,2) float32 half-extents in pixels used for binning (see the module docstring)."""
    return native.core().tile_extents(*_extent_args(radii, conics, opacities))


def _extent_args(radii, conics, opacities) -> tuple:
    """The C++ binning's extent inputs: radii, and conics and opacities only when both are given."""
    r = native.host_array(radii, np.float32).reshape(-1)
    if conics is None or opacities is None:
        return r, None, None
    return r, native.host_array(conics, np.float32).reshape(-1, 3), native.host_array(opacities, np.float32).reshape(-1)


def bin_tiles(means2d, radii, depths, width: int, height: int, tile_size: int = TILE_SIZE, conics=None, opacities=None) -> Bins:
    """Bin projected Gaussians into tiles. means2d (N,2), radii (N,) (0 = culled), depths (N,);
    with ``conics`` (N,3) and ``opacities`` (N,) the extents are tightened (same image)."""
    if tile_size < 1:
        raise ValueError(f"tile_size must be >= 1, got {tile_size}")
    tiles_x = -(-int(width) // tile_size)
    tiles_y = -(-int(height) // tile_size)
    from .raster_cpu import get_num_threads  # the CPU kernels' thread setting; the result is the same for any

    r, con, opac = _extent_args(radii, conics, opacities)
    means = native.host_array(means2d, np.float32).reshape(-1, 2)
    offsets, ids = native.core().bin_tiles(means, r, native.host_array(depths, np.float32).reshape(-1), int(width), int(height), tile_size,
                                           get_num_threads(), con, opac)
    return Bins(offsets, ids, tiles_x, tiles_y, tile_size)


def _grid(width: int, height: int, tile_size: int) -> tuple:
    return -(-int(width) // tile_size), -(-int(height) // tile_size)


def bin_gaussians(means2d, radii, depths, width: int, height: int, conics=None, *, opacities=None, tile_size: int = TILE_SIZE) -> tuple:
    """Assign projected Gaussians to 16x16 screen tiles, front to back within each tile.

    means2d (N,2) pixel centres, radii (N,) pixel radii (0 = culled), depths
    (N,) camera z. With ``conics`` (N,3) a tile is listed only where the
    Gaussian can reach alpha >= 1/255 there assuming opacity 1 (``opacities``
    (N,), keyword-only, tightens this to the real opacities); either way the
    rendered image is the same as without.

    Returns ``(sorted_ids, tile_ranges, tiles_x, tiles_y)``: ``sorted_ids``
    (D,) int32 Gaussian indices of every (tile, Gaussian) pair in render order
    (by tile, then depth, then index); ``tile_ranges`` (tiles_x * tiles_y, 2)
    int32 [start, end) rows into ``sorted_ids``, tiles row-major; the tile
    grid size as ints. Not differentiable. ``tile_size`` (keyword-only)
    changes the tile edge from 16 pixels.
    """
    if conics is not None and opacities is None:
        opacities = np.ones(np.shape(radii)[0], np.float32)
    bins = bin_tiles(means2d, radii, depths, width, height, tile_size, conics, opacities)
    return bins.flatten_ids, ranges_of(bins), bins.tiles_x, bins.tiles_y


def ranges_of(bins: Bins) -> mx.array:
    """(tiles, 2) int32 [start, end) rows of ``bins``."""
    return mx.stack([bins.tile_offsets[:-1], bins.tile_offsets[1:]], axis=-1)


def bins_from_ranges(sorted_ids, tile_ranges, width: int, height: int, tiles_x: int, tiles_y: int, tile_size: int = TILE_SIZE) -> Bins:
    """``Bins`` from ``bin_gaussians``' tuple; raises ValueError where they do not fit the image.

    Ranges need not be contiguous (an empty tile may be (0, 0), tiles may skip
    or share entries): the ids are then gathered tile by tile.
    """
    if isinstance(tile_size, bool) or not isinstance(tile_size, (int, np.integer)) or tile_size < 1:
        raise ValueError(f"tile_size must be a positive int, got {tile_size!r}")
    if (int(tiles_x), int(tiles_y)) != _grid(width, height, tile_size):
        raise ValueError(
            f"tiles_x, tiles_y = ({tiles_x}, {tiles_y}) do not fit a {width}x{height} image with {tile_size}-pixel tiles "
            f"(expected {_grid(width, height, tile_size)})"
        )
    ids = np.asarray(mx.stop_gradient(sorted_ids) if isinstance(sorted_ids, mx.array) else sorted_ids).reshape(-1).astype(np.int64)
    ranges = np.asarray(mx.stop_gradient(tile_ranges) if isinstance(tile_ranges, mx.array) else tile_ranges).astype(np.int64)
    tiles = int(tiles_x) * int(tiles_y)
    if ranges.shape != (tiles, 2):
        raise ValueError(f"tile_ranges must have shape (tiles_x * tiles_y, 2) = ({tiles}, 2), got {ranges.shape}")
    start, end = ranges[:, 0], ranges[:, 1]
    counts = end - start
    if (counts < 0).any() or (start < 0).any() or (end > ids.size).any():
        raise ValueError(f"tile_ranges must be [start, end) rows with 0 <= start <= end <= len(sorted_ids) = {ids.size}")
    offsets = np.concatenate([[0], np.cumsum(counts)])
    if offsets[-1] == ids.size and (start[counts > 0] == offsets[:-1][counts > 0]).all():
        flat = ids  # already the contiguous layout the rasterizer reads
    else:
        flat = ids[np.repeat(start - offsets[:-1], counts) + np.arange(offsets[-1])]
    return Bins(mx.array(offsets.astype(np.int32)), mx.array(flat.astype(np.int32)), int(tiles_x), int(tiles_y), int(tile_size))
