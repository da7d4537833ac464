"""Depth fusion (mlx3d.meshing.fusion) against surfaces known exactly.

Oracles: depth maps ray-traced analytically from a sphere (radius, volume, colour
of the mesh against the sphere's), space no camera saw (no triangles there),
a floater seen by one view against many that see through it, and the
connected pieces of two separate spheres.

Fusion is numpy; the median depth it renders from splats is tested on the pure
MLX path and the kernels alike in ``test_surfels.py``, so ``make test-pure``
skips this module (``runs_no_kernel``).
"""

from __future__ import annotations

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.meshing import DepthView, MeshingError, fuse_depth_maps, keep_large_components, marching_tetrahedra
from mlx3d.meshing.fusion import fusion_grid, is_surfel_model, orbit_cameras
from core_marks import runs_no_kernel

pytestmark = runs_no_kernel


def sphere_view(camera, centre=(0.0, 0.0, 0.0), radius=1.0):
    """A DepthView of a sphere ray-traced from ``camera`` (inf where the ray misses), coloured by its normal."""
    origins, dirs = camera.rays()
    o = np.broadcast_to(origins, dirs.shape) - np.asarray(centre)
    b = np.sum(o * dirs, axis=-1)
    disc = b * b - (np.sum(o * o, axis=-1) - radius * radius)
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    normal = (o + dirs * t[..., None]) / radius
    z = np.asarray(camera.world_to_camera(np.asarray(centre) + o + dirs * t[..., None]))[..., 2]
    color = np.where(hit[..., None], 0.5 + 0.5 * normal, 0.0)
    return DepthView(camera, np.where(hit, z, np.inf), color)


def ring_cameras(count, elevations, distance=3.0, size=(96, 72), seed=0):
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(count):
        az, el = 2 * np.pi * (i / count) * 2.3 + rng.uniform(0, 0.1), np.radians(rng.uniform(*elevations))
        eye = distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cams.append(Camera.look_at(eye, up=(0.0, 0.0, 1.0), fov=45, width=size[0], height=size[1]))
    return cams


def test_a_sphere_seen_from_all_round_becomes_a_closed_sphere_with_its_colours():
    views = [sphere_view(c) for c in ring_cameras(40, (-65, 65))]
    mesh = fuse_depth_maps(views, resolution=64)
    voxel = fusion_grid(views, 64).voxel
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert mesh.is_watertight()
    assert np.abs(r - 1.0).mean() < 0.15 * voxel and np.abs(r - 1.0).max() < 1.0 * voxel
    assert abs(mesh.volume() / (4 / 3 * np.pi) - 1.0) < 0.02  # faces face outwards: positive volume
    np.testing.assert_allclose(mesh.colors, 0.5 + 0.5 * mesh.vertices / r[:, None], atol=0.03)


def test_space_no_camera_saw_stays_empty():
    """Cameras only above the sphere: the mesh is the seen cap, open, not closed by a blob beneath."""
    views = [sphere_view(c) for c in ring_cameras(30, (40, 70))]
    mesh = fuse_depth_maps(views, resolution=64)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - 1.0).max() < 0.05
    assert mesh.vertices[:, 2].min() > -0.5  # the lowest point any camera sees is at z = -sin(40 deg)... of the far side: above -0.65
    assert not mesh.is_watertight()


def test_a_floater_one_view_sees_is_carved_by_the_views_that_see_through_it():
    cams = ring_cameras(24, (-40, 40))
    views = [sphere_view(c) for c in cams]
    floater = sphere_view(cams[0], centre=np.asarray(cams[0].center) * 0.5, radius=0.15)  # halfway to the camera
    views[0] = DepthView(cams[0], np.minimum(views[0].depth, floater.depth), views[0].color)
    mesh = fuse_depth_maps(views, resolution=64, bounds=[[-1.6] * 3, [1.6] * 3])
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1.0).max() < 0.06  # nothing but the sphere


