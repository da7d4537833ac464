"""The CPU SH colour primitive (mlx3d._core.sh_colors through mlx3d.render.sh_color) against the
pure-MLX reference (eval_sh), float64 finite differences, and across thread counts."""

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.render.sh_color import sh_colors
from mlx3d.splatting.sh import eval_sh
from thread_counts import per_thread_count
from core_marks import needs_core

pytestmark = needs_core

# float32 kernels against the float32 reference: both sum the same terms in the same order, but
# the reference's normalisation uses pow(·, -0.5) and autodiff's own expression order
FWD_ATOL = 2e-6
GRAD_RTOL = 2e-5  # of the largest gradient entry


def problem(n=777, k=16, seed=0, scale=0.5):
    rng = np.random.default_rng(seed)
    sh = rng.normal(0, scale, (n, k, 3)).astype(np.float32)
    means = rng.normal(0, 1.5, (n, 3)).astype(np.float32)
    return mx.array(sh), mx.array(means), (0.3, -0.2, 0.1), rng


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_forward_and_gradients_match_the_reference(degree):
    sh, means, centre, rng = problem(scale=1.0)
    cot = mx.array(rng.normal(0, 1, (sh.shape[0], 3)).astype(np.float32))
    out = {}
    for backend in ("cpu", "reference"):
        rgb, vjp = mx.vjp(lambda s, m: sh_colors(s, m, centre, degree, backend), [sh, means], [cot])
        out[backend] = [np.array(rgb)] + [np.array(g) for g in vjp]
    np.testing.assert_allclose(out["cpu"][0], out["reference"][0], rtol=0, atol=FWD_ATOL)
    assert (out["cpu"][0] == 0).any() and (out["cpu"][0] > 0).any()  # both sides of the clamp are exercised
    for got, want in zip(out["cpu"][1:], out["reference"][1:]):
        np.testing.assert_allclose(got, want, rtol=0, atol=GRAD_RTOL * max(np.abs(want).max(), 1.0))
    if degree == 0:
        assert not out["cpu"][2].any()  # colour does not depend on position
    assert not out["cpu"][1][:, (degree + 1) ** 2:].any()  # coefficients past the degree get no gradient


def test_position_gradient_matches_float64_finite_differences():
    sh, means, centre, rng = problem(n=64, scale=0.1)
    sh = mx.concatenate([mx.ones((64, 1, 3)), sh[:, 1:]], axis=1)  # colours near 0.78: the clamp stays inactive
    sh64, m64 = np.array(sh, np.float64), np.array(means, np.float64)
    w = rng.normal(0, 1, (64, 3))

    def loss64(m):
        return float(np.sum(w * eval_sh(3, sh64, m - np.array(centre))))

    assert (eval_sh(3, sh64, m64 - np.array(centre)) > 0.05).all()
    grad = np.array(mx.grad(lambda m: mx.sum(mx.array(w.astype(np.float32)) * sh_colors(sh, m, centre, 3, "cpu")))(means))
    h = 1e-6
    fd = np.zeros_like(m64)
    for i in range(64):
        for j in range(3):
            plus, minus = m64.copy(), m64.copy()
            plus[i, j] += h
            minus[i, j] -= h
            fd[i, j] = (loss64(plus) - loss64(minus)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-3, atol=1e-3 * np.abs(fd).max())


def test_bitwise_identical_for_any_thread_count():
    sh, means, centre, rng = problem(n=10_001)
    cot = mx.array(rng.normal(0, 1, (10_001, 3)).astype(np.float32))

    def run():
        rgb, (g_sh, g_means) = mx.vjp(lambda s, m: sh_colors(s, m, centre, 3, "cpu"), [sh, means], [cot])
        return [np.array(a) for a in (rgb, g_sh, g_means)]

    runs = per_thread_count(run)
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("degree", [1, 3])
def test_each_gaussian_gets_the_bits_it_gets_alone(degree):
    """The kernel computes several Gaussians at once (one per vector lane, the last batch padded):
    each one's colour and gradients are bit for bit those of evaluating it on its own."""
    sh, means, centre, rng = problem(n=21)
    cot = mx.array(rng.normal(0, 1, (21, 3)).astype(np.float32))

    def run(s, m, c):
        rgb, grads = mx.vjp(lambda s_, m_: sh_colors(s_, m_, centre, degree, "cpu"), [s, m], [c])
        return [np.array(a) for a in (rgb[0], *grads)]

    together = run(sh, means, cot)
    for i in range(21):
        alone = run(sh[i : i + 1], means[i : i + 1], cot[i : i + 1])
        for a, b in zip(together, alone):
            assert a[i : i + 1].tobytes() == b.tobytes()


@pytest.mark.parametrize("backend", ["cpu", "reference"])
@pytest.mark.parametrize("k, degree", [(16, 3), (16, 1), (1, 0)])
def test_the_pair_sh_dc_sh_rest_renders_as_their_concatenation(backend, k, degree):
    # a model's two SH parameters are read in place: the same colours, and each block's gradient is
    # its slice of the concatenated array's gradient (bitwise on the CPU: the same sums in the same order)
    sh, means, centre, rng = problem(k=k, scale=1.0)
    dc, rest = mx.array(np.array(sh[:, :1])), mx.array(np.array(sh[:, 1:]))  # separate buffers, rest (N,0,3) when K = 1
    cot = mx.array(rng.normal(0, 1, (sh.shape[0], 3)).astype(np.float32))
    rgb, (g_sh, g_m) = mx.vjp(lambda s, m: sh_colors(s, m, centre, degree, backend), [sh, means], [cot])
    rgb2, (g_dc, g_rest, g_m2) = mx.vjp(lambda a, b, m: sh_colors((a, b), m, centre, degree, backend), [dc, rest, means], [cot])
    assert g_dc.shape == dc.shape and g_rest.shape == rest.shape
    for got, want in [(rgb2, rgb), (g_dc, g_sh[:, :1]), (g_rest, g_sh[:, 1:]), (g_m2, g_m)]:
        np.testing.assert_array_equal(np.array(got), np.array(want))


def test_blocks_of_different_gaussian_counts_are_refused():
    with pytest.raises(ValueError, match=r"every sh block must have shape \(5, K, 3\)"):
        mx.eval(sh_colors((mx.zeros((5, 1, 3)), mx.zeros((4, 15, 3))), mx.zeros((5, 3)), (0, 0, 0), 3, "cpu"))


def test_a_gaussian_at_the_camera_centre_stays_finite():
    sh, means, centre, _ = problem(n=4)
    means = mx.array(np.tile(np.array(centre, np.float32), (4, 1)))
    rgb, grads = mx.vjp(lambda s, m: sh_colors(s, m, centre, 3, "cpu"), [sh, means], [mx.ones((4, 3))])
    assert np.isfinite(np.array(rgb)).all() and all(np.isfinite(np.array(g)).all() for g in grads)


@pytest.mark.parametrize("sh_shape, means_shape, degree, message", [
    ((5, 16, 3), (4, 3), 3, "means must have shape"),
    ((5, 4, 3), (5, 3), 2, "degree 2 needs K >= 9"),
    ((5, 16), (5, 3), 3, "sh must have shape"),
    ((5, 16, 3), (5, 3), 4, "degree must be 0..3"),
])
def test_bad_input_is_refused_with_a_message(sh_shape, means_shape, degree, message):
    with pytest.raises(ValueError, match=message):
        mx.eval(sh_colors(mx.zeros(sh_shape), mx.zeros(means_shape), (0, 0, 0), degree, "cpu"))
