"""File input/output for splats, without MLX (numpy; Pillow for SOG images, zstandard for SPZ v4).

- :func:`read_splats` / :func:`write_splats`: every splat file format (PLY,
  compressed PLY, SPZ, ``.splat``, ``.ksplat``, SOG, glTF), recognised by
  content / chosen by extension (:mod:`mlx3d.io.formats` lists them);
- :func:`read_splat_ply` / :func:`write_splat_ply`: standard 3DGS PLY files,
  to and from :class:`SplatArrays`;
- :func:`atomic_write`: write-to-temporary-then-rename helper used by the
  writers;
- :func:`read_exr`: the channels of an OpenEXR file (Blender's render passes)
  as float32 arrays.
"""

from .atomic import atomic_write
from .exr import ExrError, read_exr
from .formats import FORMATS, SplatFormat, detect_format, format_for_path, read_splats, with_sh_degree, write_splats
from .ply import NONFINITE_MODES, NORMAL_NAMES, SplatArrays, read_splat_ply, write_splat_ply

__all__ = [
    "FORMATS",
    "NONFINITE_MODES",
    "NORMAL_NAMES",
    "ExrError",
    "SplatArrays",
    "SplatFormat",
    "atomic_write",
    "detect_format",
    "format_for_path",
    "read_exr",
    "read_splat_ply",
    "read_splats",
    "with_sh_degree",
    "write_splat_ply",
    "write_splats",
]
