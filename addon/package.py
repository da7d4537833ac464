"""Build the Blender extension zips of mlx3d (``make extension``).

    .venv/bin/python addon/package.py [--platform NAME[,NAME...]|all] [--python 3.11,3.13] [--out dist]

``NAME`` is a Blender platform: ``linux-x64``, ``macos-arm64``, ``windows-x64``,
``linux-arm64``; ``all`` builds the four; the default is this machine's. Each
platform gets its own zip, ``dist/mlx3d_splat-VERSION-PLATFORM.zip`` (``-`` in
the name written ``_``), which holds only that platform's wheels: its
manifest's ``platforms`` names that one platform and its ``wheels`` lists
exactly the wheels inside. Per platform, for each Python (3.11 and 3.13):

- ``linux-x64``: ``mlx`` and ``mlx-cpu`` (``manylinux_2_35_x86_64``) and our
  compiled wheel ``mlx3d_splat-VERSION-cp3X-cp3X-linux_x86_64.whl`` with the
  C++ kernels ``mlx3d._core`` and the kernel library
  ``mlx3d/_kernels/libmlx3d_kernels.so``.
- ``macos-arm64``: ``mlx`` and ``mlx-metal`` (``macosx_14_0_arm64``; there is no
  ``mlx-cpu`` on macOS, ``mlx-metal`` carries ``libmlx.dylib`` and MLX's Metal
  kernels) and our wheel ``mlx3d_splat-VERSION-py3-none-macosx_11_0_arm64.whl``
  (pure Python and ``mlx3d/_kernels/libmlx3d_kernels.dylib``): mlx3d's Metal
  kernels (``mlx3d/render/raster_metal.py``) on the GPU.
- ``windows-x64``: ``mlx`` and ``mlx-cpu`` (``win_amd64``; ``mlx/core.pyd``
  loads ``mlx.dll`` and ``libopenblas.dll``, which ``mlx-cpu`` puts next to it)
  and our wheel ``mlx3d_splat-VERSION-py3-none-win_amd64.whl`` (pure Python and
  ``mlx3d/_kernels/mlx3d_kernels.dll``): MLX on the CPU.
- ``linux-arm64``: ``mlx`` and ``mlx-cpu`` (``manylinux_2_35_aarch64``) and our
  wheel ``mlx3d_splat-VERSION-py3-none-manylinux_2_17_aarch64.whl`` (pure
  Python and ``mlx3d/_kernels/libmlx3d_kernels.so``): MLX on the CPU.

All of them also bundle ``plyfile``, ``pillow`` and ``zstandard``, and the
``poses`` extra: ``av`` (PyAV, frames from videos) everywhere, one wheel per
platform (``cp311-abi3``: stable ABI, it serves Python 3.11 and 3.13, so each
zip carries it once), and ``pycolmap`` (camera poses from photos) everywhere but
``linux-arm64`` (it publishes no Linux arm64 wheels, so that zip does without
it). numpy is not bundled: Blender ships it. Every zip is built on any machine
from the registry's wheels, except that the compiled linux-x64 wheels are built
on a linux-x64 machine (elsewhere they must already be in ``wheels/``).

Steps, each printed as it runs (once per platform):

1. Read the pins: this project's wheel name and version from ``pyproject.toml``
   (``[project]``), and the exact pins of the bundled dependencies from its
   ``[project].dependencies`` (``mlx==…``, ``plyfile==…``, ``pillow==…``; a pin
   of MLX's library wheel, ``mlx-cpu==…`` for Windows, must equal mlx's) and
   from the extras in ``BUNDLED_EXTRAS`` (``pycolmap==…`` and ``av==…`` of
   ``poses``).
   The ``platforms`` and ``wheels = [...]`` lists of ``blender_manifest.toml``
   are generated from ``PLATFORMS`` below and these pins (every platform,
   Python 3.11 and 3.13) and rewritten when they differ, so versions live in
   one place.
2. Download the third-party wheels with ``pip download --only-binary=:all:
   --no-deps --python-version 3.X --platform TAG`` into ``wheels/``: ``mlx`` (one
   wheel per Python), its library wheel (``mlx-cpu`` on Linux and Windows,
   ``mlx-metal`` on macOS), the compiled dependencies of
   ``BINARY_WHEEL_TAGS`` (``pillow``, ``zstandard``, ``pycolmap``: one per
   Python, on the platforms the table names; ``av``, in ``STABLE_ABI``: one per
   platform, for every Python) and ``plyfile``. Files already
   there are reused. Then check that a ``pip install`` of our wheel on that
   platform pulls exactly ``mlx`` and that library wheel: from the markers of
   ``[project].dependencies`` and the downloaded ``mlx`` wheel's own
   ``Requires-Dist`` (with the extras we ask for). mlx's ``cpu`` extra adds
   ``mlx-cpu`` on Linux only, while its Windows wheel needs ``mlx.dll`` from
   ``mlx-cpu``: hence the explicit ``mlx-cpu`` pin for Windows in pyproject.toml.
   And that the markers of every other bundled pin (``pycolmap``'s and
   ``av``'s in ``poses``) pull it on exactly the platforms whose zip bundles it.
3. The kernel library, then this project's wheel ``mlx3d_splat``:

   - the kernel library for the platform: ``mlx3d/csrc/kernels/build.py
     PLATFORM --out DIR`` (the host C++ compiler for linux-x64, zig for the
     others: without zig the build stops and names ``make cross-tools``) into
     ``build/extension/kernels-PLATFORM/``, reused while it is newer than every
     file of ``mlx3d/csrc/kernels`` (``--rebuild`` forces a build). Its header
     must say the platform's format and machine (ELF x86-64, PE32+ x86-64, ELF
     aarch64, Mach-O arm64), it must export ``mlx3d_kernels_abi``, and it must
     keep the promise of its wheel's tag (``manylinux_2_17``: no glibc symbol
     newer than 2.17; ``macosx_11_0``: macOS 11 or older as its minimum); the
     macOS one must carry a code signature (ad hoc: Apple silicon runs no
     unsigned code). It goes into the wheel as ``mlx3d/_kernels/NAME``,
     ``NAME`` being build.py's ``library_name(PLATFORM)``, where
     ``mlx3d.kernel_library`` loads it.
   - linux-x64: the compiled wheel (``mlx3d`` and ``mlx3d._core``), built once
     per Python: with the running interpreter when it has the build
     requirements (the project's ``.venv``), otherwise in a build venv
     ``build/extension/venv-cp3XY`` made from ``python3.X`` (on PATH or from
     pyenv) with ``[build-system].requires`` installed. CMake build
     directories are kept under ``build/extension/`` so rebuilds are
     incremental; a wheel newer than every source file is reused
     (``--rebuild`` forces a build). The kernel library is added to it
     (``RECORD`` updated; a wheel that holds the same bytes already is left
     alone, and the wheel keeps its time, which says when ``_core`` was built).
     Each wheel built is then imported next to the bundled MLX in a clean
     interpreter (``python -I -S``): ``mlx3d._core`` must load and accept an
     ``mx.array``; and in each wheel built or given a new library,
     ``mlx3d.kernel_library`` (run by this interpreter, with its MLX and numpy:
     a build venv has no numpy) must load the library from the wheel's
     ``mlx3d/_kernels/``. On another machine the compiled wheels must be in
     ``wheels/`` with their library already.
   - the other platforms: the pure-Python wheel, written by this script with
     ``zipfile`` (no compiler, any machine, in seconds), twice: the generic
     ``py3-none-any`` one, for ``pip install`` anywhere MLX runs (no kernel
     library, as a ``pip install .`` leaves it out), and the one the zip
     carries, the same files plus ``mlx3d/_kernels/NAME``, tagged
     ``py3-none-PLATFORMTAG`` (``Platform.pure_tag``) with ``Root-Is-Purelib:
     false``. Each holds the files of
     ``[tool.scikit-build] wheel.packages`` less ``wheel.exclude`` (so no
     ``mlx3d/csrc``) and less caches and compiled modules, plus
     ``mlx3d/render/raster_math.h`` copied from ``mlx3d/csrc`` (the compiled
     wheel gets it from CMakeLists.txt's ``install(FILES ...)``; the Metal
     kernels read it there), and a ``.dist-info`` (METADATA from
     ``[project]``, with the same ``Requires-Dist`` markers, entry points,
     ``WHEEL`` with ``Root-Is-Purelib: true`` and ``Tag: py3-none-any``,
     ``RECORD``). Its bytes do not depend on when it is built (fixed
     timestamps), and the file is rewritten only when they change. It is
     checked like the compiled one, unpacked alone next to the running
     interpreter's MLX in ``python -I -S`` with ``MLX3D_NO_CORE=1``: ``mlx3d``
     imports from it, holds no ``_core``, its ``mlx3d/_kernels/`` holds the
     platform's library alone (the generic wheel: no such folder), and
     ``mlx3d.render.raster_metal.kernel_header()`` returns ``raster_math.h``.
4. Check that every wheel the manifest lists for the platform exists, and that
   our wheel(s) hold exactly the platform's kernel library, the one of step 3.
5. Stage the extension (manifest narrowed to the platform and Pythons, root
   ``__init__.py``, ``addon/`` without this script, the wheels) in a new
   ``build/extension/stage-PLATFORM-*`` (removed afterwards) and run Blender's
   ``blender_ext.py build --split-platforms`` (from the ``bpy`` package, or
   ``--blender-ext PATH``), then ``blender_ext.py validate`` on the zip.
6. Check the zip's wheels and manifest, print its path, size and the wheels
   inside.

Blender 4.5 LTS and 5.0 embed Python 3.11, Blender 5.1+ Python 3.13, hence the
default ``--python 3.11,3.13``. MLX publishes one wheel per Python version, so
the extension ships one ``mlx`` wheel (and on linux-x64 one ``mlx3d_splat``
wheel) per version, and one wheel of a stable-ABI package (``STABLE_ABI``:
``av``, ``cp311-abi3``) for both; Blender installs the matching ones into
``<user resources>/extensions/.local/lib/python3.X/site-packages``, where
``mlx3d/_core`` finds ``libmlx`` through its rpath ``$ORIGIN/../mlx/lib``.
(A stable-ABI ``abi3`` build of ``_core`` is not used: nanobind keeps
stable-ABI modules in a type registry of their own, so such a ``_core`` cannot
take the ``mx.array`` objects of ``mlx.core``, which is not a stable-ABI build.)

Linux x86-64 (``linux-x64``): MLX's wheels are tagged ``manylinux_2_35_x86_64``
(glibc 2.35+); ours is tagged ``linux_x86_64``, which Blender maps to
``linux-x64`` like any ``manylinux_*_x86_64`` tag. Building it needs Python
3.11 (the venv) and Python 3.13 (``python3.13`` on PATH, or ``pyenv install
3.13``) with development headers, a C++20 compiler and CMake >= 3.24.

The other platforms' zips need no machine of that platform, and no compiler
but zig (``make cross-tools`` installs the pinned ``ziglang`` into the venv)
for their kernel library; ``tests/test_packaging.py`` builds and validates all
four. Their pure-Python ``mlx3d`` uses the Metal kernels on Apple GPUs and pure
MLX elsewhere, with the kernel library's functions where it has them.

The kernel library and the wheel tags. The library (``mlx3d/csrc/kernels``, a
C ABI) links neither Python nor MLX, so one build per platform serves every
Python: the compiled linux-x64 wheels, platform-tagged already, carry it beside
``_core``; the pure wheel the other zips carry would be platform-independent
but for it, and a wheel holding a native library must not claim ``any``, so
that one is ``py3-none-PLATFORMTAG`` (Python 3, no ABI of Python's, one
platform, as MLX's own ``mlx-cpu`` and ``mlx-metal`` wheels), with
``Root-Is-Purelib: false`` (it installs into platlib), and the manifest's
``wheels`` lists the three names. The tags say what the builds are made for
(build.py's zig targets): ``win_amd64``, ``manylinux_2_17_aarch64`` (glibc
2.17, libc, libpthread and libdl alone, the C++ runtime inside) and
``macosx_11_0_arm64``. The ordinary builds, ``pip install .`` and editable
installs, keep leaving ``mlx3d/_kernels/`` out (``wheel.exclude`` in
pyproject.toml, decided here): CMakeLists.txt does not build the library, so
that folder holds whatever ``make kernels`` last built in this checkout, maybe
from older sources, and a wheel must not depend on such leftovers. An editable
install reads the folder in place anyway; elsewhere ``MLX3D_KERNELS`` names a
library. Only the extension's wheels, whose library this script builds from the
sources and checks, carry one.
"""

