"""k-nearest neighbours (mlx3d.neighbors, mlx3d._core.KDTree) against a
brute-force float64 numpy oracle."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mlx3d import native, neighbors
from mlx3d.errors import ExtensionBuildError, NonFiniteError

RTOL = 1e-6


# --------------------------------------------------------------------------- #
# oracle
# --------------------------------------------------------------------------- #
def oracle_d2(points, queries, self_index=None):
    """Squared float64 distances (M, N) between the float32-rounded inputs."""
    p = np.asarray(points, dtype=np.float32).astype(np.float64)
    q = np.asarray(queries, dtype=np.float32).astype(np.float64)
    d2 = ((q[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    if self_index is not None:
        rows = np.flatnonzero(self_index >= 0)
        d2[rows, self_index[rows]] = np.inf
    return d2


def check_knn(points, queries, k, idx, dist, self_index=None):
    """Asserts that (idx, dist) is a valid k-NN answer (ties allowed)."""
    m = len(queries)
    assert idx.shape == (m, k) and idx.dtype == np.int64
    assert dist.shape == (m, k) and dist.dtype == np.float32
    d2 = oracle_d2(points, queries, self_index)
    srt = np.sort(d2, axis=1)
    ref = np.sqrt(srt[:, :k])
    # 1. distances equal the k smallest true distances, sorted
    np.testing.assert_allclose(dist, ref, rtol=RTOL, atol=0)
    assert np.all(np.diff(dist, axis=1) >= 0)
    # 2. each returned index really lies at the returned distance
    got = np.sqrt(d2[np.arange(m)[:, None], idx])
    np.testing.assert_allclose(got, dist, rtol=RTOL, atol=0)
    # 3. no index twice in a row, never the query's own point
    assert np.all(np.diff(np.sort(idx, axis=1), axis=1) > 0)
    assert np.all((idx >= 0) & (idx < len(points)))
    if self_index is not None:
        assert not np.any(idx == self_index[:, None])
    # 4. where a distance is unambiguous, the index is the oracle's
    order = np.argsort(d2, axis=1, kind="stable")[:, :k]
    cur = srt[:, :k]
    prev = np.concatenate([np.full((m, 1), -np.inf), srt[:, : k - 1]], axis=1)
    nxt = srt[:, 1 : k + 1]
    if nxt.shape[1] < k:
        nxt = np.concatenate([nxt, np.full((m, 1), np.inf)], axis=1)
    tol = 1e-5 * np.maximum(cur, 1e-30)
    distinct = (cur - prev > tol) & (nxt - cur > tol)
    np.testing.assert_array_equal(idx[distinct], order[distinct])
    return distinct.mean()


def self_check(points, k, **kw):
    idx, dist = neighbors.knn(points, k, **kw)
    n = len(points)
    return check_knn(points, points, k, idx, dist, self_index=np.arange(n))


# --------------------------------------------------------------------------- #
# data sets
# --------------------------------------------------------------------------- #
def uniform(rng, n=1500):
    return rng.random((n, 3), dtype=np.float32)


def clustered(rng):
    # blobs whose spreads differ by 1000x, far apart
    spreads = [1e-3, 3e-2, 1.0]
    centres = [[0, 0, 0], [10, 0, 0], [0, 40, 5]]
    parts = [c + s * rng.standard_normal((500, 3)) for c, s in zip(centres, spreads)]
    pts = np.concatenate(parts).astype(np.float32)
    return pts[rng.permutation(len(pts))]


def duplicated(rng):
    base = rng.random((300, 3), dtype=np.float32)
    reps = rng.integers(1, 6, size=300)
    pts = np.repeat(base, reps, axis=0)
    return pts[rng.permutation(len(pts))]


def far_outliers(rng):
    dense = rng.random((1200, 3), dtype=np.float32)
    direction = rng.standard_normal((12, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    far = direction * 10.0 ** rng.uniform(3, 6, size=(12, 1))
    pts = np.concatenate([dense, far.astype(np.float32)])
    return pts[rng.permutation(len(pts))]


def collinear(rng):
    t = rng.uniform(-5, 5, size=700)
    line = np.stack([t, 2 * t, -t], axis=1)
    even = np.arange(300, dtype=np.float64)[:, None] * np.array([[0.5, 0.0, 0.0]]) + 20
    return np.concatenate([line, even]).astype(np.float32)


def far_from_origin(rng):
    return (1e5 + 1e-2 * rng.random((1000, 3))).astype(np.float32)


DATASETS = {
    "uniform": uniform,
    "clustered": clustered,
    "duplicated": duplicated,
    "far_outliers": far_outliers,
    "collinear": collinear,
    "far_from_origin": far_from_origin,
}


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# --------------------------------------------------------------------------- #
# correctness
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("name", sorted(DATASETS))
@pytest.mark.parametrize("k", [1, 7, 25])
def test_self_knn_matches_oracle(name, k, rng):
    pts = DATASETS[name](rng)
    distinct = self_check(pts, k)
    if name in ("uniform", "clustered", "far_outliers"):
        assert distinct > 0.99  # the index comparison was not vacuous


def test_all_identical_points():
    pts = np.tile(np.array([[1.0, -2.0, 3.5]], dtype=np.float32), (200, 1))
    idx, dist = neighbors.knn(pts, 10)
    assert np.all(dist == 0)
    assert not np.any(idx == np.arange(200)[:, None])
    assert np.all(np.diff(np.sort(idx, axis=1), axis=1) > 0)
    np.testing.assert_array_equal(neighbors.mean_knn_distance(pts, 10), np.zeros(200))
    # k = N - 1: every other point
    idx, dist = neighbors.knn(pts, 199)
    assert np.all(np.sort(idx[0]) == np.arange(1, 200))


def test_duplicates_of_self_are_neighbours():
    p = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [3, 0, 0]], dtype=np.float32)
    idx, dist = neighbors.knn(p, 1)
    np.testing.assert_array_equal(idx[:, 0], [1, 0, 0, 2])
    np.testing.assert_array_equal(dist[:, 0], [0, 0, 1, 2])


def test_explicit_queries_m_ne_n(rng):
    pts = clustered(rng)
    queries = rng.uniform(-5, 45, size=(700, 3)).astype(np.float32)
    idx, dist = neighbors.knn(pts, 9, queries)
    check_knn(pts, queries, 9, idx, dist)
    # queries at the points themselves, without exclusion: nearest is distance 0
    idx, dist = neighbors.knn(pts, 3, pts[:50])
    assert np.all(dist[:, 0] == 0)


def test_reference_index_subset(rng):
    queries = uniform(rng, 1200)
    sub = np.sort(rng.choice(len(queries), 400, replace=False))
    ref = np.full(len(queries), -1, dtype=np.int64)
    ref[sub] = np.arange(len(sub))
    pts = queries[sub]
    idx, dist = neighbors.knn(pts, 6, queries, reference_index=ref)
    check_knn(pts, queries, 6, idx, dist, self_index=ref)
    mean = neighbors.mean_knn_distance(pts, 6, queries, reference_index=ref)
    np.testing.assert_allclose(mean, dist.astype(np.float64).mean(axis=1), rtol=RTOL)


def test_empty_queries(rng):
    idx, dist = neighbors.knn(uniform(rng, 10), 3, np.zeros((0, 3)))
    assert idx.shape == (0, 3) and dist.shape == (0, 3)
    assert neighbors.mean_knn_distance(uniform(rng, 10), 3, np.zeros((0, 3))).shape == (0,)


def test_mean_and_kth_match_oracle(rng):
    pts = far_outliers(rng)
    k = 25
    srt = np.sqrt(np.sort(oracle_d2(pts, pts, np.arange(len(pts))), axis=1)[:, :k])
    mean = neighbors.mean_knn_distance(pts, k)
    kth = neighbors.kth_knn_distance(pts, k)
    assert mean.dtype == np.float32 and mean.shape == (len(pts),)
    np.testing.assert_allclose(mean, srt.mean(axis=1), rtol=RTOL)
    np.testing.assert_allclose(kth, srt[:, -1], rtol=RTOL)


def test_threads_and_chunks_do_not_change_results(rng):
    pts = np.concatenate([uniform(rng, 4000), duplicated(rng)])
    a = neighbors.knn(pts, 8, num_threads=1)
    b = neighbors.knn(pts, 8, num_threads=2)
    c = neighbors.knn(pts, 8, num_threads=2, chunk_size=777)
    for x, y in [(a, b), (a, c)]:
        np.testing.assert_array_equal(x[0], y[0])
        np.testing.assert_array_equal(x[1], y[1])
    m1 = neighbors.mean_knn_distance(pts, 8, num_threads=1)
    m2 = neighbors.mean_knn_distance(pts, 8, num_threads=2, chunk_size=1000)
    np.testing.assert_array_equal(m1, m2)
    q = uniform(rng, 3000)
    np.testing.assert_array_equal(
        neighbors.mean_knn_distance(pts, 8, q, num_threads=1),
        neighbors.mean_knn_distance(pts, 8, q, num_threads=2, chunk_size=100),
    )


def test_accepts_float64_and_int_input(rng):
    pts64 = rng.random((300, 3))
    idx, dist = neighbors.knn(pts64, 4)
    check_knn(pts64, pts64, 4, idx, dist, self_index=np.arange(300))
    grid = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    kth = neighbors.kth_knn_distance(grid, 1)
    np.testing.assert_array_equal(kth, np.ones(len(grid), dtype=np.float32))


def test_kdtree_low_level(rng):
    core = native.core()
    pts = uniform(rng, 5000)
    tree = core.KDTree(pts, 16)
    assert tree.size == 5000
    assert 10 <= tree.depth <= 16
    order = tree.order()
    np.testing.assert_array_equal(np.sort(order), np.arange(5000))
    idx, d2 = tree.query(pts[:10], 3, np.arange(10, dtype=np.int64), 1)
    assert idx.shape == (10, 3) and d2.dtype == np.float32
    with pytest.raises(ValueError, match="self_index"):
        tree.query(pts[:10], 3, np.arange(9, dtype=np.int64), 1)
    with pytest.raises(ValueError, match="k = 5000 exceeds"):
        tree.query(pts[:10], 5000, np.arange(10, dtype=np.int64), 1)
    with pytest.raises(ValueError, match="outside"):
        tree.query(pts[:2], 3, np.array([0, 5000], dtype=np.int64), 1)
    assert core.hardware_threads() >= 1


# --------------------------------------------------------------------------- #
# argument errors
# --------------------------------------------------------------------------- #
P10 = np.random.default_rng(0).random((10, 3), dtype=np.float32)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(points=P10[:, :2], k=1), r"points must have shape \(N, 3\), got shape \(10, 2\)"),
        (dict(points=P10.ravel(), k=1), r"points must have shape \(N, 3\), got shape \(30,\)"),
        (dict(points=np.zeros((0, 3)), k=1), r"points is empty"),
        (dict(points=P10.astype(complex), k=1), r"points must be a real numeric array"),
        (dict(points=P10, k=0), r"k must be >= 1, got k=0"),
        (dict(points=P10, k=-3), r"k must be >= 1, got k=-3"),
        (dict(points=P10, k=2.5), r"k must be an integer, got k=2.5"),
        (dict(points=P10, k=True), r"k must be an integer"),
        (dict(points=P10, k=10), r"k=10 exceeds the 9 available neighbours"),
        (dict(points=P10, k=11, queries=P10), r"k=11 exceeds the 10 available neighbours"),
        (dict(points=P10, k=2, queries=P10[:, :1]), r"queries must have shape \(N, 3\)"),
        (dict(points=P10, k=2, num_threads=-1), r"num_threads must be >= 0"),
        (dict(points=P10, k=2, chunk_size=0), r"chunk_size must be >= 1, got chunk_size=0"),
        (
            dict(points=P10, k=2, reference_index=np.arange(10)),
            r"reference_index is only used with explicit queries",
        ),
        (
            dict(points=P10, k=2, queries=P10, reference_index=np.arange(9)),
            r"reference_index must have shape \(10,\)",
        ),
        (
            dict(points=P10, k=2, queries=P10, reference_index=np.full(10, 10)),
            r"reference_index\[0\]=10 is outside \[-1, 10\)",
        ),
        (
            dict(points=P10, k=2, queries=P10, reference_index=np.zeros(10)),
            r"reference_index must be an integer array",
        ),
    ],
)
@pytest.mark.parametrize("fn", [neighbors.knn, neighbors.mean_knn_distance, neighbors.kth_knn_distance])
def test_bad_arguments(fn, kwargs, match):
    kwargs = dict(kwargs)
    points, k = kwargs.pop("points"), kwargs.pop("k")
    with pytest.raises(ValueError, match=match):
        fn(points, k, **kwargs)


def test_non_finite_rows_are_counted():
    pts = P10.copy()
    pts[[2, 5, 7], [0, 1, 2]] = [np.nan, np.inf, -np.inf]
    with pytest.raises(NonFiniteError, match=r"points has 3 of 10 rows with non-finite .* row 2"):
        neighbors.knn(pts, 2)
    q = P10.copy()
    q[4, 1] = np.nan
    with pytest.raises(ValueError, match=r"queries has 1 of 10 rows .* row 4"):
        neighbors.mean_knn_distance(P10, 2, q)
    with pytest.raises(NonFiniteError, match="after conversion to float32"):
        neighbors.knn(np.full((4, 3), 1e39), 1)


# --------------------------------------------------------------------------- #
# the compiled module itself
# --------------------------------------------------------------------------- #
def test_extension_links_mlx():
    import mlx.core as mx

    core = native.core()
    assert core.mlx_version() == mx.__version__
    out = core._mlx_scale(mx.array([1.0, 2.0]), 3.0)
    assert isinstance(out, mx.array)
    np.testing.assert_array_equal(np.array(out), [3.0, 6.0])


def test_missing_extension_raises_build_error(monkeypatch):
    import mlx3d

    monkeypatch.setattr(native, "_core", None)
    monkeypatch.delattr(mlx3d, "_core", raising=False)
    monkeypatch.setitem(sys.modules, "mlx3d._core", None)
    with pytest.raises(ExtensionBuildError) as info:
        native.core()
    msg = str(info.value)
    assert "mlx3d._core is missing or broken" in msg
    assert "pip install --no-build-isolation -e ." in msg
    assert isinstance(info.value, ImportError)
    assert not native.available()


def test_progress_callback(rng):
    pts = uniform(rng, 1000)
    calls = []
    neighbors.mean_knn_distance(pts, 4, chunk_size=300, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(300, 1000), (600, 1000), (900, 1000), (1000, 1000)]
    calls.clear()
    neighbors.knn(pts, 2, pts[:10], progress=lambda d, t: calls.append((d, t)))
    assert calls == [(10, 10)]
    with pytest.raises(ValueError, match="progress must be a callable"):
        neighbors.knn(pts, 2, progress=5)