def test_a_far_backdrop_stays_out_of_the_volume():
    """Where the rays miss the sphere they hit a backdrop 40 units away (as training's far shell): the volume
    stays near the cameras, so the sphere keeps its voxels."""
    views = []
    for c in ring_cameras(30, (-60, 60)):
        near = sphere_view(c)
        origins, dirs = c.rays()
        o = np.broadcast_to(origins, dirs.shape)
        b = np.sum(o * dirs, axis=-1)
        t = -b + np.sqrt(b * b - (np.sum(o * o, axis=-1) - 1600.0))  # from inside the big sphere: its far side
        far_z = np.asarray(c.world_to_camera(o + dirs * t[..., None]))[..., 2]
        views.append(DepthView(c, np.where(np.isfinite(near.depth), near.depth, far_z)))
    grid = fusion_grid(views, 64)
    assert grid.voxel < 0.1
    mesh = fuse_depth_maps(views, resolution=64)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1.0).max() < 2 * grid.voxel


def test_an_object_on_a_floor_keeps_the_voxels_of_the_object_alone():
    """A sphere resting above an endless floor, seen from above all round (a statue on the ground): the floor
    fills the edges of every photo out to the horizon, but the volume holds what the views share, so the
    sphere comes out about as fine as with no floor at all."""
    cams = ring_cameras(40, (8, 65), size=(120, 90))
    views = []
    for c in cams:
        alone = sphere_view(c)
        origins, dirs = c.rays()
        o = np.broadcast_to(origins, dirs.shape)
        down = dirs[..., 2] < -1e-9
        t = np.where(down, (-1.1 - o[..., 2]) / np.where(down, dirs[..., 2], -1.0), np.inf)
        floor_z = np.asarray(c.world_to_camera(o + dirs * np.where(down, t, 0.0)[..., None]))[..., 2]
        views.append(DepthView(c, np.where(np.isfinite(alone.depth), alone.depth, np.where(down, floor_z, np.inf))))
    alone = fusion_grid([sphere_view(c) for c in cams], 64).voxel
    voxel = fusion_grid(views, 64).voxel
    assert voxel < 2.5 * alone  # the floor near the sphere only (all the framed floor: 9x)
    mesh = fuse_depth_maps(views, resolution=64)
    on_sphere = mesh.vertices[mesh.vertices[:, 2] > -1.0]
    assert np.abs(np.linalg.norm(on_sphere, axis=1) - 1.0).mean() < 0.2 * voxel < 0.015


def test_a_box_given_by_hand_is_meshed_as_given():
    """Bounds set by hand (a box around a statue, above its floor): the surface inside them, cut at the walls,
    none of the truncation band beyond; the default bounds keep that band, so nothing is cut short."""
    views = [sphere_view(c) for c in ring_cameras(30, (-60, 60))]
    box = np.array([[-1.5, -1.5, 0.25], [1.5, 0.4, 1.5]])
    mesh = fuse_depth_maps(views, resolution=64, bounds=box)
    assert (mesh.vertices >= box[0] - 1e-6).all() and (mesh.vertices <= box[1] + 1e-6).all()
    assert mesh.vertices[:, 2].min() < 0.25 + 0.05 and mesh.vertices[:, 1].max() > 0.4 - 0.05  # up to both walls
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1.0).max() < 0.05
    whole = fuse_depth_maps(views, resolution=64)
    assert whole.vertices[:, 2].min() < -0.95 and whole.vertices[:, 1].max() > 0.95


