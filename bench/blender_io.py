"""Benchmark importing and exporting splats in Blender (the ``bpy`` module).

1M splats at SH degree 3 by default. Import is split into file read, object
creation (mesh with positions converted to a point cloud) and attribute
transfer; export (with a non-uniform, rotated object transform baked in) into
attribute read, transform and file write. Targets: import <= 3 s, export <= 3 s.

    python bench/blender_io.py [--n 1000000] [--markdown PATH]

Runs the add-on from this checkout (not an installed extension).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time

import numpy as np

from common import emit  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--markdown", metavar="PATH")
    args = parser.parse_args()

    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp())
    import bpy

    sys.path.insert(0, os.path.dirname(HERE))  # the add-on package from this checkout
    from addon import splat_object, workflows
    from mlx3d.io import SplatArrays, read_splat_ply, write_splat_ply
    from mlx3d.splatting import transform_splats

    rng = np.random.default_rng(0)
    n = args.n
    arrays = SplatArrays(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        scales=rng.normal(-4, 0.5, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.normal(size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 1, 3)).astype(np.float32),
        sh_rest=rng.normal(0, 0.1, (n, 15, 3)).astype(np.float32),
    )
    tmp = tempfile.mkdtemp()
    src, dst = os.path.join(tmp, "in.ply"), os.path.join(tmp, "out.ply")
    write_splat_ply(src, arrays)
    bpy.ops.wm.read_homefile(use_empty=True)

    t0 = time.perf_counter()
    loaded = read_splat_ply(src)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    obj, _ = workflows.import_splat_file(src)
    t_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    splat_object.write_attributes(obj.data, loaded)  # the attribute transfer alone, measured again
    t_attrs = time.perf_counter() - t0
    t_create = t_import - t_read - t_attrs

    obj.location, obj.rotation_euler, obj.scale = (1, 2, 3), (0.3, 0.2, 0.1), (1.0, 2.0, 0.5)
    bpy.context.view_layer.update()
    t0 = time.perf_counter()
    workflows.export_splat_file(dst, [obj])
    t_export = time.perf_counter() - t0
    t0 = time.perf_counter()
    raw, _ = splat_object.read_splats(obj)
    t_get = time.perf_counter() - t0
    t0 = time.perf_counter()
    baked = transform_splats(raw, np.array(obj.matrix_world))
    t_transform = time.perf_counter() - t0
    t0 = time.perf_counter()
    write_splat_ply(dst, baked)
    t_write = time.perf_counter() - t0

    rows = [
        ("import total", t_import, 3.0),
        ("  file read", t_read, None),
        ("  object creation", t_create, None),
        ("  attribute transfer", t_attrs, None),
        ("export total (transform baked)", t_export, 3.0),
        ("  attribute read", t_get, None),
        ("  transform (non-uniform scale)", t_transform, None),
        ("  file write", t_write, None),
    ]
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Blender {bpy.app.version_string} (bpy module)"
    table = f"Blender import/export, {n:,} splats, SH degree 3 ({machine})\n\n| step | time (s) | target (s) |\n|---|---:|---:|\n"
    table += "".join(f"| {name} | {t:.2f} | {'' if target is None else f'{target:.0f}'} |\n" for name, t, target in rows)
    emit(table, args.markdown)


if __name__ == "__main__":
    main()
