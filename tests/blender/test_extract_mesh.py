"""Extracting a surface mesh from a splat object (``workflows.extract_mesh``, the ``mlx3d.extract_mesh``
operator, its panel section and the ``extract-mesh``/``mesh`` headless command), through the installed extension.

Oracles: the splats are flat Gaussians tangent to a unit sphere, so the mesh must lie on that sphere
mapped by the transform set on the object (composed here with ``mlx3d.transforms.compose_affine``,
not read back from Blender: an ellipsoid under a non-uniform scale, checked by the sphere's implicit
equation |x| = 1 in the object's frame); cameras that see only the top of the sphere must give no
vertex in its bottom half; closedness (Poisson) is counted from the faces; the colour attribute must hold
the splats' base colour decoded from sRGB with the IEC 61966-2-1 formula written out here.
"""

import json
import os
import subprocess
import sys
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from modal_state import ESC, KEY, MOVE, OperatorState, TIMER
from panel_layout import RecordingLayout

from mlx3d.io import SplatArrays, write_splat_ply
from mlx3d.splatting import C0
from mlx3d.transforms import compose_affine
from core_marks import above_kernels

# The add-on over mlx3d.meshing: the pure path runs the same code there, and its median depth is tested in
# tests/test_surfels.py (the default 60 views of 512 x 512 would take minutes on it).
pytestmark = above_kernels

bpy = pytest.importorskip("bpy")

SRGB = np.array([0.8, 0.3, 0.1])  # the splats' base colour, as training images hold it
LOCATION, ROTATION_DEG, SCALE = (0.5, -1.0, 2.0), (20.0, -35.0, 60.0), (1.5, 0.8, 1.2)
RESOLUTION = 48
VOXEL = 2.0 * 1.2 / RESOLUTION  # the unit sphere's extent with 10 % padding each side, over the grid


# ------------------------------------------------------------------ helpers
def sphere_splats(n=3000, opacity_logit=4.0):
    """Flat Gaussians (σ = 0.04, 0.04, 0.001) tangent to the unit sphere at Fibonacci points, all of colour ``SRGB``."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    normals = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    # the rotation taking +z onto the normal: half-way quaternion (1 + z.n, z x n), never degenerate here (n_z > -1)
    quats = np.column_stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(n)])
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return SplatArrays(
        means=normals.astype(np.float32),
        scales=np.log(np.tile([0.04, 0.04, 0.001], (n, 1))).astype(np.float32),
        quats=quats.astype(np.float32),
        opacities=np.full(n, opacity_logit, np.float32),
        sh_dc=np.tile((SRGB - 0.5) / C0, (n, 1, 1)).astype(np.float32),
        sh_rest=np.zeros((n, 0, 3), np.float32),
    )


def srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def import_splats(path, arrays=None, transform=True):
    write_splat_ply(path, arrays if arrays is not None else sphere_splats())
    assert bpy.ops.import_scene.gaussian_splat_ply(filepath=str(path)) == {"FINISHED"}
    obj = bpy.context.active_object
    if transform:
        obj.location = LOCATION
        obj.rotation_euler = tuple(np.radians(ROTATION_DEG))
        obj.scale = SCALE
        bpy.context.view_layer.update()
    return obj


def mesh_arrays(obj):
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    loops = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", loops)
    totals = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_total", totals)
    assert np.all(totals == 3), "triangles"
    return co.reshape(-1, 3).astype(np.float64), loops.reshape(-1, 3)


def boundary_edges(faces):
    """Edges used by other than exactly two faces (0 for a closed manifold surface)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts != 2).sum())


def signed_volume(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def scene_state():
    return (sorted(o.name for o in bpy.data.objects), sorted(m.name for m in bpy.data.meshes),
            sorted(m.name for m in bpy.data.materials), len(bpy.context.scene.objects))


def on_unit_sphere(obj):
    """(V,3) world vertices of ``obj`` and the same points in the splat object's frame (where the splats lie on
    the unit sphere), the transform built from the values set on the object."""
    bpy.context.view_layer.update()  # matrix_world is stale until the view layer updates
    local, faces = mesh_arrays(obj)
    world = local @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
    placed = compose_affine(np.array(SCALE), ROTATION_DEG, LOCATION)  # the transform set on the object, built independently
    return world, world @ np.linalg.inv(placed)[:3, :3].T + np.linalg.inv(placed)[:3, 3], faces


def check_mesh_object(obj, splat_obj, voxel=VOXEL):
    """The mesh object sits under the splat object, on the transformed unit sphere, coloured by the splats;
    returns (points in the splat object's frame, faces)."""
    assert obj.type == "MESH" and obj.parent == splat_obj and obj.name == f"{splat_obj.name} mesh"
    assert obj.users_collection[0] == splat_obj.users_collection[0]
    bpy.context.view_layer.update()
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(splat_obj.matrix_world), atol=1e-6)
    _, on_sphere, faces = on_unit_sphere(obj)
    radius = np.linalg.norm(on_sphere, axis=1)
    assert np.abs(radius - 1.0).max() < 2 * voxel, (radius.min(), radius.max())
    assert len(faces) > 500
    attr = obj.data.color_attributes["Color"]
    assert (attr.domain, attr.data_type) == ("POINT", "FLOAT_COLOR")
    rgba = np.empty(len(attr.data) * 4, np.float32)
    attr.data.foreach_get("color", rgba)
    rgba = rgba.reshape(-1, 4)
    np.testing.assert_allclose(rgba[:, :3], np.tile(srgb_to_linear(SRGB), (len(rgba), 1)), atol=2e-3)
    np.testing.assert_array_equal(rgba[:, 3], 1.0)
    material = obj.material_slots[0].material
    assert material.name == "MLX3D Mesh"
    return on_sphere, faces


