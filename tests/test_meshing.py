"""Poisson surface reconstruction (mlx3d.meshing) against analytic shapes.

Oracles: exact area / volume / Euler characteristic of spheres and tori, the
exact volume of the piecewise-linear superlevel set for marching tetrahedra,
and invariance of the result under translation, scaling, reordering and
rescaled weights / normals.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mlx3d.errors import Mlx3dError
from mlx3d.meshing import DEFAULT_TRIM, MeshingError, SurfaceMesh, marching_tetrahedra, reconstruct_surface
from mlx3d.meshing.poisson import STAGES
from mlx3d.neighbors import kth_knn_distance


# --------------------------------------------------------------------------- #
# samples
# --------------------------------------------------------------------------- #
def sphere_samples(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n uniform random points on the unit sphere and their areas (4 pi / n)."""
    v = np.random.default_rng(seed).standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.full(n, 4.0 * np.pi / n)


def torus_samples(n: int, big: float, small: float, seed: int = 1):
    """n points uniform by area on a torus around z; (points, normals, areas)."""
    rng = np.random.default_rng(seed)
    u = rng.random(n) * 2.0 * np.pi
    tube: list[np.ndarray] = []
    while sum(map(len, tube)) < n:  # area density of the tube angle ~ (R + r cos v)
        v = rng.random(n) * 2.0 * np.pi
        tube.append(v[rng.random(n) * (big + small) < big + small * np.cos(v)])
    v = np.concatenate(tube)[:n]
    normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    centre = np.stack([big * np.cos(u), big * np.sin(u), np.zeros(n)], axis=1)
    area = 4.0 * np.pi**2 * big * small
    return centre + small * normals, normals, np.full(n, area / n)


def voxel_of(points: np.ndarray, resolution: int, padding: float = 0.1) -> float:
    extent = float((points.max(0) - points.min(0)).max())
    return extent * (1.0 + 2.0 * padding) / resolution


def hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    return float(max(kth_knn_distance(a, 1, b).max(), kth_knn_distance(b, 1, a).max()))


def boundary_edge_count(mesh: SurfaceMesh) -> int:
    f = mesh.faces.astype(np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


@pytest.fixture(scope="module")
def sphere128():
    pts, area = sphere_samples(30_000)
    return pts, reconstruct_surface(pts, pts, area, resolution=128)


# --------------------------------------------------------------------------- #
# SurfaceMesh
# --------------------------------------------------------------------------- #
def octahedron() -> SurfaceMesh:
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    faces = []
    for x, y, z in itertools.product((0, 1), (2, 3), (4, 5)):
        tri = [x, y, z]
        if np.linalg.det(v[tri]) < 0:  # counter-clockwise seen from outside
            tri = [x, z, y]
        faces.append(tri)
    return SurfaceMesh(v, np.array(faces))


def test_surface_mesh_measures_of_an_octahedron():
    m = octahedron()
    assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32 and m.colors is None
    assert m.area() == pytest.approx(8 * np.sqrt(3) / 2, rel=1e-6)
    assert m.volume() == pytest.approx(4.0 / 3.0, rel=1e-6)
    assert m.is_watertight() and m.euler_characteristic() == 2
    normals = m.vertex_normals()
    assert normals.dtype == np.float32
    np.testing.assert_allclose(normals, m.vertices, atol=1e-6)

    flipped = SurfaceMesh(m.vertices, m.faces[:, ::-1])
    assert flipped.volume() == pytest.approx(-4.0 / 3.0, rel=1e-6)
    assert flipped.is_watertight()  # consistently inward is still closed
    assert not SurfaceMesh(m.vertices, m.faces[1:]).is_watertight()  # a hole
    mixed = m.faces.copy()
    mixed[0] = mixed[0, ::-1]  # one face against its neighbours
    assert not SurfaceMesh(m.vertices, mixed).is_watertight()
    doubled = np.concatenate([m.faces, m.faces])  # each edge used four times
    assert not SurfaceMesh(m.vertices, doubled).is_watertight()
    assert not SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), int)).is_watertight()


