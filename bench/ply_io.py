"""Benchmark 3DGS PLY reading and writing against plyfile/numpy baselines.

Generates random splats (SH degree 3: 62 float32 properties per splat) in a
temporary directory and reports the best of ``--repeat`` runs, all in one
process:

- read baselines: plyfile's own reading materialised into memory
  (``np.array(PlyData.read(path)['vertex'].data)``; plyfile memory-maps, so
  the copy is what actually reads the bytes) and ``np.fromfile`` of the body;
- ``read_splat_ply``;
- write baseline: ``PlyData([PlyElement.describe(arr, 'vertex')]).write(path)``
  of the same structured array.  Before each timed write (untimed) the
  previous output is removed and ``os.sync()`` is called, so every write
  creates a new file on a quiet disk;
- ``write_splat_ply`` (atomic, with ``fsync`` as by default, and without);
- ``GaussianModel.load_ply`` / ``save_ply`` when ``mlx3d.splatting`` is
  importable.

Ratios are ours / baseline (target <= 1.5).  Usage::

    python bench/ply_io.py [--n 1000000] [--repeat 3] [--markdown out.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import numpy as np
import plyfile


from mlx3d.io import read_splat_ply, write_splat_ply


def property_names(sh_degree: int = 3) -> list[str]:
    k1 = (sh_degree + 1) ** 2 - 1
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * k1)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def make_splats(n: int, seed: int = 0) -> np.ndarray:
    names = property_names(3)
    rng = np.random.default_rng(seed)
    arr = np.empty(n, dtype=[(nm, "<f4") for nm in names])
    arr.view("<f4").reshape(n, len(names))[...] = rng.standard_normal(
        (n, len(names)), dtype=np.float32)
    return arr


def best_of(fn, repeat: int, setup=None) -> float:
    """Best wall time of ``repeat`` calls of ``fn``; ``setup()`` runs untimed before each."""
    best = float("inf")
    for _ in range(repeat):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def header_bytes(path: str) -> int:
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    return head.index(b"end_header\n") + len(b"end_header\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1_000_000, help="number of splats (default 1,000,000)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per measurement; the best is kept")
    ap.add_argument("--markdown", metavar="PATH", help="also write the table to PATH (Markdown)")
    ap.add_argument("--dir", help="directory for the temporary files (default: system temp)")
    args = ap.parse_args(argv)

    n, rep = args.n, args.repeat
    arr = make_splats(n)
    rows: list[tuple[str, float | None, str, float | None]] = []

    with tempfile.TemporaryDirectory(dir=args.dir, prefix="ply_io_bench_") as tmp:
        src = os.path.join(tmp, "src.ply")
        base_out = os.path.join(tmp, "baseline_out.ply")
        ours_out = os.path.join(tmp, "ours_out.ply")
        plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(src)
        size_mb = os.path.getsize(src) / 1e6
        hdr = header_bytes(src)

        # Warm the page cache and check correctness once.
        splats = read_splat_ply(src)
        assert np.array_equal(splats.means[:, 0].view(np.uint32), arr["x"].view(np.uint32))
        assert np.array_equal(splats.sh_rest[:, 2, 1].view(np.uint32), arr["f_rest_17"].view(np.uint32))

        t_base_ply = best_of(lambda: np.array(plyfile.PlyData.read(src)["vertex"].data), rep)
        t_base_raw = best_of(lambda: np.fromfile(src, dtype=arr.dtype, offset=hdr), rep)
        t_read = best_of(lambda: read_splat_ply(src), rep)
        rows.append(("baseline read: plyfile + np.array", t_base_ply, "", None))
        rows.append(("baseline read: np.fromfile of the body", t_base_raw, "", None))
        rows.append(("read_splat_ply", t_read, "vs plyfile", t_read / t_base_ply))
        rows.append(("read_splat_ply", t_read, "vs np.fromfile", t_read / t_base_raw))

        def base_write():
            plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(base_out)

        def fresh(*paths):
            # Untimed: every write goes to a new file (so no run pays for
            # discarding the previous one) with no dirty data pending.
            def setup():
                for p in paths:
                    if os.path.exists(p):
                        os.remove(p)
                if hasattr(os, "sync"):
                    os.sync()
            return setup

        t_base_w = best_of(base_write, rep, fresh(base_out))
        t_write = best_of(lambda: write_splat_ply(ours_out, splats), rep, fresh(ours_out))
        t_write_nosync = best_of(lambda: write_splat_ply(ours_out, splats, fsync=False), rep,
                                 fresh(ours_out))
        with open(base_out, "rb") as a, open(ours_out, "rb") as b:
            identical = a.read() == b.read()
        rows.append(("baseline write: plyfile PlyData.write", t_base_w, "", None))
        rows.append(("write_splat_ply (atomic + fsync)", t_write, "vs plyfile", t_write / t_base_w))
        rows.append(("write_splat_ply (atomic, fsync=False)", t_write_nosync, "vs plyfile",
                     t_write_nosync / t_base_w))

        try:
            from mlx3d.splatting import GaussianModel

            load, _ = GaussianModel.load_ply, GaussianModel.save_ply
        except (ImportError, AttributeError) as exc:
            rows.append((f"GaussianModel.load_ply/save_ply: not available ({type(exc).__name__})",
                         None, "", None))
        else:
            try:
                model = load(src)
                t_load = best_of(lambda: load(src), rep)
                t_save = best_of(lambda: model.save_ply(ours_out), rep, fresh(ours_out))
                rows.append(("GaussianModel.load_ply", t_load, "vs plyfile", t_load / t_base_ply))
                rows.append(("GaussianModel.save_ply", t_save, "vs plyfile", t_save / t_base_w))
            except Exception as exc:  # the model is optional here: report, don't fail
                rows.append((f"GaussianModel.load_ply/save_ply: failed ({type(exc).__name__}: {exc})",
                             None, "", None))

    title = (f"PLY I/O, {n:,} splats, SH degree 3, {size_mb:.1f} MB; best of {rep}; "
             f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPUs, "
             f"numpy {np.__version__}")
    lines = [title, "", "| operation | time (ms) | ratio | ours / baseline |",
             "|---|---:|---|---:|"]
    for name, t, what, ratio in rows:
        lines.append(f"| {name} | {'' if t is None else f'{t * 1e3:.1f}'} | {what} | "
                     f"{'' if ratio is None else f'{ratio:.2f}'} |")
    lines.append("")
    lines.append(f"written file byte-identical to plyfile's: {'yes' if identical else 'no'}; "
                 "target: ratio <= 1.5")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
