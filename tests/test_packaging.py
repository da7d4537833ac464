"""The extension zips of every platform (``addon/package.py --platform all``).

Builds the four zips once per module into a temporary folder (the wheels come
from ``wheels/``, downloaded from the registry on first use; the compiled
linux-x64 wheels already there are reused even when older than the sources,
and are built only when missing) and checks each: Blender's validator accepts
it, its manifest names exactly its platform and the wheels inside, and the
wheels are one ``mlx`` per Python (3.11, 3.13), MLX's library wheel, ours
(compiled with ``_core`` per Python on linux-x64, the pure-Python one with
``raster_math.h`` elsewhere), ``pillow`` and ``zstandard`` per Python and ``plyfile``,
and the ``poses`` extra: ``pycolmap`` per Python on every platform but
linux-arm64, for which pycolmap publishes no wheels, and ``av`` (PyAV) once on
every platform, a stable-ABI wheel (``cp311-abi3``) that serves both Pythons.

The expected tags below are written out here, not taken from package.py, so a
change there has to agree with what the registry publishes. The pure wheel is
also installed with pip into an empty folder and imported in a clean
interpreter, and pip's resolver (with each platform's environment markers) must
pull exactly mlx and its library wheel from our wheel's Requires-Dist, and
from ``[poses]`` pycolmap's wheel for the platform where the zip bundles it and
the av wheel the zip carries.

Each zip carries its platform's kernel library (mlx3d/csrc/kernels) inside our
wheel, at ``mlx3d/_kernels/NAME`` where ``mlx3d.kernel_library`` loads it: the
file's header says the platform's format and machine (read here byte by byte),
its export table names ``mlx3d_kernels_abi``, and it keeps what the wheel's
platform tag promises (glibc 2.17, macOS 11; the macOS one is signed). The
linux-x64 zip's wheel, installed alone next to the zip's MLX, loads it. The pure wheels the other zips carry are
therefore tagged for their platform (``py3-none-win_amd64``, ...); the generic
``py3-none-any`` wheel (for pip, in no zip) has no library.

Installing the linux-x64 zip into Blender and using it is
``tests/blender/test_extension_install.py``'s part.
"""

from __future__ import annotations

import base64
import csv
import hashlib
import importlib.util
import io
import json
import os
import platform as platform_module
import re
import struct
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from core_marks import once_per_suite, runs_no_kernel  # noqa: E402

pytestmark = [runs_no_kernel, once_per_suite]  # no kernel of ours runs here, and the zips are built for every Python

ROOT = Path(__file__).resolve().parents[1]
PYTHONS = ("cp311", "cp313")
HEADER = ROOT / "mlx3d" / "csrc" / "raster_math.h"

# Per Blender platform: the platform tag of mlx 0.32.4's wheels, MLX's library
# wheel there, pillow 13.0.0's, zstandard 0.25.0's and pycolmap 4.2.1's tags (None: pycolmap
# publishes no wheel there), av 18.1.0's (one cp311-abi3 wheel for every Python), the
# tags pip may pick for that platform, its environment markers, the platform tag of our
# pure wheel there (None: the compiled wheel), and its kernel library: file name and
# (format, machine) of its header.
EXPECTED = {
    "linux-x64": {
        "mlx": "manylinux_2_35_x86_64",
        "library": "mlx_cpu",
        "pillow": "manylinux_2_27_x86_64.manylinux_2_28_x86_64",
        "zstandard": "manylinux2014_x86_64.manylinux_2_17_x86_64",
        "pycolmap": "manylinux_2_28_x86_64",
        "av": "manylinux_2_28_x86_64",
        "pip_tags": ("manylinux_2_35_x86_64", "manylinux_2_28_x86_64", "manylinux_2_17_x86_64"),
        "markers": {"sys_platform": "linux", "platform_system": "Linux", "platform_machine": "x86_64",
                    "os_name": "posix"},
        "own": None,
        "kernel": "libmlx3d_kernels.so",
        "binary": ("ELF64", "x86-64"),
    },
    "macos-arm64": {
        "mlx": "macosx_14_0_arm64",
        "library": "mlx_metal",
        "pillow": "macosx_11_0_arm64",
        "zstandard": "macosx_11_0_arm64",
        "pycolmap": "macosx_14_0_arm64",
        "av": "macosx_14_0_arm64",
        "pip_tags": ("macosx_14_0_arm64",),
        "markers": {"sys_platform": "darwin", "platform_system": "Darwin", "platform_machine": "arm64",
                    "os_name": "posix"},
        "own": "macosx_11_0_arm64",
        "kernel": "libmlx3d_kernels.dylib",
        "binary": ("Mach-O 64", "arm64"),
    },
    "windows-x64": {
        "mlx": "win_amd64",
        "library": "mlx_cpu",
        "pillow": "win_amd64",
        "zstandard": "win_amd64",
        "pycolmap": "win_amd64",
        "av": "win_amd64",
        "pip_tags": ("win_amd64",),
        "markers": {"sys_platform": "win32", "platform_system": "Windows", "platform_machine": "AMD64",
                    "os_name": "nt"},
        "own": "win_amd64",
        "kernel": "mlx3d_kernels.dll",
        "binary": ("PE32+", "x86-64"),
    },
    "linux-arm64": {
        "mlx": "manylinux_2_35_aarch64",
        "library": "mlx_cpu",
        "pillow": "manylinux_2_27_aarch64.manylinux_2_28_aarch64",
        "zstandard": "manylinux2014_aarch64.manylinux_2_17_aarch64",
        "pycolmap": None,
        "av": "manylinux_2_28_aarch64",
        "pip_tags": ("manylinux_2_35_aarch64", "manylinux_2_28_aarch64", "manylinux_2_17_aarch64"),
        "markers": {"sys_platform": "linux", "platform_system": "Linux", "platform_machine": "aarch64",
                    "os_name": "posix"},
        "own": "manylinux_2_17_aarch64",
        "kernel": "libmlx3d_kernels.so",
        "binary": ("ELF64", "aarch64"),
    },
}
PLATFORMS = tuple(EXPECTED)


