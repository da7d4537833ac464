"""Fewer triangles: quadric vertex clustering to a target face count (numpy only).

:func:`simplify` puts the mesh's vertices in a regular grid of cubic cells,
merges each cell's vertices into one and keeps the faces whose corners fall
in three different cells (Lindstrom 2000, "Out-of-core simplification of
large polygonal models"). The merged vertex sits where the squared distances
to the planes of the faces around the cell's vertices are smallest (their
quadric error, as Garland and Heckbert's edge collapse measures it), so
sharp edges and corners stay where they are; where the faces around a cell
are flat or meet in one crease, the free directions keep the vertices' mean.
The cell size is searched (bisection) for the finest grid that leaves at most
the target count. Vertex colours are the mean of the merged vertices'.

Clustering is fast and needs no connectivity, but merges what shares a cell:
walls thinner than a cell close up, and the result may be non-manifold where
that happens. For a fused mesh, a target above about a tenth of its faces
keeps cells near the fusion's voxel size, where that cannot happen.
"""

from __future__ import annotations

import numpy as np

from .mesh import MeshingError, SurfaceMesh, compact_faces

__all__ = ["simplify"]

#: Bisection steps on the cell size: each halves the bracket (ratio of its ends) in log scale.
SEARCH_STEPS = 24
#: Eigenvalues of a cell's quadric below this fraction of its largest are free directions (kept at the mean).
RANK_TOLERANCE = 1e-3


def simplify(mesh: SurfaceMesh, target_faces: int) -> SurfaceMesh:
    """``mesh`` with at most ``target_faces`` faces (usually within a few percent of it), by quadric vertex
    clustering; unchanged when it already has that few. Same frame and units; colours averaged."""
    target = int(target_faces)
    if target != target_faces or target < 1:
        raise MeshingError(f"the target face count must be a whole number of at least 1, got {target_faces!r}")
    if len(mesh.faces) <= target:
        return mesh
    vertices = mesh.vertices.astype(np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)  # every vertex in a cell of the grid
    quadrics = _face_quadrics(vertices, mesh.faces)
    edges = np.linalg.norm(vertices[mesh.faces] - vertices[np.roll(mesh.faces, 1, axis=1)], axis=-1)
    small = max(float(np.median(edges)) * 0.5, 1e-12)  # about as fine as the mesh: keeps almost every face
    large = max(float(np.max(hi - lo)), small) * 2.0  # one or two cells: no face survives
    best = None
    for _ in range(SEARCH_STEPS):
        size = float(np.sqrt(small * large))
        result = _cluster(mesh, vertices, quadrics, lo, size)
        if len(result.faces) <= target:
            large = size
            if best is None or len(result.faces) > len(best.faces):
                best = result
        else:
            small = size
        if best is not None and len(best.faces) >= 0.97 * target:
            break
    if best is None or len(best.faces) == 0:
        raise MeshingError(f"no mesh of at most {target:,} faces keeps a face of this one ({len(mesh.faces):,} faces)")
    return best


def _face_quadrics(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 10) the upper triangle of each face's plane quadric p pᵀ, p = (n, -n·v0), weighted by its area."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    n = cross / np.maximum(norm, 1e-300)[:, None]
    p = np.concatenate([n, -np.sum(n * corners[:, 0], axis=1, keepdims=True)], axis=1)
    i, j = np.triu_indices(4)
    return 0.5 * norm[:, None] * p[:, i] * p[:, j]


def _cluster(mesh: SurfaceMesh, vertices: np.ndarray, quadrics: np.ndarray, origin: np.ndarray, size: float) -> SurfaceMesh:
    """The mesh with its vertices merged per cubic cell of side ``size`` (grid from ``origin``)."""
    cell = np.floor((vertices - origin) / size).astype(np.int64)
    dims = cell.max(axis=0) + 1
    _, label = np.unique((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2], return_inverse=True)
    label = label.ravel()
    count = int(label.max()) + 1
    faces = label[mesh.faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    corners = np.sort(faces, axis=1)  # two faces on the same three cells (a fold): keep one
    order = np.lexsort((corners[:, 2], corners[:, 1], corners[:, 0]))
    repeat = np.zeros(len(faces), dtype=bool)
    repeat[order[1:]] = np.all(corners[order[1:]] == corners[order[:-1]], axis=1)
    faces = faces[~repeat]
    # each cell's quadric: the planes of every face touching one of its vertices, kept or collapsed
    q = np.zeros((count, 10))
    for corner in range(3):
        for k in range(10):
            q[:, k] += np.bincount(label[mesh.faces[:, corner]], weights=quadrics[:, k], minlength=count)
    members = np.maximum(np.bincount(label, minlength=count), 1).astype(np.float64)[:, None]
    mean = np.stack([np.bincount(label, weights=vertices[:, a], minlength=count) for a in range(3)], axis=1) / members
    positions = _minimise(q, mean, origin + (np.floor((mean - origin) / size) + 0.5) * size, size)
    positions, faces, used = compact_faces(positions, faces, np.ones(len(faces), dtype=bool))
    colors = None
    if mesh.colors is not None:
        colors = np.stack([np.bincount(label, weights=mesh.colors[:, a], minlength=count) for a in range(3)], axis=1) / members
        colors = colors[used]
    return SurfaceMesh(positions, faces, colors)


def _minimise(q: np.ndarray, mean: np.ndarray, centre: np.ndarray, size: float) -> np.ndarray:
    """(C, 3) the points of least quadric error, from ``mean`` along the quadric's constrained directions only;
    the mean where that point leaves the cell (grown by half a cell)."""
    a = np.empty((len(q), 3, 3))
    index = {(0, 0): 0, (0, 1): 1, (0, 2): 2, (1, 1): 4, (1, 2): 5, (2, 2): 7}  # into the 10 of triu_indices(4)
    for (r, c), k in index.items():
        a[:, r, c] = a[:, c, r] = q[:, k]
    b = q[:, [3, 6, 8]]
    w, u = np.linalg.eigh(a)
    residual = -b - np.einsum("cij,cj->ci", a, mean)  # the gradient's negative at the mean, halved
    along = np.einsum("cji,cj->ci", u, residual)
    constrained = w > RANK_TOLERANCE * np.maximum(w[:, -1:], 1e-300)
    step = np.where(constrained, along / np.where(constrained, w, 1.0), 0.0)
    point = mean + np.einsum("cij,cj->ci", u, step)
    outside = np.any(np.abs(point - centre) > size, axis=1)
    point[outside] = mean[outside]
    return point
