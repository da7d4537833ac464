"""Extracting a surface mesh from a splat object (``workflows.extract_mesh``, the ``mlx3d.extract_mesh``
operator, its panel section and the ``extract-mesh`` headless command), through the installed extension.

Oracles: the splats are flat Gaussians tangent to a unit sphere, so the mesh must lie on that sphere
mapped by the transform set on the object (composed here with ``mlx3d.transforms.compose_affine``,
not read back from Blender); closedness is counted from the faces; the colour attribute must hold
the splats' base colour decoded from sRGB with the IEC 61966-2-1 formula written out here.
"""

import os
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest
from modal_state import ESC, KEY, MOVE, OperatorState, TIMER
from panel_layout import RecordingLayout

from mlx3d.io import SplatArrays, write_splat_ply
from mlx3d.splatting import C0
from mlx3d.transforms import compose_affine

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


def check_sphere_mesh(obj, splat_obj):
    """The mesh object sits under the splat object, on the transformed unit sphere, closed, outward, coloured."""
    assert obj.type == "MESH" and obj.parent == splat_obj and obj.name == f"{splat_obj.name} mesh"
    assert obj.users_collection[0] == splat_obj.users_collection[0]
    bpy.context.view_layer.update()
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(splat_obj.matrix_world), atol=1e-6)
    local, faces = mesh_arrays(obj)
    world = local @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
    placed = compose_affine(np.array(SCALE), ROTATION_DEG, LOCATION)  # the transform set on the object, built independently
    on_sphere = world @ np.linalg.inv(placed)[:3, :3].T + np.linalg.inv(placed)[:3, 3]
    radius = np.linalg.norm(on_sphere, axis=1)
    assert np.abs(radius - 1.0).max() < 2 * VOXEL, (radius.min(), radius.max())
    assert len(faces) > 500
    assert boundary_edges(faces) == 0, "closed"
    assert signed_volume(on_sphere, faces) == pytest.approx(4 / 3 * np.pi, rel=0.1)  # faces wound outward
    attr = obj.data.color_attributes["Color"]
    assert (attr.domain, attr.data_type) == ("POINT", "FLOAT_COLOR")
    rgba = np.empty(len(attr.data) * 4, np.float32)
    attr.data.foreach_get("color", rgba)
    rgba = rgba.reshape(-1, 4)
    np.testing.assert_allclose(rgba[:, :3], np.tile(srgb_to_linear(SRGB), (len(rgba), 1)), atol=2e-3)
    np.testing.assert_array_equal(rgba[:, 3], 1.0)
    material = obj.material_slots[0].material
    assert material.name == "MLX3D Mesh"
    return world, faces


