"""The installed extension driven through ``bpy.ops``, checked in the scene and on disk.

Oracles: the source file's own bits (round trips), ``mlx3d``'s data-layer
affine (transform baking), the SH colour invariance colour(R d) == colour(d),
and counts computed independently with numpy.
"""

import math
import os
import subprocess
import sys

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from mlx3d.io import read_splat_ply, write_splat_ply
from mlx3d.splatting import eval_sh, transform_splats
from mlx3d.transforms import covariances

bpy = pytest.importorskip("bpy")

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data")
OPENSPLAT = os.path.join(DATA, "opensplat_trained.ply")


def make_ply(path, n=300, degree=3, seed=0, extras=True):
    """A random 3DGS PLY with mixed-type extra properties; returns the structured array."""
    rng = np.random.default_rng(seed)
    k1 = (degree + 1) ** 2 - 1
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * k1)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    dtype = [(name, "<f4") for name in names]
    if extras:
        dtype += [("red", "u1"), ("segment", "<i4"), ("confidence", "<f4")]
    data = np.zeros(n, dtype=dtype)
    for name in names:
        data[name] = rng.normal(size=n).astype(np.float32)
    data["scale_0"] -= 3
    data["scale_1"] -= 3
    data["scale_2"] -= 3
    if extras:
        data["red"] = rng.integers(0, 256, n)
        data["segment"] = rng.integers(-(2**31), 2**31 - 1, n)
        data["confidence"] = rng.uniform(size=n)
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
    return data


def assert_same_bits(a, b):
    assert a.dtype.names == b.dtype.names
    for name in a.dtype.names:
        assert np.array_equal(a[name].view(f"u{a[name].itemsize}"), b[name].view(f"u{b[name].itemsize}")), name


def vertex(path):
    return PlyData.read(str(path))["vertex"].data


def import_file(path, **kwargs):
    assert bpy.ops.import_scene.gaussian_splat_ply(filepath=str(path), **kwargs) == {"FINISHED"}
    return bpy.context.active_object


def export_file(path, **kwargs):
    assert bpy.ops.export_scene.gaussian_splat_ply(filepath=str(path), **kwargs) == {"FINISHED"}


def select_only(*objects):
    for obj in bpy.context.scene.objects:
        obj.select_set(obj in objects)
    bpy.context.view_layer.objects.active = objects[-1]


# ------------------------------------------------------------------ round trips
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_bit_exact(extension, clean_scene, tmp_path, degree):
    src = make_ply(tmp_path / "in.ply", degree=degree)
    obj = import_file(tmp_path / "in.ply")
    assert obj.type == "POINTCLOUD" and obj.name == "in" and len(obj.data.points) == 300
    names = set(obj.data.attributes.keys())
    assert {"radiance:base", "scale", "rotation", "red", "segment", "confidence", "nx"} <= names
    assert len([n for n in names if n.startswith("radiance:sh_")]) == (degree + 1) ** 2 - 1
    export_file(tmp_path / "out.ply")
    assert_same_bits(src, vertex(tmp_path / "out.ply"))


@pytest.mark.skipif(not os.path.exists(OPENSPLAT), reason="shared/data/opensplat_trained.ply not present")
def test_round_trip_of_a_file_written_elsewhere(extension, clean_scene, tmp_path):
    import_file(OPENSPLAT)
    export_file(tmp_path / "out.ply")
    assert_same_bits(vertex(OPENSPLAT), vertex(tmp_path / "out.ply"))


