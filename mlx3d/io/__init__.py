"""File input/output for splats (numpy only: importable without MLX, e.g. in Blender).

- :func:`read_splat_ply` / :func:`write_splat_ply`: standard 3DGS PLY files,
  to and from :class:`SplatArrays`;
- :func:`atomic_write`: write-to-temporary-then-rename helper used by the
  writers.
"""

from .atomic import atomic_write
from .ply import NONFINITE_MODES, NORMAL_NAMES, SplatArrays, read_splat_ply, write_splat_ply

__all__ = [
    "NONFINITE_MODES",
    "NORMAL_NAMES",
    "SplatArrays",
    "atomic_write",
    "read_splat_ply",
    "write_splat_ply",
]
