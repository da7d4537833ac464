"""The densification statistics of one view (``mlx3d_add_screen_statistics``)."""

from __future__ import annotations

import numpy as np

from . import _call, _contiguous, _f32p, _f64, _f64p, _i32p, _i64, _int, _numpy_out, _ptr, _threads, _u8p, register

register({"mlx3d_add_screen_statistics": ([_u8p, _f32p, _i32p, _i64, _f64, _f64, _f64p, _f64p, _f64p, _int], _int)})


def add_screen_statistics(visible, grad2d, radii, sx: float, sy: float, grad_accum: np.ndarray, grad_count: np.ndarray,
                          max_radii: np.ndarray, num_threads: int = 0) -> None:
    """Adds one view to the float64 (N,) densification statistics in place: grad_accum += |grad2d * (sx, sy)| where
    visible (bool (N,)), grad_count += visible, max_radii = max(max_radii, radii (int32 (N,))); grad2d float32 (N, 2)
    (``mlx3d._core.add_screen_statistics``'s contract)."""
    stats = (grad_accum, grad_count, max_radii)
    n = grad_accum.shape[0] if isinstance(grad_accum, np.ndarray) else -1
    for name, a in zip(("grad_accum", "grad_count", "max_radii"), stats):
        _numpy_out(a, name, np.float64, (n,))
    threads = _threads(num_threads)
    vis, g, r = _contiguous(visible, np.bool_), _contiguous(grad2d, np.float32), _contiguous(radii, np.int32)
    if (vis.size, g.size, r.size) != (n, 2 * n, n):
        raise ValueError(f"add_screen_statistics: visible (N,), grad2d (N,2), radii (N,) and the three (N,) statistics must "
                         f"agree on N = {n}, got {vis.size}, {g.shape} and {r.size}")
    _call("mlx3d_add_screen_statistics", _ptr(vis), _ptr(g), _ptr(r), n, float(sx), float(sy), *(_ptr(a) for a in stats), threads)
