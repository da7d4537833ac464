"""Capturing a Blender scene as a training dataset (``addon/capture.py``), through the installed extension.

Oracles: the rendered images themselves (the sphere's world centre, projected
with the written intrinsics and poses by hand in nerfstudio's and COLMAP's
conventions, lands on the centroid of the sphere-coloured pixels), the PNG
bytes decoded here with zlib, the mesh triangles (sampled points lie on them),
the materials' base colours, and the scene's settings before the capture.
"""

import importlib.util
import json
import math
import os
import struct
import subprocess
import sys
import time
import zlib
from types import SimpleNamespace

import numpy as np
import pytest
from node_trees import node_tree
from modal_state import ESC, KEY, MOVE, OperatorState, TIMER
from panel_layout import RecordingLayout

bpy = pytest.importorskip("bpy")

SPHERE_CENTRE = np.array([0.0, 0.0, 1.0])
SPHERE_RADIUS = 0.4
CUBE_HALF = 0.5
SPHERE_RGB = (0.8, 0.05, 0.05)  # linear base colours
CUBE_RGB = (0.05, 0.05, 0.8)


# ------------------------------------------------------------------ helpers
def srgb8(linear):
    c = np.asarray(linear, dtype=np.float64)
    return np.round(255 * np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)).astype(int)


def read_png(path):
    """(H, W, C) uint8 pixels of an 8-bit, non-interlaced PNG (decoded here, independently of Blender)."""
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    pos, idat = 8, b""
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            width, height, depth, colour_type, _, _, interlace = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            break
    assert depth == 8 and interlace == 0, (depth, interlace)
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour_type]
    stride = width * channels
    raw = zlib.decompress(idat)
    rows, prev = [], [0] * stride
    for y in range(height):
        start = y * (stride + 1)
        kind, line = raw[start], raw[start + 1 : start + 1 + stride]
        cur = [0] * stride
        for x in range(stride):
            a = cur[x - channels] if x >= channels else 0
            b = prev[x]
            c = prev[x - channels] if x >= channels else 0
            if kind == 0:
                pred = 0
            elif kind == 1:
                pred = a
            elif kind == 2:
                pred = b
            elif kind == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            cur[x] = (line[x] + pred) & 255
        rows.append(cur)
        prev = cur
    return np.array(rows, dtype=np.uint8).reshape(height, width, channels)


def project_nerfstudio(meta, frame, point):
    """Pixel (x, y) of a world point from a nerfstudio frame: OpenGL c2w, rays through (x - cx) / fx, -(y - cy) / fy, -1."""
    k = {**{key: meta[key] for key in ("fl_x", "fl_y", "cx", "cy") if key in meta}, **frame}
    c2w = np.array(frame["transform_matrix"], dtype=np.float64)
    p = np.linalg.inv(c2w) @ np.append(point, 1.0)
    depth = -p[2]
    return np.array([k["cx"] + k["fl_x"] * p[0] / depth, k["cy"] - k["fl_y"] * p[1] / depth])


def sphere_outline_centre(meta, frame, centre, radius):
    """Centre (x, y) of the ellipse a sphere projects to, in the nerfstudio frame's pixels.

    Directions x = (a, b, 1) (OpenCV camera axes) tangent to the sphere satisfy
    (x.C)^2 = (|C|^2 - r^2)|x|^2: a conic in (a, b) whose centre is where its
    gradient vanishes. Perspective moves it off the projected sphere centre.
    """
    k = {**{key: meta[key] for key in ("fl_x", "fl_y", "cx", "cy") if key in meta}, **frame}
    c2w_cv = np.array(frame["transform_matrix"], dtype=np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])
    c = (np.linalg.inv(c2w_cv) @ np.append(centre, 1.0))[:3]
    m = np.outer(c, c) - (c @ c - radius**2) * np.eye(3)
    a, b = np.linalg.solve(m[:2, :2], -m[:2, 2])
    return np.array([k["cx"] + k["fl_x"] * a, k["cy"] + k["fl_y"] * b])


def qvec_to_matrix(q):
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def read_colmap_text(folder):
    """Tiny COLMAP text-model parser: (cameras {id: (model, w, h, params)}, images [(id, q, t, cam, name, points2d)], points)."""
    def lines(name):
        with open(os.path.join(folder, name), encoding="utf-8") as f:
            return [line.rstrip("\n") for line in f]

    cameras = {}
    for line in lines("cameras.txt"):
        if line and not line.startswith("#"):
            e = line.split()
            cameras[int(e[0])] = (e[1], int(e[2]), int(e[3]), [float(v) for v in e[4:]])
    images, body = [], [line for line in lines("images.txt") if not line.startswith("#")]
    for head, pts in zip(body[0::2], body[1::2]):
        e = head.split()
        images.append((int(e[0]), np.array(e[1:5], float), np.array(e[5:8], float), int(e[8]), e[9], pts.split()))
    points = []
    for line in lines("points3D.txt"):
        if line and not line.startswith("#"):
            e = line.split()
            points.append((int(e[0]), [float(v) for v in e[1:4]], [int(v) for v in e[4:7]], float(e[7]), e[8:]))
    return cameras, images, points


