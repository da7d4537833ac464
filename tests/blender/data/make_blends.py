"""Writes the .blend fixtures of ``test_splat_layout.py``: ``splats.ply`` imported by the add-on and
saved by one Blender version, so the tests can open it in the others.

Run with the ``bpy`` of the version to save (from the repository root)::

    .venv-blender45/bin/python tests/blender/data/make_blends.py   # splats_4_5.blend
    .venv-blender53/bin/python tests/blender/data/make_blends.py   # splats_5_3.blend

``splats.ply`` itself (40 splats, SH degree 3, logits up to ±20, unnormalised quaternions,
an int and a float extra property) is written first if it is missing.
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))

from mlx3d.io import SplatArrays, write_splat_ply  # noqa: E402


def write_source(path: Path) -> None:
    rng = np.random.default_rng(32)
    n = 40
    arrays = SplatArrays(
        means=rng.normal(0, 0.5, (n, 3)).astype(np.float32),
        scales=rng.uniform(-4.5, -1.5, (n, 3)).astype(np.float32),
        quats=(rng.normal(size=(n, 4)) * rng.uniform(0.2, 3.0, (n, 1))).astype(np.float32),
        opacities=rng.uniform(-20, 20, n).astype(np.float32),
        sh_dc=rng.normal(0, 1, (n, 1, 3)).astype(np.float32),
        sh_rest=rng.normal(0, 0.2, (n, 15, 3)).astype(np.float32),
        extra={"segment": rng.integers(0, 9, n).astype(np.int32), "confidence": rng.uniform(size=n).astype(np.float32)},
    )
    write_splat_ply(path, arrays)


def main() -> None:
    import bpy

    import addon

    source = HERE / "splats.ply"
    if not source.exists():
        write_source(source)
    addon.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    obj, _ = addon.workflows.import_splat_file(source)
    obj.location = (0.25, -0.5, 1.0)
    out = HERE / f"splats_{bpy.app.version[0]}_{bpy.app.version[1]}.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(out), compress=True)
    print(f"wrote {out.name} ({out.stat().st_size:,} bytes) with Blender {bpy.app.version_string}")


if __name__ == "__main__":
    main()
