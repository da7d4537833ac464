"""Pure-MLX reference rasterizer: small, vectorised, differentiable by autodiff.

The test oracle for the compiled kernels. Same inputs, outputs and math as the
C++/Metal rasterizers (the 3DGS rules: alpha = min(0.99, o·exp(power)), skip
power > 0 and alpha < 1/255, stop before transmittance drops below 1e-4).

Front-to-back compositing is written without a loop: with α_k zero for skipped
Gaussians, T_after_k = Π_{j≤k} (1 - α_j). A Gaussian contributes iff
T_after_k ≥ 1e-4; since T only decreases, the contributors are a prefix of the
non-skipped Gaussians, so T_before_k (exclusive product) is exactly the 3DGS
transmittance, and the final T is the product over contributors.

With a surface layer (``mlx3d.render.surface``), the Gaussians at or behind
the surface's depth are those with depth >= d (a suffix of the depth-sorted
list). The pixel reaches the surface iff T_front = Π over the Gaussians in
front of (1 - α) is >= 1e-4 (T only decreases, so no Gaussian in front
stopped it); it then adds T_front · colour, and every Gaussian behind sees
its transmittances multiplied by (1 - surface alpha). Each pixel thus stops
as the sequential rules say, including right after the surface.

Tiles are processed in chunks whose (pixels × Gaussians) size is bounded by
``max_elements`` so memory stays bounded; it is still O(pixels × Gaussians per
tile) work and meant for tests and small scenes.
"""

from __future__ import annotations

import mlx.core as mx
import numpy as np

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


def _surface_per_tile(surface, tiles_x: int, tiles_y: int, tile_size: int):
    """The surface's colour (tiles, P, C), alpha and depth (tiles, P) at each tile's pixels (row-major in the
    tile, P = tile_size²); alpha 0 and depth +inf outside the image."""
    height, width = surface.alpha.shape
    pad = [(0, tiles_y * tile_size - height), (0, tiles_x * tile_size - width)]

    def per_tile(a):
        rest = tuple(a.shape[2:])
        a = a.reshape(tiles_y, tile_size, tiles_x, tile_size, *rest).swapaxes(1, 2)
        return a.reshape(tiles_x * tiles_y, tile_size * tile_size, *rest)

    color = per_tile(mx.pad(surface.color, pad + [(0, 0)]))
    return color, per_tile(mx.pad(surface.alpha, pad)), per_tile(mx.pad(surface.depth, pad, constant_values=float("inf")))


