"""Blender side of mlx3d: splat objects, their operators and the N-panel.

The math lives in ``mlx3d`` (bundled as a wheel); this package only converts
between Blender data and ``mlx3d`` arrays. See ``splat_object`` for the
attribute layout.
"""

import bpy

from . import operators, panel

_CLASSES = operators.CLASSES + panel.CLASSES


def register():
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.mlx3d_splats = bpy.props.PointerProperty(type=panel.MLX3D_PG_settings)
    bpy.types.TOPBAR_MT_file_import.append(operators.menu_import)
    bpy.types.TOPBAR_MT_file_export.append(operators.menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(operators.menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(operators.menu_import)
    del bpy.types.Scene.mlx3d_splats
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
