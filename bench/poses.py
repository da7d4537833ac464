"""Cameras solved from photos (``mlx3d poses``): how many register, how close to the truth, how long.

    .venv/bin/python bench/poses.py [--lund ../shared/data/real/lund] [--markdown docs/benchmarks/poses.md]

Cases:

- ``lund``: a real handheld street walk (29 photos, 1024x768, OpenSfM's example data, BSD-2). No true
  cameras come with it: registered photos and the reprojection error are what can be measured.
- ``orbit-60``: 60 photos at 480x480 rendered with our renderer on two rings around the test scene
  (``tests/photo_capture.py``), solved and aligned to the true cameras by a similarity: the largest
  rotation error and the largest position error (% of the orbit's diameter).
- ``orbit-50``: the same at 50 photos, for the time a capture of that size takes.

Each case runs ``mlx3d.sfm.solve_poses`` with its defaults in this process.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from common import LoadSampler, emit, machine_line  # noqa: E402  bench/ is on sys.path when run as a script
from photo_capture import photo_orbit, similarity_errors  # noqa: E402

LUND = os.path.join(HERE, "..", "..", "shared", "data", "real", "lund")


def solve(name: str, photos: str, work: str, truth=None) -> dict:
    from mlx3d.datasets import load_dataset
    from mlx3d.sfm import solve_poses

    out = os.path.join(work, name)
    start = time.perf_counter()
    result = solve_poses(photos, out)
    seconds = time.perf_counter() - start
    row = {"case": name, "photos": result.photos, "registered": len(result.registered),
           "error_px": result.reprojection_error, "points": result.points, "matching": result.matching,
           "camera": f"{result.camera_model} f={result.focal:.0f}", "seconds": seconds, "stages": result.seconds}
    if truth is not None:
        by_name = {f.name: f.camera for f in load_dataset(out).frames}
        names = [f"{i:03d}.png" for i in range(len(truth))]
        placed = [i for i, n in enumerate(names) if n in by_name]
        rotation, position = similarity_errors([by_name[names[i]] for i in placed], [truth[i] for i in placed])
        row.update(rotation_deg=rotation, position_pct=100 * position)
    print(f"{name}: {result.summary()} in {seconds:.1f} s", file=sys.stderr, flush=True)
    return row


def table(rows: list) -> str:
    lines = ["| case | photos | registered | reprojection error | points | matching | camera | max rotation error | "
             "max position error | features | matching | mapping | total |",
             "|---|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        s = r["stages"]
        rot = f"{r['rotation_deg']:.3f}°" if "rotation_deg" in r else "(no truth)"
        pos = f"{r['position_pct']:.3f}% of the diameter" if "position_pct" in r else "(no truth)"
        lines.append(f"| {r['case']} | {r['photos']} | {r['registered']} | {r['error_px']:.2f} px | {r['points']:,} | "
                     f"{r['matching']} | {r['camera']} | {rot} | {pos} | {s['features']:.1f} s | {s['matching']:.1f} s | "
                     f"{s['mapping']:.1f} s | {r['seconds']:.1f} s |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lund", default=LUND, metavar="DIR", help="the lund photos (default: shared/data/real/lund)")
    parser.add_argument("--cases", default="lund,orbit-60,orbit-50", help="comma-separated cases (default all)")
    parser.add_argument("--markdown", metavar="PATH", help="also write the page here")
    args = parser.parse_args(argv)
    cases = args.cases.split(",")
    load = LoadSampler()
    load.start()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-poses-") as work:
        if "lund" in cases:
            rows.append(solve("lund", args.lund, work))
        for count in (60, 50):
            if f"orbit-{count}" in cases:
                photos = os.path.join(work, f"photos-{count}")
                truth = photo_orbit(photos, count, 480)
                rows.append(solve(f"orbit-{count}", photos, work, truth))
                shutil.rmtree(photos)
    load.stop.set()
    load.join()
    samples = load.samples or [float("nan")]
    page = (f"# Cameras from photos\n\n{machine_line(f', {datetime.date.today().isoformat()}')}\n\n"
            f"1-minute load average during the run: median {sorted(samples)[len(samples) // 2]:.1f}, range "
            f"{min(samples):.1f}-{max(samples):.1f} on {os.cpu_count()} cores\n\n"
            "`mlx3d poses` with its defaults (`python bench/poses.py`): SIFT on photos scaled to at most 1600 pixels, "
            "exhaustive matching (fewer than 100 photos), COLMAP's incremental mapper through pycolmap 4.2.1, on the "
            "CPU. Errors against the truth after a similarity alignment of the camera centres.\n\n" + table(rows))
    emit(page, args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
