"""MLX3D Gaussian Splats, a Blender extension: its code is the ``addon`` package.

``register``/``unregister`` import ``addon`` when Blender calls them rather
than when this file is imported: this file also makes the repository root a
Python package, which pytest imports when it runs any test, and that must not
import ``bpy``.
"""

__all__ = ("register", "unregister")


def register():
    from .addon import register as register_addon

    register_addon()


def unregister():
    from .addon import unregister as unregister_addon

    unregister_addon()
