"""Per-image bilateral grids of affine colour transforms, in MLX.

The bilateral grid of "Bilateral Guided Radiance Field Processing" (Wang et
al., SIGGRAPH 2024), in the form used by gsplat's trainer (``BilateralGrid``
in ``lib_bilagrid.py`` and its fused CUDA variant): every training image gets
a small 3-D grid of 3x4 affine colour matrices, indexed by pixel position and
by the pixel's luminance.  Rendering ``img`` for image ``i`` then returns

    out[p] = M_i(x_p, y_p, l_p) @ [r, g, b, 1]

where ``M_i(...)`` is the trilinear interpolation of the grid.  Trained
jointly with the scene (with a small total-variation penalty), the grids
absorb per-photo exposure, white balance and tone-curve differences that the
3D model should not explain.

Conventions (matching gsplat):

* ``params`` has shape ``(num_images, grid_y, grid_x, grid_guidance, 12)``;
  the 12 values are the row-major 3x4 matrix ``[[a00 a01 a02 b0], [a10 a11
  a12 b1], [a20 a21 a22 b2]]``, initialised to the identity ``[I | 0]``.
* Slicing coordinates are pixel centres: ``x = (col + 0.5) / W`` and
  ``y = (row + 0.5) / H`` (row 0 at the top), and the guidance is the BT.601
  luma ``l = 0.299 r + 0.587 g + 0.114 b``; each lies in ``[0, 1]`` and maps
  linearly onto the grid's index range ``[0, n - 1]`` (``grid_sample`` with
  ``align_corners=True``).  Out-of-range guidance (colours outside ``[0, 1]``)
  is clamped to the border cells (``padding_mode="border"``, zero gradient
  with respect to the clamped coordinate).
* ``tv_loss`` is gsplat's ``total_variation_loss``: for each grid axis, the
  mean over all grids and channels of the squared difference of neighbours
  along that axis, summed over the three axes.

Implementation.  The MLX CPU backend runs every op on one thread with a
fixed overhead, and its scatter-add (the VJP of a gather) costs about 20 ns
per element, so the slice and the TV term have hand-written VJPs
(``mx.custom_function``) whose work is done by numpy:

* Slicing.  Image columns are grouped by the grid x-interval they fall in
  (``gx - 1`` segments, padded to a common length), the grid is interpolated
  along y for every image row, and each (row, segment) block of pixels is one
  small matrix product ``cells (12, 2 x-columns * guidance cells) @ weights
  (.., pixels)``: the row's cells of the segment's two x-columns times the
  trilinear weights, dense along guidance.  Backward, the transposed products
  give the cells' gradient (summed over rows with the y weights: no scatter)
  and, from the cells' steps along guidance, the luminance path of the image
  gradient.  Float32 and float64 only; inside ``mx.compile`` or ``mx.vmap``
  (where arrays cannot be evaluated) and for other dtypes,
  :func:`apply_grid_reference` (the MLX graph: two-stage gathers, MLX's own
  gradients, also the tests' oracle) is used.  The hand-written VJP is first
  order: differentiate the reference for higher derivatives.
* TV.  Differences along each axis on flat views and the gradient assembled
  in place (:func:`total_variation_reference` is the MLX graph).

Training cost.  Only the stepped image's grid gets a data gradient, but the
TV over all grids and an Adam step over the whole ``(num_images, ...)`` stack
cost O(num_images) per step.  :class:`GridAdam` with the TV of the stepped
grid alone (``tv_loss(grid)`` on that grid) keeps the cost per step
independent of the number of images; see :class:`GridAdam` for what it
changes and what it keeps.
"""

from __future__ import annotations

import functools
import itertools
import os
from collections import OrderedDict
from typing import Callable, Dict, Optional, Sequence, Tuple

import mlx.core as mx
import numpy as np

from ..io.atomic import atomic_write

__all__ = [
    "LUMA_WEIGHTS",
    "DEFAULT_GRID_SHAPE",
    "identity_grid",
    "slice_affine",
    "apply_grid",
    "apply_grid_reference",
    "total_variation",
    "total_variation_reference",
    "BilateralGrid",
    "GridAdam",
]

# BT.601 RGB -> luma, as gsplat's rgb2gray.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
DEFAULT_GRID_SHAPE = (16, 16, 8)  # (grid_y, grid_x, grid_guidance)

_IDENTITY_3x4 = np.array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], np.float32)

# dtypes the numpy kernels handle (others use the MLX graph)
_NUMPY_DTYPES = {mx.float32: np.float32, mx.float64: np.float64}


def _check_grid_shape(grid_shape) -> Tuple[int, int, int]:
    shape = tuple(int(s) for s in grid_shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"grid_shape must be three positive sizes (y, x, guidance), got {grid_shape}")
    return shape


def identity_grid(grid_shape: Sequence[int] = DEFAULT_GRID_SHAPE) -> mx.array:
    """One grid ``(gy, gx, gg, 12)`` of identity transforms."""
    gy, gx, gg = _check_grid_shape(grid_shape)
    return mx.array(np.broadcast_to(_IDENTITY_3x4, (gy, gx, gg, 12)).copy())


def _evaluable(*arrays: mx.array) -> bool:
    """Evaluate ``arrays``; False inside transformations that forbid it (compile, vmap)."""
    try:
        mx.eval(*arrays)
    except ValueError as e:
        if "transformation" in str(e):
            return False
        raise
    return True


def _numpy(a: mx.array) -> np.ndarray:
    """A numpy view of an evaluated MLX array (no copy)."""
    return np.array(a, copy=False)


# ----------------------------------------------------------------------------
# slicing: the MLX graph (reference and fallback)
# ----------------------------------------------------------------------------


