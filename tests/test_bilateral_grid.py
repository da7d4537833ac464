"""Tests for mlx3d.training.bilateral_grid (per-image affine colour grids)."""

import math

import mlx.core as mx
import mlx.optimizers as optim
import numpy as np
import pytest

from mlx3d.training.bilateral_grid import (
    DEFAULT_GRID_SHAPE,
    BilateralGrid,
    apply_grid,
    identity_grid,
    slice_affine,
    total_variation,
)

F64 = mx.float64


def A(x, dtype=mx.float32):
    return mx.array(np.asarray(x), dtype=dtype)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


# ----------------------------------------------------------------------------
# numpy reference: explicit per-pixel trilinear slicing
# ----------------------------------------------------------------------------


def ref_coord(t, n):
    """[0, 1] -> [0, n - 1] (align_corners=True), border clamp; (i0, i1, w)."""
    c = min(max(t, 0.0), 1.0) * (n - 1)
    i0 = min(int(math.floor(c)), n - 1)
    i1 = min(i0 + 1, n - 1)
    return i0, i1, c - i0


def ref_slice(grid, img):
    """Per-pixel 3x4 matrices (H, W, 3, 4) and transformed image, float64."""
    grid = np.asarray(grid, np.float64)
    img = np.asarray(img, np.float64)
    gy, gx, gg, _ = grid.shape
    h, w, _ = img.shape
    mats = np.zeros((h, w, 12))
    for i in range(h):
        y0, y1, fy = ref_coord((i + 0.5) / h, gy)
        for j in range(w):
            x0, x1, fx = ref_coord((j + 0.5) / w, gx)
            r, g, b = img[i, j]
            z0, z1, fz = ref_coord(0.299 * r + 0.587 * g + 0.114 * b, gg)
            acc = np.zeros(12)
            for yi, wy in ((y0, 1 - fy), (y1, fy)):
                for xi, wx in ((x0, 1 - fx), (x1, fx)):
                    for zi, wz in ((z0, 1 - fz), (z1, fz)):
                        acc += wy * wx * wz * grid[yi, xi, zi]
            mats[i, j] = acc
    mats = mats.reshape(h, w, 3, 4)
    out = np.einsum("hwds,hws->hwd", mats[..., :3], img) + mats[..., 3]
    return mats, out


def ref_tv(params):
    """gsplat total_variation_loss with explicit loops over neighbours."""
    p = np.asarray(params, np.float64)
    n, gy, gx, gg, c = p.shape
    total = 0.0
    for axis, size in ((1, gy), (2, gx), (3, gg)):
        if size < 2:
            continue
        s, count = 0.0, 0
        for idx in np.ndindex(*p.shape):
            if idx[axis] + 1 < size:
                nxt = list(idx)
                nxt[axis] += 1
                s += (p[tuple(nxt)] - p[idx]) ** 2
                count += 1
        total += s / count
    return total


def random_grid(rng, shape, scale=0.3):
    return np.broadcast_to(np.eye(3, 4).reshape(-1), (*shape, 12)) + scale * rng.standard_normal((*shape, 12))


# ----------------------------------------------------------------------------
# slicing
# ----------------------------------------------------------------------------


def test_identity_leaves_image_unchanged(rng):
    bg = BilateralGrid(3)
    assert bg.params.shape == (3, *DEFAULT_GRID_SHAPE, 12)
    img = rng.random((37, 53, 3))
    for i in range(3):
        np.testing.assert_allclose(np.array(bg.apply(A(img), i)), img, atol=1e-6, rtol=0)
    # Out-of-range colours too (the guidance is clamped, the matrix is still I).
    wild = rng.uniform(-0.5, 1.5, (9, 11, 3))
    np.testing.assert_allclose(np.array(apply_grid(identity_grid(), A(wild))), wild, atol=1e-6, rtol=0)


def test_constant_affine_applies_exactly(rng):
    m = np.array([[1.2, 0.0, 0.0, 0.05], [0.0, 1.2, 0.0, 0.05], [0.0, 0.0, 1.2, 0.05]])
    mixed = np.array([[0.9, 0.1, -0.05, 0.02], [0.05, 1.1, 0.0, -0.03], [-0.1, 0.2, 0.8, 0.1]])
    img = rng.random((31, 24, 3))
    for mat in (m, mixed):
        grid = np.broadcast_to(mat.reshape(-1), (5, 7, 4, 12))
        want = img @ mat[:, :3].T + mat[:, 3]
        np.testing.assert_allclose(np.array(apply_grid(A(grid), A(img))), want, atol=1e-6, rtol=0)
        sliced = np.array(slice_affine(A(grid), A(img)))
        np.testing.assert_allclose(sliced, np.broadcast_to(mat, sliced.shape), atol=1e-6)