from __future__ import annotations

import argparse
import base64
import csv
import dataclasses
import email.parser
import fnmatch
import hashlib
import importlib.metadata
import importlib.util
import io
import os
import platform as _platform
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MANIFEST = ROOT / "blender_manifest.toml"
PYPROJECT = ROOT / "pyproject.toml"
WHEELS_DIR = ROOT / "wheels"
WORK_DIR = ROOT / "build" / "extension"
DEFAULT_OUT = ROOT / "dist"

#: Python versions of the Blender releases the extension supports:
#: 3.11 (Blender 4.5 LTS, 5.0) and 3.13 (Blender 5.1+).
DEFAULT_PYTHONS: tuple[tuple[int, int], ...] = ((3, 11), (3, 13))

#: Dependencies of ``[project].dependencies`` that Blender already provides.
PROVIDED_BY_BLENDER = frozenset({"numpy"})

#: Bundled dependencies (besides mlx and its library wheel) that are pure Python.
PURE_PYTHON = frozenset({"plyfile"})

#: Extras of ``[project.optional-dependencies]`` the zips bundle too (the add-on
#: offers what they enable): their pins are ``Pins.extras``, and each of their
#: dependencies is in ``PURE_PYTHON``, ``BINARY_WHEEL_TAGS`` or ``PROVIDED_BY_BLENDER``.
BUNDLED_EXTRAS = ("poses",)

#: MLX's library wheels (``libmlx``); a pin of one in ``[project].dependencies``
#: must equal mlx's. Which one a platform bundles is ``Platform.mlx_library``.
MLX_LIBRARIES = frozenset({"mlx_cpu", "mlx_metal"})

#: Bundled compiled dependencies (one wheel per Python and platform, or per platform
#: for those in ``STABLE_ABI``): the platform part of their wheel file names as
#: published for the pinned version, per Blender platform. ``pip download
#: --platform`` gets the last tag of a compound one. A platform left out gets none
#: of the package's wheels (the package publishes none there), and the markers of
#: its pin must leave it out too (checked in step 2).
BINARY_WHEEL_TAGS = {
    "pillow": {
        "linux-x64": "manylinux_2_27_x86_64.manylinux_2_28_x86_64",
        "macos-arm64": "macosx_11_0_arm64",
        "windows-x64": "win_amd64",
        "linux-arm64": "manylinux_2_27_aarch64.manylinux_2_28_aarch64",
    },
    "zstandard": {
        "linux-x64": "manylinux2014_x86_64.manylinux_2_17_x86_64",
        "macos-arm64": "macosx_11_0_arm64",
        "windows-x64": "win_amd64",
        "linux-arm64": "manylinux2014_aarch64.manylinux_2_17_aarch64",
    },
    # The poses extra. No Linux arm64 wheels; the macOS ones need macOS 14.
    "pycolmap": {
        "linux-x64": "manylinux_2_28_x86_64",
        "macos-arm64": "macosx_14_0_arm64",
        "windows-x64": "win_amd64",
    },
    # The poses extra: frames from videos. Stable ABI (STABLE_ABI), FFmpeg inside.
    "av": {
        "linux-x64": "manylinux_2_28_x86_64",
        "macos-arm64": "macosx_14_0_arm64",
        "windows-x64": "win_amd64",
        "linux-arm64": "manylinux_2_28_aarch64",
    },
}

#: Packages of ``BINARY_WHEEL_TAGS`` whose wheels are built for CPython's stable ABI,
#: with the oldest Python they are tagged for: ``NAME-VERSION-cp311-abi3-TAG.whl``,
#: one wheel per platform that serves that Python and every later one. A zip
#: carries it once, whatever its Pythons, and the manifest lists it once; a Python
#: older than that one stops the build (the wheel would not serve it).
STABLE_ABI = {"av": (3, 11)}

#: Sources of our compiled wheel: a wheel older than any of these is rebuilt.
SOURCE_INPUTS = ("pyproject.toml", "CMakeLists.txt", "mlx3d")

#: Files CMakeLists.txt installs into the compiled wheel besides ``_core``
#: (``install(FILES ...)``): (source in the tree, path in the wheel). The pure
#: wheel copies them to the same place; the Metal kernels read raster_math.h
#: next to ``mlx3d/render/raster_metal.py``.
PURE_WHEEL_EXTRA_FILES = (("mlx3d/csrc/raster_math.h", "mlx3d/render/raster_math.h"),)

#: The kernel library (a C ABI; links neither Python nor MLX): its sources, and the
#: script that builds it for a platform (``build.py PLATFORM --out DIR``) and names
#: its file (``library_name(PLATFORM)``).
KERNEL_SOURCES = ROOT / "mlx3d" / "csrc" / "kernels"
KERNEL_BUILD_SCRIPT = KERNEL_SOURCES / "build.py"
#: The folder of our wheels it goes into: ``mlx3d.kernel_library`` loads ``mlx3d/_kernels/NAME``.
KERNEL_DIR_IN_WHEEL = "mlx3d/_kernels"
#: The function every build of it must export (its ABI version; the loader calls it first).
KERNEL_ABI_SYMBOL = "mlx3d_kernels_abi"

#: Never put into the pure wheel: caches and compiled modules of a checkout.
_NOT_PACKAGED_SUFFIXES = frozenset({".pyc", ".pyo", ".so", ".pyd", ".dylib", ".dll"})

#: ``[project]`` keys the pure wheel's METADATA is written from; any other key
#: stops the build (teach ``_pure_metadata`` about it first).
_PURE_METADATA_KEYS = frozenset({
    "name", "version", "description", "requires-python", "dependencies", "optional-dependencies",
    "scripts", "gui-scripts", "entry-points", "keywords", "classifiers", "urls",
})


class PackagingError(RuntimeError):
    """A step failed; the message says which and what to do."""


@dataclasses.dataclass(frozen=True)
class Platform:
    name: str  # Blender's platform name (manifest ``platforms``)
    mlx_tag: str  # platform tag of MLX's wheels (``pip download --platform``)
    mlx_library: str  # the wheel that carries libmlx
    host: tuple[str, str]  # (platform.system(), platform.machine()) of a machine of this platform
    markers: tuple[tuple[str, str], ...]  # its PEP 508 environment markers (Requires-Dist checks)
    kernel_binary: tuple[str, str]  # (format, machine) of its kernel library, as binary_kind reads them
    own_tag: str | None = None  # platform tag of our compiled wheel; None: the pure-Python wheel
    pure_tag: str | None = None  # platform tag of the pure wheel that carries its kernel library (py3-none-TAG)

    @property
    def compiled(self) -> bool:
        return self.own_tag is not None


PLATFORMS = {
    "linux-x64": Platform(
        name="linux-x64",
        mlx_tag="manylinux_2_35_x86_64",
        mlx_library="mlx-cpu",
        host=("Linux", "x86_64"),
        markers=(("sys_platform", "linux"), ("platform_system", "Linux"), ("platform_machine", "x86_64"),
                 ("os_name", "posix")),
        kernel_binary=("ELF", "x86-64"),
        own_tag="linux_x86_64",
    ),
    "macos-arm64": Platform(
        name="macos-arm64",
        mlx_tag="macosx_14_0_arm64",
        mlx_library="mlx-metal",
        host=("Darwin", "arm64"),
        markers=(("sys_platform", "darwin"), ("platform_system", "Darwin"), ("platform_machine", "arm64"),
                 ("os_name", "posix")),
        kernel_binary=("Mach-O", "arm64"),
        pure_tag="macosx_11_0_arm64",
    ),
    "windows-x64": Platform(
        name="windows-x64",
        mlx_tag="win_amd64",
        mlx_library="mlx-cpu",
        host=("Windows", "x86_64"),
        markers=(("sys_platform", "win32"), ("platform_system", "Windows"), ("platform_machine", "AMD64"),
                 ("os_name", "nt")),
        kernel_binary=("PE32+", "x86-64"),
        pure_tag="win_amd64",
    ),
    "linux-arm64": Platform(
        name="linux-arm64",
        mlx_tag="manylinux_2_35_aarch64",
        mlx_library="mlx-cpu",
        host=("Linux", "arm64"),
        markers=(("sys_platform", "linux"), ("platform_system", "Linux"), ("platform_machine", "aarch64"),
                 ("os_name", "posix")),
        kernel_binary=("ELF", "aarch64"),
        pure_tag="manylinux_2_17_aarch64",
    ),
}


