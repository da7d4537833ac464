"""What depth fusion costs at each resolution: time, peak memory and accuracy on an analytic sphere.

    python bench/fusion_cost.py [--resolutions 128,256,512] [--views 60] [--markdown PATH]

A unit sphere, ray-traced from ``--views`` cameras all round it (the depth
maps are exact, so only the fusion is measured; ``tests/test_fusion.py``'s
oracle), each view ``1.25 x resolution`` pixels wide so a pixel is about a
voxel at the sphere, is fused by ``mlx3d.meshing.fuse_depth_maps`` at each
resolution, each in its own process (its peak resident memory is the
process's, Python and MLX included, next to what it held before fusing).
The table gives the fusion time, the peak memory, the mesh's faces and its
distance to the true sphere (mean and largest ``| |v| - 1 |``, in voxels).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))

from common import LoadSampler, machine_line, peak_rss_mb  # noqa: E402  (bench/ is on sys.path when run as a script)


def _child(resolution: int, views: int) -> dict:
    import numpy as np

    from mlx3d.meshing import fuse_depth_maps
    from mlx3d.meshing.fusion import fusion_grid
    from test_fusion import ring_cameras, sphere_view

    width = int(1.25 * resolution)
    cameras = ring_cameras(views, (-65, 65), size=(width, width * 3 // 4))
    depth = [sphere_view(c) for c in cameras]
    grid = fusion_grid(depth, resolution)
    before = peak_rss_mb()
    t0 = time.perf_counter()
    mesh = fuse_depth_maps(depth, resolution=resolution)
    seconds = time.perf_counter() - t0
    error = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1.0) / grid.voxel
    return {"resolution": resolution, "views": views, "image": f"{width}x{width * 3 // 4}", "seconds": seconds,
            "peak_mb": peak_rss_mb(), "peak_before_mb": before, "faces": int(len(mesh.faces)),
            "error_mean_voxels": float(error.mean()),
            "error_max_voxels": float(error.max()), "watertight": bool(mesh.is_watertight())}


def table(rows) -> str:
    out = ["| resolution | views | image | fusion (s) | peak memory (MB) | memory before fusing (MB) | faces | "
           "mean error (voxels) | max error (voxels) | watertight |",
           "|---:|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        out.append(f"| {r['resolution']}³ | {r['views']} | {r['image']} | {r['seconds']:.1f} | {r['peak_mb']:.0f} | "
                   f"{r['peak_before_mb']:.0f} | {r['faces']:,} | {r['error_mean_voxels']:.3f} | {r['error_max_voxels']:.2f} | "
                   f"{'yes' if r['watertight'] else 'no'} |")
    return "\n".join(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", default="128,256,512")
    parser.add_argument("--views", type=int, default=60)
    parser.add_argument("--markdown", default=None, metavar="PATH", help="also write the table as markdown")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_child(args.child, args.views)))
        return 0
    load = LoadSampler()
    load.start()
    rows = []
    for resolution in (int(s) for s in args.resolutions.split(",") if s.strip()):
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", str(resolution), "--views", str(args.views)],
                              stdout=subprocess.PIPE, text=True)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
        if proc.returncode != 0 or not lines:
            print(f"resolution {resolution}: failed (exit code {proc.returncode})", file=sys.stderr)
            return 1
        rows.append(json.loads(lines[-1]))
        print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    load.stop.set()
    load.join()
    text = table(rows)
    head = (f"{machine_line()}, {datetime.date.today().isoformat()}; 1-minute load average during the run: "
            f"median {load.summary().get('median', float('nan')):.1f} on {os.cpu_count()} cores.")
    print(head + "\n\n" + text)
    if args.markdown:
        with open(args.markdown, "w", encoding="utf-8") as f:
            f.write(head + "\n\n" + text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
