"""The CPU rasterizer: a C++ MLX primitive (``mlx3d._core.rasterize_forward``).

``rasterize_cpu`` composites binned 2D Gaussians front to back with the 3DGS
rules (docs/guides/rendering.md; the per-pixel code is
``mlx3d/csrc/raster_math.h``, shared with the Metal kernels) and is
differentiable with ``mx.grad`` / ``mx.value_and_grad`` / ``mx.vjp`` with
respect to means2d, conics, features and opacities; tile_offsets and
flatten_ids get zero gradients. Forward-mode (``mx.jvp``) and ``mx.vmap`` are
not implemented.

``rasterize_cpu_surface`` is the forward-only variant that composites a
per-pixel surface layer (colour, alpha, depth) with the Gaussians in depth
order (``mlx3d.render.surface``); its gradients raise.

Both passes are threaded over tiles. The backward pass sums gradients per tile
entry, then per Gaussian in flatten_ids order, so its results are bitwise
identical for any thread count. Threads: :func:`set_num_threads` (default:
all cores, or the ``MLX3D_NUM_THREADS`` environment variable).

Inside a tile, each block of 8 (or 4) pixels only evaluates the Gaussians that
can reach one of its pixels with alpha >= 1/255: a bound on each Gaussian's
footprint, with margins that cover float32 rounding, so every pair it leaves
out is one the rules skip anyway and the results are bitwise those of
evaluating every pair (``MLX3D_RASTER_CULL=0`` turns this off, for testing).
"""

from __future__ import annotations

import os
import threading

import mlx.core as mx
import numpy as np

__all__ = ["rasterize_cpu", "rasterize_cpu_surface", "set_num_threads", "get_num_threads", "prepare_inputs", "surface_forward_only", "surface_layer"]

_ENV_THREADS = "MLX3D_NUM_THREADS"
_lock = threading.Lock()
_num_threads: int | None = None  # None: the default (environment variable, else all cores)


def _default_threads() -> int:
    value = os.environ.get(_ENV_THREADS, "").strip()
    if value:
        try:
            n = int(value)
        except ValueError:
            raise ValueError(f"{_ENV_THREADS} must be a positive integer, got {value!r}") from None
        if n < 1:
            raise ValueError(f"{_ENV_THREADS} must be a positive integer, got {value!r}")
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def set_num_threads(n: int | None) -> None:
    """Threads used by the CPU rasterizer; ``None`` or 0 restores the default
    (``MLX3D_NUM_THREADS`` if set, else all cores available to this process)."""
    global _num_threads
    if n is not None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
            raise ValueError(f"num_threads must be an int, got {n!r}")
        if n < 0:
            raise ValueError(f"num_threads must be >= 0, got {n}")
    with _lock:
        _num_threads = None if not n else int(n)


def get_num_threads() -> int:
    """Threads the CPU rasterizer uses (a positive int)."""
    n = _num_threads
    return n if n is not None else _default_threads()


def _as_array(x, name: str) -> mx.array:
    if isinstance(x, mx.array):
        return x
    try:
        return mx.array(np.asarray(x))
    except Exception as exc:  # noqa: BLE001 - reported with the argument's name
        raise ValueError(f"{name}: cannot convert {type(x).__name__} to an array ({exc})") from None


def _float32(x, name: str) -> mx.array:
    a = _as_array(x, name)
    if a.dtype == mx.bool_ or mx.issubdtype(a.dtype, mx.complexfloating):
        raise ValueError(f"{name} must be a real floating-point array, got dtype {a.dtype}")
    return a if a.dtype == mx.float32 else a.astype(mx.float32)


def _int32(x, name: str) -> mx.array:
    a = _as_array(x, name)
    if not mx.issubdtype(a.dtype, mx.integer) or a.dtype == mx.bool_:
        raise ValueError(f"{name} must be an integer array, got dtype {a.dtype}")
    return a if a.dtype == mx.int32 else a.astype(mx.int32)


