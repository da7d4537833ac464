"""Blender side of mlx3d: splat objects, their operators and the N-panel.

The math lives in ``mlx3d`` (bundled as a wheel); this package only converts
between Blender data and ``mlx3d`` arrays. See ``splat_layout`` for the
attribute layout.
"""

import bpy
from bpy.app.handlers import persistent

from . import operators, panel, splat_object

_CLASSES = operators.CLASSES + panel.CLASSES


@persistent
def upgrade_splat_objects(*_args):
    """After a .blend is opened: give splat objects saved by another Blender version (or an
    earlier add-on) this Blender's layout and display, so 4.5 files open in 5.3 as native splats."""
    for obj in bpy.data.objects:
        try:
            if splat_object.upgrade(obj):
                print(f"mlx3d: '{obj.name}' now has this Blender's splat layout")
        except ValueError as exc:  # a malformed object is reported, never half converted
            print(f"mlx3d: '{obj.name}' kept as it was: {exc}")


def register():
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.mlx3d_splats = bpy.props.PointerProperty(type=panel.MLX3D_PG_settings)
    bpy.types.TOPBAR_MT_file_import.append(operators.menu_import)
    bpy.types.TOPBAR_MT_file_export.append(operators.menu_export)
    bpy.app.handlers.load_post.append(upgrade_splat_objects)


def unregister():
    if upgrade_splat_objects in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(upgrade_splat_objects)
    bpy.types.TOPBAR_MT_file_export.remove(operators.menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(operators.menu_import)
    del bpy.types.Scene.mlx3d_splats
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