@dataclasses.dataclass(frozen=True)
class Pins:
    own_name: str  # distribution name of this project, normalised for wheel file names
    own_version: str
    bundled: dict  # normalised distribution name -> exact version, of [project].dependencies
    build_requires: tuple[str, ...]
    extras: dict  # the same, of the extras in BUNDLED_EXTRAS (pycolmap and av of poses)

    @property
    def pinned(self) -> dict:
        """Every bundled pin: ``bundled`` and ``extras``."""
        return {**self.bundled, **self.extras}


@dataclasses.dataclass(frozen=True)
class Wheel:
    filename: str
    requirement: str | None  # what ``pip download`` fetches; None for our own wheel
    python: tuple[int, int] | None  # the Python it is for; None when any (pure Python, stable ABI)
    platform: str | None  # Blender platform; None when any
    pip_platform: str | None = None  # ``pip download --platform`` tag; None when any


@dataclasses.dataclass
class BuildResult:
    platform: str
    zip_path: Path
    size: int
    wheels: list[str]
    seconds: float = 0.0  # wall time of the build


def log(message: str) -> None:
    print(f"[extension] {message}", flush=True)


def _normalise(name: str) -> str:
    """Distribution name as it appears in wheel file names (PEP 427/503)."""
    return re.sub(r"[-_.]+", "_", name).lower()


def _py_tag(python: tuple[int, int]) -> str:
    return f"cp{python[0]}{python[1]}"


def _fmt_py(python: tuple[int, int]) -> str:
    return f"{python[0]}.{python[1]}"


def parse_pythons(text: str) -> tuple[tuple[int, int], ...]:
    pythons = []
    for part in text.split(","):
        part = part.strip()
        match = re.fullmatch(r"3\.(\d+)", part)
        if not match:
            raise PackagingError(f"--python: expected versions like 3.11,3.13, got {part!r}")
        version = (3, int(match.group(1)))
        if version < (3, 11):
            raise PackagingError(f"--python: Blender extensions need Python 3.11 or newer, got {part}")
        if version not in pythons:
            pythons.append(version)
    if not pythons:
        raise PackagingError("--python: no version given")
    return tuple(sorted(pythons))


def parse_platforms(text: str) -> tuple[str, ...]:
    """``linux-x64``, ``linux-x64,macos-arm64`` or ``all`` -> platform names, in ``PLATFORMS`` order."""
    names = []
    for part in text.split(","):
        part = part.strip()
        if part == "all":
            names += PLATFORMS
        elif part in PLATFORMS:
            names.append(part)
        else:
            raise PackagingError(f"--platform: unknown platform {part!r}; choose from {', '.join(PLATFORMS)} or all")
    if not names:
        raise PackagingError("--platform: no platform given")
    return tuple(name for name in PLATFORMS if name in names)


def host_platform() -> str | None:
    """The Blender platform name of this machine, or None when unsupported."""
    host = (_platform.system(), _platform.machine().lower().replace("amd64", "x86_64").replace("aarch64", "arm64"))
    for plat in PLATFORMS.values():
        if plat.host == host:
            return plat.name
    return None


# --------------------------------------------------------------------------- pins
_REQ = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[[^\]]*\])?\s*(?:==\s*([^\s;,]+))?\s*(?:[<>=!~;,].*)?$")


def read_pins(pyproject: Path = PYPROJECT) -> Pins:
    data = tomllib.loads(pyproject.read_text())
    project = data["project"]
    optional = project.get("optional-dependencies", {})
    bundled: dict[str, str] = {}
    extras: dict[str, str] = {}
    libraries: dict[str, str] = {}
    sources = [("[project].dependencies", project.get("dependencies", []), bundled)]
    for extra in BUNDLED_EXTRAS:
        if extra not in optional:
            raise PackagingError(f"{pyproject.name}: no [project.optional-dependencies] {extra} (BUNDLED_EXTRAS)")
        sources.append((f"[project.optional-dependencies] {extra}", optional[extra], extras))
    for source, requirements, pins in sources:
        for requirement in requirements:
            match = _REQ.match(requirement)
            if not match:
                raise PackagingError(f"{pyproject.name}: cannot read dependency {requirement!r} of {source}")
            name, version = _normalise(match.group(1)), match.group(2)
            if name in PROVIDED_BY_BLENDER:
                continue
            if pins is bundled and name in MLX_LIBRARIES:
                libraries[requirement] = version
                continue
            if not (name in PURE_PYTHON or name in BINARY_WHEEL_TAGS or (name == "mlx" and pins is bundled)):
                raise PackagingError(
                    f"{pyproject.name}: dependency {requirement!r} of {source} is neither bundled nor provided by "
                    "Blender; add it to PURE_PYTHON, BINARY_WHEEL_TAGS or PROVIDED_BY_BLENDER in addon/package.py"
                )
            if not version:
                raise PackagingError(f"{pyproject.name}: bundled dependency {requirement!r} must be pinned with ==")
            have = {**bundled, **extras}.get(name, version)
            if have != version:
                raise PackagingError(f"{pyproject.name}: {name} is pinned to both {have} and {version}")
            pins[name] = version
    if "mlx" not in bundled:
        raise PackagingError(f"{pyproject.name}: no mlx==VERSION pin in [project].dependencies")
    for requirement, version in libraries.items():
        if version != bundled["mlx"]:
            raise PackagingError(
                f"{pyproject.name}: {requirement!r} must pin the same version as mlx=={bundled['mlx']}")
    return Pins(
        own_name=_normalise(project["name"]),
        own_version=project["version"],
        bundled=bundled,
        build_requires=tuple(data["build-system"]["requires"]),
        extras=extras,
    )


def pure_wheel_name(pins: Pins, plat: Platform | None = None) -> str:
    """File name of our pure-Python wheel: the generic one (``py3-none-any``, no kernel library), or with
    ``plat`` the one that platform's zip carries, with its kernel library (``py3-none-TAG``)."""
    if plat is None:
        return f"{pins.own_name}-{pins.own_version}-py3-none-any.whl"
    if plat.pure_tag is None:
        raise PackagingError(f"{plat.name} carries the compiled wheel, not a pure one")
    return f"{pins.own_name}-{pins.own_version}-py3-none-{plat.pure_tag}.whl"


def compiled_wheel_name(pins: Pins, plat: Platform, python: tuple[int, int]) -> str:
    """File name of our wheel with ``mlx3d._core`` for this platform and Python."""
    return f"{pins.own_name}-{pins.own_version}-{_py_tag(python)}-{_py_tag(python)}-{plat.own_tag}.whl"


def expected_wheels(pins: Pins, platforms, pythons) -> list[Wheel]:
    """Every wheel the extension bundles for these platforms and Pythons (sorted, no duplicates)."""
    mlx = pins.bundled["mlx"]
    wheels: dict[str, Wheel] = {}

    def add(wheel: Wheel) -> None:
        wheels.setdefault(wheel.filename, wheel)

    for plat_name in platforms:
        plat = PLATFORMS[plat_name]
        if not plat.compiled:
            add(Wheel(pure_wheel_name(pins, plat), None, None, plat.name))
        for python in pythons:
            tag = _py_tag(python)
            add(Wheel(f"mlx-{mlx}-{tag}-{tag}-{plat.mlx_tag}.whl", f"mlx=={mlx}", python, plat.name, plat.mlx_tag))
            if plat.compiled:
                add(Wheel(compiled_wheel_name(pins, plat, python), None, python, plat.name))
            for name in sorted((BINARY_WHEEL_TAGS.keys() & pins.pinned.keys()) - STABLE_ABI.keys()):
                if plat.name not in BINARY_WHEEL_TAGS[name]:
                    continue  # no wheels for this platform: not bundled there
                version, wheel_tag = pins.pinned[name], BINARY_WHEEL_TAGS[name][plat.name]
                add(Wheel(f"{name}-{version}-{tag}-{tag}-{wheel_tag}.whl", f"{name}=={version}", python, plat.name, wheel_tag.split(".")[-1]))
        for name in sorted(BINARY_WHEEL_TAGS.keys() & pins.pinned.keys() & STABLE_ABI.keys()):
            if plat.name not in BINARY_WHEEL_TAGS[name]:
                continue
            oldest = STABLE_ABI[name]
            if too_old := [p for p in pythons if p < oldest]:
                raise PackagingError(
                    f"{name}'s wheels (stable ABI, {_py_tag(oldest)}-abi3) need Python {_fmt_py(oldest)} or newer, "
                    f"not {', '.join(map(_fmt_py, too_old))}: leave that version out with --python, or update "
                    "STABLE_ABI in addon/package.py")
            version, wheel_tag = pins.pinned[name], BINARY_WHEEL_TAGS[name][plat.name]
            # One wheel for every Python: downloaded for the oldest one asked for (download_wheels).
            add(Wheel(f"{name}-{version}-{_py_tag(oldest)}-abi3-{wheel_tag}.whl", f"{name}=={version}", None,
                      plat.name, wheel_tag.split(".")[-1]))
        add(Wheel(f"{_normalise(plat.mlx_library)}-{mlx}-py3-none-{plat.mlx_tag}.whl",
                  f"{plat.mlx_library}=={mlx}", None, plat.name, plat.mlx_tag))
    for name in sorted(PURE_PYTHON & pins.pinned.keys()):
        version = pins.pinned[name]
        add(Wheel(f"{name}-{version}-py3-none-any.whl", f"{name}=={version}", None, None))
    return [wheels[k] for k in sorted(wheels)]


# ----------------------------------------------------------------------- manifest
def _toml_list_block(key: str, values) -> str:
    return "\n".join([f"{key} = [", *[f'  "{v}",' for v in values], "]"])


