"""Generate the benchmark scene set: Blender scenes rendered like real captures, one folder per scene.

    .venv/bin/python bench/scenes.py [--out bench_data/scenes] [--size 128] [--only NAME,...] [--samples 16]

Every scene is built here with ``bpy`` (headless) and captured with the
add-on's own capture code (``addon/capture.py``: Cycles on the CPU, no
denoiser, fixed seeds), so the same command writes the same data. Each folder
holds a dataset ``mlx3d.datasets.load_dataset`` reads (``bench/train.py
--suite bench_data/scenes`` trains on all of them) and a ``scene.json``
saying what the scene is, what it tests and how it was made. About two
minutes on 2 cores at the default size (128 x 128, 16 samples).

outdoor
    A backdrop that must be reconstructed: four procedurally textured objects
    (checker crate, marbled ball, brick pillar, striped cone) on an 80 m wide
    textured ground running out to the horizon, under a plain sky colour (the
    World background; opaque images, alpha 255). Training: two camera rings
    around the objects (24 views each at 15 and 35 degrees elevation, 3.2 units
    away). Held out: 10 views off the rings (15 to 60 degrees up, 0.7x closer,
    1.2x and 1.4x farther, other azimuths; OUTDOOR_HELD_OUT), so the test views measure novel-view
    synthesis rather than interpolation along a ring. nerfstudio layout
    (``transforms.json`` with explicit ``train_filenames`` / ``test_filenames``)
    and 20k initial points with colours on the objects and on the ground
    within 2.5 units of their middle (none in the sky).
exposure
    ``outdoor`` with every training photo re-exposed as a camera with auto
    exposure and auto white balance would: a gain in 0.55-1.6 and a
    white-balance factor of 0.88-1.12 per channel, applied in linear light
    (per-image values in scene.json). Held-out photos are untouched, so a
    method that bakes the exposure changes into the scene loses PSNR there;
    per-image appearance models (e.g. the bilateral grid) should not.
object_rgba
    An object captured for insertion into another scene: a small textured
    house (brick walls, checker roof, chimney) with a transparent background
    (RGBA, alpha masks). Training rings at 10 and 40 degrees, 10 held-out
    views off the rings; nerfstudio layout with 10k points on the object.
synthetic_nopoints
    The NeRF-synthetic (Blender) layout: ``transforms_train.json`` /
    ``_val`` / ``_test`` with ``camera_angle_x``, images in ``train/``,
    ``val/``, ``test/`` (RGBA, transparent background), a torus with a monkey
    in it, and NO initial points, so training starts from random ones.
    Training views at random on the upper hemisphere, validation views at
    other random places, test views on a ring at 30 degrees between them.
open_points, open_nopoints
    An open scene of another kind than ``outdoor`` (and than the demo): a
    stone plaza (Voronoi cells) running out to the horizon under a warm sky, a
    standing ring, a striped monolith, a chequered ball and a brick plinth
    spread over 2.5 units. 72 training views on three rings (10, 25 and 45
    degrees elevation, 24 each, 3.6 units away), 12 held-out views at other
    heights, distances and azimuths. ``open_nopoints`` is what a capture app
    or Blender's NeRF exporter gives: the NeRF-synthetic layout
    (``transforms_train.json`` / ``transforms_test.json`` with ``camera_model``
    and ``fl_x``), opaque PNGs, no points. ``open_points`` is the same photos
    in the nerfstudio layout with 20k points on the objects and the plaza
    within 3 units: the from-points result to compare with.

Each dataset folder also keeps the capture's ``mesh.ply`` (the captured
objects' triangles, ground truth for mesh extraction). Capture defaults that
differ per scene: ``transparent`` (film), ``held_out`` (explicit test views)
and ``colmap=False`` (so ``load_dataset`` reads the ``transforms.json``
splits rather than a COLMAP model).
"""

from __future__ import annotations

import argparse
import atexit
import json
import math
import os
import shutil
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = ("outdoor", "exposure", "object_rgba", "synthetic_nopoints", "open_points", "open_nopoints")
FORMAT_VERSION = 2  # bump when a scene changes, so stale renders are not reused

# Outdoor and exposure cameras.
RING_ELEVATIONS = (15.0, 35.0)
RING_VIEWS = 48
RING_DISTANCE = 3.2
OUTDOOR_LENS = 40.0  # mm on a 36 mm sensor: 48 degrees across
# Held-out views: (elevation degrees, distance as a multiple of RING_DISTANCE, azimuth degrees).
# None is lower than the lowest ring: the lowest ring (15 degrees, +-24 degree field) sees the sky
# up to 9 degrees above the horizon, and a lower camera at ring distance would look at sky and at
# ground-level space around itself that no training photo shows (no method can know them).
OUTDOOR_HELD_OUT = (
    (20.0, 1.0, 10.0), (20.0, 1.0, 190.0),
    (60.0, 1.0, 80.0), (60.0, 1.0, 260.0),
    (25.0, 0.7, 40.0), (25.0, 0.7, 220.0),
    (25.0, 1.4, 130.0), (25.0, 1.4, 310.0),
    (48.0, 0.85, 160.0), (15.0, 1.2, 345.0),
)
GROUND_SIZE = 80.0  # metres across
POINT_GROUND_RADIUS = 2.5  # initial points on the ground within this distance of the origin (the objects' middle)
EXPOSURE_GAIN = (0.55, 1.6)
WHITE_BALANCE = 0.12  # per-channel factor in 1 +- this
SEED = 0