def read_points_ply(path):
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"]
    assert [p.name for p in v.properties] == ["x", "y", "z", "red", "green", "blue"]
    d = v.data
    return np.stack([d["x"], d["y"], d["z"]], 1).astype(np.float64), np.stack([d["red"], d["green"], d["blue"]], 1).astype(int)


def principled(name, rgb):
    material = bpy.data.materials.new(name)
    node_tree(material).nodes["Principled BSDF"].inputs["Base Color"].default_value = (*rgb, 1.0)
    return material


def build_scene():
    """A white world, a blue unit cube at the origin and a red UV sphere above it, plus user settings to keep."""
    scene = bpy.context.scene
    world = bpy.data.worlds.new("World")
    scene.world = world
    background = node_tree(world).nodes["Background"]
    background.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    background.inputs["Strength"].default_value = 1.0
    bpy.ops.mesh.primitive_cube_add(size=2 * CUBE_HALF, location=(0, 0, 0))
    cube = bpy.context.active_object
    cube.name = "Cube"
    cube.data.materials.append(principled("Blue", CUBE_RGB))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=SPHERE_RADIUS, location=tuple(SPHERE_CENTRE), segments=32, ring_count=16)
    sphere = bpy.context.active_object
    sphere.name = "Sphere"
    sphere.data.materials.append(principled("Red", SPHERE_RGB))
    user_cam = bpy.data.objects.new("UserCam", bpy.data.cameras.new("UserCam"))
    scene.collection.objects.link(user_cam)
    user_cam.location = (5, -5, 3)
    user_cam.data.lens = 85
    scene.camera = user_cam
    r = scene.render
    engines = {item.identifier for item in r.bl_rna.properties["engine"].enum_items}
    r.engine = "BLENDER_EEVEE" if "BLENDER_EEVEE" in engines else "BLENDER_EEVEE_NEXT"  # EEVEE's name in 4.x
    r.resolution_x, r.resolution_y, r.resolution_percentage = 640, 360, 50
    r.film_transparent = False
    r.filepath = "//user_render_"
    r.image_settings.file_format = "JPEG"
    r.image_settings.color_mode = "RGB"
    scene.cycles.samples = 7
    scene.cycles.use_denoising = True
    scene.view_settings.view_transform = "AgX"
    scene.view_settings.exposure = 0.5
    for obj in scene.objects:
        obj.select_set(obj is cube)
    bpy.context.view_layer.objects.active = cube
    bpy.context.view_layer.update()
    return scene


def snapshot(scene):
    """Everything of the user's scene a capture might touch."""
    r, im, c, v = scene.render, scene.render.image_settings, scene.cycles, scene.view_settings
    active = bpy.context.view_layer.objects.active
    return {
        "objects": sorted(o.name for o in bpy.data.objects),
        "cameras": sorted(o.name for o in bpy.data.cameras),
        "meshes": sorted(o.name for o in bpy.data.meshes),
        "scene_objects": sorted(o.name for o in scene.objects),
        "matrices": {o.name: [list(row) for row in o.matrix_world] for o in scene.objects},
        "camera": scene.camera.name if scene.camera else None,
        "render": (r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage, r.pixel_aspect_x, r.pixel_aspect_y,
                   r.film_transparent, r.filepath, r.use_persistent_data, r.use_compositing, r.dither_intensity, r.use_border),
        "image": (getattr(im, "media_type", None),  # 5.0+
                   im.file_format, im.color_mode, im.color_depth, im.color_management),
        "cycles": (c.samples, c.device, c.use_denoising, c.use_adaptive_sampling),
        "view": (v.view_transform, v.look, v.exposure, v.gamma, v.use_curve_mapping, scene.display_settings.display_device),
        "selected": sorted(o.name for o in scene.objects if o.select_get()),
        "active": active.name if active else None,
    }


def world_triangles(obj):
    mesh = obj.data
    mesh.calc_loop_triangles()
    co = np.array([v.co for v in mesh.vertices], dtype=np.float64)
    m = np.array(obj.matrix_world)
    co = co @ m[:3, :3].T + m[:3, 3]
    return co[np.array([t.vertices for t in mesh.loop_triangles])]


