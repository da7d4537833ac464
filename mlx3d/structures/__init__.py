"""Data structures of mlx3D's ``mlx3d.structures`` that the splatting API returns: :class:`Meshes`."""

from .meshes import Meshes, join_meshes_as_batch

__all__ = ["Meshes", "join_meshes_as_batch"]