def load_package_script():
    """``addon/package.py`` as a module (the same module object tests/blender/conftest.py loads)."""
    name = "mlx3d_extension_package"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "addon" / "package.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def package():
    return load_package_script()


@pytest.fixture(scope="module")
def pins(package):
    return package.read_pins()


@pytest.fixture(scope="module")
def blender_ext(package):
    try:
        return package.find_blender_ext()
    except package.PackagingError as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def zips(package, blender_ext, tmp_path_factory):
    """Platform name -> BuildResult, each zip built on first use."""
    out = tmp_path_factory.mktemp("extension-zips")
    built = {}

    def get(name):
        if name not in built:
            if name == "linux-x64" and package.host_platform() != "linux-x64":
                pins = package.read_pins()
                plat = package.PLATFORMS[name]
                missing = [package.compiled_wheel_name(pins, plat, (3, int(py[3:]))) for py in PYTHONS]
                missing = [w for w in missing if not (package.WHEELS_DIR / w).is_file()]
                if missing:
                    pytest.skip(f"the compiled linux-x64 wheels are built on linux-x64 only; missing {missing}")
            built[name] = package.build(name, package.DEFAULT_PYTHONS, out, update_manifest=False,
                                        reuse_compiled=True)
            result = built[name]
            print(f"\n{result.zip_path.name}: {result.size / 1e6:.1f} MB, built in {result.seconds:.1f} s")
        return built[name]

    return get


def expected_wheels(pins, platform):
    e = EXPECTED[platform]
    mlx, own = pins.bundled["mlx"], f"{pins.own_name}-{pins.own_version}"
    names = {f"{e['library']}-{mlx}-py3-none-{e['mlx']}.whl", f"plyfile-{pins.bundled['plyfile']}-py3-none-any.whl",
             f"av-{pins.extras['av']}-cp311-abi3-{e['av']}.whl"}
    for py in PYTHONS:
        names.add(f"mlx-{mlx}-{py}-{py}-{e['mlx']}.whl")
        names.add(f"pillow-{pins.bundled['pillow']}-{py}-{py}-{e['pillow']}.whl")
        names.add(f"zstandard-{pins.bundled['zstandard']}-{py}-{py}-{e['zstandard']}.whl")
        if e["pycolmap"]:
            names.add(f"pycolmap-{pins.extras['pycolmap']}-{py}-{py}-{e['pycolmap']}.whl")
        if platform == "linux-x64":
            names.add(f"{own}-{py}-{py}-linux_x86_64.whl")
    if platform != "linux-x64":
        names.add(f"{own}-py3-none-{e['own']}.whl")
    return names


def nested_wheel(zip_path, name) -> zipfile.ZipFile:
    with zipfile.ZipFile(zip_path) as zf:
        return zipfile.ZipFile(io.BytesIO(zf.read(f"wheels/{name}")))


