"""Meshes of non-convex surfaces from oriented surfels, against analytic volume and area.

A torus (R = 1, r = 0.35: volume 2π²Rr², area 4π²Rr, genus 1) and a closed box seen from inside
(a room: normals point inward, so the mesh is the box with faces turned inward and signed volume
-V) are sampled with discs whose local z axis is the surface normal. The quaternions are built here
from the normals (half-angle formula), independently of mlx3d.transforms.

Each case is meshed with the normals the quaternions give (``orient_towards=None``) and, with the
discs' signs randomised, with ``orient_towards`` (camera centres around the torus; the centre of
the room). A control reconstruction with normals turned away from the samples' centroid (the rule
mlx3d used before) shows the comparison catches wrong orientation: +40 % volume on the torus, the
wrong sign for the room.

Tolerances: volume 2 % and area 2 % for the torus at resolution 64 (measured error < 0.2 %); for
the box volume 1 %, and area 6 %: the solver's 1-voxel smoothing rounds the 12 edges (measured -4.5 %).
"""

import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.meshing import reconstruct_surface
from mlx3d.splatting import GaussianModel
from mlx3d.structures import Meshes

R, r = 1.0, 0.35
TORUS_VOLUME, TORUS_AREA = 2 * math.pi**2 * R * r * r, 4 * math.pi**2 * R * r
BOX = np.array([2.0, 1.5, 1.0])
BOX_CENTRE = np.array([0.3, -0.2, 0.1])
BOX_VOLUME, BOX_AREA = float(BOX.prod()), float(2 * (BOX[0] * BOX[1] + BOX[1] * BOX[2] + BOX[0] * BOX[2]))
RESOLUTION = 64


def quats_z_to(normals):
    """(N,4) w,x,y,z quaternions whose rotation takes +z onto each unit normal (half-angle formula)."""
    n = np.asarray(normals, np.float64)
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)
    down = 1.0 + n[:, 2] < 1e-9  # -z: half a turn about x
    q[down] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def flip_some(quats, rng):
    """Half of the discs turned over (half a turn about their local x): their z axis is reversed."""
    flip = rng.random(len(quats)) < 0.5
    w, x, y, z = quats.T.copy()
    out = quats.copy()
    out[flip] = np.stack([-x, w, z, -y], axis=1)[flip]  # q ⊗ (0, 1, 0, 0)
    return out, np.where(flip, -1.0, 1.0)


def surfel_model(points, normals, area_per_disc, quats=None):
    n = len(points)
    s = math.sqrt(area_per_disc)
    params = {
        "means": np.asarray(points, np.float32),
        "quats": np.asarray(quats_z_to(normals) if quats is None else quats, np.float32),
        "scales": np.log(np.tile([s, s, 1e-3], (n, 1))).astype(np.float32),
        "opacities": np.full(n, 3.0, np.float32),
        "sh_dc": np.zeros((n, 1, 3), np.float32),
        "sh_rest": np.zeros((n, 0, 3), np.float32),
    }
    return GaussianModel({k: mx.array(v) for k, v in params.items()})


def torus_samples(n=12_000, seed=0):
    """Points uniform in area on the torus and their outward normals."""
    rng = np.random.default_rng(seed)
    theta, phi = np.empty(0), np.empty(0)
    while len(theta) < n:  # area element (R + r cos φ) dθ dφ: rejection on φ
        t, p = rng.uniform(0, 2 * np.pi, (2, n))
        ok = rng.uniform(0, R + r, n) < R + r * np.cos(p)
        theta, phi = np.concatenate([theta, t[ok]]), np.concatenate([phi, p[ok]])
    theta, phi = theta[:n], phi[:n]
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros(n)], axis=1)
    normals = np.cos(phi)[:, None] * radial + np.sin(phi)[:, None] * np.array([0.0, 0.0, 1.0])
    return R * radial + r * normals, normals


def torus_cameras(offset=0.5):
    """Camera centres all around the torus, on the torus of tube radius r + offset."""
    t, p = np.meshgrid(np.linspace(0, 2 * np.pi, 16, endpoint=False), np.linspace(0, 2 * np.pi, 8, endpoint=False))
    radial = np.stack([np.cos(t.ravel()), np.sin(t.ravel()), np.zeros(t.size)], axis=1)
    out = np.cos(p.ravel())[:, None] * radial + np.sin(p.ravel())[:, None] * np.array([0.0, 0.0, 1.0])
    return R * radial + (r + offset) * out