def _axis_lerp(n_pix: int, n_cells: int):
    """Pixel-centre coordinates on one axis: lower/upper cell and weight."""
    t = (np.arange(n_pix, dtype=np.float64) + 0.5) / n_pix * (n_cells - 1)
    lo = np.clip(np.floor(t), 0, n_cells - 1).astype(np.int32)
    hi = np.minimum(lo + 1, n_cells - 1).astype(np.int32)
    return lo, hi, t - lo


class _Slicer:
    """Static index data and the slicing graph (MLX ops) for one (H, W, grid) shape."""

    def __init__(self, h: int, w: int, grid_shape: Tuple[int, int, int]):
        gy, gx, gg = grid_shape
        self.h, self.w, self.grid_shape = h, w, grid_shape
        y0, y1, wy = _axis_lerp(h, gy)
        x0, x1, wx = _axis_lerp(w, gx)
        self.y0, self.y1 = mx.array(y0), mx.array(y1)
        self._wy = wy[:, None, None, None]  # (H, 1, 1, 1), float64
        self._wx = wx[None, :, None]  # (1, W, 1), float64
        self._weights: Dict[mx.Dtype, Tuple[mx.array, mx.array]] = {}
        # Row of the row-interpolated grid (H * gx * gg, 12) holding each
        # pixel's lower/upper x corner at guidance cell 0.
        rows = np.arange(h, dtype=np.int64)[:, None] * gx
        self.base_x0 = mx.array(((rows + x0[None, :]) * gg).astype(np.int32))
        self.base_x1 = mx.array(((rows + x1[None, :]) * gg).astype(np.int32))
        self.compiled = mx.compile(self.forward)

    def weights(self, dtype) -> Tuple[mx.array, mx.array]:
        """Static (wy, wx) interpolation weights in the compute dtype."""
        if dtype not in self._weights:
            self._weights[dtype] = (mx.array(self._wy, dtype=dtype), mx.array(self._wx, dtype=dtype))
        return self._weights[dtype]

    def affine(self, grid: mx.array, img: mx.array) -> mx.array:
        """Trilinearly interpolated matrices, (H, W, 12)."""
        gy, gx, gg = self.grid_shape
        h, w = self.h, self.w
        # Interpolate along y once per image row: (H, gx, gg, 12).
        wy, wx = self.weights(img.dtype)
        rowgrid = mx.take(grid, self.y0, axis=0) * (1.0 - wy) + mx.take(grid, self.y1, axis=0) * wy
        rowgrid = rowgrid.reshape(h * gx * gg, 12)
        gray = img[..., 0] * LUMA_WEIGHTS[0] + img[..., 1] * LUMA_WEIGHTS[1] + img[..., 2] * LUMA_WEIGHTS[2]
        # Clamped guidance coordinate (zero gradient where clamped, like
        # grid_sample's border padding); the cell index carries no gradient.
        z = mx.clip(gray, 0.0, 1.0) * float(gg - 1)
        z0f = mx.stop_gradient(mx.clip(mx.floor(z), 0.0, float(gg - 1)))
        z0 = z0f.astype(mx.int32)
        z1 = mx.minimum(z0 + 1, gg - 1)
        wz = (z - z0f)[..., None]  # (H, W, 1)

        def corner(base, zi):
            return mx.take(rowgrid, (base + zi).reshape(-1), axis=0).reshape(h, w, 12)

        return (1.0 - wx) * ((1.0 - wz) * corner(self.base_x0, z0) + wz * corner(self.base_x0, z1)) + wx * (
            (1.0 - wz) * corner(self.base_x1, z0) + wz * corner(self.base_x1, z1)
        )

    def forward(self, grid: mx.array, img: mx.array) -> mx.array:
        return _affine(self.affine(grid, img), img)


def _affine(a: mx.array, img: mx.array) -> mx.array:
    """Apply per-pixel 3x4 matrices ``a`` (H, W, 12) to ``img`` (H, W, 3)."""
    a = a.reshape(*a.shape[:-1], 3, 4)
    return a[..., 0] * img[..., 0:1] + a[..., 1] * img[..., 1:2] + a[..., 2] * img[..., 2:3] + a[..., 3]


@functools.lru_cache(maxsize=32)
def _slicer(h: int, w: int, grid_shape: Tuple[int, int, int]) -> _Slicer:
    return _Slicer(h, w, grid_shape)


# ----------------------------------------------------------------------------
# slicing: numpy kernels with a hand-written VJP
# ----------------------------------------------------------------------------