def test_import_export_import_export_is_stable(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply")
    obj = import_file(tmp_path / "in.ply")
    obj.location = (0.5, -1.0, 2.0)
    obj.rotation_euler = (0.4, -0.2, 1.1)
    obj.scale = (1.5, 0.5, 2.0)
    export_file(tmp_path / "a.ply")
    bpy.ops.wm.read_homefile(use_empty=True)
    import_file(tmp_path / "a.ply")
    export_file(tmp_path / "b.ply")
    assert_same_bits(vertex(tmp_path / "a.ply"), vertex(tmp_path / "b.ply"))


# ------------------------------------------------------------------ transform baking
def colours(arrays, dirs):
    sh = np.concatenate([arrays.sh_dc, arrays.sh_rest], axis=1).astype(np.float64)
    return eval_sh(arrays.sh_degree, sh[:, None], dirs[None])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_export_bakes_world_transform_with_parent(extension, clean_scene, tmp_path, seed):
    rng = np.random.default_rng(seed)
    make_ply(tmp_path / "in.ply", n=200, seed=seed, extras=False)
    original = read_splat_ply(tmp_path / "in.ply")
    obj = import_file(tmp_path / "in.ply")
    parent = bpy.data.objects.new("parent", None)
    bpy.context.collection.objects.link(parent)
    parent.location = tuple(rng.normal(size=3))
    parent.rotation_euler = tuple(rng.uniform(-math.pi, math.pi, 3))
    parent.scale = (2.0, 2.0, 2.0)
    obj.parent = parent
    obj.location = tuple(rng.normal(size=3))
    obj.rotation_euler = tuple(rng.uniform(-math.pi, math.pi, 3))
    obj.scale = tuple(rng.uniform(0.3, 3.0, 3))  # non-uniform
    bpy.context.view_layer.update()
    world = np.array(obj.matrix_world, dtype=np.float64)
    select_only(obj)
    export_file(tmp_path / "out.ply")
    got = read_splat_ply(tmp_path / "out.ply")
    want = transform_splats(original, world)
    np.testing.assert_allclose(got.means, want.means, rtol=1e-5, atol=1e-5)
    c_got, c_want = covariances(got.quats, got.scales), covariances(want.quats, want.scales)
    rel = np.linalg.norm(c_got - c_want, axis=(1, 2)) / np.linalg.norm(c_want, axis=(1, 2))
    assert rel.max() < 1e-5
    # independent check of the covariance: L Σ Lᵀ from Blender's own matrix
    lin = world[:3, :3]
    c_blender = lin @ covariances(original.quats, original.scales) @ lin.T
    assert (np.linalg.norm(c_got - c_blender, axis=(1, 2)) / np.linalg.norm(c_blender, axis=(1, 2))).max() < 1e-5
    # view-dependent colour: colour_out(R d) == colour_in(d), R the rotation part of the world matrix
    u, _, vt = np.linalg.svd(lin)
    rot = u @ vt
    dirs = rng.normal(size=(32, 3))
    np.testing.assert_allclose(colours(got, dirs @ rot.T), colours(original, dirs), atol=1e-5)


def test_compose_scene_and_moved_object(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "scene.ply", n=150, seed=4, extras=False)
    make_ply(tmp_path / "object.ply", n=100, degree=1, seed=5, extras=False)
    scene_obj = import_file(tmp_path / "scene.ply")
    obj = import_file(tmp_path / "object.ply")
    obj.location = (0.05, -0.3, 0.6)
    obj.rotation_euler = tuple(math.radians(a) for a in (80, -180, 30))
    obj.scale = (0.06, 0.06, 0.06)
    select_only(scene_obj, obj)
    export_file(tmp_path / "merged.ply")
    merged = read_splat_ply(tmp_path / "merged.ply")
    assert merged.count == 250 and merged.sh_degree == 3
    scene_src = read_splat_ply(tmp_path / "scene.ply")
    np.testing.assert_array_equal(merged.means[:150], scene_src.means)
    bpy.context.view_layer.update()
    want = transform_splats(read_splat_ply(tmp_path / "object.ply"), np.array(obj.matrix_world))
    np.testing.assert_allclose(merged.means[150:], want.means, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(merged.sh_rest[150:, 3:], 0)  # degree 1 padded to 3


# ------------------------------------------------------------------ edit operators
def test_apply_transform_then_export_equals_export(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply", extras=False)
    obj = import_file(tmp_path / "in.ply")
    obj.location, obj.rotation_euler, obj.scale = (1, 2, 3), (0.3, 0.2, 0.1), (1, 2, 0.5)
    export_file(tmp_path / "before.ply")
    assert bpy.ops.mlx3d.apply_transform() == {"FINISHED"}
    assert np.allclose(np.array(obj.matrix_basis), np.eye(4))
    export_file(tmp_path / "after.ply")
    a, b = read_splat_ply(tmp_path / "before.ply"), read_splat_ply(tmp_path / "after.ply")
    np.testing.assert_allclose(a.means, b.means, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(covariances(a.quats, a.scales), covariances(b.quats, b.scales), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(a.sh_rest, b.sh_rest, atol=1e-6)


def test_merge_selected_bakes_transforms(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "a.ply", n=50, seed=6)
    make_ply(tmp_path / "b.ply", n=70, seed=7, extras=False)
    a = import_file(tmp_path / "a.ply")
    b = import_file(tmp_path / "b.ply")
    b.location = (3, 0, 0)
    select_only(a, b)
    export_file(tmp_path / "expected.ply")
    assert bpy.ops.mlx3d.merge_selected() == {"FINISHED"}
    merged = bpy.context.scene.objects["Merged splats"]
    assert len(merged.data.points) == 120
    select_only(merged)
    export_file(tmp_path / "merged.ply")
    assert_same_bits(vertex(tmp_path / "expected.ply"), vertex(tmp_path / "merged.ply"))


def test_crop_to_box_keeps_or_deletes_inside(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply", n=400, extras=False)
    means = read_splat_ply(tmp_path / "in.ply").means
    obj = import_file(tmp_path / "in.ply")
    obj.location = (1.0, 0.0, 0.0)
    box = bpy.data.objects.new("box", None)
    bpy.context.collection.objects.link(box)
    box.empty_display_size = 0.5
    box.location = (1.2, 0.1, 0.0)
    box.scale = (2.0, 1.0, 1.0)
    world = means.astype(np.float64) + [1.0, 0.0, 0.0]
    local = (world - [1.2, 0.1, 0.0]) / [2.0, 1.0, 1.0]
    inside = int(np.all(np.abs(local) <= 0.5, axis=1).sum())
    assert 0 < inside < 400
    select_only(obj)
    assert bpy.ops.mlx3d.crop_to_box(box="box", keep_inside=True) == {"FINISHED"}
    assert len(obj.data.points) == inside
    bpy.ops.wm.read_homefile(use_empty=True)
    obj = import_file(tmp_path / "in.ply")
    obj.location = (1.0, 0.0, 0.0)
    box = bpy.data.objects.new("box", None)
    bpy.context.collection.objects.link(box)
    box.empty_display_size, box.location, box.scale = 0.5, (1.2, 0.1, 0.0), (2.0, 1.0, 1.0)
    assert bpy.ops.mlx3d.crop_to_box(box="box", keep_inside=False) == {"FINISHED"}
    assert len(obj.data.points) == 400 - inside


def test_remove_floaters_and_compact(extension, clean_scene, tmp_path):
    data = make_ply(tmp_path / "in.ply", n=2000, extras=False)
    data["z"] *= 0.01  # a thin slab...
    data["x"][-10:] = 50 + np.arange(10) * 7  # ...and ten far floaters
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "in.ply"))
    obj = import_file(tmp_path / "in.ply")
    assert bpy.ops.mlx3d.remove_floaters(method="STATISTICAL", k=10, std_ratio=3.0) == {"FINISHED"}
    assert len(obj.data.points) == 1990
    export_file(tmp_path / "clean.ply")
    assert read_splat_ply(tmp_path / "clean.ply").means[:, 0].max() < 50
    assert bpy.ops.mlx3d.compact(max_gaussians=500, sh_degree="1") == {"FINISHED"}
    export_file(tmp_path / "small.ply")
    small = read_splat_ply(tmp_path / "small.ply")
    assert small.count == 500 and small.sh_degree == 1


# ------------------------------------------------------------------ bad input, nothing lost
def test_bad_file_reports_and_leaves_no_data_behind(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply")
    (tmp_path / "cut.ply").write_bytes((tmp_path / "in.ply").read_bytes()[:5000])
    before = (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.pointclouds))
    with pytest.raises(RuntimeError, match="truncated"):
        bpy.ops.import_scene.gaussian_splat_ply(filepath=str(tmp_path / "cut.ply"))
    assert (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.pointclouds)) == before


def test_failed_export_keeps_existing_file(extension, clean_scene, tmp_path):
    (tmp_path / "out.ply").write_bytes(b"previous")
    cube = bpy.data.objects.new("not a splat", None)
    bpy.context.collection.objects.link(cube)
    select_only(cube)
    with pytest.raises(RuntimeError, match="no splat objects"):
        bpy.ops.export_scene.gaussian_splat_ply(filepath=str(tmp_path / "out.ply"))
    assert (tmp_path / "out.ply").read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["out.ply"]


def test_nan_rows_dropped_with_count(extension, clean_scene, tmp_path):
    data = make_ply(tmp_path / "in.ply", extras=False)
    data["opacity"][[3, 7]] = np.nan
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "in.ply"))
    with pytest.raises(RuntimeError, match="2"):
        bpy.ops.import_scene.gaussian_splat_ply(filepath=str(tmp_path / "in.ply"))
    obj = import_file(tmp_path / "in.ply", drop_nonfinite=True)
    assert len(obj.data.points) == 298
    _, messages = extension.addon.workflows.import_splat_file(tmp_path / "in.ply", drop_nonfinite=True)
    assert any("2 of 300" in m for m in messages[1:])  # reported to the user, not only to Python's warnings


def test_merge_reports_zero_filled_properties(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "a.ply", n=10, seed=1)
    make_ply(tmp_path / "b.ply", n=10, seed=2, extras=False)
    a, b = import_file(tmp_path / "a.ply"), import_file(tmp_path / "b.ply")
    _, messages = extension.addon.workflows.export_splat_file(tmp_path / "out.ply", [a, b])
    assert any("filled with 0" in m and "segment" in m for m in messages[1:])
    out = read_splat_ply(tmp_path / "out.ply")
    np.testing.assert_array_equal(out.extra["segment"][10:], 0)


# ------------------------------------------------------------------ options
def test_axis_preset_round_trips_and_rotates(extension, clean_scene, tmp_path):
    src = make_ply(tmp_path / "in.ply", extras=False)
    obj = import_file(tmp_path / "in.ply", axis="Y_DOWN")
    bpy.context.view_layer.update()
    world_up = np.array(obj.matrix_world)[:3, :3] @ [0.0, -1.0, 0.0]  # the file's up (-Y) ...
    np.testing.assert_allclose(world_up, [0, 0, 1], atol=1e-6)  # ... is Blender's +Z
    export_file(tmp_path / "same.ply", axis="Y_DOWN")
    assert_same_bits(src, vertex(tmp_path / "same.ply"))
    export_file(tmp_path / "zup.ply", axis="NONE")
    zup = read_splat_ply(tmp_path / "zup.ply").means
    np.testing.assert_allclose(zup, np.column_stack([src["x"], src["z"], -src["y"]]), atol=1e-6)


def test_sh_cap_and_cursor(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply", extras=False)
    bpy.context.scene.cursor.location = (1.0, 2.0, 3.0)
    obj = import_file(tmp_path / "in.ply", sh_degree="1", at_cursor=True)
    assert len([n for n in obj.data.attributes.keys() if n.startswith("radiance:sh_")]) == 3
    assert tuple(obj.location) == pytest.approx((1.0, 2.0, 3.0))


def test_export_without_the_raw_values_derives_them(extension, clean_scene, tmp_path):
    """Splats made by Blender's own importer or by Geometry Nodes carry no hidden raw values:
    logits, log scales and quaternions come from radiance:base, scale and rotation."""
    make_ply(tmp_path / "in.ply", n=20, degree=2, extras=False)
    arrays = read_splat_ply(tmp_path / "in.ply")
    obj = import_file(tmp_path / "in.ply")
    for name in (".mlx3d_opacity", ".mlx3d_log_scale", ".mlx3d_rot"):
        obj.data.attributes.remove(obj.data.attributes[name])
    export_file(tmp_path / "out.ply")
    out = read_splat_ply(tmp_path / "out.ply")
    np.testing.assert_array_equal(out.sh_rest, arrays.sh_rest)
    np.testing.assert_array_equal(out.sh_dc, arrays.sh_dc)
    np.testing.assert_allclose(out.scales, arrays.scales, atol=1e-6)
    np.testing.assert_allclose(out.opacities, arrays.opacities, atol=1e-5)
    quats = arrays.quats.astype(np.float64)
    np.testing.assert_allclose(out.quats, quats / np.linalg.norm(quats, axis=1, keepdims=True), atol=2e-7)


# ------------------------------------------------------------------ headless
def test_headless_compose_script(extension, extension_env, tmp_path):
    make_ply(tmp_path / "scene.ply", n=120, seed=8, extras=False)
    make_ply(tmp_path / "object.ply", n=80, seed=9, extras=False)
    script = os.path.join(os.path.dirname(extension.__file__), "addon", "blender_splat.py")
    args = ["compose", "--scene", str(tmp_path / "scene.ply"), "--insert", str(tmp_path / "object.ply"),
            "--location", "0.05", "-0.3", "0.6", "--rotation-deg", "80", "-180", "30", "--scale", "0.06", "--out", str(tmp_path / "out.ply")]
    result = subprocess.run([sys.executable, script, *args], env=extension_env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "exported 200 splats" in result.stdout
    out = read_splat_ply(tmp_path / "out.ply")
    from mlx3d.transforms import compose_affine

    want = transform_splats(read_splat_ply(tmp_path / "object.ply"), compose_affine(0.06, (80, -180, 30), (0.05, -0.3, 0.6)))
    np.testing.assert_allclose(out.means[120:], want.means, rtol=1e-5, atol=1e-6)
    bad = subprocess.run([sys.executable, script, "compose", "--scene", str(tmp_path / "nope.ply"), "--insert", str(tmp_path / "object.ply"),
                          "--out", str(tmp_path / "x.ply")], env=extension_env, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "nope.ply" in bad.stderr
    assert not (tmp_path / "x.ply").exists()


def test_ellipsoid_display_instances_oriented_scaled_spheres(extension, clean_scene, tmp_path):
    from mlx3d.transforms import quaternion_to_matrix

    make_ply(tmp_path / "in.ply", n=40, extras=False)
    arrays = read_splat_ply(tmp_path / "in.ply")
    obj = import_file(tmp_path / "in.ply")
    assert bpy.ops.mlx3d.show_ellipsoids(show=True) == {"FINISHED"}
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mats = [np.array(i.matrix_world) for i in depsgraph.object_instances if i.is_instance and i.parent and i.parent.original == obj]
    assert len(mats) == 40
    for i, m in enumerate(mats):
        want = np.eye(4)
        want[:3, :3] = quaternion_to_matrix(arrays.quats[i].astype(np.float64)) @ np.diag(2 * np.exp(arrays.scales[i].astype(np.float64)))
        want[:3, 3] = arrays.means[i]
        np.testing.assert_allclose(m, want, rtol=1e-5, atol=1e-5 * np.abs(want[:3, :3]).max())
    export_file(tmp_path / "out.ply")  # display only: the file is unchanged
    assert_same_bits(vertex(tmp_path / "in.ply"), vertex(tmp_path / "out.ply"))
    assert bpy.ops.mlx3d.show_ellipsoids(show=False) == {"FINISHED"}
    assert [m.name for m in obj.modifiers] == ([] if bpy.app.version >= (5, 3, 0) else ["MLX3D Splat Display"])


def test_info_box_values(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply", n=123, degree=2)
    arrays = read_splat_ply(tmp_path / "in.ply")
    obj = import_file(tmp_path / "in.ply")
    obj.location = (10.0, 0.0, 0.0)
    info = extension.addon.workflows.splat_info(obj)
    assert info["count"] == 123 and info["sh_degree"] == 2
    np.testing.assert_allclose(info["bounds_min"], arrays.means.min(axis=0) + [10, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(info["bounds_max"], arrays.means.max(axis=0) + [10, 0, 0], rtol=1e-6)
    write_splat_ply(tmp_path / "written.ply", arrays)
    header = (tmp_path / "written.ply").read_bytes().index(b"end_header\n") + len(b"end_header\n")
    assert info["memory_bytes"] == os.path.getsize(tmp_path / "written.ply") - header  # PLY body size


# ------------------------------------------------------------------ rendering
def add_camera(location=(0.0, -4.0, 0.3), rotation_deg=(88.0, 0.0, 2.0), **data):
    cam_data = bpy.data.cameras.new("cam")
    for key, value in data.items():
        setattr(cam_data, key, value)
    cam = bpy.data.objects.new("cam", cam_data)
    bpy.context.collection.objects.link(cam)
    cam.location = location
    cam.rotation_euler = tuple(math.radians(a) for a in rotation_deg)
    bpy.context.scene.camera = cam
    return cam


@pytest.mark.parametrize(
    "settings",
    [
        {},
        {"lens": 35.0, "shift_x": 0.1, "shift_y": -0.05},
        {"sensor_fit": "VERTICAL", "sensor_height": 20.0, "lens": 70.0},
        {"sensor_fit": "HORIZONTAL", "sensor_width": 24.0, "res": (300, 500, 50)},
        {"aspect": (2.0, 1.0), "shift_x": -0.2},
        {"type": "ORTHO", "ortho_scale": 3.0, "shift_y": 0.1},
    ],
)
def test_blender_camera_maps_exactly(extension, clean_scene, settings):
    from bpy_extras.object_utils import world_to_camera_view

    scene = bpy.context.scene
    settings = dict(settings)
    res = settings.pop("res", (640, 360, 100))
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = res
    aspect = settings.pop("aspect", (1.0, 1.0))
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    cam_obj = add_camera(**settings)
    bpy.context.view_layer.update()
    cam = extension.addon.camera.camera_from_blender(cam_obj, scene)
    assert (cam.width, cam.height) == (res[0] * res[2] // 100, res[1] * res[2] // 100)
    points = np.random.default_rng(0).uniform(-1.5, 1.5, (50, 3))
    uv, depth = cam.project_points(points)
    from mathutils import Vector

    for p, (u, v), d in zip(points, uv, depth):
        ndc = world_to_camera_view(scene, cam_obj, Vector(p))
        assert u == pytest.approx(ndc.x * cam.width, abs=1e-3)
        assert v == pytest.approx((1.0 - ndc.y) * cam.height, abs=1e-3)
        if cam.model == "pinhole":
            assert d == pytest.approx(ndc.z, rel=1e-5)


def test_render_operator_matches_mlx3d_and_saves_png(extension, clean_scene, tmp_path):
    from mlx3d.splatting import GaussianModel

    make_ply(tmp_path / "in.ply", n=300, extras=False)
    obj = import_file(tmp_path / "in.ply")
    obj.location = (0.2, 0.0, 0.0)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 48, 100
    cam_obj = add_camera()
    out_png = tmp_path / "render.png"
    scene.view_settings.view_transform = "Standard"
    assert scene.world is None  # a black world behind the splats, no Blender render (no other object)
    assert bpy.ops.mlx3d.render(filepath=str(out_png)) == {"FINISHED"}
    image = bpy.data.images["MLX3D Render"]
    assert tuple(image.size) == (64, 48)
    pixels = np.empty(64 * 48 * 4, np.float32)
    image.pixels.foreach_get(pixels)
    got = pixels.reshape(48, 64, 4)[::-1, :, :3]
    bpy.context.view_layer.update()
    cam = extension.addon.camera.camera_from_blender(cam_obj, scene)
    model = GaussianModel.from_arrays(transform_splats(read_splat_ply(tmp_path / "in.ply"), np.array(obj.matrix_world)))
    want = np.clip(np.array(model.render(cam, background=(0.0, 0.0, 0.0))["image"]), 0, 1)
    np.testing.assert_allclose(got, want, atol=1.0 / 255 + 1e-6)
    assert np.abs(want).max() > 0.1  # the splats are in view
    assert out_png.exists() and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp.png")]
    loaded = bpy.data.images.load(str(out_png))
    assert tuple(loaded.size) == (64, 48)


def test_render_without_camera_is_refused(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply", n=10, extras=False)
    import_file(tmp_path / "in.ply")
    with pytest.raises(RuntimeError, match="no active camera"):
        bpy.ops.mlx3d.render()


def test_headless_render(extension, clean_scene, tmp_path):
    make_ply(tmp_path / "in.ply", n=100, extras=False)
    import_file(tmp_path / "in.ply")
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = 32, 24
    add_camera()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    import importlib

    headless = importlib.import_module(extension.__name__ + ".addon.headless")
    code = headless.main(["render", "--blend", str(tmp_path / "scene.blend"), "--out", str(tmp_path / "out.png")])
    assert code == 0 and (tmp_path / "out.png").exists()
    assert tuple(bpy.data.images.load(str(tmp_path / "out.png")).size) == (32, 24)


def test_headless_commands_take_only_the_options_they_use(extension, capsys):
    """Import options (--sh-degree, --drop-nonfinite) belong to the commands that read splat files, --axis to
    those that read or write them: an option a command would ignore is refused, not dropped silently."""
    import importlib

    parser = importlib.import_module(extension.__name__ + ".addon.headless").build_parser()
    assert parser.parse_args(["import", "a.ply", "--axis", "Y_UP", "--sh-degree", "1", "--drop-nonfinite"]).sh_degree == 1
    assert parser.parse_args(["export", "--blend", "a.blend", "--out", "a.ply", "--axis", "Y_UP"]).axis == "Y_UP"
    for argv in (["export", "--blend", "a.blend", "--out", "a.ply", "--sh-degree", "1"],
                 ["export", "--blend", "a.blend", "--out", "a.ply", "--drop-nonfinite"],
                 ["render", "--blend", "a.blend", "--out", "a.png", "--axis", "Y_UP"]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)
        assert "unrecognized arguments" in capsys.readouterr().err


def test_panel_compact_and_render_sections_pass_their_settings(extension, clean_scene):
    from types import SimpleNamespace

    from panel_layout import RecordingLayout

    settings = clean_scene.mlx3d_splats
    settings.compact_max, settings.compact_min_opacity, settings.compact_sh = 1234, 0.25, "1"
    settings.render_antialias, settings.render_path = True, "//out.png"
    log = []
    extension.addon.panel.VIEW3D_PT_mlx3d_splats.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
    ops = {entry[1]: entry[2] for entry in log if entry[0] == "operator"}
    compact, render, animation = ops["mlx3d.compact"], ops["mlx3d.render"], ops["mlx3d.render_animation"]
    assert (compact.max_gaussians, compact.min_opacity, compact.sh_degree) == (1234, pytest.approx(0.25), "1")
    assert render.antialias is True and render.filepath == "//out.png" and animation.antialias is True
    labels = [entry[1] for entry in log if entry[0] == "label"]
    assert "Compact" in labels and "Render (scene camera)" in labels


def test_the_documented_headless_commands_parse(extension, capsys):
    """Every `blender_splat.py ...` command the README and the docs show (after `python` or `blender -b -P ... --`)
    parses with the headless script's own definitions, so a renamed or removed option fails here."""
    import importlib
    import shlex
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from test_docs import PAGES, SHELL, _blocks

    parser = importlib.import_module(extension.__name__ + ".addon.headless").build_parser()
    checked = 0
    for page in PAGES:
        for line, body in _blocks(page, SHELL):
            for raw in body.replace("\\\n", " ").splitlines():
                text = raw.strip()[2:] if raw.strip().startswith("$ ") else raw.strip()
                words = shlex.split(text, comments=True) if "blender_splat.py" in text or '-P "$S"' in text else []
                at = next((i for i, w in enumerate(words) if w.endswith("blender_splat.py") or w == '$S'), None)
                if at is None:
                    continue
                argv = words[at + 1:]
                if argv[:1] == ["--"]:
                    argv = argv[1:]
                if not argv or argv[0] in ("COMMAND", "--help", "-h", "…"):
                    continue
                try:
                    parser.parse_args(argv)
                except SystemExit as exc:
                    raise AssertionError(f"{page.name}:{line}: `{text}` does not parse: {capsys.readouterr().err.strip()}") from exc
                checked += 1
    assert checked >= 10