OBJECT_RINGS = (10.0, 40.0)
OBJECT_DISTANCE = 2.1
OBJECT_HELD_OUT = (
    (-15.0, 1.0, 20.0), (-15.0, 1.0, 200.0),
    (65.0, 1.0, 100.0), (65.0, 1.0, 280.0),
    (25.0, 0.7, 50.0), (25.0, 0.7, 230.0),
    (25.0, 1.4, 140.0), (25.0, 1.4, 320.0),
    (0.0, 1.0, 75.0), (55.0, 0.85, 165.0),
)

OPEN_RINGS = (10.0, 25.0, 45.0)
OPEN_VIEWS = 72
OPEN_DISTANCE = 3.6
OPEN_LENS = 35.0  # mm on a 36 mm sensor: 54 degrees across
OPEN_HELD_OUT = (
    (18.0, 1.0, 7.5), (18.0, 1.0, 187.5), (35.0, 1.0, 97.5), (35.0, 1.0, 277.5),
    (60.0, 1.0, 52.5), (60.0, 1.0, 232.5), (18.0, 0.8, 142.5), (35.0, 0.8, 322.5),
    (25.0, 1.25, 37.5), (25.0, 1.25, 217.5), (50.0, 0.9, 127.5), (14.0, 1.1, 307.5),
)
OPEN_POINT_RADIUS = 3.0

SYNTH_DISTANCE = 4.0
SYNTH_LENS = 50.0  # camera_angle_x = 2 atan(18 / 50) = 0.6911, as in the NeRF-synthetic scenes
SYNTH_TRAIN, SYNTH_VAL, SYNTH_TEST = 60, 4, 12
SYNTH_TEST_ELEVATION = 30.0


# ------------------------------------------------------------------ Blender scene building
def _bpy():
    if "BLENDER_USER_RESOURCES" not in os.environ:  # a throw-away Blender user folder: no user settings or add-ons
        folder = tempfile.mkdtemp(prefix="mlx3d-scenes-")
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        os.environ["BLENDER_USER_RESOURCES"] = folder
    import bpy

    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)  # the add-on package from this checkout
    return bpy


def _new_scene(bpy, sky_rgb, sky_strength, sun_strength, sun_elevation, sun_azimuth):
    """An empty scene with a plain-coloured World and a sun."""
    from addon.demo import node_tree

    assert bpy.ops.wm.read_homefile(use_empty=True) == {"FINISHED"}
    scene = bpy.context.scene
    world = bpy.data.worlds.new("World")
    scene.world = world
    background = node_tree(world).nodes["Background"]
    background.inputs["Color"].default_value = (*sky_rgb, 1.0)
    background.inputs["Strength"].default_value = sky_strength
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = sun_strength
    sun.data.angle = math.radians(3.0)
    sun.rotation_euler = (math.radians(90.0 - sun_elevation), 0.0, math.radians(sun_azimuth))
    scene.collection.objects.link(sun)
    cycles = scene.cycles
    cycles.seed = SEED
    cycles.use_animated_seed = False
    cycles.max_bounces = 4
    cycles.diffuse_bounces = cycles.glossy_bounces = 2
    cycles.transmission_bounces = cycles.volume_bounces = cycles.transparent_max_bounces = 2
    cycles.caustics_reflective = cycles.caustics_refractive = False
    return scene


def _material(bpy, name, texture, colours, scale, roughness=0.6, upright=False, **settings):
    """A Principled BSDF whose Base Color is a procedural texture in object coordinates.

    texture: 'CHECKER', 'BRICK', 'NOISE', 'WAVE' or 'VORONOI'; colours: linear
    RGB tuples (the texture's two colours, or a colour ramp's stops). The Base
    Color socket's own value is set to their mean: the capture seeds point
    colours from it (it does not sample textures). upright: feed the texture
    (x + y, z) instead of (x, y, z), so that a 2D texture (bricks) stands on
    vertical faces.
    """
    from addon.demo import node_tree

    material = bpy.data.materials.new(name)
    tree = node_tree(material)
    nodes, links = tree.nodes, tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = roughness
    coords = nodes.new("ShaderNodeTexCoord")
    kind = {"CHECKER": "ShaderNodeTexChecker", "BRICK": "ShaderNodeTexBrick", "NOISE": "ShaderNodeTexNoise",
            "WAVE": "ShaderNodeTexWave", "VORONOI": "ShaderNodeTexVoronoi"}[texture]
    tex = nodes.new(kind)
    vector = coords.outputs["Object"]
    if upright:
        xyz, add, combine = nodes.new("ShaderNodeSeparateXYZ"), nodes.new("ShaderNodeMath"), nodes.new("ShaderNodeCombineXYZ")
        links.new(vector, xyz.inputs[0])
        links.new(xyz.outputs["X"], add.inputs[0])
        links.new(xyz.outputs["Y"], add.inputs[1])
        links.new(add.outputs[0], combine.inputs["X"])
        links.new(xyz.outputs["Z"], combine.inputs["Y"])
        vector = combine.outputs[0]
    links.new(vector, tex.inputs["Vector"])
    tex.inputs["Scale"].default_value = scale
    for key, value in settings.items():
        if key in tex.inputs:
            tex.inputs[key].default_value = value
        else:
            setattr(tex, key, value)
    if texture in ("CHECKER", "BRICK"):
        tex.inputs["Color1"].default_value = (*colours[0], 1.0)
        tex.inputs["Color2"].default_value = (*colours[1], 1.0)
        if texture == "BRICK":
            tex.inputs["Mortar"].default_value = (*colours[2], 1.0)
        colour = tex.outputs["Color"]
    else:
        ramp = nodes.new("ShaderNodeValToRGB")
        stops = ramp.color_ramp.elements
        while len(stops) < len(colours):
            stops.new(0.5)
        for k, (stop, rgb) in enumerate(zip(stops, colours)):
            stop.position = k / (len(colours) - 1)
            stop.color = (*rgb, 1.0)
        links.new(tex.outputs["Fac"] if texture != "VORONOI" else tex.outputs["Distance"], ramp.inputs["Fac"])
        colour = ramp.outputs["Color"]
    links.new(colour, bsdf.inputs["Base Color"])
    mean = np.mean(np.asarray(colours[:2] if texture == "BRICK" else colours, dtype=np.float64), axis=0)
    bsdf.inputs["Base Color"].default_value = (*mean, 1.0)
    material.diffuse_color = (*mean, 1.0)
    return material