class _NumpySlicer:
    """Static data and numpy kernels for one (H, W, grid shape, dtype).

    Pixels are laid out as (row, segment, slot): segment ``s`` holds the
    columns whose x-coordinate lies in cell interval ``[s, s + 1]`` (one
    segment when ``gx == 1``), ``L`` slots each; unused slots have zero
    weights.  A pixel's weights over its row's cells of the segment's lower
    and upper x-column (``K = 2 * gz`` entries, ``gz = max(gg, 2)`` guidance
    cells per column, the second one zero when ``gg == 1``) are the column's
    x weight times the hat functions ``max(0, 1 - |z - j|)`` of the guidance
    coordinate ``z``: nonzero at ``floor(z)`` and the cell above only.  Per
    (row, segment): matrices ``(12, L) = cells (12, K) @ weights (K, L)``;
    backward, ``q @ weights^T`` gives the cells' gradient and ``steps^T @ q``
    (``steps``: the cells' differences along guidance) the guidance
    derivative, read at each pixel's lower guidance cell (``floor(z)``, or
    the last but one at the top), ``q`` being the matrices' gradient.
    Per-pixel arrays are planes ``(C, H, nseg, L)``; the products read and
    write them as strided blocks.
    """

    def __init__(self, h: int, w: int, grid_shape: Tuple[int, int, int], dtype):
        gy, gx, gg = grid_shape
        self.h, self.w, self.grid_shape, self.dtype = h, w, grid_shape, np.dtype(dtype)
        y0, y1, wy = _axis_lerp(h, gy)
        wy_mat = np.zeros((h, gy))
        np.add.at(wy_mat, (np.arange(h), y0), 1.0 - wy)
        np.add.at(wy_mat, (np.arange(h), y1), wy)
        self.wy = wy_mat.astype(dtype)  # (H, gy): y-interpolation of the grid per image row
        x0, _, wx = _axis_lerp(w, gx)
        nseg = max(gx - 1, 1)
        counts = np.bincount(x0, minlength=nseg)
        seg_len = max(int(counts.max()), 1)
        first = np.cumsum(counts) - counts
        self.nseg, self.seg_len = nseg, seg_len
        self.slot = (x0 * seg_len + np.arange(w) - first[x0]).astype(np.intp)  # column -> slot (of nseg * L)
        self.column = np.zeros(nseg * seg_len, np.intp)  # slot -> column (0 for unused slots)
        self.column[self.slot] = np.arange(w)
        wlo = np.zeros((nseg, seg_len))
        whi = np.zeros((nseg, seg_len))
        wlo.reshape(-1)[self.slot] = 1.0 - wx
        whi.reshape(-1)[self.slot] = wx
        self.wlo, self.whi = wlo.astype(dtype), whi.astype(dtype)
        self.upper = np.minimum(np.arange(nseg) + 1, gx - 1)  # the upper x-column of each segment
        self.gz = max(gg, 2)
        self.k = 2 * self.gz
        self.pixel = np.arange(h * nseg * seg_len, dtype=np.intp).reshape(h, nseg, seg_len)  # flat slot index

    def _cells(self, grid: np.ndarray) -> np.ndarray:
        """(H, nseg, 12, K): each row's y-interpolated cells of each segment's two x-columns."""
        gy, gx, gg = self.grid_shape
        gt = np.swapaxes(grid, 2, 3)  # (gy, gx, 12, gg)
        cells = np.zeros((gy, self.nseg, 12, self.k), self.dtype)
        cells[..., :gg] = gt[:, : self.nseg]
        cells[..., self.gz : self.gz + gg] = gt[:, self.upper]
        return (self.wy @ cells.reshape(gy, -1)).reshape(self.h, self.nseg, 12, self.k)

    def _planes(self, image: np.ndarray) -> np.ndarray:
        """(3, H, nseg, L) channel planes of an (H, W, 3) image in the slot layout."""
        return np.take(np.moveaxis(image, 2, 0), self.column, axis=2).reshape(3, self.h, self.nseg, self.seg_len)

    def _unplanes(self, planes: np.ndarray) -> np.ndarray:
        """(H, W, 3) from (3, H, nseg, L) planes."""
        out = np.empty((self.h, self.w, 3), self.dtype)
        for c in range(3):
            out[..., c] = planes[c].reshape(self.h, -1)[:, self.slot]
        return out

    def forward(self, grid: np.ndarray, image: np.ndarray):
        """``(out (H, W, 3), saved)`` for ``grid (gy, gx, gg, 12)``, ``image (H, W, 3)``."""
        gy, gx, gg = self.grid_shape
        h, nseg, seg_len, dt = self.h, self.nseg, self.seg_len, self.dtype
        cells = self._cells(grid)
        pix = self._planes(image)
        r, g, b = pix
        lum = r * LUMA_WEIGHTS[0] + g * LUMA_WEIGHTS[1] + b * LUMA_WEIGHTS[2]
        z = np.clip(lum, 0.0, 1.0) * (gg - 1)
        # Weights (K, H, nseg, L): the hat functions max(0, 1 - |z - j|) of the guidance cells
        # (1 - wz at z0, wz at z0 + 1), times the x weights of each column.
        weights = np.empty((self.k, h, nseg, seg_len), dt)
        for j in range(self.gz):
            hat = weights[j]
            np.subtract(z, j, out=hat)
            np.abs(hat, out=hat)
            np.subtract(1.0, hat, out=hat)
            np.maximum(hat, 0.0, out=hat)
            np.multiply(hat, self.whi, out=weights[self.gz + j])
            hat *= self.wlo
        mats = np.empty((12, h, nseg, seg_len), dt)
        np.matmul(cells, np.moveaxis(weights, 0, 2), out=np.moveaxis(mats, 0, 2))
        out = np.empty((3, h, nseg, seg_len), dt)
        tmp = np.empty((h, nseg, seg_len), dt)
        for d in range(3):
            o = out[d]
            np.multiply(mats[4 * d], r, out=o)
            o += np.multiply(mats[4 * d + 1], g, out=tmp)
            o += np.multiply(mats[4 * d + 2], b, out=tmp)
            o += mats[4 * d + 3]
        return self._unplanes(out), (cells, pix, z, weights, mats)

    def backward(self, saved, grad_out: np.ndarray):
        """``(grad_grid, grad_image)`` from ``forward``'s ``saved`` and ``grad_out (H, W, 3)``."""
        cells, pix, z, weights, mats = saved
        gy, gx, gg = self.grid_shape
        h, nseg, seg_len, dt = self.h, self.nseg, self.seg_len, self.dtype
        gp = self._planes(grad_out)
        # Gradient of the matrices, q[4d + c] = grad_out[d] * [r, g, b, 1][c] (unused slots: their
        # weights are 0, so whatever they hold reaches neither the grid nor a real pixel).
        q = np.empty((12, h, nseg, seg_len), dt)
        for d in range(3):
            for c in range(3):
                np.multiply(gp[d], pix[c], out=q[4 * d + c])
            q[4 * d + 3] = gp[d]
        q_blocks = np.moveaxis(q, 0, 2)  # (H, nseg, 12, L)
        dcells = np.matmul(q_blocks, np.moveaxis(weights, 0, 3))  # (H, nseg, 12, K)
        dcells = np.moveaxis((dcells.reshape(h, -1).T @ self.wy).reshape(nseg, 12, self.k, gy), 3, 0)
        dgt = np.zeros((gy, gx, 12, gg), dt)
        dgt[:, :nseg] = dcells[..., :gg]
        if gx > 1:
            dgt[:, 1:] += dcells[..., self.gz : self.gz + gg]
        else:
            dgt[:, 0] += dcells[:, 0, :, self.gz : self.gz + gg]
        grad_grid = np.ascontiguousarray(np.swapaxes(dgt, 2, 3))
        # Guidance: the matrices' z-derivative is wlo * (lower column's cells[z0 + 1] - cells[z0])
        # + whi * (the upper column's), so d(out . grad_out)/dz comes from steps^T q, steps being
        # the cells' differences along guidance, at z0 of each column.
        gz1 = self.gz - 1
        steps = np.concatenate((np.diff(cells[..., : self.gz], axis=3), np.diff(cells[..., self.gz :], axis=3)), axis=3)
        t = np.empty((2 * gz1, h, nseg, seg_len), dt)
        np.matmul(np.swapaxes(steps, 2, 3), q_blocks, out=np.moveaxis(t, 0, 2))
        at = self.pixel + np.minimum(np.floor(z), gz1 - 1).astype(np.intp) * self.pixel.size
        t = t.reshape(-1)
        gz = np.multiply(t[at], self.wlo)
        gz += np.multiply(t[at + gz1 * self.pixel.size], self.whi)
        gz *= ((z > 0.0) & (z < gg - 1)) * (gg - 1)  # zero where the guidance is clamped
        gi = np.empty((3, h, nseg, seg_len), dt)
        tmp = np.empty((h, nseg, seg_len), dt)
        for c in range(3):
            o = gi[c]
            np.multiply(gp[0], mats[c], out=o)
            o += np.multiply(gp[1], mats[4 + c], out=tmp)
            o += np.multiply(gp[2], mats[8 + c], out=tmp)
            o += np.multiply(gz, LUMA_WEIGHTS[c], out=tmp)
        return grad_grid, self._unplanes(gi)


