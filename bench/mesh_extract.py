"""Benchmark of mlx3d.meshing.reconstruct_surface (Poisson reconstruction + marching tetrahedra).

Input: N random samples on the unit sphere with outward normals and equal
areas. Each resolution runs in a fresh subprocess so that its peak RSS is its
own. Prints the wall time of one ``reconstruct_surface`` call, split into its
stages, the mesh size, its area error and the peak RSS.

    python bench/mesh_extract.py                       # 200k samples at 64, 128, 256
    python bench/mesh_extract.py --n 50000 --res 64 128
    python bench/mesh_extract.py --markdown bench/out/mesh_extract.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

from common import emit, rss_kib  # bench/ is on sys.path when run as a script


def run_case(n: int, resolution: int) -> dict:
    import mlx.core as mx
    import numpy as np

    from mlx3d import native
    from mlx3d.meshing import reconstruct_surface
    from mlx3d.meshing.poisson import STAGES

    native.core()
    mx.eval(mx.fft.rfft(mx.zeros(8), stream=mx.cpu))  # load MLX outside the timing
    rng = np.random.default_rng(0)
    v = rng.standard_normal((n, 3))
    points = v / np.linalg.norm(v, axis=1, keepdims=True)
    weights = np.full(n, 4.0 * np.pi / n)
    rss_before, _ = rss_kib()
    stamps = []
    t0 = time.perf_counter()
    mesh = reconstruct_surface(
        points, points, weights, resolution=resolution,
        progress=lambda done, total: stamps.append(time.perf_counter()),
    )
    wall = time.perf_counter() - t0
    _, peak = rss_kib()
    stages = {name: stamps[i + 1] - stamps[i] for i, name in enumerate(STAGES)}
    return {
        "n": n,
        "resolution": resolution,
        "wall_s": wall,
        "stages_s": stages,
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "watertight": mesh.is_watertight(),
        "area_error": mesh.area() / (4.0 * np.pi) - 1.0,
        "rss_before_mib": rss_before / 1024,
        "peak_rss_mib": peak / 1024,
    }


def _spawn(n: int, resolution: int) -> dict:
    cmd = [sys.executable, __file__, "--child", str(n), str(resolution)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"case n={n} resolution={resolution} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _table(rows: list[dict]) -> list[str]:
    stage_names = list(rows[0]["stages_s"]) if rows else []
    head = (["N", "resolution", "wall [s]"] + [f"{s} [s]" for s in stage_names]
            + ["vertices", "faces", "watertight", "area error", "RSS before [MiB]", "peak RSS [MiB]"])
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---:" for _ in head) + "|"]
    for r in rows:
        cells = ([f"{r['n']:,}", str(r["resolution"]), f"{r['wall_s']:.2f}"]
                 + [f"{r['stages_s'][s]:.2f}" for s in stage_names]
                 + [f"{r['vertices']:,}", f"{r['faces']:,}", "yes" if r["watertight"] else "no",
                    f"{100 * r['area_error']:+.2f}%", f"{r['rss_before_mib']:.0f}",
                    f"{r['peak_rss_mib']:.0f}"])
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200_000, help="samples on the sphere")
    ap.add_argument("--res", type=int, nargs="+", default=[64, 128, 256], help="grid resolutions")
    ap.add_argument("--markdown", metavar="PATH", help="also write the table as markdown")
    ap.add_argument("--child", nargs=2, metavar=("N", "RES"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        print(json.dumps(run_case(int(args.child[0]), int(args.child[1]))))
        return 0

    rows = []
    for res in args.res:
        row = _spawn(args.n, res)
        rows.append(row)
        print(f"  N={row['n']:,} resolution={res}: {row['wall_s']:.2f} s, "
              f"peak RSS {row['peak_rss_mib']:.0f} MiB", file=sys.stderr)

    cpu = platform.processor() or platform.machine()
    header = (f"reconstruct_surface on N random unit-sphere samples (outward normals, equal "
              f"areas, default trim, no colours); {os.cpu_count()} CPUs ({cpu}), Python "
              f"{platform.python_version()}; RSS before = after imports and input generation.")
    emit(header + "\n\n" + "\n".join(_table(rows)) + "\n", args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
