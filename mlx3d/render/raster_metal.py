"""The Metal rasterizer (Apple GPUs): ``mx.fast.metal_kernel`` kernels wrapped
in an ``mx.custom_function`` whose vjp runs the backward kernel.

Same signature and outputs as :func:`mlx3d.render.raster_cpu.rasterize_cpu`.
The per-pixel math is ``mlx3d/csrc/raster_math.h``, read at import time and
passed as the kernels' ``header``; the C++ CPU primitives compile the same
file, so the CPU tests check the math these kernels run. Only the kernel
bodies below are Metal-specific.

- forward: one thread per pixel, one threadgroup per tile (tile_size² threads,
  so tile_size <= 32); each thread walks its tile's range of flatten_ids front
  to back and writes accum, alpha, last and the final transmittance (kept for
  the backward pass).
- backward: one thread per pixel, back to front from ``last``; per-Gaussian
  gradients are summed with float atomics (``atomic_outputs=True``), so their
  summation order (and last bits) can vary from run to run, unlike the CPU
  kernel's.

Importing this module never builds a kernel; kernels are built on first use,
and :func:`rasterize_metal` raises RuntimeError where Metal is unavailable
(check :func:`metal_available`).
"""

from __future__ import annotations

import functools
import threading
from pathlib import Path

import mlx.core as mx

from .raster_cpu import prepare_inputs

__all__ = ["rasterize_metal", "metal_available", "kernel_header", "forward_source", "backward_source"]

_HERE = Path(__file__).resolve().parent
# Installed wheels carry a copy next to this file (CMakeLists.txt installs it);
# source trees and editable installs read the one the C++ code includes.
_HEADER_CANDIDATES = (_HERE / "raster_math.h", _HERE.parent / "csrc" / "raster_math.h")


def _read_header() -> str | None:
    for path in _HEADER_CANDIDATES:
        if path.is_file():
            return path.read_text(encoding="utf-8")
    return None


_HEADER = _read_header()

FORWARD_INPUTS = ["means2d", "conics", "features", "opacities", "tile_offsets", "flatten_ids"]
FORWARD_OUTPUTS = ["out_accum", "out_alpha", "out_last", "out_final_T"]
BACKWARD_INPUTS = FORWARD_INPUTS + ["last", "final_T", "cot_accum", "cot_alpha"]
BACKWARD_OUTPUTS = ["g_means2d", "g_conics", "g_features", "g_opacities"]

# Template constants of both kernels: WIDTH, HEIGHT, TILE, TILES_X, CH (channels).
_PIXEL_PREAMBLE = """
    const int tx = int(threadgroup_position_in_grid.x);
    const int ty = int(threadgroup_position_in_grid.y);
    const int px = tx * TILE + int(thread_position_in_threadgroup.x);
    const int py = ty * TILE + int(thread_position_in_threadgroup.y);
    if (px >= WIDTH || py >= HEIGHT) {
        return;
    }
    const int tile = ty * TILES_X + tx;
    const int start = tile_offsets[tile];
    const int end = tile_offsets[tile + 1];
    const float fx = float(px) + 0.5f;
    const float fy = float(py) + 0.5f;
    const int pix = py * WIDTH + px;
"""

_FORWARD_BODY = """
    float acc[CH];
    for (int ch = 0; ch < CH; ++ch) {
        acc[ch] = 0.0f;
    }
    float T = 1.0f;
    int n_last = 0;
    for (int k = start; k < end; ++k) {
        const int g = flatten_ids[k];
        const float dx = means2d[2 * g] - fx;
        const float dy = means2d[2 * g + 1] - fy;
        const float power = rm_power(conics[3 * g], conics[3 * g + 1], conics[3 * g + 2], dx, dy);
        const float alpha = rm_alpha(opacities[g], rm_exp(power), power);
        if (!(alpha > 0.0f)) {
            continue;
        }
        const float next_T = rm_next_T(T, alpha);
        if (next_T < RM_T_MIN) {
            break;
        }
        const float w = alpha * T;
        for (int ch = 0; ch < CH; ++ch) {
            acc[ch] = acc[ch] + features[g * CH + ch] * w;
        }
        T = next_T;
        n_last = k - start + 1;
    }
    for (int ch = 0; ch < CH; ++ch) {
        out_accum[pix * CH + ch] = acc[ch];
    }
    out_alpha[pix] = 1.0f - T;
    out_last[pix] = n_last;
    out_final_T[pix] = T;
"""

