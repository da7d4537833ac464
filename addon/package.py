"""Build the Blender extension zip of mlx3d (``make extension``).

    .venv/bin/python addon/package.py [--platform linux-x64] [--python 3.11,3.13] [--out dist]

Steps, each printed as it runs:

1. Read the pins: this project's wheel name and version from ``pyproject.toml``
   (``[project]``), and the exact pins of the bundled dependencies from its
   ``[project].dependencies`` (``mlx==…``, ``plyfile==…``). numpy is not bundled:
   Blender ships it. The ``wheels = [...]`` list of ``blender_manifest.toml``
   is generated from these pins (every platform, Python 3.11 and 3.13) and
   rewritten when it differs, so versions live in one place.
2. Download the third-party wheels with ``pip download --only-binary=:all:
   --no-deps --python-version 3.X --platform TAG`` into ``wheels/``: ``mlx`` (one
   wheel per Python), its library wheel (``mlx-cpu`` on Linux, ``mlx-metal`` on
   macOS) and ``plyfile``. Files already there are reused.
3. Build this project's wheel ``mlx3d_splat`` (``mlx3d`` and the compiled
   ``mlx3d._core``) once per Python: with the running interpreter when it has
   the build requirements (the project's ``.venv``), otherwise in a build venv
   ``build/extension/venv-cp3XY`` made from ``python3.X`` (on PATH or from
   pyenv) with ``[build-system].requires`` installed. CMake build directories
   are kept under ``build/extension/`` so rebuilds are incremental; a wheel
   newer than every source file is reused (``--rebuild`` forces a build).
   Each wheel is then imported next to the bundled MLX in a clean interpreter
   (``python -I -S``): ``mlx3d._core`` must load and accept an ``mx.array``.
4. Check that every wheel the manifest lists for the platform exists.
5. Stage the extension (manifest narrowed to the platform and Pythons, root
   ``__init__.py``, ``addon/`` without this script, the wheels) under
   ``build/extension/stage-PLATFORM`` and run Blender's
   ``blender_ext.py build --split-platforms`` (from the ``bpy`` package, or
   ``--blender-ext PATH``), then ``blender_ext.py validate`` on the zip.
6. Print the zip path, its size and the wheels inside.

Blender 4.5 LTS and 5.0 embed Python 3.11, Blender 5.1+ Python 3.13, hence the
default ``--python 3.11,3.13``. MLX publishes one wheel per Python version, so
the extension ships one ``mlx`` and one ``mlx3d_splat`` wheel per version;
Blender installs the matching ones into
``<user resources>/extensions/.local/lib/python3.X/site-packages``, where
``mlx3d/_core`` finds ``libmlx`` through its rpath ``$ORIGIN/../mlx/lib``.
(A stable-ABI ``abi3`` build of ``_core`` is not used: nanobind keeps
stable-ABI modules in a type registry of their own, so such a ``_core`` cannot
take the ``mx.array`` objects of ``mlx.core``, which is not a stable-ABI build.)

Linux x86-64 (``linux-x64``): MLX's wheels are tagged ``manylinux_2_35_x86_64``
(glibc 2.35+); ours is tagged ``linux_x86_64``, which Blender maps to
``linux-x64`` like any ``manylinux_*_x86_64`` tag. It needs Python 3.11 (the
venv) and Python 3.13 (``python3.13`` on PATH, or ``pyenv install 3.13``) with
development headers, a C++20 compiler and CMake >= 3.24.

macOS on Apple silicon (``macos-arm64``): run the same command on a Mac with
the project's venv (``make extension``): it downloads the ``mlx==…`` and
``mlx-metal==…`` wheels tagged ``macosx_14_0_arm64`` (there is no ``mlx-cpu``
on macOS; ``mlx-metal`` carries ``libmlx.dylib`` and the Metal kernels), builds
our wheel with ``MACOSX_DEPLOYMENT_TARGET=14.0`` for Python 3.11 and 3.13
(``python3.13`` from python.org, Homebrew or pyenv) and writes
``dist/mlx3d_splat-VERSION-macos_arm64.zip``. Xcode's command line tools and
CMake are needed. A zip for a platform other than the machine's is built only
when that platform's ``mlx3d_splat`` wheels are already in ``wheels/`` (for
example copied from a Mac); otherwise the script names the missing files.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import importlib.util
import os
import platform as _platform
import re
import shutil
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

#: Bundled compiled dependencies (one wheel per Python and platform): the platform
#: part of their wheel file names as published for the pinned version, per Blender
#: platform. ``pip download --platform`` gets the last tag of a compound one.
BINARY_WHEEL_TAGS = {
    "pillow": {"linux-x64": "manylinux_2_27_x86_64.manylinux_2_28_x86_64", "macos-arm64": "macosx_11_0_arm64"},
}

#: Sources of our wheel: a wheel older than any of these is rebuilt.
SOURCE_INPUTS = ("pyproject.toml", "CMakeLists.txt", "mlx3d")


class PackagingError(RuntimeError):
    """A step failed; the message says which and what to do."""


@dataclasses.dataclass(frozen=True)
class Platform:
    name: str  # Blender's platform name (manifest ``platforms``)
    mlx_tag: str  # platform tag of MLX's wheels (``pip download --platform``)
    own_tag: str  # platform tag of our wheel as built on that platform
    mlx_library: str  # the wheel that carries libmlx
    host: tuple[str, str]  # (platform.system(), platform.machine()) of a build machine
    build_env: tuple[tuple[str, str], ...] = ()


PLATFORMS = {
    "linux-x64": Platform(
        name="linux-x64",
        mlx_tag="manylinux_2_35_x86_64",
        own_tag="linux_x86_64",
        mlx_library="mlx-cpu",
        host=("Linux", "x86_64"),
    ),
    "macos-arm64": Platform(
        name="macos-arm64",
        mlx_tag="macosx_14_0_arm64",
        own_tag="macosx_14_0_arm64",
        mlx_library="mlx-metal",
        host=("Darwin", "arm64"),
        build_env=(("MACOSX_DEPLOYMENT_TARGET", "14.0"),),
    ),
}


@dataclasses.dataclass(frozen=True)
class Pins:
    own_name: str  # distribution name of this project, normalised for wheel file names
    own_version: str
    bundled: dict  # normalised distribution name -> exact version
    build_requires: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class Wheel:
    filename: str
    requirement: str | None  # what ``pip download`` fetches; None for our own wheel
    python: tuple[int, int] | None  # the Python it is for; None when any
    platform: str | None  # Blender platform; None when any
    pip_platform: str | None = None  # ``pip download --platform`` tag; None when any


@dataclasses.dataclass
class BuildResult:
    platform: str
    zip_path: Path
    size: int
    wheels: list[str]


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
    bundled: dict[str, str] = {}
    for requirement in project.get("dependencies", []):
        match = _REQ.match(requirement)
        if not match:
            raise PackagingError(f"{pyproject.name}: cannot read dependency {requirement!r}")
        name, version = _normalise(match.group(1)), match.group(2)
        if name in PROVIDED_BY_BLENDER:
            continue
        if name != "mlx" and name not in PURE_PYTHON and name not in BINARY_WHEEL_TAGS:
            raise PackagingError(
                f"{pyproject.name}: dependency {requirement!r} is neither bundled nor provided by Blender; "
                "add it to PURE_PYTHON, BINARY_WHEEL_TAGS or PROVIDED_BY_BLENDER in addon/package.py"
            )
        if not version:
            raise PackagingError(f"{pyproject.name}: bundled dependency {requirement!r} must be pinned with ==")
        if bundled.setdefault(name, version) != version:
            raise PackagingError(f"{pyproject.name}: {name} is pinned to both {bundled[name]} and {version}")
    if "mlx" not in bundled:
        raise PackagingError(f"{pyproject.name}: no mlx==VERSION pin in [project].dependencies")
    return Pins(
        own_name=_normalise(project["name"]),
        own_version=project["version"],
        bundled=bundled,
        build_requires=tuple(data["build-system"]["requires"]),
    )


def expected_wheels(pins: Pins, platforms, pythons) -> list[Wheel]:
    """Every wheel the extension bundles for these platforms and Pythons (sorted, no duplicates)."""
    mlx = pins.bundled["mlx"]
    wheels: dict[str, Wheel] = {}

    def add(wheel: Wheel) -> None:
        wheels.setdefault(wheel.filename, wheel)

    for plat_name in platforms:
        plat = PLATFORMS[plat_name]
        for python in pythons:
            tag = _py_tag(python)
            add(Wheel(f"mlx-{mlx}-{tag}-{tag}-{plat.mlx_tag}.whl", f"mlx=={mlx}", python, plat.name, plat.mlx_tag))
            add(Wheel(f"{pins.own_name}-{pins.own_version}-{tag}-{tag}-{plat.own_tag}.whl", None, python, plat.name))
            for name in sorted(BINARY_WHEEL_TAGS.keys() & pins.bundled.keys()):
                version, wheel_tag = pins.bundled[name], BINARY_WHEEL_TAGS[name][plat.name]
                add(Wheel(f"{name}-{version}-{tag}-{tag}-{wheel_tag}.whl", f"{name}=={version}", python, plat.name, wheel_tag.split(".")[-1]))
        add(Wheel(f"{_normalise(plat.mlx_library)}-{mlx}-py3-none-{plat.mlx_tag}.whl",
                  f"{plat.mlx_library}=={mlx}", None, plat.name, plat.mlx_tag))
    for name in sorted(PURE_PYTHON & pins.bundled.keys()):
        version = pins.bundled[name]
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
    """Make the manifest's ``wheels`` list the full list derived from the pins.

    Returns True when the manifest already matched. With ``write`` a stale list is
    rewritten (and False returned); without, a stale list raises PackagingError.
    """
    text = MANIFEST.read_text()
    want = manifest_wheel_paths(expected_wheels(pins, PLATFORMS, DEFAULT_PYTHONS))
    have = tomllib.loads(text).get("wheels")
    if have == want:
        return True
    if not write:
        raise PackagingError(
            f"{MANIFEST.name}: the wheels list does not match the pins in pyproject.toml; "
            "run `make extension` (addon/package.py rewrites it)"
        )
    new_text = replace_toml_list(text, "wheels", want, source=MANIFEST.name)
    if tomllib.loads(new_text).get("wheels") != want:
        raise PackagingError(f"{MANIFEST.name}: rewriting the wheels list failed")
    MANIFEST.write_text(new_text)
    log(f"updated the wheels list of {MANIFEST.name} ({len(want)} wheels)")
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
                        "if the package now publishes other platform tags, update PLATFORMS in addon/package.py"
                    )
                os.replace(Path(tmp) / w.filename, WHEELS_DIR / w.filename)
                log(f"  got  {w.filename} ({_mb(WHEELS_DIR / w.filename)})")


def _valid_zip(path: Path) -> bool:
    return path.is_file() and zipfile.is_zipfile(path)


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


def _newest_source_mtime() -> float:
    newest = 0.0
    for name in SOURCE_INPUTS:
        path = ROOT / name
        files = [path] if path.is_file() else [
            p for p in path.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.suffix not in {".pyc", ".so", ".dylib"}
        ]
        for p in files:
            newest = max(newest, p.stat().st_mtime)
    return newest


def build_own_wheel(pins: Pins, plat: Platform, python: tuple[int, int], *, rebuild: bool) -> Path:
    filename = f"{pins.own_name}-{pins.own_version}-{_py_tag(python)}-{_py_tag(python)}-{plat.own_tag}.whl"
    target = WHEELS_DIR / filename
    if not rebuild and _valid_zip(target) and target.stat().st_mtime >= _newest_source_mtime():
        log(f"  have {filename} (newer than the sources)")
        return target
    exe = build_interpreter(pins, python)
    out = WORK_DIR / f"out-{_py_tag(python)}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    build_dir = WORK_DIR / f"cmake-{_py_tag(python)}-{plat.own_tag}"
    env = {**os.environ, **dict(plat.build_env)}
    log(f"  building {filename} with {exe}")
    start = time.perf_counter()
    _run([exe, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
          "--config-settings", f"build-dir={build_dir}", "--wheel-dir", out, ROOT],
         what=f"building the {_py_tag(python)} wheel", env=env, cwd=ROOT, capture=True)
    built = sorted(out.glob("*.whl"))
    if [p.name for p in built] != [filename]:
        raise PackagingError(f"building the {_py_tag(python)} wheel gave {[p.name for p in built]}, not {filename}")
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


def check_own_wheel(wheel: Path, exe: str) -> None:
    """Import ``mlx3d._core`` from the wheel next to the build interpreter's MLX, in ``python -I -S``."""
    site_dir = _run([exe, "-c", "import sysconfig; print(sysconfig.get_paths()['platlib'])"],
                    what="locating site-packages", capture=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="mlx3d-wheel-check-") as tmp:
        with zipfile.ZipFile(wheel) as zf:
            zf.extractall(tmp)
        result = subprocess.run([exe, "-I", "-S", "-c", _CHECK, tmp, site_dir], cwd=tmp,
                                capture_output=True, text=True)
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
    log(f"  checked {wheel.name}: mlx3d._core loads with MLX and takes mx.array")


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
    """A source tree with only what the zip holds, and a manifest for this platform."""
    stage_dir = WORK_DIR / f"stage-{platform_name}"
    shutil.rmtree(stage_dir, ignore_errors=True)
    (stage_dir / "wheels").mkdir(parents=True)
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
          rebuild: bool = False, update_manifest: bool = True, blender_ext: str | None = None) -> BuildResult:
    """Builds the extension zip for one platform; returns its path, size and wheels."""
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
    log(f"  {pins.own_name} {pins.own_version}; bundled: "
        + ", ".join(f"{k}=={v}" for k, v in sorted(pins.bundled.items())) + f", {plat.mlx_library}=={pins.bundled['mlx']}")
    if sync_manifest(pins, write=update_manifest):
        log(f"  {MANIFEST.name} wheels list is up to date")
    wheels = expected_wheels(pins, [platform_name], pythons)

    log("2/6 third-party wheels")
    download_wheels(wheels, pythons)

    log("3/6 mlx3d_splat wheels")
    if platform_name == host:
        for python in pythons:
            build_own_wheel(pins, plat, python, rebuild=rebuild)
    else:
        log(f"  this machine is not {platform_name}: using the mlx3d_splat wheels already in wheels/")

    log("4/6 checking the wheels the manifest lists")
    missing = [w.filename for w in wheels if not _valid_zip(WHEELS_DIR / w.filename)]
    if missing:
        hint = "" if platform_name == host else f" (build them with `make extension` on a {platform_name} machine)"
        raise PackagingError(f"missing from {WHEELS_DIR.relative_to(ROOT)}/: {', '.join(missing)}{hint}")
    log(f"  all {len(wheels)} present")

    log("5/6 blender_ext.py build")
    cli = find_blender_ext(blender_ext)
    stage_dir = stage(platform_name, wheels)
    out_dir.mkdir(parents=True, exist_ok=True)
    _run([*cli, "build", "--source-dir", stage_dir, "--output-dir", out_dir, "--split-platforms"],
         what="blender_ext.py build", capture=True)
    manifest = tomllib.loads((stage_dir / MANIFEST.name).read_text())
    zip_path = out_dir / f"{manifest['id']}-{manifest['version']}-{platform_name.replace('-', '_')}.zip"
    if not zip_path.is_file():
        raise PackagingError(f"blender_ext.py build did not write {zip_path}")
    _run([*cli, "validate", zip_path], what="blender_ext.py validate", capture=True)

    with zipfile.ZipFile(zip_path) as zf:
        inside = sorted(n.split("/", 1)[1] for n in zf.namelist() if n.startswith("wheels/") and n.endswith(".whl"))
    if inside != sorted(w.filename for w in wheels):
        raise PackagingError(f"{zip_path.name} holds wheels {inside}, expected {[w.filename for w in wheels]}")
    result = BuildResult(platform_name, zip_path, zip_path.stat().st_size, inside)
    log(f"6/6 {zip_path} ({_mb(zip_path)}, validated, {time.perf_counter() - start:.1f} s)")
    for name in inside:
        log(f"  wheels/{name} ({_mb(WHEELS_DIR / name)})")
    return result


def _mb(path: Path) -> str:
    return f"{path.stat().st_size / 1e6:.2f} MB"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="addon/package.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--platform", choices=sorted(PLATFORMS), default=None,
                        help="Blender platform to package (default: this machine's)")
    parser.add_argument("--python", default=",".join(map(_fmt_py, DEFAULT_PYTHONS)),
                        help="Python versions to ship wheels for (default: %(default)s)")
    parser.add_argument("--out", default=str(DEFAULT_OUT), help="output directory (default: dist/)")
    parser.add_argument("--rebuild", action="store_true", help="rebuild the mlx3d_splat wheels even when up to date")
    parser.add_argument("--blender-ext", default=None, help="path of Blender's blender_ext.py")
    args = parser.parse_args(argv)
    try:
        pythons = parse_pythons(args.python)
        if args.platform is None and host_platform() is None:
            raise PackagingError(
                f"this machine ({_platform.system()} {_platform.machine()}) builds no supported platform; "
                f"pass --platform with wheels already in wheels/"
            )
        build(args.platform, pythons, args.out, rebuild=args.rebuild, blender_ext=args.blender_ext)
    except PackagingError as exc:
        print(f"addon/package.py: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("addon/package.py: cancelled", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