@functools.lru_cache(maxsize=32)
def _numpy_slicer(h: int, w: int, grid_shape: Tuple[int, int, int], dtype) -> _NumpySlicer:
    return _NumpySlicer(h, w, grid_shape, dtype)


# What a numpy forward (slice or TV) computed, for its VJP, by ticket (the forward's second
# output): the latest two, up to _SAVED_BYTES in all (a forward whose graph is never
# differentiated leaves its entry until two more come).  A VJP whose entry is gone (or that runs
# twice) recomputes it.
_SAVED: "OrderedDict[int, tuple]" = OrderedDict()
_SAVED_BYTES = 512 * 2**20
_TICKETS = itertools.count()


def _save(saved) -> mx.array:
    """Keep ``saved`` (numpy arrays) for the VJP; the ticket to return as an extra output."""
    ticket = next(_TICKETS) % 2**31
    size = sum(a.nbytes for a in _flat_arrays(saved))
    if size <= _SAVED_BYTES:
        _SAVED[ticket] = (saved, size)
        while len(_SAVED) > 2 or sum(n for _, n in _SAVED.values()) > _SAVED_BYTES:
            _SAVED.popitem(last=False)
    return mx.array(ticket, dtype=mx.int32)


def _saved(ticket: mx.array):
    entry = _SAVED.pop(int(ticket.item()), None)
    return None if entry is None else entry[0]


def _flat_arrays(obj):
    if isinstance(obj, np.ndarray):
        yield obj
    elif isinstance(obj, (list, tuple)):
        for item in obj:
            yield from _flat_arrays(item)


def _numpy_slicer_for(grid: mx.array, image: mx.array) -> _NumpySlicer:
    return _numpy_slicer(image.shape[0], image.shape[1], tuple(grid.shape[:3]), _NUMPY_DTYPES[image.dtype])


@mx.custom_function
def _apply_numpy(grid: mx.array, image: mx.array):
    out, saved = _numpy_slicer_for(grid, image).forward(_numpy(grid), _numpy(image))
    return mx.array(out, dtype=image.dtype), _save(saved)


@_apply_numpy.vjp
def _apply_numpy_vjp(primals, cotangents, outputs):
    grid, image = primals
    s = _numpy_slicer_for(grid, image)
    saved = _saved(outputs[1])
    if saved is None:
        saved = s.forward(_numpy(grid), _numpy(image))[1]
    grad_grid, grad_image = s.backward(saved, _numpy(cotangents[0]))
    return mx.array(grad_grid, dtype=grid.dtype), mx.array(grad_image, dtype=image.dtype)


def _check_inputs(grid: mx.array, image: mx.array) -> Tuple[int, int, int]:
    if grid.ndim != 4 or grid.shape[-1] != 12:
        raise ValueError(f"grid must be (grid_y, grid_x, grid_guidance, 12), got {grid.shape}")
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    return _check_grid_shape(grid.shape[:3])