_BACKWARD_BODY = """
    const float T_final = final_T[pix];
    const float g_alpha = cot_alpha[pix];
    float g_acc[CH];
    float behind[CH];
    float prev_feat[CH];
    for (int ch = 0; ch < CH; ++ch) {
        g_acc[ch] = cot_accum[pix * CH + ch];
        behind[ch] = 0.0f;
        prev_feat[ch] = 0.0f;
    }
    float T = T_final;
    float prev_alpha = 0.0f;
    const int n = last[pix];
    for (int k = start + n - 1; k >= start; --k) {
        const int g = flatten_ids[k];
        const float ca = conics[3 * g];
        const float cb = conics[3 * g + 1];
        const float cc = conics[3 * g + 2];
        const float o = opacities[g];
        const float dx = means2d[2 * g] - fx;
        const float dy = means2d[2 * g + 1] - fy;
        const float power = rm_power(ca, cb, cc, dx, dy);
        const float e = rm_exp(power);
        const float alpha = rm_alpha(o, e, power);
        if (!(alpha > 0.0f)) {
            continue;
        }
        T = rm_T_before(T, alpha);
        const float w = alpha * T;
        float dot = 0.0f;
        for (int ch = 0; ch < CH; ++ch) {
            const float f = features[g * CH + ch];
            const float nb = rm_behind(behind[ch], prev_alpha, prev_feat[ch]);
            behind[ch] = nb;
            dot += (f - nb) * g_acc[ch];
            prev_feat[ch] = f;
            atomic_fetch_add_explicit(&g_features[g * CH + ch], w * g_acc[ch], memory_order_relaxed);
        }
        prev_alpha = alpha;
        const float dl_dalpha = rm_dl_dalpha(T, dot, T_final, g_alpha, alpha);
        const RmGaussGrad<float> gg = rm_gaussian_grad(ca, cb, cc, dx, dy, o, e, dl_dalpha);
        atomic_fetch_add_explicit(&g_means2d[2 * g], gg.mean_x, memory_order_relaxed);
        atomic_fetch_add_explicit(&g_means2d[2 * g + 1], gg.mean_y, memory_order_relaxed);
        atomic_fetch_add_explicit(&g_conics[3 * g], gg.conic_a, memory_order_relaxed);
        atomic_fetch_add_explicit(&g_conics[3 * g + 1], gg.conic_b, memory_order_relaxed);
        atomic_fetch_add_explicit(&g_conics[3 * g + 2], gg.conic_c, memory_order_relaxed);
        atomic_fetch_add_explicit(&g_opacities[g], gg.opacity, memory_order_relaxed);
    }
"""


def metal_available() -> bool:
    """True where MLX can run Metal kernels (Apple GPUs)."""
    try:
        return bool(mx.metal.is_available())
    except Exception:  # noqa: BLE001 - a missing backend means "not available"
        return False


def kernel_header() -> str:
    """The ``header`` of both kernels: the text of raster_math.h."""
    if _HEADER is None:
        raise RuntimeError(
            "mlx3d: raster_math.h was not found next to mlx3d/render/raster_metal.py "
            f"or in mlx3d/csrc (looked in {', '.join(str(p) for p in _HEADER_CANDIDATES)}); reinstall mlx3d."
        )
    return _HEADER


def forward_source() -> str:
    """Body of the forward kernel (one thread per pixel)."""
    return _PIXEL_PREAMBLE + _FORWARD_BODY


def backward_source() -> str:
    """Body of the backward kernel (one thread per pixel, atomic adds)."""
    return _PIXEL_PREAMBLE + _BACKWARD_BODY


_kernel_lock = threading.Lock()
_kernel_cache: dict = {}


def _metal_kernel(**kwargs):
    # rm_exp rounds with (x + 1.5·2^23) - 1.5·2^23 and the skip rules rely on
    # NaN comparisons: both need IEEE ("safe") math, MLX's default; ask for it
    # explicitly where this MLX takes compile options.
    try:
        return mx.fast.metal_kernel(**kwargs, compile_options={"math_mode": "safe"})
    except TypeError:
        return mx.fast.metal_kernel(**kwargs)


