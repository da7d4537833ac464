"""Build the kernel library (and its test driver) for one of the platforms Blender ships on.

    python mlx3d/csrc/kernels/build.py PLATFORM [--out DIR] [--driver] [--cxx COMPILER]

PLATFORM is a Blender platform name: ``linux-x64`` (the host's C++ compiler,
``$CXX`` or g++, as mlx3d._core), ``windows-x64``, ``linux-arm64`` or
``macos-arm64`` (cross-compiled with zig, PyPI's ``ziglang``, the version pinned
in the Makefile: clang with each platform's C library and a static libc++, so the
Windows DLL needs only KERNEL32 and the Universal C runtime, the Linux arm64
library glibc 2.17, the macOS library macOS 11). The library goes to
``DIR/NAME`` (default ``build/kernels/PLATFORM/``), NAME as
``mlx3d.kernel_library.LIBRARY_NAMES``; with ``--driver`` also the test driver
(``driver.c``, ``kernel_driver`` or ``kernel_driver.exe``). Only the functions of
``mlx3d_kernels.h`` are exported (hidden visibility; on Linux also the version
script ``exports.map``), and the Linux x86-64 build carries its C++ runtime.

Every file gets the flags mlx3d._core's build gives the kernels
(CMakeLists.txt): ``-O3 -ffp-contract=off -fno-math-errno`` (no FMA
contraction: results do not depend on the instruction set, so builds for
different CPUs agree to the bit where their libm agrees).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
#: Every .cpp file in this folder is part of the library.
SOURCES = sorted(p.name for p in HERE.glob("*.cpp"))
#: With GCC, per file: the rasterizer's tile kernels are scheduled before register allocation too, which
#: interleaves their independent exp chains (the same arithmetic in another order; as CMakeLists.txt).
GCC_FLAGS = {"raster.cpp": ["-fschedule-insns", "-fsched-pressure"]}
FLAGS = ["-std=c++17", "-O3", "-ffp-contract=off", "-fno-math-errno", "-fvisibility=hidden", "-Wall", "-Wno-psabi"]
#: zig target triples; None: the host compiler.
TARGETS = {"linux-x64": None, "windows-x64": "x86_64-windows-gnu", "linux-arm64": "aarch64-linux-gnu.2.17",
           "macos-arm64": "aarch64-macos.11.0"}
LIBRARY = {"windows-x64": "mlx3d_kernels.dll", "macos-arm64": "libmlx3d_kernels.dylib"}
DRIVER = {"windows-x64": "kernel_driver.exe"}


def library_name(platform: str) -> str:
    return LIBRARY.get(platform, "libmlx3d_kernels.so")


def driver_name(platform: str) -> str:
    return DRIVER.get(platform, "kernel_driver")


def zig() -> list[str]:
    """The zig command: PyPI's ziglang in this interpreter, or zig on PATH."""
    if importlib.util.find_spec("ziglang") is not None:
        return [sys.executable, "-m", "ziglang"]
    if shutil.which("zig"):
        return [shutil.which("zig")]
    raise SystemExit("zig was not found: pip install ziglang (the Makefile's ZIGLANG pin), or put zig on PATH")


def compilers(platform: str, cxx: str | None) -> tuple[list[str], list[str]]:
    """(C++ command, C command) for ``platform``."""
    target = TARGETS[platform]
    if target is None:
        cxx = cxx or os.environ.get("CXX") or "g++"
        cc = "clang" if "clang" in Path(cxx).name else "gcc"
        return [cxx], [os.environ.get("CC") or cc]
    return [*zig(), "c++", "-target", target], [*zig(), "cc", "-target", target]


def build(platform: str, out: Path, driver: bool = False, cxx: str | None = None) -> Path:
    """Compile and link the library for ``platform`` into ``out``; returns its path."""
    if platform not in TARGETS:
        raise SystemExit(f"unknown platform {platform!r}; use one of {', '.join(TARGETS)}")
    out.mkdir(parents=True, exist_ok=True)
    cxx_cmd, cc_cmd = compilers(platform, cxx)
    lib = out / library_name(platform)
    link = ["-shared", "-s"]
    if platform == "macos-arm64":
        link += [f"-Wl,-install_name,@rpath/{lib.name}"]
    elif platform != "windows-x64":  # Linux: the API alone (std:: templates would otherwise be exported too)
        link += ["-pthread", f"-Wl,--version-script={HERE / 'exports.map'}"]
    if platform == "linux-x64":  # the C++ runtime inside: the library needs only glibc, whatever the host ships
        link += ["-static-libstdc++", "-static-libgcc", "-Wl,--exclude-libs,ALL"]  # and none of its symbols exported
    gcc = TARGETS[platform] is None and "clang" not in Path(cxx_cmd[0]).name
    pic = [] if platform == "windows-x64" else ["-fPIC"]
    with tempfile.TemporaryDirectory(prefix="mlx3d-kernels-") as tmp:
        objects = []
        for source in SOURCES:  # one by one, for per-file flags (zig caches each object by its inputs)
            objects.append(str(Path(tmp) / (source + ".o")))
            extra = GCC_FLAGS.get(source, []) if gcc else []
            subprocess.run([*cxx_cmd, *FLAGS, *extra, *pic, "-c", str(HERE / source), "-o", objects[-1]], check=True)
        subprocess.run([*cxx_cmd, *link, *objects, "-o", str(lib)], check=True)
    if driver:
        exe = out / driver_name(platform)
        libs = [] if platform in ("windows-x64", "macos-arm64") else ["-ldl"]
        subprocess.run([*cc_cmd, "-std=c11", "-O2", "-Wall", str(HERE / "driver.c"), "-o", str(exe), *libs], check=True)
    return lib


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("platform", choices=list(TARGETS))
    parser.add_argument("--out", type=Path, default=None, help="output folder (default build/kernels/PLATFORM)")
    parser.add_argument("--driver", action="store_true", help="also build the test driver")
    parser.add_argument("--cxx", default=None, help="linux-x64: the C++ compiler (default $CXX or g++)")
    args = parser.parse_args()
    lib = build(args.platform, args.out or ROOT / "build" / "kernels" / args.platform, args.driver, args.cxx)
    print(lib)
    return 0


if __name__ == "__main__":
    sys.exit(main())
