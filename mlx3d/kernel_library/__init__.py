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

This module loads the library and carries what every wrapper shares (the
argument checks, pointers, the call and its error); each area of kernels has its
module beside it (``sh``, ``statistics``, ``knn``, ...), which declares the C
signatures it calls with :func:`register`. Their functions are re-exported here.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading
from pathlib import Path

import mlx.core as mx
import numpy as np

__all__ = ["available", "failure", "library", "library_path", "build_info", "register", "ABI", "PATH_ENV"]

#: mlx3d_kernels.h's MLX3D_KERNELS_ABI this module is written for.
ABI = 2
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
_i64p = ctypes.POINTER(ctypes.c_int64)
_u8p = ctypes.POINTER(ctypes.c_uint8)
_i64 = ctypes.c_int64
_int = ctypes.c_int
_f32 = ctypes.c_float
_f64 = ctypes.c_double
#: C signatures, {name: ([argument types], result type)}: the library's own, and each area module's (register).
_SIGNATURES = {
    "mlx3d_kernels_abi": ([], _int),
    "mlx3d_kernels_build": ([], ctypes.c_char_p),
    "mlx3d_last_error": ([], ctypes.c_char_p),
}


def register(signatures: dict) -> None:
    """Declare the C signatures an area module calls ({name: ([argument ctypes], result ctype)}); at import,
    before the library loads, which checks that it has every one."""
    if _lib is not None:
        raise RuntimeError("kernel signatures must be registered before the library is loaded")
    _SIGNATURES.update(signatures)


def library_path() -> Path:
    """The file :func:`library` loads: ``MLX3D_KERNELS`` when set, else this platform's name in mlx3d/_kernels/."""
    if os.environ.get(PATH_ENV):
        return Path(os.environ[PATH_ENV])
    return Path(__file__).resolve().parent.parent / "_kernels" / LIBRARY_NAMES.get(sys.platform, "libmlx3d_kernels.so")


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


def _host(a: mx.array, name: str, shape: tuple, dtype=mx.float32) -> np.ndarray:
    """``a`` evaluated as a C-contiguous numpy array of ``dtype`` (its own memory when it is one already), checked
    against ``shape`` (None: any size on that axis)."""
    if a.dtype != dtype:
        raise TypeError(f"{name} must be {str(dtype).rsplit('.', 1)[-1]}, got {a.dtype}")
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(a.shape)}")
    return _contiguous(a, _NUMPY[dtype])


_NUMPY = {mx.float32: np.float32, mx.int32: np.int32}


def _output(shape: tuple, dtype=mx.float32) -> tuple[mx.array, np.ndarray]:
    """A fresh MLX array of ``shape`` and ``dtype`` and a writable numpy view of its memory, for a kernel to fill."""
    out = mx.zeros(shape, dtype=dtype)
    mx.eval(out)
    view = np.asarray(out)
    assert view.flags.c_contiguous and view.flags.writeable
    return out, view


_POINTERS = {np.dtype(np.float32): _f32p, np.dtype(np.float64): _f64p, np.dtype(np.int32): _i32p, np.dtype(np.bool_): _u8p,
             np.dtype(np.uint8): _u8p, np.dtype(np.int64): _i64p}


def _ptr(a: np.ndarray | None):
    return None if a is None or a.size == 0 else a.ctypes.data_as(_POINTERS[a.dtype])


def _call(name: str, *args) -> None:
    """Call the library's function ``name``; its failure as ValueError (an invalid argument) or RuntimeError."""
    lib = library()
    rc = getattr(lib, name)(*args)
    if rc != 0:
        raise (ValueError if rc == 2 else RuntimeError)(lib.mlx3d_last_error().decode())


def _reverse_mode_only(fn, name: str):
    """Give ``fn`` (an ``mx.custom_function``) a jvp and a vmap that raise, naming ``name``, as _core's primitives do:
    MLX would otherwise trace the forward function, whose kernel call it cannot see, and give zero tangents."""
    def jvp(primals, tangents):
        raise RuntimeError(f"{name}: forward-mode differentiation (jvp) is not implemented; use mx.grad / mx.vjp.")

    def vmap(inputs, axes):
        raise RuntimeError(f"{name}: vmap is not implemented.")

    fn.jvp(jvp)
    fn.vmap(vmap)
    return fn


def _numpy_in(a, dtype, name: str, size: int) -> np.ndarray:
    """``_contiguous(a, dtype)``, which must hold ``size`` elements."""
    a = _contiguous(a, dtype)
    if a.size != size:
        raise ValueError(f"{name} must hold {size} elements, got {a.size}")
    return a


def _numpy_out(a, name: str, dtype, shape: tuple) -> np.ndarray:
    """``a``, a numpy array a kernel writes in place, checked: writable, C-contiguous, of ``dtype`` and ``shape``."""
    if not (isinstance(a, np.ndarray) and a.dtype == dtype and a.shape == shape and a.flags.c_contiguous and a.flags.writeable):
        got = (f"{a.dtype} {a.shape}{'' if a.flags.c_contiguous else ', strided'}{'' if a.flags.writeable else ', read-only'}"
               if isinstance(a, np.ndarray) else type(a).__name__)
        raise ValueError(f"{name} must be a writable C-contiguous {np.dtype(dtype).name} {shape} numpy array, got {got}")
    return a


def _require(ok: bool, op: str, message: str) -> None:
    """A ValueError ``op: message`` unless ``ok`` (the wording of _core's op checks)."""
    if not ok:
        raise ValueError(f"{op}: {message}")


def _threads(num_threads) -> int:
    """``num_threads`` checked: >= 0 (0 = every core)."""
    if int(num_threads) < 0:
        raise ValueError(f"num_threads must be >= 0 (0 = all cores), got {num_threads}")
    return int(num_threads)


# The areas (each registers its signatures at import). Keep sorted.
from .affine import affine_covariances  # noqa: E402
from .knn import KDTree  # noqa: E402
from .optim import activation, adam_step, all_finite  # noqa: E402
from .photometric import mse, photometric_loss  # noqa: E402
from .render import (bin_tiles, project_ewa, rasterize_forward, rasterize_forward_surface, rasterizer_simd_lanes,  # noqa: E402
                     tile_extents)
from .sh import sh_colors  # noqa: E402
from .statistics import add_screen_statistics  # noqa: E402

__all__ += ["KDTree", "sh_colors", "add_screen_statistics", "mse", "photometric_loss", "adam_step", "all_finite", "activation",
            "affine_covariances", "rasterize_forward", "rasterize_forward_surface", "rasterizer_simd_lanes",
            "project_ewa", "bin_tiles", "tile_extents"]
