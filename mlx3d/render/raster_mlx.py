"""The tile rasterizer in MLX operations: backend 'mlx', for wherever the compiled module is missing.

Same inputs, outputs and rules as the C++ and Metal rasterizers
(``raster_math.h``; docs/guides/rendering.md), forward and backward, and the
forward-only composite with a surface layer (``mlx3d.render.surface``). It
runs on any MLX device and needs nothing but MLX and numpy.

Work layout. The tiles' pixels and their entries are processed in *depth
batches*: batch b takes entries [s, s + B) of every active tile's range (all
active tiles are at the same position s) and evaluates them at the tile's
pixels as (tiles, pixels, B) arrays. Inside a batch the front-to-back
recurrence is a cumulative product: with α_k zero for skipped entries,
``T_after_k = T_in · Π_{j≤k} (1 - α_j)``; an entry contributes iff it is kept,
its pixel had not stopped, and ``T_after_k >= 1e-4``. T only decreases, so the
contributors are a prefix of the kept entries and ``T_in · Π_{j<k}`` is
exactly their transmittance (the rules of the sequential loop; float32
products are rounded in another order, so values agree to float precision,
not bitwise). A pixel stops at its first kept entry that would take T below
1e-4, as in the kernels. After each batch a tile leaves the active set when
its range is used up or all its pixels have stopped (one small read of the
stop flags per batch). Each batch's size B is set from the binning alone (the
tiles whose range reaches it), so that a batch holds at most about
``BATCH_ELEMENTS`` (pixel, entry) pairs: memory stays bounded, and the
arithmetic (so the result) does not depend on how the tiles are shared out.
On the CPU the tiles are shared between one group per core (``MLX3D_NUM_THREADS``),
each on its own MLX stream, whose batches run side by side. The work is about
the sum over the tiles of their pixels times the entries they visit.

The backward pass (an ``mx.custom_function`` vjp) replays the same batches
(the same schedule and arithmetic, so the same contributors) and uses, per
pixel, the colour behind each entry dotted with dL/daccum as the total minus a
running prefix: ``dL/dα_k = T_before·(f_k·g) - (S_k·g - dL/dalpha·T_final)/(1 - α_k)``
with ``S_k·g = accum·g - Σ_{j≤k} w_j (f_j·g)``; the per-entry gradients are
summed over the tile's pixels and added to their Gaussians once at the end.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mlx.core as mx
import numpy as np

from .raster_cpu import prepare_inputs, surface_forward_only, surface_layer

__all__ = ["rasterize_mlx", "rasterize_mlx_surface", "BATCH_ELEMENTS"]

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
BATCH_ELEMENTS = 1 << 21  # (pixel, entry) pairs per batch: about 8 MB per float32 temporary


@dataclass(eq=False)
class _Tiles:
    """The binning on the host and the pixel layout: tiles of P = tile² pixels, row-major inside a tile."""

    offsets: np.ndarray  # (tiles + 1,) int64
    counts: np.ndarray  # (tiles,) int64
    tile: int
    tiles_x: int
    tiles_y: int

    @classmethod
    def of(cls, tile_offsets, width: int, height: int, tile: int) -> "_Tiles":
        offsets = np.asarray(tile_offsets).astype(np.int64)
        return cls(offsets, np.diff(offsets), tile, -(-width // tile), -(-height // tile))

    @property
    def pixels(self) -> int:
        return self.tile * self.tile

    def bounds(self, budget: int) -> list:
        """(start, size) of the depth batches: each as large as ``budget`` (pixel, entry) pairs allow
        over the tiles whose range reaches it."""
        ordered = np.sort(self.counts)
        out, start, end = [], 0, int(ordered[-1]) if ordered.size else 0
        while start < end:
            active = ordered.size - np.searchsorted(ordered, start, side="right")
            size = int(min(end - start, max(1, budget // (active * self.pixels))))
            out.append((start, size))
            start += size
        return out

    def centres(self, tiles: np.ndarray) -> tuple:
        """Pixel centres (x, y) of ``tiles``, each (n, P) float32."""
        local = np.arange(self.pixels)
        x = (tiles % self.tiles_x)[:, None] * self.tile + (local % self.tile)[None] + 0.5
        y = (tiles // self.tiles_x)[:, None] * self.tile + (local // self.tile)[None] + 0.5
        return mx.array(x.astype(np.float32)), mx.array(y.astype(np.float32))

    def to_image(self, per_tile: mx.array, width: int, height: int) -> mx.array:
        """(tiles, P, ...) in tile order -> (H, W, ...)."""
        rest = tuple(per_tile.shape[2:])
        t = self.tile
        img = per_tile.reshape(self.tiles_y, self.tiles_x, t, t, *rest).swapaxes(1, 2)
        return img.reshape(self.tiles_y * t, self.tiles_x * t, *rest)[:height, :width]

    def from_image(self, image: mx.array) -> mx.array:
        """(H, W, ...) -> (tiles, P, ...), zero-padded to whole tiles."""
        rest = tuple(image.shape[2:])
        t = self.tile
        pad = [(0, self.tiles_y * t - image.shape[0]), (0, self.tiles_x * t - image.shape[1])] + [(0, 0)] * len(rest)
        img = mx.pad(image, pad).reshape(self.tiles_y, t, self.tiles_x, t, *rest).swapaxes(1, 2)
        return img.reshape(self.tiles_y * self.tiles_x, t * t, *rest)


@dataclass
class _Batch:
    """Entries [start, start + size) of the ranges of ``tiles`` (n,), with the Gaussians' values per entry."""

    tiles: np.ndarray  # (n,) tile ids, in the order of the carried per-tile state
    start: int
    size: int
    ids: mx.array  # (n, B) Gaussian index (0 where invalid)
    valid: mx.array  # (n, 1, B) bool: the entry exists and its id is in [0, N)
    exists: mx.array  # (n, 1, B) bool: the entry exists (its tile's range is not used up)
    position: mx.array  # (B,) int32: 1 + the entries' position in their tile's range


