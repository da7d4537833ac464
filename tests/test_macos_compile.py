"""The compiled module's sources compile for macOS on Apple silicon (arm64).

Users are mostly on Macs, where Apple clang builds ``mlx3d._core`` against
libc++ and the macOS MLX wheel's headers; the rest of the suite only ever
builds it on Linux. This check cross-compiles every C++ source of the module
(the list in CMakeLists.txt) to an arm64 Mach-O object file with ``zig c++
-target aarch64-macos.14.0`` (clang with the macOS libc and libc++ headers),
against the headers of the macOS MLX wheel (``mlx-metal``, which holds MLX's
include directory and CMake config on macOS), nanobind's headers and this
interpreter's Python headers (Linux's pyconfig.h: the Python API itself is the
same). It checks compiling and code generation, not linking, nor results.
The flags are the module's Release flags; every file gets ``-ffp-contract=off``
and ``-fno-math-errno`` (CMakeLists.txt gives them to most files; they change
no diagnostics).

Skipped unless zig (the PyPI package ``ziglang``, or ``zig`` on PATH) and the
macOS MLX headers are there: ``make test-macos-compile`` installs zig into
its own venv and unpacks the headers of the pinned version into
build/macos-mlx/<version>/, or point MLX3D_MACOS_MLX_INCLUDE at the
``mlx/include`` directory of an unpacked ``mlx-metal`` macOS arm64 wheel.
"""

from __future__ import annotations

import concurrent.futures
import importlib.util
import os
import re
import shutil
import struct
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TARGET = "aarch64-macos.14.0"  # the macOS MLX wheels are macosx_14_0_arm64
MACH_O_64 = 0xFEEDFACF
CPU_TYPE_ARM64 = 0x0100000C


def module_sources() -> list[str]:
    """The C++ sources of nanobind_add_module(_core ...) in CMakeLists.txt."""
    text = (ROOT / "CMakeLists.txt").read_text(encoding="utf-8")
    block = re.search(r"nanobind_add_module\(\s*_core(.*?)\)", text, re.S)
    assert block, "CMakeLists.txt: no nanobind_add_module(_core ...)"
    sources = re.findall(r"mlx3d/csrc/[\w/]+\.cpp", block.group(1))
    assert sources, "CMakeLists.txt: nanobind_add_module(_core ...) names no sources"
    return sources


def zig_command() -> list[str] | None:
    if importlib.util.find_spec("ziglang") is not None:
        return [sys.executable, "-m", "ziglang"]
    zig = shutil.which("zig")
    return [zig] if zig else None


def mlx_macos_include() -> Path:
    """MLX3D_MACOS_MLX_INCLUDE, else where `make test-macos-compile` unpacks the pinned version's headers."""
    if os.environ.get("MLX3D_MACOS_MLX_INCLUDE"):
        return Path(os.environ["MLX3D_MACOS_MLX_INCLUDE"])
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["dependencies"]
    pin = next((m.group(1) for d in deps if (m := re.match(r"mlx==([\w.]+)\s*;.*darwin", d))), "unknown")
    return ROOT / "build" / "macos-mlx" / pin / "mlx" / "include"


def missing() -> str | None:
    """Why the check cannot run here, or None."""
    if zig_command() is None:
        return "zig was not found: `pip install ziglang` (or put zig on PATH); `make test-macos-compile` does it"
    mlx_include = mlx_macos_include()
    if not (mlx_include / "mlx" / "mlx.h").is_file():
        return (f"the macOS MLX headers were not found at {mlx_include}: `make test-macos-compile` downloads them, "
                "or set MLX3D_MACOS_MLX_INCLUDE to the mlx/include directory of the mlx-metal macOS arm64 wheel")
    if importlib.util.find_spec("nanobind") is None:
        return "nanobind is not installed (its headers are needed)"
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").is_file():
        return f"Python.h was not found in {sysconfig.get_paths()['include']}"
    return None


if missing():
    pytest.skip(missing(), allow_module_level=True)


def compile_flags() -> list[str]:
    import nanobind

    mlx_include = mlx_macos_include()
    return [
        *zig_command(), "c++", "-target", TARGET, "-std=c++20", "-O3", "-DNDEBUG", "-fPIC", "-fvisibility=hidden",
        # nanobind_add_module(... NB_DOMAIN mlx)
        "-DNB_DOMAIN=mlx",
        # MLX's exported compile options and include directories on macOS (its MLXConfig.cmake)
        "-DACCELERATE_NEW_LAPACK", "-D_METAL_",
        "-isystem", str(mlx_include), "-isystem", str(mlx_include / "metal_cpp"),
        "-isystem", str(mlx_include / "mlx" / "backend" / "metal" / "kernels" / "metal_3_1"),
        "-I", str(ROOT / "mlx3d" / "csrc"), "-I", sysconfig.get_paths()["include"], "-I", nanobind.include_dir(),
        "-ffp-contract=off", "-fno-math-errno",
    ]


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    """source -> (exit status, compiler output, object path), all sources compiled on all cores."""
    flags = compile_flags()
    out = tmp_path_factory.mktemp("macos-objects")
    # zig's caches in this temporary folder (not ~/.cache/zig): every run compiles afresh
    env = dict(os.environ, ZIG_GLOBAL_CACHE_DIR=str(out / "zig-global"), ZIG_LOCAL_CACHE_DIR=str(out / "zig-local"))

    def build(source):
        obj = out / (Path(source).stem + ".o")
        run = subprocess.run([*flags, "-c", str(ROOT / source), "-o", str(obj)], env=env, capture_output=True,
                             text=True, timeout=900)
        return run.returncode, run.stdout + run.stderr, obj

    sources = module_sources()
    with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        return dict(zip(sources, pool.map(build, sources)))


@pytest.mark.parametrize("source", module_sources())
def test_source_compiles_for_macos_arm64(compiled, source):
    status, output, obj = compiled[source]
    assert status == 0, f"zig c++ -target {TARGET} failed on {source}:\n{output}"
    # none of the module's own code may draw a warning from clang (MLX's and nanobind's are system headers)
    ours = [line for line in output.splitlines() if "warning:" in line and "mlx3d/csrc/" in line]
    assert not ours, f"{source}: clang warnings for macOS arm64:\n{output}"
    magic, cputype = struct.unpack("<II", obj.read_bytes()[:8])
    assert (magic, cputype) == (MACH_O_64, CPU_TYPE_ARM64), f"{obj.name} is not an arm64 Mach-O object"
