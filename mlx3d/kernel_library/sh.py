"""View-dependent colour from spherical harmonics (``mlx3d_sh_forward`` / ``mlx3d_sh_backward``)."""

from __future__ import annotations

import functools

import mlx.core as mx

from . import _call, _f32p, _host, _i64, _int, _output, _ptr, _require, _reverse_mode_only, _threads, register

register({
    "mlx3d_sh_forward": ([_f32p, _i64, _f32p, _i64, _f32p, _f32p, _i64, _int, _int, _f32p], _int),
    "mlx3d_sh_backward": ([_f32p, _i64, _f32p, _i64, _f32p, _f32p, _i64, _int, _f32p, _int, _f32p, _f32p, _f32p], _int),
})


def _sh_inputs(block0, block1, means, centre):
    n = block0.shape[0]
    b0 = _host(block0, "sh block 0", (n, None, 3))
    b1 = _host(block1, "sh block 1", (n, None, 3))
    return b0, b1, _host(means, "means", (n, 3)), _host(centre, "centre", (3,))


@functools.lru_cache(maxsize=None)
def _sh_function(degree: int, threads: int):
    @mx.custom_function
    def colours(block0, block1, means, centre):
        b0, b1, m, c = _sh_inputs(block0, block1, means, centre)
        n = b0.shape[0]
        rgb, out = _output((n, 3))
        _call("mlx3d_sh_forward", _ptr(b0), b0.shape[1], _ptr(b1), b1.shape[1], _ptr(m), _ptr(c), n, degree, threads, _ptr(out))
        return rgb

    @colours.vjp
    def colours_vjp(primals, cotangent, output):
        block0, block1, means, centre = primals
        b0, b1, m, c = _sh_inputs(block0, block1, means, centre)
        n = b0.shape[0]
        cot = _host(cotangent.astype(mx.float32), "dL/drgb", (n, 3))
        (d0, v0), (d1, v1), (dm, vm) = _output(b0.shape), _output(b1.shape), _output((n, 3))
        _call("mlx3d_sh_backward", _ptr(b0), b0.shape[1], _ptr(b1), b1.shape[1], _ptr(m), _ptr(c), n, degree, _ptr(cot),
              threads, _ptr(v0), _ptr(v1), _ptr(vm))
        return d0, d1, dm, mx.zeros_like(centre)

    return _reverse_mode_only(colours, "sh_colors")


def sh_colors(sh: list, means: mx.array, centre: mx.array, degree: int, num_threads: int = 0) -> mx.array:
    """max(colour, 0) (N, 3) of float32 SH coefficients seen from ``centre`` (3,) at ``means`` (N, 3), up to
    ``degree`` (0..3); ``sh``: [(N, K, 3)] or two blocks [(N, K0, 3), (N, K1, 3)] read as their concatenation.
    Differentiable with respect to the blocks and the means (``mlx3d._core.sh_colors``'s contract)."""
    _require(0 <= int(degree) <= 3, "sh_colors", f"degree must be 0..3, got {degree}")
    _require(len(sh) in (1, 2), "sh_colors", f"sh must be one (N, K, 3) array or two blocks, got {len(sh)} arrays")
    _require(sh[0].ndim == 3 and sh[0].shape[2] == 3 and sh[0].shape[1] >= 1, "sh_colors",
             f"sh must have shape (N, K, 3) with K >= 1, got {tuple(sh[0].shape)}")
    n = sh[0].shape[0]
    for b in sh:
        _require(b.ndim == 3 and b.shape[0] == n and b.shape[2] == 3, "sh_colors",
                 f"every sh block must have shape ({n}, K, 3), got {tuple(b.shape)}")
    k, bases = sum(b.shape[1] for b in sh), (int(degree) + 1) ** 2
    _require(k >= bases, "sh_colors", f"degree {degree} needs K >= {bases} coefficients, got {k}")
    _require(means.ndim == 2 and tuple(means.shape) == (n, 3), "sh_colors",
             f"means must have shape (N, 3) = ({n}, 3), got {tuple(means.shape)}")
    _require(centre.ndim == 1 and centre.shape[0] == 3, "sh_colors", f"centre must have shape (3,), got {tuple(centre.shape)}")
    block0 = sh[0]
    block1 = sh[1] if len(sh) == 2 else mx.zeros((block0.shape[0], 0, 3), dtype=mx.float32)
    return _sh_function(int(degree), _threads(num_threads))(block0, block1, means, centre)
