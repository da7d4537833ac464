"""``Meshes``: a batch of triangle meshes as MLX arrays (mlx3D's container, after PyTorch3D's).

A batch holds ``len(meshes)`` meshes, each with its own vertex and face count,
seen three ways:

- list: ``verts_list()[i]`` (V_i, 3) float, ``faces_list()[i]`` (F_i, 3) int32
  indices into that mesh's vertices;
- packed: ``verts_packed()`` (ΣV_i, 3) and ``faces_packed()`` (ΣF_i, 3) with
  indices shifted to address the packed vertices;
- padded: ``verts_padded()`` (B, max V_i, 3) padded with zeros and
  ``faces_padded()`` (B, max F_i, 3) padded with -1.

Vertex arrays are kept as given (MLX), so gradients flow from a rebuilt
``Meshes`` back to the arrays it was built from. ``verts_colors`` (one (V_i, 3)
array per mesh, RGB in [0, 1]) is an mlx3d addition that
``GaussianModel.extract_surface_mesh`` fills; ``surface_mesh(i)`` converts a
mesh to :class:`mlx3d.meshing.SurfaceMesh` (area, volume, watertightness,
PLY output).
"""

from __future__ import annotations

import mlx.core as mx
import numpy as np

__all__ = ["Meshes", "join_meshes_as_batch"]


def _float_array(a) -> mx.array:
    if not isinstance(a, mx.array):
        a = np.asarray(a)
        a = mx.array(a.astype(np.float32) if a.dtype != np.float32 else a)
    return a if mx.issubdtype(a.dtype, mx.floating) else a.astype(mx.float32)


def _index_array(a) -> mx.array:
    if not isinstance(a, mx.array):
        a = mx.array(np.asarray(a).astype(np.int32))
    return a.astype(mx.int32) if a.dtype != mx.int32 else a


def _split(packed: mx.array, counts: list[int]) -> list[mx.array]:
    out, start = [], 0
    for c in counts:
        out.append(packed[start : start + c])
        start += c
    return out


