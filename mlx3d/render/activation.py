"""The Gaussians' parameter activations, one entry per backend: scales = exp(log-scales),
opacities = sigmoid(logits).

'cpu' runs ``mlx3d._core.activation``, a threaded C++ MLX primitive that
calls MLX's own scalar functions, so values and gradients are bitwise those of
``mx.exp`` / ``mx.sigmoid`` (which run on one core); other backends run those.
"""

from __future__ import annotations

import mlx.core as mx

from .rasterize import resolve_backend

__all__ = ["exp", "sigmoid"]


def _activation(x: mx.array, kind: str, backend: str) -> mx.array:
    if resolve_backend(backend) == "cpu":
        from mlx3d import native

        from .raster_cpu import get_num_threads

        return native.core().activation(x.astype(mx.float32), kind, get_num_threads())
    return mx.exp(x) if kind == "exp" else mx.sigmoid(x)


def exp(x: mx.array, backend: str = "auto") -> mx.array:
    """e^x elementwise (float32), differentiable."""
    return _activation(x, "exp", backend)


def sigmoid(x: mx.array, backend: str = "auto") -> mx.array:
    """1 / (1 + e^-x) elementwise (float32), differentiable."""
    return _activation(x, "sigmoid", backend)
