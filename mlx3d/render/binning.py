"""Tile binning: which Gaussians touch which 16x16 tile, front to back.

A Gaussian with half-extents (ex, ey) > 0 pixels and centre (mx, my) covers
the tiles ``floor((mx ± ex) / tile)`` × ``floor((my ± ey) / tile)`` clipped to
the image (inclusive). Intersections are sorted by tile id (row-major), then
depth (negative < -0 = 0 < positive < NaN), then Gaussian index. Not
differentiable. Two implementations, chosen by the resolved renderer backend:
'cpu' runs the threaded C++ of ``mlx3d._core.bin_tiles`` (the result does not
depend on the thread count); every other backend runs MLX operations
(``_bin_mlx``), which stay on the device (Metal on Apple GPUs) but for one
read of two scalars, and need no compiled module.

The half-extents are the radius r on both axes, or, given ``conics`` and
``opacities``, each axis' half-extent is tightened to the box of the ellipse
where the Gaussian can reach alpha = 1/255, ``dᵀ Σ⁻¹ d ≤ 2 ln(255 o)``, i.e.
``sqrt(2 ln(255 o) Σxx)`` (+1 px for rounding), never beyond r
(``tile_extents`` returns them). Outside it every pixel would skip the
Gaussian anyway, so the image is unchanged while the rasterizer visits fewer
entries; a Gaussian with 255·o ≤ 1, det ≤ 0 or r ≤ 0 touches no tile.

float32 and double: the C++ computes the extents in double, then rounds them
to float32, and the rectangles in double. MLX has no float64 on GPUs, so the
MLX path works in float32: the rectangles come out the same, bit for bit
(error-free sums ``m ± e``, with double's rounding of a sum that ties a tile
border reproduced); the extents are computed with a compensated determinant
(error-free products) and ``log1p(255 o - 1)``, so that the tests r > 0,
det > 0 and 255·o > 1 are exact and the extents differ from the C++ ones by at
most a few float32 ulps (2 in the tests). Without conics the two
paths therefore bin identically, bit for bit. With conics they differ only
where a tile border lies between the two extents (rare): every pixel of such a
tile lies farther than the ellipse's box + 1 px - those ulps from the centre
along that axis, where alpha < 1/255 and the rasterizer skips the Gaussian,
so the rendered image is the same (tests/test_render_binning.py renders
both).

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
_INT32_MAX = 2**31 - 1


def _faint_limit() -> float:
    """The largest float32 opacity o with 255·o <= 1 exactly: a Gaussian at or below it touches no tile."""
    o = np.float32(1 / 255)
    return float(o if 255.0 * float(o) <= 1 else np.nextafter(o, np.float32(0)))


_FAINT = _faint_limit()


class Bins(NamedTuple):
    """tile_offsets (tiles_y*tiles_x + 1,) int32 and flatten_ids (M,) int32, as mx arrays;
    intersections of tile t are ``flatten_ids[tile_offsets[t]:tile_offsets[t+1]]``."""

    tile_offsets: mx.array
    flatten_ids: mx.array
    tiles_x: int
    tiles_y: int
    tile_size: int


def _resolve(backend: str) -> str:
    """A renderer backend name, with 'auto' resolved (``rasterize.resolve_backend``)."""
    if backend != "auto":
        return backend
    from .rasterize import resolve_backend

    return resolve_backend(backend)


def tile_extents(radii, conics=None, opacities=None, backend: str = "auto") -> np.ndarray:
    """(N,2) float32 half-extents in pixels used for binning (see the module docstring); ``backend``
    'cpu': the C++ values, any other: the MLX float32 ones."""
    if _resolve(backend) == "cpu":
        return native.core().tile_extents(*_extent_args(radii, conics, opacities))
    ext = _extents_mlx(_f32(radii, ()), *_conic_inputs(conics, opacities))
    return np.array(ext)


def _extent_args(radii, conics, opacities) -> tuple:
    """The C++ binning's extent inputs: radii, and conics and opacities only when both are given."""
    r = native.host_array(radii, np.float32).reshape(-1)
    if conics is None or opacities is None:
        return r, None, None
    return r, native.host_array(conics, np.float32).reshape(-1, 3), native.host_array(opacities, np.float32).reshape(-1)


