"""Real spherical harmonics in the 3D Gaussian Splatting convention.

Coefficient layout (as in the 3DGS PLY format and training code): a splat's
view-dependent colour is ``sh`` of shape ``(..., K, 3)`` with
``K = (degree + 1) ** 2`` coefficients per colour channel, channel last, in the
order

* ``0``        DC term (band 0),
* ``1 .. 3``   band 1,
* ``4 .. 8``   band 2,
* ``9 .. 15``  band 3.

The model stores the DC part as ``sh_dc (N, 1, 3)`` and the rest as
``sh_rest (N, K - 1, 3)``.  The colour seen along the unit direction ``d``
(camera centre -> splat) is ``sum_k Y_k(d) * sh[k] + 0.5``; clamping is left
to the renderer.

The basis constants, their order and their signs follow the reference
implementation of 3D Gaussian Splatting (graphdeco-inria/gaussian-splatting,
``utils/sh_utils.py``, identical to ``computeColorFromSH`` in
graphdeco-inria/diff-gaussian-rasterization), itself derived from PlenOctrees.

Rotating a splat by an orthogonal ``R`` (positions ``x -> R x``) must carry its
view-dependent colour along: :func:`sh_rotation` returns, per band ``l``, the
matrix ``D_l`` with ``colour(D_l c, R d) == colour(c, d)`` for every direction,
and :func:`rotate_sh` applies it to ``sh_rest``.
"""

from __future__ import annotations

import functools
import operator
from typing import Any, List

import mlx.core as mx
import numpy as np

from mlx3d.errors import TransformError

__all__ = [
    "C0",
    "C1",
    "C2",
    "C3",
    "MAX_SH_DEGREE",
    "num_sh_bases",
    "sh_degree_from_bases",
    "sh_basis",
    "eval_sh",
    "rgb_to_sh",
    "sh_to_rgb",
    "sh_rotation",
    "rotate_sh",
]

# Constants of the 3DGS reference implementation (graphdeco-inria
# gaussian-splatting, utils/sh_utils.py; same values as SH_C0..SH_C3 in
# diff-gaussian-rasterization's computeColorFromSH).
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

MAX_SH_DEGREE = 3

# Guard added to |d|^2 before the inverse square root: invisible for unit-ish
# directions in float32, keeps zero vectors finite (they map to 0).
_NORM_EPS = 1e-12

# Largest accepted max |R^T R - I| for a matrix to count as orthogonal.
_ORTHO_TOL = 1e-5


# ----------------------------------------------------------------------------
# degree <-> number of coefficients
# ----------------------------------------------------------------------------


