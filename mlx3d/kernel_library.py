"""The CPU kernels as a C library (``mlx3d/csrc/kernels``, header ``mlx3d_kernels.h``), called through ctypes.

The library does not link MLX or Python, so one build per platform serves every
Python and MLX version: ``libmlx3d_kernels.so`` (Linux x86-64 and arm64),
``mlx3d_kernels.dll`` (Windows x64), ``libmlx3d_kernels.dylib`` (macOS arm64),
found in ``mlx3d/_kernels/`` (where ``make kernels`` and the extension zips put
it) or at the path in ``MLX3D_KERNELS``. It is loaded on first use; when it is
missing, was built for another ABI version or fails to load, :func:`available`
is False and the reason is logged once (``mlx3d`` logger) and kept in
:func:`failure`.

Each function here takes and returns MLX arrays, with the signature and
meaning of the ``mlx3d._core`` function of the same name: inputs are checked
(shape, dtype float32), evaluated and read in place when they are row-contiguous
(copied once otherwise); outputs are MLX arrays the kernel writes into (no
copy). Gradients: ``mx.custom_function`` with the kernel's backward pass, so
``mx.grad`` and ``mx.value_and_grad`` work as with ``_core``; not inside
``mx.compile`` or ``mx.vmap``.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import sys
import threading
from pathlib import Path

import mlx.core as mx
import numpy as np

__all__ = ["available", "failure", "library", "library_path", "build_info", "sh_colors", "add_screen_statistics", "KDTree",
           "ABI", "PATH_ENV"]

#: mlx3d_kernels.h's MLX3D_KERNELS_ABI this module is written for.
ABI = 1
#: Environment variable: the library file to load instead of mlx3d/_kernels/'s.
PATH_ENV = "MLX3D_KERNELS"
LIBRARY_NAMES = {"win32": "mlx3d_kernels.dll", "darwin": "libmlx3d_kernels.dylib"}

_log = logging.getLogger("mlx3d")
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_failure: str | None = None

_f32p = ctypes.POINTER(ctypes.c_float)
_f64p = ctypes.POINTER(ctypes.c_double)
_i32p = ctypes.POINTER(ctypes.c_int32)
_u8p = ctypes.POINTER(ctypes.c_uint8)
_i64 = ctypes.c_int64
_int = ctypes.c_int
_f64 = ctypes.c_double
_SIGNATURES = {
    "mlx3d_kernels_abi": ([], _int),
    "mlx3d_kernels_build": ([], ctypes.c_char_p),
    "mlx3d_last_error": ([], ctypes.c_char_p),
    "mlx3d_sh_forward": ([_f32p, _i64, _f32p, _i64, _f32p, _f32p, _i64, _int, _int, _f32p], _int),
    "mlx3d_sh_backward": ([_f32p, _i64, _f32p, _i64, _f32p, _f32p, _i64, _int, _f32p, _int, _f32p, _f32p, _f32p], _int),
    "mlx3d_add_screen_statistics": ([_u8p, _f32p, _i32p, _i64, _f64, _f64, _f64p, _f64p, _f64p, _int], _int),
    "mlx3d_knn_build": ([_f32p, _i64, _int, ctypes.POINTER(ctypes.c_void_p)], _int),
    "mlx3d_knn_free": ([ctypes.c_void_p], _int),
    "mlx3d_knn_info": ([ctypes.c_void_p, ctypes.POINTER(_i64), ctypes.POINTER(_int), ctypes.POINTER(_int), ctypes.POINTER(_i64)], _int),
    "mlx3d_knn_order": ([ctypes.c_void_p, ctypes.POINTER(_i64)], _int),
    "mlx3d_knn_query": ([ctypes.c_void_p, _f32p, _i64, _int, ctypes.POINTER(_i64), _int, _int, ctypes.POINTER(_i64), _f32p], _int),
}


def library_path() -> Path:
    """The file :func:`library` loads: ``MLX3D_KERNELS`` when set, else this platform's name in mlx3d/_kernels/."""
    if os.environ.get(PATH_ENV):
        return Path(os.environ[PATH_ENV])
    return Path(__file__).resolve().parent / "_kernels" / LIBRARY_NAMES.get(sys.platform, "libmlx3d_kernels.so")


