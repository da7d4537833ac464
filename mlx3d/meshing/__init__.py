"""Surface meshes from oriented points (numpy, with MLX's FFT for the solve).

- :func:`reconstruct_surface`: Poisson surface reconstruction from points with
  normals (and optional per-sample areas and colours) to a :class:`SurfaceMesh`;
- :func:`marching_tetrahedra`: watertight isosurface of a regular grid;
- :class:`SurfaceMesh`: indexed triangle mesh (area, volume, watertightness,
  normals, PLY output via :mod:`mlx3d.io.mesh_ply`);
- :class:`MeshingError`: raised for input the reconstruction cannot use.

MLX and the compiled extension (k-NN for trimming and colours) are imported
on first use, so importing this package needs numpy only.
"""

from .isosurface import marching_tetrahedra
from .mesh import MeshingError, SurfaceMesh
from .poisson import DEFAULT_TRIM, reconstruct_surface

__all__ = [
    "DEFAULT_TRIM",
    "MeshingError",
    "SurfaceMesh",
    "marching_tetrahedra",
    "reconstruct_surface",
]
