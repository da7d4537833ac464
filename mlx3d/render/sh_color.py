"""The renderer's colour stage: RGB (N,3) = max(eval_sh(degree, sh, means - centre), 0), one entry per backend.

'cpu' runs ``mlx3d._core.sh_colors``, a threaded C++ MLX primitive with a
hand-written backward pass (the kernel library's ``mlx3d_sh_forward`` and
``mlx3d_sh_backward``, ``mlx3d/csrc/kernels/sh.cpp``; math in
``mlx3d/csrc/sh_math.h``, the header a Metal kernel would share); 'metal' and 'reference' run the pure-MLX
reference, :func:`mlx3d.splatting.sh.eval_sh`, which is also the test oracle.
Differentiable with respect to ``sh`` and ``means`` on every backend.

``sh`` is one (N,K,3) array or the pair (sh_dc (N,1,3), sh_rest (N,K-1,3))
as a model stores them: the CPU kernel reads the pair in place, which saves
concatenating the coefficients on every render and splitting their gradient.
"""

from __future__ import annotations

import mlx.core as mx

from ..splatting.sh import eval_sh
from .rasterize import resolve_backend

__all__ = ["sh_colors", "num_coefficients"]


def num_coefficients(sh) -> int:
    """K of ``sh`` given as one (N,K,3) array or a pair of blocks (see ``sh_colors``)."""
    return sum(int(b.shape[1]) for b in sh) if isinstance(sh, (tuple, list)) else int(sh.shape[1])


def sh_colors(sh: mx.array, means: mx.array, centre, degree: int, backend: str = "auto") -> mx.array:
    """View-dependent colour of Gaussians, clamped at 0 as in 3DGS.

    sh: (N, K, 3) coefficients, K >= (degree+1)² (extra ones ignored), or a
    pair of blocks (N, K0, 3), (N, K1, 3) read as their concatenation; means:
    (N, 3) world positions; centre: (3,) camera centre (world); degree: 0..3.
    Returns (N, 3) float32. The gradient passes where the unclamped colour is
    positive; the centre gets none.
    """
    backend = resolve_backend(backend)
    centre = mx.array(centre, dtype=mx.float32)
    blocks = list(sh) if isinstance(sh, (tuple, list)) else [sh]
    if backend == "cpu":
        from mlx3d import native

        from .raster_cpu import get_num_threads

        blocks = [b.astype(mx.float32) for b in blocks]
        return native.core().sh_colors(blocks, means.astype(mx.float32), centre, int(degree), get_num_threads())
    sh = mx.concatenate(blocks, axis=1) if len(blocks) > 1 else blocks[0]
    return mx.maximum(eval_sh(degree, sh, means - centre), 0.0)
