"""Access to the compiled extension ``mlx3d._core``.

This is the only module that imports ``mlx3d._core``; everything else calls
:func:`core`. The import happens on first use (so pure-Python parts of mlx3d
work without the extension) and raises :class:`~mlx3d.errors.ExtensionBuildError`
with build instructions when the extension is missing or cannot be loaded.

``_core`` is an accelerator: every public operation also runs without it
(backend 'mlx', chosen by ``resolve_backend('auto')`` when :func:`available`
is False). Setting the environment variable ``MLX3D_NO_CORE=1`` makes
:func:`core` fail as if the extension were missing, which forces that path
(the test suite's ``make test-pure`` entry runs under it).
"""

from __future__ import annotations

import os
import threading
from types import ModuleType

from mlx3d.errors import ExtensionBuildError

__all__ = ["core", "available", "host_array", "BUILD_HINT", "DISABLE_ENV"]

DISABLE_ENV = "MLX3D_NO_CORE"

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
    """Returns the compiled module ``mlx3d._core``, importing it on first call.

    Raises:
        ExtensionBuildError: the extension is not built, was built against a
            different Python / MLX, or its shared libraries cannot be loaded.
            The message includes the original import error. Also raised
            while ``MLX3D_NO_CORE`` is set.
    """
    global _core, _failure
    if disabled():
        raise ExtensionBuildError(f"mlx3d._core is turned off by {DISABLE_ENV}={os.environ[DISABLE_ENV]!r}; unset it to use the compiled kernels")
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
        try:
            from mlx3d import _core as module
        except ImportError as exc:
            _failure = ExtensionBuildError(
                "The compiled extension mlx3d._core is missing or broken "
                f"({type(exc).__name__}: {exc}). {BUILD_HINT}"
            )
            raise _failure from exc
        _core = module
        return module


def available() -> bool:
    """True when :func:`core` succeeds (never raises; False while ``MLX3D_NO_CORE`` is set)."""
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