# ------------------------------------------------------------------ every zip
@pytest.mark.parametrize("platform", PLATFORMS)
def test_zip_validates(platform, zips, blender_ext):
    result = subprocess.run([*blender_ext, "validate", str(zips(platform).zip_path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("platform", PLATFORMS)
def test_zip_holds_its_platforms_wheels_and_names_them(platform, zips, pins):
    result = zips(platform)
    assert result.zip_path.name == f"{pins.own_name}-{pins.own_version}-{platform.replace('-', '_')}.zip"
    with zipfile.ZipFile(result.zip_path) as zf:
        names = zf.namelist()
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        licence = zf.read("LICENSE").decode()
    wheels = sorted(n.removeprefix("wheels/") for n in names if n.startswith("wheels/"))
    assert set(wheels) == expected_wheels(pins, platform)
    # The licence text the manifest names travels with the add-on.
    assert manifest["license"] == ["SPDX:MIT"] and licence.startswith("MIT License") and licence == (ROOT / "LICENSE").read_text()
    assert manifest["platforms"] == [platform]
    assert manifest["wheels"] == [f"./wheels/{w}" for w in wheels]
    assert sorted(result.wheels) == wheels
    # Nothing else but the add-on: no sources of the core, no tooling.
    assert {n.split("/", 1)[0] for n in names} == {"blender_manifest.toml", "__init__.py", "LICENSE", "addon", "wheels"}
    assert "addon/package.py" not in names and not any("__pycache__" in n for n in names)


@pytest.mark.parametrize("platform", PLATFORMS)
def test_one_mlx_and_one_of_our_wheels_per_python(platform, zips, pins):
    wheels = zips(platform).wheels
    for py in PYTHONS:
        mlx = [w for w in wheels if w.startswith("mlx-") and (f"-{py}-" in w)]
        own = [w for w in wheels if w.startswith(f"{pins.own_name}-") and (f"-{py}-" in w or "-py3-none-" in w)]
        assert len(mlx) == 1 and len(own) == 1, (py, wheels)
    e = EXPECTED[platform]
    libraries = [w for w in wheels if w.startswith(("mlx_cpu-", "mlx_metal-"))]
    assert libraries == [f"{e['library']}-{pins.bundled['mlx']}-py3-none-{e['mlx']}.whl"]


@pytest.mark.parametrize("platform", PLATFORMS)
def test_pycolmap_per_python_where_it_has_wheels(platform, zips, pins):
    """One pycolmap wheel per Python, tagged (its own WHEEL file) for the platform; none on linux-arm64."""
    result = zips(platform)
    with zipfile.ZipFile(result.zip_path) as zf:
        manifest_text = zf.read("blender_manifest.toml").decode()
    wheels = [w for w in result.wheels if w.startswith("pycolmap-")]
    tag = EXPECTED[platform]["pycolmap"]
    if tag is None:
        assert wheels == [] and "pycolmap" not in manifest_text.lower(), (wheels, manifest_text)
        return
    version = pins.extras["pycolmap"]
    assert sorted(wheels) == [f"pycolmap-{version}-{py}-{py}-{tag}.whl" for py in PYTHONS]
    assert [w for w in tomllib.loads(manifest_text)["wheels"] if "pycolmap" in w] == [f"./wheels/{w}" for w in wheels]
    for name, py in zip(sorted(wheels), PYTHONS):
        inner = nested_wheel(result.zip_path, name)
        dist_info = f"pycolmap-{version}.dist-info"
        tags = [line.removeprefix("Tag: ") for line in inner.read(f"{dist_info}/WHEEL").decode().splitlines()
                if line.startswith("Tag: ")]
        metadata = inner.read(f"{dist_info}/METADATA").decode()
        assert tags == [f"{py}-{py}-{tag}"], (name, tags)
        assert "Name: pycolmap\n" in metadata and f"Version: {version}\n" in metadata
        assert any(n.startswith("pycolmap/") for n in inner.namelist())
        # Its only dependency outside its extras is numpy, which Blender ships.
        requires = [line for line in metadata.splitlines() if line.startswith("Requires-Dist: ")]
        assert [r for r in requires if "extra ==" not in r] == ["Requires-Dist: numpy"], requires


def supported_tags(python: tuple[int, int], platforms) -> set[str]:
    """The wheel tags CPython ``python`` accepts on these platform tags, as pip computes them."""
    try:
        from packaging import tags
    except ImportError:
        from pip._vendor.packaging import tags
    return {str(tag) for tag in tags.cpython_tags(python, platforms=platforms)}


@pytest.mark.parametrize("platform", PLATFORMS)
def test_one_av_wheel_for_both_pythons(platform, zips, pins):
    """One av wheel per zip, tagged (its own WHEEL file) ``cp311-abi3`` for the platform: CPython 3.11 and 3.13
    both take it, 3.10 does not; the manifest lists it once."""
    result = zips(platform)
    with zipfile.ZipFile(result.zip_path) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    tag, version = EXPECTED[platform]["av"], pins.extras["av"]
    wheels = [w for w in result.wheels if w.startswith("av-")]
    assert wheels == [f"av-{version}-cp311-abi3-{tag}.whl"], wheels
    assert [w for w in manifest["wheels"] if "/av-" in w] == [f"./wheels/{wheels[0]}"]
    inner = nested_wheel(result.zip_path, wheels[0])
    dist_info = f"av-{version}.dist-info"
    tags = [line.removeprefix("Tag: ") for line in inner.read(f"{dist_info}/WHEEL").decode().splitlines()
            if line.startswith("Tag: ")]
    assert tags == [f"cp311-abi3-{tag}"], tags
    pip_tags = EXPECTED[platform]["pip_tags"]
    assert set(tags) <= supported_tags((3, 11), pip_tags) and set(tags) <= supported_tags((3, 13), pip_tags)
    assert not set(tags) & supported_tags((3, 10), pip_tags)
    # Its compiled modules are stable-ABI builds: none is named for one Python version.
    files = inner.namelist()
    modules = [f for f in files if f.startswith("av/") and f.endswith((".so", ".pyd"))]
    suffix = ".pyd" if platform == "windows-x64" else ".abi3.so"
    assert modules and all(f.endswith(suffix) and "cpython-" not in f for f in modules), modules
    # FFmpeg inside, no Python dependencies.
    metadata = inner.read(f"{dist_info}/METADATA").decode().splitlines()  # CRLF in the Windows wheel
    assert {"Name: av", f"Version: {version}", "Requires-Python: >=3.11"} <= set(metadata)
    assert not [line for line in metadata if line.startswith("Requires-Dist: ")]
    assert any("avcodec" in f for f in files), "no FFmpeg library in the av wheel"


def test_stable_abi_wheel_once_whatever_the_pythons(package, pins):
    """package.py's table: av's one wheel per platform for 3.11, 3.13 or both; none for a Python older than 3.11."""
    assert package.STABLE_ABI == {"av": (3, 11)}
    for pythons in (((3, 11),), ((3, 13),), ((3, 11), (3, 13))):
        for platform in PLATFORMS:
            names = [w.filename for w in package.expected_wheels(pins, [platform], pythons)]
            assert [n for n in names if n.startswith("av-")] == \
                [f"av-{pins.extras['av']}-cp311-abi3-{EXPECTED[platform]['av']}.whl"], (pythons, names)
    every = [w for w in package.expected_wheels(pins, package.PLATFORMS, package.DEFAULT_PYTHONS)
             if w.filename.startswith("av-")]
    assert len(every) == len(PLATFORMS) and all(w.python is None for w in every)
    with pytest.raises(package.PackagingError, match="av.*3.11 or newer"):
        package.expected_wheels(pins, ["linux-x64"], ((3, 10), (3, 11)))


@pytest.mark.parametrize("platform", PLATFORMS)
def test_core_only_on_linux_x64_and_raster_math_everywhere(platform, zips, pins):
    result = zips(platform)
    own = [w for w in result.wheels if w.startswith(f"{pins.own_name}-")]
    for name in own:
        files = nested_wheel(result.zip_path, name).namelist()
        core = [f for f in files if f.startswith("mlx3d/_core")]
        native = [f for f in files if f.endswith((".so", ".pyd", ".dylib", ".dll"))]
        kernels = f"mlx3d/_kernels/{EXPECTED[platform]['kernel']}"
        if platform == "linux-x64":
            py = name.split("-")[2]
            assert core == [f"mlx3d/_core.cpython-{py[2:]}-x86_64-linux-gnu.so"], (name, core)
            assert sorted(native) == sorted([*core, kernels]), (name, native)
        else:
            assert name.endswith(f"-py3-none-{EXPECTED[platform]['own']}.whl")
            assert core == [] and not any("_core" in f for f in files) and native == [kernels], (name, native)
        assert "mlx3d/render/raster_math.h" in files, name
        assert not any(f.startswith("mlx3d/csrc/") for f in files), name


# ------------------------------------------------------------------ the kernel library
# sys.platform of each Blender platform: the loader picks the file name by it.
SYS_PLATFORM = {"linux-x64": "linux", "macos-arm64": "darwin", "windows-x64": "win32", "linux-arm64": "linux"}


def binary_header(data: bytes) -> tuple[str, str]:
    """(format, machine) of a shared library, read from its header; asserts that it is a shared library."""
    if data[:4] == b"\x7fELF":
        assert data[5] == 1, "not a little-endian ELF file"
        e_type, e_machine = struct.unpack_from("<HH", data, 16)
        assert e_type == 3, f"ELF type {e_type}: not a shared object (ET_DYN)"
        return {1: "ELF32", 2: "ELF64"}[data[4]], {62: "x86-64", 183: "aarch64"}.get(e_machine, str(e_machine))
    if data[:2] == b"MZ":
        pe, = struct.unpack_from("<I", data, 0x3C)
        assert data[pe:pe + 4] == b"PE\0\0", "MZ file without a PE header"
        machine, _, _, _, _, _, characteristics = struct.unpack_from("<HHIIIHH", data, pe + 4)
        magic, = struct.unpack_from("<H", data, pe + 24)
        assert characteristics & 0x2000, "PE file without IMAGE_FILE_DLL: not a DLL"
        return {0x20B: "PE32+", 0x10B: "PE32"}[magic], {0x8664: "x86-64", 0xAA64: "arm64"}.get(machine, hex(machine))
    magic, cputype, _, filetype = struct.unpack_from("<IIII", data, 0)
    if magic == 0xFEEDFACF:  # MH_MAGIC_64
        assert filetype == 6, f"Mach-O file type {filetype}: not a dylib (MH_DYLIB)"
        return "Mach-O 64", {0x0100000C: "arm64", 0x01000007: "x86-64"}.get(cputype, hex(cputype))
    return "unknown", data[:4].hex()


def _c_string(data: bytes, offset: int) -> str:
    return data[offset:data.index(b"\0", offset)].decode()


def exported_names(data: bytes) -> set[str]:
    """The names a shared library exports, from its own tables: ELF's .dynsym (defined, global or weak, default
    visibility), PE's export directory, Mach-O's symbol table (external, defined in a section, not private)."""
    kind = binary_header(data)[0]
    names = set()
    if kind == "ELF64":
        shoff, = struct.unpack_from("<Q", data, 40)
        shentsize, shnum = struct.unpack_from("<HH", data, 58)
        # sh_name, sh_type, sh_flags, sh_addr, sh_offset, sh_size, sh_link, sh_info, sh_addralign, sh_entsize
        sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize) for i in range(shnum)]
        for _, sh_type, _, _, offset, size, link, _, _, entsize in sections:
            if sh_type == 11:  # SHT_DYNSYM
                strtab = sections[link][4]
                for i in range(size // entsize):
                    st_name, st_info, st_other, st_shndx = struct.unpack_from("<IBBH", data, offset + i * entsize)
                    if st_shndx != 0 and st_info >> 4 in (1, 2) and st_other & 3 == 0:
                        names.add(_c_string(data, strtab + st_name))
    elif kind == "PE32+":
        pe, = struct.unpack_from("<I", data, 0x3C)
        nsections, = struct.unpack_from("<H", data, pe + 6)
        optional_size, = struct.unpack_from("<H", data, pe + 20)
        export_rva, = struct.unpack_from("<I", data, pe + 24 + 112)  # data directory 0 of a PE32+ optional header
        # VirtualSize, VirtualAddress, SizeOfRawData, PointerToRawData of each section
        sections = [struct.unpack_from("<IIII", data, pe + 24 + optional_size + 40 * i + 8) for i in range(nsections)]

        def at(rva: int) -> int:
            for virtual_size, address, raw_size, raw in sections:
                if address <= rva < address + max(virtual_size, raw_size):
                    return rva - address + raw
            raise AssertionError(f"RVA {rva:#x} lies in no section")

        if export_rva:
            directory = at(export_rva)
            count, = struct.unpack_from("<I", data, directory + 24)  # NumberOfNames
            table = at(struct.unpack_from("<I", data, directory + 32)[0])  # AddressOfNames
            names |= {_c_string(data, at(struct.unpack_from("<I", data, table + 4 * i)[0])) for i in range(count)}
    elif kind == "Mach-O 64":
        ncmds, = struct.unpack_from("<I", data, 16)
        offset = 32
        for _ in range(ncmds):
            cmd, size = struct.unpack_from("<II", data, offset)
            if cmd == 0x2:  # LC_SYMTAB
                symoff, nsyms, stroff, _ = struct.unpack_from("<IIII", data, offset + 8)
                for i in range(nsyms):
                    n_strx, n_type = struct.unpack_from("<IB", data, symoff + 16 * i)
                    if n_type & 0x01 and n_type & 0x0E == 0x0E and not n_type & 0x10:  # N_EXT, N_SECT, not N_PEXT
                        names.add(_c_string(data, stroff + n_strx).removeprefix("_"))
            offset += size
    return names


def zip_kernel_library(result, pins, platform) -> bytes:
    """The kernel library our wheel(s) in a zip carry (one build for every Python), checked to be the one file of
    mlx3d/_kernels/ and listed in RECORD with its hash and size."""
    path = f"mlx3d/_kernels/{EXPECTED[platform]['kernel']}"
    dist_info = f"{pins.own_name}-{pins.own_version}.dist-info"
    found = set()
    for name in sorted(w for w in result.wheels if w.startswith(f"{pins.own_name}-")):
        inner = nested_wheel(result.zip_path, name)
        assert [f for f in inner.namelist() if f.startswith("mlx3d/_kernels/")] == [path], name
        data = inner.read(path)
        record = {row[0]: row[1:] for row in csv.reader(io.StringIO(inner.read(f"{dist_info}/RECORD").decode())) if row}
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        assert record[path] == [f"sha256={digest}", str(len(data))], (name, record.get(path))
        found.add(data)
    assert len(found) == 1, f"{platform}: the wheels carry {len(found)} different libraries"
    return found.pop()


@pytest.mark.parametrize("platform", PLATFORMS)
def test_each_zip_carries_its_platforms_kernel_library(platform, zips, pins):
    """Exactly the platform's library, at the path the loader reads there, of the platform's binary format, exporting
    the ABI function; the wheel that carries it claims that platform (no ``any``), installed into platlib."""
    from mlx3d import kernel_library

    e = EXPECTED[platform]
    assert kernel_library.LIBRARY_NAMES.get(SYS_PLATFORM[platform], "libmlx3d_kernels.so") == e["kernel"]
    result = zips(platform)
    data = zip_kernel_library(result, pins, platform)
    assert binary_header(data) == e["binary"], platform
    assert "mlx3d_kernels_abi" in exported_names(data)
    for name in (w for w in result.wheels if w.startswith(f"{pins.own_name}-")):
        wheel_meta = nested_wheel(result.zip_path, name).read(f"{pins.own_name}-{pins.own_version}.dist-info/WHEEL")
        lines = wheel_meta.decode().splitlines()
        tags = [line.removeprefix("Tag: ") for line in lines if line.startswith("Tag: ")]
        py = name.split("-")[2]
        assert tags == ([f"{py}-{py}-linux_x86_64"] if platform == "linux-x64" else [f"py3-none-{e['own']}"]), tags
        assert "Root-Is-Purelib: false" in lines, lines


def test_kernel_libraries_keep_their_wheel_tags_promise(zips, pins):
    """manylinux_2_17_aarch64: no glibc symbol newer than 2.17, and no C++ runtime of the system's;
    macosx_11_0_arm64: a minimum macOS of 11.0 or older (LC_BUILD_VERSION), and a code signature, without which
    macOS on Apple silicon refuses arm64 code (an ad hoc one will do)."""
    data = zip_kernel_library(zips("linux-arm64"), pins, "linux-arm64")
    versions = {(int(a), int(b)) for a, b in re.findall(rb"GLIBC_(\d+)\.(\d+)", data)}
    assert versions and max(versions) <= (2, 17), sorted(versions)
    assert not re.search(rb"GLIBCXX_|CXXABI_|libstdc\+\+|libc\+\+\.so", data), "the C++ runtime is not inside"
    data = zip_kernel_library(zips("macos-arm64"), pins, "macos-arm64")
    ncmds, = struct.unpack_from("<I", data, 16)
    offset, minimum, signature = 32, None, None
    for _ in range(ncmds):
        cmd, size = struct.unpack_from("<II", data, offset)
        if cmd == 0x32:  # LC_BUILD_VERSION: platform, minos (xxxx.yy.zz), sdk, ntools
            platform_id, minos = struct.unpack_from("<II", data, offset + 8)
            assert platform_id == 1, platform_id  # PLATFORM_MACOS
            minimum = (minos >> 16, (minos >> 8) & 0xFF)
        elif cmd == 0x1D:  # LC_CODE_SIGNATURE: dataoff, datasize
            start, length = struct.unpack_from("<II", data, offset + 8)
            signature = data[start:start + length]
        offset += size
    assert minimum is not None and minimum <= (11, 0), minimum
    assert signature and struct.unpack_from(">I", signature, 0)[0] == 0xFADE0CC0, "no embedded code signature"


LOAD_KERNELS = r"""
import json
import mlx.core as mx
import mlx3d
import mlx3d.kernel_library as kernels
loaded = kernels.available()
print(json.dumps({"mlx3d": mlx3d.__file__, "mlx": mx.__file__, "path": str(kernels.library_path()),
                  "available": loaded, "failure": kernels.failure(),
                  "build": kernels.build_info() if loaded else None}))
"""


def test_linux_x64_zips_wheel_loads_its_kernel_library(zips, pins, tmp_path):
    """The zip's wheels (ours for the running Python, mlx, mlx-cpu) installed into an empty folder: a Python
    with that folder on PYTHONPATH (and numpy, as in Blender), no site-packages, loads the library from it."""
    if (sys.platform, platform_module.machine()) != ("linux", "x86_64"):
        pytest.skip("the linux-x64 library runs on Linux x86-64 only")
    result = zips("linux-x64")
    py, e, mlx = "cp{}{}".format(*sys.version_info[:2]), EXPECTED["linux-x64"], pins.bundled["mlx"]
    names = [f"{pins.own_name}-{pins.own_version}-{py}-{py}-linux_x86_64.whl", f"mlx-{mlx}-{py}-{py}-{e['mlx']}.whl",
             f"{e['library']}-{mlx}-py3-none-{e['mlx']}.whl"]
    with zipfile.ZipFile(result.zip_path) as zf:
        for name in names:
            (tmp_path / name).write_bytes(zf.read(f"wheels/{name}"))
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-index", "--no-deps", "--target", str(site),
                    *(str(tmp_path / n) for n in names)], check=True, capture_output=True, text=True)
    env = {k: v for k, v in os.environ.items() if k not in ("MLX3D_KERNELS", "MLX3D_NO_CORE", "PYTHONHOME")}
    env["PYTHONPATH"] = os.pathsep.join([str(site), str(numpy_only(tmp_path))])
    # -S: no site-packages, so neither the venv's mlx nor its editable mlx3d; PYTHONPATH alone.
    run = subprocess.run([sys.executable, "-S", "-c", LOAD_KERNELS], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert report["mlx3d"].startswith(str(site)) and report["mlx"].startswith(str(site)), report
    assert report["path"] == str((site / "mlx3d" / "_kernels" / e["kernel"]).resolve()), report
    assert report["available"] is True and report["failure"] is None, report
    assert report["build"], report


def test_missing_zig_stops_the_zip_and_names_make_cross_tools(package, monkeypatch, tmp_path):
    """Without zig a cross-compiled platform's library cannot be built: the build stops before any zip is written,
    and the message says what to run."""
    def no_zig():
        raise SystemExit("zig was not found")

    monkeypatch.setattr(package.kernel_build(), "zig", no_zig)
    monkeypatch.setattr(package, "_run", lambda *args, **kwargs: pytest.fail(f"ran {args[0]}"))
    with pytest.raises(package.PackagingError, match=r"windows-x64 kernel library .* zig.*`make cross-tools`"):
        package.build_kernel_library("windows-x64", rebuild=True)
    for step in ("download_wheels", "check_mlx_requirements", "check_bundled_markers"):  # not this test's subject
        monkeypatch.setattr(package, step, lambda *args: None)
    with pytest.raises(package.PackagingError, match="make cross-tools"):
        package.build("linux-arm64", package.DEFAULT_PYTHONS, tmp_path, rebuild=True, update_manifest=False)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ the pure wheel
@pytest.fixture(scope="module")
def pure_wheel(zips, package, pins) -> Path:
    zips("windows-x64")  # builds it
    path = package.WHEELS_DIR / package.pure_wheel_name(pins)
    assert path.is_file()
    return path


def test_pure_wheel_metadata_and_record(pure_wheel, pins):
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    with zipfile.ZipFile(pure_wheel) as zf:
        dist_info = f"{pins.own_name}-{pins.own_version}.dist-info"
        wheel_meta = zf.read(f"{dist_info}/WHEEL").decode()
        metadata = zf.read(f"{dist_info}/METADATA").decode()
        entry_points = zf.read(f"{dist_info}/entry_points.txt").decode()
        record = list(csv.reader(io.StringIO(zf.read(f"{dist_info}/RECORD").decode())))
        contents = {n: zf.read(n) for n in zf.namelist()}
    assert "Root-Is-Purelib: true" in wheel_meta and "Tag: py3-none-any" in wheel_meta
    assert f"Name: {project['name']}\n" in metadata and f"Version: {project['version']}\n" in metadata
    requires = [line.removeprefix("Requires-Dist: ") for line in metadata.splitlines()
                if line.startswith("Requires-Dist: ") and "extra ==" not in line]
    assert requires == project["dependencies"]
    assert "Provides-Extra: poses\n" in metadata
    poses = [line for line in metadata.splitlines() if line.startswith("Requires-Dist: pycolmap") and "poses" in line]
    assert len(poses) == 1 and poses[0].startswith(f"Requires-Dist: pycolmap=={pins.extras['pycolmap']}; ("), poses
    assert f"Requires-Dist: av=={pins.extras['av']}; extra == \"poses\"\n" in metadata
    assert "[console_scripts]\nmlx3d = mlx3d.cli:main" in entry_points
    # RECORD lists every file once, with its hash and size.
    assert sorted(row[0] for row in record) == sorted(contents)
    for path, digest, size in record:
        if path.endswith("/RECORD"):
            continue
        data = contents[path]
        expected = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        assert digest == f"sha256={expected}" and int(size) == len(data), path
    assert contents["mlx3d/render/raster_math.h"] == HEADER.read_bytes()
    # The generic wheel (for pip, in no zip) leaves the kernel library out, as `pip install .` does.
    assert not any(n.startswith("mlx3d/_kernels/") or n.endswith((".so", ".dll", ".dylib")) for n in contents)
    exclude = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["scikit-build"]["wheel"]["exclude"]
    assert "mlx3d/_kernels/**" in exclude


def test_pure_wheel_has_the_compiled_wheels_files(pure_wheel, package, pins):
    """The pure wheel is the compiled one less ``_core`` and the kernel library: same files, same Requires-Dist."""
    host = package.host_platform()
    if host is None or not package.PLATFORMS[host].compiled:
        pytest.skip("no compiled wheel is built on this machine")
    py = (3, int(PYTHONS[0][3:]))
    compiled = package.WHEELS_DIR / package.compiled_wheel_name(pins, package.PLATFORMS[host], py)
    if not compiled.is_file() or compiled.stat().st_mtime < package._newest_source_mtime():
        pytest.skip(f"{compiled.name} is missing or older than the sources")

    def files(path):
        with zipfile.ZipFile(path) as zf:
            return {n for n in zf.namelist()
                    if ".dist-info/" not in n and not n.startswith(("mlx3d/_core", "mlx3d/_kernels/"))}

    def requires(path):  # as packaging writes them (quotes, order of specifiers)
        return sorted(str(requirement(r)) for r in package.wheel_requires_dist(path))

    requirement = package._requirement_class()
    assert files(pure_wheel) == files(compiled)
    assert requires(pure_wheel) == requires(compiled)


CLEAN_IMPORT = r"""
import importlib.util, json, sys
target, numpy_dir, header = sys.argv[1:4]
sys.path[:0] = [target]
sys.path.append(numpy_dir)
import mlx.core as mx
import mlx3d
from mlx3d import native
from mlx3d.render.raster_metal import kernel_header
print(json.dumps({
    "mlx": mx.__file__, "mlx3d": mlx3d.__file__, "core_spec": importlib.util.find_spec("mlx3d._core") is not None,
    "core_available": native.available(), "header_ok": kernel_header() == open(header, encoding="utf-8").read(),
    "sum": mx.array([1.0, 2.0, 3.0]).sum().item(),
}))
"""


def numpy_only(tmp_path) -> Path:
    """A folder with the venv's numpy alone (Blender ships it): not the venv's site-packages, which would bring
    its own mlx (and mlx3d)."""
    import numpy

    numpy_dir = tmp_path / "numpy-only"
    numpy_dir.mkdir()
    site = Path(numpy.__file__).resolve().parents[1]
    for name in ("numpy", "numpy.libs"):
        if (site / name).exists():
            (numpy_dir / name).symlink_to(site / name)
    return numpy_dir


def test_pure_wheel_installs_and_imports_in_a_clean_interpreter(pure_wheel, package, pins, zips, tmp_path):
    """pip installs the pure wheel and this machine's MLX wheels into an empty folder; mlx3d imports from there."""
    host = package.host_platform()
    if host is None:
        pytest.skip("this machine is none of the extension's platforms")
    zips(host)  # downloads this machine's MLX wheels
    py = "cp{}{}".format(*sys.version_info[:2])
    mlx_tag = EXPECTED[host]["mlx"]
    mlx = pins.bundled["mlx"]
    wheels = [pure_wheel, package.WHEELS_DIR / f"mlx-{mlx}-{py}-{py}-{mlx_tag}.whl",
              package.WHEELS_DIR / f"{EXPECTED[host]['library']}-{mlx}-py3-none-{mlx_tag}.whl"]
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-index", "--no-deps", "--target",
                    str(target), *map(str, wheels)], check=True, capture_output=True, text=True)
    assert (target / "mlx3d" / "render" / "raster_math.h").read_bytes() == HEADER.read_bytes()
    numpy_dir = numpy_only(tmp_path)
    result = subprocess.run(
        [sys.executable, "-I", "-S", "-c", CLEAN_IMPORT, str(target), str(numpy_dir), str(HEADER)],
        cwd=tmp_path, env={**os.environ, "MLX3D_NO_CORE": "1"}, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["mlx3d"].startswith(str(target)) and report["mlx"].startswith(str(target)), report
    assert report["core_spec"] is False and report["core_available"] is False
    assert report["header_ok"] is True and report["sum"] == 6.0


# ------------------------------------------------------------------ Requires-Dist per platform
PIP_WITH_MARKERS = r"""
import json, sys
from pip._vendor.packaging import markers
env = json.loads(sys.argv[1])
default_environment = markers.default_environment
markers.default_environment = lambda: {**default_environment(), **env}
from pip._internal.cli.main import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.fixture(scope="module")
def pip_resolutions(pure_wheel, package, tmp_path_factory):
    """Platform -> {name: wheel file} that ``pip install`` of the pure wheel with its ``poses`` extra picks
    there (running Python's version).

    pip evaluates environment markers for the machine it runs on, whatever
    ``--platform`` says, so each run gets the platform's markers patched in.
    The four resolutions run side by side.
    """
    tmp = tmp_path_factory.mktemp("pip-resolve")
    version = "{}.{}".format(*sys.version_info[:2])
    runs = {}
    for platform, e in EXPECTED.items():
        cmd = [sys.executable, "-c", PIP_WITH_MARKERS, json.dumps(e["markers"]), "install", "--dry-run",
               "--ignore-installed", "--quiet", "--only-binary=:all:", "--python-version", version,
               "--target", str(tmp / f"target-{platform}"), "--report", str(tmp / f"{platform}.json"),
               "--find-links", str(package.WHEELS_DIR), f"{pure_wheel}[poses]"]
        for tag in e["pip_tags"]:
            cmd += ["--platform", tag]
        runs[platform] = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    resolutions = {}
    for platform, proc in runs.items():
        output, _ = proc.communicate(timeout=600)
        assert proc.returncode == 0, f"{platform}: {output[-3000:]}"
        report = json.loads((tmp / f"{platform}.json").read_text())
        resolutions[platform] = {item["metadata"]["name"].replace("-", "_").lower():
                                 item["download_info"]["url"].rsplit("/", 1)[-1] for item in report["install"]}
    return resolutions


@pytest.mark.parametrize("platform", PLATFORMS)
def test_pip_install_of_the_pure_wheel_pulls_mlx_and_its_library(platform, pip_resolutions, pins):
    got = pip_resolutions[platform]
    e = EXPECTED[platform]
    py = "cp{}{}".format(*sys.version_info[:2])
    mlx = pins.bundled["mlx"]
    assert {n for n in got if n.startswith("mlx") and n != pins.own_name} == {"mlx", e["library"]}, got
    assert got["mlx"] == f"mlx-{mlx}-{py}-{py}-{e['mlx']}.whl"
    assert got[e["library"]] == f"{e['library']}-{mlx}-py3-none-{e['mlx']}.whl"
    assert {"numpy", "plyfile", "pillow", "zstandard", pins.own_name} <= set(got)


@pytest.mark.parametrize("platform", PLATFORMS)
def test_pip_install_of_poses_pulls_the_pycolmap_wheel_the_zip_bundles(platform, pip_resolutions, pins, zips):
    """The markers of the poses pin pick, through pip, the very wheel the zip carries (and nothing on linux-arm64)."""
    got = pip_resolutions[platform]
    py = "cp{}{}".format(*sys.version_info[:2])
    in_zip = [w for w in zips(platform).wheels if w.startswith("pycolmap-") and f"-{py}-" in w]
    if EXPECTED[platform]["pycolmap"] is None:
        assert "pycolmap" not in got and in_zip == [], (got, in_zip)
    else:
        assert [got["pycolmap"]] == in_zip, (got, in_zip)
        assert got["pycolmap"].startswith(f"pycolmap-{pins.extras['pycolmap']}-{py}-{py}-")


@pytest.mark.parametrize("platform", PLATFORMS)
def test_pip_install_of_poses_pulls_the_av_wheel_the_zip_bundles(platform, pip_resolutions, pins, zips):
    """pip picks from ``[poses]`` the very av wheel the zip carries, for the running Python (3.11 or 3.13)."""
    got = pip_resolutions[platform]
    in_zip = [w for w in zips(platform).wheels if w.startswith("av-")]
    assert [got["av"]] == in_zip, (got, in_zip)
    assert got["av"] == f"av-{pins.extras['av']}-cp311-abi3-{EXPECTED[platform]['av']}.whl"


def test_pycolmap_publishes_no_linux_arm64_wheel(pins, tmp_path):
    """Why linux-arm64's zip goes without: the registry has no pycolmap wheel for that platform."""
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version", "3.11",
           "--dest", str(tmp_path), f"pycolmap=={pins.extras['pycolmap']}"]
    for tag in EXPECTED["linux-arm64"]["pip_tags"]:
        cmd += ["--platform", tag]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode != 0 and "No matching distribution" in result.stdout + result.stderr, \
        result.stdout[-2000:] + result.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []


def test_mlx_check_follows_markers_and_mlx_metadata(package, zips, pins):
    """package.py's own check: mlx's `cpu` extra adds mlx-cpu on Linux only, so Windows needs its explicit pin."""
    for platform in ("windows-x64", "linux-arm64", "macos-arm64"):
        zips(platform)  # downloads the mlx wheels
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    mlx = pins.bundled["mlx"]
    # What `mlx[cpu]` alone pulls: nothing but mlx on Windows, whose mlx/core.pyd needs mlx-cpu's mlx.dll.
    extra_only = {"windows-x64": {"mlx"}, "linux-arm64": {"mlx", "mlx_cpu"}, "macos-arm64": {"mlx", "mlx_metal"}}
    for platform, want in extra_only.items():
        plat = package.PLATFORMS[platform]
        mlx_requires = package.wheel_requires_dist(package.WHEELS_DIR / f"mlx-{mlx}-cp311-cp311-{plat.mlx_tag}.whl")
        assert package.mlx_distributions(plat, (3, 11), project["dependencies"], mlx_requires) == \
            {"mlx", EXPECTED[platform]["library"]}
        assert package.mlx_distributions(plat, (3, 11), [f"mlx[cpu]=={mlx}"], mlx_requires) == want


def test_bundled_markers_check_follows_the_wheel_table(package, pins, monkeypatch):
    """package.py stops when pycolmap's markers and the platforms it bundles pycolmap for disagree."""
    tags = package.BINARY_WHEEL_TAGS["pycolmap"]
    for platform in PLATFORMS:
        package.check_bundled_markers(pins, package.PLATFORMS[platform], package.DEFAULT_PYTHONS)
    monkeypatch.setitem(package.BINARY_WHEEL_TAGS, "pycolmap", {**tags, "linux-arm64": "manylinux_2_28_aarch64"})
    with pytest.raises(package.PackagingError, match="linux-arm64.*does not pull pycolmap"):
        package.check_bundled_markers(pins, package.PLATFORMS["linux-arm64"], package.DEFAULT_PYTHONS)
    monkeypatch.setitem(package.BINARY_WHEEL_TAGS, "pycolmap", {k: v for k, v in tags.items() if k != "windows-x64"})
    with pytest.raises(package.PackagingError, match="windows-x64.*pulls pycolmap"):
        package.check_bundled_markers(pins, package.PLATFORMS["windows-x64"], package.DEFAULT_PYTHONS)
    # av has no markers: every platform pulls it, so every platform must bundle it.
    monkeypatch.setitem(package.BINARY_WHEEL_TAGS, "pycolmap", tags)
    av_tags = package.BINARY_WHEEL_TAGS["av"]
    monkeypatch.setitem(package.BINARY_WHEEL_TAGS, "av", {k: v for k, v in av_tags.items() if k != "linux-arm64"})
    with pytest.raises(package.PackagingError, match="linux-arm64.*pulls av"):
        package.check_bundled_markers(pins, package.PLATFORMS["linux-arm64"], package.DEFAULT_PYTHONS)


def test_poses_pins_are_optional_and_the_test_extra_has_the_same(pins):
    """pycolmap and av are no dependencies of `pip install mlx3d-splat`; ``[poses]`` and ``[test]`` pin them
    alike; mlx3d/sfm/video.py names av's pin in its message."""
    from mlx3d.sfm.video import PYAV_PIN

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    optional = project["optional-dependencies"]
    assert not {r.split("=")[0] for r in project["dependencies"]} & {"pycolmap", "av"}
    assert set(pins.extras) == {"pycolmap", "av"} and not set(pins.extras) & set(pins.bundled)
    for name in pins.extras:
        poses = [r for r in optional["poses"] if r.split("=")[0] == name]
        test = [r for r in optional["test"] if r.split("=")[0] == name]
        assert len(poses) == 1 and test == poses, (name, poses, test)
    pycolmap, av = (next(r for r in optional["poses"] if r.startswith(f"{n}==")) for n in ("pycolmap", "av"))
    assert pycolmap.startswith(f"pycolmap=={pins.extras['pycolmap']};")
    assert av == f"av=={pins.extras['av']}" == f"av=={PYAV_PIN}"  # no markers: wheels on every platform


# ------------------------------------------------------------------ CLI
def test_parse_platforms(package):
    assert package.parse_platforms("all") == PLATFORMS
    assert package.parse_platforms("windows-x64, linux-x64") == ("linux-x64", "windows-x64")
    with pytest.raises(package.PackagingError):
        package.parse_platforms("windows-arm64")


def test_manifest_lists_follow_platforms(package, pins):
    """What `make extension` writes into blender_manifest.toml: every platform, every platform's wheels."""
    assert list(package.PLATFORMS) == list(PLATFORMS)
    wheels = {w.filename for w in package.expected_wheels(pins, package.PLATFORMS, package.DEFAULT_PYTHONS)}
    assert wheels == set().union(*(expected_wheels(pins, p) for p in PLATFORMS))
