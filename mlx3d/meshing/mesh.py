"""Triangle meshes (numpy only): :class:`SurfaceMesh` and :class:`MeshingError`.

A mesh is an indexed triangle list. Faces are counter-clockwise seen from
outside, so the right-hand normal ``(v1 - v0) x (v2 - v0)`` points out of the
enclosed solid and the signed volume of a closed mesh is positive.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from mlx3d.errors import Mlx3dError

__all__ = ["MeshingError", "SurfaceMesh", "compact_faces"]


def compact_faces(vertices: np.ndarray, faces: np.ndarray, keep_faces: np.ndarray):
    """Keeps ``faces[keep_faces]`` and only the vertices they use: ``(vertices, faces, vertex_index)``, the last
    the (V',) indices of the kept vertices in the input."""
    faces = faces[keep_faces]
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used, dtype=np.int64) - 1
    return vertices[used], remap[faces].astype(np.int32), np.flatnonzero(used)


class MeshingError(Mlx3dError, ValueError):
    """Surface reconstruction cannot run on the given input (the message says why)."""


@dataclass
class SurfaceMesh:
    """Indexed triangle mesh.

    Attributes:
        vertices: (V, 3) float32 positions, in the units and frame of the input.
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside
            (right-hand normals point out of the solid).
        colors: (V, 3) float32 RGB in [0, 1], or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(np.asarray(self.vertices, dtype=np.float32).reshape(-1, 3))
        faces = np.asarray(self.faces)
        if faces.size == 0:
            faces = faces.reshape(0, 3)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got shape {faces.shape}")
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        if self.colors is not None:
            colors = np.ascontiguousarray(np.asarray(self.colors, dtype=np.float32))
            if colors.shape != self.vertices.shape:
                raise ValueError(
                    f"colors must have shape {self.vertices.shape} (one RGB per vertex), "
                    f"got shape {colors.shape}"
                )
            self.colors = colors

    # ------------------------------------------------------------------ #
    def _corners(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v = self.vertices.astype(np.float64)
        f = self.faces
        return v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]

    def face_normals(self) -> np.ndarray:
        """(F, 3) float64 un-normalised right-hand normals (length = twice the face area)."""
        a, b, c = self._corners()
        return np.cross(b - a, c - a)

    def area(self) -> float:
        """Total surface area (input units squared)."""
        if len(self.faces) == 0:
            return 0.0
        return float(0.5 * np.linalg.norm(self.face_normals(), axis=1).sum())

    def volume(self) -> float:
        """Signed enclosed volume (divergence theorem); positive for outward faces.

        Meaningful for closed meshes; for an open mesh it depends on the origin.
        """
        if len(self.faces) == 0:
            return 0.0
        a, b, c = self._corners()
        return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)

    def edges(self) -> np.ndarray:
        """(E, 2) int64 unique undirected edges, each as (smaller, larger) index."""
        f = self.faces.astype(np.int64)
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        e.sort(axis=1)
        return np.unique(e, axis=0)

    def euler_characteristic(self) -> int:
        """V - E + F (2 for a sphere-like closed surface, 0 for a torus)."""
        return len(self.vertices) - len(self.edges()) + len(self.faces)

    def is_watertight(self) -> bool:
        """True when every edge is shared by exactly two faces with opposite orientation.

        Each directed edge (a, b) then occurs exactly once and so does (b, a).
        An empty mesh is not watertight.
        """
        if len(self.faces) == 0:
            return False
        f = self.faces.astype(np.int64)
        a = f.ravel()
        b = f[:, [1, 2, 0]].ravel()
        n = np.int64(len(self.vertices))
        fwd = np.sort(a * n + b)
        if fwd.size > 1 and (fwd[1:] == fwd[:-1]).any():
            return False
        rev = np.sort(b * n + a)
        return bool(np.array_equal(fwd, rev))

    def vertex_normals(self) -> np.ndarray:
        """(V, 3) float32 unit normals: area-weighted mean of the incident face normals.

        Vertices without faces (or with only degenerate ones) get (0, 0, 0).
        """
        nv = len(self.vertices)
        out = np.zeros((nv, 3), dtype=np.float64)
        if len(self.faces):
            fn = self.face_normals()
            idx = self.faces.ravel()
            for c in range(3):
                out[:, c] = np.bincount(idx, np.repeat(fn[:, c], 3), minlength=nv)
        length = np.linalg.norm(out, axis=1, keepdims=True)
        np.divide(out, length, out=out, where=length > 0)
        return out.astype(np.float32)

    def save_ply(self, path: str | os.PathLike) -> None:
        """Write a binary PLY file (see :func:`mlx3d.io.mesh_ply.write_mesh_ply`)."""
        from mlx3d.io.mesh_ply import write_mesh_ply

        write_mesh_ply(path, self.vertices, self.faces, self.colors)
