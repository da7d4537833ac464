"""The render path's kernels, under ``mlx3d._core``'s signatures: the EWA projection (``mlx3d_project_ewa*``),
the tile binning (``mlx3d_bin_tiles``) and the tile rasterizer (``mlx3d_rasterize_*``).

``rasterize_forward`` is differentiable with respect to means2d, conics, features, opacities and the
background (``mx.custom_function`` over ``mlx3d_rasterize_backward``); the ids get zero gradients.
``rasterize_forward_surface`` is forward-only. ``project_ewa`` is differentiable with respect to means, quats and
scales. Inputs are checked as ``_core``'s ops check them
(``ValueError`` naming the input); the Python wrappers of mlx3d.render.raster_cpu cast them first.
"""

from __future__ import annotations

import ctypes
import functools

import mlx.core as mx
import numpy as np

from . import (_call, _contiguous, _f32, _f32p, _host, _i32p, _i64, _int, _numpy_in, _output, _ptr,
              _require, _reverse_mode_only, _threads, library, register)

register({
    "mlx3d_rasterize_forward": ([_f32p, _f32p, _f32p, _f32p, _i32p, _i32p, _i64, _int, _i64, _int, _int, _int, _f32p, _int,
                                 _f32p, _f32p, _i32p, _f32p], _int),
    "mlx3d_rasterize_forward_surface": ([_f32p, _f32p, _f32p, _f32p, _i32p, _i32p, _i64, _int, _i64, _int, _int, _int, _f32p,
                                         _f32p, _f32p, _f32p, _int, _f32p, _f32p, _i32p, _f32p], _int),
    "mlx3d_rasterize_backward": ([_f32p, _f32p, _f32p, _f32p, _i32p, _i32p, _i64, _int, _i64, _int, _int, _int, _i32p, _f32p,
                                  _f32p, _f32p, _f32p, _int, _f32p, _f32p, _f32p, _f32p], _int),
    "mlx3d_rasterizer_lanes": ([], _int),
})


def rasterizer_simd_lanes() -> int:
    """Pixels per SIMD step of the CPU rasterizer on this machine (8: AVX2, 4: SSE2/NEON, 1: scalar)."""
    return int(library().mlx3d_rasterizer_lanes())


def _check(ok: bool, message: str) -> None:
    _require(ok, "rasterize", message)


