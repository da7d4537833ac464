"""Access to the compiled CPU kernels: the extension ``mlx3d._core``, or the kernel library in its place.

This is the only module that imports ``mlx3d._core``; everything else calls
:func:`core`, which returns the module whose functions the CPU backend calls
(:data:`CPU_FUNCTIONS`). That is ``_core`` (MLX primitives over the kernel
library, built for Linux x86-64) where it imports, and otherwise the kernel
library itself through ctypes (:mod:`mlx3d.kernel_library`, which offers every
one of those functions under the same name, signature and meaning: Windows,
Linux arm64, macOS' CPU path). The import happens on first use (so pure-Python
parts of mlx3d work without either) and raises
:class:`~mlx3d.errors.ExtensionBuildError` with both reasons when neither loads.

The kernels are an accelerator: every public operation also runs without them
(backend 'mlx', chosen by ``resolve_backend('auto')`` when :func:`available`
is False). Environment:

- ``MLX3D_NO_CORE=1`` makes :func:`core` fail as if no kernels were there,
  which forces the pure MLX path (the test suite's ``make test-pure`` entry);
- ``MLX3D_CPU_KERNELS=library`` skips ``_core`` and uses the kernel library
  (as on the platforms without ``_core``; ``make test-library`` runs the
  suite so); ``auto`` (the default) prefers ``_core``.
"""

from __future__ import annotations

import os
import threading
from types import ModuleType

from mlx3d.errors import ExtensionBuildError

__all__ = ["core", "available", "host_array", "BUILD_HINT", "DISABLE_ENV", "KERNELS_ENV", "CPU_FUNCTIONS"]

DISABLE_ENV = "MLX3D_NO_CORE"
KERNELS_ENV = "MLX3D_CPU_KERNELS"
#: What the CPU backend calls on :func:`core`'s module (each in mlx3d._core and in mlx3d.kernel_library).
CPU_FUNCTIONS = ("project_ewa", "bin_tiles", "tile_extents", "rasterize_forward", "rasterize_forward_surface",
                 "rasterizer_simd_lanes", "sh_colors", "activation", "mse", "photometric_loss", "adam_step", "all_finite",
                 "add_screen_statistics", "affine_covariances", "KDTree")

BUILD_HINT = (
    "Build it from the repository root: install the build requirements "
    "(Linux: pip install \"mlx[cpu]==0.32.4\" nanobind==3.1.0 scikit-build-core; "
    "macOS: pip install mlx==0.32.4 nanobind==3.1.0 scikit-build-core), then run "
    "`pip install --no-build-isolation -e .` (or `make install`). "
    "A C++20 compiler (required by the MLX headers) and CMake >= 3.24 are needed."
)

_lock = threading.Lock()
_core: ModuleType | None = None
_failure: ExtensionBuildError | None = None  # the first failed import, raised again without retrying


def disabled() -> bool:
    """True when ``MLX3D_NO_CORE`` is set to anything but '' or '0'."""
    return os.environ.get(DISABLE_ENV, "").strip() not in ("", "0")


def core() -> ModuleType:
    """Returns the module of the compiled CPU kernels: ``mlx3d._core``, or else :mod:`mlx3d.kernel_library`
    (see the module doc), loading it on first call.

    Raises:
        ExtensionBuildError: neither loads (``_core`` is not built, was built against a different Python / MLX,
            or its shared libraries cannot be loaded; the library is missing or of another version). The message
            includes both reasons. Also raised while ``MLX3D_NO_CORE`` is set.
    """
    global _core, _failure
    if disabled():
        raise ExtensionBuildError(f"the compiled CPU kernels (mlx3d._core and the kernel library) are turned off by "
                                  f"{DISABLE_ENV}={os.environ[DISABLE_ENV]!r}; unset it to use them")
    if _core is not None:
        return _core
    with _lock:
        if _core is not None:
            return _core
        if _failure is not None:
            raise ExtensionBuildError(str(_failure)) from _failure.__cause__
        try:
            # Load libmlx (and register mx.array with nanobind) before _core,
            # which links against it.
            import mlx.core  # noqa: F401
        except ImportError as exc:
            _failure = ExtensionBuildError(
                "mlx3d needs MLX 0.32.4, which failed to import "
                f"({type(exc).__name__}: {exc}). Install it with "
                "`pip install \"mlx[cpu]==0.32.4\"` (Linux) or "
                "`pip install mlx==0.32.4` (macOS)."
            )
            raise _failure from exc
        choice = os.environ.get(KERNELS_ENV, "auto").strip() or "auto"
        if choice not in ("auto", "library"):
            raise ExtensionBuildError(f"{KERNELS_ENV} must be 'auto' or 'library', got {choice!r}")
        reason = f"mlx3d._core is skipped ({KERNELS_ENV}=library)"
        if choice == "auto":
            try:
                from mlx3d import _core as module
            except ImportError as exc:
                reason = f"mlx3d._core is missing or broken ({type(exc).__name__}: {exc})"
            else:
                _core = module
                return module
        from mlx3d import kernel_library

        if kernel_library.available() and all(hasattr(kernel_library, name) for name in CPU_FUNCTIONS):
            _core = kernel_library
            return kernel_library
        _failure = ExtensionBuildError(
            f"No compiled CPU kernels: {reason}, and {kernel_library.failure() or 'the kernel library lacks functions'}. "
            f"{BUILD_HINT} (or `make kernels` for the kernel library alone)"
        )
        raise _failure


def available() -> bool:
    """True when :func:`core` succeeds: compiled CPU kernels are there (never raises; False while ``MLX3D_NO_CORE``
    is set)."""
    try:
        core()
    except ExtensionBuildError:
        return False
    return True


def host_array(a, dtype):
    """``a`` as a C-contiguous numpy array of ``dtype``, for the native functions that take numpy arrays.

    An MLX array is evaluated (outside any gradient) and its own memory used when it already has that
    dtype and layout; anything else is converted (a copy).
    """
    import mlx.core as mx
    import numpy as np

    return np.ascontiguousarray(np.asarray(mx.stop_gradient(a) if isinstance(a, mx.array) else a), dtype=dtype)