def _kernels():
    """(forward, backward) metal_kernel objects, built on first use."""
    with _kernel_lock:
        if not _kernel_cache:
            header = kernel_header()
            _kernel_cache["forward"] = _metal_kernel(
                name="mlx3d_rasterize_forward",
                input_names=FORWARD_INPUTS,
                output_names=FORWARD_OUTPUTS,
                source=forward_source(),
                header=header,
            )
            _kernel_cache["backward"] = _metal_kernel(
                name="mlx3d_rasterize_backward",
                input_names=BACKWARD_INPUTS,
                output_names=BACKWARD_OUTPUTS,
                source=backward_source(),
                header=header,
                atomic_outputs=True,
            )
        return _kernel_cache["forward"], _kernel_cache["backward"]


@functools.lru_cache(maxsize=64)
def _rasterizer(width: int, height: int, tile: int, channels: int):
    """The differentiable rasterizer for one image size, tile size and channel count."""
    forward, backward = _kernels()
    tiles_x = -(-width // tile)
    tiles_y = -(-height // tile)
    template = [("WIDTH", width), ("HEIGHT", height), ("TILE", tile), ("TILES_X", tiles_x), ("CH", channels)]
    grid = (tiles_x * tile, tiles_y * tile, 1)
    threadgroup = (tile, tile, 1)

    @mx.custom_function
    def raster(means2d, conics, features, opacities, tile_offsets, flatten_ids):
        outs = forward(
            inputs=[means2d, conics, features, opacities, tile_offsets, flatten_ids],
            template=template,
            grid=grid,
            threadgroup=threadgroup,
            output_shapes=[(height, width, channels), (height, width), (height, width), (height, width)],
            output_dtypes=[mx.float32, mx.float32, mx.int32, mx.float32],
        )
        return tuple(outs)

    @raster.vjp
    def raster_vjp(primals, cotangents, outputs):
        means2d, conics, features, opacities, tile_offsets, flatten_ids = primals
        cot_accum = cotangents[0] if cotangents[0] is not None else mx.zeros((height, width, channels))
        cot_alpha = cotangents[1] if cotangents[1] is not None else mx.zeros((height, width))
        grads = backward(
            inputs=[
                means2d, conics, features, opacities, tile_offsets, flatten_ids,
                outputs[2], outputs[3], cot_accum.astype(mx.float32), cot_alpha.astype(mx.float32),
            ],
            template=template,
            grid=grid,
            threadgroup=threadgroup,
            output_shapes=[means2d.shape, conics.shape, features.shape, opacities.shape],
            output_dtypes=[mx.float32] * 4,
            init_value=0,
        )
        return (grads[0], grads[1], grads[2], grads[3], mx.zeros_like(tile_offsets), mx.zeros_like(flatten_ids))

    return raster


def rasterize_metal(
    means2d,
    conics,
    features,
    opacities,
    tile_offsets,
    flatten_ids,
    width: int,
    height: int,
    tile_size: int = 16,
    num_threads: int | None = None,
):
    """Composite binned Gaussians on an Apple GPU; arguments and outputs as in
    :func:`mlx3d.render.raster_cpu.rasterize_cpu` (``num_threads`` is accepted
    and ignored). Differentiable w.r.t. means2d, conics, features, opacities.

    Raises:
        ValueError: bad inputs (named), or tile_size > 32 (threadgroups hold
            at most 1024 threads).
        RuntimeError: Metal is not available here.
    """
    (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size) = prepare_inputs(
        means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size
    )
    if tile_size > 32:
        raise ValueError(f"tile_size must be <= 32 for the Metal rasterizer (one thread per pixel), got {tile_size}")
    if not metal_available():
        raise RuntimeError(
            "rasterize_metal needs Metal (an Apple GPU), which MLX reports as unavailable here; "
            "use mlx3d.render.raster_cpu.rasterize_cpu (the 'cpu' backend)."
        )
    channels = features.shape[1]
    if means2d.shape[0] == 0 or flatten_ids.shape[0] == 0:
        # Nothing is drawn; the outputs do not depend on the inputs (zero gradients).
        return (
            mx.zeros((height, width, channels), dtype=mx.float32),
            mx.zeros((height, width), dtype=mx.float32),
            mx.zeros((height, width), dtype=mx.int32),
        )
    accum, alpha, last, _final_t = _rasterizer(width, height, tile_size, channels)(
        means2d, conics, features, opacities, tile_offsets, flatten_ids
    )
    return accum, alpha, last