def _gaussians(means2d, conics, features, opacities, tile_offsets, flatten_ids, width: int, height: int, tile_size: int):
    """The six inputs as host arrays (checked as _core's op checks them) and the kernel's sizes (n, C, m)."""
    _check(width >= 1 and height >= 1, f"width and height must be >= 1, got {width} x {height}")
    _check(tile_size >= 1, f"tile_size must be >= 1, got {tile_size}")
    _check(means2d.ndim == 2 and means2d.shape[1] == 2, f"means2d must have shape (N, 2), got {tuple(means2d.shape)}")
    n = means2d.shape[0]
    _check(features.ndim == 2 and features.shape[0] == n and features.shape[1] >= 1,
           f"features must have shape (N, C) with N = {n} and C >= 1, got {tuple(features.shape)}")
    tiles = -(-width // tile_size) * -(-height // tile_size)
    arrays = (_host(means2d, "rasterize: means2d", (n, 2)), _host(conics, "rasterize: conics", (n, 3)),
              _host(features, "rasterize: features", (n, None)), _host(opacities, "rasterize: opacities", (n,)),
              _host(tile_offsets, "rasterize: tile_offsets", (tiles + 1,), mx.int32),
              _host(flatten_ids, "rasterize: flatten_ids", (None,), mx.int32))
    return arrays, (n, features.shape[1], arrays[5].size)


def _forward(name: str, inputs: tuple, extra: tuple, width: int, height: int, tile_size: int, threads: int):
    arrays, (n, c, m) = _gaussians(*inputs, width, height, tile_size)
    (accum, a), (alpha, al), (last, la), (final_t, ft) = (_output((height, width, c)), _output((height, width)),
                                                          _output((height, width), mx.int32), _output((height, width)))
    _call(name, *(_ptr(x) for x in arrays), n, c, m, width, height, tile_size, *extra, threads, _ptr(a), _ptr(al), _ptr(la),
          _ptr(ft))
    return [accum, alpha, last, final_t]


@functools.lru_cache(maxsize=None)
def _rasterizer(width: int, height: int, tile_size: int, threads: int, with_background: bool):
    """The differentiable forward pass for these sizes: f(means2d, conics, features, opacities, tile_offsets,
    flatten_ids[, background]) -> [accum, alpha, last, final_T]."""

    def background_of(rest):
        return _host(rest[0], "rasterize: background", (None,)) if with_background else None

    @mx.custom_function
    def rasterize(*inputs):
        bg = background_of(inputs[6:])
        return _forward("mlx3d_rasterize_forward", inputs[:6], (_ptr(bg),), width, height, tile_size, threads)

    @rasterize.vjp
    def rasterize_vjp(primals, cotangents, outputs):
        arrays, (n, c, m) = _gaussians(*primals[:6], width, height, tile_size)
        bg = background_of(primals[6:])
        d_accum = _host(cotangents[0].astype(mx.float32), "dL/daccum", (height, width, c))
        d_alpha = _host(cotangents[1].astype(mx.float32), "dL/dalpha", (height, width))
        last = _host(outputs[2], "last", (height, width), mx.int32)
        final_t = _host(outputs[3], "final_T", (height, width))
        grads = [_output(tuple(p.shape)) for p in primals[:4]]
        _call("mlx3d_rasterize_backward", *(_ptr(x) for x in arrays), n, c, m, width, height, tile_size, _ptr(last), _ptr(final_t),
              _ptr(d_accum), _ptr(d_alpha), _ptr(bg), threads, *(_ptr(view) for _, view in grads))
        result = [g for g, _ in grads] + [mx.zeros_like(primals[4]), mx.zeros_like(primals[5])]
        if with_background:  # the sum over pixels of dL/daccum (1 - alpha)
            result.append(mx.sum(cotangents[0] * (1.0 - outputs[1])[..., None], axis=(0, 1)))
        return tuple(result)

    return _reverse_mode_only(rasterize, "rasterize_forward")


def rasterize_forward(means2d, conics, features, opacities, tile_offsets, flatten_ids, width: int, height: int,
                      tile_size: int = 16, num_threads: int = 0, background=None) -> list:
    """3DGS tile rasterizer (``mlx3d._core.rasterize_forward``'s contract): float32 means2d (N,2), conics (N,3),
    features (N,C), opacities (N,); int32 tile_offsets (tiles+1,), flatten_ids (M,); background None or float32
    (C,), composited behind accum. Returns [accum (H,W,C), alpha (H,W), last (H,W) int32, final_T (H,W)]."""
    threads = _threads(num_threads)
    args = (means2d, conics, features, opacities, tile_offsets, flatten_ids)
    if background is not None:
        _check(background.ndim == 1 and background.shape[0] == features.shape[-1] and background.dtype == mx.float32,
               f"background must be float32 (C,) with C = {features.shape[-1]}, got {tuple(background.shape)}")
        args += (background,)
    return _rasterizer(int(width), int(height), int(tile_size), threads, background is not None)(*args)


def rasterize_forward_surface(means2d, conics, features, opacities, tile_offsets, flatten_ids, depths, surface_color,
                              surface_alpha, surface_depth, width: int, height: int, tile_size: int = 16,
                              num_threads: int = 0) -> list:
    """``rasterize_forward`` composited in depth order with a per-pixel surface layer, forward-only
    (``mlx3d._core.rasterize_forward_surface``'s contract): float32 depths (N,), surface_color (H,W,C) premultiplied,
    surface_alpha (H,W), surface_depth (H,W)."""
    width, height, tile_size, threads = int(width), int(height), int(tile_size), _threads(num_threads)
    n, c = means2d.shape[0], features.shape[-1]
    hw = f"({height}, {width}"
    for a, name, shape in ((depths, "depths", (n,)), (surface_color, f"surface_color (H, W, C) = {hw}, {c})", (height, width, c)),
                           (surface_alpha, f"surface_alpha (H, W) = {hw})", (height, width)),
                           (surface_depth, f"surface_depth (H, W) = {hw})", (height, width))):
        _host(a, "rasterize: " + name, shape)  # checked here, read in the custom function
    surface = (depths, surface_color, surface_alpha, surface_depth)
    return _surface_rasterizer(width, height, tile_size, threads)(means2d, conics, features, opacities, tile_offsets, flatten_ids,
                                                                 *surface)


@functools.lru_cache(maxsize=None)
def _surface_rasterizer(width: int, height: int, tile_size: int, threads: int):
    """The surface variant for these sizes, whose gradients raise (as _core's)."""

    @mx.custom_function
    def rasterize(*inputs):
        surface = tuple(_host(a, "rasterize: a surface input", tuple(a.shape)) for a in inputs[6:])
        return _forward("mlx3d_rasterize_forward_surface", inputs[:6], tuple(_ptr(a) for a in surface), width, height, tile_size,
                        threads)

    @rasterize.vjp
    def rasterize_vjp(primals, cotangents, outputs):
        raise RuntimeError("rasterize_forward_surface: compositing over a surface is forward-only (no gradients); render "
                           "without `surface` to differentiate.")

    return _reverse_mode_only(rasterize, "rasterize_forward_surface")


# ------------------------------------------------------------------ EWA projection
register({
    "mlx3d_project_ewa": ([_f32p, _f32p, _f32p, _i64, _f32p, _f32, _f32, _f32, _f32, _int, _int, _f32, _f32, _f32, _int, _int,
                           _f32p, _f32p, _i32p, _f32p, _f32p], _int),
    "mlx3d_project_ewa_backward": ([_f32p, _f32p, _f32p, _i64, _f32p, _f32, _f32, _f32, _f32, _int, _int, _f32, _f32, _f32, _int,
                                    _f32p, _f32p, _f32p, _f32p, _int, _f32p, _f32p, _f32p], _int),
})


@functools.lru_cache(maxsize=64)
def _projector(camera: tuple, threads: int):
    """The differentiable projection for one camera: f(means, quats, scales) -> [means2d, conics, radii, depths,
    compensation]. ``camera``: (viewmat (16 floats), fx, fy, cx, cy, width, height, near, far, blur, antialias)."""
    viewmat = np.array(camera[0], np.float32)
    scalars = camera[1:]

    def inputs(means, quats, scales):
        n = means.shape[0]
        return (_host(means, "project_ewa: means", (n, 3)), _host(quats, "project_ewa: quats", (n, 4)),
                _host(scales, "project_ewa: scales", (n, 3)))

    @mx.custom_function
    def project(means, quats, scales):
        m, q, s = inputs(means, quats, scales)
        n = m.shape[0]
        outs = [_output((n, 2)), _output((n, 3)), _output((n,), mx.int32), _output((n,)), _output((n,))]
        _call("mlx3d_project_ewa", _ptr(m), _ptr(q), _ptr(s), n, _ptr(viewmat), *scalars, threads, *(_ptr(v) for _, v in outs))
        return [a for a, _ in outs]

    @project.vjp
    def project_vjp(primals, cotangents, outputs):
        m, q, s = inputs(*primals)
        n = m.shape[0]
        cot = [_host(c.astype(mx.float32), name, shape) for c, name, shape in
               zip((cotangents[0], cotangents[1], cotangents[3], cotangents[4]),
                   ("dL/dmeans2d", "dL/dconics", "dL/ddepths", "dL/dcompensation"), ((n, 2), (n, 3), (n,), (n,)))]
        grads = [_output((n, 3)), _output((n, 4)), _output((n, 3))]
        _call("mlx3d_project_ewa_backward", _ptr(m), _ptr(q), _ptr(s), n, _ptr(viewmat), *scalars, *(_ptr(c) for c in cot),
              threads, *(_ptr(v) for _, v in grads))
        return tuple(g for g, _ in grads)

    return _reverse_mode_only(project, "project_ewa")


def project_ewa(means, quats, scales, viewmat, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                near: float, far: float, blur: float = 0.3, antialias: bool = False, num_threads: int = 0) -> list:
    """EWA projection (``mlx3d._core.project_ewa``'s contract; differentiable w.r.t. means, quats, scales): float32
    means (N,3), quats (N,4), scales (N,3); viewmat 16 floats (4x4 row-major). Returns [means2d (N,2), conics
    (N,3), radii (N,) int32, depths (N,), compensation (N,)]."""
    _require(means.ndim == 2 and means.shape[1] == 3, "project_ewa", f"means must have shape (N, 3), got {tuple(means.shape)}")
    viewmat = tuple(float(v) for v in np.asarray(viewmat, np.float64).reshape(-1))
    _require(len(viewmat) == 16, "project_ewa", "viewmat must have 16 entries (4x4 row-major)")
    _require(int(width) >= 1 and int(height) >= 1, "project_ewa", "width and height must be >= 1")
    camera = (viewmat, float(fx), float(fy), float(cx), float(cy), int(width), int(height), float(near), float(far), float(blur),
              int(bool(antialias)))
    return _projector(camera, _threads(num_threads))(means, quats, scales)


# ------------------------------------------------------------------ tile binning
register({
    "mlx3d_bin_tiles": ([_f32p, _f32p, _f32p, _i64, _int, _int, _int, _f32p, _f32p, _int, _i32p, ctypes.POINTER(_i32p),
                         ctypes.POINTER(_i64)], _int),
    "mlx3d_tile_extents": ([_f32p, _f32p, _f32p, _i64, _f32p], _int),
    "mlx3d_free": ([ctypes.c_void_p], None),
})


def _extent_inputs(radii, conics, opacities, n: int) -> tuple:
    """radii (N,) and, together or not at all, conics (N, 3) and opacities (N,), as float32 host arrays."""
    if (conics is None) != (opacities is None):
        raise ValueError("bin_tiles: give conics and opacities together, or neither")
    r = _numpy_in(radii, np.float32, "bin_tiles: radii (one entry per Gaussian)", n)
    if conics is None:
        return r, None, None
    return (r, _numpy_in(conics, np.float32, "bin_tiles: conics (one row of 3 per Gaussian)", 3 * n),
            _numpy_in(opacities, np.float32, "bin_tiles: opacities (one per Gaussian)", n))


def tile_extents(radii, conics=None, opacities=None) -> np.ndarray:
    """(N, 2) float32 half-extents in pixels that bin_tiles gives each Gaussian (``mlx3d._core.tile_extents``)."""
    r = _contiguous(radii, np.float32).reshape(-1)
    r, c, o = _extent_inputs(r, conics, opacities, r.size)
    out = np.empty((r.size, 2), np.float32)
    _call("mlx3d_tile_extents", _ptr(r), _ptr(c), _ptr(o), r.size, _ptr(out))
    return out


def bin_tiles(means2d, radii, depths, width: int, height: int, tile_size: int = 16, num_threads: int = 0, conics=None,
              opacities=None) -> tuple:
    """Tile intersections (``mlx3d._core.bin_tiles``'s contract): float32 means2d (N, 2), radii (N,) (0 = culled), depths
    (N,), optionally conics (N, 3) and opacities (N,). Returns MLX int32 (tile_offsets (tiles + 1,), flatten_ids
    (M,)) sorted by tile, depth, index."""
    means = _contiguous(means2d, np.float32)
    if means.ndim != 2 or means.shape[1] != 2:
        raise ValueError(f"bin_tiles: means2d must have shape (N, 2), got {means.shape}")
    n = means.shape[0]
    d = _numpy_in(depths, np.float32, "bin_tiles: depths (one per Gaussian)", n)
    r, c, o = _extent_inputs(radii, conics, opacities, n)
    width, height, tile_size = int(width), int(height), int(tile_size)
    if width < 1 or height < 1 or tile_size < 1:
        raise ValueError("bin_tiles: width, height and tile_size must be >= 1")
    offsets = np.empty(-(-width // tile_size) * -(-height // tile_size) + 1, np.int32)
    ids, m = _i32p(), _i64()
    lib = library()
    rc = lib.mlx3d_bin_tiles(_ptr(means), _ptr(r), _ptr(d), n, width, height, tile_size, _ptr(c), _ptr(o), _threads(num_threads),
                             _ptr(offsets), ctypes.byref(ids), ctypes.byref(m))
    if rc != 0:  # as _core: more entries than int32 indices reach is an OverflowError
        message = lib.mlx3d_last_error().decode()
        raise (ValueError if rc == 2 else OverflowError if "2^31" in message else RuntimeError)(message)
    try:
        entries = mx.array(np.ctypeslib.as_array(ids, (m.value,))) if m.value else mx.array(np.zeros(0, np.int32))
        mx.eval(entries)  # a copy: the block is the library's
    finally:
        lib.mlx3d_free(ids)
    return mx.array(offsets), entries