def _batch(tiles: np.ndarray, start: int, size: int, grid: _Tiles, flatten_ids: mx.array, n: int) -> _Batch:
    pos = start + np.arange(size)
    exists = pos[None] < grid.counts[tiles][:, None]
    entry = np.where(exists, grid.offsets[tiles][:, None] + pos[None], 0)
    ids = flatten_ids[mx.array(entry.reshape(-1).astype(np.int32))].reshape(entry.shape) if flatten_ids.size else mx.zeros(entry.shape, mx.int32)
    exists = mx.array(exists)
    valid = exists & (ids >= 0) & (ids < n)
    return _Batch(tiles, start, size, mx.where(valid, ids, 0), valid[:, None, :], exists[:, None, :], mx.array((pos + 1).astype(np.int32)))


class _Schedule:
    """The depth batches of a group of tiles (see the module docstring), identical in both passes.

    The batches' bounds come from the whole binning (``_Tiles.bounds``), not from the group or from which
    pixels stopped, so the arithmetic (and the result) is the same for any number of groups.
    ``next()`` gives the next ``_Batch`` (None when every tile has left); ``advance(batch, stopped)``
    moves past it given its (n, P) stop flags and returns the (n,) mask of its tiles that stay active.
    """

    def __init__(self, grid: _Tiles, tiles: np.ndarray, flatten_ids: mx.array, n: int, batch_elements: int):
        self.grid, self.ids, self.n = grid, flatten_ids, n
        self.tiles = tiles
        self.bounds = iter(grid.bounds(int(batch_elements)))

    def next(self) -> _Batch | None:
        if self.tiles.size == 0:
            return None
        start, size = next(self.bounds)
        return _batch(self.tiles, start, size, self.grid, self.ids, self.n)

    def advance(self, batch: _Batch, stopped: mx.array) -> np.ndarray:
        end = batch.start + batch.size
        stay = (self.grid.counts[batch.tiles] > end) & ~np.asarray(mx.all(stopped, axis=1))
        self.tiles = batch.tiles[stay]
        return stay


class _State:
    """Per-pixel fields of the active tiles, (n, P, ...) rows in the schedule's tile order.

    ``keep(stay)`` sets the rows that leave aside (``left_tiles``, ``left``).
    """

    def __init__(self, grid: _Tiles, tiles: np.ndarray, fields: dict):
        self.grid, self.tiles = grid, tiles
        self.active = fields
        self.left_tiles: list = []
        self.left: dict = {k: [] for k in fields}

    def keep(self, stay: np.ndarray) -> None:
        if stay.all():
            return
        leave, rows = mx.array(np.flatnonzero(~stay)), mx.array(np.flatnonzero(stay))
        self.left_tiles.append(self.tiles[~stay])
        self.tiles = self.tiles[stay]
        for k, v in self.active.items():
            self.left[k].append(v[leave])
            self.active[k] = v[rows]