def _add(bpy, primitive, name, material, location, rotation=(0.0, 0.0, 0.0), smooth=False, **kwargs):
    """A mesh primitive with ``material`` (not the UV sphere: its element order changes from run to run)."""
    getattr(bpy.ops.mesh, f"primitive_{primitive}_add")(location=location, rotation=rotation, **kwargs)
    obj = bpy.context.active_object
    obj.name = obj.data.name = name
    obj.data.materials.append(material)
    if smooth:
        obj.data.shade_smooth()
    return obj


def _remove_bottom(bpy, obj):
    """Delete the faces an object stands on (hidden by the ground), so that no initial points are sampled there."""
    import bmesh

    bpy.context.view_layer.update()
    world = np.array(obj.matrix_world)
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    hidden = [f for f in bm.faces
              if (world[:3, :3] @ np.array(f.normal))[2] < -0.99 and (world @ np.append(f.calc_center_median()[:], 1.0))[2] < 1e-4]
    bmesh.ops.delete(bm, geom=hidden, context="FACES_ONLY")
    bm.to_mesh(obj.data)
    bm.free()


def _mesh(bpy, scene, name, vertices, faces, material):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in vertices], [], [tuple(f) for f in faces])
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    return obj


def _ground(bpy, scene, material, inner_radius, size, segments=64):
    """The ground as two seamless meshes sharing one material: a disc (points are sampled on it) and the rest out to ``size``."""
    a = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    inner = ring * inner_radius
    disc = _mesh(bpy, scene, "Ground near", np.vstack([[0.0, 0.0, 0.0], inner]),
                 [(0, 1 + k, 1 + (k + 1) % segments) for k in range(segments)], material)
    outer = ring * (size / 2.0)
    far = _mesh(bpy, scene, "Ground far", np.vstack([inner, outer]),
                [(k, segments + k, segments + (k + 1) % segments, (k + 1) % segments) for k in range(segments)], material)
    return disc, far


def build_outdoor(bpy):
    """The outdoor scene; returns (scene, meshes to sample points on, centre of the objects)."""
    scene = _new_scene(bpy, sky_rgb=(0.30, 0.50, 0.90), sky_strength=1.0, sun_strength=3.0, sun_elevation=50.0, sun_azimuth=30.0)
    ground = _material(bpy, "Grass and dirt", "NOISE", [(0.02, 0.05, 0.01), (0.12, 0.20, 0.03), (0.30, 0.20, 0.08), (0.45, 0.38, 0.22)],
                       scale=3.0, roughness=0.9, Detail=10.0, Roughness=0.7)
    near, _ = _ground(bpy, scene, ground, POINT_GROUND_RADIUS, GROUND_SIZE)
    crate = _add(bpy, "cube", "Crate", _material(bpy, "Checker", "CHECKER", [(0.60, 0.08, 0.05), (0.85, 0.75, 0.55)], scale=6.0),
                 location=(-0.35, 0.15, 0.3), rotation=(0.0, 0.0, math.radians(25.0)), size=0.6)
    ball = _add(bpy, "ico_sphere", "Ball", _material(bpy, "Marble", "NOISE", [(0.01, 0.03, 0.25), (0.05, 0.35, 0.45), (0.90, 0.90, 0.85), (0.02, 0.10, 0.40)],
                                                      scale=6.0, roughness=0.3, Detail=6.0, Roughness=0.65),
                location=(0.42, -0.22, 0.3), radius=0.3, subdivisions=4, smooth=True)
    pillar = _add(bpy, "cylinder", "Pillar", _material(bpy, "Bricks", "BRICK", [(0.45, 0.12, 0.06), (0.30, 0.20, 0.12), (0.6, 0.6, 0.55)],
                                                         scale=4.0, roughness=0.8, upright=True),
                  location=(0.25, 0.5, 0.45), radius=0.18, depth=0.9, vertices=48, smooth=True)
    cone = _add(bpy, "cone", "Cone", _material(bpy, "Stripes", "WAVE", [(0.80, 0.60, 0.05), (0.10, 0.35, 0.10)], scale=3.0,
                                                 Distortion=4.0, Detail=2.0),
                location=(-0.5, -0.45, 0.25), radius1=0.22, depth=0.5, vertices=48, smooth=True)
    objects = [crate, ball, pillar, cone]
    for obj in (crate, pillar, cone):
        _remove_bottom(bpy, obj)
    centre = _centre(objects)
    return scene, objects + [near], centre


