"""The Metal rasterizer (Apple GPUs): ``mx.fast.metal_kernel`` kernels wrapped
in an ``mx.custom_function`` whose vjp runs the backward kernel.

Same signature and outputs as :func:`mlx3d.render.raster_cpu.rasterize_cpu`
(and ``rasterize_metal_surface`` as ``rasterize_cpu_surface``). The per-pixel
math is ``mlx3d/csrc/raster_math.h``, read at import time and passed as the
kernels' ``header``; the C++ CPU primitives compile the same file, so the CPU
tests check the math these kernels run. Only the kernel bodies below are
Metal-specific.

- forward: one thread per pixel, one threadgroup per tile (tile_size² threads,
  so tile_size <= 32); each thread walks its tile's range of flatten_ids front
  to back and writes accum, alpha, last and the final transmittance (kept for
  the backward pass).
- backward: one thread per pixel, back to front from ``last``; per-Gaussian
  gradients are summed with float atomics (``atomic_outputs=True``), so their
  summation order (and last bits) can vary from run to run, unlike the CPU
  kernel's.
- surface forward: the forward with a surface layer composited in depth order
  (``mlx3d.render.surface``), forward-only.

The kernels are launched through one small interface, :class:`RasterKernels`
(``forward``, ``backward``, ``surface``: arrays in, arrays out), built from a
*kernel builder* with ``mx.fast.metal_kernel``'s signature. ``use_builder``
swaps the builder: the test suite runs these exact kernel sources compiled as
C++ through it (``tests/metal_emulator.py``), so every line of this module
runs on Linux; another GPU backend (MLX's ``mx.fast.cuda_kernel``) would give
``RasterKernels`` its own bodies and builder, with the rest of the path
unchanged.

Importing this module never builds a kernel; kernels are built on first use,
and :func:`rasterize_metal` raises RuntimeError where Metal is unavailable
(check :func:`metal_available`).
"""

from __future__ import annotations

import contextlib
import functools
import threading
from pathlib import Path

import mlx.core as mx

from .raster_cpu import prepare_inputs, surface_forward_only, surface_layer

__all__ = [
    "rasterize_metal", "rasterize_metal_surface", "metal_available", "kernel_header", "forward_source", "backward_source",
    "surface_source", "RasterKernels", "use_builder",
]

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
SURFACE_INPUTS = FORWARD_INPUTS + ["depths", "surface_color", "surface_alpha", "surface_depth"]

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

