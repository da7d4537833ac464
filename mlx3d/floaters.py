"""Floater (outlier) removal for splat centres / point clouds (numpy).

Two deterministic rules, both based on k-nearest-neighbour distances
(:mod:`mlx3d.neighbors`) and both returning an :class:`OutlierResult` whose
``keep`` mask selects the points to keep:

* :func:`statistical_outliers` — statistical outlier removal (SOR), the rule
  behind ``3dgsconverter --remove_flyers`` (defaults k=25, 10.5 std).
* :func:`radius_outliers` — too few neighbours within a radius.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from mlx3d import neighbors
from mlx3d.neighbors import DEFAULT_CHUNK_SIZE
from mlx3d.progress import ProgressFn

__all__ = ["OutlierResult", "statistical_outliers", "radius_outliers"]


@dataclass(frozen=True, eq=False)
class OutlierResult:
    """Outcome of a floater-removal rule.

    Attributes:
        keep: bool (N,), True for points to keep (``points[keep]``).
        kept: number of kept points (``keep.sum()``).
        removed: number of floaters (``N - kept``).
        threshold: the distance threshold used, in coordinate units (see the
            rule's docstring).
        method: ``"statistical"`` or ``"radius"``.
        scores: float32 (N,), the per-point statistic compared with
            ``threshold`` (mean k-NN distance, or distance to the
            ``min_neighbours``-th neighbour).
    """

    keep: np.ndarray
    kept: int
    removed: int
    threshold: float
    method: str
    scores: np.ndarray

    @property
    def floaters(self) -> np.ndarray:
        """bool (N,), True for removed points (``~keep``)."""
        return ~self.keep

    def __repr__(self) -> str:
        return (
            f"OutlierResult(method={self.method!r}, kept={self.kept}, "
            f"removed={self.removed}, threshold={self.threshold:.6g})"
        )


def _as_real(name: str, value: object, *, minimum: float | None = None) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {name}={value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {name}={v}")
    if minimum is not None and v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {name}={v}")
    return v


def _result(keep: np.ndarray, threshold: float, method: str, scores: np.ndarray) -> OutlierResult:
    keep.setflags(write=False)
    scores.setflags(write=False)
    kept = int(np.count_nonzero(keep))
    return OutlierResult(
        keep=keep,
        kept=kept,
        removed=int(keep.size - kept),
        threshold=float(threshold),
        method=method,
        scores=scores,
    )


def _num_points(points: object) -> int:
    shape = np.shape(points)
    return int(shape[0]) if len(shape) >= 1 else 0


def statistical_outliers(
    points: np.ndarray,
    k: int = 25,
    std_ratio: float = 10.5,
    *,
    num_threads: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: ProgressFn = None,
) -> OutlierResult:
    """Statistical outlier removal on (N, 3) points.

    Rule: for each point i, ``d_i`` = mean Euclidean distance to its k nearest
    *other* points (exact duplicates count as neighbours at distance 0);
    ``threshold = mean(d) + std_ratio * std(d)`` with the population standard
    deviation (ddof=0), both over all N points and computed in float64; point
    i is a floater when ``d_i > threshold``. Deterministic (independent of
    threads and chunking).

    This is the rule of 3dgsconverter's ``--remove_flyers`` (current
    ``DataProcessor.remove_flyers``: k=25, factor 10.5, neighbours from one
    tree over the whole cloud, ``np.std``), except that 3dgsconverter keeps
    ``d_i < threshold``, i.e. it also drops points exactly at the threshold,
    and averages in float32. Its older releases searched neighbours inside
    50 000-point chunks with a per-chunk threshold and clamped k to
    ``max(3, min(k, N // 100))``; neither is done here. Open3D's
    ``remove_statistical_outlier`` differs too (sample std, ddof=1, and it
    drops points with ``d_i == 0``).

    Args:
        points: (N, 3) coordinates, finite, N >= 2.
        k: neighbours per point, 1 <= k <= N - 1.
        std_ratio: multiple of the standard deviation, >= 0.
        num_threads: worker threads, 0 = all hardware threads.
        chunk_size: queries per native call.
        progress: optional ``progress(done, total)`` callback for the
            neighbour search (``total`` = N).

    Returns:
        :class:`OutlierResult` with ``method="statistical"``, ``threshold`` in
        coordinate units and ``scores = d`` (float32 (N,)).
    """
    std_ratio = _as_real("std_ratio", std_ratio, minimum=0.0)
    n = _num_points(points)
    if isinstance(k, numbers.Integral) and not isinstance(k, (bool, np.bool_)) and n >= 1:
        if k >= n:
            raise ValueError(
                f"k={int(k)} must be smaller than the number of points ({n}): "
                f"each point needs k other points"
            )
    d = neighbors.mean_knn_distance(
        points, k, num_threads=num_threads, chunk_size=chunk_size, progress=progress
    )
    d64 = d.astype(np.float64)
    mean = float(d64.mean())
    std = float(d64.std())  # ddof=0
    threshold = mean + std_ratio * std
    keep = ~(d64 > threshold)
    return _result(keep, threshold, "statistical", d)


def radius_outliers(
    points: np.ndarray,
    radius: float,
    min_neighbours: int,
    *,
    num_threads: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: ProgressFn = None,
) -> OutlierResult:
    """Radius outlier removal on (N, 3) points.

    Rule: point i is a floater when fewer than ``min_neighbours`` *other*
    points lie within Euclidean distance ``radius`` of it (inclusive, ``<=``).
    Equivalently, when the distance to its ``min_neighbours``-th nearest other
    point exceeds ``radius``; that distance is computed in float64 and
    compared after rounding to float32 (so a neighbour within one float32
    rounding of ``radius`` may count either way).

    ``min_neighbours = 0`` keeps every point. ``min_neighbours >= N`` cannot
    be met by any point (there are only N - 1 others) and raises
    ``ValueError`` rather than silently removing everything.

    Args:
        points: (N, 3) coordinates, finite, N >= 1.
        radius: neighbourhood radius in coordinate units, >= 0.
        min_neighbours: required number of other points within ``radius``,
            0 <= min_neighbours <= N - 1.
        num_threads: worker threads, 0 = all hardware threads.
        chunk_size: queries per native call.
        progress: optional ``progress(done, total)`` callback for the
            neighbour search (``total`` = N).

    Returns:
        :class:`OutlierResult` with ``method="radius"``, ``threshold =
        radius`` and ``scores`` = distance to the ``min_neighbours``-th
        nearest other point (float32 (N,); zeros when ``min_neighbours=0``).
    """
    radius = _as_real("radius", radius, minimum=0.0)
    if isinstance(min_neighbours, (bool, np.bool_)) or not isinstance(
        min_neighbours, numbers.Integral
    ):
        raise ValueError(f"min_neighbours must be an integer, got min_neighbours={min_neighbours!r}")
    min_neighbours = int(min_neighbours)
    if min_neighbours < 0:
        raise ValueError(f"min_neighbours must be >= 0, got min_neighbours={min_neighbours}")
    n = _num_points(points)
    if min_neighbours == 0:
        # Validate the points (shape, finiteness) the same way, then keep all.
        pts = neighbors._as_points("points", points)
        n = pts.shape[0]
        if progress is not None:
            progress(n, n)
        return _result(np.ones(n, dtype=bool), radius, "radius", np.zeros(n, dtype=np.float32))
    if n >= 1 and min_neighbours >= n:
        raise ValueError(
            f"min_neighbours={min_neighbours} must be smaller than the number of points ({n}): "
            f"no point can have {min_neighbours} other points, so every point would be a floater"
        )
    kth = neighbors.kth_knn_distance(
        points, min_neighbours, num_threads=num_threads, chunk_size=chunk_size, progress=progress
    )
    keep = kth <= np.float32(radius)
    return _result(keep, radius, "radius", kth)