def build_open(bpy):
    """The open plaza scene; returns (scene, meshes to sample points on, centre of the objects)."""
    scene = _new_scene(bpy, sky_rgb=(0.85, 0.70, 0.55), sky_strength=1.0, sun_strength=3.5, sun_elevation=35.0, sun_azimuth=-60.0)
    plaza = _material(bpy, "Plaza stones", "VORONOI", [(0.35, 0.33, 0.30), (0.55, 0.50, 0.42), (0.25, 0.22, 0.20)],
                      scale=4.0, roughness=0.85)
    near, _ = _ground(bpy, scene, plaza, OPEN_POINT_RADIUS, 100.0)
    ring = _add(bpy, "torus", "Ring", _material(bpy, "Ring bands", "WAVE", [(0.10, 0.30, 0.60), (0.90, 0.85, 0.70)], scale=3.0,
                                                  Distortion=2.0),
                location=(-0.8, 0.3, 0.45), rotation=(math.radians(90.0), 0.0, math.radians(30.0)), major_radius=0.35,
                minor_radius=0.1, major_segments=64, minor_segments=16, smooth=True)
    monolith = _add(bpy, "cube", "Monolith", _material(bpy, "Monolith stripes", "WAVE", [(0.15, 0.12, 0.10), (0.80, 0.35, 0.10)],
                                                         scale=5.0, Distortion=1.0, wave_type="BANDS", bands_direction="Z"),
                    location=(0.7, 0.6, 0.6), rotation=(0.0, 0.0, math.radians(-20.0)), size=1.0, scale=(0.3, 0.15, 1.2))
    ball = _add(bpy, "uv_sphere", "Chequered ball", _material(bpy, "Ball checker", "CHECKER", [(0.10, 0.45, 0.15), (0.95, 0.95, 0.90)],
                                                               scale=8.0),
                location=(0.35, -0.7, 0.25), radius=0.25, segments=48, ring_count=24, smooth=True)
    plinth = _add(bpy, "cylinder", "Plinth", _material(bpy, "Plinth bricks", "BRICK", [(0.55, 0.25, 0.12), (0.40, 0.30, 0.25), (0.7, 0.7, 0.65)],
                                                         scale=5.0, roughness=0.8, upright=True),
                  location=(-0.45, -0.55, 0.15), radius=0.35, depth=0.3, vertices=48, smooth=True)
    objects = [ring, monolith, ball, plinth]
    for obj in (monolith, plinth):
        _remove_bottom(bpy, obj)
    return scene, objects + [near], _centre(objects)


def build_object(bpy):
    """A small house for object_rgba; returns (scene, meshes, centre)."""
    scene = _new_scene(bpy, sky_rgb=(0.6, 0.6, 0.6), sky_strength=1.0, sun_strength=3.0, sun_elevation=55.0, sun_azimuth=-40.0)
    walls = _add(bpy, "cube", "Walls", _material(bpy, "House bricks", "BRICK", [(0.70, 0.55, 0.30), (0.55, 0.30, 0.15), (0.85, 0.85, 0.80)],
                                                   scale=5.0, roughness=0.8, upright=True),
                 location=(0.0, 0.0, 0.25), size=1.0, scale=(0.8, 0.55, 0.5))
    roof = _add(bpy, "cone", "Roof", _material(bpy, "Roof tiles", "CHECKER", [(0.35, 0.05, 0.04), (0.12, 0.10, 0.10)], scale=12.0),
                location=(0.0, 0.0, 0.72), rotation=(0.0, 0.0, math.radians(45.0)), radius1=0.62, depth=0.44, vertices=4,
                scale=(1.05, 0.75, 1.0))
    chimney = _add(bpy, "cylinder", "Chimney", _material(bpy, "Chimney", "VORONOI", [(0.2, 0.2, 0.22), (0.55, 0.5, 0.45)], scale=25.0),
                   location=(0.22, 0.1, 0.85), radius=0.07, depth=0.35, vertices=24)
    door = _add(bpy, "cube", "Door", _material(bpy, "Door", "WAVE", [(0.15, 0.07, 0.02), (0.40, 0.22, 0.08)], scale=6.0,
                                                 Distortion=6.0, wave_type="BANDS", bands_direction="Z"),
                location=(-0.1, -0.285, 0.17), size=1.0, scale=(0.18, 0.03, 0.34))
    objects = [walls, roof, chimney, door]
    bpy.context.view_layer.update()
    return scene, objects, _centre(objects)