class Meshes:
    """A batch of triangle meshes.

    Args:
        verts: a list of (V_i, 3) float arrays, or a padded (B, V, 3) MLX array
            (every mesh then has V vertices).
        faces: a list of (F_i, 3) integer arrays, or a padded (B, F, 3) MLX
            array whose unused rows are -1 (a row with any -1 ends the mesh's
            faces).
        verts_colors: optional list of (V_i, 3) RGB arrays in [0, 1], one per
            mesh (an mlx3d addition).

    numpy arrays are accepted in the lists and converted to MLX.
    """

    def __init__(self, verts, faces, verts_colors=None) -> None:
        if isinstance(verts, (list, tuple)) and isinstance(faces, (list, tuple)):
            if len(verts) != len(faces):
                raise ValueError(f"verts and faces must hold the same number of meshes, got {len(verts)} and {len(faces)}")
            vl = [_float_array(v) for v in verts]
            fl = [_index_array(f) for f in faces]
        elif isinstance(verts, mx.array) and isinstance(faces, mx.array):
            if verts.ndim != 3 or verts.shape[-1] != 3:
                raise ValueError(f"padded verts must have shape (B, V, 3), got {tuple(verts.shape)}")
            if faces.ndim != 3 or faces.shape[-1] != 3:
                raise ValueError(f"padded faces must have shape (B, F, 3), got {tuple(faces.shape)}")
            if verts.shape[0] != faces.shape[0]:
                raise ValueError(f"padded verts and faces hold {verts.shape[0]} and {faces.shape[0]} meshes")
            verts, faces = _float_array(verts), _index_array(faces)
            valid = np.array(mx.all(faces >= 0, axis=-1))
            # a mesh's faces end at its first padded row
            counts = [int(np.argmin(row)) if not row.all() else len(row) for row in valid]
            vl = [verts[i] for i in range(verts.shape[0])]
            fl = [faces[i, : counts[i]] for i in range(faces.shape[0])]
        else:
            raise ValueError("verts and faces must both be lists of arrays or both padded mx.arrays")
        for i, (v, f) in enumerate(zip(vl, fl)):
            if v.ndim != 2 or v.shape[1] != 3:
                raise ValueError(f"verts of mesh {i} must have shape (V, 3), got {tuple(v.shape)}")
            if f.ndim != 2 or f.shape[1] != 3:
                raise ValueError(f"faces of mesh {i} must have shape (F, 3), got {tuple(f.shape)}")
        self._verts_list, self._faces_list = vl, fl
        if verts_colors is not None:
            if len(verts_colors) != len(vl):
                raise ValueError(f"verts_colors must hold one array per mesh ({len(vl)}), got {len(verts_colors)}")
            cl = [_float_array(c) for c in verts_colors]
            for i, (c, v) in enumerate(zip(cl, vl)):
                if tuple(c.shape) != tuple(v.shape):
                    raise ValueError(f"verts_colors of mesh {i} must have shape {tuple(v.shape)}, got {tuple(c.shape)}")
            self._colors_list = cl
        else:
            self._colors_list = None
        self._cache: dict = {}

    # ----------------------------------------------------------------- basics
    def __len__(self) -> int:
        return len(self._verts_list)

    def __getitem__(self, index) -> "Meshes":
        if isinstance(index, (int, np.integer)):
            index = [int(index)]
        elif isinstance(index, slice):
            index = list(range(len(self)))[index]
        index = [int(i) for i in index]
        colors = None if self._colors_list is None else [self._colors_list[i] for i in index]
        return Meshes([self._verts_list[i] for i in index], [self._faces_list[i] for i in index], colors)

    def __repr__(self) -> str:
        return f"Meshes(n={len(self)}, verts={self._counts('v')}, faces={self._counts('f')})"

    def _counts(self, which: str) -> list[int]:
        arrays = self._verts_list if which == "v" else self._faces_list
        return [int(a.shape[0]) for a in arrays]

    def isempty(self) -> bool:
        """True when the batch holds no mesh or only meshes without vertices."""
        return len(self) == 0 or all(n == 0 for n in self._counts("v"))

    @property
    def num_verts_per_mesh(self) -> mx.array:
        """(B,) int32 vertex counts."""
        return mx.array(self._counts("v"), dtype=mx.int32)

    @property
    def num_faces_per_mesh(self) -> mx.array:
        """(B,) int32 face counts."""
        return mx.array(self._counts("f"), dtype=mx.int32)

    # ------------------------------------------------------------------ lists
    def verts_list(self) -> list[mx.array]:
        return list(self._verts_list)

    def faces_list(self) -> list[mx.array]:
        return list(self._faces_list)

    def verts_colors_list(self) -> list[mx.array] | None:
        """Per-mesh (V_i, 3) colours, or None when the meshes have none."""
        return None if self._colors_list is None else list(self._colors_list)

    # ----------------------------------------------------------------- packed
    def _cached(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def verts_packed(self) -> mx.array:
        """(ΣV_i, 3) all vertices, mesh after mesh."""
        return self._cached("verts_packed", lambda: mx.concatenate(self._verts_list, axis=0) if len(self) else mx.zeros((0, 3)))

    def faces_packed(self) -> mx.array:
        """(ΣF_i, 3) int32 faces indexing ``verts_packed()``."""

        def make():
            if not len(self):
                return mx.zeros((0, 3), dtype=mx.int32)
            offsets = np.concatenate([[0], np.cumsum(self._counts("v"))[:-1]]).astype(np.int32)
            return mx.concatenate([f + int(o) for f, o in zip(self._faces_list, offsets)], axis=0)

        return self._cached("faces_packed", make)

    def _first_index(self, which: str) -> mx.array:
        counts = self._counts(which)
        return mx.array(np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32) if counts else np.zeros(0, np.int32))

    def mesh_to_verts_packed_first_idx(self) -> mx.array:
        """(B,) int32 index of each mesh's first vertex in ``verts_packed()``."""
        return self._first_index("v")

    def mesh_to_faces_packed_first_idx(self) -> mx.array:
        """(B,) int32 index of each mesh's first face in ``faces_packed()``."""
        return self._first_index("f")

    def verts_packed_to_mesh_idx(self) -> mx.array:
        """(ΣV_i,) int32 mesh of each packed vertex."""
        return mx.array(np.repeat(np.arange(len(self), dtype=np.int32), self._counts("v")))

    def faces_packed_to_mesh_idx(self) -> mx.array:
        """(ΣF_i,) int32 mesh of each packed face."""
        return mx.array(np.repeat(np.arange(len(self), dtype=np.int32), self._counts("f")))

    # ----------------------------------------------------------------- padded
    def verts_padded(self) -> mx.array:
        """(B, max V_i, 3) vertices, zero-padded."""

        def make():
            if not len(self):
                return mx.zeros((0, 0, 3))
            n = max(self._counts("v"))
            return mx.stack([mx.pad(v, [(0, n - v.shape[0]), (0, 0)]) for v in self._verts_list])

        return self._cached("verts_padded", make)

    def faces_padded(self) -> mx.array:
        """(B, max F_i, 3) int32 faces, padded with -1."""

        def make():
            if not len(self):
                return mx.zeros((0, 0, 3), dtype=mx.int32)
            n = max(self._counts("f"))
            return mx.stack([mx.pad(f, [(0, n - f.shape[0]), (0, 0)], constant_values=-1) for f in self._faces_list])

        return self._cached("faces_padded", make)

    # --------------------------------------------------------------- geometry
    def faces_normals_packed(self) -> mx.array:
        """(ΣF_i, 3) right-hand face normals ``(v1 - v0) x (v2 - v0)``, not normalised (length: twice the area)."""

        def make():
            v, f = self.verts_packed(), self.faces_packed()
            v0, v1, v2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
            return mx.linalg.cross(v1 - v0, v2 - v0)

        return self._cached("faces_normals", make)

    def faces_areas_packed(self) -> mx.array:
        """(ΣF_i,) face areas."""
        return self._cached("faces_areas", lambda: 0.5 * mx.linalg.norm(self.faces_normals_packed(), axis=-1))

    def verts_normals_packed(self) -> mx.array:
        """(ΣV_i, 3) unit vertex normals: area-weighted sums of the incident face normals (0 for isolated vertices)."""

        def make():
            v, f = self.verts_packed(), self.faces_packed()
            fn = self.faces_normals_packed()
            acc = mx.zeros(v.shape, dtype=fn.dtype)
            for corner in range(3):
                acc = acc.at[f[:, corner]].add(fn)
            return acc / mx.maximum(mx.linalg.norm(acc, axis=-1, keepdims=True), 1e-12)

        return self._cached("verts_normals", make)

    def verts_normals_list(self) -> list[mx.array]:
        return _split(self.verts_normals_packed(), self._counts("v"))

    def edges_packed(self) -> mx.array:
        """(E, 2) int32 unique undirected edges (smaller index first) of the packed mesh."""

        def make():
            f = np.array(self.faces_packed(), dtype=np.int64)
            if not len(f):
                return mx.zeros((0, 2), dtype=mx.int32)
            e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
            return mx.array(np.unique(e, axis=0).astype(np.int32))

        return self._cached("edges", make)

    def bounding_boxes(self) -> mx.array:
        """(B, 3, 2) per-mesh [min, max] of each coordinate."""
        return mx.stack([mx.stack([v.min(axis=0), v.max(axis=0)], axis=-1) for v in self._verts_list])

    # -------------------------------------------------------------- new batches
    def offset_verts(self, offsets) -> "Meshes":
        """A new batch with ``offsets`` ((ΣV_i, 3) or (3,)) added to the packed vertices."""
        moved = self.verts_packed() + _float_array(offsets)
        return Meshes(_split(moved, self._counts("v")), self._faces_list, self._colors_list)

    def update_padded(self, new_verts_padded) -> "Meshes":
        """A new batch with the same faces and vertices taken from a (B, max V_i, 3) array."""
        new = _float_array(new_verts_padded)
        return Meshes([new[i, : v.shape[0]] for i, v in enumerate(self._verts_list)], self._faces_list, self._colors_list)

    def scale_verts(self, scale) -> "Meshes":
        """A new batch with every vertex multiplied by ``scale``."""
        return Meshes([v * scale for v in self._verts_list], self._faces_list, self._colors_list)

    # ---------------------------------------------------------------- mlx3d
    def surface_mesh(self, index: int = 0):
        """Mesh ``index`` as a :class:`mlx3d.meshing.SurfaceMesh` (numpy; area, volume, ``save_ply``)."""
        from ..meshing import SurfaceMesh

        colors = None if self._colors_list is None else np.array(self._colors_list[index])
        return SurfaceMesh(np.array(self._verts_list[index]), np.array(self._faces_list[index]), colors)

    @classmethod
    def from_surface_meshes(cls, meshes) -> "Meshes":
        """A batch from :class:`mlx3d.meshing.SurfaceMesh` objects (colours kept when all have them)."""
        meshes = list(meshes)
        with_colors = bool(meshes) and all(m.colors is not None for m in meshes)
        return cls([m.vertices for m in meshes], [m.faces for m in meshes], [m.colors for m in meshes] if with_colors else None)


def join_meshes_as_batch(meshes) -> Meshes:
    """One batch holding the meshes of several batches, in order (colours kept when all have them)."""
    meshes = list(meshes)
    verts = [v for m in meshes for v in m.verts_list()]
    faces = [f for m in meshes for f in m.faces_list()]
    with_colors = bool(meshes) and all(m.verts_colors_list() is not None for m in meshes)
    colors = [c for m in meshes for c in m.verts_colors_list()] if with_colors else None
    return Meshes(verts, faces, colors)