# ------------------------------------------------------------------ the operator and the function
def test_operator_extracts_the_sphere_under_the_transformed_splat_object(extension, clean_scene, tmp_path):
    splats = import_splats(tmp_path / "sphere.ply")
    before = len(bpy.data.meshes)
    t0 = time.perf_counter()
    assert bpy.ops.mlx3d.extract_mesh(resolution=RESOLUTION) == {"FINISHED"}
    seconds = time.perf_counter() - t0
    assert len(bpy.data.meshes) == before + 1
    obj = bpy.context.scene.objects["sphere mesh"]
    assert bpy.context.active_object == obj and obj.select_get() and not splats.select_get()
    check_sphere_mesh(obj, splats)
    assert any(p.use_smooth for p in obj.data.polygons[:10])
    assert seconds < 30
    # The material shows the attribute (and a capture of the mesh would read the same colours).
    assert extension.addon.capture.material_colour_source(obj.material_slots[0].material)[1] == "Color"
    # Moving the splat object carries the mesh along.
    splats.location = (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    np.testing.assert_allclose(np.array(obj.matrix_world), np.array(splats.matrix_world), atol=1e-6)


def test_workflow_function_returns_the_object_and_a_report(extension, clean_scene, tmp_path):
    workflows = extension.addon.workflows
    splats = import_splats(tmp_path / "sphere.ply")
    target = bpy.data.collections.new("meshes")
    clean_scene.collection.children.link(target)
    seen = []
    obj, messages = workflows.extract_mesh(splats, resolution=RESOLUTION, name="shell", collection=target,
                                           progress=lambda done, total: seen.append((done, total)))
    assert obj.name == "shell" and obj.users_collection == (target,) and obj.parent == splats
    assert seen and all(0 <= d <= t for d, t in seen)
    n_v, n_f = len(obj.data.vertices), len(obj.data.polygons)
    assert messages[0].startswith("extracted 'shell' from 'sphere' (3,000 splats, resolution 48): ")
    assert f"{n_v:,} vertices, {n_f:,} faces in " in messages[0]
    # camera_centres are world positions: one inside the sphere turns every normal, and so the surface, inward.
    inside = compose_affine(np.array(SCALE), ROTATION_DEG, LOCATION) @ [0.0, 0.0, 0.2, 1.0]
    obj, _ = workflows.extract_mesh(splats, resolution=32, name="inward", camera_centres=[inside[:3]])
    assert signed_volume(*mesh_arrays(obj)) == pytest.approx(-4 / 3 * np.pi, rel=0.15)
    # Invoked without a window (background), the operator runs at once.
    bpy.context.view_layer.objects.active = splats
    assert bpy.ops.mlx3d.extract_mesh("INVOKE_DEFAULT", resolution=16, trim=0.0) == {"FINISHED"}
    assert bpy.context.active_object.name == "sphere mesh" and bpy.context.active_object.parent == splats


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
    message = "no splat of 'clear' has opacity >= 0.01 (of 200); nothing to mesh"
    with pytest.raises(RuntimeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        bpy.ops.mlx3d.extract_mesh(resolution=16)
    with pytest.raises(MeshingError, match="opacity >= 0.5"):
        workflows.extract_mesh(bpy.context.active_object, resolution=16, min_opacity=0.5)
    assert scene_state() == before
    # A splat object without points (all deleted).
    obj = bpy.context.active_object
    extension.addon.splat_object.replace_splats(obj, SplatArrays(
        **{k: getattr(transparent, k)[:0] for k in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")}))
    assert extension.addon.splat_object.is_splat_object(obj) and len(obj.data.points) == 0
    before = scene_state()
    with pytest.raises(MeshingError, match="no splats"):
        workflows.extract_mesh(obj)
    with pytest.raises(RuntimeError, match="no splats"):
        bpy.ops.mlx3d.extract_mesh()
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

    with pytest.raises(Stop):
        workflows.extract_mesh(splats, resolution=RESOLUTION, progress=progress)
    assert scene_state() == before
    # The worker-thread path the operator uses: cancel() makes the next progress report raise.
    job = workflows.MeshExtraction(splats, resolution=RESOLUTION)
    job.cancel()
    job.start()
    assert job.wait(60)
    assert isinstance(job.error, workflows.ExtractionCancelled) and job.surface is None
    with pytest.raises(workflows.ExtractionCancelled, match="cancelled"):
        job.add_object()
    assert scene_state() == before


def test_modal_operator_polls_the_worker_and_esc_adds_nothing(extension, clean_scene, tmp_path):
    workflows = extension.addon.workflows
    op = extension.addon.operators.MLX3D_OT_extract_mesh
    splats = import_splats(tmp_path / "sphere.ply")
    before = scene_state()

    job = workflows.MeshExtraction(splats, resolution=RESOLUTION)
    state = OperatorState(op, job)
    gate = __import__("threading").Event()
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

    job = workflows.MeshExtraction(splats, resolution=RESOLUTION)
    state = OperatorState(op, job)
    job.start()
    assert job.wait(60)
    assert op.modal(state, bpy.context, TIMER) == {"FINISHED"}
    assert state._session is None and state.reports[0][0] == {"INFO"} and "vertices" in state.reports[0][1]
    check_sphere_mesh(bpy.context.scene.objects["sphere mesh"], splats)

    # Blender ending the operator (another file loaded) stops the worker and adds nothing.
    count = len(bpy.data.meshes)
    job = workflows.MeshExtraction(splats, resolution=RESOLUTION)
    state = OperatorState(op, job)
    job.start()
    op.cancel(state, bpy.context)
    assert job.wait(60) and state._session is None and len(bpy.data.meshes) == count


# ------------------------------------------------------------------ panel and headless
def test_panel_mesh_section_passes_its_settings(extension, clean_scene):
    settings = clean_scene.mlx3d_splats
    settings.mesh_resolution, settings.mesh_min_opacity, settings.mesh_max_points, settings.mesh_trim = 200, 0.2, 5000, 1.5
    log = []
    extension.addon.panel.VIEW3D_PT_mlx3d_splats.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
    start = log.index(("label", "Surface mesh"))
    props = [entry[1] for entry in log[start:] if entry[0] == "prop"][:4]
    assert props == ["mesh_resolution", "mesh_min_opacity", "mesh_max_points", "mesh_trim"]
    (_, idname, op), = [entry for entry in log[start:] if entry[0] == "operator"][:1]
    assert idname == "mlx3d.extract_mesh"
    assert (op.resolution, op.min_opacity, op.max_points, op.trim) == (200, pytest.approx(0.2), 5000, pytest.approx(1.5))


def test_headless_extract_mesh(extension, extension_env, tmp_path):
    from mlx3d.io.mesh_ply import read_mesh_ply

    write_splat_ply(tmp_path / "sphere.ply", sphere_splats())
    script = os.path.join(os.path.dirname(extension.__file__), "addon", "blender_splat.py")
    args = ["extract-mesh", str(tmp_path / "sphere.ply"), "--out", str(tmp_path / "mesh.ply"), "--resolution", "32",
            "--save-blend", str(tmp_path / "mesh.blend")]
    result = subprocess.run([sys.executable, script, *args], env=extension_env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "extracted 'sphere mesh' from 'sphere' (3,000 splats, resolution 32)" in result.stdout
    mesh = read_mesh_ply(tmp_path / "mesh.ply")
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 2 * (2.4 / 32)  # the file's frame: the unit sphere
    assert boundary_edges(faces) == 0 and signed_volume(vertices, faces) > 0
    np.testing.assert_allclose(np.asarray(mesh.colors), np.tile(SRGB, (len(vertices), 1)), atol=1 / 255 + 1e-3)
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "mesh.blend"))
    obj = bpy.data.objects["sphere mesh"]
    assert obj.parent == bpy.data.objects["sphere"] and len(obj.data.polygons) == len(faces)

    write_splat_ply(tmp_path / "clear.ply", sphere_splats(n=100, opacity_logit=-12.0))
    bad = subprocess.run([sys.executable, script, "extract-mesh", str(tmp_path / "clear.ply"), "--out", str(tmp_path / "bad.ply")],
                         env=extension_env, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "blender_splat extract-mesh: error:" in bad.stderr
    assert not (tmp_path / "bad.ply").exists()
