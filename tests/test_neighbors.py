"""k-nearest neighbours (mlx3d.neighbors, mlx3d._core.KDTree, mlx3d.kdtree.KDTree)
against brute-force float64 numpy oracles, and the two trees against each other.

The tests of the compiled module itself skip when it is unavailable (not
built, or ``MLX3D_NO_CORE`` set); everything else passes either way.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mlx3d import kdtree, native, neighbors
from mlx3d.errors import ExtensionBuildError, NonFiniteError
from core_marks import needs_core, needs_extension

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


@needs_core
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
@needs_extension
def test_extension_links_mlx():
    import mlx.core as mx

    core = native.core()
    assert core.mlx_version() == mx.__version__
    out = core._mlx_scale(mx.array([1.0, 2.0]), 3.0)
    assert isinstance(out, mx.array)
    np.testing.assert_array_equal(np.array(out), [3.0, 6.0])


def _without_core(monkeypatch, library):
    """native.core() loads afresh, with mlx3d._core unimportable and the kernel library at ``library``."""
    import mlx3d
    from mlx3d import kernel_library

    monkeypatch.delenv(native.DISABLE_ENV, raising=False)
    monkeypatch.delenv(native.KERNELS_ENV, raising=False)
    monkeypatch.setattr(native, "_failure", None)  # restored afterwards: the real import state is kept
    monkeypatch.setattr(native, "_core", None)
    monkeypatch.delattr(mlx3d, "_core", raising=False)
    monkeypatch.setitem(sys.modules, "mlx3d._core", None)
    monkeypatch.setenv(kernel_library.PATH_ENV, str(library))
    monkeypatch.setattr(kernel_library, "_lib", None)
    monkeypatch.setattr(kernel_library, "_failure", None)


def test_missing_extension_raises_build_error(monkeypatch, tmp_path):
    _without_core(monkeypatch, tmp_path / "nowhere.so")
    with pytest.raises(ExtensionBuildError) as info:
        native.core()
    msg = str(info.value)
    assert "mlx3d._core is missing or broken" in msg and "nowhere.so does not exist" in msg
    assert "pip install --no-build-isolation -e ." in msg and "make kernels" in msg
    assert isinstance(info.value, ImportError)
    assert not native.available()


def test_without_the_extension_the_kernel_library_serves(monkeypatch):
    """Where mlx3d._core is missing (Windows, Linux arm64, macOS) the kernel library is the CPU kernels' module,
    with every function the CPU backend calls."""
    from mlx3d import kernel_library

    path = kernel_library.library_path()
    if not path.is_file():
        pytest.skip(f"{path} is not built (make kernels)")
    _without_core(monkeypatch, path)
    assert native.core() is kernel_library and native.available()
    assert all(callable(getattr(native.core(), name)) for name in native.CPU_FUNCTIONS)
    monkeypatch.setenv(native.KERNELS_ENV, "somewhere")
    monkeypatch.setattr(native, "_core", None)
    with pytest.raises(ExtensionBuildError, match="MLX3D_CPU_KERNELS must be 'auto' or 'library', got 'somewhere'"):
        native.core()


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


# --------------------------------------------------------------------------- #
# the numpy tree (mlx3d.kdtree) against an exact oracle
# --------------------------------------------------------------------------- #
def exact_oracle(points, queries, k, self_index=None):
    """What both trees must return, by brute force with the trees' arithmetic.

    Squared distances in float64 from the float32 coordinates as
    (dx*dx + dy*dy) + dz*dz, the k smallest (d2, index) pairs per query,
    the query's own point (self_index >= 0) excluded.

    Returns (indices int64 (M, k), d2 float32 (M, k), mean float32 (M,),
    kth float32 (M,)); the mean sums the k distances in increasing order.
    """
    p = np.asarray(points, dtype=np.float32).astype(np.float64)
    q = np.asarray(queries, dtype=np.float32).astype(np.float64)
    d2 = np.zeros((len(q), len(p)))
    for a in range(3):
        t = q[:, None, a] - p[None, :, a]
        d2 = d2 + t * t
    if self_index is not None:
        rows = np.flatnonzero(self_index >= 0)
        d2[rows, self_index[rows]] = np.inf
    idx = np.argsort(d2, axis=1, kind="stable")[:, :k]  # columns are in index order: ties by index
    kd2 = np.take_along_axis(d2, idx, axis=1)
    with np.errstate(over="ignore"):  # squared distances above 3.4e38 are inf in float32
        mean = (np.cumsum(np.sqrt(kd2), axis=1)[:, -1] / k).astype(np.float32)
        kth = np.sqrt(kd2[:, -1]).astype(np.float32)
        return idx, kd2.astype(np.float32), mean, kth


def assert_tree_exact(tree, points, queries, k, self_index=None):
    """query / query_mean / query_kth of ``tree`` equal the oracle bit for bit."""
    idx, d2, mean, kth = exact_oracle(points, queries, k, self_index)
    got_idx, got_d2 = tree.query(queries, k, self_index, 1)
    assert got_idx.dtype == np.int64 and got_d2.dtype == np.float32
    np.testing.assert_array_equal(got_idx, idx)
    np.testing.assert_array_equal(got_d2, d2)
    got_mean = tree.query_mean(queries, k, self_index, 1)
    got_kth = tree.query_kth(queries, k, self_index, 1)
    assert got_mean.dtype == np.float32 and got_kth.dtype == np.float32
    np.testing.assert_array_equal(got_mean, mean)
    np.testing.assert_array_equal(got_kth, kth)


def grid(rng):
    """Integer lattice: many exactly equal distances (ties by index)."""
    g = np.stack(np.meshgrid(*[np.arange(11)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g[rng.permutation(len(g))].astype(np.float32)


def planar(rng):
    xy = rng.uniform(-3, 3, size=(1200, 2))
    return np.concatenate([xy, np.full((1200, 1), 2.5)], axis=1).astype(np.float32)


def huge_range(rng):
    """Magnitudes from 1e-20 to 1e15 in one cloud (squared distances up to ~1e31)."""
    mag = 10.0 ** rng.uniform(-20, 15, size=(1000, 3))
    return (mag * rng.choice([-1.0, 1.0], size=(1000, 3))).astype(np.float32)


def duplicate_clusters(rng):
    """Runs of identical points larger than a leaf (400 and 40), small runs, -0.0 and +0.0."""
    a = np.full((400, 3), 0.5, np.float32)
    b = np.full((40, 3), [-1.0, 2.0, 0.0], np.float32)
    b[::2, 2] = -0.0
    pts = np.concatenate([a, b, duplicated(rng)[:600], uniform(rng, 300)])
    return pts[rng.permutation(len(pts))]


def beyond_float32(rng):
    """Distances around 1e20: squared distances overflow float32 (inf), their roots do not."""
    return (rng.standard_normal((500, 3)) * 1e20).astype(np.float32)


PURE_DATASETS = dict(DATASETS, grid=grid, planar=planar, huge_range=huge_range,
                     beyond_float32=beyond_float32, duplicate_clusters=duplicate_clusters)


@pytest.mark.parametrize("name", sorted(PURE_DATASETS))
@pytest.mark.parametrize("k", [1, 3, 25])
def test_pure_tree_self_queries_exact(name, k, rng):
    pts = PURE_DATASETS[name](rng)
    tree = kdtree.KDTree(pts, neighbors._LEAF_SIZE)
    assert_tree_exact(tree, pts, pts, k, np.arange(len(pts), dtype=np.int64))


@pytest.mark.parametrize("name", ["clustered", "grid", "duplicate_clusters", "huge_range"])
def test_pure_tree_explicit_queries_exact(name, rng):
    pts = PURE_DATASETS[name](rng)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    far = rng.uniform(lo - (hi - lo), hi + (hi - lo), size=(300, 3)).astype(np.float32)
    on = pts[rng.choice(len(pts), 200)]  # at the points, nothing excluded: distance 0 first
    tree = kdtree.KDTree(pts, neighbors._LEAF_SIZE)
    for q in (far, on):
        assert_tree_exact(tree, pts, q, 9)
    ref = np.full(len(on), -1, dtype=np.int64)
    ref[::2] = rng.integers(0, len(pts), size=len(ref[::2]))
    assert_tree_exact(tree, pts, on, 9, ref)


def test_pure_tree_small_and_full_k(rng):
    one = np.array([[1.0, 2.0, 3.0]], np.float32)
    tree = kdtree.KDTree(one, 16)
    assert tree.size == 1 and tree.depth == 1
    assert_tree_exact(tree, one, uniform(rng, 5), 1)
    for n in (2, 5, 17, 40, 300):
        pts = uniform(rng, n)
        tree = kdtree.KDTree(pts, 16)
        own = np.arange(n, dtype=np.int64)
        assert_tree_exact(tree, pts, pts, n - 1, own)  # every other point
        assert_tree_exact(tree, pts, pts[:3], n)  # every point, nothing excluded
    same = np.zeros((300, 3), np.float32)
    assert_tree_exact(kdtree.KDTree(same, 16), same, same, 299, np.arange(300, dtype=np.int64))


def test_pure_tree_squared_distances_beyond_float32(rng, recwarn):
    """Distances above 1.8e19: float32 squared distances are inf (as the compiled tree's),
    means and k-th distances stay finite; no warning."""
    pts = beyond_float32(rng)
    tree = kdtree.KDTree(pts, 16)
    own = np.arange(500, dtype=np.int64)
    assert_tree_exact(tree, pts, pts, 4, own)
    assert np.isinf(tree.query(pts, 4, own)[1]).any()
    assert np.isfinite(tree.query_mean(pts, 4, own)).all()
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


@pytest.mark.parametrize("leaf_size", [1, 2, 7, 64])
def test_pure_tree_leaf_sizes(leaf_size, rng):
    pts = np.concatenate([clustered(rng)[:700], duplicated(rng)[:300]])
    tree = kdtree.KDTree(pts, leaf_size)
    assert_tree_exact(tree, pts, pts, 6, np.arange(len(pts), dtype=np.int64))


def test_pure_tree_blocks_and_threads(monkeypatch, rng):
    """Results do not depend on the block sizes nor on the thread count."""
    pts = np.concatenate([far_outliers(rng), duplicate_clusters(rng)])
    own = np.arange(len(pts), dtype=np.int64)
    tree = kdtree.KDTree(pts, 16)
    ref = tree.query(pts, 8, own, 1), tree.query_mean(pts, 8, own, 1)
    monkeypatch.setattr(kdtree, "_BLOCK_QUERIES", 300)
    monkeypatch.setattr(kdtree, "_BLOCK_CANDIDATES", 4000)
    for threads in (1, 3, 0):
        (idx, d2), mean = tree.query(pts, 8, own, threads), tree.query_mean(pts, 8, own, threads)
        np.testing.assert_array_equal(idx, ref[0][0])
        np.testing.assert_array_equal(d2, ref[0][1])
        np.testing.assert_array_equal(mean, ref[1])
    monkeypatch.setattr(kdtree, "_BLOCK_CANDIDATES", 64)  # one query per padded group
    rows = rng.choice(len(pts), 300, replace=False)
    idx, d2 = tree.query(pts[rows], 8, own[rows], 2)
    np.testing.assert_array_equal(idx, ref[0][0][rows])
    np.testing.assert_array_equal(d2, ref[0][1][rows])
    assert_tree_exact(tree, pts, pts[:300], 8, own[:300])


def test_pure_tree_low_level(rng):
    pts = uniform(rng, 5000)
    tree = kdtree.KDTree(pts, 16)
    assert tree.size == 5000 and tree.leaf_size == 16
    assert 10 <= tree.depth <= 16
    assert tree.node_count == 2**tree.depth - 1
    order = tree.order()
    assert order.dtype == np.int64
    np.testing.assert_array_equal(np.sort(order), np.arange(5000))
    # spatially coherent: consecutive points in tree order are near each other
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1)
    assert np.median(step) < 0.2 * np.median(np.linalg.norm(np.diff(pts, axis=0), axis=1))
    idx, d2 = tree.query(pts[:0], 3)
    assert idx.shape == (0, 3) and d2.shape == (0, 3)
    # runs of duplicates are listed once per member
    dup = duplicate_clusters(rng)
    np.testing.assert_array_equal(np.sort(kdtree.KDTree(dup, 16).order()), np.arange(len(dup)))
    with pytest.raises(ValueError, match="leaf_size must be >= 1"):
        kdtree.KDTree(pts, 0)


def test_pure_tree_large_duplicate_run_is_fast(rng):
    """100k identical points cost about as much as one point (no pairwise work)."""
    import time

    pts = np.concatenate([np.full((100_000, 3), 0.25, np.float32), uniform(rng, 5000)])
    t0 = time.perf_counter()
    tree = kdtree.KDTree(pts, 16)
    kth = tree.query_kth(pts, 25, np.arange(len(pts), dtype=np.int64))
    assert time.perf_counter() - t0 < 30  # a few seconds at most; pairwise work would take minutes
    assert np.all(kth[:100_000] == 0)
    idx, _ = tree.query(pts[:3], 25, np.arange(3, dtype=np.int64))
    np.testing.assert_array_equal(idx[0], np.arange(1, 26))  # the 25 smallest other indices
    np.testing.assert_array_equal(idx[2], np.delete(np.arange(26), 2))


# --------------------------------------------------------------------------- #
# the numpy tree against the compiled one, and neighbors without _core
# --------------------------------------------------------------------------- #
def assert_same_as_native(native_tree, pure_tree, queries, k, self_index):
    """Bit-identical distances, means and k-th distances; identical indices except
    where points tie at a row's k-th distance (the compiled tree keeps any of them)."""
    n_idx, n_d2 = native_tree.query(queries, k, self_index, 0)
    p_idx, p_d2 = pure_tree.query(queries, k, self_index, 0)
    np.testing.assert_array_equal(p_d2, n_d2)
    below = n_d2 < n_d2[:, -1:]  # strictly nearer than the k-th: no choice among ties
    np.testing.assert_array_equal(p_idx[below], n_idx[below])
    np.testing.assert_array_equal(pure_tree.query_mean(queries, k, self_index, 0),
                                  native_tree.query_mean(queries, k, self_index, 0))
    np.testing.assert_array_equal(pure_tree.query_kth(queries, k, self_index, 0),
                                  native_tree.query_kth(queries, k, self_index, 0))
    return p_idx, n_idx


@needs_core
@pytest.mark.parametrize("name", sorted(PURE_DATASETS))
@pytest.mark.parametrize("k", [1, 3, 25])
def test_pure_tree_matches_native(name, k, rng):
    pts = PURE_DATASETS[name](rng)
    own = np.arange(len(pts), dtype=np.int64)
    nt = native.core().KDTree(pts, neighbors._LEAF_SIZE)
    pt = kdtree.KDTree(pts, neighbors._LEAF_SIZE)
    p_idx, n_idx = assert_same_as_native(nt, pt, pts, k, own)
    if name in ("uniform", "clustered", "far_outliers"):
        np.testing.assert_array_equal(p_idx, n_idx)  # no ties: the whole index arrays agree
    q = rng.uniform(pts.min(axis=0), pts.max(axis=0), size=(400, 3)).astype(np.float32)
    assert_same_as_native(nt, pt, q, k, None)


@needs_core
@pytest.mark.parametrize("name", ["uniform", "clustered", "far_outliers"])
def test_neighbors_without_core_match_native(name, monkeypatch, rng):
    pts = PURE_DATASETS[name](rng)
    queries = rng.uniform(-2, 2, size=(500, 3)).astype(np.float32)
    sub = np.sort(rng.choice(len(pts), 300, replace=False))
    ref = np.full(len(pts), -1, dtype=np.int64)
    ref[sub] = np.arange(sub.size)
    calls = [
        lambda: neighbors.knn(pts, 7),
        lambda: neighbors.knn(pts, 4, queries, chunk_size=123),
        lambda: neighbors.mean_knn_distance(pts, 25),
        lambda: neighbors.mean_knn_distance(pts[sub], 3, pts, reference_index=ref),
        lambda: neighbors.kth_knn_distance(pts, 10, chunk_size=500),
    ]
    with_core = [call() for call in calls]
    monkeypatch.setenv("MLX3D_NO_CORE", "1")
    assert not native.available()
    assert isinstance(neighbors._tree(pts), kdtree.KDTree)
    for call, expected in zip(calls, with_core):
        got = call()
        for a, b in zip(got if isinstance(got, tuple) else (got,),
                        expected if isinstance(expected, tuple) else (expected,)):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["clustered", "grid", "duplicate_clusters"])
