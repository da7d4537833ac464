"""The extension zip: its manifest and contents, installing and enabling it in
Blender, the bundled wheels (used from the extension's own site-packages), and
a register/unregister round trip."""

from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXTENSION_ID = "mlx3d_splat"
OPERATORS = ("IMPORT_SCENE_OT_gaussian_splat_ply", "EXPORT_SCENE_OT_gaussian_splat_ply")


def manifest():
    return tomllib.loads((ROOT / "blender_manifest.toml").read_text())


# ------------------------------------------------------------------ manifest
def test_manifest_fields():
    m = manifest()
    assert m["schema_version"] == "1.0.0"
    assert m["id"] == EXTENSION_ID and m["type"] == "add-on"
    assert m["license"] == ["SPDX:MIT"]
    assert m["blender_version_min"] == "4.5.0"
    assert m["platforms"] == ["linux-x64", "macos-arm64", "windows-x64", "linux-arm64"]
    assert len(m["tagline"]) <= 64 and not m["tagline"].endswith((".", "!", "?"))
    reason = m["permissions"]["files"]
    assert len(reason) <= 64 and not reason.endswith(".")


def test_manifest_wheels_follow_the_pins(package_script):
    package = package_script
    pins = package.read_pins()
    assert set(pins.bundled) == {"mlx", "plyfile", "pillow", "zstandard"}  # numpy comes with Blender
    want = package.manifest_wheel_paths(package.expected_wheels(pins, package.PLATFORMS, package.DEFAULT_PYTHONS))
    assert manifest()["wheels"] == want, "stale wheels list: run `make extension`"
    names = " ".join(want)
    for py in ("cp311", "cp313"):
        assert f"mlx-{pins.bundled['mlx']}-{py}-{py}-manylinux_2_35_x86_64.whl" in names
        assert f"mlx3d_splat-{pins.own_version}-{py}-{py}-linux_x86_64.whl" in names  # with mlx3d._core
        assert f"mlx-{pins.bundled['mlx']}-{py}-{py}-macosx_14_0_arm64.whl" in names
        assert f"pillow-{pins.bundled['pillow']}-{py}-{py}-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl" in names
        assert f"pillow-{pins.bundled['pillow']}-{py}-{py}-macosx_11_0_arm64.whl" in names
    # Pure Python with the platform's kernel library: macOS, Windows, Linux arm64.
    for tag in ("macosx_11_0_arm64", "win_amd64", "manylinux_2_17_aarch64"):
        assert f"mlx3d_splat-{pins.own_version}-py3-none-{tag}.whl" in names
    assert f"mlx3d_splat-{pins.own_version}-py3-none-any.whl" not in names  # none of ours claims every platform
    assert "numpy" not in names


