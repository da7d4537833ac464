"""The CPU rasterizer (mlx3d.render.raster_cpu, the C++ MLX primitives) against
a float64 numpy oracle written here from the rasterizer rules of docs/guides/rendering.md.

The oracle loops over pixels and, for each, over its tile's Gaussians in
flatten_ids order, exactly as the rules read. Binning is also rebuilt here from
radii and depths with the tile rule of docs/guides/rendering.md. Gradients are checked against
central finite differences of the oracle on scenes generated with a margin
from every discontinuity (the 1/255 skip, the 0.99 clamp, the 1e-4 stop), so
that finite differences are meaningful.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import mlx.core as mx
import numpy as np
import pytest

from mlx3d import native
from mlx3d.render import raster_cpu
from mlx3d.render.raster_cpu import get_num_threads, rasterize_cpu, set_num_threads
from core_marks import needs_core

pytestmark = needs_core

# The rules' constants as the float32 kernels hold them (0.99f, 1/255.f, 1e-4f):
# with float64 constants, a pixel where two clamped Gaussians meet
# (T = (1 - 0.99)^2 = 1e-4) would stop in float32 and not in float64.
ALPHA_MAX = float(np.float32(0.99))
ALPHA_MIN = float(np.float32(1.0) / np.float32(255.0))
T_MIN = float(np.float32(1e-4))

FWD_ATOL = 1e-5  # forward vs oracle (accum, alpha), absolute
# gradients vs central differences of the float64 oracle, per parameter group:
# |kernel - fd| <= GRAD_RTOL * |fd| + GRAD_ATOL * max|fd of the group|
GRAD_RTOL = 1e-4
GRAD_ATOL = 1e-5


# --------------------------------------------------------------------------- #
# binning and oracle (float64, literal)
# --------------------------------------------------------------------------- #
def bin_scene(means, radii, depths, width, height, tile):
    """tile_offsets, flatten_ids by the tile rule of docs/guides/rendering.md (loops, no vectorisation)."""
    tiles_x = -(-width // tile)
    tiles_y = -(-height // tile)
    lists = [[] for _ in range(tiles_x * tiles_y)]
    for g in range(len(means)):
        r = float(radii[g])
        if r <= 0:
            continue
        mx_, my_ = float(means[g][0]), float(means[g][1])
        x0 = max(math.floor((mx_ - r) / tile), 0)
        x1 = min(math.floor((mx_ + r) / tile), tiles_x - 1)
        y0 = max(math.floor((my_ - r) / tile), 0)
        y1 = min(math.floor((my_ + r) / tile), tiles_y - 1)
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                lists[ty * tiles_x + tx].append(g)
    offsets = [0]
    ids = []
    for lst in lists:
        lst.sort(key=lambda g: (float(np.float32(depths[g])), g))
        ids.extend(lst)
        offsets.append(len(ids))
    return np.array(offsets, dtype=np.int32), np.array(ids, dtype=np.int32)


def oracle(means, conics, feats, opac, offsets, ids, width, height, tile, tiles=None, margins=None):
    """Returns accum (H,W,C), alpha (H,W), last (H,W) in float64 / int.

    With ``tiles`` only those tiles' pixels are rendered (others stay 0). With a
    ``margins`` dict, the smallest distances of any evaluated (pixel, Gaussian)
    pair to the skip / clamp / stop thresholds are recorded there.
    """
    m = np.asarray(means, np.float64)
    con = np.asarray(conics, np.float64)
    f = np.asarray(feats, np.float64)
    o = np.asarray(opac, np.float64)
    channels = f.shape[1]
    tiles_x = -(-width // tile)
    accum = np.zeros((height, width, channels))
    alpha_out = np.zeros((height, width))
    last = np.zeros((height, width), dtype=np.int64)
    if tiles is None:
        tiles = range(len(offsets) - 1)
    for t in tiles:
        tx, ty = t % tiles_x, t // tiles_x
        entries = [int(g) for g in ids[offsets[t] : offsets[t + 1]]]
        for i in range(ty * tile, min((ty + 1) * tile, height)):
            for j in range(tx * tile, min((tx + 1) * tile, width)):
                px, py = j + 0.5, i + 0.5
                T = 1.0
                n_contrib = 0
                acc = np.zeros(channels)
                for k, g in enumerate(entries):
                    dx, dy = m[g, 0] - px, m[g, 1] - py
                    a, b, c = con[g]
                    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
                    if power > 0:
                        continue
                    raw = o[g] * math.exp(power)
                    alpha = min(ALPHA_MAX, raw)
                    if margins is not None:
                        margins["clamp"] = min(margins.get("clamp", 1.0), abs(raw - ALPHA_MAX))
                        margins["skip"] = min(margins.get("skip", 1.0), abs(alpha - ALPHA_MIN))
                    if alpha < ALPHA_MIN:
                        continue
                    next_T = T * (1.0 - alpha)
                    if margins is not None:
                        margins["stop"] = min(margins.get("stop", 1.0), abs(next_T - T_MIN))
                        margins["clamped"] = margins.get("clamped", 0) + (raw > ALPHA_MAX)
                        margins["stopped"] = margins.get("stopped", 0) + (next_T < T_MIN)
                    if next_T < T_MIN:
                        break
                    acc += f[g] * alpha * T
                    T = next_T
                    n_contrib = k + 1
                accum[i, j] = acc
                alpha_out[i, j] = 1.0 - T
                last[i, j] = n_contrib
    return accum, alpha_out, last


def random_scene(seed, n, width, height, channels, tile=16, opacity=(0.05, 0.95), sigma=(1.0, 6.0)):
    """float32 Gaussians (random anisotropic covariances) and their binning."""
    rng = np.random.default_rng(seed)
    means = np.stack([rng.uniform(-4, width + 4, n), rng.uniform(-4, height + 4, n)], 1)
    s = rng.uniform(*sigma, (n, 2))
    theta = rng.uniform(0, np.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    cov = rot @ (s[:, :, None] ** 2 * np.swapaxes(rot, -1, -2))
    inv = np.linalg.inv(cov)
    conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    feats = rng.uniform(-1, 1, (n, channels))
    opac = np.minimum(rng.uniform(*opacity, n), 1.0)  # a range above 1 gives many opacities of 1
    depths = rng.uniform(1, 10, n)
    radii = np.ceil(3 * s.max(1))
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    means, conics, feats, opac = f32(means), f32(conics), f32(feats), f32(opac)
    offsets, ids = bin_scene(means, radii, depths, width, height, tile)
    return means, conics, feats, opac, offsets, ids


def run(scene, width, height, tile=16, num_threads=None):
    accum, alpha, last = rasterize_cpu(*scene, width, height, tile, num_threads=num_threads)
    mx.eval(accum, alpha, last)
    return np.array(accum), np.array(alpha), np.array(last)


# --------------------------------------------------------------------------- #
# forward
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("seed,n,channels", [(0, 30, 1), (1, 120, 3), (2, 200, 5)])
def test_forward_matches_oracle(seed, n, channels):
    width, height = 40, 30  # 16x16 tiles: the right and bottom tiles are partial
    scene = random_scene(seed, n, width, height, channels)
    accum, alpha, last = run(scene, width, height)
    ref_accum, ref_alpha, ref_last = oracle(*scene, width, height, 16)
    assert accum.shape == (height, width, channels) and accum.dtype == np.float32
    assert alpha.shape == (height, width) and alpha.dtype == np.float32
    assert last.shape == (height, width) and last.dtype == np.int32
    np.testing.assert_allclose(accum, ref_accum, rtol=0, atol=FWD_ATOL)
    np.testing.assert_allclose(alpha, ref_alpha, rtol=0, atol=FWD_ATOL)
    np.testing.assert_array_equal(last, ref_last)
    assert ref_alpha.max() > 0.5 and (ref_last > 0).mean() > 0.5  # a non-trivial scene


def test_forward_other_tile_sizes_and_float64_inputs():
    width, height = 37, 21
    scene = random_scene(3, 80, width, height, 2, tile=8)
    accum, alpha, last = run(scene, width, height, tile=8)
    ref_accum, ref_alpha, ref_last = oracle(*scene, width, height, 8)
    np.testing.assert_allclose(accum, ref_accum, atol=FWD_ATOL)
    np.testing.assert_array_equal(last, ref_last)
    # float64 / int64 inputs are cast (float32, int32) and give the same result
    means, conics, feats, opac, offsets, ids = scene
    wide = (means.astype(np.float64), conics.astype(np.float64), feats.astype(np.float64),
            opac.astype(np.float64), offsets.astype(np.int64), ids.astype(np.int64))
    accum64, alpha64, last64 = run(wide, width, height, tile=8)
    np.testing.assert_array_equal(accum64, accum)
    np.testing.assert_array_equal(alpha64, alpha)
    np.testing.assert_array_equal(last64, last)


def test_tiles_of_over_64_pixel_blocks(monkeypatch):
    """32-pixel tiles (128 or more pixel blocks, so each entry's block bitset
    spans several words) with over 64 entries per tile (several groups of the
    transposed block lists): the forward pass matches the oracle, and culled
    and unculled kernels (spans, or every block) give the same bits."""
    width, height, tile = 70, 45, 32
    scene = random_scene(31, 500, width, height, 3, tile=tile)
    offsets = scene[4]
    assert np.diff(offsets).max() > 64
    accum, alpha, last = run(scene, width, height, tile=tile)
    ref_accum, ref_alpha, ref_last = oracle(*scene, width, height, tile)
    np.testing.assert_allclose(accum, ref_accum, rtol=0, atol=FWD_ATOL)
    np.testing.assert_allclose(alpha, ref_alpha, rtol=0, atol=FWD_ATOL)
    np.testing.assert_array_equal(last, ref_last)
    for isa in ("best", "baseline"):
        _variant(monkeypatch, isa)
        monkeypatch.setenv("MLX3D_RASTER_CULL", "0")
        full = all_outputs(scene, width, height, tile)
        monkeypatch.delenv("MLX3D_RASTER_CULL")
        culled = all_outputs(scene, width, height, tile)
        for name, a, b in zip(FORWARD_OUTPUTS + GRADIENTS, full, culled):
            assert a.tobytes() == b.tobytes(), (isa, name)


def test_early_stop_keeps_transmittance_above_threshold():
    width = height = 8
    n = 1000
    means = np.tile(np.array([[3.5, 4.5]], np.float32), (n, 1))  # centre of pixel (row 4, col 3)
    conics = np.tile(np.array([[0.5, 0.0, 0.5]], np.float32), (n, 1))
    feats = np.ones((n, 1), np.float32)
    depths = np.arange(n, dtype=np.float32)
    offsets, ids = bin_scene(means, np.full(n, 4.0), depths, width, height, 8)
    for opacity, contributions in ((0.99, 1), (0.5, 13)):
        scene = (means, conics, feats, np.full(n, opacity, np.float32), offsets, ids)
        accum, alpha, last = run(scene, width, height, tile=8)
        ref_accum, ref_alpha, ref_last = oracle(*scene, width, height, 8)
        # at the centre alpha = opacity: T = (1 - opacity)^k while >= 1e-4
        assert last[4, 3] == contributions == ref_last[4, 3]
        t_final = (1.0 - np.float32(opacity)) ** contributions
        assert t_final >= T_MIN and t_final * (1 - opacity) < T_MIN
        assert alpha[4, 3] == pytest.approx(1.0 - t_final, abs=1e-6)
        assert accum[4, 3, 0] == pytest.approx(1.0 - t_final, abs=1e-5)  # features are 1
        assert 1.0 - alpha.max() >= T_MIN * (1 - 1e-5)  # no pixel goes below the threshold
        np.testing.assert_allclose(accum, ref_accum, atol=FWD_ATOL)
        np.testing.assert_allclose(alpha, ref_alpha, atol=FWD_ATOL)
        np.testing.assert_array_equal(last, ref_last)


def test_skip_rules_low_alpha_and_positive_power():
    width = height = 8
    means = np.array([[2.5, 2.5], [5.5, 5.5], [5.25, 2.5]], np.float32)
    conics = np.array([[1, 0, 1], [1, 0, 1], [-1, 0, -1]], np.float32)  # the last one: power > 0 everywhere
    feats = np.array([[1.0], [2.0], [4.0]], np.float32)
    opac = np.array([ALPHA_MIN * 0.999, ALPHA_MIN * 1.02, 0.9], np.float32)
    offsets, ids = bin_scene(means, np.full(3, 3.0), np.arange(3.0), width, height, 8)
    accum, alpha, last = run((means, conics, feats, opac, offsets, ids), width, height, tile=8)
    assert accum[2, 2, 0] == 0 and alpha[2, 2] == 0 and last[2, 2] == 0  # alpha < 1/255: skipped
    assert accum[5, 5, 0] == pytest.approx(2.0 * ALPHA_MIN * 1.02, rel=1e-5)  # just above: kept
    assert last[5, 5] == 2  # the second entry of the tile's list
    assert accum[2, 5, 0] == 0 and last[2, 5] == 0  # power > 0: skipped despite opacity 0.9
    ref_accum, _, ref_last = oracle(means, conics, feats, opac, offsets, ids, width, height, 8)
    np.testing.assert_allclose(accum, ref_accum, atol=FWD_ATOL)
    np.testing.assert_array_equal(last, ref_last)


def test_nan_gaussians_are_skipped():
    width = height = 8
    means = np.array([[3.5, 3.5], [3.5, 3.5], [3.5, 3.5]], np.float32)
    conics = np.array([[np.nan, 0, 1], [0.5, 0, 0.5], [0.5, 0, 0.5]], np.float32)
    feats = np.array([[5.0], [1.0], [7.0]], np.float32)
    opac = np.array([0.5, np.nan, 0.5], np.float32)
    offsets, ids = bin_scene(means, np.full(3, 3.0), np.arange(3.0), width, height, 8)
    accum, alpha, last = run((means, conics, feats, opac, offsets, ids), width, height, tile=8)
    assert np.isfinite(accum).all() and np.isfinite(alpha).all()
    assert accum[3, 3, 0] == pytest.approx(3.5) and last[3, 3] == 3  # only the third Gaussian


# --------------------------------------------------------------------------- #
# gradients
# --------------------------------------------------------------------------- #
def grads_cpu(scene, width, height, tile, cot_accum, cot_alpha, num_threads=None):
    means, conics, feats, opac, offsets, ids = scene
    offsets, ids = mx.array(offsets), mx.array(ids)

    def f(m, c, fe, o):
        accum, alpha, _ = rasterize_cpu(m, c, fe, o, offsets, ids, width, height, tile, num_threads=num_threads)
        return accum, alpha

    primals = [mx.array(x) for x in (means, conics, feats, opac)]
    _, vjps = mx.vjp(f, primals, [mx.array(cot_accum), mx.array(cot_alpha)])
    mx.eval(vjps)
    return [np.array(v) for v in vjps]


def fd_grads(scene, width, height, tile, cot_accum, cot_alpha):
    """Central differences of L = <accum, cot_accum> + <alpha, cot_alpha> (oracle)."""
    means, conics, feats, opac, offsets, ids = [np.array(x) for x in scene]
    params = [means.astype(np.float64), conics.astype(np.float64), feats.astype(np.float64), opac.astype(np.float64)]
    tiles_of = [[] for _ in range(len(means))]
    for t in range(len(offsets) - 1):
        for g in ids[offsets[t] : offsets[t + 1]]:
            tiles_of[g].append(t)

    def loss(ps, tiles):
        accum, alpha, _ = oracle(*ps, offsets, ids, width, height, tile, tiles=tiles)
        return float((accum * cot_accum).sum() + (alpha * cot_alpha).sum())

    out = []
    for p_idx, p in enumerate(params):
        g = np.zeros_like(p)
        for idx in np.ndindex(p.shape):
            gauss = idx[0]
            if not tiles_of[gauss]:
                continue
            eps = 1e-4 if p_idx == 0 else 1e-6 * max(1.0, abs(p[idx]))
            plus = [q.copy() for q in params]
            minus = [q.copy() for q in params]
            plus[p_idx][idx] += eps
            minus[p_idx][idx] -= eps
            g[idx] = (loss(plus, tiles_of[gauss]) - loss(minus, tiles_of[gauss])) / (2 * eps)
        out.append(g)
    return out


def smooth_scene(seed, n, width, height, channels, tile, opacity, sigma, hard):
    """A random scene whose (pixel, Gaussian) pairs all keep a margin from the
    skip, clamp and stop thresholds (seeds are tried in order until one does).
    With ``hard``, the scene must also have clamped pairs and stopped pixels."""
    for s in range(seed, seed + 200):
        scene = random_scene(s, n, width, height, channels, tile=tile, opacity=opacity, sigma=sigma)
        m = {}
        oracle(*scene, width, height, tile, margins=m)
        if hard and not (m.get("clamped", 0) and m.get("stopped", 0)):
            continue
        if m.get("skip", 1) > 2e-6 and m.get("clamp", 1) > 1e-5 and m.get("stop", 1) > 1e-8:
            return scene
    raise AssertionError("no smooth scene found")


def assert_grads_close(got, want, name):
    scale = max(np.abs(want).max(), 1e-12)
    err = np.abs(got - want)
    bound = GRAD_RTOL * np.abs(want) + GRAD_ATOL * scale
    worst = np.unravel_index(np.argmax(err - bound), err.shape)
    assert (err <= bound).all(), f"{name}: got {got[worst]} want {want[worst]} at {worst} (scale {scale})"


FD_CASES = [  # seed, n, channels, opacity, sigma, width, height, hard (the rasterizers' finite-difference scenes)
    (10, 12, 3, (0.1, 1.0), (0.8, 3.0), 22, 19, False),  # mostly translucent, partial tiles
    (30, 30, 1, (0.7, 1.4), (1.5, 3.5), 16, 16, True),  # clamped pairs and stopped pixels
]


def fd_case(seed, n, channels, opacity, sigma, width, height, hard, tile=8):
    """One ``FD_CASES`` scene with random cotangents and its finite-difference gradients:
    (scene, cot_accum, cot_alpha, want)."""
    scene = smooth_scene(seed, n, width, height, channels, tile, opacity, sigma, hard)
    rng = np.random.default_rng(seed + 1)
    cot_accum = rng.normal(size=(height, width, channels)).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    return scene, cot_accum, cot_alpha, fd_grads(scene, width, height, tile, cot_accum, cot_alpha)


@pytest.mark.parametrize("seed,n,channels,opacity,sigma,width,height,hard", FD_CASES)
def test_gradients_match_finite_differences(seed, n, channels, opacity, sigma, width, height, hard):
    tile = 8
    scene, cot_accum, cot_alpha, want = fd_case(seed, n, channels, opacity, sigma, width, height, hard, tile)
    got = grads_cpu(scene, width, height, tile, cot_accum, cot_alpha)
    for name, g, w in zip(("means2d", "conics", "features", "opacities"), got, want):
        assert g.shape == w.shape and g.dtype == np.float32
        assert np.abs(w).max() > 0
        assert_grads_close(g, w, name)


def test_value_and_grad_and_clamp():
    """mx.value_and_grad works; a Gaussian clamped at 0.99 on every pixel it
    touches gets zero opacity / mean / conic gradients but a feature gradient."""
    width = height = 8
    means = np.array([[3.5, 3.5], [4.2, 3.9]], np.float32)
    conics = np.array([[1e-6, 0, 1e-6], [0.3, 0.05, 0.4]], np.float32)  # the first is flat: alpha = 0.99
    feats = np.array([[1.0, 0.5], [0.2, 0.7]], np.float32)
    opac = np.array([1.0, 0.6], np.float32)
    offsets, ids = bin_scene(means, np.full(2, 3.0), np.array([2.0, 1.0]), width, height, 8)
    args = [mx.array(x) for x in (means, conics, feats, opac)]

    def loss(m, c, f, o):
        accum, alpha, _ = rasterize_cpu(m, c, f, o, offsets, ids, width, height, 8)
        return (accum * accum).sum() + alpha.sum()

    value, grads = mx.value_and_grad(loss, argnums=(0, 1, 2, 3))(*args)
    mx.eval(value, grads)
    accum, alpha, _ = oracle(means, conics, feats, opac, offsets, ids, width, height, 8)
    assert float(value) == pytest.approx((accum * accum).sum() + alpha.sum(), rel=1e-5)
    g_means, g_conics, g_feats, g_opac = (np.array(g) for g in grads)
    assert g_opac[0] == 0 and (g_means[0] == 0).all() and (g_conics[0] == 0).all()
    assert (g_feats[0] != 0).all()
    assert g_opac[1] != 0 and (g_means[1] != 0).all() and (g_conics[1] != 0).all()


@pytest.mark.parametrize("channels", [3, 5])
def test_background_in_the_kernel_is_the_mlx_expression_bit_for_bit(channels):
    # composite()'s CPU path adds the background in the kernel's threads: the same bits as the MLX
    # expression accum + (1 - alpha) * bg on the plain output, forward and backward
    width, height = 45, 33
    scene = random_scene(11, 150, width, height, channels)
    means, conics, feats, opac, offsets, ids = scene
    offsets, ids = mx.array(offsets), mx.array(ids)
    rng = np.random.default_rng(5)
    bg = mx.array(rng.uniform(0, 1, channels).astype(np.float32))
    cot_accum = mx.array(rng.normal(size=(height, width, channels)).astype(np.float32))
    cot_alpha = mx.array(rng.normal(size=(height, width)).astype(np.float32))

    def fused(m, c, fe, o, b):
        accum, alpha, _ = rasterize_cpu(m, c, fe, o, offsets, ids, width, height, background=b)
        return accum, alpha

    def expression(m, c, fe, o, b):
        accum, alpha, _ = rasterize_cpu(m, c, fe, o, offsets, ids, width, height)
        return accum + (1.0 - alpha)[..., None] * b, alpha

    primals = [mx.array(x) for x in (means, conics, feats, opac)] + [bg]
    outs = {}
    for name, f in (("fused", fused), ("expression", expression)):
        value, grads = mx.vjp(f, primals, [cot_accum, cot_alpha])
        outs[name] = [np.array(v) for v in value] + [np.array(g) for g in grads]
    for got, want in zip(outs["fused"][:-1], outs["expression"][:-1]):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(outs["fused"][-1], outs["expression"][-1], rtol=1e-6)  # d/dbackground: a sum over pixels
    assert np.abs(outs["fused"][-1]).max() > 0
    # a scalar background is every channel's
    a, _, _ = rasterize_cpu(*primals[:4], offsets, ids, width, height, background=0.25)
    b, _, _ = rasterize_cpu(*primals[:4], offsets, ids, width, height, background=mx.full((channels,), 0.25))
    np.testing.assert_array_equal(np.array(a), np.array(b))
    with pytest.raises(ValueError, match="background"):
        rasterize_cpu(*primals[:4], offsets, ids, width, height, background=mx.zeros((channels + 1,)))


def test_non_contributing_gaussians_get_exactly_zero_gradient():
    width, height = 24, 16
    rng = np.random.default_rng(5)
    # a wall of 2 opaque Gaussians in front, 3 Gaussians behind it (never reached),
    # 1 binned Gaussian too faint everywhere (alpha < 1/255) and 1 not binned at all
    means = np.array([[12, 8], [12, 8], [10, 6], [14, 9], [6, 7], [20, 10], [3, 3]], np.float32)
    # the wall is flat enough to be clamped at 0.99 on every pixel
    conics = np.array([[1e-6, 0, 1e-6]] * 2 + [[0.2, 0.01, 0.3]] * 5, np.float32)
    feats = rng.uniform(0.1, 1, (7, 3)).astype(np.float32)
    opac = np.array([0.995, 0.995, 0.8, 0.8, 0.8, 0.003, 0.8], np.float32)
    depths = np.array([1, 2, 3, 4, 5, 0.5, 7], np.float32)  # the faint one is in front
    radii = np.array([40, 40, 5, 5, 5, 5, 0], np.float32)
    offsets, ids = bin_scene(means, radii, depths, width, height, 8)
    scene = (means, conics, feats, opac, offsets, ids)
    cot_accum = rng.normal(size=(height, width, 3)).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    g_means, g_conics, g_feats, g_opac = grads_cpu(scene, width, height, 8, cot_accum, cot_alpha)
    # every pixel: the first wall Gaussian contributes (alpha 0.99), the second stops it
    _, alpha, _ = oracle(*scene, width, height, 8)
    np.testing.assert_allclose(alpha, ALPHA_MAX, rtol=1e-6)
    for g in range(1, 7):
        assert (g_means[g] == 0).all() and (g_conics[g] == 0).all()
        assert (g_feats[g] == 0).all() and g_opac[g] == 0
    assert (g_feats[0] != 0).all()


def test_gradients_finite_in_hard_cases():
    width = height = 8
    means = np.array([[3.5, 3.5], [3.5, 3.5], [3.5, 3.5], [2.5, 5.5], [5.5, 2.5], [4.1, 4.7], [1.5, 1.5]], np.float32)
    conics = np.array(
        [
            [1e30, 0, 1e30],  # zero-area: alpha only at its own pixel centre
            [0, 0, 0],  # infinitely wide
            [1e38, -1e38, 1e38],  # overflows to inf - inf = NaN off-centre: skipped
            [0.5, 0.0, 0.5],
            [0.5, 0.49, 0.5],  # nearly singular
            [-1, 0, -1],  # not positive definite: power > 0, skipped
            [3e-8, 0, 3e-8],
        ],
        np.float32,
    )
    opac = np.array([1.0, 0.999999, 1.0, 0.99, 0.98, 1.0, 1e-30], np.float32)
    feats = np.ones((7, 3), np.float32)
    offsets, ids = bin_scene(means, np.full(7, 6.0), np.arange(7.0), width, height, 8)
    scene = (means, conics, feats, opac, offsets, ids)
    rng = np.random.default_rng(0)
    cot_accum = rng.normal(size=(height, width, 3)).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    accum, alpha, _ = run(scene, width, height, tile=8)
    assert np.isfinite(accum).all() and np.isfinite(alpha).all()
    grads = grads_cpu(scene, width, height, 8, cot_accum, cot_alpha)
    for g in grads:
        assert np.isfinite(g).all()
    assert np.abs(grads[2]).max() > 0


# --------------------------------------------------------------------------- #
# threads, empty inputs, errors
# --------------------------------------------------------------------------- #
def test_thread_count_gives_bitwise_identical_results():
    width, height = 100, 70
    scene = random_scene(7, 1500, width, height, 3)
    rng = np.random.default_rng(8)
    cot_accum = rng.normal(size=(height, width, 3)).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    outs = {}
    for threads in (1, 2, 3):
        fwd = run(scene, width, height, num_threads=threads)
        bwd = grads_cpu(scene, width, height, 16, cot_accum, cot_alpha, num_threads=threads)
        outs[threads] = fwd + tuple(bwd)
    for threads in (2, 3):
        for a, b in zip(outs[1], outs[threads]):
            assert a.tobytes() == b.tobytes()
    assert np.abs(outs[1][3]).max() > 0


def test_thread_count_gives_bitwise_identical_gradients_over_many_chunks():
    """Large enough that the backward pass runs its tiles in several chunks and zeroes and splits
    the per-Gaussian records on several threads: the same bits for any thread count, and no entry
    lost between chunks: with dL/daccum = 1 and dL/dalpha = 0, the feature gradients sum to the
    sum of the pixels' alphas (each pixel's weights sum to its alpha)."""
    width = height = 128
    scene = random_scene(11, 80_000, width, height, 3, sigma=(4.0, 12.0))
    assert len(scene[5]) > 2 * ((1 << 20) // 9)  # more than two chunks of slots (kSlotBudget, K = 6 + 3 fields)
    cot_accum = np.ones((height, width, 3), np.float32)
    cot_alpha = np.zeros((height, width), np.float32)
    grads = {t: grads_cpu(scene, width, height, 16, cot_accum, cot_alpha, num_threads=t) for t in (1, 2, 3)}
    for t in (2, 3):
        for a, b in zip(grads[1], grads[t]):
            assert a.tobytes() == b.tobytes()
    _, alpha, _ = run(scene, width, height, num_threads=1)
    feature_grads = grads[1][2].astype(np.float64).sum(0)
    np.testing.assert_allclose(feature_grads, alpha.astype(np.float64).sum(), rtol=1e-4)


def test_cpu_variants_agree(monkeypatch):
    """The baseline kernel variant (SSE2 / NEON) and the one picked for this CPU
    (AVX2 where available) give the same forward outputs and gradients."""
    from mlx3d import native

    monkeypatch.delenv("MLX3D_RASTER_ISA", raising=False)
    lanes = native.core().rasterizer_simd_lanes()
    assert lanes in (1, 4, 8)
    monkeypatch.setenv("MLX3D_RASTER_ISA", "baseline")
    if native.core().rasterizer_simd_lanes() == lanes:
        pytest.skip(f"one CPU variant on this machine ({lanes} lanes)")
    width, height = 50, 35
    scene = random_scene(9, 400, width, height, 3)
    rng = np.random.default_rng(9)
    cot_accum = rng.normal(size=(height, width, 3)).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    base = run(scene, width, height) + tuple(grads_cpu(scene, width, height, 16, cot_accum, cot_alpha))
    monkeypatch.delenv("MLX3D_RASTER_ISA")
    best = run(scene, width, height) + tuple(grads_cpu(scene, width, height, 16, cot_accum, cot_alpha))
    for a, b in zip(base[:3], best[:3]):
        assert a.tobytes() == b.tobytes()
    for a, b in zip(base[3:], best[3:]):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * np.abs(b).max())


def test_empty_inputs():
    width, height = 20, 12
    tiles = 2
    cases = {
        "N=0": (np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), np.zeros(tiles + 1), np.zeros(0)),
        "M=0": (np.ones((3, 2)), np.ones((3, 3)), np.ones((3, 4)), np.ones(3), np.zeros(tiles + 1), np.zeros(0)),
    }
    for name, (m, c, f, o, off, ids) in cases.items():
        off, ids = off.astype(np.int32), ids.astype(np.int32)
        accum, alpha, last = run((m, c, f, o, off, ids), width, height)
        assert accum.shape == (height, width, 4) and not accum.any(), name
        assert alpha.shape == (height, width) and not alpha.any(), name
        assert last.shape == (height, width) and not last.any(), name

        def loss(m_, c_, f_, o_):
            a, al, _ = rasterize_cpu(m_, c_, f_, o_, off, ids, width, height)
            return a.sum() + al.sum()

        grads = mx.grad(loss, argnums=(0, 1, 2, 3))(*[mx.array(x, dtype=mx.float32) for x in (m, c, f, o)])
        mx.eval(grads)
        for g, x in zip(grads, (m, c, f, o)):
            assert g.shape == x.shape and not np.array(g).any(), name


def test_input_validation():
    width, height = 20, 12
    scene = random_scene(0, 10, width, height, 3)
    means, conics, feats, opac, off, ids = scene

    def call(**kw):
        args = dict(means2d=means, conics=conics, features=feats, opacities=opac, tile_offsets=off,
                    flatten_ids=ids, width=width, height=height)
        args.update(kw)
        return rasterize_cpu(**args)

    bad = [
        (dict(means2d=means[:, :1]), "means2d"),
        (dict(means2d=means[:, 0]), "means2d"),
        (dict(conics=conics[:5]), "conics"),
        (dict(features=feats[:, 0]), "features"),
        (dict(features=feats[:, :0]), "features"),
        (dict(opacities=opac[:, None]), "opacities"),
        (dict(tile_offsets=off[:-1]), "tile_offsets"),
        (dict(tile_offsets=off.astype(np.float32)), "tile_offsets"),
        (dict(flatten_ids=ids.astype(np.float32)), "flatten_ids"),
        (dict(flatten_ids=ids[:, None]), "flatten_ids"),
        (dict(means2d=means.astype(bool)), "means2d"),
        (dict(opacities=opac.astype(np.complex64)), "opacities"),
        (dict(width=0), "width"),
        (dict(height=-3), "height"),
        (dict(width=2.5), "width"),
        (dict(tile_size=0), "tile_size"),
        (dict(num_threads=-1), "num_threads"),
        (dict(flatten_ids=np.full_like(ids, 10)), "flatten_ids"),
        (dict(flatten_ids=np.full_like(ids, -1)), "flatten_ids"),
        (dict(tile_offsets=np.maximum(off - 1, 0)), "tile_offsets"),
        (dict(tile_offsets=off[::-1].copy()), "tile_offsets"),
    ]
    for kw, name in bad:
        with pytest.raises(ValueError, match=name):
            call(**kw)
    call()  # the unmodified call is fine
    call(num_threads=0)  # 0: all hardware threads


def test_jvp_raises_clear_error():
    width, height = 16, 16
    means, conics, feats, opac, off, ids = random_scene(0, 5, width, height, 1)
    primals = [mx.array(x) for x in (means, conics, feats, opac)]

    def f(m, c, fe, o):
        return rasterize_cpu(m, c, fe, o, off, ids, width, height)[0]

    with pytest.raises(Exception, match="jvp"):
        mx.eval(mx.jvp(f, primals, [mx.zeros_like(p) for p in primals]))


def test_num_threads_setting(monkeypatch):
    monkeypatch.setattr(raster_cpu, "_num_threads", None)
    monkeypatch.delenv("MLX3D_NUM_THREADS", raising=False)
    assert get_num_threads() >= 1
    monkeypatch.setenv("MLX3D_NUM_THREADS", "3")
    assert get_num_threads() == 3
    set_num_threads(1)
    assert get_num_threads() == 1
    set_num_threads(None)
    assert get_num_threads() == 3
    set_num_threads(0)
    assert get_num_threads() == 3
    monkeypatch.setenv("MLX3D_NUM_THREADS", "zero")
    with pytest.raises(ValueError, match="MLX3D_NUM_THREADS"):
        get_num_threads()
    with pytest.raises(ValueError, match="num_threads"):
        set_num_threads(-2)
    with pytest.raises(ValueError, match="num_threads"):
        set_num_threads(1.5)


def test_worker_pool_after_fork_and_with_concurrent_callers():
    """The kernels' threads come from a pool kept between calls. A forked child, where the parent's
    workers do not exist, gets its own pool: tile binning (a native call that needs no MLX evaluation,
    which MLX itself does not support after a fork) runs there on 2 threads. Callers on several threads at
    once (the pool runs one job; the others start their own threads) get the same bits as one caller."""
    import os
    import signal
    import threading
    import time

    from mlx3d import native

    rng = np.random.default_rng(5)
    n = 20_000
    means = (rng.random((n, 2)) * [640, 480]).astype(np.float32)
    radii = rng.uniform(0.5, 40, n).astype(np.float32)
    depths = rng.uniform(0.1, 10, n).astype(np.float32)
    core = native.core()

    def bins():  # 2 threads; bin_tiles releases the GIL
        offsets, ids = core.bin_tiles(means, radii, depths, 640, 480, 16, 2)
        return np.array(offsets).tobytes() + np.array(ids).tobytes()

    alone = bins()  # the pool's worker exists from here on
    pid = os.fork()
    if pid == 0:  # the child: exit status 0 when it bins the same
        signal.alarm(30)
        try:
            os._exit(0 if bins() == alone else 1)
        except BaseException:
            os._exit(2)
    deadline = time.monotonic() + 60
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail("the forked child hung binning on 2 threads")
        time.sleep(0.05)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0, f"the forked child's status: {status}"

    results, errors = [], []

    def caller():
        try:
            for _ in range(10):
                results.append(bins())
        except BaseException as e:  # reported below
            errors.append(e)

    threads = [threading.Thread(target=caller) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors and len(results) == 40 and all(r == alone for r in results)


# --------------------------------------------------------------------------- #
# sub-tile culling (the kernels skip pixel blocks outside each Gaussian's
# reach): results are bitwise those of evaluating every (pixel, Gaussian) pair
# --------------------------------------------------------------------------- #
FROZEN = Path(__file__).resolve().parent / "data" / "raster_frozen.npz"
FROZEN_INPUTS = ("means", "conics", "feats", "opac", "offsets", "ids", "width", "height", "tile")
FORWARD_OUTPUTS = ("accum", "alpha", "last", "final_T")
GRADIENTS = ("g_means", "g_conics", "g_feats", "g_opac")


def _frozen_tools():
    """tests/data/make_raster_frozen.py (its cotangents and outputs())."""
    path = FROZEN.parent / "make_raster_frozen.py"
    spec = importlib.util.spec_from_file_location("make_raster_frozen", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _variant(monkeypatch, isa):
    if isa == "baseline":
        monkeypatch.setenv("MLX3D_RASTER_ISA", "baseline")
    else:
        monkeypatch.delenv("MLX3D_RASTER_ISA", raising=False)
    return native.core().rasterizer_simd_lanes()


@pytest.mark.parametrize("cull", ["1", "0"])
def test_frozen_outputs_are_bit_identical(monkeypatch, cull):
    """Outputs (accum, alpha, last, final_T) and gradients that the kernel wrote
    without culling pixel blocks (tests/data/raster_frozen.npz, seeded scenes:
    translucent, opaque, very anisotropic, faint, degenerate and non-finite
    parameters, isolated Gaussians, alpha = 1/255 on pixel centres, signed
    zeros; 1 to 5 channels; tiles of 8, 12 and 16) are reproduced bit for bit,
    by each kernel variant, for 1 and 3 threads, with culling on and off."""
    data = np.load(FROZEN)
    tools = _frozen_tools()
    names = sorted(k[: -len("/means")] for k in data.files if k.endswith("/means"))
    assert len(names) >= 7
    monkeypatch.setenv("MLX3D_RASTER_CULL", cull)
    checked_grads, frozen_widths = 0, 0
    for isa in ("best", "baseline"):
        lanes = _variant(monkeypatch, isa)
        # gradients depend on the lane width (lane sums), forward outputs do not
        grads_from = {int(data["best_lanes"]): "best", int(data["baseline_lanes"]): "baseline"}.get(lanes)
        frozen_widths += grads_from is not None
        for name in names:
            case = {k: data[f"{name}/{k}"] for k in FROZEN_INPUTS}
            for threads in (1, 3):
                got = tools.outputs(case, num_threads=threads)
                for k in FORWARD_OUTPUTS:
                    assert got[k].tobytes() == data[f"{name}/best/{k}"].tobytes(), (name, isa, threads, k)
                if grads_from is None:
                    continue
                for k in GRADIENTS:
                    assert got[k].tobytes() == data[f"{name}/{grads_from}/{k}"].tobytes(), (name, isa, threads, k)
                    checked_grads += 1
    # a build whose lanes match neither frozen width (one lane: compilers without vector extensions) has
    # its gradients checked by the finite-difference tests only
    assert checked_grads > 0 or frozen_widths == 0


def adversarial_conics(rng, n, sigma=(0.05, 60.0), aniso=1e5):
    """float32 conics of random rotated covariances: std-devs log-uniform in
    ``sigma``, anisotropy log-uniform up to ``aniso`` (past the culling's 1e4
    condition bound), some nearly singular and some with b = -0.0."""
    major = np.exp(rng.uniform(np.log(sigma[0]), np.log(sigma[1]), n))
    minor = major / np.exp(rng.uniform(0, np.log(aniso), n))
    theta = rng.uniform(0, np.pi, n)
    theta[::5] = rng.choice([0.0, np.pi / 2, np.pi / 4], len(theta[::5]))
    cos, sin = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    s = np.stack([major, minor], 1)
    cov = rot @ (s[:, :, None] ** 2 * np.swapaxes(rot, -1, -2))
    inv = np.linalg.inv(cov)
    conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1).astype(np.float32)
    conics[7::11, 1] = -0.0
    return conics


def adversarial_opacities(rng, n):
    """Log-uniform in [1e-3, 20], with many within 1e-5 of 1/255 (float32)."""
    opac = np.exp(rng.uniform(np.log(1e-3), np.log(20.0), n))
    near = rng.random(n) < 0.3
    opac[near] = ALPHA_MIN * (1 + rng.uniform(-1e-5, 1e-5, near.sum()))
    opac[::13] = ALPHA_MIN
    opac[1::17] = 1.0
    return opac.astype(np.float32)


def isolated_scene(seed, tile, tiles_x, tiles_y, per_tile, channels):
    """Each tile lists its own ``per_tile`` Gaussians, centred anywhere from 1.5
    tiles before to 1.5 tiles after the tile: every (pixel, Gaussian) decision
    shows in the outputs."""
    rng = np.random.default_rng(seed)
    tiles = tiles_x * tiles_y
    n = tiles * per_tile
    t = np.arange(n) // per_tile
    origin = np.stack([(t % tiles_x) * tile, (t // tiles_x) * tile], 1)
    means = (origin + rng.uniform(-1.5 * tile, 2.5 * tile, (n, 2))).astype(np.float32)
    conics = adversarial_conics(rng, n)
    opac = adversarial_opacities(rng, n)
    feats = rng.uniform(-1, 1, (n, channels)).astype(np.float32)
    offsets = np.arange(0, n + 1, per_tile, dtype=np.int32)
    ids = np.arange(n, dtype=np.int32)
    return (means, conics, feats, opac, offsets, ids), tiles_x * tile, tiles_y * tile


def boundary_scene(seed, tile, tiles_x, tiles_y):
    """One Gaussian per tile, its mean placed so that alpha = 1/255 (within a
    relative 1e-6 of the exponent) falls on a pixel centre of the tile."""
    rng = np.random.default_rng(seed)
    n = tiles_x * tiles_y
    conics = adversarial_conics(rng, n, sigma=(0.3, 30.0), aniso=1e3)
    opac = np.exp(rng.uniform(np.log(0.005), np.log(1.5), n)).astype(np.float32)
    c64, o64 = conics.astype(np.float64), opac.astype(np.float64)
    t = np.arange(n)
    pix = np.stack([(t % tiles_x) * tile, (t // tiles_x) * tile], 1) + rng.integers(0, tile, (n, 2)) + 0.5
    ang = rng.uniform(0, 2 * np.pi, n)
    u = np.stack([np.cos(ang), np.sin(ang)], 1)
    q = c64[:, 0] * u[:, 0] ** 2 + 2 * c64[:, 1] * u[:, 0] * u[:, 1] + c64[:, 2] * u[:, 1] ** 2
    dist = np.sqrt(2 * np.log(o64 / ALPHA_MIN) / q) * (1 + rng.uniform(-1e-6, 1e-6, n))
    means = (pix + u * dist[:, None]).astype(np.float32)
    feats = rng.uniform(0.5, 1, (n, 1)).astype(np.float32)
    offsets = np.arange(n + 1, dtype=np.int32)
    return (means, conics, feats, opac, offsets, np.arange(n, dtype=np.int32)), tiles_x * tile, tiles_y * tile


def all_outputs(scene, width, height, tile, cot_seed=0):
    """Forward outputs (with final_T) and gradients for random cotangents."""
    args = [mx.array(x) for x in scene]
    fwd = native.core().rasterize_forward(*args, width, height, tile, 2)
    rng = np.random.default_rng(cot_seed)
    cot_accum = rng.normal(size=(height, width, scene[2].shape[1])).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    grads = grads_cpu(scene, width, height, tile, cot_accum, cot_alpha, num_threads=2)
    mx.eval(fwd)
    return [np.array(a) for a in fwd] + grads


@pytest.mark.parametrize("isa", ["best", "baseline"])
def test_culling_changes_no_bit(monkeypatch, isa):
    """Culled and unculled kernels agree bit for bit on adversarial scenes:
    isolated Gaussians (one or a few per tile list, anywhere around the tile),
    alpha = 1/255 on pixel centres, extreme anisotropy and opacities near
    1/255; tiles of 8, 13, 16 and 32 pixels; 1, 3 and 7 channels."""
    _variant(monkeypatch, isa)
    scenes = [
        (isolated_scene(1, 16, 24, 16, 1, 1), 16),
        (isolated_scene(2, 16, 16, 12, 3, 3), 16),
        (isolated_scene(3, 13, 12, 10, 2, 7), 13),
        (isolated_scene(4, 8, 24, 20, 1, 3), 8),
        (isolated_scene(5, 32, 8, 6, 4, 3), 32),
        (boundary_scene(6, 16, 24, 16), 16),
        (boundary_scene(7, 13, 16, 16), 13),
    ]
    kept = 0
    for (scene, width, height), tile in scenes:
        monkeypatch.setenv("MLX3D_RASTER_CULL", "0")
        full = all_outputs(scene, width, height, tile)
        monkeypatch.delenv("MLX3D_RASTER_CULL")
        culled = all_outputs(scene, width, height, tile)
        names = FORWARD_OUTPUTS + GRADIENTS
        for name, a, b in zip(names, full, culled):
            assert a.tobytes() == b.tobytes(), (tile, width, height, name)
        kept += int((full[2] > 0).sum())
    assert kept > 10000  # the scenes do composite something


def test_culling_on_random_and_dense_scenes(monkeypatch):
    """Culled and unculled kernels agree bit for bit on ordinary scenes
    (random_scene, partial tiles) and on a dense one with early stops."""
    width, height = 70, 45
    cases = [random_scene(21, 600, width, height, 3), random_scene(22, 300, width, height, 4, sigma=(0.3, 2.0)),
             random_scene(23, 1500, width, height, 2, opacity=(0.5, 1.5), sigma=(2.0, 12.0))]
    for scene in cases:
        monkeypatch.setenv("MLX3D_RASTER_CULL", "0")
        full = all_outputs(scene, width, height, 16, cot_seed=3)
        monkeypatch.delenv("MLX3D_RASTER_CULL")
        culled = all_outputs(scene, width, height, 16, cot_seed=3)
        for a, b in zip(full, culled):
            assert a.tobytes() == b.tobytes()