def box_samples(n=16_000, seed=0):
    """Points uniform in area on the box's faces and their inward normals (seen from inside)."""
    rng = np.random.default_rng(seed)
    areas = np.repeat([BOX[1] * BOX[2], BOX[0] * BOX[2], BOX[0] * BOX[1]], 2)
    face = rng.choice(6, size=n, p=areas / areas.sum())
    axis, side = face // 2, np.where(face % 2 == 0, -1.0, 1.0)
    points = rng.uniform(-0.5, 0.5, (n, 3)) * BOX
    points[np.arange(n), axis] = side * BOX[axis] / 2
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = -side
    return points + BOX_CENTRE, normals


def away_from_centroid(points, normals):
    """The old orientation rule: every normal turned away from the samples' centroid."""
    return normals * np.where(np.sum(normals * (points - points.mean(axis=0)), axis=1) < 0, -1.0, 1.0)[:, None]


# ------------------------------------------------------------------ torus
def test_torus_from_the_surfels_own_normals():
    points, normals = torus_samples()
    model = surfel_model(points, normals, TORUS_AREA / len(points))
    mesh = model.surface_mesh(resolution=RESOLUTION)
    assert mesh.volume() == pytest.approx(TORUS_VOLUME, rel=0.02)
    assert mesh.area() == pytest.approx(TORUS_AREA, rel=0.02)
    assert mesh.is_watertight() and mesh.euler_characteristic() == 0  # one handle
    # the same surface through mlx3D's API
    meshes = model.extract_surface_mesh(resolution=RESOLUTION)
    assert isinstance(meshes, Meshes) and meshes.surface_mesh().volume() == pytest.approx(mesh.volume(), rel=1e-6)
    # control: the centroid rule turns the inner half of the tube outward and the comparison sees it
    wrong = reconstruct_surface(points, away_from_centroid(points, normals), resolution=RESOLUTION)
    assert wrong.volume() > 1.2 * TORUS_VOLUME


def test_torus_from_flipped_surfels_oriented_towards_cameras():
    points, normals = torus_samples(seed=1)
    quats, signs = flip_some(quats_z_to(normals), np.random.default_rng(2))
    model = surfel_model(points, normals, TORUS_AREA / len(points), quats=quats)
    _, own = model.surfel_points()
    np.testing.assert_allclose(np.array(own), normals * signs[:, None], atol=1e-5)  # the discs' own (flipped) axes
    cameras = torus_cameras()
    _, towards = model.surfel_points(orient_towards=cameras)
    np.testing.assert_allclose(np.array(towards), normals, atol=1e-5)  # every one facing its nearest camera
    mesh = model.surface_mesh(resolution=RESOLUTION, orient_towards=cameras)
    assert mesh.volume() == pytest.approx(TORUS_VOLUME, rel=0.02)
    assert mesh.area() == pytest.approx(TORUS_AREA, rel=0.02)
    assert mesh.is_watertight() and mesh.euler_characteristic() == 0


# ------------------------------------------------------------------ a room seen from inside
def test_box_seen_from_inside_from_the_surfels_own_normals():
    points, normals = box_samples()
    model = surfel_model(points, normals, BOX_AREA / len(points))
    mesh = model.surface_mesh(resolution=RESOLUTION)
    assert mesh.volume() == pytest.approx(-BOX_VOLUME, rel=0.01)  # faces turned inward, towards the viewer
    assert mesh.area() == pytest.approx(BOX_AREA, rel=0.06)
    assert mesh.is_watertight() and mesh.euler_characteristic() == 2
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose(lo, BOX_CENTRE - BOX / 2, atol=0.05)
    np.testing.assert_allclose(hi, BOX_CENTRE + BOX / 2, atol=0.05)
    # control: the centroid rule turns every wall outward: a solid box, not a room
    wrong = reconstruct_surface(points, away_from_centroid(points, normals), resolution=RESOLUTION)
    assert wrong.volume() == pytest.approx(BOX_VOLUME, rel=0.01)


def test_box_from_flipped_surfels_oriented_towards_its_centre():
    points, normals = box_samples(seed=3)
    quats, _ = flip_some(quats_z_to(normals), np.random.default_rng(4))
    model = surfel_model(points, normals, BOX_AREA / len(points), quats=quats)
    _, towards = model.surfel_points(orient_towards=tuple(BOX_CENTRE))
    np.testing.assert_allclose(np.array(towards), normals, atol=1e-5)
    meshes = model.extract_surface_mesh(resolution=RESOLUTION, orient_towards=BOX_CENTRE)
    mesh = meshes.surface_mesh()
    assert mesh.volume() == pytest.approx(-BOX_VOLUME, rel=0.01)
    assert mesh.area() == pytest.approx(BOX_AREA, rel=0.06)
    assert mesh.is_watertight()
