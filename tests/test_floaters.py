"""Floater removal (mlx3d.floaters) on synthetic surfaces with planted outliers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mlx3d import floaters, neighbors
from mlx3d.errors import NonFiniteError


def noisy_sphere(rng, n):
    v = rng.standard_normal((n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v * (1.0 + 0.002 * rng.standard_normal((n, 1)))


def wavy_plane(rng, n):
    xy = rng.uniform(-1.5, 1.5, size=(n, 2))
    z = 0.1 * np.sin(3 * xy[:, :1]) * np.cos(2 * xy[:, 1:]) + 0.002 * rng.standard_normal((n, 1))
    return np.concatenate([xy, z], axis=1)


def planted(seed, surface, n=50_000, frac=0.01, lo=0.3, hi=3.0):
    """Surface points plus ~frac outliers at random distances [lo, hi] off it."""
    rng = np.random.default_rng(seed)
    surf = surface(rng, n)
    n_out = int(round(frac * n))
    anchors = surf[rng.integers(0, n, n_out)]
    u = rng.standard_normal((n_out, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    out = anchors + u * rng.uniform(lo, hi, size=(n_out, 1))
    # drop outliers that landed back near the surface
    near = neighbors.kth_knn_distance(surf, 1, out) < lo / 2
    out = out[~near]
    pts = np.concatenate([surf, out]).astype(np.float32)
    is_out = np.r_[np.zeros(n, bool), np.ones(len(out), bool)]
    perm = rng.permutation(len(pts))
    return pts[perm], is_out[perm]


def recall_precision(result, is_out):
    removed = ~result.keep
    tp = np.count_nonzero(removed & is_out)
    return tp / is_out.sum(), tp / max(np.count_nonzero(removed), 1)


@pytest.fixture(scope="module", params=[("sphere", 0), ("wavy", 1)])
def cloud(request):
    surface = {"sphere": noisy_sphere, "wavy": wavy_plane}[request.param[0]]
    return planted(request.param[1], surface)


# --------------------------------------------------------------------------- #
# recall / precision
# --------------------------------------------------------------------------- #
def test_statistical_finds_planted_outliers(cloud):
    pts, is_out = cloud
    assert 0.008 < is_out.mean() < 0.012
    res = floaters.statistical_outliers(pts, k=25, std_ratio=2.0)
    recall, precision = recall_precision(res, is_out)
    assert recall >= 0.95 and precision >= 0.95, (recall, precision, res)
    assert res.method == "statistical"
    assert res.kept + res.removed == len(pts)
    assert res.kept == np.count_nonzero(res.keep)
    assert res.keep.dtype == bool and res.keep.shape == (len(pts),)
    assert res.scores.shape == (len(pts),)


def test_radius_finds_planted_outliers(cloud):
    pts, is_out = cloud
    res = floaters.radius_outliers(pts, radius=0.1, min_neighbours=5)
    recall, precision = recall_precision(res, is_out)
    assert recall >= 0.95 and precision >= 0.95, (recall, precision, res)
    assert res.method == "radius" and res.threshold == pytest.approx(0.1)


def test_defaults_remove_far_outliers_and_keep_surface():
    rng = np.random.default_rng(7)
    surf = noisy_sphere(rng, 50_000)
    u = rng.standard_normal((20, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    far = u * rng.uniform(20, 100, size=(20, 1))
    pts = np.concatenate([surf, far]).astype(np.float32)
    res = floaters.statistical_outliers(pts)  # k=25, std_ratio=10.5
    assert res.removed == 20
    assert not res.keep[-20:].any() and res.keep[:-20].all()


# --------------------------------------------------------------------------- #
# the rules, checked against independent numpy implementations
# --------------------------------------------------------------------------- #
def brute_force_distances(pts):
    p = pts.astype(np.float64)
    d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    return np.sort(d, axis=1)


@pytest.mark.parametrize("k, std_ratio", [(5, 1.0), (25, 2.0), (25, 10.5)])
def test_statistical_rule_matches_numpy(k, std_ratio):
    rng = np.random.default_rng(3)
    pts = np.concatenate(
        [rng.standard_normal((380, 3)) * 0.1, rng.uniform(-3, 3, size=(20, 3))]
    ).astype(np.float32)
    d = brute_force_distances(pts)[:, :k].mean(axis=1)
    threshold = d.mean() + std_ratio * d.std(ddof=0)
    expected_keep = ~(d > threshold)
    res = floaters.statistical_outliers(pts, k=k, std_ratio=std_ratio)
    assert res.threshold == pytest.approx(threshold, rel=1e-6)
    np.testing.assert_allclose(res.scores, d, rtol=1e-6)
    np.testing.assert_array_equal(res.keep, expected_keep)
    assert res.removed == np.count_nonzero(~expected_keep)


def test_radius_rule_is_inclusive_and_matches_numpy():
    # unit grid: neighbours at exactly the radius count
    g = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = g.astype(np.float32)
    d = brute_force_distances(pts)
    for radius, m in [(1.0, 6), (1.0, 4), (1.5, 12), (0.99, 1), (2.0, 20)]:
        count = (d <= radius).sum(axis=1)
        res = floaters.radius_outliers(pts, radius, m)
        np.testing.assert_array_equal(res.keep, count >= m)
    # interior points have exactly 6 neighbours at distance 1
    res = floaters.radius_outliers(pts, 1.0, 6)
    interior = np.all((g > 0) & (g < 5), axis=1)
    np.testing.assert_array_equal(res.keep, interior)


def test_radius_zero_min_neighbours_keeps_all():
    pts = np.random.default_rng(0).random((50, 3))
    res = floaters.radius_outliers(pts, 0.0, 0)
    assert res.keep.all() and res.removed == 0


def test_duplicates_are_not_floaters():
    rng = np.random.default_rng(5)
    pts = np.repeat(rng.random((500, 3)), 3, axis=0).astype(np.float32)
    res = floaters.radius_outliers(pts, 0.0, 2)  # two other copies at distance 0
    assert res.keep.all()
    assert not floaters.radius_outliers(pts, 0.0, 3).keep.any()
    same = np.ones((100, 3))
    res = floaters.statistical_outliers(same, k=5)
    assert res.keep.all() and res.threshold == 0.0


# --------------------------------------------------------------------------- #
# determinism and the result type
# --------------------------------------------------------------------------- #
def test_deterministic_across_runs_threads_and_chunks(cloud):
    pts, _ = cloud
    a = floaters.statistical_outliers(pts, 25, 2.0, num_threads=1)
    b = floaters.statistical_outliers(pts, 25, 2.0, num_threads=2, chunk_size=4096)
    c = floaters.statistical_outliers(pts, 25, 2.0)
    for other in (b, c):
        np.testing.assert_array_equal(a.keep, other.keep)
        np.testing.assert_array_equal(a.scores, other.scores)
        assert a.threshold == other.threshold
    r1 = floaters.radius_outliers(pts, 0.1, 5, num_threads=1)
    r2 = floaters.radius_outliers(pts, 0.1, 5, num_threads=2, chunk_size=999)
    np.testing.assert_array_equal(r1.keep, r2.keep)


def test_result_is_frozen():
    res = floaters.statistical_outliers(np.random.default_rng(0).random((100, 3)), k=5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.kept = 0
    with pytest.raises(ValueError):
        res.keep[0] = False  # read-only array
    np.testing.assert_array_equal(res.floaters, ~res.keep)
    assert "statistical" in repr(res)


# --------------------------------------------------------------------------- #
# argument errors
# --------------------------------------------------------------------------- #
P = np.random.default_rng(0).random((10, 3))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: floaters.statistical_outliers(P, k=10), r"k=10 must be smaller than the number of points \(10\)"),
        (lambda: floaters.statistical_outliers(P, k=0), r"k must be >= 1, got k=0"),
        (lambda: floaters.statistical_outliers(P, k=3, std_ratio=-1), r"std_ratio must be >= 0"),
        (lambda: floaters.statistical_outliers(P, k=3, std_ratio=float("nan")), r"std_ratio must be finite"),
        (lambda: floaters.statistical_outliers(P[:, :2], k=3), r"points must have shape \(N, 3\)"),
        (lambda: floaters.statistical_outliers(np.zeros((0, 3))), r"points is empty"),
        (lambda: floaters.radius_outliers(P, -0.1, 3), r"radius must be >= 0"),
        (lambda: floaters.radius_outliers(P, "1", 3), r"radius must be a real number"),
        (lambda: floaters.radius_outliers(P, 0.1, -1), r"min_neighbours must be >= 0"),
        (lambda: floaters.radius_outliers(P, 0.1, 1.5), r"min_neighbours must be an integer"),
        (lambda: floaters.radius_outliers(P, 0.1, 10), r"min_neighbours=10 must be smaller than the number of points \(10\)"),
        (lambda: floaters.radius_outliers(P[:, :2], 0.1, 0), r"points must have shape \(N, 3\)"),
    ],
)
def test_bad_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("fn", [
    lambda p: floaters.statistical_outliers(p, k=3),
    lambda p: floaters.radius_outliers(p, 0.1, 2),
    lambda p: floaters.radius_outliers(p, 0.1, 0),
])
def test_nan_points_raise(fn):
    p = P.copy()
    p[[1, 4], 0] = np.nan
    with pytest.raises(NonFiniteError, match=r"points has 2 of 10 rows with non-finite"):
        fn(p)


def test_progress_is_forwarded():
    pts = np.random.default_rng(2).random((500, 3))
    calls = []
    floaters.statistical_outliers(pts, k=5, chunk_size=200, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(200, 500), (400, 500), (500, 500)]
    calls.clear()
    floaters.radius_outliers(pts, 0.1, 2, progress=lambda d, t: calls.append((d, t)))
    assert calls[-1] == (500, 500)