def check_sphere_mesh(obj, splat_obj):
    """As ``check_mesh_object``, and closed with its faces wound outward (Poisson)."""
    on_sphere, faces = check_mesh_object(obj, splat_obj)
    assert boundary_edges(faces) == 0, "closed"
    assert signed_volume(on_sphere, faces) == pytest.approx(4 / 3 * np.pi, rel=0.1)  # faces wound outward
    return on_sphere, faces


def fibonacci_directions(n):
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def largest_gap(points, directions):
    """The largest distance from one of ``directions`` (unit) to the nearest point's direction."""
    unit = points / np.linalg.norm(points, axis=1, keepdims=True)
    return max(float(np.min(np.linalg.norm(unit - d, axis=1))) for d in directions)


def world_cameras(count=8, size=64):
    """mlx3d cameras on an orbit around the splats as the object places them (``GaussianModel.transform`` of
    the sphere's splats by the transform set on the object)."""
    from mlx3d.meshing.fusion import orbit_cameras
    from mlx3d.splatting import GaussianModel

    placed = compose_affine(np.array(SCALE), ROTATION_DEG, LOCATION)
    return orbit_cameras(GaussianModel.from_arrays(sphere_splats()).transform(placed), count=count, size=size)


def look_at_c2w(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    """4x4 camera-to-world pose with OpenGL axes (x right, y up, looking down -z), written out."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(right, forward), -forward, eye
    return m


def top_eyes(count=3, elevation_deg=75.0, distance=3.5):
    """Camera positions above the unit sphere: each sees only the cap above elevation
    ``elevation_deg - degrees(arccos(1 / distance))`` (1.6 degrees here), so nothing of the bottom half."""
    e = np.radians(elevation_deg)
    return [distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            for a in np.radians(np.arange(count) * 360.0 / count + 10.0)]


def camera_collection(name, eyes, size=96):
    """A collection of Blender cameras at ``eyes`` looking at the origin; the scene renders ``size`` pixels square."""
    from mathutils import Matrix

    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    collection = bpy.data.collections.new(name)
    scene.collection.children.link(collection)
    for i, eye in enumerate(eyes):
        data = bpy.data.cameras.new(f"{name} {i}")
        data.lens = 45.0
        cam = bpy.data.objects.new(f"{name} {i}", data)
        cam.matrix_world = Matrix(look_at_c2w(eye).tolist())
        collection.objects.link(cam)
    bpy.context.view_layer.update()
    return collection


# ------------------------------------------------------------------ the operator and the function
def test_operator_fuses_the_sphere_under_the_transformed_splat_object(extension, clean_scene, tmp_path):
    """What a user gets by default: depth fusion from 60 views around the splats, under a translated, rotated and
    non-uniformly scaled object (an ellipsoid in the world)."""
    splats = import_splats(tmp_path / "sphere.ply")
    before = len(bpy.data.meshes)
    assert bpy.ops.mlx3d.extract_mesh(resolution=RESOLUTION) == {"FINISHED"}
    assert len(bpy.data.meshes) == before + 1
    obj = bpy.context.scene.objects["sphere mesh"]
    assert bpy.context.active_object == obj and obj.select_get() and not splats.select_get()
    on_sphere, faces = check_mesh_object(obj, splats, voxel=2.0 * max(SCALE) / RESOLUTION)  # the seen surface's extent over the grid
    assert largest_gap(on_sphere, fibonacci_directions(200)) < 0.1, "60 views around it see all of it"
    assert signed_volume(on_sphere, faces) == pytest.approx(4 / 3 * np.pi, rel=0.05)  # faces wound outward, holes at most tiny
    assert any(p.use_smooth for p in obj.data.polygons[:10])
    # The material shows the attribute (and a capture of the mesh would read the same colours).
    assert extension.addon.capture.material_colour_source(obj.material_slots[0].material)[1] == "Color"
    # Moving the splat object carries the mesh along.
    splats.location = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(splats.matrix_world), atol=1e-6)


def test_operator_poisson_extracts_a_closed_sphere(extension, clean_scene, tmp_path):
    splats = import_splats(tmp_path / "sphere.ply")
    assert bpy.ops.mlx3d.extract_mesh(method="POISSON", resolution=RESOLUTION) == {"FINISHED"}
    obj = bpy.context.scene.objects["sphere mesh"]
    assert bpy.context.active_object == obj
    check_sphere_mesh(obj, splats)


def test_fusion_renders_from_a_collection_of_cameras(extension, clean_scene, tmp_path):
    splats = import_splats(tmp_path / "sphere.ply", transform=False)
    camera_collection("top views", top_eyes(3))
    assert bpy.ops.mlx3d.extract_mesh(cameras="top views", resolution=32, cleanup=0.0) == {"FINISHED"}
    obj = bpy.context.scene.objects["sphere mesh"]
    assert obj.parent == splats
    vertices, faces = mesh_arrays(obj)
    radius = np.linalg.norm(vertices, axis=1)
    assert np.abs(radius - 1.0).max() < 2 * 2.0 / 32 and len(faces) > 300
    assert vertices[:, 2].min() > -0.1, "nothing of the bottom half: those cameras do not see it"
    top = fibonacci_directions(400)
    assert largest_gap(vertices, top[top[:, 2] > 0.3]) < 0.1, "the cap the cameras see is meshed"

    # The workflow function names how many views it fused; the cameras may also be mlx3d cameras.
    workflows = extension.addon.workflows
    cams = sorted((o for o in bpy.data.collections["top views"].objects), key=lambda o: o.name)
    obj, messages = workflows.extract_mesh(splats, cameras=cams, resolution=32, name="by objects")
    assert messages[0].startswith("extracted 'by objects' from 'sphere' (3,000 splats, fusion of 3 views, resolution 32): ")
    camera = extension.addon.camera.camera_from_blender(cams[0], bpy.context.scene)
    other, _ = workflows.extract_mesh(splats, cameras=[camera], resolution=32, name="one view")
    assert mesh_arrays(other)[0][:, 2].min() > -0.1


def test_fusion_meshes_what_a_box_holds(extension, clean_scene, tmp_path):
    """A box object (an object standing on a floor: the box is drawn around it) sets the volume: the mesh is the
    sphere's part inside the box as placed, a cube turned a quarter about Z, moved and scaled, cut at its walls."""
    from mlx3d.meshing import MeshingError

    workflows = extension.addon.workflows
    splats = import_splats(tmp_path / "sphere.ply", transform=False)
    camera_collection("top views", top_eyes(3))
    bpy.ops.mesh.primitive_cube_add(size=2.0, location=(0.0, 0.4, 0.7), rotation=(0.0, 0.0, np.pi / 2))
    box = bpy.context.active_object
    box.name, box.scale = "box", (0.5, 2.0, 0.5)  # world: x in [-2, 2], y in [-0.1, 0.9], z in [0.2, 1.2]
    bpy.context.view_layer.objects.active = splats
    assert bpy.ops.mlx3d.extract_mesh(cameras="top views", box="box", resolution=32, cleanup=0.0) == {"FINISHED"}
    vertices, faces = mesh_arrays(bpy.context.scene.objects["sphere mesh"])  # the splat object's frame is the world's
    assert len(faces) > 100 and np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 2 * 2.0 / 32
    lo, hi = np.array([-2.0, -0.1, 0.2]), np.array([2.0, 0.9, 1.2])
    assert (vertices >= lo - 1e-5).all() and (vertices <= hi + 1e-5).all()
    assert vertices[:, 1].min() < -0.1 + 0.07 and vertices[:, 1].max() > 0.9 - 0.07 and vertices[:, 2].min() < 0.2 + 0.07
    np.testing.assert_allclose(workflows.box_world_bounds(box), [lo, hi], atol=1e-6)
    # A box name that is not there, the splat object as its own box, a box with Poisson: refused, nothing added.
    bpy.data.meshes.remove(bpy.context.scene.objects["sphere mesh"].data, do_unlink=True)
    bpy.context.view_layer.objects.active = splats
    before = scene_state()
    with pytest.raises(RuntimeError, match="no object named 'nowhere'"):
        bpy.ops.mlx3d.extract_mesh(cameras="top views", box="nowhere", resolution=16)
    with pytest.raises(RuntimeError, match="the box must be another object than the splat object"):
        bpy.ops.mlx3d.extract_mesh(cameras="top views", box="sphere", resolution=16)
    with pytest.raises(MeshingError, match="bounds set the volume of fusion"):
        workflows.extract_mesh(splats, method="poisson", bounds=[lo, hi])
    with pytest.raises(MeshingError, match="min below max"):
        workflows.extract_mesh(splats, bounds=[hi, lo])
    box.location = (0.0, 0.4, 5.0)  # the box holds no surface now
    with pytest.raises(RuntimeError, match="inside the bounds"):
        bpy.ops.mlx3d.extract_mesh(cameras="top views", box="box", resolution=16)
    assert scene_state() == before


def test_bad_cameras_are_refused_and_add_nothing(extension, clean_scene, tmp_path):
    from mlx3d.meshing import MeshingError

    workflows = extension.addon.workflows
    splats = import_splats(tmp_path / "sphere.ply", transform=False)
    empty = bpy.data.objects.new("marker", None)
    props = bpy.data.collections.new("props")
    clean_scene.collection.children.link(props)
    props.objects.link(empty)
    bpy.context.view_layer.objects.active = splats
    before = scene_state()
    with pytest.raises(RuntimeError, match="no collection named 'nowhere'"):
        bpy.ops.mlx3d.extract_mesh(cameras="nowhere", resolution=16)
    with pytest.raises(RuntimeError, match="the collection 'props' holds no camera"):
        bpy.ops.mlx3d.extract_mesh(cameras="props", resolution=16)
    with pytest.raises(MeshingError, match=r"'marker' \(empty object\) is not a camera"):
        workflows.extract_mesh(splats, cameras=[empty])
    with pytest.raises(MeshingError, match="no cameras"):
        workflows.extract_mesh(splats, cameras=[])
    with pytest.raises(MeshingError, match="unknown mesh method 'marching'"):
        workflows.extract_mesh(splats, method="marching")
    assert scene_state() == before
    # Cameras that look away from the splats: an error after rendering, still nothing added.
    camera_collection("away", [(0.0, -4.0, 0.0)], size=16)
    bpy.data.objects["away 0"].rotation_euler = (0.0, 0.0, 0.0)  # looks down -Z, past the sphere
    bpy.context.view_layer.update()
    before = scene_state()
    with pytest.raises(RuntimeError, match="cover no pixel of the 1 views"):
        bpy.ops.mlx3d.extract_mesh(cameras="away", resolution=16)
    assert scene_state() == before


def test_workflow_function_returns_the_object_and_a_report(extension, clean_scene, tmp_path):
    workflows = extension.addon.workflows
    splats = import_splats(tmp_path / "sphere.ply")
    target = bpy.data.collections.new("meshes")
    clean_scene.collection.children.link(target)
    seen = []
    cameras = world_cameras(8, 64)
    obj, messages = workflows.extract_mesh(splats, cameras=cameras, resolution=32, name="shell", collection=target,
                                           progress=lambda done, total: seen.append((done, total)))
    assert obj.name == "shell" and obj.users_collection == (target,) and obj.parent == splats
    # One report per view rendered, then the fusion's two passes over the views: 3 x 8 steps in all.
    assert seen[:8] == [(i, 24) for i in range(1, 9)] and seen[-1] == (24, 24)
    assert all(t == 24 for _, t in seen) and [d for d, _ in seen] == sorted(d for d, _ in seen)
    n_v, n_f = len(obj.data.vertices), len(obj.data.polygons)
    assert messages[0].startswith("extracted 'shell' from 'sphere' (3,000 splats, fusion of 8 views, resolution 32): ")
    assert f"{n_v:,} vertices, {n_f:,} faces in " in messages[0]
    on_sphere = on_unit_sphere(obj)[1]
    assert np.abs(np.linalg.norm(on_sphere, axis=1) - 1.0).max() < 2 * 2.0 * max(SCALE) / 32

    obj, messages = workflows.extract_mesh(splats, method="poisson", resolution=RESOLUTION, name="closed")
    assert messages[0].startswith("extracted 'closed' from 'sphere' (3,000 splats, Poisson, resolution 48): ")
    # Poisson: camera_centres are world positions: one inside the sphere turns every normal, and so the surface, inward.
    inside = compose_affine(np.array(SCALE), ROTATION_DEG, LOCATION) @ [0.0, 0.0, 0.2, 1.0]
    obj, _ = workflows.extract_mesh(splats, method="poisson", resolution=32, name="inward", camera_centres=[inside[:3]])
    assert signed_volume(*mesh_arrays(obj)) == pytest.approx(-4 / 3 * np.pi, rel=0.15)
    # Invoked without a window (background), the operator runs at once.
    bpy.context.view_layer.objects.active = splats
    assert bpy.ops.mlx3d.extract_mesh("INVOKE_DEFAULT", method="POISSON", resolution=16, trim=0.0) == {"FINISHED"}
    assert bpy.context.active_object.name == "sphere mesh" and bpy.context.active_object.parent == splats


def test_cleanup_drops_small_pieces(extension, clean_scene, tmp_path):
    """A second, smaller sphere of splats (radius 0.5, at x = 3) is a piece of about a quarter of the big one's faces."""
    from mlx3d.splatting import merge_splats

    workflows = extension.addon.workflows
    small = sphere_splats(n=1000)
    small.means[:] = small.means * 0.5 + np.array([3.0, 0.0, 0.0], np.float32)
    splats = import_splats(tmp_path / "two.ply", merge_splats([sphere_splats(), small]), transform=False)
    for cleanup, kept in [(0.0, True), (0.1, True), (0.5, False)]:
        obj, _ = workflows.extract_mesh(splats, method="poisson", resolution=48, cleanup=cleanup, name=f"cleanup {cleanup}")
        vertices = mesh_arrays(obj)[0]
        assert (np.linalg.norm(vertices - [3.0, 0.0, 0.0], axis=1) < 0.8).any() == kept
        assert (np.linalg.norm(vertices, axis=1) < 1.2).sum() > 500


def test_faces_caps_the_triangles(extension, clean_scene, tmp_path):
    """*Faces* simplifies the extracted mesh to at most that many triangles, which stay on the sphere; a count that
    is not a whole number of triangles is refused before anything is added."""
    from mlx3d.meshing import MeshingError

    workflows = extension.addon.workflows
    splats = import_splats(tmp_path / "sphere.ply", transform=False)
    full, _ = workflows.extract_mesh(splats, method="poisson", resolution=RESOLUTION, name="full")
    full_vertices, full_faces = mesh_arrays(full)
    assert len(full_faces) > 2000
    bpy.context.view_layer.objects.active = splats
    assert bpy.ops.mlx3d.extract_mesh(method="POISSON", resolution=RESOLUTION, faces=800) == {"FINISHED"}
    vertices, faces = mesh_arrays(bpy.context.scene.objects["sphere mesh"])
    assert 0.8 * 800 <= len(faces) <= 800
    error = np.abs(np.linalg.norm(full_vertices, axis=1) - 1.0).max()
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < error + 0.02
    before = scene_state()
    for bad in (-1, 2.5):
        with pytest.raises(MeshingError, match="faces must be a whole number"):
            workflows.extract_mesh(splats, method="poisson", resolution=RESOLUTION, faces=bad)
    assert scene_state() == before


# ------------------------------------------------------------------ bad input leaves the scene alone
def test_non_splat_active_object_is_refused(extension, clean_scene, tmp_path):
    workflows = extension.addon.workflows
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    before = scene_state()
    with pytest.raises(RuntimeError, match="not a splat object"):
        bpy.ops.mlx3d.extract_mesh()
    with pytest.raises(ValueError, match="'Cube' is not a splat object"):
        workflows.extract_mesh(cube)
    with pytest.raises(ValueError, match="no active object"):
        workflows.extract_mesh(None)
    assert scene_state() == before


def test_empty_or_transparent_splats_are_a_clear_error(extension, clean_scene, tmp_path):
    from mlx3d.meshing import MeshingError

    workflows = extension.addon.workflows
    transparent = sphere_splats(n=200, opacity_logit=-12.0)  # opacity 6e-6, below any threshold
    import_splats(tmp_path / "clear.ply", transparent, transform=False)
    before = scene_state()
    with pytest.raises(RuntimeError, match=r"no splat of 'clear' is opaque enough to be rendered \(opacity >= 1/255, of 200\)"):
        bpy.ops.mlx3d.extract_mesh(resolution=16)
    message = "no splat of 'clear' has opacity >= 0.01 (of 200); nothing to mesh"
    with pytest.raises(RuntimeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        bpy.ops.mlx3d.extract_mesh(method="POISSON", resolution=16)
    with pytest.raises(MeshingError, match="opacity >= 0.5"):
        workflows.extract_mesh(bpy.context.active_object, method="poisson", resolution=16, min_opacity=0.5)
    assert scene_state() == before
    # A splat object without points (all deleted).
    obj = bpy.context.active_object
    extension.addon.splat_object.replace_splats(obj, SplatArrays(
        **{k: getattr(transparent, k)[:0] for k in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")}))
    assert extension.addon.splat_object.is_splat_object(obj) and len(obj.data.points) == 0
    before = scene_state()
    for method in ("fusion", "poisson"):
        with pytest.raises(MeshingError, match="no splats"):
            workflows.extract_mesh(obj, method=method)
        with pytest.raises(RuntimeError, match="no splats"):
            bpy.ops.mlx3d.extract_mesh(method=method.upper())
    assert scene_state() == before


# ------------------------------------------------------------------ progress and cancelling
def test_a_progress_callback_that_raises_cancels_and_adds_nothing(extension, clean_scene, tmp_path):
    workflows = extension.addon.workflows
    splats = import_splats(tmp_path / "sphere.ply")
    before = scene_state()

    class Stop(Exception):
        pass

    def progress(done, total):
        raise Stop

    for method in ("fusion", "poisson"):
        with pytest.raises(Stop):
            workflows.extract_mesh(splats, method=method, cameras=world_cameras(2, 32), resolution=RESOLUTION, progress=progress)
    assert scene_state() == before
    # The worker-thread path the operator uses: cancel() makes the next progress report raise.
    for method in ("fusion", "poisson"):
        job = workflows.MeshExtraction(splats, method=method, resolution=RESOLUTION)
        job.cancel()
        job.start()
        assert job.wait(60)
        assert isinstance(job.error, workflows.ExtractionCancelled) and job.surface is None
        with pytest.raises(workflows.ExtractionCancelled, match="cancelled"):
            job.add_object()
    # The worker only fuses: it refuses views left to render (they need the main thread).
    job = workflows.MeshExtraction(splats, cameras=world_cameras(2, 32), resolution=32)
    job.start()
    assert job.wait(60) and isinstance(job.error, RuntimeError) and "2 of 2 views" in str(job.error)
    assert scene_state() == before


def test_modal_operator_polls_the_worker_and_esc_adds_nothing(extension, clean_scene, tmp_path):
    """Poisson: the worker runs from the start."""
    workflows = extension.addon.workflows
    op = extension.addon.operators.MLX3D_OT_extract_mesh
    splats = import_splats(tmp_path / "sphere.ply")
    before = scene_state()

    job = workflows.MeshExtraction(splats, method="poisson", resolution=RESOLUTION)
    assert job.views_left == 0
    state = OperatorState(op, job)
    gate = threading.Event()
    compute = job.compute
    job.compute = lambda progress=None: (gate.wait(30), compute(progress))[1]  # holds the worker until released
    job.start()
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"} and job.running
    assert op.modal(state, bpy.context, MOVE) == {"PASS_THROUGH"}  # the view can be navigated meanwhile
    assert op.modal(state, bpy.context, KEY) == {"RUNNING_MODAL"}  # other input is held back
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    gate.set()
    assert job.wait(60) and isinstance(job.error, workflows.ExtractionCancelled)
    assert state._session is None and scene_state() == before
    assert state.reports == [({"INFO"}, "mesh extraction from 'sphere' cancelled; nothing was added")]

    job = workflows.MeshExtraction(splats, method="poisson", resolution=RESOLUTION)
    state = OperatorState(op, job)
    job.start()
    assert job.wait(60)
    assert op.modal(state, bpy.context, TIMER) == {"FINISHED"}
    assert state._session is None and state.reports[0][0] == {"INFO"} and "vertices" in state.reports[0][1]
    check_sphere_mesh(bpy.context.scene.objects["sphere mesh"], splats)

    # Blender ending the operator (another file loaded) stops the worker and adds nothing.
    count = len(bpy.data.meshes)
    job = workflows.MeshExtraction(splats, method="poisson", resolution=RESOLUTION)
    state = OperatorState(op, job)
    job.start()
    op.cancel(state, bpy.context)
    assert job.wait(60) and state._session is None and len(bpy.data.meshes) == count


def test_modal_fusion_renders_a_view_per_tick_then_fuses_and_esc_adds_nothing(extension, clean_scene, tmp_path):
    workflows = extension.addon.workflows
    op = extension.addon.operators.MLX3D_OT_extract_mesh
    splats = import_splats(tmp_path / "sphere.ply")
    cameras = world_cameras(8, 64)
    before = scene_state()

    def modal_job(**attrs):
        job = workflows.MeshExtraction(splats, cameras=cameras, resolution=32)
        headers = []
        return job, OperatorState(op, job, _area=SimpleNamespace(header_text_set=headers.append), **attrs), headers

    # One view per timer tick, on the main thread; the worker starts after the last and fuses.
    job, state, headers = modal_job()
    for i in range(1, 9):
        assert not job.running and job._thread is None
        assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
        assert len(job.views) == i and job.views_left == 8 - i
        if i < 8:
            assert job.progress == (i, 24)
            assert headers[-1] == f"Extracting mesh from 'sphere': rendering view {i + 1}/8 (Esc to cancel)"
    assert job._thread is not None and headers[-1].startswith("Extracting mesh from 'sphere': ") and headers[-1].endswith("% (Esc to cancel)")
    assert job.wait(60) and job.error is None
    assert op.modal(state, bpy.context, TIMER) == {"FINISHED"} and state._session is None
    assert "fusion of 8 views" in state.reports[0][1] and headers[-1] is None
    obj = bpy.context.scene.objects["sphere mesh"]
    assert obj.parent == splats
    on_sphere = on_unit_sphere(obj)[1]
    assert np.abs(np.linalg.norm(on_sphere, axis=1) - 1.0).max() < 2 * 2.0 * max(SCALE) / 32
    bpy.data.objects.remove(obj)
    bpy.data.meshes.remove(bpy.data.meshes["sphere mesh"])
    bpy.data.materials.remove(bpy.data.materials["MLX3D Mesh"])
    assert scene_state() == before

    # Esc while rendering: no worker was started, nothing is added.
    job, state, _ = modal_job()
    for _ in range(3):
        assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    assert job._thread is None and state._session is None and scene_state() == before
    assert state.reports == [({"INFO"}, "mesh extraction from 'sphere' cancelled; nothing was added")]

    # Esc while fusing: the worker stops at its next report, nothing is added.
    job, state, _ = modal_job()
    gate = threading.Event()
    compute = job.compute
    job.compute = lambda progress=None: (gate.wait(30), compute(progress))[1]  # holds the worker until released
    for _ in range(8):
        assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert job.running
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    gate.set()
    assert job.wait(60) and isinstance(job.error, workflows.ExtractionCancelled)
    assert state._session is None and scene_state() == before

    # An error while rendering ends the operator with an error, nothing added.
    job, state, _ = modal_job()
    from mlx3d.meshing import MeshingError

    def broken(camera):
        raise MeshingError("the renderer failed")

    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    job._render = broken
    assert op.modal(state, bpy.context, TIMER) == {"CANCELLED"}
    assert state.reports == [({"ERROR"}, "the renderer failed")] and state._session is None and job._thread is None
    assert scene_state() == before


# ------------------------------------------------------------------ panel and headless
def test_panel_mesh_section_passes_its_settings(extension, clean_scene):
    settings = clean_scene.mlx3d_splats
    panel = extension.addon.panel.VIEW3D_PT_mlx3d_splats

    def draw():
        log = []
        panel.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
        start = log.index(("label", "Surface mesh"))
        end = next(i for i, entry in enumerate(log[start:], start) if entry[0] == "operator")
        (_, idname, op) = log[end]
        assert idname == "mlx3d.extract_mesh"
        return [entry[1] for entry in log[start:end] if entry[0] == "prop"], op

    assert settings.mesh_method == "FUSION" and settings.mesh_cameras is None and settings.mesh_resolution == 128
    settings.mesh_resolution, settings.mesh_cleanup, settings.mesh_faces = 200, 0.05, 3000
    props, op = draw()
    assert props == ["mesh_method", "mesh_cameras", "mesh_box", "mesh_resolution", "mesh_cleanup", "mesh_faces"]  # no Poisson-only setting
    assert (op.method, op.cameras, op.box, op.resolution, op.cleanup, op.faces) == ("FUSION", "", "", 200, pytest.approx(0.05), 3000)
    assert not hasattr(op, "min_opacity")
    settings.mesh_cameras = camera_collection("shots", [(0.0, -4.0, 1.0)])
    settings.mesh_box = bpy.data.objects.new("crate", bpy.data.meshes.new("crate"))
    props, op = draw()
    assert (op.cameras, op.box) == ("shots", "crate")

    settings.mesh_method = "POISSON"
    settings.mesh_min_opacity, settings.mesh_max_points, settings.mesh_trim = 0.2, 5000, 1.5
    props, op = draw()
    assert props == ["mesh_method", "mesh_cameras", "mesh_resolution", "mesh_cleanup", "mesh_faces", "mesh_min_opacity", "mesh_max_points", "mesh_trim"]
    assert (op.method, op.cameras, op.box, op.resolution, op.cleanup) == ("POISSON", "shots", "", 200, pytest.approx(0.05))
    assert (op.min_opacity, op.max_points, op.trim) == (pytest.approx(0.2), 5000, pytest.approx(1.5))


def _script(extension):
    return os.path.join(os.path.dirname(extension.__file__), "addon", "blender_splat.py")


def _run(extension, extension_env, *args):
    return subprocess.run([sys.executable, _script(extension), *map(str, args)], env=extension_env, capture_output=True, text=True, timeout=300)


def test_headless_extract_mesh(extension, extension_env, tmp_path):
    """Poisson, in the file's frame, with --save-blend; a file with nothing to mesh is an error."""
    from mlx3d.io.mesh_ply import read_mesh_ply

    write_splat_ply(tmp_path / "sphere.ply", sphere_splats())
    result = _run(extension, extension_env, "extract-mesh", tmp_path / "sphere.ply", "--out", tmp_path / "mesh.ply", "--method", "poisson",
                  "--resolution", "32", "--save-blend", tmp_path / "mesh.blend")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "extracted 'sphere mesh' from 'sphere' (3,000 splats, Poisson, resolution 32)" in result.stdout
    mesh = read_mesh_ply(tmp_path / "mesh.ply")
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 2 * (2.4 / 32)  # the file's frame: the unit sphere
    assert boundary_edges(faces) == 0 and signed_volume(vertices, faces) > 0
    np.testing.assert_allclose(np.asarray(mesh.colors), np.tile(SRGB, (len(vertices), 1)), atol=1 / 255 + 1e-3)
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "mesh.blend"))
    obj = bpy.data.objects["sphere mesh"]
    assert obj.parent == bpy.data.objects["sphere"] and len(obj.data.polygons) == len(faces)

    write_splat_ply(tmp_path / "clear.ply", sphere_splats(n=100, opacity_logit=-12.0))
    for method in ("fusion", "poisson"):
        bad = _run(extension, extension_env, "extract-mesh", tmp_path / "clear.ply", "--out", tmp_path / "bad.ply", "--method", method)
        assert bad.returncode == 1 and "blender_splat extract-mesh: error: no splat of 'clear'" in bad.stderr
        assert not (tmp_path / "bad.ply").exists()


def test_headless_fusion_writes_the_sphere(extension, extension_env, tmp_path):
    """--method fusion with its default views, 60 around the splats."""
    from mlx3d.io.mesh_ply import read_mesh_ply

    write_splat_ply(tmp_path / "sphere.ply", sphere_splats())
    result = _run(extension, extension_env, "extract-mesh", tmp_path / "sphere.ply", "--out", tmp_path / "mesh.ply", "--method", "fusion",
                  "--resolution", "32")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "extracted 'sphere mesh' from 'sphere' (3,000 splats, fusion of 60 views, resolution 32)" in result.stdout
    mesh = read_mesh_ply(tmp_path / "mesh.ply")
    vertices = np.asarray(mesh.vertices, np.float64)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 2 * (2.0 / 32)
    assert largest_gap(vertices, fibonacci_directions(200)) < 0.15
    np.testing.assert_allclose(np.asarray(mesh.colors), np.tile(SRGB, (len(vertices), 1)), atol=1 / 255 + 1e-3)


def write_nerf_dataset(folder, eyes, up, size=48, angle_x=0.8):
    """A NeRF-synthetic folder: ``transforms_train.json`` (OpenGL camera-to-world poses looking at the origin) and
    blank PNGs; the cameras are what fusion reads from it."""
    from PIL import Image

    (folder / "train").mkdir(parents=True)
    frames = []
    for i, eye in enumerate(eyes):
        Image.new("RGB", (size, size)).save(folder / "train" / f"r_{i}.png")
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": look_at_c2w(eye, up=up).tolist()})
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle_x, "frames": frames}))


