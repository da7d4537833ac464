"""k-nearest-neighbour queries on 3D point clouds (numpy in, numpy out).

Backed by a k-d tree, built once per call: the compiled one in
``mlx3d._core`` when it is available, else the numpy one in
:mod:`mlx3d.kdtree` (``MLX3D_NO_CORE=1`` forces it). Queries run on
``num_threads`` threads (the GIL released), in chunks of ``chunk_size``
queries, so Ctrl-C is honoured between chunks and temporary memory stays
O(chunk_size * k).

Distances are Euclidean, in the units of the input coordinates, computed in
float64 from the float32 coordinates and returned as float32. Results are
sorted by increasing distance (ties broken by point index) and do not depend
on ``num_threads`` or ``chunk_size``. Both trees evaluate the same float64
expressions, so they return bit-identical distances, means and k-th
distances (as long as the compiler does not fuse ``csrc/kernels/knn.cpp``'s
multiply-adds); the indices are identical too except where several points
share a query's k-th distance: the numpy tree then keeps those of smallest
index, the compiled one any of them.

All argument errors raise ``ValueError`` (non-finite coordinates raise
:class:`~mlx3d.errors.NonFiniteError`, a ``ValueError``) naming the argument.
"""

from __future__ import annotations

import numbers
from typing import Iterator

import numpy as np

from mlx3d import kdtree, native
from mlx3d.errors import NonFiniteError
from mlx3d.progress import ProgressFn  # called after each chunk with the queries done so far

__all__ = [
    "knn",
    "mean_knn_distance",
    "kth_knn_distance",
    "DEFAULT_CHUNK_SIZE",
]

DEFAULT_CHUNK_SIZE = 65536
_LEAF_SIZE = 16


def _tree(points: np.ndarray):
    """k-d tree over validated float32 (N, 3) ``points``: the compiled one when
    ``mlx3d._core`` is available, else :class:`mlx3d.kdtree.KDTree` (same methods)."""
    if native.available():
        return native.core().KDTree(points, _LEAF_SIZE)
    return kdtree.KDTree(points, _LEAF_SIZE)


