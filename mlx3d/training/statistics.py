"""The screen-space statistics of density control, gathered once per training view.

Per Gaussian: ``grad_accum`` += |dL/d(means2d)| in NDC units (the pixel
gradient times (W/2, H/2)) where visible, ``grad_count`` += 1 where visible,
``max_radii`` = max(max_radii, radius in pixels). The statistics are read at
densification and checkpoint time as float64 numpy arrays (N,).

Backend 'cpu' adds each view in place with a threaded C++ pass (the kernel
library's ``mlx3d_add_screen_statistics``, ``mlx3d/csrc/kernels/statistics.cpp``),
bit for bit numpy's float64 expression. Every other backend adds each view as MLX operations on the
device, into float32 sums that are folded into the float64 arrays when they
are read, so a training step reads nothing back to the host for them (a fold
sums at most one densification interval of views in float32, about 1e-6 of
relative error).

With several ranks (``mlx3d.training.distributed``) each rank adds its own
views; :meth:`ScreenStatistics.reduce` sums them over the ranks when density
control or a checkpoint reads them.
"""

from __future__ import annotations

import mlx.core as mx
import numpy as np

__all__ = ["ScreenStatistics"]


class ScreenStatistics:
    """grad_accum, grad_count, max_radii of N Gaussians (see the module docstring)."""

    def __init__(self, n: int):
        self._host = [np.zeros(n), np.zeros(n), np.zeros(n)]
        self._pending = None  # float32 (sum, count, max radius) MLX arrays not yet folded into _host

    def add(self, camera, visible, grad2d, radii, backend: str) -> None:
        """Adds one view: visible (N,) bool, grad2d (N,2) dL/d(means2d) in pixels, radii (N,); backend resolved."""
        sx, sy = 0.5 * camera.width, 0.5 * camera.height
        if backend == "cpu":
            from mlx3d import native

            from ..render.raster_cpu import get_num_threads

            accum, count, max_radii = self.arrays()
            native.core().add_screen_statistics(
                native.host_array(visible, np.bool_), native.host_array(grad2d, np.float32), native.host_array(radii, np.int32),
                sx, sy, accum, count, max_radii, get_num_threads())
            return
        visible = mx.stop_gradient(visible)
        g = mx.stop_gradient(grad2d).astype(mx.float32)
        norm = mx.where(visible, mx.sqrt(mx.square(g[:, 0] * sx) + mx.square(g[:, 1] * sy)), 0.0)
        radius = mx.stop_gradient(radii).astype(mx.float32)
        if self._pending is None:
            self._pending = (norm, visible.astype(mx.float32), radius)
        else:
            s, c, r = self._pending
            self._pending = (s + norm, c + visible, mx.maximum(r, radius))
        mx.async_eval(*self._pending)  # keeps the graph one step deep, without waiting

    def arrays(self) -> tuple:
        """(grad_accum, grad_count, max_radii) as float64 (N,) numpy arrays (the live ones: edits stick)."""
        if self._pending is not None:
            s, c, r = (np.asarray(a, dtype=np.float64) for a in self._pending)
            self._pending = None
            accum, count, max_radii = self._host
            accum += s
            count += c
            np.maximum(max_radii, r, out=max_radii)
        return tuple(self._host)

    def reduce(self, ranks) -> tuple:
        """The statistics of every rank's views (``ranks`` a ``training.distributed.Ranks``), on every rank.

        Afterwards rank 0 holds the sums and the other ranks zeros (the maximum radii: all hold the
        maximum), so a later reduction counts no view twice."""
        accum, count, max_radii = self.arrays()
        n = accum.shape[0]
        sums = ranks.host_sum(np.concatenate([accum, count]), "the sum of the densification statistics")
        radii = ranks.host_max(max_radii, "the maximum of the screen radii")
        keep = ranks.rank == 0
        self._host = [sums[:n].copy() if keep else np.zeros(n), sums[n:].copy() if keep else np.zeros(n), radii]
        return sums[:n], sums[n:], radii

    def set(self, index: int, values) -> None:
        """Replaces statistic ``index`` (0 accum, 1 count, 2 max radii) after folding the pending views."""
        self.arrays()
        self._host[index] = np.asarray(values, dtype=np.float64)