@pytest.mark.parametrize("shape", [(5, 6, 4), (16, 16, 8), (1, 3, 2), (4, 1, 1)])
def test_trilinear_matches_numpy(rng, shape):
    grid = random_grid(rng, shape)
    img = rng.uniform(-0.1, 1.1, (13, 17, 3))  # some guidance values clamp
    img[0, 0] = 0.0
    img[0, 1] = 1.0
    mats, want = ref_slice(grid, img)
    np.testing.assert_allclose(np.array(slice_affine(A(grid), A(img))), mats, atol=2e-6, rtol=0)
    for compiled in (True, False):
        got = np.array(apply_grid(A(grid), A(img), compiled=compiled))
        np.testing.assert_allclose(got, want, atol=3e-6, rtol=0)
    # float64 end to end: agreement to rounding.
    got64 = np.array(apply_grid(A(grid, F64), A(img, F64)))
    np.testing.assert_allclose(got64, want, atol=1e-12, rtol=0)


def test_apply_uses_the_indexed_grid(rng):
    bg = BilateralGrid(3, (4, 4, 2))
    p = np.array(bg.params)
    p[1, ..., [3, 7, 11]] = 0.25  # offsets (b0, b1, b2) on image 1 only
    bg.params = A(p)
    img = rng.random((8, 10, 3))
    np.testing.assert_allclose(np.array(bg.apply(A(img), 0)), img, atol=1e-6)
    np.testing.assert_allclose(np.array(bg.apply(A(img), 1)), img + 0.25, atol=1e-6)
    np.testing.assert_allclose(np.array(bg.apply(A(img), -2)), img + 0.25, atol=1e-6)
    with pytest.raises(IndexError):
        bg.apply(A(img), 3)
    with pytest.raises(ValueError):
        apply_grid(identity_grid((4, 4, 2)), A(img[..., :2]))


# ----------------------------------------------------------------------------
# total variation
# ----------------------------------------------------------------------------


def test_tv_loss_constant_and_hand_values(rng):
    assert BilateralGrid(2, (4, 5, 3)).tv_loss().item() == 0.0
    const = np.broadcast_to(rng.standard_normal(12), (2, 4, 5, 3, 12))
    assert total_variation(A(const)).item() == 0.0
    # Two cells along y (other axes of size 1 contribute nothing): one step of
    # 1 in 11 channels and of 2 in the last -> mean square (11 + 4) / 12.
    p = np.zeros((1, 2, 1, 1, 12))
    p[0, 1] = 1.0
    p[0, 1, 0, 0, 11] = 2.0
    assert total_variation(A(p)).item() == pytest.approx(15.0 / 12.0, rel=1e-6)
    # Steps along x and guidance: a ramp 0, 1, 3 along x (squares 1, 4 ->
    # mean 2.5) plus a step of 0.5 along guidance (mean 0.25) -> 2.75.
    q = np.zeros((1, 1, 3, 2, 12))
    q[0, 0, 1] = 1.0
    q[0, 0, 2] = 3.0
    q[0, 0, :, 1] += 0.5
    assert total_variation(A(q)).item() == pytest.approx(2.75, rel=1e-6)
    # Random grids vs the loop definition.
    r = rng.standard_normal((3, 4, 5, 3, 12))
    assert total_variation(A(r, F64)).item() == pytest.approx(ref_tv(r), rel=1e-12)
    bg = BilateralGrid(3, (4, 5, 3))
    bg.params = A(r)
    assert bg.tv_loss().item() == pytest.approx(ref_tv(r), rel=1e-5)


# ----------------------------------------------------------------------------
# gradients
# ----------------------------------------------------------------------------


def _fd_fixture(rng):
    grid = random_grid(rng, (4, 5, 3), 0.2)
    img = rng.uniform(0.05, 0.95, (9, 11, 3))
    # Keep every guidance coordinate 1e-3 away from a cell boundary, so the
    # piecewise-linear slice is smooth inside the finite-difference step.
    for _ in range(50):
        z = (img @ np.array([0.299, 0.587, 0.114])) * 2.0  # gg - 1 = 2
        bad = np.abs(z - np.round(z)) < 1e-3
        if not bad.any():
            break
        img[bad] = rng.uniform(0.05, 0.95, (int(bad.sum()), 3))
    weights = rng.standard_normal((9, 11, 3))
    return grid, img, weights


