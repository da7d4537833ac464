"""The CPU training-loss primitive (photometric_loss(backend='cpu')): loss and gradients with respect
to the render and the photo against the MLX graph (backend='reference'), with and without a mask,
images smaller than the SSIM window, and bitwise equality across thread counts; the MSE primitive
(mse(backend="cpu"), the per-step PSNR) against the MLX graph and a float64 numpy sum."""

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.training.metrics import photometric_loss
from thread_counts import per_thread_count
from core_marks import needs_core

pytestmark = needs_core

# float32 sums of the same terms in another order (the loss is a mean over up to 10^6 terms)
LOSS_RTOL = 1e-5
GRAD_RTOL = 2e-5  # of the largest gradient entry


def pair(h, w, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    y = np.clip(x + rng.normal(0, 0.15, x.shape), 0, 1).astype(np.float32)
    return mx.array(x), mx.array(y), mx.array(rng.uniform(0, 1, (h, w)).astype(np.float32)), rng


@pytest.mark.parametrize("h, w", [(37, 53), (5, 7), (64, 9)])
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("lam", [0.2, 1.0])
def test_loss_and_gradients_match_the_reference(h, w, masked, lam):
    x, y, m, _ = pair(h, w)
    mask = m if masked else None
    out = {}
    for backend in ("cpu", "reference"):
        value, grads = mx.value_and_grad(lambda a, b: photometric_loss(a, b, lam, mask, backend=backend), argnums=(0, 1))(x, y)
        out[backend] = (float(value), [np.array(g) for g in grads])
    assert out["cpu"][0] == pytest.approx(out["reference"][0], rel=LOSS_RTOL)
    for got, want in zip(out["cpu"][1], out["reference"][1]):
        np.testing.assert_allclose(got, want, rtol=0, atol=GRAD_RTOL * np.abs(want).max())


def test_zero_weights_and_identical_images():
    x, _, m, _ = pair(20, 30)
    value, grad = mx.value_and_grad(lambda a: photometric_loss(a, x, 0.2, backend="cpu"))(x)
    assert float(value) == pytest.approx(0.0, abs=1e-6) and np.abs(np.array(grad)).max() < 1e-4  # a minimum
    value = photometric_loss(x, x * 0.5, 0.2, mx.zeros((20, 30)), backend="cpu")
    assert float(value) == pytest.approx(0.2)  # nothing weighted: L1 = 0, SSIM = 0, as the MLX graph


def test_bitwise_identical_for_any_thread_count():
    x, y, m, _ = pair(101, 77)

    def run():
        value, grad = mx.value_and_grad(lambda a: photometric_loss(a, y, 0.2, m, backend="cpu"))(x)
        return float(value), np.array(grad)

    runs = per_thread_count(run)
    for value, grad in runs[1:]:
        assert value == runs[0][0]
        np.testing.assert_array_equal(grad, runs[0][1])


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("clip", [False, True])
def test_mse_kernel_matches_the_mlx_graph_and_numpy(masked, clip):
    from mlx3d.training.metrics import mse, psnr

    x, y, m, _ = pair(53, 71, seed=4)
    x = x * 1.4 - 0.2  # some values outside [0, 1]
    mask = m if masked else None
    got = per_thread_count(lambda: float(mse(x, y, mask, clip=clip, backend="cpu")))
    assert got[1:] == got[:-1]  # the same bits for any thread count
    assert got[0] == pytest.approx(float(mse(x, y, mask, clip=clip, backend="reference")), rel=LOSS_RTOL)  # float32 sums
    xa = np.clip(np.array(x, np.float64), 0, 1) if clip else np.array(x, np.float64)
    per_pixel = ((xa - np.array(y, np.float64)) ** 2).mean(-1)
    w = np.array(m, np.float64) if masked else np.ones(per_pixel.shape)
    assert got[0] == pytest.approx((per_pixel * w).sum() / w.sum(), rel=1e-6)
    assert float(psnr(x, y, mask, clip=clip, backend="cpu")) == pytest.approx(-10 * np.log10(got[0]), rel=1e-6)
    with pytest.raises(ValueError, match="shapes differ"):
        mse(x[:, :, :2], y, backend="cpu")
