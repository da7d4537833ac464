"""k nearest neighbours with the library's k-d tree (``mlx3d_knn_*``: an opaque tree handle)."""

from __future__ import annotations

import ctypes

import numpy as np

from . import _call, _contiguous, _f32p, _i64, _i64p, _int, _numpy_in, _ptr, _threads, library, register

register({
    "mlx3d_knn_build": ([_f32p, _i64, _int, ctypes.POINTER(ctypes.c_void_p)], _int),
    "mlx3d_knn_free": ([ctypes.c_void_p], _int),
    "mlx3d_knn_info": ([ctypes.c_void_p, ctypes.POINTER(_i64), ctypes.POINTER(_int), ctypes.POINTER(_int), ctypes.POINTER(_i64)], _int),
    "mlx3d_knn_order": ([ctypes.c_void_p, _i64p], _int),
    "mlx3d_knn_query": ([ctypes.c_void_p, _f32p, _i64, _int, _i64p, _int, _int, _i64p, _f32p], _int),
})


class KDTree:
    """k-d tree over C-contiguous float32 (N, 3) points (median split on the widest axis): ``mlx3d._core.KDTree``'s
    methods and results, on the library's tree (freed with this object). Low-level; use mlx3d.neighbors."""

    _OUTPUTS = {"neighbours": 0, "mean": 1, "kth": 2}

    def __init__(self, points: np.ndarray, leaf_size: int = 16):
        points = _contiguous(points, np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        self._lib, self._tree = library(), ctypes.c_void_p()
        _call("mlx3d_knn_build", _ptr(points), points.shape[0], int(leaf_size), ctypes.byref(self._tree))
        size, leaf, depth, nodes = _i64(), _int(), _int(), _i64()
        _call("mlx3d_knn_info", self._tree, ctypes.byref(size), ctypes.byref(leaf), ctypes.byref(depth), ctypes.byref(nodes))
        self.size, self.leaf_size, self.depth, self.node_count = size.value, leaf.value, depth.value, nodes.value

    def __del__(self):
        tree = getattr(self, "_tree", None)
        if tree:
            self._lib.mlx3d_knn_free(tree)

    def order(self) -> np.ndarray:
        """Original point indices in tree order (spatially coherent), int64 (N,)."""
        out = np.empty(self.size, np.int64)
        _call("mlx3d_knn_order", self._tree, _ptr(out))
        return out

    def _query(self, queries, k: int, self_index, num_threads: int, output: str):
        q = _contiguous(queries, np.float32).reshape(-1, 3)
        m = q.shape[0]
        own = None if self_index is None else _numpy_in(self_index, np.int64, "self_index", m)
        threads = _threads(num_threads)
        index = np.empty((m, max(int(k), 0)), np.int64) if output == "neighbours" else None
        dist = np.empty((m, max(int(k), 0)) if output == "neighbours" else (m,), np.float32)
        _call("mlx3d_knn_query", self._tree, _ptr(q), m, int(k), _ptr(own), self._OUTPUTS[output], threads, _ptr(index),
              _ptr(dist))
        return index, dist

    def query(self, queries, k: int, self_index=None, num_threads: int = 0):
        """(indices int64 (M, k), squared distances float32 (M, k)) of each query's k nearest points, sorted by
        distance (ties by index); ``self_index`` (int64 (M,), -1 = none) names each query's own point, skipped."""
        return self._query(queries, k, self_index, num_threads, "neighbours")

    def query_mean(self, queries, k: int, self_index=None, num_threads: int = 0) -> np.ndarray:
        """Mean Euclidean distance to the k nearest points, float32 (M,)."""
        return self._query(queries, k, self_index, num_threads, "mean")[1]

    def query_kth(self, queries, k: int, self_index=None, num_threads: int = 0) -> np.ndarray:
        """Euclidean distance to the k-th nearest point, float32 (M,)."""
        return self._query(queries, k, self_index, num_threads, "kth")[1]