def slice_affine(grid: mx.array, image: mx.array) -> mx.array:
    """The per-pixel affine matrices ``(H, W, 3, 4)`` sliced from ``grid``."""
    grid_shape = _check_inputs(grid, image)
    s = _slicer(image.shape[0], image.shape[1], grid_shape)
    return s.affine(grid, image).reshape(image.shape[0], image.shape[1], 3, 4)


def apply_grid_reference(grid: mx.array, image: mx.array, *, compiled: bool = False) -> mx.array:
    """:func:`apply_grid` as a plain MLX graph, differentiated by MLX (any order, any transformation).

    Two-stage gathers: the grid interpolated along y per image row, then each
    pixel's four (x, guidance) corners.  The oracle for the numpy kernels and
    their fallback; ``compiled`` wraps it in ``mx.compile`` (no faster inside
    ``mx.grad``: its scatter-add dominates).
    """
    grid_shape = _check_inputs(grid, image)
    s = _slicer(image.shape[0], image.shape[1], grid_shape)
    if grid.dtype != image.dtype:
        grid = grid.astype(image.dtype)
    return (s.compiled if compiled else s.forward)(grid, image)


def apply_grid(grid: mx.array, image: mx.array, *, compiled: bool = True) -> mx.array:
    """Transform ``image (H, W, 3)`` by one bilateral grid ``(gy, gx, gg, 12)``.

    Differentiable (first order) with respect to both arguments.  Float32 and
    float64 run the numpy kernels with their hand-written VJP; inside
    ``mx.compile``/``mx.vmap`` and for other dtypes this is
    :func:`apply_grid_reference` (``compiled`` applies to that path only).
    """
    grid_shape = _check_inputs(grid, image)
    if grid.dtype != image.dtype:
        grid = grid.astype(image.dtype)
    if image.dtype in _NUMPY_DTYPES and _evaluable(grid, image):
        return _apply_numpy(grid, image)[0]
    s = _slicer(image.shape[0], image.shape[1], grid_shape)
    return (s.compiled if compiled else s.forward)(grid, image)


# ----------------------------------------------------------------------------
# total variation
# ----------------------------------------------------------------------------


def _as_stack(params: mx.array) -> mx.array:
    if params.ndim == 4:
        params = params[None]
    if params.ndim != 5 or params.shape[-1] != 12:
        raise ValueError(f"params must be (N, grid_y, grid_x, grid_guidance, 12), got {params.shape}")
    return params


def total_variation_reference(params: mx.array) -> mx.array:
    """:func:`total_variation` as a plain MLX graph (slices, MLX's gradients)."""
    params = _as_stack(params)
    tv = mx.array(0.0, dtype=params.dtype)
    for axis in (1, 2, 3):
        n = params.shape[axis]
        if n < 2:
            continue
        hi = [slice(None)] * 5
        lo = [slice(None)] * 5
        hi[axis] = slice(1, n)
        lo[axis] = slice(0, n - 1)
        d = params[tuple(hi)] - params[tuple(lo)]
        tv = tv + mx.mean(d * d)
    return tv


def _tv_steps(p: np.ndarray, diff: bool = True):
    """For each grid axis of size > 1: (p as 2-D rows spanning that axis, the neighbour stride,
    the differences of neighbours or None)."""
    n, gy, gx, gg, ch = p.shape
    for size, stride in ((gy, gx * gg * ch), (gx, gg * ch), (gg, ch)):
        if size > 1:
            rows = p.reshape(-1, size * stride)
            yield rows, stride, (rows[:, stride:] - rows[:, :-stride]) if diff else None


@mx.custom_function
def _tv_numpy(params: mx.array):
    steps = list(_tv_steps(_numpy(params)))
    total = sum(float(np.vdot(d, d)) / d.size for _, _, d in steps)
    return mx.array(total, dtype=params.dtype), _save([d for _, _, d in steps])


@_tv_numpy.vjp
def _tv_numpy_vjp(primals, cotangents, outputs):
    # One argument: MLX passes the array itself, not a sequence.
    params = primals[0] if isinstance(primals, (list, tuple)) else primals
    p = _numpy(params)
    diffs = _saved(outputs[1])
    steps = list(_tv_steps(p)) if diffs is None else [(rows, stride, d) for (rows, stride, _), d in zip(_tv_steps(p, False), diffs)]
    scale = 2.0 * float(cotangents[0].item())
    grad = np.empty(params.shape, _NUMPY_DTYPES[params.dtype])
    for i, (rows, stride, d) in enumerate(steps):
        g = grad.reshape(rows.shape)
        d *= scale / d.size  # the saved differences are not needed again
        if i == 0:
            g[:, :stride] = 0.0
            g[:, stride:] = d
        else:
            g[:, stride:] += d
        g[:, :-stride] -= d
    if not steps:
        grad[...] = 0.0
    return mx.array(grad, dtype=params.dtype)


def total_variation(params: mx.array) -> mx.array:
    """gsplat's bilateral-grid TV: sum over the grid axes of mean squared steps.

    ``params`` is ``(N, gy, gx, gg, 12)`` (or one grid ``(gy, gx, gg, 12)``).
    Axes of size 1 contribute 0.  Float32/float64 run numpy with a
    hand-written VJP (first order), otherwise :func:`total_variation_reference`.
    """
    params = _as_stack(params)
    if params.dtype in _NUMPY_DTYPES and _evaluable(params):
        return _tv_numpy(params)[0]
    return total_variation_reference(params)


# ----------------------------------------------------------------------------
# the per-image container
# ----------------------------------------------------------------------------


