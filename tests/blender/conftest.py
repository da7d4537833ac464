"""Fixtures for tests that drive the packaged extension inside Blender's ``bpy`` module.

The session builds the extension zip once with ``addon/package.py`` (this
machine's platform, the running Python only), installs it with
``bpy.ops.extensions.package_install_files`` into a temporary
``BLENDER_USER_RESOURCES`` and enables it, as a user installing the zip would.

Fixtures:

- ``installed_extension`` (session): an :class:`InstalledExtension` with the
  extension's module, its module name ``bl_ext.user_default.mlx3d_splat``, the
  zip, the extension directory and the site-packages its wheels went into.
- ``extension`` (session): the extension's package module (``__file__`` is the
  installed ``__init__.py``; ``extension.addon`` is the add-on code).
- ``package_script`` (session): ``addon/package.py`` loaded as a module.
- ``extension_env`` (session): environment for subprocesses that import ``bpy``
  and should see the same installed extension.
- ``clean_scene`` (function): resets Blender to an empty scene with
  ``wm.read_homefile(use_empty=True)`` (``read_factory_settings`` would disable
  extensions) and returns ``bpy.context.scene``.

``BLENDER_USER_RESOURCES`` must be set before the process first imports
``bpy``, so it is set when this file is imported, before the test modules here
are collected (they may ``import bpy`` at module level). No other test
directory imports ``bpy``. Without ``bpy`` every test here is skipped.

Which ``mlx3d`` the add-on sees: in this process the development checkout
(the editable install puts a finder in front of ``sys.path``, and pytest has
imported ``mlx3d`` already), so the add-on in-process runs the working tree's
``mlx3d``; mlx and plyfile are imported from the venv before ``bpy`` so the
process holds one copy of each. The bundled wheels are checked separately in a
clean interpreter (``test_extension_install.py``), where nothing but the
extension's site-packages provides ``mlx3d``, ``mlx`` and ``plyfile``.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType

import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
# tests/core_marks.py's marks serve this directory too (pytest puts only tests/blender on sys.path when it runs alone)
if str(HERE.parent) not in sys.path:
    sys.path.append(str(HERE.parent))
EXTENSION_ID = "mlx3d_splat"
REPO = "user_default"
MODULE_NAME = f"bl_ext.{REPO}.{EXTENSION_ID}"

HAVE_BPY = importlib.util.find_spec("bpy") is not None
SKIP_REASON = (
    "bpy (Blender as a Python module) is not installed: tests/blender need "
    "`pip install bpy==5.0.1` (Python 3.11; part of `pip install -e '.[test]'`)"
)

USER_RESOURCES: Path | None = None
if HAVE_BPY:
    if "bpy" in sys.modules:
        raise pytest.UsageError(
            "bpy was imported before tests/blender/conftest.py could set BLENDER_USER_RESOURCES; "
            "import bpy only inside tests/blender"
        )
    USER_RESOURCES = Path(tempfile.mkdtemp(prefix="mlx3d-blender-user-"))
    os.environ["BLENDER_USER_RESOURCES"] = str(USER_RESOURCES)


def pytest_collection_modifyitems(config, items):
    if HAVE_BPY:
        return
    skip = pytest.mark.skip(reason=SKIP_REASON)
    for item in items:
        if HERE in Path(str(item.path)).parents:
            item.add_marker(skip)


def pytest_unconfigure(config):
    if USER_RESOURCES is not None:
        shutil.rmtree(USER_RESOURCES, ignore_errors=True)


@dataclasses.dataclass(frozen=True)
class InstalledExtension:
    module: ModuleType  # the extension's package, bl_ext.user_default.mlx3d_splat
    module_name: str
    zip_path: Path
    zip_wheels: tuple[str, ...]  # wheel file names inside the zip
    platform: str  # Blender platform of the zip, e.g. "linux-x64"
    user_resources: Path  # BLENDER_USER_RESOURCES of this session
    extension_dir: Path  # where the zip was unpacked
    site_packages: Path  # where Blender installed the bundled wheels


def load_package_script() -> ModuleType:
    """``addon/package.py`` as a module (without importing the ``addon`` package, which needs bpy)."""
    name = "mlx3d_extension_package"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "addon" / "package.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def package_script() -> ModuleType:
    """``addon/package.py`` as a module (``build``, ``read_pins``, ``find_blender_ext``, ...)."""
    return load_package_script()


@pytest.fixture(scope="session")
def installed_extension(tmp_path_factory, package_script) -> InstalledExtension:
    if not HAVE_BPY:
        pytest.skip(SKIP_REASON)
    package = package_script
    result = package.build(pythons=[sys.version_info[:2]], out_dir=tmp_path_factory.mktemp("dist"),
                           update_manifest=False)

    # One copy of each in this process: the venv's, as the rest of the suite uses.
    import mlx.core  # noqa: F401
    import plyfile  # noqa: F401

    import bpy  # first: it puts Blender's script modules (addon_utils) on sys.path
    import addon_utils

    assert bpy.ops.extensions.package_install_files(
        filepath=str(result.zip_path), repo=REPO, enable_on_install=True
    ) == {"FINISHED"}
    # The operator reports FINISHED even for a bad path: check what it did.
    extensions = Path(bpy.utils.user_resource("EXTENSIONS"))
    extension_dir = extensions / REPO / EXTENSION_ID
    assert (extension_dir / "blender_manifest.toml").is_file(), f"not installed into {extension_dir}"
    assert MODULE_NAME in bpy.context.preferences.addons, "installed but not enabled"
    assert addon_utils.check(MODULE_NAME)[1], "enabled in the preferences but not loaded"
    module = importlib.import_module(MODULE_NAME)
    site_packages = extensions / ".local" / "lib" / "python{}.{}".format(*sys.version_info[:2]) / "site-packages"
    return InstalledExtension(
        module=module,
        module_name=MODULE_NAME,
        zip_path=result.zip_path,
        zip_wheels=tuple(result.wheels),
        platform=result.platform,
        user_resources=USER_RESOURCES,
        extension_dir=extension_dir,
        site_packages=site_packages,
    )


@pytest.fixture(scope="session")
def extension(installed_extension) -> ModuleType:
    return installed_extension.module


@pytest.fixture(scope="session")
def extension_env(installed_extension) -> dict:
    return {**os.environ, "BLENDER_USER_RESOURCES": str(installed_extension.user_resources)}


@pytest.fixture
def clean_scene(installed_extension):
    import bpy

    assert bpy.ops.wm.read_homefile(use_empty=True) == {"FINISHED"}
    assert installed_extension.module_name in bpy.context.preferences.addons, "the reset disabled the extension"
    return bpy.context.scene
