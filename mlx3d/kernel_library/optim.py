"""Adam's update, the finiteness check the trainer runs before it, and the parameter activations
(``mlx3d_adam_moment``, ``mlx3d_adam_param``, ``mlx3d_all_finite``, ``mlx3d_exp``, ``mlx3d_sigmoid``).

These run eagerly (the inputs are evaluated, the kernel writes its results into fresh arrays), where
``mlx3d._core``'s primitives are lazy. The C Adam functions may update in place, and ``_core`` writes
m', v', p' over m, v, p where nothing else holds those arrays when the update is evaluated; here the
caller always still holds them during the call (its arguments; ``mlx3d.training.adam.Adam`` keeps the old
moments until the call returns), so nothing passed in is ever written: same values, but the old and new
arrays coexist until the caller drops the old ones.
"""

from __future__ import annotations

import functools

import mlx.core as mx
import numpy as np

from . import (_call, _contiguous, _f32p, _f64, _host, _i64, _int, _output, _ptr, _reverse_mode_only, _threads, _u8p,
              register)

register({
    "mlx3d_adam_moment": ([_f32p, _f32p, _i64, _f64, _int, _int, _f32p], _int),
    "mlx3d_adam_param": ([_f32p, _f32p, _f32p, _i64, _f64, _f64, _f64, _f64, _int, _f32p], _int),
    "mlx3d_all_finite": ([_f32p, _i64, _int, _u8p], _int),
    "mlx3d_exp": ([_f32p, _i64, _int, _f32p], _int),
    "mlx3d_sigmoid": ([_f32p, _i64, _int, _f32p], _int),
})

_ACTIVATIONS = {"exp": "mlx3d_exp", "sigmoid": "mlx3d_sigmoid"}


def adam_step(p: mx.array, g: mx.array, m: mx.array, v: mx.array, lr: float, b1: float, b2: float, eps: float, c1: float,
              c2: float, num_threads: int = 0) -> list:
    """One Adam step on float32 arrays of one shape: returns [p', m', v'] (``mlx3d._core.adam_step``'s contract):
    m' = b1 m + (1 - b1) g, v' = b2 v + (1 - b2) g², p' = p - lr (m' / c1) / (sqrt(v' / c2) + eps), in float32 with
    the scalars rounded to float32; c1, c2: the bias corrections 1 - b1^t, 1 - b2^t. Fresh arrays (see the module)."""
    shape = tuple(p.shape)
    for a in (g, m, v):
        if tuple(a.shape) != shape:
            raise ValueError(f"adam_step: p, g, m and v must have the same shape, got {shape} and {tuple(a.shape)}")
    if not (c1 > 0 and c2 > 0):
        raise ValueError(f"adam_step: the bias corrections c1, c2 must be > 0, got {c1}, {c2}")
    threads = _threads(num_threads)
    hp, hg, hm, hv = (_host(a, f"adam_step: {name}", shape) for name, a in zip("pgmv", (p, g, m, v)))
    n = hp.size
    (p_new, po), (m_new, mo), (v_new, vo) = _output(shape), _output(shape), _output(shape)
    _call("mlx3d_adam_moment", _ptr(hg), _ptr(hm), n, float(b1), 0, threads, _ptr(mo))
    _call("mlx3d_adam_moment", _ptr(hg), _ptr(hv), n, float(b2), 1, threads, _ptr(vo))
    _call("mlx3d_adam_param", _ptr(hp), _ptr(mo), _ptr(vo), n, float(lr), float(eps), float(c1), float(c2), threads, _ptr(po))
    return [p_new, m_new, v_new]


def all_finite(arrays, num_threads: int = 0) -> mx.array:
    """A bool scalar: True when no element of any array is NaN or infinite, each read as float32
    (``mlx3d._core.all_finite``'s contract; True for no arrays)."""
    threads = _threads(num_threads)
    finite = np.ones(1, np.uint8)
    for a in arrays:
        if isinstance(a, mx.array) and a.dtype != mx.float32:
            a = a.astype(mx.float32)
        x = _contiguous(a, np.float32)
        _call("mlx3d_all_finite", _ptr(x), x.size, threads, _ptr(finite))
        if not finite[0]:
            return mx.array(False)
    return mx.array(True)


@functools.lru_cache(maxsize=None)
def _activation_function(kind: str, threads: int):
    name = _ACTIVATIONS[kind]

    @mx.custom_function
    def activate(x):
        shape = tuple(x.shape)
        xs = _host(x, "activation: x", (None,) * len(shape))
        y, out = _output(shape)
        _call(name, _ptr(xs), xs.size, threads, _ptr(out))
        return y

    @activate.vjp
    def activate_vjp(primals, cotangent, output):  # MLX's Exp and Sigmoid vjps: cot e^x, cot s (1 - s)
        y = output[0] if isinstance(output, (list, tuple)) else output
        cot = cotangent[0] if isinstance(cotangent, (list, tuple)) else cotangent
        return (cot * y,) if kind == "exp" else (cot * (y * (1.0 - y)),)

    return _reverse_mode_only(activate, "activation")


def activation(x: mx.array, kind: str, num_threads: int = 0) -> mx.array:
    """exp(x) (kind 'exp') or sigmoid(x) (kind 'sigmoid') of a float32 array, bit for bit MLX's CPU mx.exp /
    mx.sigmoid, values and gradients (``mlx3d._core.activation``'s contract; differentiable)."""
    if kind not in _ACTIVATIONS:
        raise ValueError(f"activation: kind must be 'exp' or 'sigmoid', got '{kind}'")
    return _activation_function(kind, _threads(num_threads))(x)