def bin_tiles(means2d, radii, depths, width: int, height: int, tile_size: int = TILE_SIZE, conics=None, opacities=None,
              backend: str = "auto") -> Bins:
    """Bin projected Gaussians into tiles. means2d (N,2) pixels, radii (N,) pixels (0 = culled), depths (N,);
    with ``conics`` (N,3) and ``opacities`` (N,) the extents are tightened (same image). ``backend``: the
    resolved renderer backend ('cpu': the C++ binning; any other: MLX operations, which read the entry count
    back to the host once, as MLX shapes are static; 'auto' is resolved here)."""
    if tile_size < 1:
        raise ValueError(f"tile_size must be >= 1, got {tile_size}")
    tiles_x, tiles_y = _grid(width, height, tile_size)
    if _resolve(backend) != "cpu":
        return _bin_mlx(means2d, radii, depths, int(width), int(height), int(tile_size), conics, opacities)
    from .raster_cpu import get_num_threads  # the CPU kernels' thread setting; the result is the same for any

    r, con, opac = _extent_args(radii, conics, opacities)
    means = native.host_array(means2d, np.float32).reshape(-1, 2)
    offsets, ids = native.core().bin_tiles(means, r, native.host_array(depths, np.float32).reshape(-1), int(width), int(height), tile_size,
                                           get_num_threads(), con, opac)
    return Bins(offsets, ids, tiles_x, tiles_y, tile_size)