def _gather(batch: _Batch, means2d, conics, opacities) -> tuple:
    """The batch's Gaussians' mean x, y, conic a, b, c and opacity, each (n, 1, B)."""
    g = batch.ids
    return tuple(v[g][:, None] for v in (means2d[:, 0], means2d[:, 1], conics[:, 0], conics[:, 1], conics[:, 2], opacities))


def _evaluate(batch: _Batch, px, py, gaussians: tuple):
    """raster_math.h on (n, P, B): (dx, dy, exp(power), alpha (0 where skipped), kept) of every (pixel, entry)."""
    mean_x, mean_y, ca, cb, cc, o = gaussians
    dx = mean_x - px[..., None]
    dy = mean_y - py[..., None]
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    e = mx.exp(mx.minimum(power, 0.0))
    alpha = mx.minimum(o * e, ALPHA_MAX)
    keep = batch.valid & (power <= 0.0) & (alpha >= ALPHA_MIN)  # NaN fails every comparison: skipped
    return dx, dy, e, mx.where(keep, alpha, 0.0), keep


def _composite(alpha, keep, T, stopped, factor=None):
    """Front to back over a batch of (n, P, B) alphas from the pixels' (n, P) T and stop flags.

    ``factor`` (n, P, B) scales the transmittance at and behind a surface layer. Returns
    (T_before, contributes, 1 - alpha, new T, new stop flags); T_before and contributes per entry.
    """
    one_minus = 1.0 - alpha
    after = mx.cumprod(one_minus, axis=-1)
    before = mx.concatenate([mx.ones_like(after[..., :1]), after[..., :-1]], axis=-1)
    scale = T[..., None] if factor is None else T[..., None] * factor
    before, after = before * scale, after * scale
    contributes = keep & (after >= T_MIN) & ~stopped[..., None]
    T_new = T * mx.prod(mx.where(contributes, one_minus, 1.0), axis=-1)
    # a kept entry that does not contribute is where the pixel stopped
    return before, contributes, one_minus, T_new, stopped | mx.any(keep & ~contributes, axis=-1)


def _surface_batch(batch: _Batch, depths, alpha, keep, s: dict):
    """A batch with the surface event (``mlx3d.render.surface``) just before each pixel's first entry at or
    behind the surface's depth; updates s['accum'], s['passed'], and returns ``_composite``'s tuple."""
    # as the kernels: +inf for an id outside [0, N), and "behind" is not (z < surface depth), NaN included; padding never is
    entry_depth = mx.where(batch.valid, depths[batch.ids][:, None], mx.where(batch.exists, mx.inf, -mx.inf))
    at_or_behind = ~(entry_depth < s["s_depth"][..., None])
    behind = (mx.cummax(at_or_behind.astype(mx.int8), axis=-1) > 0) & ~s["passed"][..., None]
    first = behind & ~mx.concatenate([mx.zeros_like(behind[..., :1]), behind[..., :-1]], axis=-1)
    # T in front of the surface over every kept entry before it: below 1e-4 when one of them stopped the pixel
    excl = mx.cumprod(mx.concatenate([mx.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1]], axis=-1), axis=-1)
    t_front = s["T"] * mx.sum(mx.where(first, excl, 0.0), axis=-1)
    reaches = mx.any(first, axis=-1) & ~s["stopped"] & (t_front >= T_MIN)
    s_keep = 1.0 - s["s_alpha"]
    before, contributes, one_minus, T_new, stopped = _composite(alpha, keep, s["T"], s["stopped"], mx.where(behind, s_keep[..., None], 1.0))
    s["accum"] = s["accum"] + mx.where(reaches, t_front, 0.0)[..., None] * s["s_color"]
    s["passed"] = s["passed"] | mx.any(first, axis=-1)
    T_new = T_new * mx.where(reaches, s_keep, 1.0)
    return before, contributes, one_minus, T_new, stopped | (reaches & (t_front * s_keep < T_MIN))


def _surface_after_last(s: dict, leaving: np.ndarray) -> None:
    """The surface event after the last entry, on the rows that leave and have not passed or stopped."""
    at = mx.array(leaving)[:, None] & ~s["passed"] & ~s["stopped"]
    s["accum"] = s["accum"] + mx.where(at, s["T"], 0.0)[..., None] * s["s_color"]
    s["T"] = s["T"] * mx.where(at, 1.0 - s["s_alpha"], 1.0)


