"""Surface reconstruction under mlx3D's name, on mlx3d's own solver (:mod:`mlx3d.meshing.poisson`)."""

from __future__ import annotations

import numpy as np

from ..meshing import DEFAULT_TRIM, reconstruct_surface
from ..structures import Meshes

__all__ = ["poisson_reconstruction"]


def poisson_reconstruction(points, normals, resolution: int = 64, padding: float = 0.1, *, weights=None, colors=None,
                           trim: float | None = DEFAULT_TRIM, progress=None) -> Meshes:
    """A one-mesh :class:`~mlx3d.structures.Meshes` of the solid whose boundary the oriented points describe.

    points, normals: (N, 3) numpy or MLX arrays; normals point out of the solid
    (any non-zero length). resolution: grid cells per side of the cube around
    the points (8..512); padding: margin on each side as a fraction of the
    bounding box's largest side. Faces are counter-clockwise seen from outside.

    mlx3d additions (keywords): ``weights`` (N,) surface area per point (None:
    uniform), ``colors`` (N, 3) in [0, 1] for vertex colours
    (``Meshes.verts_colors_list()``), ``trim`` in voxels (faces farther than it
    from every point are dropped; 0 or None keeps all), ``progress(done, total)``.
    See :func:`mlx3d.meshing.reconstruct_surface`, which does the work; raises
    :class:`mlx3d.meshing.MeshingError` (a ``ValueError``) for unusable input.
    """

    def as_numpy(a):
        return None if a is None else np.asarray(a)

    mesh = reconstruct_surface(as_numpy(points), as_numpy(normals), as_numpy(weights), as_numpy(colors),
                               resolution=resolution, padding=padding, trim=trim, progress=progress)
    return Meshes.from_surface_meshes([mesh])
