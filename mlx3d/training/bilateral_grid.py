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

Implementation: the grid is first interpolated along y for every image row
(``(H, gx, gg, 12)``, small), then each pixel gathers its four (x, guidance)
corners from that table and blends them.  Gradients come from MLX's own
rules (the gathers' VJP is a scatter-add); a hand-written VJP measured no
faster on the CPU backend.
"""

from __future__ import annotations

import functools
import os
from typing import Dict, Optional, Sequence, Tuple

import mlx.core as mx
import numpy as np

from ..io.atomic import atomic_write

__all__ = [
    "LUMA_WEIGHTS",
    "DEFAULT_GRID_SHAPE",
    "identity_grid",
    "slice_affine",
    "apply_grid",
    "total_variation",
    "BilateralGrid",
]

# BT.601 RGB -> luma, as gsplat's rgb2gray.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)
DEFAULT_GRID_SHAPE = (16, 16, 8)  # (grid_y, grid_x, grid_guidance)

_IDENTITY_3x4 = np.array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], np.float32)


def _check_grid_shape(grid_shape) -> Tuple[int, int, int]:
    shape = tuple(int(s) for s in grid_shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"grid_shape must be three positive sizes (y, x, guidance), got {grid_shape}")
    return shape


def identity_grid(grid_shape: Sequence[int] = DEFAULT_GRID_SHAPE) -> mx.array:
    """One grid ``(gy, gx, gg, 12)`` of identity transforms."""
    gy, gx, gg = _check_grid_shape(grid_shape)
    return mx.array(np.broadcast_to(_IDENTITY_3x4, (gy, gx, gg, 12)).copy())


# ----------------------------------------------------------------------------
# slicing
# ----------------------------------------------------------------------------


def _axis_lerp(n_pix: int, n_cells: int):
    """Pixel-centre coordinates on one axis: lower/upper cell and weight."""
    t = (np.arange(n_pix, dtype=np.float64) + 0.5) / n_pix * (n_cells - 1)
    lo = np.clip(np.floor(t), 0, n_cells - 1).astype(np.int32)
    hi = np.minimum(lo + 1, n_cells - 1).astype(np.int32)
    return lo, hi, t - lo


class _Slicer:
    """Static index data and the slicing graph for one (H, W, grid) shape."""

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
        # Interpolate along y once per image row: (H, gx, gg, 12).  The
        # gather's VJP (a scatter-add of H rows) is cheap.
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


def apply_grid(grid: mx.array, image: mx.array, *, compiled: bool = True) -> mx.array:
    """Transform ``image (H, W, 3)`` by one bilateral grid ``(gy, gx, gg, 12)``.

    Differentiable with respect to both arguments.  The graph is
    ``mx.compile``-d (MLX runs it uncompiled while a transformation such as
    ``mx.grad`` traces it; compile the whole training step to fuse that too).
    """
    grid_shape = _check_inputs(grid, image)
    s = _slicer(image.shape[0], image.shape[1], grid_shape)
    if grid.dtype != image.dtype:
        grid = grid.astype(image.dtype)
    return (s.compiled if compiled else s.forward)(grid, image)


def total_variation(params: mx.array) -> mx.array:
    """gsplat's bilateral-grid TV: sum over the grid axes of mean squared steps.

    ``params`` is ``(N, gy, gx, gg, 12)`` (or one grid ``(gy, gx, gg, 12)``).
    Axes of size 1 contribute 0.
    """
    if params.ndim == 4:
        params = params[None]
    if params.ndim != 5 or params.shape[-1] != 12:
        raise ValueError(f"params must be (N, grid_y, grid_x, grid_guidance, 12), got {params.shape}")
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
    (pass it to differentiate with respect to the grids).
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
        """Transform ``image (H, W, 3)`` with the grid of training image ``index``."""
        p = self.params if params is None else params
        index = int(index)
        if not -p.shape[0] <= index < p.shape[0]:
            raise IndexError(f"image index {index} out of range for {p.shape[0]} grids")
        return apply_grid(p[index], image, compiled=compiled)

    def tv_loss(self, params: Optional[mx.array] = None) -> mx.array:
        """Total variation of all grids (see :func:`total_variation`)."""
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