class _Group:
    """A share of the tiles with its own schedule, per-pixel state and MLX stream."""

    def __init__(self, grid: _Tiles, tiles: np.ndarray, flatten_ids, n: int, budget: int, fields, stream):
        self.schedule = _Schedule(grid, tiles, flatten_ids, n, budget)
        self.state = _State(grid, tiles, fields(mx.array(tiles), tiles.size))
        self.stream = stream


def _groups(grid: _Tiles, flatten_ids, n: int, budget: int, fields) -> list:
    """The tiles with entries dealt to one group per CPU stream (by entry count, so the groups' work is even);
    ``fields(rows, m)`` gives a group's initial per-pixel state for the tile rows ``rows`` (m tiles)."""
    tiles = np.flatnonzero(grid.counts > 0)
    tiles = tiles[np.argsort(-grid.counts[tiles], kind="stable")]
    streams = _streams()
    shares = [np.sort(tiles[i :: len(streams)]) for i in range(len(streams))]
    return [_Group(grid, share, flatten_ids, n, budget, fields, stream) for share, stream in zip(shares, streams) if share.size]


def _streams() -> list:
    """One stream per core on the CPU (MLX runs each operation on one thread; streams run side by side), else the default."""
    if mx.default_device() != mx.cpu:
        return [mx.default_stream(mx.default_device())]
    global _CPU_STREAMS
    if _CPU_STREAMS is None:
        from .raster_cpu import get_num_threads

        _CPU_STREAMS = [mx.default_stream(mx.cpu)] + [mx.new_stream(mx.cpu) for _ in range(max(1, get_num_threads()) - 1)]
    return _CPU_STREAMS


_CPU_STREAMS = None


def _drive(groups: list, step, after=None) -> None:
    """Runs ``step(state fields, batch)`` on every group's batches, evaluating the groups' batches together
    (each on its stream), then ``after(state fields, batch, staying mask)`` before the tiles that leave are set aside."""
    active = list(groups)
    while active:
        running = []
        for g in active:
            batch = g.schedule.next()
            if batch is not None:
                with mx.stream(g.stream):
                    step(g.state.active, batch)
                running.append((g, batch))
        mx.eval([g.state.active for g, _ in running])
        for g, _ in running:  # each batch's temporaries are freed once nothing evaluated refers to them
            g.state.active = dict(zip(g.state.active, _detached(*g.state.active.values())))
        for g, batch in running:
            stay = g.schedule.advance(batch, g.state.active["stopped"])
            if after is not None:
                after(g.state.active, batch, stay)
            g.state.keep(stay)
        active = [g for g, _ in running]


def _image(grid: _Tiles, groups: list, name: str, initial: mx.array, width: int, height: int) -> mx.array:
    """Field ``name`` of every group's tiles as an (H, W, ...) image; ``initial`` (tiles, P, ...) where no tile was active."""
    tiles = [t for g in groups for t in g.state.left_tiles]
    if tiles:
        initial[mx.array(np.concatenate(tiles))] = mx.concatenate([v for g in groups for v in g.state.left[name]], axis=0)
    return grid.to_image(initial, width, height)


def _forward(means2d, conics, features, opacities, flatten_ids, grid: _Tiles, width: int, height: int, budget: int, surface=None):
    """(accum (H,W,C) without background, alpha, last int32, final_T (H,W)).

    ``surface``: (depths (N,), colour (tiles, P, C), alpha and depth (tiles, P)) for the depth-tested layer.
    """
    n, channels, P = means2d.shape[0], features.shape[1], grid.pixels
    num_tiles = grid.tiles_x * grid.tiles_y

    def fields(rows, m):
        out = {"accum": mx.zeros((m, P, channels)), "T": mx.ones((m, P)), "stopped": mx.zeros((m, P), mx.bool_),
               "last": mx.zeros((m, P), mx.int32)}
        if surface is not None:
            out.update(passed=mx.zeros((m, P), mx.bool_), s_color=surface[1][rows], s_alpha=surface[2][rows], s_depth=surface[3][rows])
        return out

    def step(s, batch):
        px, py = grid.centres(batch.tiles)
        _, _, _, alpha, keep = _evaluate(batch, px, py, _gather(batch, means2d, conics, opacities))
        if surface is None:
            before, contributes, _, s["T"], s["stopped"] = _composite(alpha, keep, s["T"], s["stopped"])
        else:
            before, contributes, _, s["T"], s["stopped"] = _surface_batch(batch, surface[0], alpha, keep, s)
        weight = mx.where(contributes, alpha * before, 0.0)
        s["accum"] = s["accum"] + weight @ features[batch.ids]
        s["last"] = mx.maximum(s["last"], mx.max(mx.where(contributes, batch.position, 0), axis=-1))

    groups = _groups(grid, flatten_ids, n, budget, fields)
    _drive(groups, step, None if surface is None else lambda s, batch, stay: _surface_after_last(s, ~stay))
    accum0, T0 = mx.zeros((num_tiles, P, channels)), mx.ones((num_tiles, P))
    if surface is not None:  # tiles without entries: the surface alone
        accum0, T0 = surface[1], 1.0 - surface[2]
    accum = _image(grid, groups, "accum", accum0, width, height)
    T = _image(grid, groups, "T", T0, width, height)
    last = _image(grid, groups, "last", mx.zeros((num_tiles, P), mx.int32), width, height)
    return accum, 1.0 - T, last, T


