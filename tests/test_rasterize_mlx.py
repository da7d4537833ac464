"""The MLX tile rasterizer (mlx3d.render.raster_mlx, backend 'mlx') against the float64 numpy oracle of
tests/test_rasterize_cpu.py (the rasterizer rules of docs/guides/rendering.md, pixel by pixel) and its central finite
differences; its invariances (thread count, batch size); the C++ kernel where it is built."""

from __future__ import annotations

import mlx.core as mx
import numpy as np
import pytest

from mlx3d import native
from mlx3d.render import raster_mlx
from mlx3d.render.raster_cpu import set_num_threads
from mlx3d.render.raster_mlx import rasterize_mlx
from test_rasterize_cpu import FD_CASES, FWD_ATOL, assert_grads_close, bin_scene, fd_case, oracle, random_scene


def run(scene, width, height, tile=16, **kw):
    return [np.array(a) for a in rasterize_mlx(*scene, width, height, tile, **kw)]


def grads(scene, width, height, tile, cot_accum, cot_alpha, **kw):
    offsets, ids = mx.array(scene[4]), mx.array(scene[5])

    def f(m, c, fe, o):
        return rasterize_mlx(m, c, fe, o, offsets, ids, width, height, tile, **kw)[:2]

    _, vjps = mx.vjp(f, [mx.array(x) for x in scene[:4]], [mx.array(cot_accum), mx.array(cot_alpha)])
    return [np.array(v) for v in vjps]


@pytest.mark.parametrize("seed,n,channels,tile,width,height", [(0, 30, 1, 16, 40, 30), (1, 120, 3, 16, 40, 30), (2, 200, 5, 8, 37, 23)])
def test_forward_matches_oracle(seed, n, channels, tile, width, height):
    scene = random_scene(seed, n, width, height, channels, tile=tile, opacity=(0.05, 1.5))
    accum, alpha, last = run(scene, width, height, tile)
    want_accum, want_alpha, want_last = oracle(*scene, width, height, tile)
    np.testing.assert_allclose(accum, want_accum, atol=FWD_ATOL)
    np.testing.assert_allclose(alpha, want_alpha, atol=FWD_ATOL)
    np.testing.assert_array_equal(last, want_last)
    assert want_alpha.max() > 0.5 and (want_last > 0).mean() > 0.5


@pytest.mark.parametrize("seed,n,channels,opacity,sigma,width,height,hard", FD_CASES)
def test_gradients_match_finite_differences(seed, n, channels, opacity, sigma, width, height, hard):
    tile = 8
    scene, cot_accum, cot_alpha, want = fd_case(seed, n, channels, opacity, sigma, width, height, hard, tile)
    for budget in (raster_mlx.BATCH_ELEMENTS, 200):  # one batch, and many (entries carried across batches)
        got = grads(scene, width, height, tile, cot_accum, cot_alpha, batch_elements=budget)
        for name, g, w in zip(("means2d", "conics", "features", "opacities"), got, want):
            assert g.shape == w.shape and g.dtype == np.float32 and np.abs(w).max() > 0
            assert_grads_close(g, w, name)


def test_results_do_not_depend_on_the_thread_count():
    width, height, channels = 70, 50, 3
    scene = random_scene(1, 400, width, height, channels, opacity=(0.3, 1.5))
    rng = np.random.default_rng(0)
    cots = rng.normal(size=(height, width, channels)).astype(np.float32), rng.normal(size=(height, width)).astype(np.float32)
    results = []
    try:
        for threads in (1, 2, 3):
            set_num_threads(threads)
            raster_mlx._CPU_STREAMS = None
            results.append(run(scene, width, height, batch_elements=20000) + grads(scene, width, height, 16, *cots, batch_elements=20000))
    finally:
        set_num_threads(None)
        raster_mlx._CPU_STREAMS = None
    for other in results[1:]:
        for a, b in zip(results[0], other):
            np.testing.assert_array_equal(a, b)


def test_batch_size_changes_only_rounding():
    width, height = 64, 48
    scene = random_scene(3, 500, width, height, 3, opacity=(0.3, 1.5))
    one = run(scene, width, height)
    many = run(scene, width, height, batch_elements=3000)
    np.testing.assert_allclose(many[0], one[0], atol=1e-6)
    np.testing.assert_allclose(many[1], one[1], atol=1e-6)
    np.testing.assert_array_equal(many[2], one[2])


def test_skip_rules_and_stops():
    width = height = 8
    means = np.array([[3.5, 3.5]] * 4 + [[1.5, 6.5]], np.float32)
    conics = np.array([[0.1, 0, 0.1]] * 4 + [[1e30, 0, 1e30]], np.float32)  # the last: alpha at its own pixel centre only
    opac = np.array([0.99, 0.99, 0.99, 0.99, 1.0], np.float32)  # four opaque layers stop the pixels under them
    feats = np.arange(15, dtype=np.float32).reshape(5, 3)
    offsets, ids = bin_scene(means, np.full(5, 6.0), np.arange(5.0), width, height, 8)
    scene = (means, conics, feats, opac, offsets, ids)
    accum, alpha, last = run(scene, width, height, 8)
    want = oracle(*scene, width, height, 8)
    np.testing.assert_allclose(accum, want[0], atol=FWD_ATOL)
    np.testing.assert_allclose(alpha, want[1], atol=FWD_ATOL)
    np.testing.assert_array_equal(last, want[2])
    assert last[3, 3] < 4 and alpha[3, 3] > 0.98 and last[6, 1] == 5  # stopped before the last layer; the point drawn where it lies


def test_nan_gaussians_are_skipped():
    width = height = 16
    scene = random_scene(5, 40, width, height, 3)
    means, conics, feats, opac, offsets, ids = (np.array(a) for a in scene)
    bad = means.copy(), conics.copy(), opac.copy()
    bad[0][0] = np.nan
    bad[1][1, 0] = np.nan
    bad[2][2] = np.nan
    with_nan = run((bad[0], bad[1], feats, bad[2], offsets, ids), width, height)
    keep = np.ones(len(opac), np.float32)
    keep[:3] = 0  # the same Gaussians made invisible
    without = run((means, conics, feats, opac * keep, offsets, ids), width, height)
    for a, b in zip(with_nan, without):
        np.testing.assert_array_equal(a, b)


def test_nothing_to_draw():
    for n in (0, 3):
        m, c, f, o = np.ones((n, 2)), np.ones((n, 3)), np.ones((n, 2)), np.ones(n)
        accum, alpha, last = run((m, c, f, o, np.zeros(3, np.int32), np.zeros(0, np.int32)), 20, 12)
        assert accum.shape == (12, 20, 2) and not accum.any() and not alpha.any() and not last.any()


@pytest.mark.skipif(not native.available(), reason="compares with mlx3d._core, which is not available here")
def test_matches_the_cpu_kernel():
    from mlx3d.render.raster_cpu import rasterize_cpu

    width, height, channels = 83, 61, 4
    scene = random_scene(7, 600, width, height, channels, opacity=(0.2, 1.5))
    cpu = [np.array(a) for a in rasterize_cpu(*scene, width, height)]
    pure = run(scene, width, height)
    np.testing.assert_allclose(pure[0], cpu[0], atol=1e-6)
    np.testing.assert_allclose(pure[1], cpu[1], atol=1e-6)
    np.testing.assert_array_equal(pure[2], cpu[2])
