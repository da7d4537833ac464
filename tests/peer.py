"""The peer tool of the file-format tests: ``@playcanvas/splat-transform``.

``make test`` installs the pinned version into ``.tools/`` (``make peer-tools``);
``MLX3D_SPLAT_TRANSFORM=/path/to/splat-transform`` points at another install.
Tests take the ``splat_transform`` fixture (conftest), which skips with the
reason where node or the tool is missing.

Conventions of the tool that the tests rely on (read in its source):
it stores every format in the PLY axes (no conversion for SPZ, whose
specification says RUB; see :mod:`mlx3d.io.spz`), and its ``.ply`` output is
a plain 3DGS PLY with ``f_rest`` channel-major, as ours.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VERSION = "3.7.0"  # the Makefile's SPLAT_TRANSFORM_VERSION


def find_splat_transform() -> tuple[str | None, str]:
    """``(path, "")`` of a runnable splat-transform, or ``(None, reason)``."""
    if shutil.which("node") is None:
        return None, "node is not installed (splat-transform runs on node)"
    env = os.environ.get("MLX3D_SPLAT_TRANSFORM")
    path = env or str(REPO / ".tools" / "node_modules" / ".bin" / "splat-transform")
    if not os.access(path, os.X_OK):
        return None, (f"splat-transform not found at {path}; "
                      f"`make peer-tools` installs @playcanvas/splat-transform@{VERSION}")
    return path, ""


class SplatTransform:
    """Runs the splat-transform command line."""

    def __init__(self, path: str):
        self.path = path

    def run(self, *args: str, timeout: float = 600) -> str:
        """Run ``splat-transform -w ARGS``; return stdout, raise with stderr on failure."""
        proc = subprocess.run(
            [self.path, "-w", "--no-tty", *map(str, args)], capture_output=True, text=True, timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(
                f"splat-transform {' '.join(map(str, args))} failed ({proc.returncode}):\n"
                f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
        return proc.stdout

    def convert(self, src, dst, *actions: str) -> Path:
        """Convert ``src`` to ``dst`` (format from the extension) with optional actions."""
        self.run(str(src), str(dst), *actions)
        return Path(dst)
