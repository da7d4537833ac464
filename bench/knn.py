"""Benchmark of mlx3d.neighbors.mean_knn_distance (k-NN over all points, self excluded).

Each case runs in a fresh subprocess so that its peak RSS is its own. Prints a
table with the wall time of one ``mean_knn_distance(points, k)`` call (tree
build included), the peak RSS of the process, and the time as a fraction of
the 20 s target for 1M points.

    python bench/knn.py                 # 100k, 1M random + garden scene
    python bench/knn.py --quick         # small sizes only
    python bench/knn.py --markdown bench/out/knn.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from common import emit, rss_kib  # bench/ is on sys.path when run as a script

TARGET_S = 20.0
GARDEN = Path("/work/shared/data/test_garden.npz")


# --------------------------------------------------------------------------- #
# child: one case
# --------------------------------------------------------------------------- #
def _load(source: str, n: int):
    import numpy as np

    if source == "garden":
        return np.ascontiguousarray(np.load(GARDEN)["means3d"], dtype=np.float32)
    rng = np.random.default_rng(0)
    return rng.random((n, 3), dtype=np.float32)


def run_case(source: str, n: int, k: int, threads: int) -> dict:
    from mlx3d import native, neighbors

    native.core()  # import (and, for editable installs, rebuild) outside the timing
    points = _load(source, n)
    rss_before, _ = rss_kib()
    t0 = time.perf_counter()
    d = neighbors.mean_knn_distance(points, k, num_threads=threads)
    wall = time.perf_counter() - t0
    _, peak = rss_kib()
    return {
        "source": source,
        "n": int(points.shape[0]),
        "k": k,
        "threads": threads if threads > 0 else native.core().hardware_threads(),
        "wall_s": wall,
        "rss_before_mib": rss_before / 1024,
        "peak_rss_mib": peak / 1024,
        "checksum": float(d.astype("float64").sum()),
    }


# --------------------------------------------------------------------------- #
# parent: table
# --------------------------------------------------------------------------- #
def _spawn(source: str, n: int, k: int, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--child", source, str(n), str(k), str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"case {source} n={n} threads={threads} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _table(rows: list[dict]) -> list[str]:
    head = ["points", "N", "k", "threads", "wall [s]", "/ 20 s target", "RSS before [MiB]",
            "peak RSS [MiB]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---:" for _ in head) + "|"]
    for r in rows:
        cells = [
            r["source"],
            f"{r['n']:,}",
            str(r["k"]),
            str(r["threads"]),
            f"{r['wall_s']:.2f}",
            f"{r['wall_s'] / TARGET_S:.3f}",
            f"{r['rss_before_mib']:.0f}",
            f"{r['peak_rss_mib']:.0f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only (10k, 100k)")
    ap.add_argument("--k", type=int, default=25)
    ap.add_argument("--markdown", metavar="PATH", help="also write the table as markdown")
    ap.add_argument("--child", nargs=4, metavar=("SOURCE", "N", "K", "THREADS"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        source, n, k, threads = args.child
        print(json.dumps(run_case(source, int(n), int(k), int(threads))))
        return 0

    sizes = [10_000, 100_000] if args.quick else [100_000, 1_000_000]
    cases = [("random", n) for n in sizes]
    if not args.quick:
        if GARDEN.exists():
            cases.append(("garden", 0))
        else:
            print(f"note: {GARDEN} not found, garden case skipped", file=sys.stderr)
    rows = []
    for source, n in cases:
        for threads in (1, 0):
            row = _spawn(source, n, args.k, threads)
            rows.append(row)
            print(f"  {source:7s} N={row['n']:>9,} threads={row['threads']}: "
                  f"{row['wall_s']:.2f} s, peak RSS {row['peak_rss_mib']:.0f} MiB",
                  file=sys.stderr)

    cpu = platform.processor() or platform.machine()
    header = (f"mean_knn_distance, k={args.k}, all points as queries (self excluded); "
              f"{os.cpu_count()} CPUs ({cpu}), Python {platform.python_version()}; "
              f"threads 0 = all; wall time includes the tree build.")
    emit(header + "\n\n" + "\n".join(_table(rows)) + "\n", args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
