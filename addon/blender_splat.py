"""Headless entry point of the MLX3D Gaussian Splats extension.

    blender -b -P blender_splat.py -- compose --scene scene.ply --insert object.ply \\
        --location 0 0 1 --rotation-deg 0 0 90 --scale 0.5 --out merged.ply
    python blender_splat.py compose ...          # with the ``bpy`` module

The extension must be installed in Blender (``blender --command extension
install-file -r user_default mlx3d_splat-*.zip``); this script enables it if
needed and runs ``addon.headless``. ``--help`` lists the subcommands.
"""

import importlib
import sys

import bpy  # before addon_utils, which the bpy module only provides once bpy is imported
import addon_utils

EXTENSION_ID = "mlx3d_splat"


def extension_module():
    """The installed extension's package, enabling it when it is installed but off."""
    for name in bpy.context.preferences.addons.keys():
        if name.rsplit(".", 1)[-1] == EXTENSION_ID:
            return importlib.import_module(name)
    for module in addon_utils.modules(refresh=True):
        if module.__name__.rsplit(".", 1)[-1] == EXTENSION_ID:
            addon_utils.enable(module.__name__, default_set=True, handle_error=None)
            return importlib.import_module(module.__name__)
    sys.exit(f"blender_splat: the '{EXTENSION_ID}' extension is not installed in this Blender; install its zip first")


def main() -> int:
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    headless = importlib.import_module(extension_module().__name__ + ".addon.headless")
    return headless.main(argv)


if __name__ == "__main__":
    sys.exit(main())
