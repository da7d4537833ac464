"""Quadric vertex clustering (mlx3d.meshing.simplify) against shapes known exactly."""

import numpy as np
import pytest

from mlx3d.meshing import MeshingError, SurfaceMesh, marching_tetrahedra, simplify


def tessellated_cube(n=40) -> SurfaceMesh:
    """The cube [-1, 1]³, each side an n x n grid of squares cut in two triangles, welded, facing out."""
    g = np.linspace(-1.0, 1.0, n + 1)
    vertices, faces, count = [], [], 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = np.meshgrid(g, g, indexing="ij")
            p = np.zeros((n + 1, n + 1, 3))
            p[..., axis], p[..., (axis + 1) % 3], p[..., (axis + 2) % 3] = sign, u, v
            vertices.append(p.reshape(-1, 3))
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            a = count + i * (n + 1) + j
            quads = np.stack([a, a + n + 1, a + n + 2, a + 1], axis=-1).reshape(-1, 4)
            tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
            faces.append(tri if sign > 0 else tri[:, ::-1])
            count += (n + 1) ** 2
    welded, index = np.unique(np.round(np.concatenate(vertices) * 1e6).astype(np.int64), axis=0, return_inverse=True)
    return SurfaceMesh(welded / 1e6, index.ravel()[np.concatenate(faces)])


def test_a_cube_keeps_its_corners_edges_and_volume():
    """Each merged vertex sits where the planes around it meet: on a side, an edge, or the corner itself (averaging
    the vertices would round the corners off and shrink the cube)."""
    cube = tessellated_cube()
    assert cube.is_watertight() and len(cube.faces) == 19200
    small = simplify(cube, 1000)
    assert 900 <= len(small.faces) <= 1000 and small.is_watertight()
    np.testing.assert_allclose(np.abs(small.vertices).max(axis=1), 1.0, atol=1e-6)  # every vertex on the surface
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
    assert np.linalg.norm(corners[:, None] - small.vertices[None], axis=-1).min(axis=1).max() < 1e-6
    assert small.volume() == pytest.approx(8.0, rel=1e-6)


def test_a_sphere_stays_on_its_surface_with_its_colours():
    n = 96
    x = np.linspace(-1.3, 1.3, n)
    grid = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1)
    vertices, faces = marching_tetrahedra(np.linalg.norm(grid, axis=-1) - 1.0, 0.0, origin=(-1.3,) * 3, spacing=x[1] - x[0])
    sphere = SurfaceMesh(vertices, faces, (vertices + 1.0) / 2.0)  # colour: a function of position
    small = simplify(sphere, 3000)
    assert 0.9 * 3000 <= len(small.faces) <= 3000 < len(sphere.faces)
    assert np.abs(np.linalg.norm(small.vertices, axis=1) - 1.0).max() < 0.005  # cells about 0.15 across
    assert small.area() == pytest.approx(4 * np.pi, rel=0.01)
    np.testing.assert_allclose(small.colors, (small.vertices + 1.0) / 2.0, atol=0.01)  # the merged vertices' mean colour


def test_a_mesh_already_small_enough_is_returned_and_bad_targets_are_refused():
    cube = tessellated_cube(4)
    assert simplify(cube, len(cube.faces)) is cube
    for bad in (0, -3, 2.5):
        with pytest.raises(MeshingError, match="whole number of at least 1"):
            simplify(cube, bad)
    with pytest.raises(MeshingError, match="keeps a face"):
        simplify(cube, 1)  # no grid leaves a single triangle of a cube