def _load() -> ctypes.CDLL:
    path = library_path()
    if not path.is_file():
        raise OSError(f"{path} does not exist (build it with `make kernels`)")
    lib = ctypes.CDLL(str(path))
    for name, (args, result) in _SIGNATURES.items():
        try:
            fn = getattr(lib, name)
        except AttributeError:
            raise OSError(f"{path} has no function {name}: a library of another version") from None
        fn.argtypes, fn.restype = args, result
    if lib.mlx3d_kernels_abi() != ABI:
        raise OSError(f"{path} is built for kernel ABI {lib.mlx3d_kernels_abi()}, this mlx3d needs {ABI}")
    return lib


def library() -> ctypes.CDLL:
    """The loaded library; raises ``OSError`` (the reason) when it cannot be loaded."""
    global _lib, _failure
    if _lib is not None:
        return _lib
    with _lock:
        if _lib is None:
            if _failure is not None:
                raise OSError(_failure)
            try:
                _lib = _load()
            except OSError as exc:
                _failure = f"the mlx3d kernel library cannot be loaded: {exc}"
                _log.info("%s; the pure MLX path runs instead", _failure)
                raise OSError(_failure) from exc
    return _lib


def available() -> bool:
    """True when :func:`library` loads (never raises)."""
    try:
        library()
    except OSError:
        return False
    return True


def failure() -> str | None:
    """Why the library could not be loaded, or None (loaded, or not tried yet)."""
    return _failure


def build_info() -> str:
    """What the loaded library was built for and with (``mlx3d_kernels_build``)."""
    return library().mlx3d_kernels_build().decode()


# ------------------------------------------------------------------ arrays across the boundary
def _contiguous(a, dtype) -> np.ndarray:
    """``a`` (numpy or MLX) as a C-contiguous ``dtype`` array (read in place when it is one)."""
    return np.ascontiguousarray(np.asarray(mx.stop_gradient(a) if isinstance(a, mx.array) else a), dtype=dtype)


def _host(a: mx.array, name: str, shape: tuple) -> np.ndarray:
    """``a`` evaluated as a C-contiguous float32 numpy array (its own memory when it is one already), checked
    against ``shape`` (None: any size on that axis)."""
    if a.dtype != mx.float32:
        raise TypeError(f"{name} must be float32, got {a.dtype}")
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(a.shape)}")
    return _contiguous(a, np.float32)


def _output(shape: tuple) -> tuple[mx.array, np.ndarray]:
    """A fresh float32 MLX array of ``shape`` and a writable numpy view of its memory, for a kernel to fill."""
    out = mx.zeros(shape, dtype=mx.float32)
    mx.eval(out)
    view = np.asarray(out)
    assert view.flags.c_contiguous and view.flags.writeable
    return out, view


_POINTERS = {np.dtype(np.float32): _f32p, np.dtype(np.float64): _f64p, np.dtype(np.int32): _i32p, np.dtype(np.bool_): _u8p,
             np.dtype(np.int64): ctypes.POINTER(_i64)}


def _ptr(a: np.ndarray | None):
    return None if a is None or a.size == 0 else a.ctypes.data_as(_POINTERS[a.dtype])


def _call(name: str, *args) -> None:
    lib = library()
    if getattr(lib, name)(*args) != 0:
        raise RuntimeError(lib.mlx3d_last_error().decode())


# ------------------------------------------------------------------ spherical harmonics
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

    return colours


def sh_colors(sh: list, means: mx.array, centre: mx.array, degree: int, num_threads: int = 0) -> mx.array:
    """max(colour, 0) (N, 3) of float32 SH coefficients seen from ``centre`` (3,) at ``means`` (N, 3), up to
    ``degree`` (0..3); ``sh``: [(N, K, 3)] or two blocks [(N, K0, 3), (N, K1, 3)] read as their concatenation.
    Differentiable with respect to the blocks and the means (``mlx3d._core.sh_colors``'s contract)."""
    if len(sh) not in (1, 2):
        raise ValueError(f"sh must be one (N, K, 3) array or two blocks, got {len(sh)} arrays")
    block0 = sh[0]
    block1 = sh[1] if len(sh) == 2 else mx.zeros((block0.shape[0], 0, 3), dtype=mx.float32)
    if int(num_threads) < 0:
        raise ValueError(f"num_threads must be >= 0 (0 = all cores), got {num_threads}")
    return _sh_function(int(degree), int(num_threads))(block0, block1, means, centre)


# ------------------------------------------------------------------ densification statistics
def _numpy_in(a, dtype, name: str, size: int) -> np.ndarray:
    """``_contiguous(a, dtype)``, which must hold ``size`` elements."""
    a = _contiguous(a, dtype)
    if a.size != size:
        raise ValueError(f"{name} must hold {size} elements, got {a.size}")
    return a


