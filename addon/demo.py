"""The end-to-end demo in Blender (``blender_splat.py demo``): scene, capture, training, evaluation, round trip.

``run_demo(out_dir)`` does the add-on's whole job on a scene it builds from code:

1. ``build_demo_scene()``: a ground disc with a checker texture, a cube with
   a noise texture, a sphere with wave stripes and a plain magenta Suzanne,
   lit by a sun and a grey world (object scale: radius about 1.05).
2. ``capture.capture_dataset``: Cycles RGBA renders from an orbit of cameras
   (transparent background), nerfstudio + COLMAP cameras and initial points
   sampled on the surfaces; every 8th view is held out.
3. ``train.train_dataset``: vanilla 3DGS from the initial points, capped in
   Gaussians, on the training views composited on white (the SH degree rises
   every quarter of the steps, so all bands train).
4. ``mlx3d.training.evaluate.evaluate``: PSNR and SSIM on the held-out views,
   composited on the same white; ground truth | render pairs in ``renders/``.
   The report adds ``psnr_foreground``: the PSNR over the pixels the scene
   covers (alpha > 0) only, pooled over the views, since the empty
   background is easy to reproduce and raises the full-image PSNR.
5. ``workflows.export_splat_file`` writes ``trained.ply``;
   ``workflows.import_splat_file`` reads it back into a fresh scene (with a
   camera at a held-out view), saved as ``demo.blend``.
6. ``side_by_side.png`` (ground truth | render of the held-out view with the
   median PSNR) and ``metrics.json`` (the evaluation report plus the demo's
   settings, counts and stage times).

Files under ``out_dir``: ``scene.blend`` (the built scene), ``dataset/``
(the capture), ``trained.ply``, ``demo.blend``, ``renders/``,
``side_by_side.png``, ``metrics.json``.

``quick=True`` runs the same steps at toy sizes (8 views at 32 x 32, 100
steps) for tests. The current Blender file is replaced (the demo starts from
an empty scene and ends with ``demo.blend`` open).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time

import bpy
import numpy as np

from mlx3d.io import atomic_write

from . import capture, train, workflows
from .splat_object import read_splats

BACKGROUND = "white"  # training and evaluation composite the transparent capture background on this
BACKGROUND_RGB = (1.0, 1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class DemoSettings:
    """Sizes of one demo run (``DEFAULT`` and ``QUICK``)."""

    views: int
    resolution: int  # square images, pixels
    samples: int  # Cycles samples per pixel
    num_points: int  # initial points sampled on the surfaces
    steps: int
    max_gaussians: int
    sh_degree: int = 3
    elevations_deg: tuple = (15.0, 35.0, 60.0)
    test_every: int = 8
    seed: int = 0


DEFAULT = DemoSettings(views=80, resolution=256, samples=32, num_points=15_000, steps=2000, max_gaussians=30_000)
QUICK = DemoSettings(views=8, resolution=32, samples=4, num_points=2000, steps=100, max_gaussians=4000,
                     elevations_deg=(20.0, 45.0))


# ------------------------------------------------------------------ scene
def node_tree(idblock):
    """The node tree of a material or world, switching nodes on where Blender still has the toggle (4.x)."""
    if getattr(idblock, "node_tree", None) is None:
        idblock.use_nodes = True
    return idblock.node_tree


def _material(name, *, base_rgb, roughness=0.8, texture=None):
    """A Principled BSDF material; ``texture(nodes, links, bsdf_input)`` feeds its Base Color.

    ``base_rgb`` (linear) stays the socket's own value, which is what the
    capture colours its initial points with (it does not sample textures):
    the texture's mean colour.
    """
    material = bpy.data.materials.new(name)
    tree = node_tree(material)
    bsdf = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (*base_rgb, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    material.diffuse_color = (*base_rgb, 1.0)
    if texture is not None:
        texture(tree.nodes, tree.links, bsdf.inputs["Base Color"])
    return material


def _checker(colour1, colour2, scale):
    def build(nodes, links, target):
        node = nodes.new("ShaderNodeTexChecker")
        node.inputs["Color1"].default_value = (*colour1, 1.0)
        node.inputs["Color2"].default_value = (*colour2, 1.0)
        node.inputs["Scale"].default_value = scale
        links.new(node.outputs["Color"], target)
    return build


def _ramp(source_type, source_output, colour1, colour2, **inputs):
    """A procedural texture (``source_type``) through a two-colour ramp."""
    def build(nodes, links, target):
        source = nodes.new(source_type)
        for key, value in inputs.items():
            source.inputs[key].default_value = value
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (*colour1, 1.0)
        ramp.color_ramp.elements[1].color = (*colour2, 1.0)
        links.new(source.outputs[source_output], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], target)
    return build


def _mean(a, b):
    return tuple((x + y) / 2.0 for x, y in zip(a, b))


def build_demo_scene(scene=None) -> list:
    """Build the demo scene into ``scene`` (default: the current one); returns its mesh objects.

    A ground disc of radius 1 (checker texture), a cube with a noise
    texture, a sphere with wave stripes and a magenta Suzanne, with a sun
    and a grey world light. Linear colours; everything fits a sphere of
    radius about 1.05. Base Color sockets fed by a texture keep the
    texture's mean colour as their own value: the capture colours its
    initial points with it (it does not sample textures).
    """
    scene = scene or bpy.context.scene
    collection = scene.collection

    def add_mesh(op, name, material, **kwargs):
        op(**kwargs)
        obj = bpy.context.active_object
        obj.name = obj.data.name = name
        obj.data.materials.append(material)
        return obj

    cream, slate = (0.80, 0.72, 0.52), (0.06, 0.10, 0.20)
    ground = add_mesh(bpy.ops.mesh.primitive_circle_add, "Ground",
                      _material("Ground checker", base_rgb=_mean(cream, slate), roughness=0.9,
                                texture=_checker(cream, slate, 8.0)),
                      vertices=64, radius=1.0, fill_type="NGON", location=(0.0, 0.0, 0.0))
    orange, red = (0.90, 0.35, 0.03), (0.25, 0.02, 0.02)
    cube = add_mesh(bpy.ops.mesh.primitive_cube_add, "Cube",
                    _material("Cube noise", base_rgb=_mean(orange, red),
                              texture=_ramp("ShaderNodeTexNoise", "Fac", red, orange, Scale=4.0, Detail=6.0)),
                    size=0.6, location=(-0.4, 0.25, 0.3), rotation=(0.0, 0.0, math.radians(30.0)))
    teal, white = (0.02, 0.35, 0.30), (0.90, 0.90, 0.85)
    sphere = add_mesh(bpy.ops.mesh.primitive_uv_sphere_add, "Sphere",
                      _material("Sphere stripes", base_rgb=_mean(teal, white), roughness=0.6,
                                texture=_ramp("ShaderNodeTexWave", "Fac", teal, white, Scale=3.0)),
                      radius=0.35, segments=48, ring_count=24, location=(0.42, 0.28, 0.35))
    monkey = add_mesh(bpy.ops.mesh.primitive_monkey_add, "Suzanne",
                      _material("Suzanne magenta", base_rgb=(0.60, 0.05, 0.45), roughness=0.7),
                      size=0.6, location=(0.0, -0.42, 0.33), rotation=(math.radians(-10.0), 0.0, math.radians(-15.0)))
    for obj in (sphere, monkey):
        for poly in obj.data.polygons:
            poly.use_smooth = True

    sun_data = bpy.data.lights.new("Sun", "SUN")
    sun_data.energy = 3.0
    sun_data.angle = math.radians(8.0)
    sun = bpy.data.objects.new("Sun", sun_data)
    sun.rotation_euler = (math.radians(40.0), 0.0, math.radians(30.0))
    collection.objects.link(sun)

    world = scene.world or bpy.data.worlds.new("World")
    scene.world = world
    background = next(n for n in node_tree(world).nodes if n.type == "BACKGROUND")
    background.inputs["Color"].default_value = (0.40, 0.42, 0.45, 1.0)
    background.inputs["Strength"].default_value = 1.0
    bpy.context.view_layer.update()
    return [ground, cube, sphere, monkey]


# ------------------------------------------------------------------ run
class _Log:
    """``progress(line)`` (default: print to stdout), with per-stage timing."""

    def __init__(self, progress):
        self.write = progress or (lambda line: print(line, flush=True))
        self.t0 = time.perf_counter()
        self.seconds: dict = {}

    def stage(self, name, t_start):
        self.seconds[name] = time.perf_counter() - t_start


def _capture_progress(write, every=0.1):
    t0 = time.perf_counter()
    state = {"next": 0}

    def progress(done, total):
        step = max(1, round(total * every))
        if done >= state["next"] or done == total:
            state["next"] = done + step
            write(f"capture: {done}/{total} views ({time.perf_counter() - t0:.1f} s)")
    return progress


def _train_progress(write, lines=20):
    state = {"next": None}

    def progress(done, total, status):
        every = max(1, math.ceil(total / lines))
        if state["next"] is None:
            state["next"] = every
        if done >= state["next"] or done == total:
            while state["next"] <= done:
                state["next"] += every
            write(f"train: {train.format_status(status)}")
    return progress


def _foreground_psnr(model, dataset, indices) -> float:
    """PSNR over the pixels the scene covers (alpha > 0) of the views, pooled, on the demo's background.

    The full-image PSNR of ``evaluate`` also counts the empty background,
    which is easy to reproduce; this one leaves it out.
    """
    squared, count = 0.0, 0
    for i in indices:
        target, _ = dataset.load_image(i, background=BACKGROUND_RGB)
        _, coverage = dataset.load_image(i)
        image = np.clip(np.array(model.render(dataset.frames[i].camera, background=BACKGROUND_RGB)["image"]), 0.0, 1.0)
        covered = coverage > 0 if coverage is not None else np.ones(target.shape[:2], bool)
        squared += float(np.sum((image[covered] - target[covered]) ** 2, dtype=np.float64))
        count += int(covered.sum()) * 3
    return float(10.0 * np.log10(count / squared)) if squared > 0 else float("inf")


def _add_view_camera(camera, scene, name="Held-out view"):
    """A Blender camera object at an mlx3d pinhole camera's pose and field of view (square sensor fit)."""
    from mathutils import Matrix

    data = bpy.data.cameras.new(name)
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = camera.fx * data.sensor_width / camera.width
    obj = bpy.data.objects.new(name, data)
    obj.matrix_world = Matrix(camera.to_opengl_c2w().tolist())
    scene.collection.objects.link(obj)
    scene.camera = obj
    scene.render.resolution_x, scene.render.resolution_y = camera.width, camera.height
    scene.render.resolution_percentage = 100
    return obj


