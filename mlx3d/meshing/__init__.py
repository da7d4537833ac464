"""Surface meshes from oriented points or from depth maps (numpy, with MLX's FFT for Poisson's solve).

- :func:`reconstruct_surface`: Poisson surface reconstruction from points with
  normals (and optional per-sample areas and colours) to a :class:`SurfaceMesh`;
- :func:`fuse_depth_maps`: depth maps from known cameras fused into a
  truncated signed distance volume and meshed where it was seen
  (:mod:`.fusion`; :func:`keep_large_components` drops small islands);
- :func:`simplify`: at most a target number of faces (quadric vertex
  clustering, :mod:`.simplify`);
- :func:`marching_tetrahedra`: watertight isosurface of a regular grid;
- :class:`SurfaceMesh`: indexed triangle mesh (area, volume, watertightness,
  normals, PLY output via :mod:`mlx3d.io.mesh_ply`);
- :class:`MeshingError`: raised for input the reconstruction cannot use.

MLX and the compiled extension (k-NN for trimming and colours) are imported
on first use, so importing this package needs numpy only.
"""

from .fusion import DepthView, fuse_depth_maps, keep_large_components
from .isosurface import marching_tetrahedra
from .mesh import MeshingError, SurfaceMesh
from .poisson import DEFAULT_TRIM, reconstruct_surface
from .simplify import simplify

__all__ = [
    "DEFAULT_TRIM",
    "DepthView",
    "MeshingError",
    "SurfaceMesh",
    "fuse_depth_maps",
    "keep_large_components",
    "marching_tetrahedra",
    "reconstruct_surface",
    "simplify",
]
