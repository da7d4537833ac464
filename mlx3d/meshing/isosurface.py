"""Marching tetrahedra on a regular grid (numpy, vectorised).

Each grid cube is split into six tetrahedra along its main diagonal (Kuhn /
Freudenthal split): the tetrahedron of axis order (a, b, c) has the corners
``0, e_a, e_a + e_b, (1, 1, 1)``. All face diagonals then run in a positive
direction of the lattice, so neighbouring cubes split their shared face the
same way and the isosurface of the piecewise-linear interpolant is a closed
2-manifold wherever it does not reach the grid boundary.

Every tetrahedron edge joins a lattice node ``p`` to ``p + d`` with
``d`` in {0,1}^3 minus 0 (19 edges per cube: 12 cube edges, 6 face
diagonals, 1 body diagonal). A crossing edge is identified by ``(p, d)``, so
the tetrahedra around an edge share its vertex and the mesh is indexed
without duplicates. Triangles are oriented so their right-hand normal points
from the corners above ``level`` ("inside") to those below.

Grid values equal to ``level`` are moved just below it and edge parameters
are kept inside ``[1e-4, 1 - 1e-4]``, so no triangle is degenerate and none
has to be removed (removal would open holes).
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["marching_tetrahedra"]

_T_MIN = 1e-4  # edge parameters are clipped to [_T_MIN, 1 - _T_MIN]
_CUBE_CHUNK = 1 << 18  # active cubes processed per batch (bounds temporary memory)


def _bits(corner: int) -> np.ndarray:
    """Unit-cube corner index (x + 2y + 4z) -> its (3,) 0/1 offset."""
    return np.array([corner & 1, (corner >> 1) & 1, (corner >> 2) & 1])


def _build_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lookup tables of the Kuhn split.

    Returns:
        edge_lo: (19,) cube corner at the lower end of each edge.
        edge_dir: (19,) direction code ``d`` (1..7, bits x, y, z) of each edge.
        tris: (256, 12, 3) int8 edges of the (at most 12) oriented triangles
            for each cube sign pattern (bit i set = corner i inside), -1 padded.
    """
    tets = []
    for a, b, _ in itertools.permutations(range(3)):
        tets.append((0, 1 << a, (1 << a) | (1 << b), 7))
    edges: list[tuple[int, int]] = []
    for t in tets:
        for i, j in itertools.combinations(range(4), 2):
            e = (t[i], t[j] - t[i])  # t[i] is a subset of t[j]: d = t[j] - t[i]
            if e not in edges:
                edges.append(e)
    edge_of = {e: n for n, e in enumerate(edges)}

    def edge(u: int, v: int) -> int:
        lo, hi = (u, v) if (u & v) == u else (v, u)
        return edge_of[(lo, hi - lo)]

    def midpoint(e: int) -> np.ndarray:
        lo, d = edges[e]
        return _bits(lo) + 0.5 * _bits(d)

    tris = np.full((256, 12, 3), -1, dtype=np.int8)
    for mask in range(256):
        out = []
        for t in tets:
            inside = [v for v in t if mask >> v & 1]
            outside = [v for v in t if not mask >> v & 1]
            if len(inside) in (0, 4):
                continue
            if len(inside) == 1:
                polys = [[edge(inside[0], o) for o in outside]]
            elif len(inside) == 3:
                polys = [[edge(i, outside[0]) for i in inside]]
            else:  # quad, cyclic order ac, ad, bd, bc
                (pa, pb), (pc, pd) = inside, outside
                q = [edge(pa, pc), edge(pa, pd), edge(pb, pd), edge(pb, pc)]
                polys = [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
            c_in = np.mean([_bits(v) for v in inside], axis=0)
            c_out = np.mean([_bits(v) for v in outside], axis=0)
            for p in polys:
                p0, p1, p2 = (midpoint(e) for e in p)
                if np.dot(np.cross(p1 - p0, p2 - p0), c_out - c_in) < 0:
                    p = [p[0], p[2], p[1]]
                out.append(p)
        if out:
            tris[mask, : len(out)] = out
    lo = np.array([e[0] for e in edges], dtype=np.int64)
    d = np.array([e[1] for e in edges], dtype=np.int64)
    return lo, d, tris


_EDGE_LO, _EDGE_DIR, _TRIS = _build_tables()
_TRI_COUNT = (_TRIS[:, :, 0] >= 0).sum(axis=1)


def marching_tetrahedra(
    values: np.ndarray,
    level: float,
    origin: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    spacing: float = 1.0,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Isosurface ``values == level`` of a grid, as an indexed triangle mesh.

    Args:
        values: (X, Y, Z) finite real grid (used as float32), node
            ``(i, j, k)`` at ``origin + spacing * (i, j, k)``; each side
            needs >= 2 nodes.
        level: finite iso value (used as float32). Nodes above it are inside.
        origin: (3,) position of node (0, 0, 0).
        spacing: distance between neighbouring nodes (> 0).
        mask: optional (X, Y, Z) bool, False for nodes whose value is not
            known: cubes with such a corner make no triangles (the surface
            stops open there instead of closing around unknown space). Values
            at masked-out nodes may be anything finite.

    Returns:
        ``(vertices, faces)``: (V, 3) float32 positions and (F, 3) int32
        indices, oriented with normals pointing from higher to lower values
        (out of the region ``values > level``). The mesh is closed and
        manifold except where it meets the grid boundary or masked-out nodes.
    """
    vals = np.asarray(values)
    if vals.ndim != 3 or min(vals.shape) < 2:
        raise ValueError(f"values must be a 3D grid with >= 2 nodes per side, got shape {vals.shape}")
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    vals = np.ascontiguousarray(vals, dtype=np.float32)
    level = np.float32(level)  # compare and interpolate in the grid's own precision
    if not np.isfinite(level) or not np.isfinite(vals).all():
        raise ValueError("values and level must be finite (NaN or Inf found)")
    nx, ny, nz = vals.shape
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != vals.shape:
            raise ValueError(f"mask must have the grid's shape {vals.shape}, got {mask.shape}")
    inside = vals > level
    on_level = vals == level
    if on_level.any():  # keep every edge parameter strictly inside (0, 1)
        vals = vals.copy()
        vals[on_level] = np.nextafter(np.float32(level), np.float32(-np.inf))
    del on_level

    # cube sign patterns, only for cubes whose corners straddle the level
    count = np.zeros((nx - 1, ny - 1, nz - 1), dtype=np.uint8)
    for c in range(8):
        x, y, z = _bits(c)
        count += inside[x : nx - 1 + x, y : ny - 1 + y, z : nz - 1 + z]
    straddles = (count > 0) & (count < 8)
    del count
    if mask is not None:
        for c in range(8):
            x, y, z = _bits(c)
            straddles &= mask[x : nx - 1 + x, y : ny - 1 + y, z : nz - 1 + z]
    active = np.flatnonzero(straddles)
    del straddles
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    if active.size == 0:
        return empty
    ci, cj, ck = np.unravel_index(active, (nx - 1, ny - 1, nz - 1))
    base = (ci * ny + cj) * nz + ck  # flat index of each active cube's node (0, 0, 0)
    del ci, cj, ck, active
    corner_off = np.array([x * ny * nz + y * nz + z for x, y, z in map(_bits, range(8))], dtype=np.int64)
    dir_off = corner_off  # the node offset of direction code d equals that of corner d
    flat_inside = inside.ravel()

    keys = []
    for a in range(0, base.size, _CUBE_CHUNK):
        b = base[a : a + _CUBE_CHUNK]
        mask = np.zeros(b.size, dtype=np.intp)
        for c in range(8):
            mask |= flat_inside[b + corner_off[c]].astype(np.intp) << c
        # expand each cube into its triangles (at most 12), then to edge keys
        n_tri = _TRI_COUNT[mask]
        cube = np.repeat(np.arange(b.size), n_tri)
        slot = np.arange(cube.size) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
        e = _TRIS[mask[cube], slot].astype(np.intp)  # (T, 3) cube edge ids
        keys.append((b[cube][:, None] + corner_off[_EDGE_LO[e]]) * 8 + _EDGE_DIR[e])
    keys = np.concatenate(keys)
    uniq, inverse = np.unique(keys, return_inverse=True)
    faces = inverse.reshape(-1, 3).astype(np.int32)
    del keys, inverse

    # vertex positions: linear interpolation along each crossing edge
    node = uniq // 8
    d = uniq % 8
    flat_vals = vals.ravel()
    v0 = flat_vals[node].astype(np.float64)
    v1 = flat_vals[node + dir_off[d]].astype(np.float64)
    t = np.clip((np.float64(level) - v0) / (v1 - v0), _T_MIN, 1.0 - _T_MIN)
    i, j, k = np.unravel_index(node, (nx, ny, nz))
    pos = np.stack(
        [i + t * (d & 1), j + t * (d >> 1 & 1), k + t * (d >> 2 & 1)], axis=1
    )
    vertices = (origin + spacing * pos).astype(np.float32)
    return vertices, faces
