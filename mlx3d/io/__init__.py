"""File input/output for splats (numpy only: importable without MLX, e.g. in Blender).

- :func:`read_splat_ply` / :func:`write_splat_ply`: standard 3DGS PLY files,
  to and from :class:`SplatArrays`;
- :func:`atomic_write`: write-to-temporary-then-rename helper used by the
  writers;
- :func:`read_exr`: the channels of an OpenEXR file (Blender's render passes)
  as float32 arrays.
"""

from .atomic import atomic_write
from .exr import ExrError, read_exr
from .ply import NONFINITE_MODES, NORMAL_NAMES, SplatArrays, read_splat_ply, write_splat_ply

__all__ = [
    "NONFINITE_MODES",
    "NORMAL_NAMES",
    "ExrError",
    "SplatArrays",
    "atomic_write",
    "read_exr",
    "read_splat_ply",
    "write_splat_ply",
]