def rasterize_reference(
    means2d, conics, features, opacities, tile_offsets, flatten_ids, width: int, height: int, tile_size: int = 16, max_elements: int = 1 << 23,
    *, depths=None, surface=None,
):
    """Returns (accum (H,W,C) without background, alpha (H,W), last (H,W) int32) as MLX arrays,
    ``last`` as in ``rasterize_cpu`` (1 + position of the last contributing entry in the tile's range, 0 if none).
    With ``surface`` (an ``mlx3d.render.Surface``) and ``depths`` (N,) the Gaussians' camera z, the surface
    layer is composited in depth order (module docstring); alpha then includes its coverage."""
    channels = features.shape[1]
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    layer = None if surface is None else _surface_per_tile(surface, tiles_x, tiles_y, tile_size)
    offsets = np.asarray(tile_offsets, dtype=np.int64)
    ids = np.asarray(flatten_ids, dtype=np.int64)
    counts = offsets[1:] - offsets[:-1]
    if ids.size == 0:  # no Gaussian to draw (also covers N == 0)
        none = mx.zeros((height, width), dtype=mx.int32)
        if surface is not None:
            return surface.color, surface.alpha, none
        return mx.zeros((height, width, channels)), mx.zeros((height, width)), none
    pix = tile_size * tile_size
    # pixel centres of one tile, row-major inside the tile
    local = np.stack(np.meshgrid(np.arange(tile_size), np.arange(tile_size), indexing="xy"), -1).reshape(-1, 2) + 0.5

    rows_accum, rows_alpha, rows_last = [], [], []
    t = 0
    num_tiles = tiles_x * tiles_y
    tile_accum = [None] * num_tiles
    tile_alpha = [None] * num_tiles
    tile_last = [None] * num_tiles
    while t < num_tiles:
        # grow the chunk while it fits in max_elements
        end, widest = t, 0
        while end < num_tiles:
            widest_next = max(widest, int(counts[end]), 1)
            if end > t and (end + 1 - t) * pix * widest_next > max_elements:
                break
            widest = widest_next
            end += 1
        chunk = np.arange(t, end)
        index = np.full((chunk.size, widest), -1, dtype=np.int64)
        for row, tile in enumerate(chunk):
            index[row, : counts[tile]] = ids[offsets[tile] : offsets[tile + 1]]
        valid = mx.array(index >= 0)  # (T, G)
        gather = mx.array(np.maximum(index, 0))
        origin = np.stack([(chunk % tiles_x) * tile_size, (chunk // tiles_x) * tile_size], -1)  # (T,2)
        centres = mx.array((origin[:, None, :] + local[None]).astype(np.float32))  # (T,P,2)
        d = means2d[gather][:, None, :, :] - centres[:, :, None, :]  # (T,P,G,2)
        con = conics[gather][:, None, :, :]  # (T,1,G,3)
        power = -0.5 * (con[..., 0] * d[..., 0] * d[..., 0] + con[..., 2] * d[..., 1] * d[..., 1]) - con[..., 1] * d[..., 0] * d[..., 1]
        alpha = mx.minimum(ALPHA_MAX, opacities[gather][:, None, :] * mx.exp(mx.minimum(power, 0.0)))
        keep = valid[:, None, :] & (power <= 0) & (alpha >= ALPHA_MIN)
        alpha = mx.where(keep, alpha, 0.0)
        t_after = mx.cumprod(1.0 - alpha, axis=-1)
        t_before = mx.concatenate([mx.ones_like(t_after[..., :1]), t_after[..., :-1]], axis=-1)
        if layer is not None:
            s_color, s_alpha, s_depth = (a[mx.array(chunk)] for a in layer)  # (T,P,C), (T,P), (T,P)
            behind = valid[:, None, :] & (depths[gather][:, None, :] >= s_depth[..., None])  # (T,P,G)
            t_front = mx.prod(mx.where(behind, 1.0, 1.0 - alpha), axis=-1)  # (T,P)
            s_weight = mx.where(t_front >= T_MIN, t_front, 0.0)  # 0: stopped before the surface
            factor = mx.where(behind, 1.0 - s_alpha[..., None], 1.0)
            t_after, t_before = t_after * factor, t_before * factor
        contributes = keep & (t_after >= T_MIN)
        weight = mx.where(contributes, alpha * t_before, 0.0)  # (T,P,G)
        accum = weight @ features[gather]  # (T,P,G) @ (T,G,C) -> (T,P,C)
        t_final = mx.prod(mx.where(contributes, 1.0 - alpha, 1.0), axis=-1)
        if layer is not None:
            accum = accum + s_weight[..., None] * s_color
            t_final = t_final * mx.where(s_weight > 0, 1.0 - s_alpha, 1.0)
        last = mx.max(mx.where(contributes, mx.arange(1, widest + 1, dtype=mx.int32), 0), axis=-1)  # (T,P)
        for row, tile in enumerate(chunk):
            tile_accum[tile] = accum[row]
            tile_alpha[tile] = 1.0 - t_final[row]
            tile_last[tile] = last[row]
        t = end

    for ty in range(tiles_y):
        row_tiles = range(ty * tiles_x, (ty + 1) * tiles_x)
        acc = mx.concatenate([tile_accum[i].reshape(tile_size, tile_size, channels) for i in row_tiles], axis=1)
        alp = mx.concatenate([tile_alpha[i].reshape(tile_size, tile_size) for i in row_tiles], axis=1)
        lst = mx.concatenate([tile_last[i].reshape(tile_size, tile_size) for i in row_tiles], axis=1)
        rows_accum.append(acc)
        rows_alpha.append(alp)
        rows_last.append(lst)
    accum = mx.concatenate(rows_accum, axis=0)[:height, :width]
    alpha = mx.concatenate(rows_alpha, axis=0)[:height, :width]
    last = mx.concatenate(rows_last, axis=0)[:height, :width]
    return accum, alpha, last