def _as_int(value: Any, what: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{what} must be an integer, got {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{what} must be an integer, got {value!r}") from None


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree``: ``(degree+1)**2``.

    Raises ``ValueError`` if ``degree`` is not an integer in ``0..3``.
    """
    d = _as_int(degree, "SH degree")
    if not 0 <= d <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {d}")
    return (d + 1) ** 2


def sh_degree_from_bases(num_bases: int) -> int:
    """Inverse of :func:`num_sh_bases`: 1 -> 0, 4 -> 1, 9 -> 2, 16 -> 3.

    Raises ``ValueError`` naming ``num_bases`` for any other value.
    """
    k = _as_int(num_bases, "number of SH coefficients")
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(
        f"number of SH coefficients per channel must be one of 1, 4, 9, 16 "
        f"(degree 0..{MAX_SH_DEGREE}), got K={k}"
    )


# ----------------------------------------------------------------------------
# numpy / mlx dispatch (the only library-specific calls live here)
# ----------------------------------------------------------------------------


def _is_mx(*xs: Any) -> bool:
    return any(isinstance(x, mx.array) for x in xs)


def _to_backend(x: Any, use_mx: bool):
    """Return ``x`` as an ``mx.array`` (``use_mx``) or ``np.ndarray``."""
    if use_mx:
        return x if isinstance(x, mx.array) else mx.array(np.asarray(x))
    return x if isinstance(x, np.ndarray) else np.asarray(x)


def _concat_last(parts: list, use_mx: bool):
    return mx.concatenate(parts, axis=-1) if use_mx else np.concatenate(parts, axis=-1)


def _full_like(x, value: float, use_mx: bool):
    if use_mx:
        return mx.full(x.shape, value, dtype=x.dtype)
    return np.full_like(x, value)


def _broadcast_to(x, shape: tuple, use_mx: bool):
    if tuple(x.shape) == tuple(shape):
        return x
    return mx.broadcast_to(x, shape) if use_mx else np.broadcast_to(x, shape).copy()


# ----------------------------------------------------------------------------
# basis
# ----------------------------------------------------------------------------


def _unit_components(dirs):
    """``x, y, z`` of ``dirs / |dirs|`` as ``(..., 1)`` arrays (epsilon-guarded)."""
    x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
    inv_norm = (x * x + y * y + z * z + _NORM_EPS) ** -0.5
    return x * inv_norm, y * inv_norm, z * inv_norm


def _higher_terms(degree: int, x, y, z) -> list:
    """Basis functions 1 .. (degree+1)**2 - 1 at unit ``(x, y, z)``, in 3DGS order.

    Only the bands up to ``degree`` are evaluated.
    """
    terms: list = []
    if degree < 1:
        return terms
    terms += [-C1 * y, C1 * z, -C1 * x]
    if degree < 2:
        return terms
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    terms += [
        C2[0] * xy,
        C2[1] * yz,
        C2[2] * (2.0 * zz - xx - yy),
        C2[3] * xz,
        C2[4] * (xx - yy),
    ]
    if degree < 3:
        return terms
    terms += [
        C3[0] * y * (3.0 * xx - yy),
        C3[1] * xy * z,
        C3[2] * y * (4.0 * zz - xx - yy),
        C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        C3[4] * x * (4.0 * zz - xx - yy),
        C3[5] * z * (xx - yy),
        C3[6] * x * (xx - 3.0 * yy),
    ]
    return terms


def _check_dirs(dirs) -> None:
    if dirs.ndim < 1 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have shape (..., 3), got {tuple(dirs.shape)}")


def sh_basis(degree: int, dirs):
    """Real SH basis values ``(..., (degree+1)**2)`` at directions ``dirs (..., 3)``.

    ``dirs`` need not be normalised (they are, with an epsilon guard, so a zero
    vector gives finite values).  Works for ``numpy.ndarray`` and
    ``mlx.core.array`` and returns the same type.
    """
    num_sh_bases(degree)
    use_mx = _is_mx(dirs)
    dirs = _to_backend(dirs, use_mx)
    _check_dirs(dirs)
    x, y, z = _unit_components(dirs)
    parts = [_full_like(x, C0, use_mx)] + _higher_terms(degree, x, y, z)
    return _concat_last(parts, use_mx)


def eval_sh(degree: int, sh, dirs):
    """Colour ``(..., C)`` of SH coefficients ``sh (..., K, C)`` along ``dirs (..., 3)``.

    ``colour = sum_{k < (degree+1)**2} Y_k(d) * sh[..., k, :] + 0.5`` with the
    3DGS basis; no clamping.  ``K`` may exceed ``(degree+1)**2`` (the extra
    coefficients are ignored); fewer raises ``ValueError``.  ``dirs`` is
    normalised internally and broadcasts against the batch shape of ``sh``.

    Accepts ``numpy.ndarray`` or ``mlx.core.array`` (if either input is an mlx
    array the result is one, and it is differentiable with ``mx.grad``).
    """
    k_needed = num_sh_bases(degree)
    use_mx = _is_mx(sh, dirs)
    sh = _to_backend(sh, use_mx)
    dirs = _to_backend(dirs, use_mx)
    if sh.ndim < 2:
        raise ValueError(f"sh must have shape (..., K, 3), got {tuple(sh.shape)}")
    _check_dirs(dirs)
    if sh.shape[-2] < k_needed:
        raise ValueError(
            f"SH degree {degree} needs K >= {k_needed} coefficients per channel, "
            f"got sh with shape {tuple(sh.shape)} (K={sh.shape[-2]})"
        )

    result = C0 * sh[..., 0, :]
    if degree == 0:
        # Keep the output shape independent of the degree: broadcast over dirs.
        shape = np.broadcast_shapes(tuple(result.shape), tuple(dirs.shape[:-1]) + (1,))
        return _broadcast_to(result + 0.5, shape, use_mx)

    x, y, z = _unit_components(dirs)
    for k, term in enumerate(_higher_terms(degree, x, y, z), start=1):
        result = result + term * sh[..., k, :]
    return result + 0.5


def rgb_to_sh(rgb):
    """DC coefficient whose colour is ``rgb``: ``(rgb - 0.5) / C0``."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh_dc):
    """Colour of the DC coefficient alone: ``sh_dc * C0 + 0.5``."""
    return sh_dc * C0 + 0.5


# ----------------------------------------------------------------------------
# rotation
# ----------------------------------------------------------------------------


def _band_slice(band: int) -> slice:
    """Columns of band ``band`` (>= 1) inside ``sh_rest`` (which starts at band 1)."""
    start = band * band - 1
    return slice(start, start + 2 * band + 1)


def _band_basis_np(band: int, points: np.ndarray) -> np.ndarray:
    """Band ``band`` basis ``(n, 2*band+1)`` at unit rows of ``points``, float64."""
    x, y, z = _unit_components(np.asarray(points, dtype=np.float64))
    terms = _higher_terms(band, x, y, z)
    return np.concatenate(terms[_band_slice(band)], axis=-1)


@functools.lru_cache(maxsize=None)
def _band_fit(band: int):
    """Sample directions ``E (n, 3)`` and the pseudo-inverse of ``Y_band(E)``.

    ``E`` is a 64-point Fibonacci sphere: far more than the ``2*band+1``
    points needed to pin down a band-``band`` function, and well spread, so
    ``Y_band(E)`` has full column rank and a small condition number.
    """
    n = 64
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    e = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
    pinv = np.linalg.pinv(_band_basis_np(band, e))
    e.setflags(write=False)
    pinv.setflags(write=False)
    return e, pinv


def _validate_orthogonal(R: Any) -> np.ndarray:
    if isinstance(R, mx.array):
        R = np.array(R.astype(mx.float32) if R.dtype == mx.bfloat16 else R)
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise TransformError(f"R must be a 3x3 matrix, got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise TransformError("R contains NaN or Inf")
    deviation = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if deviation > _ORTHO_TOL:
        raise TransformError(
            f"R is not orthogonal: max |R^T R - I| = {deviation:.3e} "
            f"(tolerance {_ORTHO_TOL:g})"
        )
    return R


def sh_rotation(R, degree: int = MAX_SH_DEGREE) -> List[np.ndarray]:
    """Per-band SH transformation matrices for the orthogonal map ``R``.

    Returns ``[D1 (3x3), D2 (5x5), D3 (7x7)]`` (bands ``1..degree``; an empty
    list for degree 0) as float64 numpy arrays such that, for the coefficients
    ``c`` of band ``l`` (one column per colour channel, 3DGS order),
    ``Y_l(R d) . (D_l c) == Y_l(d) . c`` for every direction ``d``.  ``R`` may be
    a rotation or a reflection (``det R = -1``).

    Method: each band's span is closed under orthogonal maps, so
    ``Y_l(R^T e) = Y_l(e) D_l`` holds identically in ``e``; ``D_l`` is obtained
    by evaluating both sides on a fixed set of sample directions and solving by
    a pre-computed pseudo-inverse (exact up to float64 rounding).  The
    resulting matrices are orthogonal and satisfy
    ``D(R1 @ R2) == D(R1) @ D(R2)``.

    Raises ``TransformError`` (a ``ValueError``) if ``R`` is not a finite 3x3
    orthogonal matrix (tolerance 1e-5 on ``max |R^T R - I|``), ``ValueError``
    for a degree outside ``0..3``.
    """
    num_sh_bases(degree)
    R = _validate_orthogonal(R)
    mats = []
    for band in range(1, int(degree) + 1):
        e, pinv = _band_fit(band)
        # rows of e @ R are (R^T e_i)^T
        mats.append(pinv @ _band_basis_np(band, e @ R))
    return mats


def rotate_sh(sh_rest, R):
    """Transform ``sh_rest (..., K-1, C)`` (bands 1..degree) for the map ``x -> R x``.

    The degree is inferred from ``K``; each band block is multiplied by the
    matching :func:`sh_rotation` matrix, so that with the DC term unchanged
    ``eval_sh(deg, [dc, rotate_sh(rest, R)], R d) == eval_sh(deg, [dc, rest], d)``.
    The rotation matrices are computed in float64 and applied in the input's
    precision (float64 input stays float64; others use float32, whose error
    of ~1e-7 is below float32 storage); returns the input's array type (numpy
    or mlx) and floating dtype (non-floating input gives float64 numpy /
    float32 mlx).
    ``K - 1 == 0`` returns an unchanged copy.  The mlx path goes through numpy
    and is not differentiable (this is a data edit, not a training op).
    """
    use_mx = _is_mx(sh_rest)
    if use_mx:
        dtype = sh_rest.dtype
        if not mx.issubdtype(dtype, mx.floating):
            dtype = mx.float32
        src = sh_rest.astype(mx.float32) if sh_rest.dtype == mx.bfloat16 else sh_rest
        x = np.asarray(src, dtype=np.float32)
    else:
        arr = np.asarray(sh_rest)
        dtype = arr.dtype if np.issubdtype(arr.dtype, np.floating) else np.dtype(np.float64)
        x = np.asarray(arr, dtype=np.float64 if dtype == np.float64 else np.float32)
    if x.ndim < 2:
        raise ValueError(f"sh_rest must have shape (..., K-1, 3), got {x.shape}")
    degree = sh_degree_from_bases(x.shape[-2] + 1)
    mats = sh_rotation(R, degree)

    if degree == 0:
        out = x.copy()
    else:
        # one GEMM with the block-diagonal matrix of all bands: rows are (splat, channel)
        k1 = x.shape[-2]
        full = np.zeros((k1, k1), dtype=x.dtype)
        for band, D in enumerate(mats, start=1):
            sl = _band_slice(band)
            full[sl, sl] = D
        xt = np.ascontiguousarray(np.swapaxes(x, -1, -2))  # (..., C, K-1)
        out = np.swapaxes((xt.reshape(-1, k1) @ full.T).reshape(xt.shape), -1, -2)

    if use_mx:
        return mx.array(out, dtype=dtype)
    return out.astype(dtype, copy=False)
