"""Splat file formats: size, write and read time, and what the quantisation costs in the picture.

For each format ``mlx3d.io.write_splats`` writes, on a real scene (default:
``../shared/data/opensplat_trained.ply``, 31,995 splats, SH degree 3):

- **size** of the file and its ratio to the PLY;
- **write / read**: best of ``--repeat`` runs of ``write_splats`` / ``read_splats`` (seconds);
- **PSNR**: the decoded splats rendered from ``--views`` cameras on an arc above the
  scene against the PLY's own render with the same renderer (mean and worst view, dB;
  ``inf`` is bit-identical);
- the same for ``@playcanvas/splat-transform`` (``tests/peer.py`` finds it): its file
  size, its decoded splats (its own conversion back to PLY) and its wall times with
  node's start-up taken out (``X -> null`` minus ``small.ply -> null``; writing is
  ``PLY -> X`` minus ``PLY -> null``).

The OpenSplat file was trained with a compositing-order bug of that program, so its
renders look wrong in every correct renderer; here only the difference between two
renders of the same renderer counts. Usage::

    python bench/formats.py [--ply PATH] [--views 4] [--size 256] [--repeat 3] [--markdown PATH] [--png PATH]
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

from common import emit, machine_line  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
DEFAULT_PLY = os.path.join(HERE, "..", "..", "shared", "data", "opensplat_trained.ply")
EXTENSIONS = (".ply", ".compressed.ply", ".spz", ".sog", ".splat", ".ksplat", ".glb")


def best_of(fn, repeat: int) -> float:
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def cameras(splats, views: int, size: int):
    """``views`` cameras above the splats' median on an arc of 60 degrees, looking at it.

    The default scene was captured from one side (+z of its median, y down), so the
    arc is on that side; cameras elsewhere would sit inside its backdrop splats.
    """
    from mlx3d.cameras import Camera

    centre = np.median(splats.means, axis=0).astype(np.float64)
    spread = np.percentile(np.linalg.norm(splats.means - centre, axis=1), 90)
    out = []
    for i in range(views):
        a = math.pi / 2 + math.radians(60) * (i / max(views - 1, 1) - 0.5)
        eye = centre + spread * np.array([0.9 * math.cos(a), -1.3, 0.9 * math.sin(a)])
        out.append(Camera.look_at(eye=eye, at=centre, up=(0, -1, 0), width=size, height=size, fov=60.0))
    return out


def renders(splats, cams) -> list[np.ndarray]:
    from mlx3d.splatting import GaussianModel

    model = GaussianModel.from_arrays(splats)
    return [np.clip(np.array(model.render(c, background=(0.0, 0.0, 0.0))["image"]), 0, 1) for c in cams]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(1.0 / mse) if mse > 0 else math.inf


def peer_seconds(peer, *args) -> float:
    t = time.perf_counter()
    peer.run(*args)
    return time.perf_counter() - t


def main() -> None:
    from mlx3d.io import format_for_path, read_splat_ply, read_splats, write_splats
    from peer import SplatTransform, find_splat_transform

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ply", default=DEFAULT_PLY)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--png", metavar="PATH", help="write the worst view of each format beside the PLY's")
    args = parser.parse_args()

    src = read_splat_ply(args.ply)
    src.extra.clear()
    cams = cameras(src, args.views, args.size)
    reference = renders(src, cams)
    peer_path, reason = find_splat_transform()
    peer = SplatTransform(peer_path) if peer_path else None
    tmp = tempfile.mkdtemp()
    ply = os.path.join(tmp, "scene.ply")
    write_splats(ply, src, fsync=False)
    ply_bytes = os.path.getsize(ply)
    if peer:
        small = os.path.join(tmp, "small.ply")
        write_splats(small, read_splat_ply(os.path.join(HERE, "..", "tests", "data", "formats", "opensplat_500.ply")), fsync=False)
        startup = min(peer_seconds(peer, small, "null") for _ in range(2))
        peer_ply_read = min(peer_seconds(peer, ply, "null") for _ in range(2))

    rows, pictures = [], []
    for ext in EXTENSIONS:
        fmt = format_for_path("x" + ext)
        path = os.path.join(tmp, "ours" + ext)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            write = best_of(lambda: write_splats(path, src, fsync=False), args.repeat)
        read = best_of(lambda: read_splats(path), args.repeat)
        decoded = read_splats(path)
        scores = [psnr(a, b) for a, b in zip(renders(decoded, cams), reference)]
        worst = int(np.argmin(scores))
        pictures.append((ext, renders(decoded, cams[worst:worst + 1])[0], reference[worst]))
        row = [fmt.description + f" (`{ext}`)", f"{os.path.getsize(path) / 1e6:.2f}", f"{os.path.getsize(path) / ply_bytes:.3f}",
               f"{write:.3f}", f"{read:.3f}", f"{np.mean(scores):.2f}", f"{min(scores):.2f}"]
        if peer is None:
            row += ["-"] * 5
        elif ext == ".sog":
            row += ["GPU only"] + ["-"] * 4  # its k-means on the CPU ran over 5 min on this scene
        else:
            out = os.path.join(tmp, "peer" + ext)
            try:
                p_write = peer_seconds(peer, ply, out) - peer_ply_read
            except RuntimeError:
                row += ["does not write"] + ["-"] * 4
                rows.append(row)
                continue
            try:
                p_read = peer_seconds(peer, out, "null") - startup
                back = os.path.join(tmp, "peer_back.ply")
                peer.run(out, back)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    decoded_by_peer = read_splat_ply(back, nonfinite="keep")
                # The peer decodes alpha 0 and 1 to -inf/+inf logits: the same alphas as +-20.
                decoded_by_peer.opacities = np.clip(decoded_by_peer.opacities, -20.0, 20.0)
                p_scores = [psnr(a, b) for a, b in zip(renders(decoded_by_peer, cams), reference)]
                row += [f"{os.path.getsize(out) / 1e6:.2f}", f"{max(p_write, 0):.3f}", f"{max(p_read, 0):.3f}",
                        f"{np.mean(p_scores):.2f}", f"{min(p_scores):.2f}"]
            except RuntimeError:  # the peer writes the format but does not read it (.glb)
                row += [f"{os.path.getsize(out) / 1e6:.2f}", f"{max(p_write, 0):.3f}", "does not read", "-", "-"]
        rows.append(row)
        print(" | ".join(row), file=sys.stderr, flush=True)

    header = ["format", "MB", "/ PLY", "write s", "read s", "PSNR mean", "PSNR worst",
              "peer MB", "peer write s", "peer read s", "peer PSNR mean", "peer PSNR worst"]
    lines = ["# Splat file formats: size, speed and picture", "", "`python bench/formats.py --markdown docs/benchmarks/formats.md "
             "--png docs/benchmarks/formats.png`; the worst view of each format against the PLY's: ![](formats.png)", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]
    note = (f"\n{src.count:,} splats (SH degree {src.sh_degree}) of `{os.path.basename(args.ply)}`, {args.views} views "
            f"{args.size}x{args.size}, best of {args.repeat}; PSNR against the PLY's render (ours, same renderer). "
            + (f"Peer: splat-transform, node start-up {startup:.2f} s taken out." if peer else f"Peer not run: {reason}.")
            + f"\n\nMachine: {machine_line()}; load {os.getloadavg()[0]:.1f}; {time.strftime('%Y-%m-%d')}.\n")
    emit("\n".join(lines) + "\n" + note, args.markdown)
    if args.png:
        from PIL import Image

        strip = np.concatenate([np.concatenate([ref, img], axis=0) for _, img, ref in pictures], axis=1)
        Image.fromarray((strip * 255 + 0.5).astype(np.uint8)).save(args.png)
        print(f"worst views (top: PLY, bottom: decoded; {', '.join(e for e, _, _ in pictures)}) in {args.png}")
    subprocess.run(["rm", "-rf", tmp], check=False)


if __name__ == "__main__":
    main()