def test_surface_mesh_rejects_mismatched_colors():
    m = octahedron()
    with pytest.raises(ValueError, match="colors"):
        SurfaceMesh(m.vertices, m.faces, np.zeros((5, 3)))


# --------------------------------------------------------------------------- #
# marching tetrahedra
# --------------------------------------------------------------------------- #
def pl_superlevel_volume(values: np.ndarray, level: float) -> float:
    """Exact volume of {f > level} for the linear interpolant on the Kuhn tetrahedra.

    On a simplex the fraction of volume where a linear f exceeds L is
    sum_i (f_i - L)_+^3 / prod_{j != i} (f_i - f_j) (distinct f_i).
    """
    f = values.astype(np.float64)
    nx, ny, nz = f.shape
    corner = {}
    for c in range(8):
        x, y, z = c & 1, c >> 1 & 1, c >> 2 & 1
        corner[c] = f[x : nx - 1 + x, y : ny - 1 + y, z : nz - 1 + z]
    total = 0.0
    for a, b, _ in itertools.permutations(range(3)):
        vals = [corner[0], corner[1 << a], corner[(1 << a) | (1 << b)], corner[7]]
        frac = 0.0
        for i in range(4):  # outside corners contribute 0 (equal values allowed there)
            above = vals[i] > level
            num = np.where(above, vals[i] - level, 0.0) ** 3
            den = np.prod([vals[i] - vals[j] for j in range(4) if j != i], axis=0)
            frac = frac + num / np.where(above, den, 1.0)
        total += float(frac.sum()) / 6.0
    return total