# The forward pass of one pixel; the surface forward (mlx3d.render.surface) fills in the marked places
# (SETUP, BEFORE_ENTRY, ON_STOP, AFTER_ENTRIES), which the plain forward leaves empty.
_COMPOSITE_BODY = """
    float acc[CH];
    for (int ch = 0; ch < CH; ++ch) {
        acc[ch] = 0.0f;
    }
    float T = 1.0f;
    int n_last = 0;
SETUP
    for (int k = start; k < end; ++k) {
        const int g = flatten_ids[k];
BEFORE_ENTRY
        const float dx = means2d[2 * g] - fx;
        const float dy = means2d[2 * g + 1] - fy;
        const float power = rm_power(conics[3 * g], conics[3 * g + 1], conics[3 * g + 2], dx, dy);
        const float alpha = rm_alpha(opacities[g], rm_exp(power), power);
        if (!(alpha > 0.0f)) {
            continue;
        }
        const float next_T = rm_next_T(T, alpha);
        if (next_T < RM_T_MIN) {
ON_STOP
            break;
        }
        const float w = alpha * T;
        for (int ch = 0; ch < CH; ++ch) {
            acc[ch] = acc[ch] + features[g * CH + ch] * w;
        }
        T = next_T;
        n_last = k - start + 1;
    }
AFTER_ENTRIES
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


# The surface forward (mlx3d.render.surface): before the first entry whose depth is not below the pixel's
# surface depth (after the last if none), a pixel that has not stopped takes accum += T * colour,
# T *= 1 - surface alpha, and stops if T < RM_T_MIN.
_SURFACE_EVENT = """
            for (int ch = 0; ch < CH; ++ch) {
                acc[ch] = acc[ch] + T * surface_color[pix * CH + ch];
            }
            T = rm_next_T(T, s_alpha);"""
_SURFACE_PARTS = {
    "SETUP": """    bool passed = false;
    bool stopped = false;
    const float s_depth = surface_depth[pix];
    const float s_alpha = surface_alpha[pix];""",
    "BEFORE_ENTRY": """        if (!passed && !(depths[g] < s_depth)) {
            passed = true;""" + _SURFACE_EVENT + """
            if (T < RM_T_MIN) {
                stopped = true;
                break;
            }
        }""",
    "ON_STOP": "            stopped = true;",
    "AFTER_ENTRIES": """    if (!passed && !stopped) {""" + _SURFACE_EVENT.replace("\n    ", "\n") + """
    }""",
}


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


def _composite_source(parts: dict) -> str:
    body = _COMPOSITE_BODY
    for marker in ("SETUP", "BEFORE_ENTRY", "ON_STOP", "AFTER_ENTRIES"):
        body = body.replace(marker + "\n", parts[marker] + "\n" if marker in parts else "")
    return _PIXEL_PREAMBLE + body


def forward_source() -> str:
    """Body of the forward kernel (one thread per pixel)."""
    return _composite_source({})


def backward_source() -> str:
    """Body of the backward kernel (one thread per pixel, atomic adds)."""
    return _PIXEL_PREAMBLE + _BACKWARD_BODY


def surface_source() -> str:
    """Body of the surface forward kernel (one thread per pixel)."""
    return _composite_source(_SURFACE_PARTS)


def _metal_kernel(**kwargs):
    """``mx.fast.metal_kernel`` asking for IEEE ("safe") math where this MLX takes compile options:
    rm_exp rounds with (x + 1.5·2^23) - 1.5·2^23 and the skip rules rely on NaN comparisons."""
    try:
        return mx.fast.metal_kernel(**kwargs, compile_options={"math_mode": "safe"})
    except TypeError:
        return mx.fast.metal_kernel(**kwargs)


class RasterKernels:
    """The rasterizer's GPU kernels, each a launch function: arrays in, arrays out.

    ``build`` has ``mx.fast.metal_kernel``'s signature (name, input_names, output_names, source,
    header, atomic_outputs) and returns a launch callable (inputs, template, grid, threadgroup,
    output_shapes, output_dtypes, init_value); kernels are built on first use.
    """

    def __init__(self, build=_metal_kernel):
        self._build = build
        self._lock = threading.Lock()
        self._built: dict = {}

    def _kernel(self, name: str):
        with self._lock:
            if name not in self._built:
                inputs, outputs, source, atomic = {
                    "forward": (FORWARD_INPUTS, FORWARD_OUTPUTS, forward_source, False),
                    "backward": (BACKWARD_INPUTS, BACKWARD_OUTPUTS, backward_source, True),
                    "surface": (SURFACE_INPUTS, FORWARD_OUTPUTS, surface_source, False),
                }[name]
                self._built[name] = self._build(name=f"mlx3d_rasterize_{name}", input_names=inputs, output_names=outputs,
                                                source=source(), header=kernel_header(), atomic_outputs=atomic)
            return self._built[name]

    @staticmethod
    def _launch_args(width: int, height: int, tile: int, channels: int) -> dict:
        tiles_x, tiles_y = -(-width // tile), -(-height // tile)
        return dict(template=[("WIDTH", width), ("HEIGHT", height), ("TILE", tile), ("TILES_X", tiles_x), ("CH", channels)],
                    grid=(tiles_x * tile, tiles_y * tile, 1), threadgroup=(tile, tile, 1))

    def _composite(self, name: str, inputs: list, width: int, height: int, tile: int) -> tuple:
        channels = inputs[2].shape[1]
        return tuple(self._kernel(name)(
            inputs=inputs, output_shapes=[(height, width, channels), (height, width), (height, width), (height, width)],
            output_dtypes=[mx.float32, mx.float32, mx.int32, mx.float32], **self._launch_args(width, height, tile, channels)))

    def forward(self, inputs: list, width: int, height: int, tile: int) -> tuple:
        """``FORWARD_INPUTS`` -> (accum (H,W,C), alpha, last int32, final_T)."""
        return self._composite("forward", inputs, width, height, tile)

    def surface(self, inputs: list, width: int, height: int, tile: int) -> tuple:
        """``SURFACE_INPUTS`` -> the outputs of ``forward`` with the surface layer composited."""
        return self._composite("surface", inputs, width, height, tile)

    def backward(self, inputs: list, width: int, height: int, tile: int) -> tuple:
        """``BACKWARD_INPUTS`` -> gradients of means2d, conics, features, opacities."""
        shapes = [a.shape for a in inputs[:4]]
        return tuple(self._kernel("backward")(
            inputs=inputs, output_shapes=shapes, output_dtypes=[mx.float32] * 4, init_value=0,
            **self._launch_args(width, height, tile, inputs[2].shape[1])))


_kernels = RasterKernels()


def kernels() -> RasterKernels:
    """The active kernels (Metal's, unless ``use_builder`` is in effect)."""
    return _kernels


@contextlib.contextmanager
def use_builder(build):
    """Runs the block with kernels built by ``build`` (``mx.fast.metal_kernel``'s signature) instead of Metal's."""
    global _kernels
    previous, _kernels = _kernels, RasterKernels(build)
    _rasterizer.cache_clear()
    try:
        yield _kernels
    finally:
        _kernels = previous
        _rasterizer.cache_clear()


@functools.lru_cache(maxsize=64)
def _rasterizer(width: int, height: int, tile: int):
    """The differentiable rasterizer for one image size and tile size."""

    @mx.custom_function
    def raster(means2d, conics, features, opacities, tile_offsets, flatten_ids):
        return kernels().forward([means2d, conics, features, opacities, tile_offsets, flatten_ids], width, height, tile)

    @raster.vjp
    def raster_vjp(primals, cotangents, outputs):
        means2d, conics, features, opacities, tile_offsets, flatten_ids = primals
        cot_accum = mx.zeros_like(outputs[0]) if cotangents[0] is None else cotangents[0].astype(mx.float32)
        cot_alpha = mx.zeros_like(outputs[1]) if cotangents[1] is None else cotangents[1].astype(mx.float32)
        grads = kernels().backward(
            [means2d, conics, features, opacities, tile_offsets, flatten_ids, outputs[2], outputs[3], cot_accum, cot_alpha], width, height, tile)
        return (*grads, mx.zeros_like(tile_offsets), mx.zeros_like(flatten_ids))

    return raster


def _checked(args: tuple, check_indices: bool) -> tuple:
    """``prepare_inputs`` plus the Metal rules (tile_size <= 32, Metal available)."""
    checked = prepare_inputs(*args, check_indices=check_indices)
    if checked[-1] > 32:
        raise ValueError(f"tile_size must be <= 32 for the Metal rasterizer (one thread per pixel), got {checked[-1]}")
    if not metal_available():
        raise RuntimeError(
            "rasterize_metal needs Metal (an Apple GPU), which MLX reports as unavailable here; "
            "use mlx3d.render.raster_cpu.rasterize_cpu (the 'cpu' backend) or raster_mlx.rasterize_mlx ('mlx')."
        )
    return checked


def _nothing_drawn(means2d, flatten_ids, height: int, width: int, channels: int):
    """The outputs where no Gaussian is drawn (they then do not depend on the inputs), else None."""
    if means2d.shape[0] and flatten_ids.shape[0]:
        return None
    return mx.zeros((height, width, channels), dtype=mx.float32), mx.zeros((height, width), dtype=mx.float32), mx.zeros((height, width), dtype=mx.int32)


def rasterize_metal(
    means2d, conics, features, opacities, tile_offsets, flatten_ids, width: int, height: int, tile_size: int = 16,
    num_threads: int | None = None, *, check_indices: bool = True,
):
    """Composite binned Gaussians on an Apple GPU; arguments and outputs as in
    :func:`mlx3d.render.raster_cpu.rasterize_cpu` (``num_threads`` is accepted
    and ignored; ``check_indices=False`` skips reading the integer inputs back,
    for the renderer's own binning). Differentiable w.r.t. means2d, conics,
    features, opacities.

    Raises:
        ValueError: bad inputs (named), or tile_size > 32 (threadgroups hold
            at most 1024 threads).
        RuntimeError: Metal is not available here.
    """
    del num_threads
    means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size = _checked(
        (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size), check_indices)
    empty = _nothing_drawn(means2d, flatten_ids, height, width, features.shape[1])
    if empty is not None:
        return empty
    accum, alpha, last, _final_t = _rasterizer(width, height, tile_size)(means2d, conics, features, opacities, tile_offsets, flatten_ids)
    return accum, alpha, last


def rasterize_metal_surface(
    means2d, conics, features, opacities, tile_offsets, flatten_ids, depths, surface_color, surface_alpha, surface_depth,
    width: int, height: int, tile_size: int = 16, num_threads: int | None = None,
):
    """:func:`rasterize_metal` composited with a surface layer in depth order (forward-only); arguments
    and outputs as :func:`mlx3d.render.raster_cpu.rasterize_cpu_surface`. The surface arrays are
    checked by shape (ValueError naming them); differentiating raises."""
    del num_threads
    means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size = _checked(
        (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size), False)
    channels = features.shape[1]
    layer = surface_layer(depths, surface_color, surface_alpha, surface_depth, means2d.shape[0], height, width, channels)
    if _nothing_drawn(means2d, flatten_ids, height, width, channels) is not None:
        return layer[1], layer[2], mx.zeros((height, width), dtype=mx.int32)
    def composite(*inputs):
        return kernels().surface(list(inputs), width, height, tile_size)

    inputs = (means2d, conics, features, opacities, tile_offsets, flatten_ids, *layer)
    accum, alpha, last, _final_t = surface_forward_only(composite, "rasterize_metal_surface", *inputs)
    return accum, alpha, last