def _backward(means2d, conics, features, opacities, flatten_ids, grid: _Tiles, budget: int, accum, final_T, cot_accum, cot_alpha):
    """Gradients (means2d, conics, features, opacities) of the composite, given its outputs and their cotangents (H, W, ...)."""
    n, P = means2d.shape[0], grid.pixels
    g_all, T_final_all = grid.from_image(cot_accum), grid.from_image(final_T)
    g_alpha_all, total_all = grid.from_image(cot_alpha) * T_final_all, mx.sum(grid.from_image(accum) * g_all, axis=-1)

    def fields(rows, m):
        return {"T": mx.ones((m, P)), "stopped": mx.zeros((m, P), mx.bool_), "prefix": mx.zeros((m, P)), "g": g_all[rows],
                "g_alpha_T": g_alpha_all[rows], "total": total_all[rows]}

    def step(s, batch):
        px, py = grid.centres(batch.tiles)
        gaussians = _gather(batch, means2d, conics, opacities)
        dx, dy, e, alpha, keep = _evaluate(batch, px, py, gaussians)
        before, contributes, one_minus, s["T"], s["stopped"] = _composite(alpha, keep, s["T"], s["stopped"])
        weight = mx.where(contributes, alpha * before, 0.0)
        f = features[batch.ids]  # (n, B, C)
        fg = s["g"] @ f.swapaxes(1, 2)  # (n, P, B): f_k · dL/daccum
        prefix = mx.cumsum(weight * fg, axis=-1) + s["prefix"][..., None]
        behind_g = s["total"][..., None] - prefix  # (colour behind entry k) · dL/daccum
        dl_dalpha = mx.where(contributes, before * fg - (behind_g - s["g_alpha_T"][..., None]) / one_minus, 0.0)
        _, _, ca, cb, cc, o = gaussians
        raw = o * e
        clamped = raw > ALPHA_MAX
        dl_dpower = mx.where(clamped, 0.0, raw * dl_dalpha)
        grads = mx.stack([
            -dl_dpower * (ca * dx + cb * dy), -dl_dpower * (cb * dx + cc * dy),
            -0.5 * dl_dpower * dx * dx, -dl_dpower * dx * dy, -0.5 * dl_dpower * dy * dy,
            mx.where(clamped, 0.0, e * dl_dalpha),
        ], axis=-1).sum(axis=1)  # (n, B, 6), summed over the tile's pixels
        s["entries"] = mx.concatenate([grads, weight.swapaxes(1, 2) @ s["g"]], axis=-1).reshape(-1, 6 + f.shape[-1])
        s["prefix"] = prefix[..., -1]
        s["ids"] = mx.where(batch.valid[:, 0], batch.ids, n).reshape(-1)  # invalid entries go to a spare row n

    def after(s, batch, stay):  # the batch's per-entry results: kept aside, not carried as per-pixel state
        per_batch.setdefault(batch.start, []).append((batch.tiles, s.pop("ids"), s.pop("entries")))

    per_batch: dict = {}  # batch start -> [(tiles, ids, per-entry gradients)] of each group
    _drive(_groups(grid, flatten_ids, n, budget, fields), step, after)
    total = mx.zeros((n + 1, 6 + features.shape[1]))
    if per_batch:
        ids, rows = zip(*(_in_tile_order(per_batch[start]) for start in sorted(per_batch)))
        total = total.at[mx.concatenate(ids)].add(mx.concatenate(rows))
    total = total[:n]
    return total[:, :2], total[:, 2:5], total[:, 6:], total[:, 5]