def test_marching_tetrahedra_single_node_is_a_closed_star():
    f = np.zeros((5, 5, 5), np.float32)
    f[2, 2, 2] = 1.0
    v, faces = marching_tetrahedra(f, 0.5, origin=(1.0, 2.0, 3.0), spacing=2.0)
    m = SurfaceMesh(v, faces)
    # 14 lattice edges leave a node of the Kuhn split, 24 tetrahedra share it
    assert len(v) == 14 and len(faces) == 24
    assert m.is_watertight() and m.euler_characteristic() == 2
    assert m.volume() == pytest.approx(0.5 * 2.0**3, rel=1e-6)  # star volume 4, scaled by 1/2
    np.testing.assert_allclose(v.mean(0), [1 + 4, 2 + 4, 3 + 4], atol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_marching_tetrahedra_random_field_matches_exact_volume(seed):
    rng = np.random.default_rng(seed)
    f = rng.standard_normal((11, 12, 13)).astype(np.float32)
    for axis in range(3):  # closed: the boundary layer is outside
        idx = [slice(None)] * 3
        idx[axis] = [0, -1]
        f[tuple(idx)] = -3.0
    v, faces = marching_tetrahedra(f, 0.25)
    m = SurfaceMesh(v, faces)
    assert m.is_watertight()
    assert np.linalg.norm(m.face_normals(), axis=1).min() > 0  # no degenerate triangle
    assert m.volume() == pytest.approx(pl_superlevel_volume(f, 0.25), rel=1e-4)
    # negated field: the same surface, seen from the other side
    v2, faces2 = marching_tetrahedra(-f, -0.25)
    flipped = SurfaceMesh(v2, faces2)
    assert np.array_equal(np.sort(v2, axis=0), np.sort(v, axis=0)) and len(faces2) == len(faces)
    assert flipped.volume() == pytest.approx(-m.volume(), rel=1e-9)


def test_marching_tetrahedra_values_equal_to_level():
    # integer field: many nodes exactly at the level
    x, y, z = np.meshgrid(*[np.arange(-6, 7)] * 3, indexing="ij")
    f = (16 - (x * x + y * y + z * z)).astype(np.float32)
    v, faces = marching_tetrahedra(f, 0.0)
    m = SurfaceMesh(v, faces)
    assert m.is_watertight() and m.euler_characteristic() == 2
    assert np.linalg.norm(m.face_normals(), axis=1).min() > 0
    r = np.linalg.norm(v - 6.0, axis=1)
    assert np.abs(r - 4.0).max() < 0.6


def test_marching_tetrahedra_open_at_grid_boundary_and_empty():
    f = np.random.default_rng(0).standard_normal((6, 6, 6)).astype(np.float32)
    v, faces = marching_tetrahedra(f, 0.0)
    assert len(faces) and not SurfaceMesh(v, faces).is_watertight()
    v, faces = marching_tetrahedra(np.zeros((4, 4, 4)), 1.0)
    assert v.shape == (0, 3) and faces.shape == (0, 3)
    with pytest.raises(ValueError, match="3D grid"):
        marching_tetrahedra(np.zeros((4, 4)), 0.0)


# --------------------------------------------------------------------------- #
# reconstruction: closed surfaces
# --------------------------------------------------------------------------- #
def test_sphere_is_watertight_and_accurate(sphere128):
    pts, m = sphere128
    h = voxel_of(pts, 128)
    assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32 and m.colors is None
    assert m.is_watertight()
    assert m.euler_characteristic() == 2
    assert m.area() == pytest.approx(4.0 * np.pi, rel=0.01)
    assert m.volume() == pytest.approx(4.0 / 3.0 * np.pi, rel=0.01)
    r = np.linalg.norm(m.vertices, axis=1)
    assert np.abs(r - 1.0).max() < 0.5 * h


def test_sphere_faces_point_outward(sphere128):
    _, m = sphere128
    fn = m.face_normals()
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    centroid = m.vertices[m.faces].mean(axis=1)
    radial = centroid / np.linalg.norm(centroid, axis=1, keepdims=True)
    dots = (fn * radial).sum(axis=1)
    assert m.volume() > 0
    assert dots.mean() > 0.9 and (dots > 0).mean() > 0.99
    vn = m.vertex_normals()
    np.testing.assert_allclose(np.linalg.norm(vn, axis=1), 1.0, atol=1e-5)
    vr = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    dots = (vn * vr).sum(axis=1)
    assert dots.min() > 0.8 and np.median(dots) > 0.999


def test_inward_normals_give_the_outside_orientation():
    pts, area = sphere_samples(8_000)
    m = reconstruct_surface(pts, -pts, area, resolution=48)
    # normals pointing to the centre: the "solid" is the outside, faces point inward
    assert m.volume() < 0


def test_torus_is_watertight_with_genus_one():
    big, small = 1.0, 0.35
    pts, nrm, area = torus_samples(40_000, big, small)
    m = reconstruct_surface(pts, nrm, area, resolution=128)
    assert m.is_watertight()
    assert m.euler_characteristic() == 0
    assert m.area() == pytest.approx(4.0 * np.pi**2 * big * small, rel=0.01)
    assert m.volume() == pytest.approx(2.0 * np.pi**2 * big * small**2, rel=0.01)
    h = voxel_of(pts, 128)
    rho = np.hypot(m.vertices[:, 0], m.vertices[:, 1])
    tube = np.hypot(rho - big, m.vertices[:, 2])
    assert np.abs(tube - small).max() < 0.5 * h


def test_weights_compensate_uneven_sampling():
    rng = np.random.default_rng(3)
    chunks, count = [], 0
    while count < 20_000:  # density ~ 1 + 0.9 z: twice as dense on top
        v = rng.standard_normal((20_000, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v = v[rng.random(len(v)) * 1.9 < 1.0 + 0.9 * v[:, 2]]
        chunks.append(v)
        count += len(v)
    pts = np.concatenate(chunks)[:20_000]
    h = voxel_of(pts, 64)
    weighted = reconstruct_surface(pts, pts, 1.0 / (1.0 + 0.9 * pts[:, 2]), resolution=64)
    uniform = reconstruct_surface(pts, pts, None, resolution=64)
    err_w = np.abs(np.linalg.norm(weighted.vertices, axis=1) - 1.0).max()
    err_u = np.abs(np.linalg.norm(uniform.vertices, axis=1) - 1.0).max()
    assert err_w < 0.5 * h
    assert err_u > 1.0 * h  # ignoring the density pulls the surface toward the sparse side


# --------------------------------------------------------------------------- #
# open surfaces and trimming
# --------------------------------------------------------------------------- #
def test_plane_patch_is_trimmed_to_the_samples():
    rng = np.random.default_rng(2)
    n, side, res = 20_000, 1.0, 96
    pts = np.column_stack([rng.random((n, 2)) * side - 0.5 * side, np.full(n, 0.25)])
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    h = voxel_of(pts, res)
    m = reconstruct_surface(pts, nrm, resolution=res)
    assert len(m.faces) > 0
    assert np.abs(m.vertices[:, 2] - 0.25).max() < h
    assert boundary_edge_count(m) > 0 and not m.is_watertight()
    # every kept vertex is near a sample, and the mesh covers the patch plus a
    # band of at most DEFAULT_TRIM voxels (area of the square's d-neighbourhood)
    assert kth_knn_distance(pts, 1, m.vertices).max() <= DEFAULT_TRIM * h * (1 + 1e-5)
    d = DEFAULT_TRIM * h
    assert side**2 + 4 * side * (d - 2 * h) < m.area() < side**2 + 4 * side * d + np.pi * d * d
    # no unreferenced vertices after trimming
    assert np.array_equal(np.unique(m.faces), np.arange(len(m.vertices)))

    untrimmed = reconstruct_surface(pts, nrm, resolution=res, trim=0)
    box = side * 1.2  # the solve continues the patch to the (padded) box boundary
    assert untrimmed.area() > (box - 2 * h) ** 2
    assert len(reconstruct_surface(pts, nrm, resolution=res, trim=None).faces) == len(untrimmed.faces)


def test_default_trim_keeps_closed_surfaces(sphere128):
    pts, m = sphere128
    untrimmed = reconstruct_surface(pts, pts, np.full(len(pts), 1.0), resolution=128, trim=0)
    assert len(untrimmed.faces) == len(m.faces)


# --------------------------------------------------------------------------- #
# invariances
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def torus48():
    pts, nrm, area = torus_samples(12_000, 1.0, 0.4, seed=5)
    return pts, nrm, area, reconstruct_surface(pts, nrm, area, resolution=48)


def test_translation_and_scale_move_the_mesh(torus48):
    pts, nrm, area, m = torus48
    s, t = 2.5, np.array([10.0, -3.0, 7.0])
    moved = reconstruct_surface(pts * s + t, nrm, area * s * s, resolution=48)
    h = voxel_of(pts, 48)
    assert hausdorff(moved.vertices, m.vertices * s + t) < 1e-3 * s * h
    assert moved.area() == pytest.approx(m.area() * s * s, rel=1e-5)
    assert moved.volume() == pytest.approx(m.volume() * s**3, rel=1e-5)


def test_order_weight_scale_and_normal_length_do_not_matter(torus48):
    pts, nrm, area, m = torus48
    perm = np.random.default_rng(0).permutation(len(pts))
    other = reconstruct_surface(pts[perm], 3.0 * nrm[perm], 7.0 * area[perm], resolution=48)
    h = voxel_of(pts, 48)
    assert hausdorff(other.vertices, m.vertices) < 1e-3 * h
    assert other.area() == pytest.approx(m.area(), rel=1e-5)


# --------------------------------------------------------------------------- #
# colours
# --------------------------------------------------------------------------- #
def test_colors_follow_the_nearest_samples():
    pts, area = sphere_samples(20_000, seed=4)
    red, blue = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    colors = np.where(pts[:, 2:3] > 0, red, blue)
    m = reconstruct_surface(pts, pts, area, colors=colors, resolution=64)
    assert m.colors is not None and m.colors.shape == m.vertices.shape
    assert m.colors.dtype == np.float32
    assert m.colors.min() >= 0.0 and m.colors.max() <= 1.0
    z = m.vertices[:, 2]
    np.testing.assert_allclose(m.colors[z > 0.1], np.broadcast_to(red, (int((z > 0.1).sum()), 3)), atol=1e-6)
    np.testing.assert_allclose(m.colors[z < -0.1], np.broadcast_to(blue, (int((z < -0.1).sum()), 3)), atol=1e-6)
    # near the equator the colour is a blend, redder above
    band = np.abs(z) < 0.1
    assert np.corrcoef(z[band], m.colors[band, 0] - m.colors[band, 2])[0, 1] > 0.5
    # geometry does not depend on the colours
    plain = reconstruct_surface(pts, pts, area, resolution=64)
    assert np.array_equal(plain.vertices, m.vertices) and plain.colors is None


# --------------------------------------------------------------------------- #
# bad input
# --------------------------------------------------------------------------- #
P, _ = sphere_samples(200, seed=9)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(points=np.zeros((0, 3)), normals=np.zeros((0, 3))), "no oriented points"),
        (dict(points=np.where(np.arange(200)[:, None] == 7, np.nan, P)), r"points has 1 of 200 rows with NaN or Inf \(first at row 7\)"),
        (dict(points=np.where(np.arange(200)[:, None] == 3, np.inf, P)), "points has 1 of 200 rows with NaN or Inf"),
        (dict(normals=np.where(np.arange(200)[:, None] < 2, np.nan, P)), "normals has 2 of 200 rows with NaN"),
        (dict(normals=np.where(np.arange(200)[:, None] % 50 == 0, 0.0, P)), r"normals has 4 of 200 rows of zero length \(first at row 0\)"),
        (dict(normals=P[:-1]), r"normals must have shape \(N, 3\) with N = 200"),
        (dict(points=P[:, :2]), r"points must have shape \(N, 3\)"),
        (dict(points=P.astype(str)), "points must be a real numeric array"),
        (dict(weights=np.ones(199)), r"weights must have shape \(N,\)"),
        (dict(weights=-np.ones(200)), "weights has 200 negative"),
        (dict(weights=np.zeros(200)), "weights are all zero"),
        (dict(weights=np.where(np.arange(200) == 5, np.nan, 1.0)), "weights has 1 of 200 rows with NaN"),
        (dict(colors=np.full((200, 3), 255.0)), r"colors must lie in \[0, 1\].*255"),
        (dict(colors=np.ones((200, 4))), r"colors must have shape \(N, 3\)"),
        (dict(resolution=7), r"resolution must be in \[8, 512\].*got 7"),
        (dict(resolution=513), r"resolution must be in \[8, 512\]"),
        (dict(resolution=64.0), "resolution must be an integer"),
        (dict(resolution=True), "resolution must be an integer"),
        (dict(padding=-0.1), "padding must be a finite number >= 0"),
        (dict(padding=np.nan), "padding must be a finite number >= 0"),
        (dict(trim=-1.0), "trim must be a finite number of voxels >= 0"),
        (dict(trim="2"), "trim must be a number of voxels"),
        (dict(progress=3), "progress must be a callable"),
        (dict(points=np.tile([1.0, 2.0, 3.0], (200, 1))), "span no volume or area"),
    ],
)
def test_bad_input_raises_meshing_error(kwargs, match):
    args = dict(points=P, normals=P)
    args.update(kwargs)
    with pytest.raises(MeshingError, match=match) as info:
        reconstruct_surface(**args)
    assert isinstance(info.value, ValueError) and isinstance(info.value, Mlx3dError)


# --------------------------------------------------------------------------- #
# progress and cancellation
# --------------------------------------------------------------------------- #
def test_progress_reports_each_stage():
    pts, area = sphere_samples(2_000)
    calls = []
    reconstruct_surface(pts, pts, area, colors=np.full((2_000, 3), 0.5), resolution=16,
                        progress=lambda d, t: calls.append((d, t)))
    assert calls == [(i, len(STAGES)) for i in range(len(STAGES) + 1)]


class Cancelled(Exception):
    pass


@pytest.mark.parametrize("stop_at", [0, 3, len(STAGES)])
def test_progress_exception_cancels(stop_at):
    pts, area = sphere_samples(2_000)
    seen = []
    err = Cancelled("user cancelled")

    def progress(done, total):
        seen.append(done)
        if done == stop_at:
            raise err

    with pytest.raises(Cancelled) as info:
        reconstruct_surface(pts, pts, area, resolution=16, progress=progress)
    assert info.value is err
    assert seen == list(range(stop_at + 1))
