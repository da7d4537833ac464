"""Access to the compiled extension ``mlx3d._core``.

This is the only module that imports ``mlx3d._core``; everything else calls
:func:`core`. The import happens on first use (so pure-Python parts of mlx3d
work without the extension) and raises :class:`~mlx3d.errors.ExtensionBuildError`
with build instructions when the extension is missing or cannot be loaded.
"""

from __future__ import annotations

import threading
from types import ModuleType

from mlx3d.errors import ExtensionBuildError

__all__ = ["core", "available", "host_array", "BUILD_HINT"]

BUILD_HINT = (
    "Build it from the repository root: install the build requirements "
    "(Linux: pip install \"mlx[cpu]==0.32.4\" nanobind==3.1.0 scikit-build-core; "
    "macOS: pip install mlx==0.32.4 nanobind==3.1.0 scikit-build-core), then run "
    "`pip install --no-build-isolation -e .` (or the README's make target). "
    "A C++20 compiler (required by the MLX headers) and CMake >= 3.24 are needed."
)

_lock = threading.Lock()
_core: ModuleType | None = None


def core() -> ModuleType:
    """Returns the compiled module ``mlx3d._core``, importing it on first call.

    Raises:
        ExtensionBuildError: the extension is not built, was built against a
            different Python / MLX, or its shared libraries cannot be loaded.
            The message includes the original import error.
    """
    global _core
    if _core is not None:
        return _core
    with _lock:
        if _core is not None:
            return _core
        try:
            # Load libmlx (and register mx.array with nanobind) before _core,
            # which links against it.
            import mlx.core  # noqa: F401
        except ImportError as exc:
            raise ExtensionBuildError(
                "mlx3d needs MLX 0.32.4, which failed to import "
                f"({type(exc).__name__}: {exc}). Install it with "
                "`pip install \"mlx[cpu]==0.32.4\"` (Linux) or "
                "`pip install mlx==0.32.4` (macOS)."
            ) from exc
        try:
            from mlx3d import _core as module
        except ImportError as exc:
            raise ExtensionBuildError(
                "The compiled extension mlx3d._core is missing or broken "
                f"({type(exc).__name__}: {exc}). {BUILD_HINT}"
            ) from exc
        _core = module
        return module


def available() -> bool:
    """True when :func:`core` succeeds (never raises)."""
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