def test_neighbors_without_core_exact(name, monkeypatch, rng):
    monkeypatch.setenv("MLX3D_NO_CORE", "1")
    pts = PURE_DATASETS[name](rng)
    own = np.arange(len(pts), dtype=np.int64)
    idx, d2, mean, kth = exact_oracle(pts, pts, 5, own)
    got_idx, got_dist = neighbors.knn(pts, 5, chunk_size=333)
    np.testing.assert_array_equal(got_idx, idx)
    np.testing.assert_array_equal(got_dist, np.sqrt(d2))
    np.testing.assert_array_equal(neighbors.mean_knn_distance(pts, 5), mean)
    np.testing.assert_array_equal(neighbors.kth_knn_distance(pts, 5), kth)


def test_neighbors_without_core_progress_and_interrupt(monkeypatch, rng):
    monkeypatch.setenv("MLX3D_NO_CORE", "1")
    pts = uniform(rng, 1000)
    calls = []
    neighbors.mean_knn_distance(pts, 4, chunk_size=300, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(300, 1000), (600, 1000), (900, 1000), (1000, 1000)]

    def stop(done, total):
        if done >= 600:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        neighbors.knn(pts, 4, chunk_size=300, progress=stop)
    with pytest.raises(ValueError, match=r"k=1000 exceeds the 999 available neighbours"):
        neighbors.knn(pts, 1000)


def test_pure_tree_splits_blocks_with_wide_bounds(monkeypatch, rng):
    """Queries far from every point (wide bounds, many leaves each) still match the oracle
    when a block's walk is over the pair limit and gets halved."""
    pts = uniform(rng, 3000)
    far = (rng.standard_normal((300, 3)) * 50).astype(np.float32)
    monkeypatch.setattr(kdtree, "_MAX_PAIRS", 500)
    assert_tree_exact(kdtree.KDTree(pts, 16), pts, far, 30)