def _grid(width: int, height: int, tile_size: int) -> tuple:
    return -(-int(width) // tile_size), -(-int(height) // tile_size)


# ---- the MLX binning ---------------------------------------------------------------------------------------------


def _f32(a, tail: tuple) -> mx.array:
    """``a`` as a float32 MLX array of shape (N, *tail), outside any gradient (numpy input rounded as the C++ path does)."""
    if isinstance(a, mx.array):
        return mx.stop_gradient(a).astype(mx.float32).reshape(-1, *tail)
    return mx.array(np.asarray(a, np.float32).reshape(-1, *tail))


def _conic_inputs(conics, opacities) -> tuple:
    """(conics (N,3), opacities (N,)) as float32 MLX arrays, or (None, None) unless both are given."""
    if conics is None or opacities is None:
        return None, None
    return _f32(conics, (3,)), _f32(opacities, ())


def _two_sum(a: mx.array, b: mx.array) -> tuple:
    """(s, err) with s = fl(a + b) and s + err = a + b exactly (Knuth; finite inputs)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _split(a: mx.array) -> tuple:
    """(hi, lo), hi + lo = a, each with at most 12 significant bits (Veltkamp)."""
    t = a * 4097.0
    hi = t - (t - a)
    return hi, a - hi


def _two_prod(a: mx.array, b: mx.array) -> tuple:
    """(p, err) with p = fl(a * b) and p + err = a * b exactly (Dekker; no overflow or underflow)."""
    p = a * b
    (ah, al), (bh, bl) = _split(a), _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _det(a: mx.array, b: mx.array, c: mx.array) -> mx.array:
    """a c - b², correctly signed and accurate to a few ulps (compensated float32; plain where that overflows)."""
    (p1, e1), (p2, e2) = _two_prod(a, c), _two_prod(b, b)
    s, t = _two_sum(p1, -p2)
    det = s + (t + (e1 - e2))
    return mx.where(mx.isfinite(det), det, a * c - b * b)


def _extents_mlx(r: mx.array, conics, opacities) -> mx.array:
    """(N,2) float32 half-extents from radii (N,) and, optionally, conics (N,3) and opacities (N,) (module docstring)."""
    if conics is None:
        return mx.stack([r, r], axis=1)
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    det = _det(a, b, c)
    u = (opacities * 256.0 - 1.0) - opacities  # 255 o - 1: exact where 256 o is in [0.5, 2]
    u = mx.where(mx.isnan(u), opacities, u)  # o = inf
    k = 2.0 * mx.log1p(u)
    live = (r > 0) & (det > 0) & (opacities > _FAINT)
    inv = 1.0 / mx.where(live, det, 1.0)
    box = mx.sqrt(k[:, None] * mx.stack([c * inv, a * inv], axis=1)) + 1.0
    return mx.where(live[:, None], mx.minimum(box, r[:, None]), 0.0)


def _at_or_below(f: mx.array, s: mx.array, err: mx.array) -> mx.array:
    """f <= round_to_double(s + err), for float32 f and an error-free sum (s, err) (the C++ sums in double).

    Only s == f needs err: the double rounding of f + err gives f where err >= minus half the double spacing
    below f, 2^(E-53) with 2^E <= f < 2^(E+1) (2^(E-54) where f = 2^E; a tie rounds to f, whose double
    mantissa is even).
    """
    power = (f.view(mx.uint32) & 0x7F800000).view(mx.float32)  # 2^E
    half_gap = mx.where(f == power, power * 2.0**-54, power * 2.0**-53)
    return (s > f) | ((s == f) & (err >= -half_gap))


def _floor_tile(m: mx.array, e: mx.array, tile: int, hi: int) -> mx.array:
    """floor((m + e) / tile) as the C++ computes it in double, as int32 clipped to [-3, hi + 2] (NaN: -3);
    m, e (N,) float32, ``hi`` the tile count on the axis."""
    s, err = _two_sum(m, e)
    q = mx.floor(s / tile)  # within 1 of the answer
    q = mx.where(mx.isnan(q), -2.0, mx.clip(q, -2.0, hi + 1.0))
    q = q - (~_at_or_below(q * tile, s, err)) + _at_or_below((q + 1.0) * tile, s, err)
    return q.astype(mx.int32)


def _tile_span(m: mx.array, e: mx.array, tile: int, tiles: int) -> tuple:
    """[first, end) tile indices on one axis, clipped to [0, tiles], of the centres m (N,) with half-extents e (N,)."""
    first = mx.clip(_floor_tile(m, -e, tile, tiles), 0, tiles)
    end = mx.clip(_floor_tile(m, e, tile, tiles) + 1, 0, tiles)
    return first, end


def _depth_keys(depths: mx.array) -> mx.array:
    """(N,) uint32 keys in the order of the float depths: negative < -0 = 0 < positive < NaN."""
    bits = mx.where(depths == 0, 0.0, depths).view(mx.uint32)
    sign = mx.array(0x80000000, mx.uint32)
    keys = mx.where(bits >= sign, ~bits, bits | sign)
    return mx.where(mx.isnan(depths), mx.array(0xFFFFFFFF, mx.uint32), keys)


def _depth_order(depths: mx.array, touches: mx.array) -> mx.array:
    """(N,) int32 Gaussian indices: those that touch a tile by (depth, index), then the rest (one sort of
    unique uint64 keys: untouched << 63 | depth key << 31 | index)."""
    n = depths.shape[0]
    keys = ((~touches).astype(mx.uint64) << 63) | (_depth_keys(depths).astype(mx.uint64) << 31) | mx.arange(n, dtype=mx.uint64)
    return (mx.sort(keys) & 0x7FFFFFFF).astype(mx.int32)


def _rects(means2d: mx.array, ext: mx.array, tile: int, tiles_x: int, tiles_y: int) -> tuple:
    """Per Gaussian: (first tile (N,) int32, width in tiles (N,), entry count (N,)), 0 entries where culled."""
    x0, x1 = _tile_span(means2d[:, 0], ext[:, 0], tile, tiles_x)
    y0, y1 = _tile_span(means2d[:, 1], ext[:, 1], tile, tiles_y)
    count = mx.where((ext[:, 0] > 0) & (ext[:, 1] > 0), (x1 - x0) * (y1 - y0), 0)
    return y0 * tiles_x + x0, x1 - x0, count


def _entries(first: mx.array, width: mx.array, count: mx.array, tiles_x: int, total: int) -> tuple:
    """Tile (M,) int32 and Gaussian slot j (M,) int32 of every entry, slot by slot (slot j: first tile, width
    in tiles and count >= 1 of its rectangle, (K,) each), row-major over each rectangle. The starts by cumsum,
    each entry's slot by scatter + cumsum, then one gather of the slot's (start, first - start, tiles_x -
    width, width): entry e lies in tile first + e - start + row (tiles_x - width), row = (e - start) // width."""
    starts = mx.cumsum(count) - count
    j = mx.cumsum(mx.zeros(total, mx.int32).at[starts].add(1)) - 1
    slot = mx.stack([starts, first - starts, tiles_x - width, width], axis=1)[j]
    e = mx.arange(total, dtype=mx.int32)
    return slot[:, 1] + e + (e - slot[:, 0]) // slot[:, 3] * slot[:, 2], j


def _bin_mlx(means2d, radii, depths, width: int, height: int, tile: int, conics, opacities) -> Bins:
    """``bin_tiles`` with MLX operations. MLX shapes are static, so the entry count M (and the number of
    Gaussians that touch a tile) is read back once as two scalars; everything else stays on the device.
    Sort: one of unique keys tile * K + slot (uint32 where tiles * K < 2^32, else uint64), slots in
    (depth, index) order; tile offsets by searchsorted of the tile starts in the sorted keys."""
    tiles_x, tiles_y = _grid(width, height, tile)
    means, r, d = _f32(means2d, (2,)), _f32(radii, ()), _f32(depths, ())
    con, opac = _conic_inputs(conics, opacities)
    _check_mlx_inputs(means, r, d, con, opac, width, height)
    tiles = tiles_x * tiles_y
    empty = Bins(mx.zeros(tiles + 1, mx.int32), mx.zeros(0, mx.int32), tiles_x, tiles_y, tile)
    if means.shape[0] == 0:
        return empty
    first, w, count = _rects(means, _extents_mlx(r, con, opac), tile, tiles_x, tiles_y)
    order = _depth_order(d, count > 0)
    total, k = mx.stack([mx.sum(count.astype(mx.int64)), mx.sum((count > 0).astype(mx.int64))]).tolist()  # the host read
    if total > _INT32_MAX:
        raise OverflowError("bin_tiles: more than 2^31 tile intersections")
    if total == 0:
        return empty
    live = order[:k]
    t, j = _entries(first[live], w[live], count[live], tiles_x, total)
    key_type = mx.uint32 if tiles * k < 2**32 else mx.uint64
    keys = mx.sort(t.astype(key_type) * k + j.astype(key_type))
    ids = live[(keys % k).astype(mx.int32)]
    offsets = mx.searchsorted(keys, mx.arange(tiles + 1, dtype=key_type) * k).astype(mx.int32)
    return Bins(offsets, ids, tiles_x, tiles_y, tile)


def _check_mlx_inputs(means, r, d, con, opac, width: int, height: int) -> None:
    """The C++ binning's argument checks, as ValueError."""
    n = means.shape[0]
    if d.shape[0] != n:
        raise ValueError("bin_tiles: means2d and depths must have the same number of rows")
    if r.shape[0] != n:
        raise ValueError("bin_tiles: radii must have one entry per Gaussian")
    if con is not None and (con.shape[0] != n or opac.shape[0] != n):
        raise ValueError("bin_tiles: conics and opacities must have one row per Gaussian")
    if width < 1 or height < 1:
        raise ValueError("bin_tiles: width, height and tile_size must be >= 1")


def bin_gaussians(means2d, radii, depths, width: int, height: int, conics=None, *, opacities=None, tile_size: int = TILE_SIZE,
                  backend: str = "auto") -> tuple:
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
    changes the tile edge from 16 pixels; ``backend`` (keyword-only, as
    ``mlx3d.render.rasterize.resolve_backend``) picks the C++ ('cpu') or the
    MLX binning (any other): the same lists (with conics, the same image;
    module docstring).
    """
    from .rasterize import resolve_backend

    if conics is not None and opacities is None:
        opacities = np.ones(np.shape(radii)[0], np.float32)
    bins = bin_tiles(means2d, radii, depths, width, height, tile_size, conics, opacities, backend=resolve_backend(backend))
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
