"""Our splat render against Blender 5.3's own EEVEE and Cycles splat renders, on one camera.

Imports a 3DGS PLY (default: ``../shared/data/opensplat_trained.ply``) with the add-on, points a
camera at it over a black world, and renders it three ways: the add-on's *Render Image*
(``scene_render.render_frame``: 3DGS rasterization by ``mlx3d``), EEVEE and Cycles (Blender's
own splat drawing of the same object). Prints each render's time and the PSNR between them, with
Blender's linear output read two ways (as display values, and encoded with the sRGB curve as
the Standard view does), which is how the colour-space question is answered. Needs ``bpy`` 5.3+.

    .venv-blender53/bin/python bench/blender_native.py [--ply PATH] [--size 256] [--samples 64] [--markdown PATH]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time

import numpy as np

from common import emit, machine_line  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_PLY = os.path.join(HERE, "..", "..", "shared", "data", "opensplat_trained.ply")


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


def srgb_encode(x):
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ply", default=DEFAULT_PLY)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--samples", type=int, default=64, help="Cycles samples")
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--png", metavar="PATH", help="also write ours | EEVEE | Cycles side by side (Standard view)")
    args = parser.parse_args()

    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp())
    import bpy

    if bpy.app.version < (5, 3, 0):
        sys.exit(f"Blender {bpy.app.version_string} has no splat rendering of its own (5.3+ does)")
    sys.path.insert(0, os.path.dirname(HERE))  # the add-on package from this checkout
    import addon
    from addon import scene_render, workflows

    addon.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    obj, _ = workflows.import_splat_file(args.ply)
    positions = np.empty(len(obj.data.points) * 3, np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", positions)
    positions = positions.reshape(-1, 3)
    centre = np.median(positions, axis=0)
    spread = np.percentile(np.linalg.norm(positions - centre, axis=1), 80)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.location = tuple(centre + np.array([0.0, 4.0 * spread, 0.0]))  # outside the scene, looking along -y
    camera.rotation_euler = (math.pi / 2, 0.0, math.pi)
    scene.render.resolution_x = scene.render.resolution_y = args.size
    scene.render.resolution_percentage = 100
    world = bpy.data.worlds.new("black")
    world.color = (0.0, 0.0, 0.0)
    scene.world = world
    scene.view_settings.view_transform = "Standard"
    scene.render.film_transparent = False

    def blender(engine):
        scene.render.engine = engine
        if engine == "CYCLES":
            scene.cycles.device, scene.cycles.samples, scene.cycles.seed = "CPU", args.samples, 0
        path = os.path.join(tempfile.mkdtemp(), f"{engine}.exr")
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.filepath = path
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds = time.perf_counter() - t0
        image = bpy.data.images.load(path)
        linear = np.array(image.pixels[:], np.float32).reshape(args.size, args.size, 4)[::-1, :, :3]
        bpy.data.images.remove(image)
        return linear, seconds

    t0 = time.perf_counter()
    frame = scene_render.render_frame(scene)
    ours_seconds = time.perf_counter() - t0
    ours = frame.rgba[..., :3] * frame.rgba[..., 3:]  # display values over the black world
    smooth = scene_render.render_frame(scene, antialias=True).rgba
    smooth = smooth[..., :3] * smooth[..., 3:]
    eevee, eevee_seconds = blender("BLENDER_EEVEE")
    cycles, cycles_seconds = blender("CYCLES")

    if args.png:
        from PIL import Image

        strip = np.concatenate([ours, srgb_encode(eevee), srgb_encode(cycles)], axis=1)
        Image.fromarray((np.clip(strip, 0, 1) * 255 + 0.5).astype(np.uint8)).save(args.png)
    covered = float(np.mean(frame.rgba[..., 3] > 0.05))
    rows = [
        ["ours (mlx3d, Render Image)", f"{ours_seconds:.2f}", "-", "-"],
        ["EEVEE", f"{eevee_seconds:.2f}", f"{psnr(ours, srgb_encode(eevee)):.2f}", f"{psnr(ours, eevee):.2f}"],
        [f"Cycles, {args.samples} samples", f"{cycles_seconds:.2f}", f"{psnr(ours, srgb_encode(cycles)):.2f}", f"{psnr(ours, cycles):.2f}"],
        ["ours, antialiased (compensated 2D filter), vs EEVEE", "-", f"{psnr(smooth, srgb_encode(eevee)):.2f}", f"{psnr(smooth, eevee):.2f}"],
        ["ours, antialiased, vs Cycles", "-", f"{psnr(smooth, srgb_encode(cycles)):.2f}", f"{psnr(smooth, cycles):.2f}"],
        ["EEVEE vs Cycles", "-", f"{psnr(srgb_encode(eevee), srgb_encode(cycles)):.2f}", f"{psnr(eevee, cycles):.2f}"],
    ]
    header = ["render", "time (s)", "PSNR vs ours, Standard view (dB)", "PSNR vs ours, linear values as display (dB)"]
    title = (f"{os.path.basename(args.ply)} ({len(positions):,} splats), {args.size}x{args.size}, Blender {bpy.app.version_string}, {covered:.0%} of the frame covered; "
             + machine_line(f"; load {os.getloadavg()[0]:.1f}; {time.strftime('%Y-%m-%d')}"))
    table = f"{title}\n\n| " + " | ".join(header) + " |\n|---|---:|---:|---:|\n" + "".join("| " + " | ".join(r) + " |\n" for r in rows)
    if args.png and args.markdown:
        picture = os.path.relpath(args.png, os.path.dirname(os.path.abspath(args.markdown)))
        table += f"\n![ours | EEVEE | Cycles, Standard view]({picture})\n\nLeft to right: ours, EEVEE, Cycles.\n"
    emit(table, args.markdown)


if __name__ == "__main__":
    main()
