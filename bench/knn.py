"""Benchmark of mlx3d.neighbors.mean_knn_distance (k-NN over all points, self excluded).

Each case runs in a fresh subprocess so that its peak RSS is its own, once
with the compiled k-d tree (``mlx3d._core``) and once with the numpy one
(``mlx3d.kdtree``, forced by ``MLX3D_NO_CORE=1``), on the same machine in the
same run. Prints a table with the wall time of one
``mean_knn_distance(points, k)`` call per tree (tree build included), their
ratio, the compiled tree's time as a fraction of the 20 s target for 1M
points, each process's peak RSS, and whether both trees gave bit-identical
results.

    python bench/knn.py                 # 10k, 100k, 1M random and clustered + garden scene
    python bench/knn.py --quick         # 10k and 100k only
    python bench/knn.py --markdown bench/out/knn.md
"""

from __future__ import annotations

import argparse
import hashlib
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
TREES = ("native", "pure")


# --------------------------------------------------------------------------- #
# child: one case
# --------------------------------------------------------------------------- #
def _load(source: str, n: int):
    import numpy as np

    if source == "garden":
        return np.ascontiguousarray(np.load(GARDEN)["means3d"], dtype=np.float32)
    rng = np.random.default_rng(0)
    if source == "clustered":
        # 200 blobs whose spreads differ by 1000x, in a 100-unit box
        centres = 100 * rng.random((200, 3))
        spread = 10.0 ** rng.uniform(-3, 0, 200)
        blob = rng.integers(0, 200, n)
        return (centres[blob] + spread[blob, None] * rng.standard_normal((n, 3))).astype(np.float32)
    return rng.random((n, 3), dtype=np.float32)


def run_case(source: str, n: int, k: int, threads: int, tree: str) -> dict:
    from mlx3d import native, neighbors

    if tree == "native":
        native.core()  # import (and, for editable installs, rebuild) outside the timing
    elif native.available():
        raise RuntimeError("the pure case must run with MLX3D_NO_CORE=1")
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
        "tree": tree,
        "threads": threads if threads > 0 else os.cpu_count(),
        "wall_s": wall,
        "rss_before_mib": rss_before / 1024,
        "peak_rss_mib": peak / 1024,
        "checksum": float(d.astype("float64").sum()),
        "digest": hashlib.sha256(d.tobytes()).hexdigest(),
    }


# --------------------------------------------------------------------------- #
# parent: table
# --------------------------------------------------------------------------- #
def _spawn(source: str, n: int, k: int, threads: int, tree: str) -> dict:
    cmd = [sys.executable, __file__, "--child", source, str(n), str(k), str(threads), tree]
    env = dict(os.environ)
    env.pop("MLX3D_NO_CORE", None)
    if tree == "pure":
        env["MLX3D_NO_CORE"] = "1"
    out = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"case {source} n={n} threads={threads} tree={tree} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _table(pairs: list[tuple[dict, dict]]) -> list[str]:
    """One line per case: (native row, pure row)."""
    head = ["points", "N", "k", "threads", "native [s]", "pure [s]", "pure / native",
            "native / 20 s target", "peak RSS native [MiB]", "peak RSS pure [MiB]", "same results"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---:" for _ in head) + "|"]
    for nat, pure in pairs:
        cells = [
            nat["source"],
            f"{nat['n']:,}",
            str(nat["k"]),
            str(nat["threads"]),
            f"{nat['wall_s']:.2f}",
            f"{pure['wall_s']:.2f}",
            f"{pure['wall_s'] / nat['wall_s']:.1f}",
            f"{nat['wall_s'] / TARGET_S:.3f}",
            f"{nat['peak_rss_mib']:.0f}",
            f"{pure['peak_rss_mib']:.0f}",
            "yes" if nat["digest"] == pure["digest"] else "NO",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only (10k, 100k)")
    ap.add_argument("--k", type=int, default=25)
    ap.add_argument("--markdown", metavar="PATH", help="also write the table as markdown")
    ap.add_argument("--child", nargs=5, metavar=("SOURCE", "N", "K", "THREADS", "TREE"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        source, n, k, threads, tree = args.child
        print(json.dumps(run_case(source, int(n), int(k), int(threads), tree)))
        return 0

    sizes = [10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000]
    cases = [(source, n) for source in ("random", "clustered") for n in sizes]
    if not args.quick:
        if GARDEN.exists():
            cases.append(("garden", 0))
        else:
            print(f"note: {GARDEN} not found, garden case skipped", file=sys.stderr)
    pairs = []
    for source, n in cases:
        for threads in (1, 0):
            pair = tuple(_spawn(source, n, args.k, threads, tree) for tree in TREES)
            pairs.append(pair)
            print(f"  {source:9s} N={pair[0]['n']:>9,} threads={pair[0]['threads']}: "
                  + ", ".join(f"{r['tree']} {r['wall_s']:.2f} s (peak RSS {r['peak_rss_mib']:.0f} MiB)"
                              for r in pair),
                  file=sys.stderr)

    cpu = platform.processor() or platform.machine()
    header = (f"mean_knn_distance, k={args.k}, all points as queries (self excluded); "
              f"{os.cpu_count()} CPUs ({cpu}), Python {platform.python_version()}; "
              f"threads 0 = all; wall time includes the tree build; native = mlx3d._core's "
              f"k-d tree, pure = mlx3d.kdtree (numpy, MLX3D_NO_CORE=1); same results = "
              f"bit-identical output.")
    emit(header + "\n\n" + "\n".join(_table(pairs)) + "\n", args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
