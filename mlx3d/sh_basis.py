"""Real SH basis of 3D Gaussian Splatting and its rotation (numpy only, no MLX).

Shared by :mod:`mlx3d.splatting.sh` (which re-exports these names and adds
the MLX paths) and the file codecs in :mod:`mlx3d.io`, which must import
without MLX.  Layout and conventions are those of :mod:`mlx3d.splatting.sh`:
``sh_rest (..., K-1, C)`` holds bands ``1..degree`` (``K = (degree+1)**2``),
band ``l`` at rows ``l*l-1 .. l*l+2*l-1``, in the 3DGS order and signs
(graphdeco-inria/gaussian-splatting ``utils/sh_utils.py``).

The arithmetic helpers :func:`_unit_components` and :func:`_higher_terms` use
only operators and slicing, so they also take MLX arrays.
"""

from __future__ import annotations

import functools
import operator
from typing import Any, List

import numpy as np

from .errors import TransformError

__all__ = [
    "C0",
    "C1",
    "C2",
    "C3",
    "MAX_SH_DEGREE",
    "num_sh_bases",
    "sh_degree_from_bases",
    "sh_rotation",
    "sh_rest_rotation",
    "rotate_sh_rest",
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
# basis (generic arithmetic: numpy or MLX arrays)
# ----------------------------------------------------------------------------


def _unit_components(dirs):
    """``x, y, z`` of ``dirs (..., 3) / |dirs|`` as ``(..., 1)`` arrays (epsilon-guarded)."""
    x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
    inv_norm = (x * x + y * y + z * z + _NORM_EPS) ** -0.5
    return x * inv_norm, y * inv_norm, z * inv_norm


def _higher_terms(degree: int, x, y, z) -> list:
    """Basis functions 1 .. (degree+1)**2 - 1 at unit ``(x, y, z)``, in 3DGS order.

    Only the bands up to ``degree`` are evaluated; each term has the shape of ``x``.
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


# ----------------------------------------------------------------------------
# rotation (numpy)
# ----------------------------------------------------------------------------


def _band_slice(band: int) -> slice:
    """Rows of band ``band`` (>= 1) inside ``sh_rest`` (which starts at band 1)."""
    start = band * band - 1
    return slice(start, start + 2 * band + 1)


def _band_basis_np(band: int, points: np.ndarray) -> np.ndarray:
    """Band ``band`` basis ``(n, 2*band+1)`` at unit rows of ``points (n, 3)``, float64."""
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
    """``R`` as a float64 ``(3, 3)`` array; ``TransformError`` unless finite and orthogonal."""
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


def sh_rest_rotation(R, degree: int = MAX_SH_DEGREE) -> np.ndarray:
    """Block-diagonal ``(K-1, K-1)`` float64 matrix of :func:`sh_rotation` ``(R, degree)``.

    ``sh_rest (K-1, C)`` of the map ``x -> R x`` is ``D @ sh_rest``; ``(0, 0)``
    for degree 0.  Raises as :func:`sh_rotation`.
    """
    mats = sh_rotation(R, degree)
    k1 = num_sh_bases(degree) - 1
    full = np.zeros((k1, k1))
    for band, D in enumerate(mats, start=1):
        sl = _band_slice(band)
        full[sl, sl] = D
    return full


def rotate_sh_rest(sh_rest, R) -> np.ndarray:
    """Transform numpy ``sh_rest (..., K-1, C)`` (bands 1..degree) for the map ``x -> R x``.

    The degree is inferred from ``K``; the float64 :func:`sh_rest_rotation`
    matrix is applied in the input's precision (float64 stays float64, other
    input is computed in float32, whose error of ~1e-7 is below float32
    storage) in one GEMM.  Returns the input's floating dtype (float64 for
    non-floating input); ``K - 1 == 0`` returns an unchanged copy.  Raises
    ``ValueError`` for a bad shape, ``TransformError`` for a bad ``R``.
    """
    arr = np.asarray(sh_rest)
    dtype = arr.dtype if np.issubdtype(arr.dtype, np.floating) else np.dtype(np.float64)
    x = np.asarray(arr, dtype=np.float64 if dtype == np.float64 else np.float32)
    if x.ndim < 2:
        raise ValueError(f"sh_rest must have shape (..., K-1, 3), got {x.shape}")
    degree = sh_degree_from_bases(x.shape[-2] + 1)
    full = sh_rest_rotation(R, degree).astype(x.dtype)

    if degree == 0:
        out = x.copy()
    else:
        # rows are (splat, channel): (..., C, K-1) @ D^T
        k1 = x.shape[-2]
        xt = np.ascontiguousarray(np.swapaxes(x, -1, -2))
        out = np.swapaxes((xt.reshape(-1, k1) @ full.T).reshape(xt.shape), -1, -2)
    return out.astype(dtype, copy=False)