def distance_to_triangles(points, tris):
    """Distance of each point to the nearest triangle whose interior its projection falls in (inf when none)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = np.einsum("ptk,tk->pt", points[:, None, :] - a[None], n)  # signed plane distances (P, T)
    q = points[:, None, :] - d[..., None] * n[None]
    v0, v1, v2 = b - a, c - a, q - a[None]
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    inside = (v >= -1e-6) & (w >= -1e-6) & (v + w <= 1 + 1e-6)
    return np.where(inside, np.abs(d), np.inf).min(axis=1)


def sphere_centroid(rgba):
    """Alpha-weighted centroid (x, y) of the red (sphere) pixels, pixel (i, j) centred at (j + 0.5, i + 0.5); and their count."""
    px = rgba.astype(np.float64) / 255
    red = (px[..., 3] > 0) & (px[..., 0] > px[..., 1] + 0.15) & (px[..., 0] > px[..., 2] + 0.15)
    w = np.where(red, px[..., 3], 0.0)
    i, j = np.indices(w.shape)
    return np.array([((j + 0.5) * w).sum(), ((i + 0.5) * w).sum()]) / w.sum(), int(red.sum())


# ------------------------------------------------------------------ the capture (once for the module)
@pytest.fixture(scope="module")
def captured(extension, tmp_path_factory):
    assert bpy.ops.wm.read_homefile(use_empty=True) == {"FINISHED"}
    scene = build_scene()
    before = snapshot(scene)
    tris = {name: world_triangles(scene.objects[name]) for name in ("Cube", "Sphere")}
    out = tmp_path_factory.mktemp("capture") / "dataset"  # created by the capture
    t0 = time.perf_counter()
    result = bpy.ops.mlx3d.capture_dataset(
        directory=str(out), num_views=6, elevations="10, 40", resolution=(32, 32), samples=4, num_points=3000, test_every=4
    )
    seconds = time.perf_counter() - t0
    assert result == {"FINISHED"}
    with open(out / "transforms.json", encoding="utf-8") as f:
        meta = json.load(f)
    return SimpleNamespace(out=out, meta=meta, before=before, after=snapshot(scene), tris=tris, seconds=seconds)


def test_images_are_rgba_with_transparent_background(captured):
    names = sorted(os.listdir(captured.out / "images"))
    assert names == [f"frame_{i:05d}.png" for i in range(6)]
    for name in names:
        rgba = read_png(captured.out / "images" / name)
        assert rgba.shape == (32, 32, 4)
        assert all(rgba[i, j, 3] == 0 for i in (0, -1) for j in (0, -1)), "corners are background"
        assert rgba[15:17, 15:17, 3].min() > 0, "the objects' centre is covered"


def test_transforms_json(captured):
    meta, out = captured.meta, captured.out
    assert meta["camera_model"] == "PINHOLE"
    assert (meta["w"], meta["h"]) == (32, 32)
    assert meta["cx"] == meta["cy"] == 16.0  # centred camera: cx = w / 2 in nerfstudio's (and COLMAP's) pixel frame
    assert meta["fl_x"] == pytest.approx(meta["fl_y"]) and meta["fl_x"] > 0
    assert meta["ply_file_path"] == "points3d.ply" and (out / "points3d.ply").is_file()
    paths = [f["file_path"] for f in meta["frames"]]
    assert paths == [f"images/frame_{i:05d}.png" for i in range(6)]
    assert meta["test_filenames"] == meta["val_filenames"] == [paths[0], paths[4]]
    assert meta["train_filenames"] == [paths[i] for i in (1, 2, 3, 5)]
    centre = np.array([0.0, 0.0, 0.45])  # of the objects' bounding box
    radii, elevations = [], []
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        assert c2w.shape == (4, 4) and np.allclose(c2w[3], [0, 0, 0, 1])
        r = c2w[:3, :3]
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) == pytest.approx(1.0)  # Blender keeps float32 matrices
        eye = c2w[:3, 3]
        look = -r[:, 2]  # OpenGL cameras look down -z
        assert np.allclose(look, (centre - eye) / np.linalg.norm(centre - eye), atol=1e-6)
        assert abs(r[2, 0]) < 1e-6, "camera x axis is horizontal (world up +Z)"
        radii.append(np.linalg.norm(eye - centre))
        elevations.append(math.degrees(math.asin((eye - centre)[2] / radii[-1])))
    assert np.allclose(radii, 2.2 * np.linalg.norm([0.5, 0.5, 0.95]))  # default radius: 2.2 x the bounding sphere
    assert np.allclose(elevations, [10, 10, 10, 40, 40, 40])


def test_poses_and_intrinsics_project_a_known_point_onto_the_images(captured):
    errors, outline_errors = [], []
    for frame in captured.meta["frames"]:
        expected = project_nerfstudio(captured.meta, frame, SPHERE_CENTRE)
        found, count = sphere_centroid(read_png(captured.out / frame["file_path"]))
        assert count >= 20, f"sphere hardly visible in {frame['file_path']}"
        errors.append(np.linalg.norm(found - expected))
        outline_errors.append(found - sphere_outline_centre(captured.meta, frame, SPHERE_CENTRE, SPHERE_RADIUS))
    assert max(errors) < 1.5, errors  # measured here: 0.29-0.36 px at 32 x 32
    # Sharper: against the centre of the sphere's outline (perspective moves it ~0.15 px off the projected centre),
    # a half-pixel error in cx or cy would show. Measured: |dx| <= 0.03 px; dy -0.12 to -0.20 px because the
    # sphere's lower edge lies over the cube, where mixed pixels do not count as sphere.
    outline_errors = np.array(outline_errors)
    assert np.abs(outline_errors[:, 0]).max() < 0.2 and np.abs(outline_errors[:, 1]).max() < 0.3, outline_errors


def test_colmap_model_matches_transforms_json(captured):
    meta = captured.meta
    cameras, images, points = read_colmap_text(captured.out / "sparse" / "0")
    assert cameras == {1: ("PINHOLE", 32, 32, [meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]])}
    assert [im[4] for im in images] == [f"frame_{i:05d}.png" for i in range(6)]
    assert [im[0] for im in images] == list(range(1, 7))
    for (image_id, q, t, cam_id, name, pts), frame in zip(images, meta["frames"]):
        assert cam_id == 1 and pts == [] and q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        c2w_cv = np.array(frame["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])
        w2c = np.linalg.inv(c2w_cv)
        assert np.allclose(qvec_to_matrix(q), w2c[:3, :3], atol=1e-12)
        assert np.allclose(t, w2c[:3, 3], atol=1e-12)
        xc = qvec_to_matrix(q) @ SPHERE_CENTRE + t  # COLMAP: x = fx X/Z + cx with the same pixel frame
        fx, fy, cx, cy = cameras[1][3]
        uv = np.array([fx * xc[0] / xc[2] + cx, fy * xc[1] / xc[2] + cy])
        assert np.allclose(uv, project_nerfstudio(meta, frame, SPHERE_CENTRE), atol=1e-9)
    ply_xyz, ply_rgb = read_points_ply(captured.out / "points3d.ply")
    assert [p[0] for p in points] == list(range(1, len(ply_xyz) + 1))
    assert np.allclose([p[1] for p in points], ply_xyz, atol=1e-6)
    assert np.array_equal([p[2] for p in points], ply_rgb)
    assert all(p[3] == 0.0 and p[4] == [] for p in points)


def test_points_lie_on_the_surfaces_with_the_material_colours(captured):
    xyz, rgb = read_points_ply(captured.out / "points3d.ply")
    assert len(xyz) == 3000
    on_sphere = np.linalg.norm(xyz - SPHERE_CENTRE, axis=1) < SPHERE_RADIUS + 0.01
    on_cube = np.abs(xyz).max(axis=1) < CUBE_HALF + 1e-4
    assert np.all(on_sphere ^ on_cube)
    assert np.all(np.abs(np.abs(xyz[on_cube]).max(axis=1) - CUBE_HALF) < 1e-4)
    assert distance_to_triangles(xyz[on_sphere], captured.tris["Sphere"]).max() < 1e-4
    # Area weighting: the sphere mesh has ~1/4 of the total area.
    a = lambda t: 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    share = a(captured.tris["Sphere"]) / (a(captured.tris["Sphere"]) + a(captured.tris["Cube"]))
    assert on_sphere.mean() == pytest.approx(share, abs=4 * math.sqrt(share * (1 - share) / 3000))
    assert np.array_equal(np.unique(rgb[on_sphere], axis=0), [srgb8(SPHERE_RGB)])
    assert np.array_equal(np.unique(rgb[on_cube], axis=0), [srgb8(CUBE_RGB)])


def test_mesh_ply_holds_the_captured_triangles_in_world_space(captured):
    from mlx3d.io.mesh_ply import read_mesh_ply

    mesh = read_mesh_ply(captured.out / "mesh.ply")
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    tris = vertices[faces]
    area = lambda t: 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    volume = lambda t: np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0
    blender = np.concatenate([captured.tris["Cube"], captured.tris["Sphere"]])
    assert len(faces) == len(blender) and area(tris) == pytest.approx(area(blender), rel=1e-6)
    key = lambda t: sorted(tuple(sorted(map(tuple, np.round(c, 5)))) for c in t)
    assert key(tris) == key(blender), "the same triangles"
    assert volume(tris) == pytest.approx(volume(blender), rel=1e-5) and volume(tris) > 1.0  # wound outward, like Blender's
    assert len(vertices) == len(np.unique(faces)) == 8 + 32 * 15 + 2  # each object's own vertices, welded
    colours = np.rint(np.asarray(mesh.colors, np.float64) * 255).astype(int)  # uchar in the file, as [0, 1] here
    on_sphere = np.linalg.norm(vertices - SPHERE_CENTRE, axis=1) < SPHERE_RADIUS + 1e-4
    assert on_sphere.sum() == 32 * 15 + 2
    assert np.array_equal(np.unique(colours[on_sphere], axis=0), [srgb8(SPHERE_RGB)])
    assert np.array_equal(np.unique(colours[~on_sphere], axis=0), [srgb8(CUBE_RGB)])


def test_triangle_order_and_first_corner_do_not_change_the_point_sample(extension):
    # the same triangles in another order, each with another corner first, give the same canonical
    # list (so the same seeded points); the winding of every triangle is kept
    capture = extension.addon.capture
    rng = np.random.default_rng(4)
    verts = np.array([rng.permutation(40)[:3] for _ in range(60)])
    loops, mat = verts * 10 + 1, rng.integers(0, 3, 60)
    shuffle, turn = rng.permutation(60), rng.integers(0, 3, 60)
    cols = (turn[:, None] + np.arange(3)) % 3
    rows = np.arange(60)[:, None]
    other = (verts[shuffle][rows, cols], loops[shuffle][rows, cols], mat[shuffle])
    a, b = capture.canonical_triangles(verts, loops, mat), capture.canonical_triangles(*other)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    cyclic = {tuple(np.roll(t, k)) for t in verts for k in range(3)}
    assert all(tuple(t) in cyclic for t in a[0]) and (a[0][:, 0] == a[0].min(axis=1)).all()
    np.testing.assert_array_equal(a[1], a[0] * 10 + 1)  # loops and materials travel with their triangles


def test_scene_is_left_as_it_was(captured):
    assert captured.after == captured.before
    assert captured.seconds < 20


# ------------------------------------------------------------------ cancel, options, errors
def test_modal_operator_renders_a_view_per_tick_and_esc_keeps_what_was_rendered(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    op = extension.addon.operators.MLX3D_OT_capture_dataset
    scene = build_scene()
    before = snapshot(scene)

    session = capture.CaptureSession(tmp_path / "ds", num_views=5, elevations_deg=(20,), resolution=(16, 16), samples=1, num_points=100, test_every=0)
    session.start()
    assert "MLX3D capture camera" in bpy.data.objects and scene.render.engine == "CYCLES"
    state = OperatorState(op, session)
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, MOVE) == {"RUNNING_MODAL"} and len(session.frames) == 1  # the scene stays still, nothing renders
    assert op.modal(state, bpy.context, KEY) == {"RUNNING_MODAL"} and len(session.frames) == 1
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    assert state._session is None and snapshot(scene) == before
    assert state.reports[0] == ({"INFO"}, state.reports[0][1]) and "captured 2 of 5 views (cancelled)" in state.reports[0][1]
    assert sorted(os.listdir(tmp_path / "ds" / "images")) == ["frame_00000.png", "frame_00001.png"]
    meta = json.loads((tmp_path / "ds" / "transforms.json").read_text())
    assert [f["file_path"] for f in meta["frames"]] == ["images/frame_00000.png", "images/frame_00001.png"]
    assert meta["train_filenames"] == [f["file_path"] for f in meta["frames"]] and meta["test_filenames"] == []
    assert [im[4] for im in read_colmap_text(tmp_path / "ds" / "sparse" / "0")[1]] == ["frame_00000.png", "frame_00001.png"]

    session = capture.CaptureSession(tmp_path / "ds #2", num_views=2, elevations_deg=(20,), resolution=(16, 16), samples=1, num_points=100)
    session.start()
    state = OperatorState(op, session)
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, TIMER) == {"FINISHED"}
    assert snapshot(scene) == before and "captured 2 views" in state.reports[0][1]
    assert sorted(os.listdir(tmp_path / "ds #2" / "images")) == ["frame_00000.png", "frame_00001.png"]  # '#' is no frame number here
    # Without a window (background), invoking runs the whole capture at once.
    assert bpy.ops.mlx3d.capture_dataset("INVOKE_DEFAULT", directory=str(tmp_path / "ds3"), num_views=2, resolution=(8, 8), samples=1) == {"FINISHED"}
    assert len(json.loads((tmp_path / "ds3" / "transforms.json").read_text())["frames"]) == 2
    assert snapshot(scene) == before


def test_scene_cameras_give_per_frame_intrinsics(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    scene = build_scene()
    cams = []
    for name, lens, shift, location in [("A", 35.0, 0.1, (4, -4, 3)), ("B", 50.0, 0.0, (-4, -3, 2))]:
        obj = bpy.data.objects.new(name, bpy.data.cameras.new(name))
        scene.collection.objects.link(obj)
        obj.data.lens, obj.data.shift_x = lens, shift
        obj.location = location
        direction = obj.location - bpy.context.scene.objects["Cube"].location
        obj.rotation_euler = direction.to_track_quat("Z", "Y").to_euler()
        obj.scale = (2.0, 2.0, 2.0)  # scale must not leak into the pose
        cams.append(obj)
    bpy.context.view_layer.update()
    before = snapshot(scene)
    info, _ = capture.capture_dataset(tmp_path / "ds", use_scene_cameras=True, resolution=(24, 16), samples=1, num_points=50)
    assert snapshot(scene) == before
    meta = json.loads((tmp_path / "ds" / "transforms.json").read_text())
    assert "fl_x" not in meta and info["frames"] == 3  # A, B and UserCam, sorted by name
    for frame, obj in zip(meta["frames"], [cams[0], cams[1], scene.objects["UserCam"]]):
        m = np.array(obj.matrix_world)
        m[:3, :3] /= np.linalg.norm(m[:3, :3], axis=0)
        assert np.allclose(frame["transform_matrix"], m, atol=1e-6)
        lens, shift = obj.data.lens, obj.data.shift_x
        assert frame["fl_x"] == pytest.approx(lens / 36.0 * 24) and frame["fl_y"] == pytest.approx(lens / 36.0 * 24)
        assert frame["cx"] == pytest.approx(12 - shift * 24) and frame["cy"] == pytest.approx(8.0)
        assert (frame["w"], frame["h"]) == (24, 16)
    cameras, images, _ = read_colmap_text(tmp_path / "ds" / "sparse" / "0")
    assert len(cameras) == 3 and [im[3] for im in images] == [1, 2, 3]


def test_opaque_background_explicit_held_out_frames_and_no_colmap_model(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    scene = build_scene()  # a white world
    before = snapshot(scene)
    info, _ = capture.capture_dataset(tmp_path / "ds", num_views=4, elevations_deg=(20,), resolution=(16, 16), samples=1,
                                      num_points=50, held_out=[3, 1], transparent=False, colmap=False)
    assert snapshot(scene) == before  # film_transparent (False here) restored as well
    out = tmp_path / "ds"
    assert sorted(os.listdir(out)) == ["images", "mesh.ply", "points3d.ply", "transforms.json"]  # no sparse/
    for name in sorted(os.listdir(out / "images")):
        rgba = read_png(out / "images" / name)
        assert rgba.shape == (16, 16, 4) and rgba[..., 3].min() == 255, "opaque: alpha 255 everywhere"
        assert rgba[0, 0, :3].min() >= 250, "the white world background shows in the corners"
    meta = json.loads((out / "transforms.json").read_text())
    paths = [f["file_path"] for f in meta["frames"]]
    assert meta["test_filenames"] == meta["val_filenames"] == [paths[1], paths[3]] == info["test_filenames"]
    assert meta["train_filenames"] == [paths[0], paths[2]]
    if importlib.util.find_spec("PIL") is not None:
        from mlx3d.datasets import load_dataset

        ds = load_dataset(out)  # nerfstudio, with the explicit splits
        assert ds.kind == "nerfstudio" and ds.train == [0, 2] and ds.test == [1, 3]
    empty, _ = capture.capture_dataset(tmp_path / "none", num_views=2, elevations_deg=(20,), resolution=(8, 8), samples=1,
                                       num_points=10, held_out=())
    assert empty["test_filenames"] == [] and len(empty["train_filenames"]) == 2
    assert (tmp_path / "none" / "sparse" / "0" / "images.txt").is_file()  # the COLMAP model by default
    with pytest.raises(capture.CaptureError, match="held_out frames must be indices 0 to 3"):
        capture.capture_dataset(tmp_path / "bad", num_views=4, held_out=[4])
    assert not (tmp_path / "bad").exists()


def test_point_colours_from_colour_attributes_and_defaults(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    scene = bpy.context.scene
    # Two separate quads (x < 0 and x > 0) with a per-corner byte colour attribute, fed to the BSDF by a Color Attribute node.
    mesh = bpy.data.meshes.new("quads")
    verts = [(-2, -1, 0), (-1, -1, 0), (-1, 1, 0), (-2, 1, 0), (1, -1, 0), (2, -1, 0), (2, 1, 0), (1, 1, 0)]
    mesh.from_pydata(verts, [], [(0, 1, 2, 3), (4, 5, 6, 7)])
    attr = mesh.color_attributes.new("Col", "BYTE_COLOR", "CORNER")
    left, right = (1.0, 0.2, 0.0, 1.0), (0.0, 0.5, 1.0, 1.0)
    for i in range(8):
        attr.data[i].color = left if i < 4 else right
    material = bpy.data.materials.new("attr")
    tree = node_tree(material)
    nodes, links = tree.nodes, tree.links
    node = nodes.new("ShaderNodeVertexColor")
    node.layer_name = "Col"
    links.new(node.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
    mesh.materials.append(material)
    quads = bpy.data.objects.new("quads", mesh)
    scene.collection.objects.link(quads)
    # No material: Cycles' default grey. An Emission shader: its Color.
    plain = bpy.data.objects.new("plain", bpy.data.meshes.new("plain"))
    plain.data.from_pydata([(-1, 3, 0), (1, 3, 0), (1, 4, 0)], [], [(0, 1, 2)])
    scene.collection.objects.link(plain)
    glow = bpy.data.materials.new("glow")
    tree = node_tree(glow)
    nodes, links = tree.nodes, tree.links
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Color"].default_value = (0.2, 1.0, 0.2, 1.0)
    links.new(emission.outputs["Emission"], nodes["Material Output"].inputs["Surface"])
    assert capture.material_colour_source(glow) == (pytest.approx((0.2, 1.0, 0.2)), None)
    assert capture.material_colour_source(material)[1] == "Col"
    assert capture.material_colour_source(None) == ((0.8, 0.8, 0.8), None)

    session = capture.CaptureSession(tmp_path / "ds", objects=["quads", plain], num_points=400, seed=3)
    session.close()
    points, colours = session.points, session.colours.astype(int)
    expected_left = srgb8([attr.data[0].color[:3]])[0]
    assert np.array_equal(np.unique(colours[(points[:, 0] < -0.5) & (points[:, 1] < 2)], axis=0), [expected_left])
    assert np.array_equal(np.unique(colours[(points[:, 0] > 0.5) & (points[:, 1] < 2)], axis=0), [srgb8(right[:3])])
    assert np.array_equal(np.unique(colours[points[:, 1] > 2.5], axis=0), [[231, 231, 231]])
    again = capture.CaptureSession(tmp_path / "ds", objects=["quads", plain], num_points=400, seed=3)
    assert np.array_equal(again.points, points), "seeded"


def test_ground_truth_mesh_of_a_mirrored_object_stays_closed_and_outward(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    bpy.ops.mesh.primitive_cube_add(size=2.0, location=(1.0, 2.0, 3.0))
    cube = bpy.context.active_object
    cube.scale = (-1.0, 2.0, 0.5)  # a mirroring transform turns the winding of Blender's triangles
    bpy.context.view_layer.update()
    session = capture.CaptureSession(tmp_path / "ds", objects=[cube], num_points=10)
    session.close()
    assert session.mesh.is_watertight() and session.mesh.volume() == pytest.approx(8.0, rel=1e-6)
    assert np.allclose(session.mesh.vertices.mean(axis=0), (1.0, 2.0, 3.0), atol=1e-6)


def test_no_meshes_is_a_clear_error_and_writes_nothing(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    clean_scene.collection.objects.link(cam)
    before = snapshot(clean_scene)
    with pytest.raises(capture.CaptureError, match="no visible mesh objects"):
        capture.capture_dataset(tmp_path / "ds")
    with pytest.raises(RuntimeError, match="no visible mesh objects"):
        bpy.ops.mlx3d.capture_dataset(directory=str(tmp_path / "ds"))
    with pytest.raises(capture.CaptureError, match="'Cam' is CAMERA, not a mesh"):
        capture.capture_dataset(tmp_path / "ds", objects=["Cam"])
    with pytest.raises(capture.CaptureError, match="no object named 'Nope'"):
        capture.capture_dataset(tmp_path / "ds", objects=["Nope"])
    assert not (tmp_path / "ds").exists()
    assert snapshot(clean_scene) == before


def test_unwritable_folder_is_a_clear_error_before_rendering(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    scene = build_scene()
    before = snapshot(scene)
    blocker = tmp_path / "a_file"
    blocker.write_text("keep me")
    with pytest.raises(capture.CaptureError, match="cannot write the dataset to folder .*a_file"):
        capture.capture_dataset(blocker / "ds", num_views=2, resolution=(8, 8), samples=1)
    with pytest.raises(capture.CaptureError, match="cannot write the dataset to folder"):
        capture.capture_dataset(blocker, num_views=2, resolution=(8, 8), samples=1)
    with pytest.raises(RuntimeError, match="cannot write the dataset"):
        bpy.ops.mlx3d.capture_dataset(directory=str(blocker / "ds"), num_views=2, resolution=(8, 8), samples=1)
    assert blocker.read_text() == "keep me" and sorted(os.listdir(tmp_path)) == ["a_file"]
    if os.geteuid() != 0:  # permissions do not stop root
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        with pytest.raises(capture.CaptureError, match="cannot write"):
            capture.capture_dataset(locked, num_views=2, resolution=(8, 8), samples=1)
        assert os.listdir(locked) == []
    assert snapshot(scene) == before


def test_bad_options_are_refused(extension, clean_scene, tmp_path):
    capture = extension.addon.capture
    build_scene()
    for kwargs, message in [
        (dict(radius=0.5), "inside .* bounding sphere"),
        (dict(elevations_deg=(0, 90)), "strictly between -90 and 90"),
        (dict(elevations_deg=()), "at least one ring"),
        (dict(num_views=0), "num_views must be positive"),
        (dict(resolution=(32, 0)), "resolution must be positive"),
        (dict(test_every=-1), "test_every"),
        (dict(samples=0), "samples must be positive"),
    ]:
        with pytest.raises(capture.CaptureError, match=message):
            capture.capture_dataset(tmp_path / "ds", **kwargs)
    assert not (tmp_path / "ds").exists()


def test_headless_capture(extension, extension_env, clean_scene, tmp_path):
    build_scene()
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    script = os.path.join(os.path.dirname(extension.__file__), "addon", "blender_splat.py")
    out = tmp_path / "ds"
    args = ["capture", "--blend", str(blend), "--out", str(out), "--views", "3", "--resolution", "16", "12", "--samples", "1", "--points", "64"]
    result = subprocess.run([sys.executable, script, *args], env=extension_env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "captured 3 views of 'Cube', 'Sphere' at 16x12 (1 samples) with 64 points" in result.stdout
    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"], len(meta["frames"])) == (16, 12, 3)
    assert read_png(out / "images" / "frame_00002.png").shape == (12, 16, 4)
    bad = subprocess.run([sys.executable, script, "capture", "--blend", str(blend), "--out", str(out / "transforms.json" / "x")],
                         env=extension_env, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "cannot write the dataset to folder" in bad.stderr


def test_panel_capture_section_passes_its_settings(extension, clean_scene):
    settings = clean_scene.mlx3d_splats
    settings.capture_dir, settings.capture_views, settings.capture_samples = "//dataset", 12, 5
    settings.capture_resolution = (64, 48)
    log = []
    extension.addon.panel.VIEW3D_PT_mlx3d_splats.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
    start = log.index(("label", "Capture dataset"))
    props = [entry[1] for entry in log[start:] if entry[0] == "prop"]
    assert {"capture_dir", "capture_views", "capture_radius", "capture_resolution", "capture_samples", "capture_points"} <= set(props)
    (_, idname, op), = [entry for entry in log[start:] if entry[0] == "operator"]
    assert idname == "mlx3d.capture_dataset"
    assert (op.directory, op.num_views, op.samples, tuple(op.resolution), op.radius) == ("//dataset", 12, 5, (64, 48), 0.0)


# ------------------------------------------------------------------ the project's dataset reader
@pytest.mark.skipif(importlib.util.find_spec("mlx3d.datasets") is None, reason="mlx3d.datasets (load_dataset) is not in this checkout yet")
def test_mlx3d_datasets_loads_the_capture(captured):
    pytest.importorskip("PIL", reason="mlx3d.datasets decodes images with Pillow")
    from mlx3d.datasets import load_dataset, load_nerfstudio

    meta = captured.meta
    # load_dataset reads the COLMAP model (no splits there: hold out every 4th as the capture did); nerfstudio has them.
    for ds in (load_dataset(captured.out, test_every=4), load_nerfstudio(captured.out)):
        assert len(ds) == 6 and ds.test == [0, 4] and ds.train == [1, 2, 3, 5]
        xyz, rgb = read_points_ply(captured.out / "points3d.ply")
        assert np.allclose(ds.points, xyz, atol=1e-6) and np.array_equal(ds.point_colors, rgb)
        for frame, cam in zip(meta["frames"], ds.cameras):
            assert cam.model == "pinhole" and (cam.width, cam.height) == (32, 32)
            uv = np.asarray(cam.project_points(SPHERE_CENTRE[None])[0])[0]
            assert np.allclose(uv, project_nerfstudio(meta, frame, SPHERE_CENTRE), atol=1e-6)
        rgb_image, alpha = ds.load_image(1)
        assert rgb_image.shape == (32, 32, 3) and alpha is not None and alpha[0, 0] == 0.0
