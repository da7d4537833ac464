"""Benchmark whole-scene frames: Blender's objects by Cycles, 300k splats by mlx3d, composited by depth.

The splats are a garden capture (``shared/data/test_garden.npz``: 138,766 SfM
points, each Gaussian from its neighbours; jittered copies make up 300,000),
seen through the capture's first camera at 1920x1080; the Blender scene is a
sun, a cube, a sphere and a ground disc among them (Cycles, CPU, 8 samples by
default). Per frame: seconds in Blender's render, the splat pass and the
compositing, against a splat-only frame of the same camera (the meshes hidden,
so no Blender render and no depth test). Target: the splat pass with the depth
test costs at most 10% more than the splat-only one. Frames alternate between
the two, ``--repeats`` each; medians.

    python bench/scene_render.py [--splats 300000] [--size 1920 1080] [--samples 8] [--repeats 5] [--markdown PATH] [--png PATH]

Runs the add-on from this checkout (not an installed extension).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time

import numpy as np

from common import LoadSampler, emit, machine_line  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
GARDEN = os.path.join(os.path.dirname(os.path.dirname(HERE)), "shared", "data", "test_garden.npz")


def garden_splats(count: int, seed: int = 0):
    """(SplatArrays, OpenCV world-to-camera (4,4), K (3,3), width, height) of the garden capture, ``count`` splats."""
    from mlx3d.splatting import GaussianModel

    data = np.load(GARDEN)
    points = data["means3d"].astype(np.float32)
    colours = data["colors"].astype(np.float32) / 255.0
    rng = np.random.default_rng(seed)
    reps = math.ceil(count / len(points))
    spacing = np.median(np.linalg.norm(points[rng.integers(0, len(points), 2000)] - points[rng.integers(0, len(points), 2000)], axis=1)) * 1e-3
    means = np.concatenate([points] + [points + rng.normal(0, spacing, points.shape).astype(np.float32) for _ in range(reps - 1)])[:count]
    cols = np.concatenate([colours] * reps)[:count]
    model = GaussianModel.from_points(means, cols, sh_degree=3)
    return model.to_arrays(), data["viewmats"][0].astype(np.float64), data["Ks"][0].astype(np.float64), int(data["width"]), int(data["height"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--splats", type=int, default=300_000)
    parser.add_argument("--size", type=int, nargs=2, default=(1920, 1080), metavar=("W", "H"))
    parser.add_argument("--samples", type=int, default=8, help="Cycles samples (default 8)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--png", metavar="PATH", help="also save the composited frame")
    args = parser.parse_args()

    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp())
    import bpy
    from mathutils import Matrix

    sys.path.insert(0, os.path.dirname(HERE))  # the add-on package from this checkout
    from addon import scene_render, splat_object

    arrays, w2c, K, width0, height0 = garden_splats(args.splats)
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    width, height = args.size
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", args.samples, False
    scene.view_settings.view_transform = "Standard"
    splat_object.create_splat_object("garden", arrays)

    # The capture's camera: OpenCV (x right, y down, z forward) -> Blender's (y up, looking down -z).
    c2w = np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam)
    cam.matrix_world = Matrix(c2w.tolist())
    cam.data.sensor_fit, cam.data.sensor_width = "HORIZONTAL", 36.0
    cam.data.lens = K[0, 0] / width0 * 36.0  # the capture's horizontal field of view
    scene.camera = cam

    # Meshes among the splats: in front of the camera, at the median depth of the visible points.
    pts = arrays.means.astype(np.float64)
    cam_pts = pts @ w2c[:3, :3].T + w2c[:3, 3]
    depth = float(np.median(cam_pts[cam_pts[:, 2] > 0, 2]))
    centre = c2w[:3, :3] @ np.array([0.0, 0.0, -depth]) + c2w[:3, 3]
    size = 0.08 * depth
    bpy.ops.mesh.primitive_cube_add(size=size, location=tuple(centre + c2w[:3, 0] * size))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6 * size, location=tuple(centre - c2w[:3, 0] * size))
    bpy.ops.mesh.primitive_circle_add(radius=3 * size, fill_type="NGON", location=tuple(centre - c2w[:3, 1] * size))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    scene.collection.objects.link(sun)
    meshes = [o for o in scene.objects if o.type == "MESH"]

    sampler = LoadSampler(5.0)
    sampler.start()
    source = scene_render.SplatSource()
    scene_render.render_frame(scene, source=source)  # warm-up: reads the attributes, compiles
    rows = {"with meshes": [], "splats only": []}
    composited = None
    for _ in range(args.repeats):
        for name, hide in (("with meshes", False), ("splats only", True)):
            for obj in meshes:
                obj.hide_render = hide
            t0 = time.perf_counter()
            frame = scene_render.render_frame(scene, source=source)
            total = time.perf_counter() - t0
            rows[name].append((frame.seconds["blender"], frame.seconds["splats"], frame.seconds["composite"], total, frame.stages))
            if not hide:
                composited = frame
    sampler.stop.set()
    sampler.join()

    def med(name, i):
        return float(np.median([r[i] for r in rows[name]]))

    lines = [
        f"Whole-scene frame at {width}x{height}: {arrays.count:,} splats (SH degree 3) + 3 meshes and a sun, Cycles CPU {args.samples} samples; "
        f"median of {args.repeats}. {machine_line('; ' + sampler.line(2, 1.5))}",
        "",
        "| frame | Blender render (s) | splat pass (s) | compositing (s) | total (s) | stages |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for name in rows:
        lines.append(f"| {name} | {med(name, 0):.2f} | {med(name, 1):.2f} | {med(name, 2):.2f} | {med(name, 3):.2f} | {', '.join(rows[name][-1][4])} |")
    ratio = med("with meshes", 1) / med("splats only", 1)
    lines += ["", f"Splat pass with the depth test / splat-only: {ratio:.2f} (target <= 1.10)."]
    emit("\n".join(lines) + "\n", args.markdown)
    if args.png and composited is not None:
        scene_render.save_frame(scene, composited.rgba, os.path.abspath(args.png), png=True)
        print(f"saved {args.png}")


if __name__ == "__main__":
    main()