def replace_toml_list(text: str, key: str, values, *, source: str) -> str:
    """Replace the top-level ``key = [...]`` of a TOML text (one match required)."""
    pattern = re.compile(rf"^{re.escape(key)}\s*=\s*\[[^\]]*\]", re.MULTILINE)
    if len(pattern.findall(text)) != 1:
        raise PackagingError(f"{source}: expected exactly one top-level `{key} = [...]` list")
    return pattern.sub(lambda _m: _toml_list_block(key, values), text)


def manifest_wheel_paths(wheels) -> list[str]:
    return [f"./wheels/{w.filename}" for w in wheels]


def sync_manifest(pins: Pins, *, write: bool) -> bool:
    """Make the manifest's ``platforms`` and ``wheels`` lists the full lists derived
    from ``PLATFORMS`` and the pins.

    Returns True when the manifest already matched. With ``write`` stale lists are
    rewritten (and False returned); without, the file is left as it is and False
    returned (the zips do not depend on it: their manifests are generated per
    platform; tests/blender/test_extension_install.py checks it is up to date).
    """
    text = MANIFEST.read_text()
    want = {
        "platforms": list(PLATFORMS),
        "wheels": manifest_wheel_paths(expected_wheels(pins, PLATFORMS, DEFAULT_PYTHONS)),
    }
    have = tomllib.loads(text)
    stale = [key for key, values in want.items() if have.get(key) != values]
    if not stale:
        return True
    if not write:
        log(f"  {MANIFEST.name}: the {' and '.join(stale)} list(s) do not match PLATFORMS and the pins in "
            "pyproject.toml; left as they are (`make extension` rewrites them)")
        return False
    new_text = text
    for key in stale:
        new_text = replace_toml_list(new_text, key, want[key], source=MANIFEST.name)
    parsed = tomllib.loads(new_text)
    if any(parsed.get(key) != values for key, values in want.items()):
        raise PackagingError(f"{MANIFEST.name}: rewriting the {' and '.join(stale)} list(s) failed")
    MANIFEST.write_text(new_text)
    log(f"updated the {' and '.join(stale)} list(s) of {MANIFEST.name} "
        f"({len(want['platforms'])} platforms, {len(want['wheels'])} wheels)")
    return False


# ---------------------------------------------------------------------- downloads
def download_wheels(wheels: list[Wheel], pythons) -> None:
    WHEELS_DIR.mkdir(exist_ok=True)
    todo = [w for w in wheels if w.requirement and not _valid_zip(WHEELS_DIR / w.filename)]
    for w in wheels:
        if w.requirement and w not in todo:
            log(f"  have {w.filename}")
    # One pip call per (Python, platform): pip picks wheels for one interpreter at a time.
    groups: dict[tuple, list[Wheel]] = {}
    for w in todo:
        python = w.python or pythons[0]
        groups.setdefault((python, w.pip_platform), []).append(w)
    for (python, plat_tag), group in groups.items():
        with tempfile.TemporaryDirectory(dir=WHEELS_DIR, prefix=".download-") as tmp:
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--only-binary=:all:", "--no-deps",
                   "--python-version", _fmt_py(python), "--dest", tmp]
            if plat_tag:
                cmd += ["--platform", plat_tag]
            cmd += [w.requirement for w in group]
            log(f"  pip download {' '.join(w.requirement for w in group)} "
                f"(Python {_fmt_py(python)}, {plat_tag or 'any platform'})")
            _run(cmd, what="pip download")
            got = sorted(p.name for p in Path(tmp).glob("*.whl"))
            for w in group:
                if w.filename not in got:
                    raise PackagingError(
                        f"pip download {w.requirement} gave {got or 'nothing'}, not {w.filename}; "
                        "if the package now publishes other tags, update PLATFORMS, BINARY_WHEEL_TAGS or "
                        "STABLE_ABI in addon/package.py"
                    )
                os.replace(Path(tmp) / w.filename, WHEELS_DIR / w.filename)
                log(f"  got  {w.filename} ({_mb(WHEELS_DIR / w.filename)})")


def _valid_zip(path: Path) -> bool:
    return path.is_file() and zipfile.is_zipfile(path)


# ------------------------------------------------------------- MLX's requirements
def _requirement_class():
    """``packaging``'s Requirement (installed with the build requirements; pip vendors a copy)."""
    try:
        from packaging.requirements import Requirement
    except ImportError:
        try:
            from pip._vendor.packaging.requirements import Requirement
        except ImportError:
            return None
    return Requirement


def wheel_requires_dist(path: Path) -> list[str]:
    """The ``Requires-Dist`` lines of a wheel's METADATA."""
    with zipfile.ZipFile(path) as zf:
        names = [n for n in zf.namelist() if re.fullmatch(r"[^/]+\.dist-info/METADATA", n)]
        if len(names) != 1:
            raise PackagingError(f"{path.name}: expected one *.dist-info/METADATA, found {names}")
        metadata = email.parser.BytesHeaderParser().parsebytes(zf.read(names[0]))
    return metadata.get_all("Requires-Dist") or []


def _marker_environment(plat: Platform, python: tuple[int, int]) -> dict[str, str]:
    """The PEP 508 environment of CPython ``python`` on ``plat`` (what markers are evaluated against)."""
    return {**dict(plat.markers), "python_version": _fmt_py(python), "python_full_version": f"{_fmt_py(python)}.0",
            "implementation_name": "cpython", "platform_python_implementation": "CPython"}


def mlx_distributions(plat: Platform, python: tuple[int, int], own_requires, mlx_requires) -> set[str]:
    """MLX's distributions that ``pip install`` of our wheel pulls on this platform and Python.

    From our ``Requires-Dist`` (``[project].dependencies``) with their markers,
    and, for the ``mlx`` requirement that applies, the mlx wheel's own
    ``Requires-Dist`` with the extras we ask for (normalised names).
    """
    requirement = _requirement_class()
    env = _marker_environment(plat, python)

    def applies(req, extras=("",)) -> bool:
        return req.marker is None or any(req.marker.evaluate({**env, "extra": extra}) for extra in extras)

    found: set[str] = set()
    mlx_extras: set[str] | None = None
    for text in own_requires:
        req = requirement(text)
        name = _normalise(req.name)
        if (name == "mlx" or name in MLX_LIBRARIES) and applies(req):
            found.add(name)
            if name == "mlx":
                mlx_extras = (mlx_extras or set()) | set(req.extras)
    if mlx_extras is not None:
        for text in mlx_requires:
            req = requirement(text)
            if applies(req, ("", *sorted(mlx_extras))):
                found.add(_normalise(req.name))
    return found


def check_mlx_requirements(pins: Pins, plat: Platform, pythons) -> None:
    """A ``pip install`` of our wheel must pull exactly mlx and ``plat.mlx_library`` there."""
    if _requirement_class() is None:
        log("  (packaging is not installed: the Requires-Dist check of MLX is skipped)")
        return
    own = tomllib.loads(PYPROJECT.read_text())["project"].get("dependencies", [])
    want = {"mlx", _normalise(plat.mlx_library)}
    for python in pythons:
        tag = _py_tag(python)
        mlx_wheel = WHEELS_DIR / f"mlx-{pins.bundled['mlx']}-{tag}-{tag}-{plat.mlx_tag}.whl"
        got = mlx_distributions(plat, python, own, wheel_requires_dist(mlx_wheel))
        if got != want:
            raise PackagingError(
                f"on {plat.name} (Python {_fmt_py(python)}) `pip install {pins.own_name}` would install "
                f"{sorted(got) or 'no MLX'} (from the markers of [project].dependencies in {PYPROJECT.name} and "
                f"{mlx_wheel.name}'s Requires-Dist), but the zip bundles {sorted(want)}: fix the markers, "
                "or Platform.mlx_library in addon/package.py"
            )
    log(f"  Requires-Dist: pip install {pins.own_name} pulls mlx and {plat.mlx_library} on {plat.name}")


def check_bundled_markers(pins: Pins, plat: Platform, pythons) -> None:
    """Every bundled pin but MLX's: its markers pull it on this platform exactly where the zip bundles it.

    A ``pip install`` of our wheel (``[project].dependencies``) or of an extra of
    ``BUNDLED_EXTRAS`` (``mlx3d-splat[poses]``) with this platform's markers, for
    each Python, against ``PURE_PYTHON`` (every platform) and the platforms
    ``BINARY_WHEEL_TAGS`` names for the package (a stable-ABI wheel of
    ``STABLE_ABI``, one for all Pythons, likewise).
    """
    requirement = _requirement_class()
    if requirement is None:
        log("  (packaging is not installed: the markers check of the bundled pins is skipped)")
        return
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    optional = project.get("optional-dependencies", {})
    sources = [("", project.get("dependencies", []))] + [(extra, optional.get(extra, [])) for extra in BUNDLED_EXTRAS]
    pulled_here = []
    for extra, requirements in sources:
        what = f"{pins.own_name}[{extra}]" if extra else pins.own_name
        for text in requirements:
            req = requirement(text)
            name = _normalise(req.name)
            if name not in PURE_PYTHON and name not in BINARY_WHEEL_TAGS:
                continue  # MLX (check_mlx_requirements) or provided by Blender
            bundled = name in PURE_PYTHON or plat.name in BINARY_WHEEL_TAGS[name]
            for python in pythons:
                env = {**_marker_environment(plat, python), "extra": extra}
                pulled = req.marker is None or req.marker.evaluate(env)
                if pulled != bundled:
                    raise PackagingError(
                        f"on {plat.name} (Python {_fmt_py(python)}) `pip install {what}` "
                        f"{'pulls' if pulled else 'does not pull'} {name} ({text!r} in {PYPROJECT.name}), but the "
                        f"zip {'bundles' if bundled else 'does not bundle'} it: the markers and BINARY_WHEEL_TAGS "
                        "in addon/package.py must name the same platforms"
                    )
            if req.marker is not None:
                state = "pulled and bundled" if bundled else "neither pulled nor bundled"
                pulled_here.append(f"{name} ({what}: {state})")
    if pulled_here:
        log(f"  markers on {plat.name}: {', '.join(pulled_here)}")


# ------------------------------------------------------------- the kernel library
_kernel_build_module = None


