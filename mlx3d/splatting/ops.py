"""Whole-splat-set edits on plain numpy ``SplatArrays``: transform, merge, SH resize.

``GaussianModel`` calls these for its own ``transform``/``merge``; the Blender
add-on calls them directly on attribute arrays (no MLX round trip).
"""

from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np

from ..errors import TransformError
from ..io.ply import NORMAL_NAMES, SplatArrays
from ..transforms import split_affine, transform_gaussians, transform_normals
from .sh import num_sh_bases, rotate_sh


def resize_sh_rest(sh_rest, degree: int):
    """Truncate or zero-pad the bands of ``sh_rest`` (N, K-1, 3) to ``degree``.

    Works on numpy and MLX arrays and returns the same type. Truncation keeps
    the first coefficients of every channel (the in-memory layout is
    coefficient-major, so that is a slice).
    """
    target = num_sh_bases(degree) - 1
    have = sh_rest.shape[1]
    if target <= have:
        return sh_rest[:, :target, :]
    pad_shape = (sh_rest.shape[0], target - have, 3)
    if isinstance(sh_rest, np.ndarray):
        return np.concatenate([sh_rest, np.zeros(pad_shape, sh_rest.dtype)], axis=1)
    import mlx.core as mx

    return mx.concatenate([sh_rest, mx.zeros(pad_shape, dtype=sh_rest.dtype)], axis=1)


def transform_splats(arrays: SplatArrays, matrix) -> SplatArrays:
    """New ``SplatArrays`` with the 4x4 affine ``matrix`` applied (object insertion).

    Means map as points, each covariance Σ becomes L Σ Lᵀ (L = linear part,
    non-uniform scale and shear included), SH bands rotate with the orthogonal
    polar factor of L (reflections too), and normals in the extras
    (nx, ny, nz) map by the inverse transpose. Other extras are copied.
    Raises ``TransformError`` for a bad matrix or non-finite geometry.
    """
    parts = split_affine(matrix)
    if not all(np.isfinite(a).all() for a in (arrays.means, arrays.quats, arrays.scales)):
        raise TransformError("splats have NaN/Inf means, quats or scales; cannot transform them")
    means, quats, scales = transform_gaussians(parts, arrays.means, arrays.quats, arrays.scales)
    extra = {name: np.array(values) for name, values in arrays.extra.items()}
    if all(name in extra for name in NORMAL_NAMES):
        normals = transform_normals(parts, np.stack([extra[name] for name in NORMAL_NAMES], axis=1))
        for i, name in enumerate(NORMAL_NAMES):
            extra[name] = normals[:, i].astype(extra[name].dtype)
    return SplatArrays(
        means=means,
        scales=scales,
        quats=quats,
        opacities=np.array(arrays.opacities, np.float32),
        sh_dc=np.array(arrays.sh_dc, np.float32),
        sh_rest=rotate_sh(np.asarray(arrays.sh_rest, np.float32), parts.rotation),
        extra=extra,
    )


def merge_splats(parts: Sequence[SplatArrays], sh_degree: int | None = None) -> SplatArrays:
    """One ``SplatArrays`` from several, rows concatenated in order.

    SH is zero-padded to the highest degree present, or truncated/padded to
    ``sh_degree`` when given. Extra properties are the union over inputs; rows
    from an input without one are filled with zeros (a warning names them).
    """
    parts = list(parts)
    if not parts:
        raise ValueError("merge needs at least one set of splats")
    degree = max(p.sh_degree for p in parts) if sh_degree is None else sh_degree
    dtypes: dict[str, np.dtype] = {}
    for p in parts:
        for name, values in p.extra.items():
            dtypes[name] = np.result_type(dtypes[name], values.dtype) if name in dtypes else values.dtype
    partial = [name for name in dtypes if any(name not in p.extra for p in parts)]
    if partial:
        warnings.warn(f"merge: extra properties {partial} are missing in some inputs and are filled with 0 there", stacklevel=2)

    def cat(name):
        return np.concatenate([np.asarray(getattr(p, name), np.float32) for p in parts], axis=0)

    return SplatArrays(
        means=cat("means"),
        scales=cat("scales"),
        quats=cat("quats"),
        opacities=cat("opacities"),
        sh_dc=cat("sh_dc"),
        sh_rest=np.concatenate([resize_sh_rest(np.asarray(p.sh_rest, np.float32), degree) for p in parts], axis=0),
        extra={
            name: np.concatenate([p.extra[name].astype(dtype) if name in p.extra else np.zeros(p.count, dtype) for p in parts])
            for name, dtype in dtypes.items()
        },
    )
