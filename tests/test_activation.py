"""The CPU parameter activations (mlx3d.render.activation) against mx.exp / mx.sigmoid: bitwise
values and gradients, for any thread count, over the whole float range including non-finite input."""

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.render import activation
from thread_counts import per_thread_count
from core_marks import needs_core

pytestmark = needs_core


def inputs(n=100_003, seed=0):
    rng = np.random.default_rng(seed)
    x = np.concatenate([rng.normal(0, 3, n), rng.uniform(-120, 120, n), [0.0, -0.0, 88.7, 89.0, -87.5, -104.0, 1e-40, np.inf, -np.inf, np.nan]])
    return mx.array(x.astype(np.float32).reshape(-1, 2)), mx.array(rng.normal(0, 1, x.size).astype(np.float32).reshape(-1, 2))


@pytest.mark.parametrize("kind", ["exp", "sigmoid"])
def test_values_and_gradients_are_bitwise_mlx(kind):
    x, cot = inputs()
    ours, theirs = getattr(activation, kind), getattr(mx, kind)

    def run(fn):
        y, (g,) = mx.vjp(lambda a: fn(a), [x], [cot])
        return np.array(y), np.array(g)

    want = run(theirs)
    for got in per_thread_count(lambda: run(lambda a: ours(a, "cpu"))):
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)  # NaN where NaN (assert_array_equal treats NaNs as equal)
    assert np.isnan(want[0]).sum() == 1  # the NaN input stays NaN; inf and huge inputs saturate as MLX's do


def test_other_backends_run_mlx_and_bad_kind_is_refused():
    x, _ = inputs(n=10)
    np.testing.assert_array_equal(np.array(activation.exp(x, "reference")), np.array(mx.exp(x)))
    from mlx3d import native

    with pytest.raises(ValueError, match="kind must be 'exp' or 'sigmoid'"):
        native.core().activation(x, "tanh", 1)