def test_headless_mesh_alias_renders_the_dataset_cameras(extension, extension_env, tmp_path):
    """`mesh` is `extract-mesh`; --cameras-from reads a dataset in the file's frame, here a Y-up file imported with
    --axis Y_UP: cameras above the file's +Y pole mesh nothing of its y < 0 half."""
    from mlx3d.io.mesh_ply import read_mesh_ply

    write_splat_ply(tmp_path / "sphere.ply", sphere_splats())
    eyes = [np.array([x, y_up, z]) for x, z, y_up in top_eyes(4)]  # the file's up is +Y
    write_nerf_dataset(tmp_path / "data", eyes, up=(0.0, 1.0, 0.0))
    result = _run(extension, extension_env, "mesh", tmp_path / "sphere.ply", "--out", tmp_path / "top.ply", "--cameras-from", tmp_path / "data",
                  "--axis", "Y_UP", "--resolution", "32", "--cleanup", "0")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "extracted 'sphere mesh' from 'sphere' (3,000 splats, fusion of 4 views, resolution 32)" in result.stdout
    vertices = np.asarray(read_mesh_ply(tmp_path / "top.ply").vertices, np.float64)  # the file's frame
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 2 * (2.0 / 32)
    assert vertices[:, 1].min() > -0.1, "nothing of the half the cameras do not see"
    top = fibonacci_directions(400)[:, [0, 2, 1]]
    assert largest_gap(vertices, top[top[:, 1] > 0.3]) < 0.1
    # --bounds in the file's frame: the cap above y = 0.5 only
    result = _run(extension, extension_env, "mesh", tmp_path / "sphere.ply", "--out", tmp_path / "cap.ply", "--cameras-from", tmp_path / "data",
                  "--axis", "Y_UP", "--resolution", "32", "--cleanup", "0", "--bounds", -2, 0.5, -2, 2, 2, 2)
    assert result.returncode == 0, result.stderr[-3000:]
    cap = np.asarray(read_mesh_ply(tmp_path / "cap.ply").vertices, np.float64)
    assert cap[:, 1].min() >= 0.5 - 1e-5 and cap[:, 1].min() < 0.5 + 2.0 / 32 and cap[:, 1].max() > 0.95

    bad = _run(extension, extension_env, "mesh", tmp_path / "sphere.ply", "--out", tmp_path / "bad.ply", "--cameras-from", tmp_path / "none")
    assert bad.returncode == 1 and "blender_splat mesh: error:" in bad.stderr and not (tmp_path / "bad.ply").exists()


def test_headless_parser_knows_the_methods_and_the_alias(extension, capsys):
    import importlib

    headless = importlib.import_module(extension.__name__ + ".addon.headless")
    parser = headless.build_parser()
    for name in ("extract-mesh", "mesh"):
        args = parser.parse_args([name, "in.ply", "--out", "out.ply"])
        assert args.func is headless.cmd_extract_mesh and (args.method, args.cleanup, args.faces, args.cameras_from) == ("fusion", 0.01, 0, None)
    args = parser.parse_args(["mesh", "in.ply", "--out", "out.ply", "--method", "poisson", "--cleanup", "0.2", "--faces", "5000", "--cameras-from", "data"])
    assert (args.method, args.cleanup, args.faces, args.cameras_from) == ("poisson", 0.2, 5000, "data")
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args(["extract-mesh", "in.ply", "--out", "out.ply", "--method", "marching"])
    assert exit_info.value.code == 2 and "invalid choice: 'marching'" in capsys.readouterr().err
    assert "extract-mesh (mesh)" in parser.format_help()
    with pytest.raises(SystemExit):
        parser.parse_args(["mesh", "--help"])
    assert "`mesh` is the same command" in " ".join(capsys.readouterr().out.split())