class BilateralGrid:
    """Bilateral grids for ``num_images`` training images.

    ``params`` is a plain ``mx.array`` of shape ``(num_images, gy, gx, gg, 12)``
    (identity at start) that an optimizer can update, e.g.::

        bg = BilateralGrid(len(images))
        opt = mlx.optimizers.Adam(learning_rate=2e-3)

        def loss_fn(params):
            out = bg.apply(render, i, params=params)
            return photometric_loss(out, gt) + 10.0 * bg.tv_loss(params)

        loss, g = mx.value_and_grad(loss_fn)(bg.params)
        bg.update(opt.apply_gradients({"params": g}, bg.parameters()))

    ``apply`` and ``tv_loss`` read ``self.params`` unless ``params`` is passed
    (pass it to differentiate with respect to the grids).  ``apply`` also takes
    the image's own grid ``(gy, gx, gg, 12)`` as ``params``: differentiating
    with respect to that grid alone, with its TV and :class:`GridAdam`, keeps
    a training step's cost independent of the number of images::

        opt = GridAdam(learning_rate=2e-3)
        grid = opt.current(bg, i)  # image i's grid, up to date

        def loss_fn(grid):
            out = bg.apply(render, i, grid)
            return photometric_loss(out, gt) + 10.0 * bg.tv_loss(grid)

        loss, g = mx.value_and_grad(loss_fn)(grid)
        opt.update(bg, i, g)
    """

    def __init__(self, num_images: int, grid_shape: Sequence[int] = DEFAULT_GRID_SHAPE):
        num_images = int(num_images)
        if num_images < 1:
            raise ValueError(f"num_images must be >= 1, got {num_images}")
        shape = _check_grid_shape(grid_shape)
        self.params = mx.array(np.broadcast_to(_IDENTITY_3x4, (num_images, *shape, 12)).copy())

    # -- shape ------------------------------------------------------------------

    @property
    def num_images(self) -> int:
        return int(self.params.shape[0])

    @property
    def grid_shape(self) -> Tuple[int, int, int]:
        return tuple(int(s) for s in self.params.shape[1:4])

    def __repr__(self) -> str:
        return f"BilateralGrid(num_images={self.num_images}, grid_shape={self.grid_shape})"

    # -- optimisation -----------------------------------------------------------

    def parameters(self) -> Dict[str, mx.array]:
        """``{"params": params}``: the tree that optimizers take."""
        return {"params": self.params}

    def update(self, tree: Dict[str, mx.array]) -> None:
        """Replace ``params`` from a tree like :meth:`parameters`' result."""
        new = tree["params"]
        if tuple(new.shape) != tuple(self.params.shape):
            raise ValueError(f"params shape {new.shape} != {self.params.shape}")
        self.params = new

    def apply(self, image: mx.array, index: int, params: Optional[mx.array] = None, *, compiled: bool = True) -> mx.array:
        """Transform ``image (H, W, 3)`` with the grid of training image ``index``.

        ``params``: the stacked grids ``(num_images, gy, gx, gg, 12)`` (default
        ``self.params``) or image ``index``'s own grid ``(gy, gx, gg, 12)``.
        ``compiled`` only matters where :func:`apply_grid` falls back to the
        MLX graph.
        """
        p = self.params if params is None else params
        index = int(index)
        count = self.num_images if p.ndim == 4 else p.shape[0]
        if not -count <= index < count:
            raise IndexError(f"image index {index} out of range for {count} grids")
        return apply_grid(p if p.ndim == 4 else p[index], image, compiled=compiled)

    def tv_loss(self, params: Optional[mx.array] = None) -> mx.array:
        """Total variation (see :func:`total_variation`) of all grids, or of the one grid passed."""
        return total_variation(self.params if params is None else params)

    def reset(self, index: Optional[int] = None) -> None:
        """Set one grid (or all) back to the identity."""
        ident = np.broadcast_to(_IDENTITY_3x4, (*self.grid_shape, 12))
        if index is None:
            self.params = mx.array(np.broadcast_to(ident, self.params.shape).copy())
        else:
            p = np.array(self.params)
            p[int(index)] = ident
            self.params = mx.array(p)

    # -- checkpoints --------------------------------------------------------------

    def state_dict(self) -> Dict[str, np.ndarray]:
        """Numpy state: ``{"params": float32 (N, gy, gx, gg, 12)}``."""
        return {"params": np.array(self.params, dtype=np.float32)}

    def load_state_dict(self, state: Dict[str, np.ndarray]) -> None:
        """Load :meth:`state_dict` output (the number of images and grid shape
        are taken from it)."""
        p = np.asarray(state["params"], dtype=np.float32)
        if p.ndim != 5 or p.shape[-1] != 12:
            raise ValueError(f"bilateral grid params must be (N, gy, gx, gg, 12), got {p.shape}")
        _check_grid_shape(p.shape[1:4])
        self.params = mx.array(p)

    @classmethod
    def from_state_dict(cls, state: Dict[str, np.ndarray]) -> "BilateralGrid":
        p = np.asarray(state["params"])
        bg = cls(p.shape[0], p.shape[1:4])
        bg.load_state_dict(state)
        return bg

    def save(self, path: str | os.PathLike) -> None:
        """Write the state to an ``.npz`` file (atomically)."""
        with atomic_write(path) as f:
            np.savez(f, **self.state_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "BilateralGrid":
        with np.load(path) as data:
            return cls.from_state_dict({k: data[k] for k in data.files})


# ----------------------------------------------------------------------------
# Adam for per-image grids
# ----------------------------------------------------------------------------


def warmup_decay(total_steps: int, warmup_steps: int = 1000, start: float = 0.01, final: float = 0.01):
    """Learning-rate multiplier for step ``t`` (1-based): a linear warm-up from ``start`` to 1 over
    ``warmup_steps``, times an exponential decay to ``final`` at ``total_steps`` (gsplat's
    schedule for the grids).  The warm-up keeps the grids from taking on the colour of a scene
    that has no geometry yet; the decay settles them once it has.
    """
    if total_steps < 1 or warmup_steps < 0 or not (0.0 < start <= 1.0) or not (0.0 < final <= 1.0):
        raise ValueError(f"warmup_decay: need total_steps >= 1, warmup_steps >= 0 and start, final in (0, 1], "
                         f"got {total_steps}, {warmup_steps}, {start}, {final}")

    def factor(t: np.ndarray) -> np.ndarray:
        s = np.asarray(t, np.float64) - 1.0  # steps taken before this one
        warm = 1.0 if warmup_steps == 0 else start + (1.0 - start) * np.minimum(s / warmup_steps, 1.0)
        return warm * final ** (s / total_steps)

    return factor


class GridAdam:
    """Adam over a :class:`BilateralGrid`'s stacked grids that touches one grid per step.

    The same update as ``mlx3d.training.adam.Adam({"grid": lr})`` applied to
    the whole ``(num_images, ...)`` stack every step, with a zero gradient for
    every grid but the stepped one, at the cost of one grid.  A grid without
    gradient is not left alone by Adam: its moments decay (``m *= beta1``,
    ``v *= beta2``) and it keeps moving by ``lr * m_hat / (sqrt(v_hat) + eps)``.
    Those steps are applied in closed form when the grid is next read
    (:meth:`current`, :meth:`update`, :meth:`sync`), equal to the step-by-step
    result up to float32 rounding.  Skipping them instead (a "sparse" Adam)
    would change the optimiser, not just its cost: with images drawn one at a
    time, the momentum tail after a gradient is about nine tenths of the move
    it causes (``beta1 = 0.9``), so the grids would learn several times slower.

    The premise is that the loss reads one grid: the stepped image's slice and
    the TV of that grid, ``tv_loss(grid)``.  That is the one change from
    gsplat's trainer, whose loss has the TV of all grids every step, so that
    every grid gets a (small) gradient every step.  ``lambda * tv(grid_i)`` on
    the stepped grid has the same expected gradient per grid (``tv(all) =
    mean_i tv(grid_i)``, and each image is drawn once per ``num_images`` steps
    on average) but arrives together with the image's data gradient instead of
    spread over the steps in between, so Adam (which normalises per element)
    sees a different sequence: the same regulariser in expectation, not the
    same trajectory.

    ``schedule`` maps step numbers to a learning-rate multiplier (e.g.
    :func:`warmup_decay`); the closed form sums the scheduled rates.

    Use: ``grid = opt.current(bg, i)`` before building the loss (the grid with
    its pending steps applied), ``opt.update(bg, i, grad)`` after, and
    ``opt.sync(bg)`` before reading ``bg.params`` as a whole (checkpoints,
    export, evaluation).  ``state_dict``/``load_state_dict`` round-trip
    exactly (pending steps included) and load ``Adam``'s ``step_count``,
    ``m/grid``, ``v/grid`` state as well.
    """

    def __init__(self, learning_rate: float, betas=(0.9, 0.999), eps: float = 1e-15,
                 schedule: Optional[Callable[[np.ndarray], np.ndarray]] = None):
        self.lr = float(learning_rate)
        self.schedule = schedule  # step t (1-based, int array) -> lr multiplier; None: constant
        self.b1, self.b2 = (float(b) for b in betas)
        self.eps = float(eps)
        self.step_count = 0
        self.m: Optional[np.ndarray] = None  # (num_images, gy, gx, gg, 12) float32
        self.v: Optional[np.ndarray] = None
        self.last: Optional[np.ndarray] = None  # (num_images,): the step each grid and its moments are at
        # The j-th zero-gradient step moves a grid by ~ (beta1 / sqrt(beta2))^j times the first: the
        # steps that matter (to 1e-12) are the first `_horizon` (all of them if that does not decay).
        ratio = self.b1 / np.sqrt(self.b2)
        if ratio <= 0.0:
            self._horizon = 0
        elif ratio < 1.0:
            self._horizon = int(np.ceil(np.log(1e-12) / np.log(ratio)))
        else:
            self._horizon = np.iinfo(np.int64).max

    def _state(self, bg: BilateralGrid) -> None:
        shape = tuple(bg.params.shape)
        if self.m is None:
            self.m = np.zeros(shape, np.float32)
            self.v = np.zeros(shape, np.float32)
        elif self.m.shape != shape:
            raise ValueError(f"optimizer state is for grids {self.m.shape}, not {shape}")
        if self.last is None:
            self.last = np.full(shape[0], self.step_count, np.int64)

    def _index(self, bg: BilateralGrid, index: int) -> int:
        n = bg.num_images
        index = int(index)
        if not -n <= index < n:
            raise IndexError(f"image index {index} out of range for {n} grids")
        return index % n

    def _pending(self, indices: np.ndarray, start: int) -> np.ndarray:
        """Parameter change of grids ``indices`` over the zero-gradient steps start+1..step_count."""
        k = self.step_count - start
        j = np.arange(1, min(k, self._horizon) + 1, dtype=np.float64)
        m = self.m[indices].astype(np.float64)
        if j.size == 0 or not m.any():
            return np.zeros_like(m)
        t = start + j
        # step j: m_j = b1^j m, v_j = b2^j v -> lr * (m_j / c1) / (sqrt(v_j / c2) + eps)
        #       = m * alpha_j / (beta_j * sqrt(v) + eps)
        alpha = self._lrs(t) * self.b1**j / (1.0 - self.b1**t)
        beta = self.b2 ** (j / 2) / np.sqrt(1.0 - self.b2**t)
        u = np.sqrt(self.v[indices].astype(np.float64))
        out = np.zeros_like(m)
        # sqrt(v) well above eps: expand 1 / (beta u + eps) in eps / (beta u) (third order, < 1e-9).
        big = u * beta.min() > 1e3 * self.eps
        if big.any():
            ub = u[big]
            p1, p2, p3 = (np.sum(alpha / beta**n) for n in (1, 2, 3))
            out[big] = m[big] * (p1 / ub - self.eps * p2 / ub**2 + self.eps**2 * p3 / ub**3)
        small = ~big & (m != 0.0)
        if small.any():  # rare (gradients below ~1e-11): the sum itself
            us = u[small][:, None]
            out[small] = m[small] * np.sum(alpha / (beta * us + self.eps), axis=1)
        return out

    def _lrs(self, t: np.ndarray) -> np.ndarray:
        """Learning rates of steps ``t`` (1-based)."""
        if self.schedule is None:
            return np.full(np.shape(t), self.lr)
        return self.lr * np.asarray(self.schedule(np.asarray(t, np.int64)), np.float64)

    def _catch_up(self, bg: BilateralGrid, indices: np.ndarray) -> None:
        """Apply the pending zero-gradient steps of grids ``indices`` (distinct)."""
        indices = np.asarray(indices, np.intp)
        stale = indices[self.last[indices] < self.step_count]
        if stale.size == 0:
            return
        params = np.array(bg.params[mx.array(stale)], dtype=np.float64)
        for start in np.unique(self.last[stale]):
            sel = self.last[stale] == start
            group = stale[sel]
            k = self.step_count - int(start)
            params[sel] -= self._pending(group, int(start))
            self.m[group] *= np.float32(self.b1**k)
            self.v[group] *= np.float32(self.b2**k)
        self.last[stale] = self.step_count
        bg.params = _set_grids(bg.params, stale, params.astype(np.float32))

    def current(self, bg: BilateralGrid, index: int) -> mx.array:
        """Grid ``index`` ``(gy, gx, gg, 12)`` with its pending steps applied (also in ``bg.params``)."""
        self._state(bg)
        i = self._index(bg, index)
        self._catch_up(bg, np.array([i]))
        return bg.params[i]

    def update(self, bg: BilateralGrid, index, grad) -> None:
        """One Adam step: ``grad (gy, gx, gg, 12)`` for grid ``index``, zero for every other grid.

        ``index`` may also be a sequence of distinct grids, with ``grad`` their gradients stacked
        ``(k, gy, gx, gg, 12)`` (a batch of views of different images: still one step)."""
        self._state(bg)
        single = np.ndim(index) == 0
        rows = np.array([self._index(bg, i) for i in np.atleast_1d(index)], np.intp)
        if len(np.unique(rows)) != len(rows):
            raise ValueError(f"grid indices must be distinct, got {rows.tolist()}")
        g = np.asarray(np.array(grad), dtype=np.float32)
        if single:
            g = g[None]
        if g.shape != (len(rows),) + self.m.shape[1:]:
            raise ValueError(f"gradient shape {g.shape[1:] if single else g.shape} != grid shape "
                             f"{self.m.shape[1:] if single else (len(rows),) + self.m.shape[1:]}")
        self._catch_up(bg, rows)
        self.step_count += 1
        c1 = 1.0 - self.b1**self.step_count
        c2 = 1.0 - self.b2**self.step_count
        # The float32 arithmetic of mlx3d.training.adam.Adam.update, in its order.
        m = self.b1 * self.m[rows] + (1 - self.b1) * g
        v = self.b2 * self.v[rows] + (1 - self.b2) * g * g
        self.m[rows], self.v[rows] = m, v
        p = np.array(bg.params[mx.array(rows)])
        lr = self.lr if self.schedule is None else float(self._lrs(np.array([self.step_count]))[0])
        p = p - lr * (m / c1) / (np.sqrt(v / c2) + np.float32(self.eps))
        self.last[rows] = self.step_count
        bg.params = _set_grids(bg.params, rows, p)

    def sync(self, bg: BilateralGrid) -> None:
        """Apply every grid's pending steps, so that ``bg.params`` is what step-by-step Adam would hold."""
        self._state(bg)
        self._catch_up(bg, np.arange(bg.num_images))

    def state_dict(self) -> Dict[str, np.ndarray]:
        """Numpy state; ``step_count``, ``m/grid``, ``v/grid`` as ``Adam``'s, and ``last``."""
        out = {"step_count": np.array(self.step_count)}
        if self.m is not None:
            out.update({"m/grid": self.m.copy(), "v/grid": self.v.copy(), "last": self.last.copy()})
        return out

    def load_state_dict(self, state: Dict[str, np.ndarray]) -> None:
        """Load :meth:`state_dict` output, or ``Adam``'s (whose grids are all current)."""
        self.step_count = int(state["step_count"])
        if "m/grid" in state:
            self.m = np.array(state["m/grid"], dtype=np.float32)
            self.v = np.array(state["v/grid"], dtype=np.float32)
            last = state.get("last")
            self.last = np.full(self.m.shape[0], self.step_count, np.int64) if last is None else np.array(last, np.int64)
        else:
            self.m = self.v = self.last = None


def _set_grids(params: mx.array, indices: np.ndarray, grids: np.ndarray) -> mx.array:
    """``params`` with grids ``indices`` replaced (a new array; MLX reuses the buffer when it can)."""
    new = mx.array(grids, dtype=params.dtype)
    if np.array_equal(indices, np.arange(params.shape[0])):
        return new
    for row, i in enumerate(np.asarray(indices).tolist()):
        params = mx.slice_update(params, new[row : row + 1], mx.array([i]), axes=(0,))
    return params