# --------------------------------------------------------------------------- #
# validation
# --------------------------------------------------------------------------- #
def _as_points(name: str, value: object) -> np.ndarray:
    """Returns ``value`` as a C-contiguous float32 (N, 3) array, or raises."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} is empty (shape {arr.shape}); at least one point is required")
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(arr, dtype=np.float32)
    finite = np.isfinite(out).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        extra = ""
        if arr.dtype != np.float32 and np.isfinite(arr[bad[0]]).all():
            extra = " after conversion to float32 (magnitude above 3.4e38)"
        raise NonFiniteError(
            f"{name} has {bad.size} of {out.shape[0]} rows with non-finite coordinates "
            f"(NaN or Inf){extra}; first at row {int(bad[0])}"
        )
    return out


def _as_int(name: str, value: object, minimum: int, hint: str = "") -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer, got {name}={value!r}")
    value = int(value)
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}{hint}, got {name}={value}")
    return value


def _as_reference_index(value: object, m: int, n: int) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"reference_index must be an integer array, got dtype {arr.dtype}")
    if arr.shape != (m,):
        raise ValueError(
            f"reference_index must have shape ({m},) (one entry per query), got shape {arr.shape}"
        )
    out = np.ascontiguousarray(arr, dtype=np.int64)
    if m:
        bad = np.flatnonzero((out < -1) | (out >= n))
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"reference_index[{i}]={int(out[i])} is outside [-1, {n}) "
                f"(-1 = query is not one of the {n} points); {bad.size} entries are invalid"
            )
    return out


class _Plan:
    """Validated arguments of one neighbour query and the built tree."""

    def __init__(
        self,
        points: object,
        k: object,
        queries: object,
        reference_index: object,
        num_threads: object,
        chunk_size: object,
        progress: ProgressFn = None,
    ) -> None:
        if progress is not None and not callable(progress):
            raise ValueError(f"progress must be a callable (done, total) or None, got {progress!r}")
        self.progress = progress
        pts = _as_points("points", points)
        n = pts.shape[0]
        self.k = _as_int("k", k, 1)
        self.num_threads = _as_int("num_threads", num_threads, 0, " (0 = all hardware threads)")
        self.chunk_size = _as_int("chunk_size", chunk_size, 1)
        self.points = pts
        self.self_query = queries is None
        if self.self_query:
            if reference_index is not None:
                raise ValueError(
                    "reference_index is only used with explicit queries; with "
                    "queries=None each point's own index is already excluded"
                )
            self.queries = pts
            self.reference_index = None
            excludes_self = True
        else:
            q = np.asarray(queries)
            if q.ndim == 2 and q.shape[0] == 0 and q.shape[1] == 3:
                self.queries = np.zeros((0, 3), dtype=np.float32)
            else:
                self.queries = _as_points("queries", q)
            m = self.queries.shape[0]
            if reference_index is None:
                self.reference_index = None
                excludes_self = False
            else:
                self.reference_index = _as_reference_index(reference_index, m, n)
                excludes_self = bool((self.reference_index >= 0).any())
        available = n - 1 if excludes_self else n
        if self.k > available:
            why = (
                f"points has {n} rows and each query's own point is excluded"
                if excludes_self
                else f"points has {n} rows"
            )
            raise ValueError(f"k={self.k} exceeds the {available} available neighbours ({why})")
        self.tree = _tree(pts)

    @property
    def m(self) -> int:
        return int(self.queries.shape[0])

    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray | None, slice | np.ndarray]]:
        """Yields (queries, self_index, destination rows) per chunk.

        Self-queries run in tree order (spatially coherent, faster), so their
        destination is an index array; explicit queries run in input order.
        """
        c = self.chunk_size
        m = self.m
        if self.self_query:
            order = self.tree.order()
            for a in range(0, m, c):
                rows = order[a : a + c]
                yield np.ascontiguousarray(self.points[rows]), rows, rows
                self._report(min(a + c, m))
        else:
            for a in range(0, m, c):
                sl = slice(a, a + c)
                ref = None if self.reference_index is None else self.reference_index[sl]
                yield self.queries[sl], ref, sl
                self._report(min(a + c, m))
        if m == 0:
            self._report(0)

    def _report(self, done: int) -> None:
        if self.progress is not None:
            self.progress(done, self.m)


def _reduce(plan: _Plan, method: str) -> np.ndarray:
    out = np.empty(plan.m, dtype=np.float32)
    query = getattr(plan.tree, method)
    for q, ref, rows in plan.chunks():
        out[rows] = query(q, plan.k, ref, plan.num_threads)
    return out


# --------------------------------------------------------------------------- #
# public API
# --------------------------------------------------------------------------- #
def knn(
    points: np.ndarray,
    k: int,
    queries: np.ndarray | None = None,
    *,
    reference_index: np.ndarray | None = None,
    num_threads: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: ProgressFn = None,
) -> tuple[np.ndarray, np.ndarray]:
    """k nearest neighbours of each query among ``points``.

    Args:
        points: (N, 3) coordinates (any real dtype; used as float32), N >= 1.
        k: neighbours per query, 1 <= k <= N (N - 1 when self is excluded).
        queries: (M, 3) query coordinates. ``None`` queries every point and
            excludes the point itself, so each row holds k *other* points
            (exact duplicates with other indices are still returned).
        reference_index: with explicit ``queries`` only: (M,) int, each query's
            index in ``points`` (excluded from its result) or -1.
        num_threads: worker threads, 0 = all hardware threads.
        chunk_size: queries per tree call.
        progress: optional ``progress(done, total)`` called after each chunk
            (``total`` = M queries).

    Returns:
        ``(indices, distances)``: int64 (M, k) indices into ``points`` and
        float32 (M, k) Euclidean distances, each row sorted by increasing
        distance (ties by index).
    """
    plan = _Plan(points, k, queries, reference_index, num_threads, chunk_size, progress)
    indices = np.empty((plan.m, plan.k), dtype=np.int64)
    distances = np.empty((plan.m, plan.k), dtype=np.float32)
    for q, ref, rows in plan.chunks():
        idx, d2 = plan.tree.query(q, plan.k, ref, plan.num_threads)
        indices[rows] = idx
        distances[rows] = np.sqrt(d2, out=d2)
    return indices, distances


def mean_knn_distance(
    points: np.ndarray,
    k: int,
    queries: np.ndarray | None = None,
    *,
    reference_index: np.ndarray | None = None,
    num_threads: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: ProgressFn = None,
) -> np.ndarray:
    """Mean Euclidean distance from each query to its k nearest points.

    Same arguments as :func:`knn`: ``queries=None`` queries every point with
    itself excluded; ``reference_index`` gives each query's own index in
    ``points`` (or -1), e.g. when ``points`` is a random subset of
    ``queries``. Only the per-query mean is kept, so memory is O(N + M) plus
    O(chunk_size) per chunk, never O(M * k).

    Returns:
        float32 (M,), in the units of the coordinates (mean accumulated in
        float64).
    """
    plan = _Plan(points, k, queries, reference_index, num_threads, chunk_size, progress)
    return _reduce(plan, "query_mean")


def kth_knn_distance(
    points: np.ndarray,
    k: int,
    queries: np.ndarray | None = None,
    *,
    reference_index: np.ndarray | None = None,
    num_threads: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: ProgressFn = None,
) -> np.ndarray:
    """Euclidean distance from each query to its k-th nearest point.

    Same arguments as :func:`mean_knn_distance`. Returns float32 (M,).
    """
    plan = _Plan(points, k, queries, reference_index, num_threads, chunk_size, progress)
    return _reduce(plan, "query_kth")