def _in_tile_order(parts: list) -> tuple:
    """One batch's (ids, per-entry rows) of every group, merged in tile order: the gradients are then summed in
    the same order for any number of groups."""
    if len(parts) == 1:
        return parts[0][1], parts[0][2]
    tiles = np.concatenate([p[0] for p in parts])
    per_tile = parts[0][1].size // parts[0][0].size
    order = mx.array((np.argsort(tiles, kind="stable")[:, None] * per_tile + np.arange(per_tile)).reshape(-1))
    return mx.concatenate([p[1] for p in parts])[order], mx.concatenate([p[2] for p in parts])[order]


def _detached(*arrays) -> list:
    """Evaluated copies of ``arrays`` that refer to no graph. While a gradient is taken (``mx.grad``, ``mx.vjp``),
    MLX keeps the inputs of every evaluated array alive; the depth batches start from such copies (the inputs, and
    the per-pixel state after each batch), so that each batch's temporaries (gigabytes over a large frame
    altogether) are freed as the next one runs."""
    return [mx.array(np.asarray(a)) for a in arrays]


@functools.lru_cache(maxsize=64)
def _rasterizer(width: int, height: int, tile: int, budget: int):
    """The differentiable composite for one image and tile size: (accum, alpha, last, final_T)."""

    @mx.custom_function
    def raster(means2d, conics, features, opacities, tile_offsets, flatten_ids):
        grid = _Tiles.of(tile_offsets, width, height, tile)
        return _forward(*_detached(means2d, conics, features, opacities, flatten_ids), grid, width, height, budget)

    @raster.vjp
    def raster_vjp(primals, cotangents, outputs):
        means2d, conics, features, opacities, tile_offsets, flatten_ids = primals
        accum, _, _, final_T = outputs
        cot_accum = mx.zeros_like(accum) if cotangents[0] is None else cotangents[0].astype(mx.float32)
        cot_alpha = mx.zeros_like(final_T) if cotangents[1] is None else cotangents[1].astype(mx.float32)
        grid = _Tiles.of(tile_offsets, width, height, tile)
        arrays = _detached(means2d, conics, features, opacities, flatten_ids, accum, final_T, cot_accum, cot_alpha)
        grads = _backward(*arrays[:5], grid, budget, *arrays[5:])
        return (*grads, mx.zeros_like(tile_offsets), mx.zeros_like(flatten_ids))

    return raster


def rasterize_mlx(
    means2d, conics, features, opacities, tile_offsets, flatten_ids, width: int, height: int, tile_size: int = 16,
    num_threads: int | None = None, *, check_indices: bool = True, batch_elements: int = BATCH_ELEMENTS,
):
    """Composite binned Gaussians with MLX operations; arguments and outputs as
    :func:`mlx3d.render.raster_cpu.rasterize_cpu` (``num_threads`` is accepted and ignored;
    ``batch_elements``: (pixel, entry) pairs per depth batch, the memory/overhead trade-off).
    Returns (accum (H,W,C) without background, alpha (H,W), last (H,W) int32); differentiable
    w.r.t. means2d, conics, features and opacities (entries with an id outside [0, N) are skipped).
    """
    del num_threads
    (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size) = prepare_inputs(
        means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size, check_indices
    )
    accum, alpha, last, _ = _rasterizer(width, height, tile_size, int(batch_elements))(means2d, conics, features, opacities, tile_offsets, flatten_ids)
    return accum, alpha, last


def rasterize_mlx_surface(
    means2d, conics, features, opacities, tile_offsets, flatten_ids, depths, surface_color, surface_alpha, surface_depth,
    width: int, height: int, tile_size: int = 16, num_threads: int | None = None, *, batch_elements: int = BATCH_ELEMENTS,
):
    """:func:`rasterize_mlx` composited with a surface layer in depth order (forward-only); arguments and
    outputs as :func:`mlx3d.render.raster_cpu.rasterize_cpu_surface`."""
    del num_threads
    (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size) = prepare_inputs(
        means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size, False
    )
    grid = _Tiles.of(tile_offsets, width, height, tile_size)
    arrays = surface_layer(depths, surface_color, surface_alpha, surface_depth, means2d.shape[0], height, width, features.shape[1])
    surface = (arrays[0], grid.from_image(arrays[1]), grid.from_image(arrays[2]), grid.from_image(arrays[3]))

    def composite(means2d, conics, features, opacities):
        return _forward(means2d, conics, features, opacities, flatten_ids, grid, width, height, int(batch_elements), surface)

    accum, alpha, last, _ = surface_forward_only(composite, "rasterize_mlx_surface", means2d, conics, features, opacities)
    return accum, alpha, last
