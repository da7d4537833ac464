"""Tests for mlx3d.training.bilateral_grid (per-image affine colour grids)."""

import math

import mlx.core as mx
import mlx.optimizers as optim
import numpy as np
import pytest

from mlx3d.training.adam import Adam
from mlx3d.training.bilateral_grid import (
    DEFAULT_GRID_SHAPE,
    BilateralGrid,
    GridAdam,
    apply_grid,
    apply_grid_reference,
    identity_grid,
    slice_affine,
    total_variation,
    total_variation_reference,
    warmup_decay,
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
# the numpy kernels against the MLX graph (the reference)
# ----------------------------------------------------------------------------

# (H, W, grid shape): segments of unequal length, one grid cell along an axis,
# fewer pixels than cells, single rows and columns.
SHAPES = [
    (13, 17, (5, 6, 4)),
    (32, 48, (16, 16, 8)),
    (9, 11, (1, 3, 2)),
    (9, 11, (4, 1, 1)),
    (7, 5, (3, 9, 8)),
    (1, 7, (2, 2, 3)),
    (6, 1, (2, 2, 3)),
]


def _image(rng, h, w, gg):
    """Colours partly outside [0, 1] (clamped guidance), luma exactly 0 and 1, and luma exactly on a
    guidance cell boundary (where the slice's derivative switches cells)."""
    img = rng.uniform(-0.2, 1.2, (h, w, 3))
    img.reshape(-1, 3)[0] = 0.0
    if h * w > 1:
        img.reshape(-1, 3)[1] = 1.0
    if h * w > 2 and gg > 2:
        img.reshape(-1, 3)[2] = 1.0 / (gg - 1)  # grey: luma 1 / (gg - 1), the boundary of cells 0 and 1
    return img


@pytest.mark.parametrize("h,w,shape", SHAPES)
def test_fast_slice_matches_reference(rng, h, w, shape):
    grid = random_grid(rng, shape)
    img = _image(rng, h, w, shape[2])
    for dtype, tol in ((mx.float32, 3e-6), (F64, 1e-12)):
        want = np.array(apply_grid_reference(A(grid, dtype), A(img, dtype)))
        got = apply_grid(A(grid, dtype), A(img, dtype))
        assert got.dtype == dtype
        np.testing.assert_allclose(np.array(got), want, atol=tol, rtol=0)
    _, want = ref_slice(grid, img)
    np.testing.assert_allclose(np.array(apply_grid(A(grid, F64), A(img, F64))), want, atol=1e-12, rtol=0)


@pytest.mark.parametrize("h,w,shape", SHAPES)
def test_fast_slice_gradients_match_reference(rng, h, w, shape):
    """Gradient to grid and image of a random linear + quadratic loss, vs MLX's autodiff of the graph."""
    grid = random_grid(rng, shape)
    img = _image(rng, h, w, shape[2])
    wts = rng.standard_normal((h, w, 3))
    for dtype, tol in ((F64, 1e-11), (mx.float32, 2e-5)):

        def loss(fn):
            def f(g, x):
                out = fn(g, x)
                return mx.sum(out * A(wts, dtype)) + 0.5 * mx.sum(out * out)

            return f

        want = mx.value_and_grad(loss(apply_grid_reference), argnums=(0, 1))(A(grid, dtype), A(img, dtype))
        got = mx.value_and_grad(loss(apply_grid), argnums=(0, 1))(A(grid, dtype), A(img, dtype))
        assert abs(got[0].item() - want[0].item()) <= tol * max(1.0, abs(want[0].item()))
        for g, r in zip(got[1], want[1]):
            scale = max(1.0, float(np.abs(np.array(r)).max()))
            np.testing.assert_allclose(np.array(g), np.array(r), atol=tol * scale, rtol=0)


def test_identity_grid_is_identity_map_on_both_paths(rng):
    for h, w, shape in SHAPES:
        img = rng.uniform(-0.5, 1.5, (h, w, 3))
        for fn in (apply_grid, apply_grid_reference):
            np.testing.assert_allclose(np.array(fn(identity_grid(shape), A(img, F64))), img, atol=1e-14, rtol=0)
        # Its gradient: the image's passes through unchanged (the luma path sees equal cells).
        g = mx.grad(lambda x: mx.sum(apply_grid(A(identity_grid(shape), F64), x) * A(img, F64)))(A(img, F64))
        np.testing.assert_allclose(np.array(g), img, atol=1e-12, rtol=0)


def test_fast_slice_gradient_through_stacked_params_and_repeated_use(rng):
    """The trainer's call (one grid of the stack, differentiated w.r.t. the stack), and a loss that
    slices several times before its VJPs run (their saved forwards are dropped and recomputed)."""
    bg = BilateralGrid(4, (4, 5, 3))
    bg.params = A(random_grid(rng, (4, 4, 5, 3), 0.2))
    imgs = [A(rng.uniform(0, 1, (10, 12, 3))) for _ in range(4)]

    def loss(fn):
        def f(p, x):
            return sum(mx.sum(fn(p[i], x * (i + 1) / 4) ** 2) for i in range(4)) + mx.sum(fn(p[2], imgs[1]))

        return f

    want = mx.grad(loss(apply_grid_reference), argnums=(0, 1))(bg.params, imgs[0])
    got = mx.grad(loss(lambda g, x: bg.apply(x, 0, g, compiled=False)), argnums=(0, 1))(bg.params, imgs[0])
    for g, r in zip(got, want):
        np.testing.assert_allclose(np.array(g), np.array(r), atol=2e-4, rtol=1e-5)


def test_slice_falls_back_to_the_graph_where_arrays_cannot_be_evaluated(rng):
    grid, img = A(random_grid(rng, (4, 5, 3))), A(rng.random((6, 7, 3)))
    want = np.array(apply_grid_reference(grid, img))
    np.testing.assert_allclose(np.array(mx.compile(apply_grid)(grid, img)), want, atol=1e-6)
    batched = mx.vmap(apply_grid, in_axes=(None, 0))(grid, mx.stack([img, img * 0.5]))
    np.testing.assert_allclose(np.array(batched[0]), want, atol=1e-6)
    np.testing.assert_allclose(np.array(batched[1]), np.array(apply_grid_reference(grid, img * 0.5)), atol=1e-6)
    # dtypes numpy lacks: the graph too
    half = apply_grid(grid.astype(mx.float16), img.astype(mx.float16))
    assert half.dtype == mx.float16
    np.testing.assert_allclose(np.array(half.astype(mx.float32)), want, atol=2e-2)


@pytest.mark.parametrize("shape", [(3, 4, 5, 3), (2, 1, 3, 2), (2, 4, 1, 1), (1, 1, 1, 1), (4, 5, 3)])
def test_fast_tv_matches_reference(rng, shape):
    p = rng.standard_normal((*shape, 12))
    w = 7.0
    for dtype, tol in ((F64, 1e-12), (mx.float32, 1e-5)):
        got = mx.value_and_grad(lambda q: w * total_variation(q))(A(p, dtype))
        want = mx.value_and_grad(lambda q: w * total_variation_reference(q))(A(p, dtype))
        assert got[0].dtype == dtype
        assert got[0].item() == pytest.approx(want[0].item(), rel=tol, abs=tol)
        np.testing.assert_allclose(np.array(got[1]), np.array(want[1]), atol=tol * max(1.0, float(np.abs(np.array(want[1])).max())))
    assert total_variation(A(p, F64)).item() == pytest.approx(ref_tv(p if p.ndim == 5 else p[None]), rel=1e-12, abs=1e-300)


def test_apply_takes_the_image_own_grid(rng):
    bg = BilateralGrid(3, (4, 4, 2))
    bg.params = A(random_grid(rng, (3, 4, 4, 2)))
    img = A(rng.random((8, 10, 3)))
    np.testing.assert_array_equal(np.array(bg.apply(img, 2, bg.params[2])), np.array(bg.apply(img, 2)))
    with pytest.raises(IndexError):
        bg.apply(img, 3, bg.params[0])
    g = mx.grad(lambda grid: mx.sum(bg.apply(img, 1, grid) ** 2) + bg.tv_loss(grid))(bg.params[1])
    full = mx.grad(lambda p: mx.sum(bg.apply(img, 1, p) ** 2) + total_variation(p[1]))(bg.params)
    np.testing.assert_allclose(np.array(g), np.array(full[1]), atol=1e-5)


# ----------------------------------------------------------------------------
# GridAdam: one grid per step, the same as Adam over the stack
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("scheduled", [False, True], ids=["constant", "warmup_decay"])
def test_grid_adam_equals_adam_over_the_stack(rng, scheduled):
    num, shape = 5, (3, 4, 2)
    start = random_grid(rng, (num, *shape), 0.1)
    dense, lazy = BilateralGrid(num, shape), BilateralGrid(num, shape)
    dense.params = A(start)
    lazy.params = A(start)
    # With a schedule, pending steps must sum each step's own rate: a warm-up over 20 steps from
    # 1% (so that a grid idle through it moves far less than at the full rate), decay to 5%.
    schedule = warmup_decay(50, 20, 0.01, 0.05) if scheduled else None
    adam, grid_adam = Adam({"grid": 2e-3}), GridAdam(2e-3, schedule=schedule)
    # Image 4 waits 40 steps, image 0 comes back after 1 and after 30, image 3 is never drawn.
    draws = [0, 0, 1, 2, 1] + [1, 2] * 14 + [0] + [2] * 10 + [4, 1, 0]
    for t, i in enumerate(draws):
        # The grid the step reads: what Adam over the stack holds now.
        np.testing.assert_allclose(np.array(grid_adam.current(lazy, i)), np.array(dense.params[i]), atol=2e-6, rtol=0)
        g = rng.standard_normal((*shape, 12)) * rng.choice([1e-1, 1e-3, 1e-5], size=(*shape, 12))
        if t % 3 == 0:  # gradients near and below Adam's eps, and exact zeros
            g *= rng.choice([0.0, 1e-13, 1e-16, 1e-20, 1.0], size=g.shape)
        full = np.zeros((num, *shape, 12))
        full[i] = g
        if scheduled:
            adam.lrs["grid"] = 2e-3 * float(schedule(np.array([t + 1]))[0])
        dense.params = adam.update({"grid": dense.params}, {"grid": A(full)})["grid"]
        grid_adam.update(lazy, i, A(g))
        np.testing.assert_allclose(np.array(lazy.params[i]), np.array(dense.params[i]), atol=2e-6, rtol=0)
    assert np.abs(np.array(lazy.params) - np.array(dense.params)).max() > 1e-4  # grids with pending steps
    grid_adam.sync(lazy)
    np.testing.assert_allclose(np.array(lazy.params), np.array(dense.params), atol=2e-6, rtol=0)
    np.testing.assert_allclose(np.array(lazy.params[3]), start[3], atol=0)  # never drawn: never moved
    np.testing.assert_allclose(grid_adam.m, np.array(adam.m["grid"]), rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(grid_adam.v, np.array(adam.v["grid"]), rtol=1e-5, atol=1e-20)
    assert grid_adam.step_count == adam.step_count == len(draws)


def test_warmup_decay_matches_its_definition():
    f = warmup_decay(3000, 1000, start=0.01, final=0.01)
    t = np.array([1, 501, 1001, 3001])
    np.testing.assert_allclose(f(t), [0.01, 0.505 * 0.01 ** (500 / 3000), 0.01 ** (1000 / 3000), 0.01], rtol=1e-12)
    np.testing.assert_allclose(warmup_decay(10, 0, final=1.0)(np.arange(1, 11)), 1.0)
    with pytest.raises(ValueError, match="warmup_decay"):
        warmup_decay(100, 10, start=0.0)


def test_grid_adam_first_step_is_adam_bit_for_bit(rng):
    bg = BilateralGrid(3, (2, 3, 2))
    p0 = bg.params
    g = A(rng.standard_normal((2, 3, 2, 12)))
    adam, grid_adam = Adam({"grid": 2e-3}), GridAdam(2e-3)
    want = adam.update({"grid": p0[1]}, {"grid": g})["grid"]
    grid_adam.update(bg, 1, g)
    np.testing.assert_array_equal(np.array(bg.params[1]), np.array(want))
    np.testing.assert_array_equal(np.array(p0), np.array(BilateralGrid(3, (2, 3, 2)).params))  # not modified in place


def test_grid_adam_state_roundtrip_and_adam_state(rng):
    num, shape = 4, (2, 2, 3)
    bg = BilateralGrid(num, shape)
    opt = GridAdam(1e-2)
    for t in range(12):
        opt.current(bg, t % 3)
        opt.update(bg, t % 3, A(rng.standard_normal((*shape, 12))))
    # Resume from the state (pending steps included) and go on: same as not stopping.
    other_bg = BilateralGrid(num, shape)
    other_bg.params = mx.array(np.array(bg.params))
    other = GridAdam(1e-2)
    other.load_state_dict({k: np.array(v) for k, v in opt.state_dict().items()})
    for t in range(12, 20):
        g = A(rng.standard_normal((*shape, 12)))
        for o, b in ((opt, bg), (other, other_bg)):
            o.current(b, t % 4)
            o.update(b, t % 4, g)
    for o, b in ((opt, bg), (other, other_bg)):
        o.sync(b)
    np.testing.assert_array_equal(np.array(other_bg.params), np.array(bg.params))
    # Adam's state (all grids current) loads too.
    adam = Adam({"grid": 1e-2})
    adam.update({"grid": bg.params}, {"grid": A(rng.standard_normal((num, *shape, 12)))})
    from_adam = GridAdam(1e-2)
    from_adam.load_state_dict(adam.state_dict())
    assert from_adam.step_count == 1 and list(from_adam.last) == [1] * num
    np.testing.assert_array_equal(from_adam.m, np.array(adam.m["grid"]))
    with pytest.raises(ValueError):
        from_adam.update(BilateralGrid(num + 1, shape), 0, A(np.zeros((*shape, 12))))


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


def test_grid_adam_per_image_fits_each_image(rng):
    """The per-image scheme (the stepped image's grid, its TV, GridAdam) fits per-image colour changes."""
    h, w = 32, 40
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    src = A(np.clip(np.stack([0.2 + 0.7 * x, 0.5 + 0.4 * np.sin(6 * y), 0.9 - 0.8 * x * y], axis=-1), 0, 1))
    gains = [np.array([0.8, 0.8, 0.75]), np.array([1.1, 1.0, 0.9]), np.array([0.9, 1.05, 1.15])]
    targets = [src * A(g) for g in gains]
    bg = BilateralGrid(4, (4, 4, 4))
    opt = GridAdam(learning_rate=1e-2)

    def loss_fn(grid, i):
        return mx.mean((bg.apply(src, i, grid) - targets[i]) ** 2) + 10.0 * bg.tv_loss(grid)

    err0 = [mx.mean((src - t) ** 2).item() for t in targets]
    for step in range(600):
        i = step % 3
        _, g = mx.value_and_grad(loss_fn)(opt.current(bg, i), i)
        opt.update(bg, i, g)
    opt.sync(bg)
    for i in range(3):
        err1 = mx.mean((bg.apply(src, i) - targets[i]) ** 2).item()
        assert err1 < err0[i] / 10, (i, err0[i], err1)
    np.testing.assert_array_equal(np.array(bg.params[3]), np.array(identity_grid((4, 4, 4))))  # never drawn


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


def test_auto_grid_is_decided_from_the_dataset_and_off_without_one():
    """'auto' is the default; a trainer made without initial_state (which measures the photos'
    exposure, tests/test_sfm.py) trains without a grid; anything but True, False or 'auto' is refused."""
    from mlx3d.splatting import GaussianModel
    from mlx3d.training import GaussianTrainer, TrainerConfig

    assert TrainerConfig().bilateral_grid == "auto"
    model = GaussianModel.from_points(np.random.default_rng(0).normal(size=(20, 3)), sh_degree=0)
    trainer = GaussianTrainer(model, TrainerConfig(), num_images=4)
    assert trainer.config.bilateral_grid is False and trainer.bilateral is None
    assert GaussianTrainer(model, TrainerConfig(bilateral_grid=True), num_images=4).bilateral.num_images == 4
    assert TrainerConfig(bilateral_grid=np.True_).bilateral_grid is True  # as the step plan reads it
    with pytest.raises(ValueError, match="bilateral_grid must be True, False or 'auto'"):
        TrainerConfig(bilateral_grid="on")