def run_demo(out_dir="demo_out", quick=False, progress=None, settings: DemoSettings | None = None) -> dict:
    """Run the demo into ``out_dir``; returns the report written to ``metrics.json``.

    quick: toy sizes (``QUICK``) for tests; settings: explicit sizes
    (overrides ``quick``); progress: ``progress(line)`` for each progress and
    result line (default: print).
    """
    from mlx3d.datasets import load_dataset
    from mlx3d.splatting import GaussianModel
    from mlx3d.training.evaluate import evaluate

    s = settings or (QUICK if quick else DEFAULT)
    log = _Log(progress)
    write = log.write
    out = os.path.abspath(os.fspath(out_dir))
    os.makedirs(out, exist_ok=True)
    data_dir = os.path.join(out, "dataset")
    if os.path.isdir(data_dir):  # stale frames of an earlier run would not be part of this capture
        shutil.rmtree(data_dir)
    renders = os.path.join(out, "renders")
    if os.path.isdir(renders):
        shutil.rmtree(renders)

    # 1. scene
    t = time.perf_counter()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    objects = build_demo_scene(scene)
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(out, "scene.blend"), check_existing=False)
    log.stage("scene", t)
    write(f"scene: {', '.join(o.name for o in objects)} with a sun and world light "
          f"({sum(len(o.data.polygons) for o in objects):,} faces); saved scene.blend ({log.seconds['scene']:.1f} s)")

    # 2. capture
    t = time.perf_counter()
    info, messages = capture.capture_dataset(
        data_dir, objects=objects, num_views=s.views, elevations_deg=s.elevations_deg,
        resolution=(s.resolution, s.resolution), samples=s.samples, num_points=s.num_points,
        test_every=s.test_every, seed=s.seed, progress=_capture_progress(write), scene=scene,
    )
    log.stage("capture", t)
    for message in messages:
        write(f"capture: {message}")

    # 3. train
    t = time.perf_counter()
    dataset = load_dataset(data_dir)
    trained, messages = train.train_dataset(
        dataset, steps=s.steps, method="vanilla", max_gaussians=s.max_gaussians, sh_degree=s.sh_degree,
        background=BACKGROUND, seed=s.seed, progress=_train_progress(write),
        sh_increase_every=max(1, s.steps // (s.sh_degree + 1)),
    )
    log.stage("train", t)
    for message in messages:
        if not message.startswith("test PSNR"):  # the evaluation below reports PSNR and SSIM
            write(f"train: {message}")

    # 4. evaluate on the held-out views
    t = time.perf_counter()
    model = GaussianModel.from_arrays(read_splats(trained)[0])  # the object holds the final model, identity transform
    report = evaluate(model, dataset, split="test", background=BACKGROUND_RGB, out_dir=out)
    report["psnr_foreground"] = _foreground_psnr(model, dataset, dataset.test)
    log.stage("evaluate", t)
    views = report["views"]
    median = sorted(views, key=lambda v: v["psnr"])[len(views) // 2]
    name = os.path.splitext(os.path.basename(median["name"]))[0] + ".png"
    shutil.copyfile(os.path.join(renders, name), os.path.join(out, "side_by_side.png"))
    write(f"evaluate: {len(views)} held-out view{'' if len(views) == 1 else 's'}: PSNR {report['psnr']:.2f} dB, SSIM {report['ssim']:.4f} "
          f"(views {min(v['psnr'] for v in views):.2f}-{max(v['psnr'] for v in views):.2f} dB; "
          f"{report['psnr_foreground']:.2f} dB on the pixels the scene covers)")
    write(f"evaluate: side_by_side.png is {name} (the median view, PSNR {median['psnr']:.2f} dB)")

    # 5. export, import into a fresh scene, save
    t = time.perf_counter()
    ply = os.path.join(out, "trained.ply")
    count, messages = workflows.export_splat_file(ply, [trained])
    for message in messages:
        write(f"export: {message}")
    bpy.ops.wm.read_homefile(use_empty=True)
    imported, messages = workflows.import_splat_file(ply)
    for message in messages:
        write(f"import: {message}")
    held_out = dataset.frames[next(i for i in dataset.test if dataset.frames[i].name == median["name"])].camera
    _add_view_camera(held_out, bpy.context.scene)
    blend = os.path.join(out, "demo.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend, check_existing=False)
    log.stage("export_import", t)
    write(f"saved demo.blend: '{imported.name}' ({count:,} splats) and a camera at {median['name']}")

    total = time.perf_counter() - log.t0
    result = dict(report)
    result.update({
        "demo": {"quick": bool(quick), **dataclasses.asdict(s), "background": BACKGROUND, "method": "vanilla"},
        "train_views": len(dataset.train), "test_views": len(dataset.test),
        "num_points": info["num_points"], "num_gaussians": count, "scene_radius": info["bound_radius"],
        "side_by_side": {"view": median["name"], "psnr": median["psnr"], "ssim": median["ssim"]},
        "seconds": {**{k: round(v, 2) for k, v in log.seconds.items()}, "total": round(total, 2)},
        "files": {k: os.path.join(out, v) for k, v in [("ply", "trained.ply"), ("blend", "demo.blend"),
                                                     ("scene", "scene.blend"), ("dataset", "dataset"),
                                                     ("side_by_side", "side_by_side.png")]},
    })
    with atomic_write(os.path.join(out, "metrics.json"), mode="w") as f:
        json.dump(result, f, indent=2)
    times = ", ".join(f"{k} {v:.1f} s" for k, v in log.seconds.items())
    write(f"demo finished in {total:.1f} s ({times}); files in {out_dir}/")
    return result