def kernel_build():
    """``mlx3d/csrc/kernels/build.py`` as a module (``library_name``, ``TARGETS``, ``zig``)."""
    global _kernel_build_module
    if _kernel_build_module is None:
        spec = importlib.util.spec_from_file_location("mlx3d_kernels_build", KERNEL_BUILD_SCRIPT)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        _kernel_build_module = module
    return _kernel_build_module


def kernel_wheel_path(platform_name: str) -> str:
    """Where the platform's kernel library lies in our wheel: ``mlx3d/_kernels/`` + build.py's name for it."""
    return f"{KERNEL_DIR_IN_WHEEL}/{kernel_build().library_name(platform_name)}"


def binary_kind(data: bytes) -> tuple[str, str]:
    """(format, machine) of a shared library, from its header: ``("ELF", "x86-64")``, ``("PE32+", "x86-64")``,
    ``("ELF", "aarch64")``, ``("Mach-O", "arm64")``, ...; ``("unknown", "")`` when none of these formats."""
    if data[:4] == b"\x7fELF" and len(data) >= 20:
        bits = {1: "ELF32", 2: "ELF"}.get(data[4], "ELF?")
        machine = struct.unpack_from("<H" if data[5] == 1 else ">H", data, 18)[0]
        return bits, {62: "x86-64", 183: "aarch64", 3: "x86", 40: "arm"}.get(machine, f"machine {machine}")
    if data[:2] == b"MZ" and len(data) >= 64:
        pe = struct.unpack_from("<I", data, 0x3C)[0]
        if data[pe:pe + 4] == b"PE\0\0" and len(data) >= pe + 26:
            machine, = struct.unpack_from("<H", data, pe + 4)
            magic, = struct.unpack_from("<H", data, pe + 24)  # the optional header's
            return ({0x20B: "PE32+", 0x10B: "PE32"}.get(magic, "PE?"),
                    {0x8664: "x86-64", 0xAA64: "arm64", 0x14C: "x86"}.get(machine, f"machine {machine:#x}"))
    if data[:4] == b"\xcf\xfa\xed\xfe" and len(data) >= 8:  # MH_MAGIC_64, little-endian
        cputype, = struct.unpack_from("<I", data, 4)
        return "Mach-O", {0x0100000C: "arm64", 0x01000007: "x86-64"}.get(cputype, f"cputype {cputype:#x}")
    return "unknown", ""


def _glibc_needed(data: bytes) -> tuple[int, int] | None:
    """The newest ``GLIBC_X.Y`` symbol version an ELF library names (None: none)."""
    versions = {(int(a), int(b)) for a, b in re.findall(rb"GLIBC_(\d+)\.(\d+)", data)}
    return max(versions) if versions else None


def _macho_commands(data: bytes) -> list[tuple[int, int]]:
    """(command, offset) of each load command of a 64-bit Mach-O file."""
    ncmds, = struct.unpack_from("<I", data, 16)
    commands, offset = [], 32  # after mach_header_64
    for _ in range(ncmds):
        cmd, size = struct.unpack_from("<II", data, offset)
        commands.append((cmd, offset))
        if size <= 0:
            break
        offset += size
    return commands


def _macos_minimum(data: bytes) -> tuple[int, int] | None:
    """The minimum macOS of a 64-bit Mach-O file (``LC_BUILD_VERSION`` or ``LC_VERSION_MIN_MACOSX``)."""
    for cmd, offset in _macho_commands(data):
        if cmd in (0x32, 0x24):  # LC_BUILD_VERSION (platform, minos, ...), LC_VERSION_MIN_MACOSX (version, ...)
            version, = struct.unpack_from("<I", data, offset + (12 if cmd == 0x32 else 8))
            return version >> 16, (version >> 8) & 0xFF
    return None


def check_kernel_library(data: bytes, plat: Platform, what: str) -> str:
    """Stops unless ``data`` is ``plat``'s kernel library: its format and machine, the ABI function exported, and
    what its wheel's tag promises (glibc and macOS versions); returns a description of it."""
    kind = binary_kind(data)
    if kind != plat.kernel_binary:
        raise PackagingError(f"{what} is {' '.join(kind)}, not the {plat.name} kernel library "
                             f"({' '.join(plat.kernel_binary)})")
    if KERNEL_ABI_SYMBOL.encode() + b"\0" not in data:
        raise PackagingError(f"{what} does not export {KERNEL_ABI_SYMBOL}: not a build of mlx3d/csrc/kernels")
    described = f"{' '.join(kind)}, {len(data) / 1e3:.0f} kB"
    tag = plat.pure_tag or ""
    if match := re.fullmatch(r"manylinux_(\d+)_(\d+)_\w+", tag):
        promised, needed = (int(match.group(1)), int(match.group(2))), _glibc_needed(data)
        if needed is None or needed > promised:
            raise PackagingError(f"{what} needs glibc {'.'.join(map(str, needed or ()))}, newer than its wheel's tag "
                                 f"{tag} allows: build it for glibc {'.'.join(map(str, promised))} (build.py's target)")
        described += f", glibc {needed[0]}.{needed[1]}"
    elif match := re.fullmatch(r"macosx_(\d+)_(\d+)_\w+", tag):
        promised, needed = (int(match.group(1)), int(match.group(2))), _macos_minimum(data)
        if needed is None or needed > promised:
            raise PackagingError(f"{what} needs macOS {'.'.join(map(str, needed or ('?',)))}, newer than its "
                                 f"wheel's tag {tag} allows: build it for macOS {'.'.join(map(str, promised))} "
                                 "(build.py's target)")
        described += f", macOS {needed[0]}.{needed[1]}"
    if kind == ("Mach-O", "arm64"):  # macOS on Apple silicon loads no arm64 code without a signature (ad hoc will do)
        if not any(cmd == 0x1D for cmd, _ in _macho_commands(data)):  # LC_CODE_SIGNATURE
            raise PackagingError(f"{what} has no code signature (LC_CODE_SIGNATURE): macOS would refuse to load it")
        described += ", signed"
    return described


def build_kernel_library(platform_name: str, *, rebuild: bool = False) -> Path:
    """The platform's kernel library, built by build.py into ``build/extension/kernels-PLATFORM/`` (reused while
    newer than every file of mlx3d/csrc/kernels) and checked (``check_kernel_library``)."""
    build_script = kernel_build()
    plat = PLATFORMS[platform_name]
    out = WORK_DIR / f"kernels-{platform_name}"
    library = out / build_script.library_name(platform_name)
    if not rebuild and library.is_file() and library.stat().st_mtime >= _newest_source_mtime((KERNEL_SOURCES,)):
        log(f"  have {library.relative_to(ROOT)} (newer than {KERNEL_SOURCES.relative_to(ROOT)})")
    else:
        if build_script.TARGETS.get(platform_name) is not None:
            try:
                build_script.zig()
            except SystemExit:
                raise PackagingError(
                    f"the {platform_name} kernel library is cross-compiled with zig, which is not installed (no "
                    f"ziglang in {sys.executable}, no zig on PATH): run `make cross-tools`, which installs the pinned "
                    "ziglang into the venv. The zip is not built without its library"
                ) from None
        WORK_DIR.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        with tempfile.TemporaryDirectory(dir=WORK_DIR, prefix=f".kernels-{platform_name}-") as tmp:
            _run([sys.executable, KERNEL_BUILD_SCRIPT, platform_name, "--out", tmp],
                 what=f"building the {platform_name} kernel library", capture=True)
            built = Path(tmp) / library.name
            if not built.is_file():
                raise PackagingError(f"{KERNEL_BUILD_SCRIPT.relative_to(ROOT)} {platform_name} wrote no {library.name}")
            out.mkdir(parents=True, exist_ok=True)
            os.replace(built, library)
        log(f"  built {library.relative_to(ROOT)} ({time.perf_counter() - start:.1f} s)")
    log(f"  kernel library: {check_kernel_library(library.read_bytes(), plat, library.name)}")
    return library


def _record_line(name: str, data: bytes) -> list[str]:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return [name, f"sha256={digest}", str(len(data))]


def holds_kernel_library(wheel: Path, platform_name: str, library: Path) -> bool:
    """True when the wheel's ``mlx3d/_kernels/`` holds this library alone (the same bytes)."""
    name = kernel_wheel_path(platform_name)
    with zipfile.ZipFile(wheel) as zf:
        ours = [n for n in zf.namelist() if n.startswith(f"{KERNEL_DIR_IN_WHEEL}/")]
        return ours == [name] and zf.read(name) == library.read_bytes()