def build_synthetic(bpy):
    """A torus with a monkey sitting in it; returns (scene, meshes, centre)."""
    scene = _new_scene(bpy, sky_rgb=(0.5, 0.5, 0.5), sky_strength=1.2, sun_strength=2.5, sun_elevation=60.0, sun_azimuth=120.0)
    torus = _add(bpy, "torus", "Torus", _material(bpy, "Torus waves", "WAVE", [(0.05, 0.20, 0.55), (0.85, 0.45, 0.10)], scale=2.0,
                                                    Distortion=3.0, Detail=3.0),
                 location=(0.0, 0.0, -0.35), major_radius=0.75, minor_radius=0.25, major_segments=64, minor_segments=24, smooth=True)
    monkey = _add(bpy, "monkey", "Monkey", _material(bpy, "Monkey cells", "VORONOI", [(0.60, 0.05, 0.35), (0.95, 0.85, 0.30)], scale=6.0),
                  location=(0.0, 0.0, 0.2), rotation=(math.radians(-15.0), 0.0, 0.0), size=1.3, smooth=True)
    subsurf = monkey.modifiers.new("Subdivision", "SUBSURF")
    subsurf.levels = subsurf.render_levels = 1
    objects = [torus, monkey]
    bpy.context.view_layer.update()
    return scene, objects, np.zeros(3)


def _centre(objects) -> np.ndarray:
    """Centre of the world-space bounding box of the objects."""
    corners = np.array([np.array(o.matrix_world) @ np.append(c[:], 1.0) for o in objects for c in o.bound_box])[:, :3]
    return (corners.min(axis=0) + corners.max(axis=0)) / 2.0


