"""Gaussian covariances re-decomposed under a linear map (``mlx3d_affine_covariances``), numpy in and out."""

from __future__ import annotations

import numpy as np

from . import _call, _contiguous, _f32p, _f64p, _i64, _int, _numpy_out, _ptr, _threads, register

register({"mlx3d_affine_covariances": ([_f64p, _f32p, _f32p, _i64, _int, _f32p, _f32p], _int)})


def affine_covariances(linear, quats, log_scales, quats_out: np.ndarray, log_scales_out: np.ndarray, num_threads: int = 0) -> None:
    """Covariances R diag(s)² Rᵀ of (N, 4) quats (w, x, y, z) and (N, 3) log scales mapped by a 3x3 linear map L
    (L Σ Lᵀ, in float64), re-decomposed into unit quaternions (w >= 0) and descending log scales written to the
    float32 outputs (N, 4) and (N, 3) (``mlx3d._core.affine_covariances``'s contract)."""
    lin = _contiguous(linear, np.float64)
    if lin.shape != (3, 3):
        raise ValueError(f"affine_covariances: linear must have shape (3, 3), got {lin.shape}")
    q, s = _contiguous(quats, np.float32), _contiguous(log_scales, np.float32)
    if q.ndim != 2 or q.shape[1] != 4:
        raise ValueError(f"affine_covariances: quats must have shape (N, 4), got {q.shape}")
    n = q.shape[0]
    if s.shape != (n, 3):
        raise ValueError(f"affine_covariances: log_scales must have shape ({n}, 3) as quats, got {s.shape}")
    for name, out, width in (("quats_out", quats_out, 4), ("log_scales_out", log_scales_out, 3)):
        _numpy_out(out, f"affine_covariances: {name}", np.float32, (n, width))
    _call("mlx3d_affine_covariances", _ptr(lin), _ptr(q), _ptr(s), n, _threads(num_threads), _ptr(quats_out), _ptr(log_scales_out))