def add_kernel_library(wheel: Path, platform_name: str, library: Path) -> bool:
    """Puts the kernel library into a built wheel at ``mlx3d/_kernels/NAME`` (any other file of that folder
    out), with its ``RECORD`` line; True when the wheel changed, False when it held the same bytes already.

    The wheel keeps its modification time: it says when the wheel was built from the sources."""
    if holds_kernel_library(wheel, platform_name, library):
        return False
    name, data = kernel_wheel_path(platform_name), library.read_bytes()
    with zipfile.ZipFile(wheel) as zf:
        records = [n for n in zf.namelist() if re.fullmatch(r"[^/]+\.dist-info/RECORD", n)]
        if len(records) != 1:
            raise PackagingError(f"{wheel.name}: expected one *.dist-info/RECORD, found {records}")
        record = records[0]
        rows = [row for row in csv.reader(io.StringIO(zf.read(record).decode()))
                if row and row[0] != record and not row[0].startswith(f"{KERNEL_DIR_IN_WHEEL}/")]
        entries = [(info, zf.read(info)) for info in zf.infolist()
                   if info.filename != record and not info.filename.startswith(f"{KERNEL_DIR_IN_WHEEL}/")]
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows([*rows, _record_line(name, data), [record, "", ""]])
    stat = wheel.stat()
    tmp = wheel.with_name(f".{wheel.name}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w") as out:
            for info, content in entries:  # the package's files, then the library, then .dist-info
                if ".dist-info/" not in info.filename:
                    out.writestr(info, content)
            _zip_entry(out, name, data, 0o755)
            for info, content in entries:
                if ".dist-info/" in info.filename:
                    out.writestr(info, content)
            out.writestr(zipfile.ZipInfo(record, date_time=(1980, 1, 1, 0, 0, 0)), text.getvalue(),
                         compress_type=zipfile.ZIP_DEFLATED)
        os.replace(tmp, wheel)
    finally:
        tmp.unlink(missing_ok=True)
    os.utime(wheel, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    return True


def check_wheel_kernel_library(wheel: Path, plat: Platform, library: Path | None) -> None:
    """Our wheel for ``plat`` holds its kernel library alone in ``mlx3d/_kernels/`` (the bytes of ``library``
    when given), with the right ``RECORD`` line."""
    name = kernel_wheel_path(plat.name)
    with zipfile.ZipFile(wheel) as zf:
        ours = [n for n in zf.namelist() if n.startswith(f"{KERNEL_DIR_IN_WHEEL}/")]
        if ours != [name]:
            hint = "" if ours else f" (build it with `make extension` on a {plat.name} machine)"
            raise PackagingError(f"{wheel.name} holds {ours or 'no kernel library'}, not {name}{hint}")
        data = zf.read(name)
        record = next(n for n in zf.namelist() if re.fullmatch(r"[^/]+\.dist-info/RECORD", n))
        lines = zf.read(record).decode().splitlines()
    if library is not None and data != library.read_bytes():
        raise PackagingError(f"{wheel.name}: its {name} is not {library.relative_to(ROOT)}")
    if ",".join(_record_line(name, data)) not in lines:
        raise PackagingError(f"{wheel.name}: its RECORD has no line for {name} with its hash and size")
    check_kernel_library(data, plat, f"{wheel.name}'s {name}")


# ------------------------------------------------------------------ our own wheel
def _run(cmd, *, what: str, env=None, cwd=None, capture: bool = False) -> subprocess.CompletedProcess:
    try:
        result = subprocess.run([str(c) for c in cmd], env=env, cwd=cwd, text=True,
                                stdout=subprocess.PIPE if capture else None,
                                stderr=subprocess.STDOUT if capture else None)
    except OSError as exc:
        raise PackagingError(f"{what}: cannot run {cmd[0]}: {exc}") from exc
    if result.returncode != 0:
        tail = ""
        if capture and result.stdout:
            tail = "\n" + "\n".join(result.stdout.strip().splitlines()[-30:])
        raise PackagingError(f"{what} failed (exit {result.returncode}): {' '.join(map(str, cmd))}{tail}")
    return result


def _python_version_of(executable: str) -> tuple[int, int] | None:
    try:
        out = subprocess.run([executable, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
                             capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return None
    major, minor = out.stdout.strip().split(".")
    return int(major), int(minor)


def find_python(python: tuple[int, int]) -> str:
    """An interpreter of this version: the running one, ``python3.X`` on PATH, or pyenv's."""
    if sys.version_info[:2] == python:
        return sys.executable
    name = f"python{_fmt_py(python)}"
    candidates = []
    if found := shutil.which(name):
        candidates.append(found)
    pyenv_root = Path(os.environ.get("PYENV_ROOT", Path.home() / ".pyenv"))
    candidates += [str(p) for p in sorted((pyenv_root / "versions").glob(f"{_fmt_py(python)}.*/bin/{name}"), reverse=True)]
    for candidate in candidates:
        if _python_version_of(candidate) == python:
            return candidate
    raise PackagingError(
        f"Python {_fmt_py(python)} is needed to build the {_py_tag(python)} wheel of mlx3d_splat, "
        f"but no working `{name}` was found (PATH, pyenv). Install it (with its headers), "
        f"or leave that version out with --python"
    )


def _has_build_requirements(pins: Pins) -> bool:
    """True when the running interpreter can build our wheel without isolation."""
    for module in ("scikit_build_core", "nanobind"):
        if importlib.util.find_spec(module) is None:
            return False
    try:
        return importlib.metadata.version("mlx") == pins.bundled["mlx"]
    except importlib.metadata.PackageNotFoundError:
        return False


def build_interpreter(pins: Pins, python: tuple[int, int]) -> str:
    """A Python of this version with ``[build-system].requires`` installed."""
    if sys.version_info[:2] == python and _has_build_requirements(pins):
        return sys.executable
    venv = WORK_DIR / f"venv-{_py_tag(python)}"
    exe = venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    stamp = venv / "build-requires.txt"
    wanted = "\n".join(pins.build_requires) + "\n"
    if exe.exists() and stamp.exists() and stamp.read_text() == wanted:
        return str(exe)
    base = find_python(python)
    log(f"  creating build venv {venv.relative_to(ROOT)} ({base})")
    shutil.rmtree(venv, ignore_errors=True)
    _run([base, "-m", "venv", venv], what=f"python{_fmt_py(python)} -m venv")
    _run([exe, "-m", "pip", "install", "--quiet", *pins.build_requires], what="installing the build requirements")
    stamp.write_text(wanted)
    return str(exe)


def _newest_source_mtime(inputs=SOURCE_INPUTS) -> float:
    """The newest modification time of the files of ``inputs`` (paths under ROOT: files or folders)."""
    newest = 0.0
    for name in inputs:
        path = ROOT / name
        files = [path] if path.is_file() else [
            p for p in path.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.suffix not in {".pyc", ".so", ".dylib"}
        ]
        for p in files:
            newest = max(newest, p.stat().st_mtime)
    return newest


def build_own_wheel(pins: Pins, plat: Platform, python: tuple[int, int], *, rebuild: bool,
                    reuse: bool = False, library: Path) -> Path:
    """Our compiled wheel (with ``mlx3d._core`` and the kernel library ``library``) for this machine's platform
    and this Python.

    One in ``wheels/`` is reused when newer than the sources, or with ``reuse`` whatever its age; the kernel
    library is put into it when it does not hold those bytes (and checked to load from it).
    """
    filename = compiled_wheel_name(pins, plat, python)
    target = WHEELS_DIR / filename
    if not rebuild and _valid_zip(target):
        fresh = target.stat().st_mtime >= _newest_source_mtime()
        if fresh or reuse:
            state = "newer than the sources" if fresh else "older than the sources, reused as asked"
            if holds_kernel_library(target, plat.name, library):
                log(f"  have {filename} ({state}, with this kernel library)")
                return target
            with tempfile.TemporaryDirectory(dir=WHEELS_DIR, prefix=".kernels-") as tmp:
                candidate = Path(tmp) / filename
                shutil.copy2(target, candidate)  # its time too
                add_kernel_library(candidate, plat.name, library)
                with tempfile.TemporaryDirectory(prefix="mlx3d-wheel-check-") as unpacked:
                    with zipfile.ZipFile(candidate) as zf:
                        zf.extractall(unpacked)
                    checked = _check_kernels_load(candidate, unpacked)  # _core is as it was
                os.replace(candidate, target)
            log(f"  have {filename} ({state}); added {kernel_wheel_path(plat.name)}: {checked}")
            return target
    exe = build_interpreter(pins, python)
    out = WORK_DIR / f"out-{_py_tag(python)}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    build_dir = WORK_DIR / f"cmake-{_py_tag(python)}-{plat.own_tag}"
    log(f"  building {filename} with {exe}")
    start = time.perf_counter()
    _run([exe, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
          "--config-settings", f"build-dir={build_dir}", "--wheel-dir", out, ROOT],
         what=f"building the {_py_tag(python)} wheel", cwd=ROOT, capture=True)
    built = sorted(out.glob("*.whl"))
    if [p.name for p in built] != [filename]:
        raise PackagingError(f"building the {_py_tag(python)} wheel gave {[p.name for p in built]}, not {filename}")
    add_kernel_library(built[0], plat.name, library)
    check_own_wheel(built[0], exe)
    WHEELS_DIR.mkdir(exist_ok=True)
    os.replace(built[0], target)
    shutil.rmtree(out, ignore_errors=True)
    log(f"  built {filename} ({_mb(target)}, {time.perf_counter() - start:.1f} s)")
    return target


_CHECK = r"""
import sys
wheel_dir, site_dir = sys.argv[1], sys.argv[2]
sys.path.insert(0, wheel_dir)
sys.path.append(site_dir)
import mlx.core as mx
import mlx3d._core as core
assert core.__file__.startswith(wheel_dir), core.__file__
assert core.mlx_version() == mx.__version__, (core.mlx_version(), mx.__version__)
scale = getattr(core, "_mlx_scale", None)
if scale is not None:
    try:
        out = scale(mx.array([1.0, 2.0]), 3.0)
    except TypeError:
        print(core.__file__)
        sys.exit(3)
    assert out.tolist() == [3.0, 6.0], out
print("ok", core.__file__)
"""

#: The kernel library from an unpacked wheel, through ``mlx3d.kernel_library`` (pure Python: any Python with
#: MLX and numpy runs it, whatever the wheel's Python).
_KERNEL_CHECK = r"""
import os, sys
wheel_dir, site_dir = sys.argv[1], sys.argv[2]
sys.path.insert(0, wheel_dir)
sys.path.append(site_dir)
import mlx3d.kernel_library as kernels
assert kernels.__file__.startswith(wheel_dir), kernels.__file__
assert kernels.available(), kernels.failure()
assert str(kernels.library_path()).startswith(os.path.realpath(wheel_dir)), kernels.library_path()
print("ok", kernels.library_path(), kernels.build_info())
"""


def check_own_wheel(wheel: Path, exe: str) -> None:
    """Import ``mlx3d._core`` from the wheel next to the build interpreter's MLX, in ``python -I -S``; and load
    its kernel library through ``mlx3d.kernel_library`` with the running interpreter's MLX and numpy (the build
    interpreter may have no numpy)."""
    site_dir = _run([exe, "-c", "import sysconfig; print(sysconfig.get_paths()['platlib'])"],
                    what="locating site-packages", capture=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="mlx3d-wheel-check-") as tmp:
        with zipfile.ZipFile(wheel) as zf:
            zf.extractall(tmp)
        result = subprocess.run([exe, "-I", "-S", "-c", _CHECK, tmp, site_dir], cwd=tmp,
                                capture_output=True, text=True)
        if result.returncode == 0:
            kernels = _check_kernels_load(wheel, tmp)
    if result.returncode == 3:
        raise PackagingError(
            f"{wheel.name}: mlx3d._core ({Path(result.stdout.strip()).name}) loads but rejects mlx.core's "
            "mx.array (TypeError from _core._mlx_scale). It was compiled for Python's stable ABI: "
            "nanobind keeps stable-ABI modules in a type registry of their own, and mlx.core is not a "
            "stable-ABI build. Drop STABLE_ABI from nanobind_add_module in CMakeLists.txt"
        )
    if result.returncode != 0:
        raise PackagingError(f"{wheel.name}: importing mlx3d._core from the wheel failed:\n"
                             f"{(result.stdout + result.stderr).strip()}")
    log(f"  checked {wheel.name}: mlx3d._core loads with MLX and takes mx.array; {kernels}")


def _check_kernels_load(wheel: Path, unpacked: str) -> str:
    """``mlx3d.kernel_library`` of the unpacked wheel loads the wheel's library (``_KERNEL_CHECK``)."""
    if importlib.util.find_spec("mlx") is None or importlib.util.find_spec("numpy") is None:
        return f"(no mlx or numpy in {sys.executable}: the kernel library's load check is skipped)"
    import sysconfig

    env = {k: v for k, v in os.environ.items() if k != "MLX3D_KERNELS"}  # the wheel's library, not another
    result = subprocess.run([sys.executable, "-I", "-S", "-c", _KERNEL_CHECK, unpacked,
                             sysconfig.get_paths()["platlib"]], cwd=unpacked, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise PackagingError(f"{wheel.name}: mlx3d.kernel_library does not load the wheel's kernel library:\n"
                             f"{(result.stdout + result.stderr).strip()}")
    return "mlx3d.kernel_library loads the wheel's kernel library"


# ------------------------------------------------------------ our pure wheel
def _pure_metadata(project: dict) -> str:
    """METADATA (core metadata 2.1) of the pure wheel, from ``[project]``."""
    unknown = sorted(set(project) - _PURE_METADATA_KEYS)
    if unknown:
        raise PackagingError(
            f"{PYPROJECT.name}: [project] has {', '.join(unknown)}, which the pure wheel's METADATA does not "
            "carry yet: add it to _pure_metadata in addon/package.py"
        )
    lines = ["Metadata-Version: 2.1", f"Name: {project['name']}", f"Version: {project['version']}"]
    if project.get("description"):
        lines.append(f"Summary: {project['description']}")
    if project.get("keywords"):
        lines.append(f"Keywords: {','.join(project['keywords'])}")
    for label, url in project.get("urls", {}).items():
        lines.append(f"Project-URL: {label}, {url}")
    lines += [f"Classifier: {c}" for c in project.get("classifiers", [])]
    if project.get("requires-python"):
        lines.append(f"Requires-Python: {project['requires-python']}")
    lines += [f"Requires-Dist: {r}" for r in project.get("dependencies", [])]
    for extra, requirements in project.get("optional-dependencies", {}).items():
        lines.append(f"Provides-Extra: {extra}")
        for requirement in requirements:
            spec, _, marker = requirement.partition(";")
            marker = f"({marker.strip()}) and extra == \"{extra}\"" if marker.strip() else f"extra == \"{extra}\""
            lines.append(f"Requires-Dist: {spec.strip()}; {marker}")
    return "\n".join(lines) + "\n"


def _pure_entry_points(project: dict) -> str | None:
    groups = {"console_scripts": project.get("scripts", {}), "gui_scripts": project.get("gui-scripts", {}),
              **project.get("entry-points", {})}
    blocks = [f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items())
              for group, entries in groups.items() if entries]
    return "\n".join(blocks) if blocks else None


def _excluded(archive_name: str, patterns) -> bool:
    """``wheel.exclude`` globs (``**`` as any depth) against a path in the wheel."""
    for pattern in patterns:
        if pattern.endswith("/**") and archive_name.startswith(pattern[:-2]):
            return True
        if fnmatch.fnmatchcase(archive_name, pattern.replace("**/", "*").replace("**", "*")):
            return True
    return False


def pure_wheel_files() -> dict[str, Path]:
    """Path in the pure wheel -> source file, as scikit-build-core packages ``mlx3d`` (without ``_core``)."""
    wheel_config = tomllib.loads(PYPROJECT.read_text()).get("tool", {}).get("scikit-build", {}).get("wheel", {})
    packages, excludes = wheel_config.get("packages"), wheel_config.get("exclude", [])
    if not packages:
        raise PackagingError(f"{PYPROJECT.name}: no [tool.scikit-build] wheel.packages")
    files: dict[str, Path] = {}
    for package in packages:
        source_dir = ROOT / package
        if not source_dir.is_dir():
            raise PackagingError(f"{PYPROJECT.name}: wheel.packages names {package}, which is not a directory")
        for path in sorted(source_dir.rglob("*")):
            rel = path.relative_to(source_dir)
            if not path.is_file() or "__pycache__" in rel.parts or path.suffix in _NOT_PACKAGED_SUFFIXES:
                continue
            name = f"{source_dir.name}/{rel.as_posix()}"
            if not _excluded(name, excludes):
                files[name] = path
    for source, name in PURE_WHEEL_EXTRA_FILES:
        if not (ROOT / source).is_file():
            raise PackagingError(f"the pure wheel needs {source}, which does not exist")
        files[name] = ROOT / source
    return dict(sorted(files.items()))


def _zip_entry(zf: zipfile.ZipFile, name: str, data: bytes, mode: int = 0o644) -> str:
    """Writes one file with a fixed timestamp; returns its RECORD line."""
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    info.external_attr = mode << 16
    info.compress_type = zipfile.ZIP_DEFLATED
    zf.writestr(info, data)
    return ",".join(_record_line(name, data))


def write_pure_wheel(pins: Pins, path: Path, plat: Platform | None = None, library: Path | None = None) -> None:
    """Writes our pure-Python wheel (no ``_core``, no compiler) to ``path``: ``py3-none-any``, or with ``plat``
    and ``library`` that platform's, ``py3-none-TAG`` with the kernel library in ``mlx3d/_kernels/``."""
    if (plat is None) != (library is None):
        raise PackagingError("write_pure_wheel: a platform's wheel needs its kernel library, the generic one none")
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    dist_info = f"{pins.own_name}-{pins.own_version}.dist-info"
    tag, purelib = ("py3-none-any", "true") if plat is None else (f"py3-none-{plat.pure_tag}", "false")
    meta = {
        "METADATA": _pure_metadata(project),
        "WHEEL": f"Wheel-Version: 1.0\nGenerator: mlx3d addon/package.py\nRoot-Is-Purelib: {purelib}\nTag: {tag}\n",
    }
    if (entry_points := _pure_entry_points(project)) is not None:
        meta["entry_points.txt"] = entry_points
    with zipfile.ZipFile(path, "w") as zf:
        record = [_zip_entry(zf, name, source.read_bytes()) for name, source in pure_wheel_files().items()]
        if plat is not None:
            record.append(_zip_entry(zf, kernel_wheel_path(plat.name), library.read_bytes(), 0o755))
        record += [_zip_entry(zf, f"{dist_info}/{name}", text.encode()) for name, text in meta.items()]
        record.append(f"{dist_info}/RECORD,,")
        zf.writestr(zipfile.ZipInfo(f"{dist_info}/RECORD", date_time=(1980, 1, 1, 0, 0, 0)),
                    "\n".join(record) + "\n", compress_type=zipfile.ZIP_DEFLATED)


def build_pure_wheel(pins: Pins, plat: Platform | None = None, library: Path | None = None) -> Path:
    """Our pure-Python wheel in ``wheels/`` (the generic one, or with ``plat`` and its kernel library
    ``library`` that platform's), rewritten only when its bytes change; checked once per process."""
    target = WHEELS_DIR / pure_wheel_name(pins, plat)
    library_name = kernel_wheel_path(plat.name).rsplit("/", 1)[1] if plat is not None else ""
    WHEELS_DIR.mkdir(exist_ok=True)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=WHEELS_DIR, prefix=".pure-") as tmp:
        built = Path(tmp) / target.name
        write_pure_wheel(pins, built, plat, library)
        if _valid_zip(target) and target.read_bytes() == built.read_bytes():
            log(f"  have {target.name} (the same bytes as built from the sources)")
        else:
            check_pure_wheel(built, library_name)
            os.replace(built, target)
            _checked_pure_wheels.add(target)
            log(f"  built {target.name} ({_mb(target)}, {time.perf_counter() - start:.1f} s)")
    if target not in _checked_pure_wheels:
        check_pure_wheel(target, library_name)
    return target


_checked_pure_wheels: set[Path] = set()

_PURE_CHECK = r"""
import importlib.util, os, sys
wheel_dir, site_dir, header_path, library = sys.argv[1:5]
sys.path.insert(0, wheel_dir)
sys.path.append(site_dir)
import mlx3d
assert mlx3d.__file__.startswith(wheel_dir), mlx3d.__file__
assert importlib.util.find_spec("mlx3d._core") is None, "the pure wheel holds mlx3d._core"
kernels = os.path.join(os.path.dirname(mlx3d.__file__), "_kernels")
found = sorted(os.listdir(kernels)) if os.path.isdir(kernels) else []
assert found == ([library] if library else []), f"mlx3d/_kernels/ holds {found}, not {library or 'nothing'}"
from mlx3d.render import raster_metal
assert raster_metal.__file__.startswith(wheel_dir), raster_metal.__file__
with open(header_path, encoding="utf-8") as f:
    assert raster_metal.kernel_header() == f.read(), "kernel_header() is not raster_math.h"
print("ok", os.path.join(os.path.dirname(raster_metal.__file__), "raster_math.h"))
"""


def check_pure_wheel(wheel: Path, library: str = "") -> None:
    """Imports ``mlx3d`` from the pure wheel alone (next to the running interpreter's MLX) in ``python -I -S``;
    its ``mlx3d/_kernels/`` holds the file ``library`` alone (none: no such folder)."""
    if importlib.util.find_spec("mlx") is None:
        log(f"  (no mlx in {sys.executable}: the import check of {wheel.name} is skipped)")
        return
    import sysconfig

    site_dir = sysconfig.get_paths()["platlib"]
    header = ROOT / PURE_WHEEL_EXTRA_FILES[0][0]
    with tempfile.TemporaryDirectory(prefix="mlx3d-wheel-check-") as tmp:
        with zipfile.ZipFile(wheel) as zf:
            zf.extractall(tmp)
        result = subprocess.run([sys.executable, "-I", "-S", "-c", _PURE_CHECK, tmp, site_dir, header, library],
                                cwd=tmp, env={**os.environ, "MLX3D_NO_CORE": "1"}, capture_output=True, text=True)
    if result.returncode != 0:
        raise PackagingError(f"{wheel.name}: importing mlx3d from the pure wheel failed:\n"
                             f"{(result.stdout + result.stderr).strip()}")
    _checked_pure_wheels.add(wheel)
    log(f"  checked {wheel.name}: mlx3d imports without _core, kernel_header() reads raster_math.h, "
        + (f"mlx3d/_kernels/ holds {library} alone" if library else "no mlx3d/_kernels/"))


# --------------------------------------------------------------------------- build
def find_blender_ext(explicit: str | None = None) -> list[str]:
    """Command prefix that runs Blender's extension CLI (``blender_ext.py``)."""
    if explicit:
        if not Path(explicit).is_file():
            raise PackagingError(f"--blender-ext: {explicit} does not exist")
        return [sys.executable, explicit]
    spec = importlib.util.find_spec("bpy")
    if spec is not None and spec.submodule_search_locations:
        found = []
        for location in spec.submodule_search_locations:
            found += Path(location).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py")
        if found:
            newest = max(found, key=lambda p: tuple(int(x) for x in p.parts[-6].split(".") if x.isdigit()))
            return [sys.executable, str(newest)]
    if blender := shutil.which("blender"):
        return [blender, "--factory-startup", "--command", "extension"]
    raise PackagingError(
        "Blender's extension CLI was not found: install the bpy module (`pip install bpy==5.0.1`, "
        "part of `pip install -e '.[test]'`), put `blender` on PATH, or pass --blender-ext PATH/blender_ext.py"
    )


def stage(platform_name: str, wheels: list[Wheel]) -> Path:
    """A source tree with only what the zip holds, and a manifest for this platform.

    A new directory each time (builds running side by side do not share one); the caller removes it.
    """
    WORK_DIR.mkdir(parents=True, exist_ok=True)
    stage_dir = Path(tempfile.mkdtemp(prefix=f"stage-{platform_name}-", dir=WORK_DIR))
    (stage_dir / "wheels").mkdir()
    text = MANIFEST.read_text()
    text = replace_toml_list(text, "platforms", [platform_name], source=MANIFEST.name)
    text = replace_toml_list(text, "wheels", manifest_wheel_paths(wheels), source=MANIFEST.name)
    (stage_dir / MANIFEST.name).write_text(text)
    shutil.copy2(ROOT / "__init__.py", stage_dir / "__init__.py")
    for extra in sorted(ROOT.glob("LICENSE*")):
        shutil.copy2(extra, stage_dir / extra.name)
    shutil.copytree(ROOT / "addon", stage_dir / "addon",
                    ignore=shutil.ignore_patterns("package.py", "__pycache__", "*.pyc", ".*"))
    for w in wheels:
        src, dst = WHEELS_DIR / w.filename, stage_dir / "wheels" / w.filename
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)
    return stage_dir


def build(platform_name: str | None = None, pythons=DEFAULT_PYTHONS, out_dir: Path | str = DEFAULT_OUT, *,
          rebuild: bool = False, update_manifest: bool = True, blender_ext: str | None = None,
          reuse_compiled: bool = False) -> BuildResult:
    """Builds the extension zip for one platform; returns its path, size, wheels and build time.

    ``update_manifest=False`` leaves the repository's ``blender_manifest.toml`` as it
    is; ``reuse_compiled=True`` takes compiled wheels already in ``wheels/`` even
    when they are older than the sources (a packaging check that does not need
    the latest ``_core``).
    """
    start = time.perf_counter()
    host = host_platform()
    platform_name = platform_name or host
    if platform_name not in PLATFORMS:
        raise PackagingError(f"unsupported platform {platform_name!r}; choose one of {', '.join(PLATFORMS)}")
    plat = PLATFORMS[platform_name]
    pythons = tuple(sorted(set(pythons)))
    out_dir = Path(out_dir).resolve()

    log(f"1/6 pins: {MANIFEST.name} for {platform_name}, Python {', '.join(map(_fmt_py, pythons))}")
    pins = read_pins()
    here = {k: v for k, v in pins.pinned.items() if k not in BINARY_WHEEL_TAGS or platform_name in BINARY_WHEEL_TAGS[k]}
    log(f"  {pins.own_name} {pins.own_version}; bundled: "
        + ", ".join(f"{k}=={v}" for k, v in sorted(here.items())) + f", {plat.mlx_library}=={pins.bundled['mlx']}")
    if sync_manifest(pins, write=update_manifest):
        log(f"  {MANIFEST.name} platforms and wheels lists are up to date")
    wheels = expected_wheels(pins, [platform_name], pythons)

    log("2/6 third-party wheels")
    download_wheels(wheels, pythons)
    check_mlx_requirements(pins, plat, pythons)
    check_bundled_markers(pins, plat, pythons)

    log("3/6 the kernel library and the mlx3d_splat wheels")
    library = None
    if not plat.compiled:
        library = build_kernel_library(platform_name, rebuild=rebuild)
        build_pure_wheel(pins)  # the generic one, for pip (no kernel library): not in the zip
        build_pure_wheel(pins, plat, library)
    elif platform_name == host:
        library = build_kernel_library(platform_name, rebuild=rebuild)
        for python in pythons:
            build_own_wheel(pins, plat, python, rebuild=rebuild, reuse=reuse_compiled, library=library)
    else:
        log(f"  this machine is not {platform_name}: using the compiled mlx3d_splat wheels already in wheels/, "
            "with the kernel library they hold")

    log("4/6 checking the wheels the manifest lists")
    missing = [w.filename for w in wheels if not _valid_zip(WHEELS_DIR / w.filename)]
    if missing:
        hint = "" if platform_name == host else f" (build them with `make extension` on a {platform_name} machine)"
        raise PackagingError(f"missing from {WHEELS_DIR.relative_to(ROOT)}/: {', '.join(missing)}{hint}")
    own = [w.filename for w in wheels if w.filename.startswith(f"{pins.own_name}-")]
    for name in own:
        check_wheel_kernel_library(WHEELS_DIR / name, plat, library)
    log(f"  all {len(wheels)} present; {', '.join(own)}: {kernel_wheel_path(platform_name)} inside")

    log("5/6 blender_ext.py build")
    cli = find_blender_ext(blender_ext)
    stage_dir = stage(platform_name, wheels)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        _run([*cli, "build", "--source-dir", stage_dir, "--output-dir", out_dir, "--split-platforms"],
             what="blender_ext.py build", capture=True)
        manifest = tomllib.loads((stage_dir / MANIFEST.name).read_text())
    finally:
        shutil.rmtree(stage_dir, ignore_errors=True)
    zip_path = out_dir / f"{manifest['id']}-{manifest['version']}-{platform_name.replace('-', '_')}.zip"
    if not zip_path.is_file():
        raise PackagingError(f"blender_ext.py build did not write {zip_path}")
    validated = _run([*cli, "validate", zip_path], what="blender_ext.py validate", capture=True)
    for line in (validated.stdout or "").strip().splitlines():
        log(f"  blender_ext.py validate: {line}")

    with zipfile.ZipFile(zip_path) as zf:
        inside = sorted(n.split("/", 1)[1] for n in zf.namelist() if n.startswith("wheels/") and n.endswith(".whl"))
        zipped = tomllib.loads(zf.read(MANIFEST.name).decode())
    if inside != sorted(w.filename for w in wheels):
        raise PackagingError(f"{zip_path.name} holds wheels {inside}, expected {[w.filename for w in wheels]}")
    if zipped.get("platforms") != [platform_name] or zipped.get("wheels") != manifest_wheel_paths(wheels):
        raise PackagingError(f"{zip_path.name}: its manifest names platforms {zipped.get('platforms')} and wheels "
                             f"{zipped.get('wheels')}, not [{platform_name!r}] and the wheels inside")
    seconds = time.perf_counter() - start
    result = BuildResult(platform_name, zip_path, zip_path.stat().st_size, inside, seconds)
    log(f"6/6 {zip_path} ({_mb(zip_path)}, validated, {seconds:.1f} s)")
    for name in inside:
        log(f"  wheels/{name} ({_mb(WHEELS_DIR / name)})")
    return result


def build_all(platform_names=None, pythons=DEFAULT_PYTHONS, out_dir: Path | str = DEFAULT_OUT,
              **options) -> list[BuildResult]:
    """Builds the zips of several platforms (default: this machine's) one after the other."""
    results = [build(name, pythons, out_dir, **options) for name in (platform_names or [None])]
    if len(results) > 1:
        log("built " + ", ".join(f"{r.zip_path.name} ({r.size / 1e6:.1f} MB, {r.seconds:.1f} s)" for r in results))
    return results


def _mb(path: Path) -> str:
    return f"{path.stat().st_size / 1e6:.2f} MB"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="addon/package.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--platform", default=None,
                        help=f"Blender platform(s) to package, comma-separated: {', '.join(PLATFORMS)}, "
                             "or all (default: this machine's)")
    parser.add_argument("--python", default=",".join(map(_fmt_py, DEFAULT_PYTHONS)),
                        help="Python versions to ship wheels for (default: %(default)s)")
    parser.add_argument("--out", default=str(DEFAULT_OUT), help="output directory (default: dist/)")
    parser.add_argument("--rebuild", action="store_true",
                        help="rebuild the kernel library and the compiled mlx3d_splat wheels even when up to date")
    parser.add_argument("--blender-ext", default=None, help="path of Blender's blender_ext.py")
    args = parser.parse_args(argv)
    try:
        pythons = parse_pythons(args.python)
        if args.platform is None and host_platform() is None:
            raise PackagingError(
                f"this machine ({_platform.system()} {_platform.machine()}) is none of the supported platforms; "
                f"pass --platform ({', '.join(PLATFORMS)} or all)"
            )
        platforms = parse_platforms(args.platform) if args.platform is not None else None
        build_all(platforms, pythons, args.out, rebuild=args.rebuild, blender_ext=args.blender_ext)
    except PackagingError as exc:
        print(f"addon/package.py: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("addon/package.py: cancelled", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