def test_grid_and_image_gradients_match_finite_differences(rng):
    """float64 run: analytic gradient vs central differences, 1e-6 relative."""
    grid, img, wts = _fd_fixture(rng)
    wts_m = A(wts, F64)

    def loss(g, x):
        out = apply_grid(g, x)
        return mx.sum(out * wts_m) + 0.5 * mx.sum(out * out)

    gg, gi = mx.grad(loss, argnums=(0, 1))(A(grid, F64), A(img, F64))
    gg, gi = np.array(gg), np.array(gi)

    def f(g, x):
        return loss(A(g, F64), A(x, F64)).item()

    h = 1e-6
    scale_g = np.abs(gg).max()
    for idx in [tuple(rng.integers(0, s) for s in grid.shape) for _ in range(25)] + [(0, 0, 0, 0), (3, 4, 2, 11)]:
        gp, gm = grid.copy(), grid.copy()
        gp[idx] += h
        gm[idx] -= h
        fd = (f(gp, img) - f(gm, img)) / (2 * h)
        assert abs(gg[idx] - fd) <= 1e-6 * scale_g, (idx, gg[idx], fd)
    scale_i = np.abs(gi).max()
    for idx in [tuple(rng.integers(0, s) for s in img.shape) for _ in range(25)]:
        xp, xm = img.copy(), img.copy()
        xp[idx] += h
        xm[idx] -= h
        fd = (f(grid, xp) - f(grid, xm)) / (2 * h)
        assert abs(gi[idx] - fd) <= 1e-6 * scale_i, (idx, gi[idx], fd)


def test_gradient_through_container_touches_only_its_grid(rng):
    bg = BilateralGrid(3, (4, 4, 2))
    img = A(rng.random((6, 7, 3)))
    g = mx.grad(lambda p: mx.sum(bg.apply(img, 1, params=p) ** 2))(bg.params)
    g = np.array(g)
    assert g.shape == bg.params.shape
    assert np.abs(g[1]).max() > 0
    assert np.abs(g[0]).max() == 0 and np.abs(g[2]).max() == 0


# ----------------------------------------------------------------------------
# fitting and checkpoints
# ----------------------------------------------------------------------------


def test_adam_absorbs_exposure_and_white_balance(rng):
    """Fit the grid so that the image maps to a 20% darker, warmer version."""
    h, w = 48, 64
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    img = np.stack([0.2 + 0.7 * x, 0.5 + 0.4 * np.sin(6 * y), 0.9 - 0.8 * x * y], axis=-1)
    img = np.clip(img + 0.05 * rng.standard_normal(img.shape), 0, 1)
    target = A(img * 0.8 * np.array([1.05, 1.0, 0.92]))
    src = A(img)

    bg = BilateralGrid(2)
    opt = optim.Adam(learning_rate=1e-2)

    def loss_fn(params):
        out = bg.apply(src, 1, params=params)
        return mx.mean((out - target) ** 2) + 10.0 * bg.tv_loss(params)

    step = mx.value_and_grad(loss_fn)
    err0 = mx.mean((bg.apply(src, 1) - target) ** 2).item()
    for _ in range(300):
        _, g = step(bg.params)
        bg.update(opt.apply_gradients({"params": g}, bg.parameters()))
        mx.eval(bg.params)
    err1 = mx.mean((bg.apply(src, 1) - target) ** 2).item()
    assert err1 < err0 / 10, (err0, err1)
    # Image 0 was never rendered, so its grid received zero gradients.
    np.testing.assert_allclose(np.array(bg.params[0]), np.array(identity_grid()), atol=1e-7)


def test_state_roundtrip(tmp_path, rng):
    bg = BilateralGrid(2, (3, 4, 5))
    bg.params = A(random_grid(rng, (2, 3, 4, 5)))
    state = bg.state_dict()
    assert isinstance(state["params"], np.ndarray) and state["params"].dtype == np.float32
    other = BilateralGrid(1)
    other.load_state_dict(state)
    assert other.num_images == 2 and other.grid_shape == (3, 4, 5)
    np.testing.assert_array_equal(np.array(other.params), state["params"])
    path = tmp_path / "bilagrid.npz"
    bg.save(path)
    again = BilateralGrid.load(path)
    np.testing.assert_array_equal(np.array(again.params), state["params"])
    img = A(rng.random((5, 6, 3)))
    np.testing.assert_array_equal(np.array(again.apply(img, 1)), np.array(bg.apply(img, 1)))
    with pytest.raises(ValueError):
        other.load_state_dict({"params": np.zeros((2, 3, 4, 12))})
    bg.reset(0)
    np.testing.assert_array_equal(np.array(bg.params[0]), np.array(identity_grid((3, 4, 5))))
    assert np.abs(np.array(bg.params[1]) - np.array(identity_grid((3, 4, 5)))).max() > 0