def test_small_pieces_are_dropped_by_their_share_of_the_largest():
    cams = ring_cameras(30, (-60, 60), distance=5.0)
    views = []
    for c in cams:  # a big sphere and a small one beside it, the nearer surface per pixel
        a, b = sphere_view(c), sphere_view(c, centre=(2.0, 0.0, 0.0), radius=0.3)
        views.append(DepthView(c, np.minimum(a.depth, b.depth)))
    mesh = fuse_depth_maps(views, resolution=96)
    both = keep_large_components(mesh, 0.0)
    big = keep_large_components(mesh, 0.5)
    assert len(both.faces) == len(mesh.faces)
    assert (both.vertices[:, 0] > 1.5).any() and not (big.vertices[:, 0] > 1.5).any()
    assert big.is_watertight() and len(big.faces) < len(mesh.faces)
    with pytest.raises(MeshingError, match="min_fraction"):
        keep_large_components(mesh, 2.0)


def test_marching_skips_cubes_with_an_unknown_corner():
    g = np.indices((6, 6, 6)).astype(np.float32)
    values = 2.5 - np.abs(g - 2.5).max(axis=0)  # a box
    mask = np.ones(values.shape, bool)
    _, closed = marching_tetrahedra(values, 1.0)
    mask[:, :, 4:] = False
    vertices, faces = marching_tetrahedra(values, 1.0, mask=mask)
    assert 0 < len(faces) < len(closed) and vertices[:, 2].max() <= 3.0
    with pytest.raises(ValueError, match="mask"):
        marching_tetrahedra(values, 1.0, mask=mask[:-1])


def test_bad_depth_maps_are_refused_by_name():
    cam = Camera.look_at((0, -3, 0), up=(0, 0, 1), fov=45, width=8, height=6)
    with pytest.raises(MeshingError, match="depth must be"):
        DepthView(cam, np.ones((5, 8)))
    with pytest.raises(MeshingError, match="negative"):
        DepthView(cam, -np.ones((6, 8)))
    with pytest.raises(MeshingError, match="none of the 1 depth maps sees a surface"):
        fuse_depth_maps([DepthView(cam, np.full((6, 8), np.inf))])
    with pytest.raises(MeshingError, match="no depth maps"):
        fuse_depth_maps([])


def disc_ball(count=6000, color=(0.9, 0.2, 0.1)):
    """A GaussianModel of discs tangent to the unit sphere."""
    from mlx3d.splatting import GaussianModel

    d = np.random.default_rng(0).normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m = GaussianModel.from_points(d.astype(np.float32), np.tile(color, (count, 1)), sh_degree=0, initial_opacity=0.9)
    q = np.concatenate([1.0 + d[:, 2:3], -d[:, 1:2], d[:, 0:1], np.zeros((count, 1))], axis=1)  # local z onto the radius
    m.params["quats"] = mx.array(q.astype(np.float32))
    m.params["scales"] = mx.array(np.log(np.tile([0.04, 0.04, 1e-3], (count, 1))).astype(np.float32))
    return m


def test_a_splat_ball_fuses_into_the_sphere_it_covers():
    """Median depth finds the front discs where the far side shows through gaps between them; the mean
    depth of everything on the ray does not."""
    model = disc_ball()
    assert is_surfel_model(model)
    cameras = ring_cameras(30, (-65, 65), distance=4.0, size=(96, 72))
    mesh = model.fused_mesh(cameras, resolution=64)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert mesh.is_watertight() and np.abs(r - 1.0).mean() < 0.01 and np.abs(r - 1.0).max() < 0.04
    np.testing.assert_allclose(np.median(mesh.colors, axis=0), [0.9, 0.2, 0.1], atol=0.02)
    expected = model.fused_mesh(cameras, resolution=64, depth="expected")
    assert np.abs(np.linalg.norm(expected.vertices, axis=1) - 1.0).max() > 0.2
    around = orbit_cameras(model, count=8, size=64)
    assert all(np.linalg.norm(c.center) > 3.0 for c in around)
    assert all(np.all(np.isfinite(c.project_points(np.zeros((1, 3)))[0])) for c in around)
    calls = []
    mesh = model.fused_mesh(cameras[:4], resolution=16, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (12, 12) and [d for d, _ in calls] == list(range(1, 13))