def add_screen_statistics(visible, grad2d, radii, sx: float, sy: float, grad_accum: np.ndarray, grad_count: np.ndarray,
                          max_radii: np.ndarray, num_threads: int = 0) -> None:
    """Adds one view to the float64 (N,) densification statistics in place: grad_accum += |grad2d * (sx, sy)| where
    visible (bool (N,)), grad_count += visible, max_radii = max(max_radii, radii (int32 (N,))); grad2d float32 (N, 2)
    (``mlx3d._core.add_screen_statistics``'s contract)."""
    stats = (grad_accum, grad_count, max_radii)
    n = grad_accum.shape[0] if isinstance(grad_accum, np.ndarray) else -1
    for name, a in zip(("grad_accum", "grad_count", "max_radii"), stats):
        if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (n,) and a.flags.c_contiguous and a.flags.writeable):
            raise ValueError(f"{name} must be a writable C-contiguous float64 (N,) numpy array, as the other statistics")
    if int(num_threads) < 0:
        raise ValueError(f"num_threads must be >= 0 (0 = all cores), got {num_threads}")
    vis, g, r = (_numpy_in(visible, np.bool_, "visible", n), _numpy_in(grad2d, np.float32, "grad2d", 2 * n),
                 _numpy_in(radii, np.int32, "radii", n))
    _call("mlx3d_add_screen_statistics", _ptr(vis), _ptr(g), _ptr(r), n, float(sx), float(sy), *(_ptr(a) for a in stats),
          int(num_threads))


# ------------------------------------------------------------------ k nearest neighbours
class KDTree:
    """k-d tree over C-contiguous float32 (N, 3) points (median split on the widest axis): ``mlx3d._core.KDTree``'s
    methods and results, on the library's tree (freed with this object). Low-level; use mlx3d.neighbors."""

    _OUTPUTS = {"neighbours": 0, "mean": 1, "kth": 2}

    def __init__(self, points: np.ndarray, leaf_size: int = 16):
        points = _contiguous(points, np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        self._lib, self._tree = library(), ctypes.c_void_p()
        _call("mlx3d_knn_build", _ptr(points), points.shape[0], int(leaf_size), ctypes.byref(self._tree))
        size, leaf, depth, nodes = _i64(), _int(), _int(), _i64()
        _call("mlx3d_knn_info", self._tree, ctypes.byref(size), ctypes.byref(leaf), ctypes.byref(depth), ctypes.byref(nodes))
        self.size, self.leaf_size, self.depth, self.node_count = size.value, leaf.value, depth.value, nodes.value

    def __del__(self):
        tree = getattr(self, "_tree", None)
        if tree:
            self._lib.mlx3d_knn_free(tree)

    def order(self) -> np.ndarray:
        """Original point indices in tree order (spatially coherent), int64 (N,)."""
        out = np.empty(self.size, np.int64)
        _call("mlx3d_knn_order", self._tree, _ptr(out))
        return out

    def _query(self, queries, k: int, self_index, num_threads: int, output: str):
        q = _contiguous(queries, np.float32).reshape(-1, 3)
        m = q.shape[0]
        own = None if self_index is None else _numpy_in(self_index, np.int64, "self_index", m)
        if int(num_threads) < 0:
            raise ValueError(f"num_threads must be >= 0 (0 = all), got {num_threads}")
        index = np.empty((m, max(int(k), 0)), np.int64) if output == "neighbours" else None
        dist = np.empty((m, max(int(k), 0)) if output == "neighbours" else (m,), np.float32)
        _call("mlx3d_knn_query", self._tree, _ptr(q), m, int(k), _ptr(own), self._OUTPUTS[output], int(num_threads), _ptr(index),
              _ptr(dist))
        return index, dist

    def query(self, queries, k: int, self_index=None, num_threads: int = 0):
        """(indices int64 (M, k), squared distances float32 (M, k)) of each query's k nearest points, sorted by
        distance (ties by index); ``self_index`` (int64 (M,), -1 = none) names each query's own point, skipped."""
        return self._query(queries, k, self_index, num_threads, "neighbours")

    def query_mean(self, queries, k: int, self_index=None, num_threads: int = 0) -> np.ndarray:
        """Mean Euclidean distance to the k nearest points, float32 (M,)."""
        return self._query(queries, k, self_index, num_threads, "mean")[1]

    def query_kth(self, queries, k: int, self_index=None, num_threads: int = 0) -> np.ndarray:
        """Euclidean distance to the k-th nearest point, float32 (M,)."""
        return self._query(queries, k, self_index, num_threads, "kth")[1]
