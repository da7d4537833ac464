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
and :func:`rotate_sh` applies it to ``sh_rest``.  The numpy core (constants,
degree helpers, rotation) is :mod:`mlx3d.sh_basis`, importable without MLX.
"""

from __future__ import annotations

from typing import Any, List

import mlx.core as mx
import numpy as np

# The basis constants, degree helpers and rotation are numpy-only and live in
# mlx3d.sh_basis (the file codecs use them without MLX); re-exported here.
from .. import sh_basis as _np_sh
from ..sh_basis import (  # noqa: F401  (private helpers kept importable from here)
    C0,
    C1,
    C2,
    C3,
    MAX_SH_DEGREE,
    _band_basis_np,
    _band_fit,
    _band_slice,
    _higher_terms,
    _unit_components,
    num_sh_bases,
    rotate_sh_rest,
    sh_degree_from_bases,
)

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


def _numpy_R(R: Any):
    """An ``mx.array`` ``R`` as numpy (bfloat16 via float32); anything else as it is."""
    if isinstance(R, mx.array):
        return np.array(R.astype(mx.float32) if R.dtype == mx.bfloat16 else R)
    return R


def _validate_orthogonal(R: Any) -> np.ndarray:
    return _np_sh._validate_orthogonal(_numpy_R(R))


def sh_rotation(R, degree: int = MAX_SH_DEGREE) -> List[np.ndarray]:
    return _np_sh.sh_rotation(_numpy_R(R), degree)


sh_rotation.__doc__ = _np_sh.sh_rotation.__doc__


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
    (:func:`mlx3d.sh_basis.rotate_sh_rest`) and is not differentiable (this is
    a data edit, not a training op).
    """
    R = _numpy_R(R)
    if not _is_mx(sh_rest):
        return rotate_sh_rest(sh_rest, R)
    dtype = sh_rest.dtype
    if not mx.issubdtype(dtype, mx.floating):
        dtype = mx.float32
    src = sh_rest.astype(mx.float32) if sh_rest.dtype == mx.bfloat16 else sh_rest
    return mx.array(rotate_sh_rest(np.asarray(src, dtype=np.float32), R), dtype=dtype)
