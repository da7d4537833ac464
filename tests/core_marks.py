"""``needs_core``: the mark of tests about the compiled CPU kernels (their results, threads and bits), in
``mlx3d._core`` or the kernel library in its place (``mlx3d.native``). They skip, with the reason, where
neither is there or they are turned off (``MLX3D_NO_CORE``, as ``make test-pure`` runs the suite); everything
else runs either way. ``needs_extension``: tests of what only the MLX extension ``mlx3d._core`` does (linking
MLX, MLX's buffer donation), which also skip where the kernel library serves (``MLX3D_CPU_KERNELS=library``).
``long_training``: the mark of the few tests that train long enough to assert a quality users rely on. They
would take most of CI's time on the pure MLX path (its trainer is the same code, which the other training
tests run there), and what they measure depends on the trainer and kernels, not on the Python or numpy
version, so they run once among the whole-suite entries: ``make test-py313`` sets ``MLX3D_SECOND_SUITE=1``.
``once_per_suite``: the mark of modules whose subject does not depend on the running Python or numpy (the
extension zips, built for every Python from any), which the second whole-suite entry skips as well.
``runs_no_kernel``: the mark of test modules whose subject runs no kernel of ours (solving cameras with
pycolmap, say): the pure path changes nothing there, so ``make test-pure`` skips them to keep CI's time.
``above_kernels``: the mark of test modules about what is built on top of the render and training entry points
(the command line, the documentation's examples, the report, the add-on's training, photo, mesh, benchmark and
demo operators): the pure path runs the same code there, above its own
kernels, which their own modules test, so ``make test-pure`` skips them to keep CI's time.
``FAST``: the backend a test uses for "the fast renderer": 'cpu' (the C++ kernels), or 'mlx' where
the compiled module is not available."""

import os

import pytest

from mlx3d import native

needs_core = pytest.mark.skipif(not native.available(), reason="tests the compiled CPU kernels, not available here (not built, or MLX3D_NO_CORE is set)")
needs_extension = pytest.mark.skipif(not native.available() or native.core().__name__ != "mlx3d._core",
                                     reason="tests the MLX extension mlx3d._core itself, which does not serve the CPU kernels here")

SECOND_SUITE = os.environ.get("MLX3D_SECOND_SUITE") == "1"
long_training = pytest.mark.skipif(
    not native.available() or SECOND_SUITE,
    reason="a long training: over 25 minutes on the pure MLX path (the same trainer code, which the other training "
    "tests run there); it runs once among the whole-suite entries (MLX3D_SECOND_SUITE=1 here)",
)
once_per_suite = pytest.mark.skipif(SECOND_SUITE, reason="does not depend on the Python or numpy running it: runs once "
                                    "among the whole-suite entries (MLX3D_SECOND_SUITE=1 here)")
runs_no_kernel = pytest.mark.skipif(not native.available(), reason="runs no kernel of ours: the pure MLX path changes nothing here")
above_kernels = pytest.mark.skipif(not native.available(), reason="built on the render and training entry points: the pure MLX "
                                   "path runs the same code here, above its kernels, which their own modules test")
FAST = "cpu" if native.available() else "mlx"
