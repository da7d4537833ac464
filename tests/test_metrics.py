"""Tests for mlx3d.training.metrics (L1, PSNR, SSIM, the 3DGS photometric loss)."""

import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.training.metrics import (
    PSNR_MAX_DB,
    gaussian_window,
    l1,
    mse,
    photometric_loss,
    photometric_loss_and_grad,
    psnr,
    ssim,
    ssim_map,
)

# ----------------------------------------------------------------------------
# float64 numpy reference (independent of the module: direct 2-D window)
# ----------------------------------------------------------------------------


def ref_window(size=11, sigma=1.5):
    """3DGS create_window: outer product of the normalised 1-D Gaussian."""
    x = np.arange(size, dtype=np.float64)
    g = np.array([math.exp(-((v - size // 2) ** 2) / (2.0 * sigma**2)) for v in x])
    g = g / g.sum()
    return np.outer(g, g)


def ref_filter(img, win):
    """Zero-padded 'same' 2-D correlation of (H, W, C) with ``win`` (k, k).

    Written with numpy sliding windows over the padded image, i.e. the full
    k x k window at every pixel (F.conv2d(padding=k // 2, groups=C)).
    """
    k = win.shape[0]
    r = k // 2
    p = np.pad(img, ((r, r), (r, r), (0, 0)))
    views = np.lib.stride_tricks.sliding_window_view(p, (k, k), axis=(0, 1))  # (H, W, C, k, k)
    return np.einsum("hwcij,ij->hwc", views, win)


def ref_ssim_map(a, b, size=11, sigma=1.5):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    win = ref_window(size, sigma)
    mu1, mu2 = ref_filter(a, win), ref_filter(b, win)
    s11 = ref_filter(a * a, win) - mu1**2
    s22 = ref_filter(b * b, win) - mu2**2
    s12 = ref_filter(a * b, win) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    return m.mean(axis=-1)


def ref_loss(a, b, lam=0.2, w=None):
    """(1 - lam) L1 + lam (1 - SSIM), weighted means over pixels."""
    q_l1 = np.abs(a - b).mean(axis=-1)
    q_ssim = ref_ssim_map(a, b)
    if w is None:
        w = np.ones(q_l1.shape)
    return (1 - lam) * (w * q_l1).sum() / w.sum() + lam * (1 - (w * q_ssim).sum() / w.sum())


def structured(h, w):
    """Edges, ramps, a disc and a checkerboard: SSIM's interesting regimes."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.zeros((h, w, 3))
    img[..., 0] = x / (w - 1)
    img[..., 1] = ((x // 4 + y // 4) % 2) * 0.8 + 0.1
    img[..., 2] = ((x - w / 2) ** 2 + (y - h / 3) ** 2 < (h / 4) ** 2) * 0.7 + 0.2 * y / h
    return img


def A(x):
    return mx.array(np.asarray(x, np.float32))


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# ----------------------------------------------------------------------------
# SSIM
# ----------------------------------------------------------------------------


def test_gaussian_window_matches_3dgs():
    g = gaussian_window(11, 1.5)
    np.testing.assert_allclose(np.outer(g, g), ref_window(11, 1.5), rtol=0, atol=1e-15)
    assert abs(g.sum() - 1) < 1e-15
    with pytest.raises(ValueError):
        gaussian_window(10, 1.5)
    with pytest.raises(ValueError):
        gaussian_window(11, 0.0)


@pytest.mark.parametrize("compiled", [True, False])
def test_ssim_random_matches_reference(rng, compiled):
    a = rng.random((37, 50, 3))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    want = ref_ssim_map(a, b)
    got = np.array(ssim_map(A(a), A(b), compiled=compiled))
    assert got.shape == (37, 50)
    # Per pixel, float32 cancellation in E[x^2] - mu^2 (divided by sigma^2 + C2
    # ~ 1e-3 in flat regions) costs up to a few 1e-5; the mean is 1e-5 exact.
    np.testing.assert_allclose(got, want, atol=5e-5, rtol=0)
    assert abs(ssim(A(a), A(b), compiled=compiled).item() - want.mean()) < 1e-5


def test_ssim_structured_matches_reference(rng):
    a = structured(48, 40)
    b = np.clip(0.9 * a + 0.05 + 0.05 * rng.standard_normal(a.shape), 0, 1)
    want = ref_ssim_map(a, b)
    np.testing.assert_allclose(np.array(ssim_map(A(a), A(b))), want, atol=5e-5, rtol=0)
    assert abs(ssim(A(a), A(b)).item() - want.mean()) < 1e-5
    # Uncorrelated images: low SSIM, still matching.
    c = rng.random(a.shape)
    assert abs(ssim(A(a), A(c)).item() - ref_ssim_map(a, c).mean()) < 1e-5


def test_ssim_other_window_and_tiny_image(rng):
    a, b = rng.random((9, 7, 3)), rng.random((9, 7, 3))  # smaller than the window
    assert abs(ssim(A(a), A(b)).item() - ref_ssim_map(a, b).mean()) < 1e-5
    a, b = rng.random((20, 24, 3)), rng.random((20, 24, 3))
    want = ref_ssim_map(a, b, size=7, sigma=1.0).mean()
    assert abs(ssim(A(a), A(b), window=7, sigma=1.0).item() - want) < 1e-5


def test_ssim_identity_and_batch(rng):
    a = rng.random((32, 32, 3))
    assert abs(ssim(A(a), A(a)).item() - 1.0) < 1e-6
    np.testing.assert_allclose(np.array(ssim_map(A(a), A(a))), 1.0, atol=1e-6)
    # Leading batch axes are filtered independently.
    b = rng.random((2, 16, 20, 3))
    c = rng.random((2, 16, 20, 3))
    got = np.array(ssim_map(A(b), A(c)))
    assert got.shape == (2, 16, 20)
    for i in range(2):
        np.testing.assert_allclose(got[i], ref_ssim_map(b[i], c[i]), atol=5e-5)


# ----------------------------------------------------------------------------
# PSNR / L1 / masks
# ----------------------------------------------------------------------------


def test_psnr_known_mse(rng):
    ref = rng.uniform(0.2, 0.8, (24, 30, 3))
    assert abs(psnr(A(ref + 0.1), A(ref)).item() - 20.0) < 1e-4
    assert abs(psnr(A(ref - 0.01), A(ref)).item() - 40.0) < 1e-3
    # MSE 0.01 from mixed signs, 3 channels.
    err = 0.1 * np.where(rng.random(ref.shape) < 0.5, -1.0, 1.0)
    assert abs(psnr(A(ref + err), A(ref)).item() - 20.0) < 1e-4
    assert abs(mse(A(ref + err), A(ref)).item() - 0.01) < 1e-7
    # Identical images: finite cap instead of +inf.
    p = psnr(A(ref), A(ref)).item()
    assert math.isfinite(p) and p == pytest.approx(PSNR_MAX_DB) and PSNR_MAX_DB == pytest.approx(100.0)


def test_l1_value(rng):
    a, b = rng.random((10, 12, 3)), rng.random((10, 12, 3))
    assert abs(l1(A(a), A(b)).item() - np.abs(a - b).mean()) < 1e-6


def test_masks_equal_metric_on_kept_region(rng):
    a, b = rng.random((20, 30, 3)), rng.random((20, 30, 3))
    m = np.zeros((20, 30), np.float32)
    m[3:15, 5:22] = 1
    crop = (slice(3, 15), slice(5, 22))
    assert abs(l1(A(a), A(b), mask=A(m)).item() - l1(A(a[crop]), A(b[crop])).item()) < 1e-6
    assert abs(psnr(A(a), A(b), mask=A(m)).item() - psnr(A(a[crop]), A(b[crop])).item()) < 1e-4
    # Arbitrary boolean mask: the mean over kept pixels.
    keep = rng.random((20, 30)) < 0.3
    want_l1 = np.abs(a - b)[keep].mean()
    want_psnr = -10 * np.log10(((a - b) ** 2)[keep].mean())
    assert abs(l1(A(a), A(b), mask=mx.array(keep)).item() - want_l1) < 1e-6
    assert abs(psnr(A(a), A(b), mask=keep).item() - want_psnr) < 1e-4
    # SSIM: the full-image map averaged with the weights.
    w = rng.random((20, 30))
    smap = ref_ssim_map(a, b)
    assert abs(ssim(A(a), A(b), mask=A(w)).item() - (w * smap).sum() / w.sum()) < 1e-5
    assert abs(ssim(A(a), A(b), mask=A(m)).item() - smap[crop].mean()) < 1e-5
    # Loss with weights.
    assert abs(photometric_loss(A(a), A(b), mask=A(w)).item() - ref_loss(a, b, 0.2, w)) < 1e-5
    # All-zero mask: zero, not NaN.
    assert l1(A(a), A(b), mask=mx.zeros((20, 30))).item() == 0.0


def test_bad_inputs():
    a = mx.zeros((8, 8, 3))
    with pytest.raises(ValueError):
        ssim(a, mx.zeros((8, 9, 3)))
    with pytest.raises(ValueError):
        l1(a, a, mask=mx.ones((8, 9)))
    with pytest.raises(ValueError):
        psnr(mx.zeros((8, 8)), mx.zeros((8, 8)))
    with pytest.raises(ValueError):
        photometric_loss(a, a, lambda_dssim=1.5)
    with pytest.raises(ValueError):
        ssim(a, a, window=4)


# ----------------------------------------------------------------------------
# the training loss: gradients, compiled vs plain
# ----------------------------------------------------------------------------


def _loss_fixture(rng, h=14, w=17):
    b = rng.uniform(0.1, 0.9, (h, w, 3))
    # Keep |a - b| >= 0.02 so finite differences never straddle the L1 kink.
    d = rng.uniform(0.02, 0.15, b.shape) * np.where(rng.random(b.shape) < 0.5, -1, 1)
    return b + d, b


def test_photometric_loss_value(rng):
    a, b = _loss_fixture(rng)
    for lam in (0.0, 0.2, 1.0):
        assert abs(photometric_loss(A(a), A(b), lam).item() - ref_loss(a, b, lam)) < 1e-5


@pytest.mark.parametrize("masked", [False, True])
def test_photometric_grad_matches_finite_differences(rng, masked):
    """MLX float32 gradient vs central differences of the float64 reference.

    Tolerance: |g - g_fd| <= 1e-3 * max|g_fd| per entry (float32 gradient,
    FD step 1e-6 on the float64 reference, truncation error ~1e-12), and
    directional derivatives to 1e-3 relative.
    """
    a, b = _loss_fixture(rng)
    w = rng.random(a.shape[:2]) if masked else None
    mask = None if w is None else A(w)
    g = np.array(mx.grad(lambda x: photometric_loss(x, A(b), 0.2, mask))(A(a)), np.float64)
    g2 = np.array(photometric_loss_and_grad(A(a), A(b), 0.2, mask)[1], np.float64)

    h = 1e-6
    idx = [tuple(rng.integers(0, s) for s in a.shape) for _ in range(40)]
    idx += [(0, 0, 0), (a.shape[0] - 1, a.shape[1] - 1, 2), (0, a.shape[1] // 2, 1)]  # borders
    g_fd = {}
    for i in idx:
        ap, am = a.copy(), a.copy()
        ap[i] += h
        am[i] -= h
        g_fd[i] = (ref_loss(ap, b, 0.2, w) - ref_loss(am, b, 0.2, w)) / (2 * h)
    scale = max(abs(v) for v in g_fd.values())
    for i, v in g_fd.items():
        assert abs(g[i] - v) <= 1e-3 * scale, (i, g[i], v)
        assert abs(g2[i] - v) <= 1e-3 * scale, (i, g2[i], v)
    for _ in range(3):
        v = rng.standard_normal(a.shape)
        dd = (ref_loss(a + h * v, b, 0.2, w) - ref_loss(a - h * v, b, 0.2, w)) / (2 * h)
        assert abs((g * v).sum() - dd) <= 1e-3 * abs(dd), ((g * v).sum(), dd)


def test_ssim_grad_wrt_both_inputs(rng):
    """The self-adjoint filter VJP is exact for either argument (float64 run)."""
    a, b = rng.random((12, 13, 3)), rng.random((12, 13, 3))
    f64 = mx.float64
    ga, gb = mx.grad(lambda x, y: ssim(x, y), argnums=(0, 1))(mx.array(a, dtype=f64), mx.array(b, dtype=f64))
    assert ga.dtype == f64 and gb.dtype == f64
    h = 1e-6
    for g, which in ((np.array(ga), 0), (np.array(gb), 1)):
        v = rng.standard_normal(a.shape)
        args_p = [a, b]
        args_m = [a, b]
        args_p[which] = args_p[which] + h * v
        args_m[which] = args_m[which] - h * v
        dd = (ref_ssim_map(*args_p).mean() - ref_ssim_map(*args_m).mean()) / (2 * h)
        assert abs((g * v).sum() - dd) <= 1e-7 * abs(dd), ((g * v).sum(), dd)


def test_compiled_and_plain_agree(rng):
    a, b = _loss_fixture(rng, 40, 33)
    w = A(rng.random((40, 33)))
    for mask in (None, w):
        l_c = photometric_loss(A(a), A(b), mask=mask, compiled=True).item()
        l_p = photometric_loss(A(a), A(b), mask=mask, compiled=False).item()
        assert abs(l_c - l_p) < 1e-6
        (v_c, g_c) = photometric_loss_and_grad(A(a), A(b), mask=mask, compiled=True)
        (v_p, g_p) = photometric_loss_and_grad(A(a), A(b), mask=mask, compiled=False)
        g_t = mx.grad(lambda x: photometric_loss(x, A(b), mask=mask))(A(a))
        assert abs(v_c.item() - v_p.item()) < 1e-6
        scale = np.abs(np.array(g_p)).max()
        np.testing.assert_allclose(np.array(g_c), np.array(g_p), atol=1e-5 * scale, rtol=0)
        np.testing.assert_allclose(np.array(g_t), np.array(g_p), atol=1e-5 * scale, rtol=0)
    np.testing.assert_allclose(
        np.array(ssim_map(A(a), A(b), compiled=True)), np.array(ssim_map(A(a), A(b), compiled=False)), atol=1e-6
    )
    # Shape changes retrace the compiled graph instead of failing.
    assert math.isfinite(photometric_loss(A(a[:20, :21]), A(b[:20, :21])).item())


# ----------------------------------------------------------------------------
# colour correction (mlx3d.training.colour)
# ----------------------------------------------------------------------------

from mlx3d.training.colour import apply_colour_map, colour_correct, fit_colour_map, identity_colour_map  # noqa: E402

# Gain, offset and channel mixing: an exposure and white-balance change.
KNOWN_MAP = np.array([[0.80, 0.10, 0.00, 0.06], [0.05, 0.70, 0.10, 0.10], [0.00, 0.15, 0.60, 0.20]])


def lstsq_map(x, y, w=None):
    """Independent oracle: weighted least squares on the design matrix [x, 1] (rows scaled by sqrt(w))."""
    x, y = x.reshape(-1, x.shape[-1]).astype(np.float64), y.reshape(-1, y.shape[-1]).astype(np.float64)
    d = np.hstack([x, np.ones((len(x), 1))])
    s = np.ones(len(x)) if w is None else np.sqrt(np.asarray(w, np.float64).reshape(-1))
    return np.linalg.lstsq(d * s[:, None], y * s[:, None], rcond=None)[0].T  # (C, C + 1)


def sse(a, b, w=None):
    e = ((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2).sum(-1)
    return float(e.sum() if w is None else (w * e).sum())


def test_colour_map_recovers_a_known_affine_map_and_cc_psnr_sees_through_it():
    img = structured(48, 40) * 0.9 + 0.05
    ref = img @ KNOWN_MAP[:, :3].T + KNOWN_MAP[:, 3]  # the ground truth: the render under a known colour map
    assert ref.min() > 0 and ref.max() < 1
    np.testing.assert_allclose(fit_colour_map(img, ref), KNOWN_MAP, atol=1e-9)
    render, truth = A(img), A(ref)
    corrected = colour_correct(render, truth)
    assert isinstance(corrected, mx.array) and corrected.shape == render.shape and corrected.dtype == mx.float32
    plain, cc = psnr(render, truth).item(), psnr(corrected, truth).item()
    assert plain < 25 and cc > 80, (plain, cc)
    assert ssim(corrected, truth).item() > 0.9999 > ssim(render, truth).item()


def test_colour_map_is_the_weighted_least_squares_optimum(rng):
    img = rng.random((30, 26, 3))
    ref = np.clip(np.sqrt(img) @ KNOWN_MAP[:, :3].T + 0.1 * rng.standard_normal((30, 26, 3)), 0, 1)  # no affine map fits exactly
    for w in (None, rng.random((30, 26)), rng.random((30, 26)) > 0.5):
        ww = None if w is None else w.astype(np.float64)
        fitted = fit_colour_map(img, ref, mask=w)
        np.testing.assert_allclose(fitted, lstsq_map(img, ref, ww), atol=1e-9)
        best = sse(apply_colour_map(img, fitted, clip=False), ref, ww)
        assert best < sse(img, ref, ww)
        for _ in range(20):  # every other map fits worse
            other = fitted + 1e-3 * rng.standard_normal(fitted.shape)
            assert sse(apply_colour_map(img, other, clip=False), ref, ww) > best
        # Clipping to [0, 1] only moves pixels towards ref: the corrected render never fits worse than the render.
        assert sse(colour_correct(img, ref, mask=w), ref, ww) <= best + 1e-12
    assert psnr(colour_correct(A(img), A(ref)), A(ref)).item() > psnr(A(img), A(ref)).item()


def test_a_mask_keeps_excluded_pixels_out_of_the_fit(rng):
    img = rng.random((20, 20, 3))
    ref = img @ KNOWN_MAP[:, :3].T + KNOWN_MAP[:, 3]
    keep = np.ones((20, 20), bool)
    keep[:, :7] = False
    ref[~keep] = rng.random((int((~keep).sum()), 3))  # e.g. a transient object only the photo shows
    np.testing.assert_allclose(fit_colour_map(img, ref, mask=keep), KNOWN_MAP, atol=1e-9)
    assert np.abs(fit_colour_map(img, ref) - KNOWN_MAP).max() > 0.05
    np.testing.assert_array_equal(fit_colour_map(img, ref, mask=np.zeros((20, 20))), identity_colour_map())


def test_colour_correction_is_idempotent_and_never_lowers_psnr(rng):
    img = rng.random((25, 31, 3)) * 0.8 + 0.1
    ref = np.clip(img @ KNOWN_MAP[:, :3].T + KNOWN_MAP[:, 3] + 0.02 * rng.standard_normal(img.shape), 0, 1)
    once = colour_correct(img, ref)
    assert once.min() > 0 and once.max() < 1  # nothing clipped: the second fit must find the identity
    np.testing.assert_allclose(fit_colour_map(once, ref), identity_colour_map(), atol=1e-9)
    np.testing.assert_allclose(colour_correct(once, ref), once, atol=1e-12)
    # A render already at the right colours is left as it is (identity map = least squares optimum).
    np.testing.assert_allclose(colour_correct(ref, ref), ref, atol=1e-12)
    for _ in range(5):
        a, b = rng.random((16, 16, 3)), rng.random((16, 16, 3))
        assert psnr(colour_correct(A(a), A(b)), A(b)).item() >= psnr(A(a), A(b)).item() - 1e-4


def test_constant_and_grey_images_give_well_defined_results(rng):
    ref = rng.random((12, 10, 3))
    flat = np.full((12, 10, 3), 0.3)
    # A constant render can only become a constant: the mean colour of the ground truth.
    out = colour_correct(flat, ref)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, np.broadcast_to(ref.reshape(-1, 3).mean(0), ref.shape), atol=1e-12)
    w = rng.random((12, 10))
    np.testing.assert_allclose(colour_correct(flat, ref, mask=w)[0, 0], (w[..., None] * ref).sum((0, 1)) / w.sum(), atol=1e-12)
    # A constant ground truth is matched exactly; a constant pair stays put.
    np.testing.assert_allclose(colour_correct(ref, flat), flat, atol=1e-12)
    np.testing.assert_allclose(colour_correct(flat, flat), flat, atol=1e-12)
    np.testing.assert_array_equal(colour_correct(np.zeros((4, 4, 3)), np.zeros((4, 4, 3))), np.zeros((4, 4, 3)))
    # A grey render (R = G = B) spans one colour direction: the map is not unique, its prediction is.
    grey = np.repeat(rng.random((12, 10, 1)), 3, axis=-1)
    m = fit_colour_map(grey, ref)
    assert np.isfinite(m).all() and np.abs(m).max() < 10
    oracle = apply_colour_map(grey, lstsq_map(grey, ref), clip=False)
    np.testing.assert_allclose(apply_colour_map(grey, m, clip=False), oracle, atol=1e-9)
    out = colour_correct(A(grey), A(ref))
    assert np.isfinite(np.array(out)).all()


def test_colour_correction_rejects_bad_input():
    with pytest.raises(ValueError, match="shapes differ"):
        fit_colour_map(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match="broadcast"):
        fit_colour_map(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), mask=np.ones((5, 4)))
    with pytest.raises(ValueError, match=">= 0"):
        fit_colour_map(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), mask=-np.ones((4, 4)))
    with pytest.raises(ValueError, match=r"\(3, 4\)"):
        apply_colour_map(np.zeros((4, 4, 3)), np.eye(3))