def test_repository_manifest_validates(package_script):
    cli = package_script.find_blender_ext()
    result = subprocess.run([*cli, "validate", str(ROOT)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


# ------------------------------------------------------------------ the zip
def test_zip_contents(installed_extension, package_script):
    ext = installed_extension
    pins = package_script.read_pins()
    mlx, ply = pins.bundled["mlx"], pins.bundled["plyfile"]
    with zipfile.ZipFile(ext.zip_path) as zf:
        names = set(zf.namelist())
        root_init = zf.read("__init__.py").decode()
        zipped = tomllib.loads(zf.read("blender_manifest.toml").decode())
    assert {"blender_manifest.toml", "__init__.py", "addon/__init__.py"} <= names
    assert "from .addon import register" in root_init and "from .addon import unregister" in root_init
    assert "sys.path" not in root_init
    wheels = sorted(n.removeprefix("wheels/") for n in names if n.startswith("wheels/"))
    assert wheels == sorted(ext.zip_wheels)
    py = "cp{}{}".format(*sys.version_info[:2])
    assert any(w.startswith("mlx3d_splat-") and f"-{py}-" in w for w in wheels)
    assert any(w.startswith(f"mlx-{mlx}-{py}-") for w in wheels)
    assert f"plyfile-{ply}-py3-none-any.whl" in wheels
    assert not any(w.startswith("numpy") for w in wheels)
    if ext.platform == "linux-x64":
        assert f"mlx_cpu-{mlx}-py3-none-manylinux_2_35_x86_64.whl" in wheels
    # Sources of the core ship only inside the wheel; tooling stays out.
    assert not any(n.startswith(("mlx3d/", "tests/", "bench/", "build/", ".")) for n in names)
    assert "addon/package.py" not in names and not any("__pycache__" in n for n in names)
    assert zipped["platforms"] == [ext.platform]
    assert zipped["wheels"] == [f"./wheels/{w}" for w in ext.zip_wheels]


def test_zip_validates(installed_extension, package_script):
    cli = package_script.find_blender_ext()
    result = subprocess.run([*cli, "validate", str(installed_extension.zip_path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


# ------------------------------------------------------------------ install
def test_install_enables_the_extension(installed_extension):
    import bpy  # first: it puts Blender's script modules (addon_utils) on sys.path
    import addon_utils

    ext = installed_extension
    assert ext.module.__name__ == f"bl_ext.user_default.{EXTENSION_ID}"
    assert Path(ext.module.__file__) == ext.extension_dir / "__init__.py"
    assert ext.module_name in bpy.context.preferences.addons
    assert addon_utils.check(ext.module_name) == (True, True)
    assert sys.modules[f"{ext.module_name}.addon"] is ext.module.addon  # imported by register()


def test_bundled_wheels_are_installed_into_the_extension_site_packages(installed_extension, package_script):
    ext = installed_extension
    pins = package_script.read_pins()
    mlx = pins.bundled["mlx"]
    sp = ext.site_packages
    assert sp.is_dir(), sp
    py = "{}{}".format(*sys.version_info[:2])
    for dist in (f"mlx-{mlx}", f"plyfile-{pins.bundled['plyfile']}", f"{pins.own_name}-{pins.own_version}"):
        assert (sp / f"{dist}.dist-info").is_dir(), dist
    assert list((sp / "mlx3d").glob(f"_core.cpython-{py}-*.so")), "no version-specific mlx3d/_core module"
    assert (sp / "plyfile.py").is_file()
    if ext.platform == "linux-x64":
        assert (sp / f"mlx_cpu-{mlx}.dist-info").is_dir()
        assert (sp / "mlx" / "lib" / "libmlx.so").is_file()  # _core's rpath: $ORIGIN/../mlx/lib
        assert list((sp / "mlx_cpu.libs").glob("libblas*"))  # libmlx's rpath: $ORIGIN/../../mlx_cpu.libs
    # Installing appends it to sys.path; at startup Blender inserts it before
    # its own site-packages (see the clean-interpreter test below).
    assert str(sp) in sys.path


CHILD = r"""
import json, site, sys
venv_prefix, venv_site, name = sys.argv[1:4]
# As in Blender: the interpreter's site-packages (here the venv's, for bpy and
# numpy) is on sys.path and is what site.getsitepackages() returns. -S keeps
# the venv's .pth files unread, so the editable mlx3d is not importable.
sys.prefix = sys.exec_prefix = venv_prefix
site.PREFIXES[:] = [venv_prefix]
sys.path.append(venv_site)
import bpy
import addon_utils
if name not in bpy.context.preferences.addons:
    assert bpy.ops.preferences.addon_enable(module=name) == {"FINISHED"}
assert addon_utils.check(name)[1]
import mlx.core as mx
import mlx3d
import numpy as np
import plyfile
from mlx3d.native import core
from mlx3d.neighbors import mean_knn_distance
assert core()._mlx_scale(mx.array([1.0, 2.0]), 3.0).tolist() == [3.0, 6.0]
assert mean_knn_distance(np.random.default_rng(0).random((100, 3), dtype=np.float32), 3).shape == (100,)
libmlx = sorted({line.split()[-1] for line in open("/proc/self/maps") if "libmlx" in line})
print("RESULT " + json.dumps({
    "mlx3d": mlx3d.__file__, "_core": core().__file__, "mlx": mx.__file__, "plyfile": plyfile.__file__,
    "libmlx": libmlx, "sys_path": sys.path,
}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
def test_extension_uses_its_bundled_wheels_in_a_clean_interpreter(installed_extension, extension_env, tmp_path):
    """In a Python without the development checkout (as in Blender), everything comes from the wheels
    (the compiled module too, so this child loads it even where the suite runs with MLX3D_NO_CORE)."""
    ext = installed_extension
    env = {k: v for k, v in extension_env.items() if k != "MLX3D_NO_CORE"}
    result = subprocess.run(
        [sys.executable, "-I", "-S", "-c", CHILD, sys.prefix, sysconfig.get_paths()["purelib"], ext.module_name],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    lines = [line for line in result.stdout.splitlines() if line.startswith("RESULT ")]
    assert result.returncode == 0 and lines, result.stdout[-3000:] + result.stderr[-3000:]
    report = json.loads(lines[-1].removeprefix("RESULT "))
    sp = str(ext.site_packages) + "/"
    for key in ("mlx3d", "_core", "mlx", "plyfile"):
        assert report[key].startswith(sp), (key, report[key], report["sys_path"])
    assert report["libmlx"] == [sp + "mlx/lib/libmlx.so"]


# ------------------------------------------------------------------ register / unregister
def _registered(bpy, module_name):
    operators = {name for name in OPERATORS if hasattr(bpy.types, name)}
    panels = {
        cls.__name__ for cls in bpy.types.Panel.__subclasses__()
        if cls.__module__.startswith(module_name) and getattr(cls, "is_registered", False)
    }
    return operators, panels


def test_operators_and_panel_are_registered(installed_extension):
    import bpy

    operators, panels = _registered(bpy, installed_extension.module_name)
    assert operators == set(OPERATORS)
    assert panels, "no panel of the extension is registered"
    assert bpy.ops.import_scene.gaussian_splat_ply.get_rna_type().identifier == OPERATORS[0]
    assert bpy.ops.export_scene.gaussian_splat_ply.get_rna_type().identifier == OPERATORS[1]


def test_register_unregister_round_trip(installed_extension):
    import bpy  # first: it puts Blender's script modules (addon_utils) on sys.path
    import addon_utils

    name = installed_extension.module_name
    before = _registered(bpy, name)
    try:
        for _ in range(2):
            assert bpy.ops.preferences.addon_disable(module=name) == {"FINISHED"}
            assert name not in bpy.context.preferences.addons
            assert addon_utils.check(name)[1] is False
            assert _registered(bpy, name) == (set(), set()), "unregister left classes registered"
            assert bpy.ops.preferences.addon_enable(module=name) == {"FINISHED"}
            assert name in bpy.context.preferences.addons and addon_utils.check(name)[1]
            assert _registered(bpy, name) == before
    finally:
        if name not in bpy.context.preferences.addons:
            bpy.ops.preferences.addon_enable(module=name)
