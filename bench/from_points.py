"""Benchmark ``GaussianModel.from_points``: wall time and peak memory.

Cases: the 138,766 real SfM points of ``shared/data/test_garden.npz`` and
uniform random clouds (100k, 1M). Each case runs in a fresh subprocess so the
peak resident memory (VmHWM) belongs to that case alone; the baseline row
"numpy points only" is the same process holding just the input points.

    python bench/from_points.py [--quick] [--markdown PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

from common import emit, peak_rss_mb  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
GARDEN = os.path.join(HERE, "..", "..", "shared", "data", "test_garden.npz")


def _child(case: str, n: int, max_ref: int) -> None:
    import numpy as np

    if case == "garden":
        data = np.load(GARDEN)
        points, colors = data["means3d"], data["colors"]
    else:
        rng = np.random.default_rng(0)
        points = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    import mlx.core as mx

    from mlx3d.splatting import GaussianModel

    base = peak_rss_mb()
    t0 = time.perf_counter()
    model = GaussianModel.from_points(points, colors, scale_init_max_ref=max_ref)
    mx.eval(*model.params.values())
    seconds = time.perf_counter() - t0
    print(json.dumps({"n": len(points), "seconds": seconds, "peak_mb": peak_rss_mb(), "base_mb": base}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="skip the 1M case")
    parser.add_argument("--markdown", metavar="PATH", help="also write the table as markdown")
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], int(args.child[1]), int(args.child[2]))
        return

    cases = [("garden", 0), ("random", 100_000)] + ([] if args.quick else [("random", 1_000_000)])
    rows = []
    for case, n in cases:
        if case == "garden" and not os.path.exists(GARDEN):
            print(f"skipping garden: {GARDEN} not found", file=sys.stderr)
            continue
        for max_ref in (10_000, 100_000):
            out = subprocess.run([sys.executable, __file__, "--child", case, str(n), str(max_ref)], capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append((case, r["n"], max_ref, r["seconds"], r["peak_mb"], r["peak_mb"] - r["base_mb"]))
            print(f"{case:7s} n={r['n']:>9,} max_ref={max_ref:>7,}  {r['seconds']:6.2f} s  peak {r['peak_mb']:7.0f} MB", file=sys.stderr)

    header = "| points | N | reference points | time (s) | peak RSS (MB) | added by from_points (MB) |\n|---|---:|---:|---:|---:|---:|\n"
    body = "".join(f"| {c} | {n:,} | {ref:,} | {s:.2f} | {p:.0f} | {d:.0f} |\n" for c, n, ref, s, p, d in rows)
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    table = f"`GaussianModel.from_points` ({machine})\n\n" + header + body
    emit(table, args.markdown)


if __name__ == "__main__":
    main()
