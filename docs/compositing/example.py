"""The composited example frame of the README (docs/compositing/example.png).

The demo's trained splats (``make demo`` writes ``demo_out/demo.blend``) with
a Blender torus standing through the checkered disc, between the splat cube
and the splat sphere, lit by a sun; Cycles for the torus, mlx3d for the splats,
composited by depth. Left to right: Blender's layer alone, the splats alone,
the composite.

    .venv/bin/python docs/compositing/example.py [--blend demo_out/demo.blend] [--size 384] [--samples 32]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blend", default=os.path.join(ROOT, "demo_out", "demo.blend"))
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--samples", type=int, default=32)
    parser.add_argument("--out", default=os.path.join(HERE, "example.png"))
    args = parser.parse_args()

    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp())
    import bpy

    sys.path.insert(0, ROOT)  # the add-on package from this checkout
    from addon import scene_render

    bpy.ops.wm.open_mainfile(filepath=args.blend)
    scene = bpy.context.scene
    scene.render.resolution_x = scene.render.resolution_y = args.size
    scene.render.resolution_percentage = 100
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples = "CPU", args.samples
    scene.view_settings.view_transform = "Standard"
    world = bpy.data.worlds.new("white") if scene.world is None else scene.world
    scene.world = world
    world.color = (1.0, 1.0, 1.0)
    if world.node_tree is not None:
        node = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
        node.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        node.inputs["Strength"].default_value = 1.0

    bpy.ops.mesh.primitive_torus_add(major_radius=0.28, minor_radius=0.06, location=(0.45, -0.62, 0.16), rotation=(math.radians(90.0), 0.0, math.radians(-75.0)))
    torus = bpy.context.active_object
    bpy.ops.object.shade_smooth()
    material = bpy.data.materials.new("red")
    if material.node_tree is None:
        material.use_nodes = True
    bsdf = next(n for n in material.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (0.8, 0.05, 0.03, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.3
    torus.data.materials.append(material)
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40.0), 0.0, math.radians(30.0))
    scene.collection.objects.link(sun)
    splats = [o for o in scene.objects if o.type == "POINTCLOUD"]

    panels = []
    for hidden in (splats, [torus], []):
        for obj in splats + [torus]:
            obj.hide_render = obj in hidden
        frame = scene_render.render_frame(scene)
        print(", ".join(frame.stages))
        panels.append(frame.rgba)
    strip = np.concatenate(panels, axis=1)
    scene.render.resolution_x = strip.shape[1]
    scene_render.save_frame(scene, strip, os.path.abspath(args.out), png=True)
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