# ------------------------------------------------------------------ cameras
def _view(capture, centre, distance, elevation, azimuth) -> np.ndarray:
    """OpenGL camera-to-world pose looking at ``centre`` from ``distance`` at ``elevation`` and ``azimuth`` (degrees; 0: on -Y, counter-clockwise)."""
    pose = capture.orbit_poses(centre, distance, 1, [elevation])[0]
    a = math.radians(azimuth)
    turn = np.eye(4)
    turn[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    return turn @ pose


def _add_cameras(bpy, scene, poses, lens):
    """One scene camera per pose, named so that sorting by name keeps their order."""
    from mathutils import Matrix

    for i, pose in enumerate(poses):
        data = bpy.data.cameras.new(f"view_{i:03d}")
        data.lens, data.sensor_width, data.sensor_fit = lens, 36.0, "HORIZONTAL"
        data.clip_start, data.clip_end = 0.05, 200.0
        obj = bpy.data.objects.new(data.name, data)
        obj.matrix_world = Matrix(pose.tolist())
        scene.collection.objects.link(obj)
    bpy.context.view_layer.update()


def _ring_and_held_out(capture, centre, distance, elevations, held_out, views=RING_VIEWS):
    """``views`` poses on rings at ``elevations`` (split evenly), then the held-out ones."""
    poses = capture.orbit_poses(centre, distance, views, elevations)
    poses += [_view(capture, centre, distance * scale, e, a) for e, scale, a in held_out]
    return poses


# ------------------------------------------------------------------ capture and layouts
def _progress(name, t0):
    def report(done, total):
        if done % 10 == 0 or done == total:
            print(f"  {name}: {done}/{total} views rendered, {time.perf_counter() - t0:.0f} s", flush=True)
    return report


def strip_png_text(path) -> None:
    """Drop the text chunks (tEXt, zTXt, iTXt) of a PNG in place, pixels untouched.

    Blender writes the render date and timings there, so the same render
    would otherwise give different files.
    """
    with open(path, "rb") as f:
        data = f.read()
    out, pos = [data[:8]], 8
    while pos < len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        end = pos + 12 + length
        if data[pos + 4:pos + 8] not in (b"tEXt", b"zTXt", b"iTXt"):
            out.append(data[pos:end])
        pos = end
    with open(path, "wb") as f:
        f.write(b"".join(out))


def _capture(capture, folder, name, **kwargs):
    """``capture.capture_dataset`` with progress lines; the images without their render-time metadata."""
    info, _ = capture.capture_dataset(folder, progress=_progress(name, time.perf_counter()), **kwargs)
    for image in os.listdir(os.path.join(folder, capture.IMAGE_DIR)):
        strip_png_text(os.path.join(folder, capture.IMAGE_DIR, image))
    return info


def _fresh(folder):
    """Remove a previous version of a scene folder (only one this script wrote, or an empty one)."""
    if os.path.isdir(folder) and os.listdir(folder):
        if not os.path.isfile(os.path.join(folder, "scene.json")):
            raise SystemExit(f"{folder} exists and has no scene.json: not removing it (choose another --out)")
        shutil.rmtree(folder)


def _write_json(path, data):
    with open(path, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=2)
        f.write("\n")


def _settings(args):
    return {"size": [args.size, args.size], "samples": args.samples, "engine": "CYCLES (CPU, no denoiser)",
            "seed": SEED, "version": FORMAT_VERSION}


def capture_outdoor(bpy, capture, folder, args):
    scene, objects, centre = build_outdoor(bpy)
    poses = _ring_and_held_out(capture, centre, RING_DISTANCE, RING_ELEVATIONS, OUTDOOR_HELD_OUT)
    _add_cameras(bpy, scene, poses, OUTDOOR_LENS)
    held_out = list(range(RING_VIEWS, len(poses)))
    info = _capture(capture, folder, "outdoor", objects=objects, use_scene_cameras=True, resolution=(args.size, args.size),
                    samples=args.samples, num_points=20000, held_out=held_out, transparent=False, colmap=False, seed=SEED,
                    scene=scene)
    return {
        "name": "outdoor",
        "purpose": "a backdrop that must be reconstructed: textured objects on an 80 m textured ground under a plain sky "
                   "(opaque images); held-out views off the training rings (other heights, closer, farther, other azimuths; none below the "
                   "lowest ring, whose photos are the only ones of the low sky)",
        "layout": "nerfstudio (transforms.json with train_filenames / test_filenames, points3d.ply)",
        "background": "sky colour from the World background, alpha 255",
        "objects": sorted(o.name for o in scene.objects if o.type == "MESH"),
        "points": {"count": info["num_points"], "on": "the objects and the ground within "
                   f"{POINT_GROUND_RADIUS} units of the origin (not the sky)", "sampled_on": [o.name for o in objects]},
        "cameras": _camera_notes(centre, OUTDOOR_LENS, RING_DISTANCE, RING_ELEVATIONS, OUTDOOR_HELD_OUT),
        "train_views": len(info["train_filenames"]), "test_views": len(info["test_filenames"]),
        "settings": _settings(args),
    }


def _camera_notes(centre, lens, distance, rings, held_out, views=RING_VIEWS):
    return {
        "look_at": [round(float(c), 4) for c in centre], "lens_mm": lens, "sensor_mm": 36.0,
        "train": f"{views} views on rings at {', '.join(f'{e:g}' for e in rings)} degrees elevation, "
                 f"distance {distance}",
        "held_out": [{"elevation": e, "distance": round(distance * s, 4), "azimuth": a} for e, s, a in held_out],
    }


def capture_open(bpy, capture, folder, args):
    scene, objects, centre = build_open(bpy)
    poses = _ring_and_held_out(capture, centre, OPEN_DISTANCE, OPEN_RINGS, OPEN_HELD_OUT, OPEN_VIEWS)
    _add_cameras(bpy, scene, poses, OPEN_LENS)
    held_out = list(range(OPEN_VIEWS, len(poses)))
    info = _capture(capture, folder, "open_points", objects=objects, use_scene_cameras=True, resolution=(args.size, args.size),
                    samples=args.samples, num_points=20000, held_out=held_out, transparent=False, colmap=False, seed=SEED,
                    scene=scene)
    return {
        "name": "open_points",
        "purpose": "an open scene (a plaza to the horizon, sky, four objects), opaque photos, trained from its points: "
                   "the result open_nopoints is compared with",
        "layout": "nerfstudio (transforms.json with train_filenames / test_filenames, points3d.ply)",
        "background": "sky colour from the World background, alpha 255",
        "objects": sorted(o.name for o in scene.objects if o.type == "MESH"),
        "points": {"count": info["num_points"], "on": f"the objects and the plaza within {OPEN_POINT_RADIUS} units of the origin",
                   "sampled_on": [o.name for o in objects]},
        "cameras": _camera_notes(centre, OPEN_LENS, OPEN_DISTANCE, OPEN_RINGS, OPEN_HELD_OUT, OPEN_VIEWS),
        "train_views": len(info["train_filenames"]), "test_views": len(info["test_filenames"]),
        "settings": _settings(args),
    }


def make_open_nopoints(source, folder, args):
    """``open_points``' photos in the NeRF-synthetic layout with nerfstudio intrinsics and no points."""
    with open(os.path.join(source, "transforms.json"), encoding="utf-8") as f:
        meta = json.load(f)
    intrinsics = {"camera_model": "PINHOLE", **{k: meta[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}}
    by_name = {fr["file_path"]: fr for fr in meta["frames"]}
    os.makedirs(folder)
    for split, names in (("train", meta["train_filenames"]), ("test", meta["test_filenames"])):
        os.makedirs(os.path.join(folder, split))
        frames = []
        for k, name in enumerate(names):
            shutil.copyfile(os.path.join(source, name), os.path.join(folder, split, f"r_{k}.png"))
            frames.append({"file_path": f"./{split}/r_{k}.png", "transform_matrix": by_name[name]["transform_matrix"]})
        _write_json(os.path.join(folder, f"transforms_{split}.json"), {**intrinsics, "frames": frames})
    with open(os.path.join(source, "scene.json"), encoding="utf-8") as f:
        source_meta = json.load(f)
    return {
        "name": "open_nopoints",
        "purpose": "an open scene as a capture app or Blender's NeRF exporter gives it: NeRF-synthetic layout, opaque "
                   "PNGs, no points (training starts from the photos alone); the same photos as open_points",
        "layout": "nerf_synthetic (transforms_train/test.json with camera_model PINHOLE and fl_x, no camera_angle_x, "
                  "no ply_file_path)",
        "background": "sky colour, alpha 255",
        "points": {"count": 0, "on": "none"},
        "cameras": source_meta["cameras"],
        "train_views": len(meta["train_filenames"]), "test_views": len(meta["test_filenames"]),
        "settings": _settings(args),
    }


def srgb_to_linear(srgb) -> np.ndarray:
    """Inverse of the sRGB transfer function (values in [0, 1])."""
    c = np.asarray(srgb, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def make_exposure(capture, outdoor, folder, args):
    """Copy ``outdoor`` and re-expose its training images (gain and white balance in linear light)."""
    from PIL import Image

    for item in ("transforms.json", "points3d.ply", "mesh.ply"):
        shutil.copy2(os.path.join(outdoor, item), os.path.join(folder, item))
    os.makedirs(os.path.join(folder, "images"))
    with open(os.path.join(outdoor, "transforms.json"), encoding="utf-8") as f:
        meta = json.load(f)
    train = set(meta["train_filenames"])
    rng = np.random.default_rng(SEED + 1)
    changes = {}
    for frame in sorted(meta["frames"], key=lambda fr: fr["file_path"]):
        path = frame["file_path"]
        src, dst = os.path.join(outdoor, path), os.path.join(folder, path)
        if path not in train:
            shutil.copy2(src, dst)
            continue
        gain = float(rng.uniform(*EXPOSURE_GAIN))
        balance = rng.uniform(1.0 - WHITE_BALANCE, 1.0 + WHITE_BALANCE, 3)
        pixels = np.asarray(Image.open(src))
        out = pixels.copy()
        linear = srgb_to_linear(pixels[..., :3] / 255.0) * (gain * balance)
        out[..., :3] = capture.srgb8(linear)  # clips to [0, 1]
        Image.fromarray(out).save(dst)
        changes[path] = {"gain": round(gain, 6), "white_balance": [round(float(b), 6) for b in balance]}
    with open(os.path.join(outdoor, "scene.json"), encoding="utf-8") as f:
        base = json.load(f)
    return {
        **base,
        "name": "exposure",
        "purpose": "outdoor with per-image exposure and white balance on the training photos (held-out photos untouched): "
                   "tests per-image appearance compensation",
        "exposure": {"applied": "sRGB -> linear, multiply by gain x white_balance[channel], clip to [0, 1], -> sRGB 8-bit",
                     "gain_range": list(EXPOSURE_GAIN), "white_balance_range": [1.0 - WHITE_BALANCE, 1.0 + WHITE_BALANCE],
                     "seed": SEED + 1, "per_image": changes},
    }


def capture_object(bpy, capture, folder, args):
    scene, objects, centre = build_object(bpy)
    poses = _ring_and_held_out(capture, centre, OBJECT_DISTANCE, OBJECT_RINGS, OBJECT_HELD_OUT)
    _add_cameras(bpy, scene, poses, OUTDOOR_LENS)
    info = _capture(capture, folder, "object_rgba", objects=objects, use_scene_cameras=True, resolution=(args.size, args.size),
                    samples=args.samples, num_points=10000, held_out=range(RING_VIEWS, len(poses)), colmap=False, seed=SEED,
                    scene=scene)
    return {
        "name": "object_rgba",
        "purpose": "an object captured for insertion: textured house, transparent background (RGBA alpha masks); "
                   "held-out views off the training rings",
        "layout": "nerfstudio (transforms.json with train_filenames / test_filenames, points3d.ply)",
        "background": "transparent (alpha 0)",
        "objects": [o.name for o in objects],
        "points": {"count": info["num_points"], "on": "the objects"},
        "cameras": _camera_notes(centre, OUTDOOR_LENS, OBJECT_DISTANCE, OBJECT_RINGS, OBJECT_HELD_OUT),
        "train_views": len(info["train_filenames"]), "test_views": len(info["test_filenames"]),
        "settings": _settings(args),
    }


def _hemisphere(rng, count, low=5.0, high=80.0):
    """(elevation, azimuth) in degrees of ``count`` directions uniform on the sphere between elevations ``low`` and ``high``."""
    z = rng.uniform(math.sin(math.radians(low)), math.sin(math.radians(high)), count)
    return np.degrees(np.arcsin(z)), rng.uniform(0.0, 360.0, count)


def capture_synthetic(bpy, capture, folder, args):
    scene, objects, centre = build_synthetic(bpy)
    rng = np.random.default_rng(SEED + 2)
    elevation, azimuth = _hemisphere(rng, SYNTH_TRAIN + SYNTH_VAL)
    test_azimuth = 15.0 + 360.0 / SYNTH_TEST * np.arange(SYNTH_TEST)
    views = list(zip(elevation, azimuth)) + [(SYNTH_TEST_ELEVATION, a) for a in test_azimuth]
    _add_cameras(bpy, scene, [_view(capture, centre, SYNTH_DISTANCE, e, a) for e, a in views], SYNTH_LENS)
    _capture(capture, folder, "synthetic_nopoints", objects=objects, use_scene_cameras=True, resolution=(args.size, args.size),
             samples=args.samples, num_points=1, test_every=0, colmap=False, seed=SEED, scene=scene)
    _nerf_synthetic_layout(folder, {"train": range(SYNTH_TRAIN), "val": range(SYNTH_TRAIN, SYNTH_TRAIN + SYNTH_VAL),
                                    "test": range(SYNTH_TRAIN + SYNTH_VAL, len(views))})
    return {
        "name": "synthetic_nopoints",
        "purpose": "NeRF-synthetic layout without initial points (training starts from random points); "
                   "RGBA with transparent background",
        "layout": "nerf_synthetic (transforms_train/val/test.json, camera_angle_x, file_path without extension)",
        "background": "transparent (alpha 0)",
        "objects": [o.name for o in objects],
        "points": {"count": 0, "on": "none"},
        "cameras": {"look_at": [0.0, 0.0, 0.0], "distance": SYNTH_DISTANCE, "lens_mm": SYNTH_LENS, "sensor_mm": 36.0,
                    "train": f"{SYNTH_TRAIN} views at random on the upper hemisphere (elevation 5-80 degrees, seed {SEED + 2})",
                    "val": f"{SYNTH_VAL} further random views",
                    "test": f"{SYNTH_TEST} views on a ring at {SYNTH_TEST_ELEVATION:g} degrees elevation"},
        "train_views": SYNTH_TRAIN, "val_views": SYNTH_VAL, "test_views": SYNTH_TEST,
        "settings": _settings(args),
    }


def _nerf_synthetic_layout(folder, splits):
    """Turn a capture's transforms.json and images/ into transforms_{split}.json and {split}/r_{k}.png; drop the points."""
    with open(os.path.join(folder, "transforms.json"), encoding="utf-8") as f:
        meta = json.load(f)
    angle_x = 2.0 * math.atan(0.5 * meta["w"] / meta["fl_x"])
    for split, indices in splits.items():
        os.makedirs(os.path.join(folder, split))
        frames = []
        for k, i in enumerate(indices):
            frame = meta["frames"][i]
            os.replace(os.path.join(folder, frame["file_path"]), os.path.join(folder, split, f"r_{k}.png"))
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": frame["transform_matrix"]})
        _write_json(os.path.join(folder, f"transforms_{split}.json"), {"camera_angle_x": angle_x, "frames": frames})
    os.rmdir(os.path.join(folder, "images"))
    for name in ("transforms.json", "points3d.ply"):
        os.remove(os.path.join(folder, name))


# ------------------------------------------------------------------ driver
def _reusable(folder, args) -> bool:
    """Whether ``folder`` holds a finished scene made with these settings."""
    try:
        with open(os.path.join(folder, "scene.json"), encoding="utf-8") as f:
            return json.load(f).get("settings") == _settings(args)
    except (OSError, ValueError):
        return False


def _folder_mb(folder) -> float:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(folder) for f in files) / 1e6


def main() -> None:
    from common import parse_only  # bench/ is on sys.path when run as a script

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join("bench_data", "scenes"), help="output folder (default bench_data/scenes)")
    parser.add_argument("--size", type=int, default=128, help="image width and height in pixels (default 128)")
    parser.add_argument("--only", help=f"comma-separated scenes to make (of {', '.join(SCENES)})")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    args = parser.parse_args()
    only = parse_only(parser, args.only, SCENES, "scene")
    if args.size < 8 or args.samples < 1:
        parser.error("--size must be at least 8 and --samples at least 1")

    t_start = time.perf_counter()
    bpy = _bpy()
    from addon import capture

    os.makedirs(args.out, exist_ok=True)
    print(f"Blender {bpy.app.version_string}, Cycles on the CPU, {args.size}x{args.size}, {args.samples} samples, into {args.out}", flush=True)
    seconds = {}
    todo = [s for s in SCENES if s in only]
    outdoor = os.path.join(args.out, "outdoor")
    if "exposure" in todo and "outdoor" not in todo and not _reusable(outdoor, args):
        print("exposure re-exposes the outdoor renders: making outdoor first", flush=True)
        todo.insert(0, "outdoor")
    open_points = os.path.join(args.out, "open_points")
    if "open_nopoints" in todo and "open_points" not in todo and not _reusable(open_points, args):
        print("open_nopoints copies the open_points renders: making open_points first", flush=True)
        todo.insert(todo.index("open_nopoints"), "open_points")
    for name in todo:
        folder = os.path.join(args.out, name)
        print(f"{name}: ...", flush=True)
        t0 = time.perf_counter()
        _fresh(folder)
        if name == "outdoor":
            meta = capture_outdoor(bpy, capture, folder, args)
        elif name == "exposure":
            os.makedirs(folder)
            meta = make_exposure(capture, outdoor, folder, args)
        elif name == "object_rgba":
            meta = capture_object(bpy, capture, folder, args)
        elif name == "open_points":
            meta = capture_open(bpy, capture, folder, args)
        elif name == "open_nopoints":
            meta = make_open_nopoints(open_points, folder, args)
        else:
            meta = capture_synthetic(bpy, capture, folder, args)
        seconds[name] = time.perf_counter() - t0
        meta["command"] = "python bench/scenes.py " + " ".join(sys.argv[1:])
        meta["seconds"] = round(seconds[name], 1)
        _write_json(os.path.join(folder, "scene.json"), meta)
        print(f"{name}: done in {seconds[name]:.1f} s", flush=True)

    from mlx3d.datasets import load_dataset

    rows = []
    for name in todo:
        folder = os.path.join(args.out, name)
        ds = load_dataset(folder)
        points = 0 if ds.points is None else len(ds.points)
        rows.append((name, ds.kind, f"{len(ds.train)}/{len(ds.test)}", f"{points:,}", f"{args.size}x{args.size}",
                     f"{_folder_mb(folder):.1f}", f"{seconds[name]:.1f}"))
    head = ("scene", "layout", "train/test", "points", "size", "MB", "seconds")
    widths = [max(len(h), *(len(r[k]) for r in rows)) for k, h in enumerate(head)]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"
    print()
    print(line(head))
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in rows:
        print(line(row))
    print(f"\n{len(rows)} scenes in {time.perf_counter() - t_start:.1f} s, in {os.path.abspath(args.out)}")


if __name__ == "__main__":
    main()