def _positive_int(v, name: str, minimum: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{name} must be an int, got {v!r}")
    if v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {v}")
    return int(v)


def prepare_inputs(
    means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size, check_indices: bool = True
):
    """Validates and casts the rasterizer inputs (shared by the CPU and Metal paths).

    Returns (means2d, conics, features, opacities, tile_offsets, flatten_ids,
    width, height, tile_size) with float32 / int32 arrays. Raises ValueError
    naming the offending argument. With ``check_indices`` the integer inputs
    are also checked by value (offsets non-decreasing from 0 to M, ids in
    [0, N)), which reads them (they come from the non-differentiable binning).
    """
    width = _positive_int(width, "width")
    height = _positive_int(height, "height")
    tile_size = _positive_int(tile_size, "tile_size")
    means2d = _float32(means2d, "means2d")
    conics = _float32(conics, "conics")
    features = _float32(features, "features")
    opacities = _float32(opacities, "opacities")
    tile_offsets = _int32(tile_offsets, "tile_offsets")
    flatten_ids = _int32(flatten_ids, "flatten_ids")

    if means2d.ndim != 2 or means2d.shape[1] != 2:
        raise ValueError(f"means2d must have shape (N, 2), got {tuple(means2d.shape)}")
    n = means2d.shape[0]
    if conics.ndim != 2 or conics.shape != (n, 3):
        raise ValueError(f"conics must have shape (N, 3) = ({n}, 3), got {tuple(conics.shape)}")
    if features.ndim != 2 or features.shape[0] != n or features.shape[1] < 1:
        raise ValueError(f"features must have shape (N, C) with N = {n} and C >= 1, got {tuple(features.shape)}")
    if opacities.ndim != 1 or opacities.shape[0] != n:
        raise ValueError(f"opacities must have shape (N,) = ({n},), got {tuple(opacities.shape)}")
    tiles = (-(-width // tile_size)) * (-(-height // tile_size))
    if tile_offsets.ndim != 1 or tile_offsets.shape[0] != tiles + 1:
        raise ValueError(
            f"tile_offsets must have shape (tiles + 1,) = ({tiles + 1},) for a {width}x{height} image "
            f"with tile_size {tile_size}, got {tuple(tile_offsets.shape)}"
        )
    if flatten_ids.ndim != 1:
        raise ValueError(f"flatten_ids must have shape (M,), got {tuple(flatten_ids.shape)}")
    m = flatten_ids.shape[0]
    if check_indices:
        off = np.asarray(tile_offsets)
        if off[0] != 0 or off[-1] != m or np.any(np.diff(off) < 0):
            raise ValueError(
                f"tile_offsets must be non-decreasing from 0 to len(flatten_ids) = {m}, "
                f"got first {int(off[0])}, last {int(off[-1])}"
            )
        if m:
            ids = np.asarray(flatten_ids)
            lo, hi = int(ids.min()), int(ids.max())
            if lo < 0 or hi >= n:
                raise ValueError(f"flatten_ids must lie in [0, N) = [0, {n}), got values in [{lo}, {hi}]")
    return means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size


def rasterize_cpu(
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
    *,
    background=None,
    check_indices: bool = True,
):
    """Composite binned Gaussians on the CPU.

    Args:
        means2d: (N, 2) pixel positions (x right, y down, pixel centres at +0.5).
        conics: (N, 3) (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
        features: (N, C) any channels (RGB, depth, normals, ...), C >= 1.
        opacities: (N,) in [0, 1].
        tile_offsets: (tiles_y * tiles_x + 1,) int; flatten_ids: (M,) int
            (the binning of ``mlx3d.render.binning.bin_gaussians``).
        width, height, tile_size: the image and its tiles.
        num_threads: None for :func:`get_num_threads`, 0 for all hardware
            threads, else that many threads.
        background: None, or (C,) composited behind the Gaussians as
            ``accum + (1 - alpha) * background`` inside the kernel's threads
            (differentiable with respect to it too).
        check_indices: check the integer inputs by value (see
            :func:`prepare_inputs`); the renderer skips it for its own binning.

    Returns:
        (accum (H, W, C) float32, with the background when given, alpha (H, W)
        float32 = 1 - final transmittance, last (H, W) int32 = 1 + position of
        the last contributing entry in the pixel's tile range, 0 if none),
        lazily evaluated mx.arrays. Float inputs are cast to float32, ids to int32.
    """
    return _forward("rasterize_forward", (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size), (), num_threads,
                    check_indices, background)


def _forward(op: str, inputs: tuple, surface: tuple, num_threads, check_indices: bool = True, background=None):
    """Run the native forward ``op`` on the checked ``inputs`` (rasterize_cpu's first nine arguments)
    with the ``surface`` arrays after the ids (and a scalar or (C,) background); returns (accum, alpha, last)."""
    *arrays, width, height, tile_size = prepare_inputs(*inputs, check_indices=check_indices)
    threads = get_num_threads() if num_threads is None else _positive_int(num_threads, "num_threads", minimum=0)
    extra = ()
    if background is not None:
        bg = _float32(background, "background").reshape(-1)
        extra = (mx.broadcast_to(bg, (arrays[2].shape[1],)) if bg.size == 1 else bg,)
    from mlx3d import native

    accum, alpha, last, _final_t = getattr(native.core(), op)(*arrays, *surface, width, height, tile_size, threads, *extra)
    return accum, alpha, last


def rasterize_cpu_surface(
    means2d,
    conics,
    features,
    opacities,
    tile_offsets,
    flatten_ids,
    depths,
    surface_color,
    surface_alpha,
    surface_depth,
    width: int,
    height: int,
    tile_size: int = 16,
    num_threads: int | None = None,
):
    """``rasterize_cpu`` composited with a surface layer in depth order (forward-only).

    Extra arguments: depths (N,) the Gaussians' camera z (the binning's sort
    key); surface_color (H, W, C) premultiplied; surface_alpha (H, W) in
    [0, 1]; surface_depth (H, W) camera z, +inf where the surface lies behind
    every Gaussian. Per pixel the surface is composited just before the first
    tile entry with depth >= surface_depth (after the last if none), unless the
    pixel has stopped: accum += T * colour, T *= 1 - alpha (stop if T < 1e-4).

    Returns (accum (H, W, C), alpha (H, W) = 1 - final T including the
    surface, last (H, W) int32) as ``rasterize_cpu``. Differentiating raises.
    """
    surface = tuple(_float32(a, name) for a, name in zip((depths, surface_color, surface_alpha, surface_depth), _SURFACE_INPUTS))
    # their shapes are checked by the op (ValueError naming the input)
    inputs = (means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size)
    return _forward("rasterize_forward_surface", inputs, surface, num_threads)


_SURFACE_INPUTS = ("depths", "surface_color", "surface_alpha", "surface_depth")


def surface_layer(depths, surface_color, surface_alpha, surface_depth, n: int, height: int, width: int, channels: int) -> list:
    """The surface variants' extra inputs as float32 arrays, checked by shape: depths (N,), colour (H,W,C),
    alpha and depth (H,W); ValueError naming the input otherwise."""
    shapes = ((n,), (height, width, channels), (height, width), (height, width))
    layer = [_float32(a, name) for a, name in zip((depths, surface_color, surface_alpha, surface_depth), _SURFACE_INPUTS)]
    for name, a, shape in zip(_SURFACE_INPUTS, layer, shapes):
        if tuple(a.shape) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {tuple(a.shape)}")
    return layer


def surface_forward_only(composite, name: str, *inputs):
    """``composite(*inputs)`` (the surface variants' outputs) with a vjp that raises, as the CPU primitive's does."""

    @mx.custom_function
    def forward(*args):
        return composite(*args)

    @forward.vjp
    def no_gradient(primals, cotangents, outputs):
        raise RuntimeError(f"{name}: compositing over a surface is forward-only (no gradients); render without `surface` to differentiate.")

    return forward(*inputs)
