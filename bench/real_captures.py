"""Train and evaluate on the realistic captures (cameras from our own SfM): held-out PSNR, worst view, time.

    .venv/bin/python bench/real_captures.py [--data bench_data/captures] [--scenes arc,lund,...]
                                            [--methods vanilla,mcmc,vanilla+grid] [--steps 3000,7000] [--factor 1]
                                            [--out bench/out/real_captures] [--markdown docs/benchmarks/real_captures.md]

The datasets are the ones ``bench/captures.py`` writes (``DATA/NAME/data``:
photos solved by ``mlx3d.sfm.solve_poses``; ``lund`` by ``mlx3d poses``).
Each scene x method trains in its own process, one at a time, as ``mlx3d
train DATA --eval`` does (``load_dataset`` with ``--factor``, every 8th photo
in name order held out, ``initial_state`` from the solved sparse points, the
command's defaults: black background, ``auto`` behind opaque photos). The
step counts are milestones of ONE run: with ``--steps 3000,7000`` the run has
a 7,000-step schedule and is evaluated after 3,000 steps and again after
7,000 (training continues in the same process; the 3,000-step row is that
run's checkpoint, not a run with a 3,000-step schedule, and the table says
which schedule each row had). Evaluation time is not counted in the train time.

Every row (held-out PSNR mean and worst view, SSIM, colour-corrected PSNR,
Gaussians, train time, steps/s, peak memory, with the date, the commit and
whether ``mlx3d/`` had uncommitted changes) is merged into
``docs/benchmarks/real_captures/results.json`` (a row replaces an earlier one
of the same scene, method, steps, schedule and factor), the worst held-out
view of each milestone is written as a side-by-side PNG (photo | render) into
``--out`` and, scaled to at most 640 pixels wide, into
``docs/benchmarks/real_captures/``, and the page ``--markdown`` is written from
all the rows. The page's hand-written parts between ``<!-- notes:NAME -->`` and
``<!-- /notes:NAME -->`` (what the solves and the worst views show) are kept
when it is rewritten; ``--page-only`` rewrites the page alone.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import threading

from common import (LoadSampler, commit_info, held_out_metrics, load_results, machine_line, page_notes, peak_rss_mb,
                    train_to_milestones)  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = ("arc", "walk", "distorted_exposure", "object_orbit", "lund")
DOCS = os.path.join(ROOT, "docs", "benchmarks")
PICTURES = os.path.join(DOCS, "real_captures")
RESULTS = os.path.join(PICTURES, "results.json")
PICTURE_WIDTH = 640
NOTES = ("captures", "views")  # hand-written parts of the page, kept when it is rewritten


# ------------------------------------------------------------------ one run (child process)
GRID, NO_GRID = "+grid", "-grid"  # a method name ending in one trains with the bilateral grid on / off; else 'auto', the default

def _child(args) -> None:
    from mlx3d.datasets import load_dataset
    from mlx3d.training import GaussianTrainer, TrainerConfig, events_at
    from mlx3d.training.evaluate import BACKGROUNDS, render_view, save_side_by_side
    from mlx3d.training.exposure import exposure_spread
    from mlx3d.training.initial import initial_state

    scene, method = args.scene, args.child
    milestones = _milestones(args.steps)
    background = BACKGROUNDS["black"]
    dataset = load_dataset(args.data_dir, factor=args.factor)
    first = dataset.frames[dataset.train[0]].camera
    grid = True if method.endswith(GRID) else False if method.endswith(NO_GRID) else "auto"
    config = TrainerConfig(method=method.removesuffix(GRID).removesuffix(NO_GRID), steps=milestones[-1], background=background,
                           opaque_background="auto", bilateral_grid=grid)
    start = initial_state(dataset, config)
    spread = exposure_spread(dataset)
    for note in start.notes:
        print(f"[{scene} {method}] {note}", file=sys.stderr, flush=True)
    trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
    base = {"scene": scene, "method": method, "schedule": milestones[-1], "factor": args.factor,
            "size": f"{first.width}x{first.height}", "train_views": len(dataset.train), "test_views": len(dataset.test),
            "start_points": 0 if dataset.points is None else int(len(dataset.points)), "start_gaussians": len(start.model),
            "grid": ("on" if start.config.bilateral_grid else "off") + (" (auto)" if grid == "auto" else ""),
            "exposure_spread": spread}
    for milestone, trained in train_to_milestones(trainer, dataset, milestones, f"{scene} {method}"):
        if milestone < milestones[-1] and "reset_opacity" in events_at(trainer.config, milestone):
            print(f"[{scene} {method}] no row at step {milestone:,}: the opacity reset has just made every Gaussian "
                  "nearly transparent", file=sys.stderr, flush=True)
            continue
        row = {**base, "steps": milestone, "seconds": trained, "steps_per_s": milestone / max(trained, 1e-9),
               "gaussians": len(trainer.model), **held_out_metrics(trainer.model, dataset, background)}
        index = next(i for i in dataset.test if dataset.frames[i].name == row["worst_view"])
        target, image = render_view(trainer.model, dataset, index, background)
        os.makedirs(args.out, exist_ok=True)
        row["worst_png"] = os.path.join(args.out, f"{_key_name(row)}_worst.png")
        save_side_by_side(row["worst_png"], target, image)
        row["peak_rss_mb"] = peak_rss_mb()
        print(json.dumps(row), flush=True)


def _key_name(row) -> str:
    factor = f"_f{row['factor']:g}" if row["factor"] != 1 else ""
    schedule = f"_of{row['schedule']}" if row["schedule"] != row["steps"] else ""
    return f"{row['scene']}_{row['method']}_{row['steps']}{schedule}{factor}"


def _milestones(text) -> list[int]:
    return sorted({int(s) for s in str(text).split(",") if s.strip()})


# ------------------------------------------------------------------ the code measured
def _small_copy(src, dst) -> None:
    from PIL import Image

    image = Image.open(src)
    if image.width > PICTURE_WIDTH:
        image = image.resize((PICTURE_WIDTH, round(image.height * PICTURE_WIDTH / image.width)), Image.LANCZOS)
    os.makedirs(os.path.dirname(dst), exist_ok=True)
    image.save(dst, optimize=True)


# ------------------------------------------------------------------ the page
def _captures_table(captures: dict) -> str:
    lines = ["| capture | photos | registered | reprojection error | sparse points | camera | focal solved (true) | "
             "k1 solved (true) | max rotation error | max position error | render | solve |",
             "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for name in [s for s in SCENES if s in captures]:
        r = captures[name]
        if "error" in r:
            lines.append(f"| {name} | {r['photos']} | solve failed: {r['error']} | | | | | | | | | |")
            continue
        solves = [(name, r)]
        if r.get("auto_matching") and "error" not in r["auto_matching"]:
            solves.append((f"{name}, every pair matched (not trained on)", {**r, **r["auto_matching"]}))
        for label, r in solves:
            t = r.get("against_truth") or {}
            focal = f"{r['focal']:.1f}" + (f" ({t['focal_true']:.1f})" if t else "")
            k1 = f"{t['k1_solved']:.3f} ({t['k1_true']:g})" if t else ""
            rot = f"{t['rotation_deg']:.2f}°" if t else "(no truth)"
            pos = f"{t['position_pct']:.2f} %" if t else "(no truth)"
            render = ("(arc's renders)" if r.get("scene") == "arc's renders" else f"{r['render_seconds']:.0f} s") \
                if r.get("render_seconds") else "(photos)"
            matching = f", {r['matching']} matching" if label == name and r.get("matching") not in (None, "auto") else ""
            lines.append(f"| {label}{matching} | {r['photos']} | {r['registered']} | {r['reprojection_error']:.2f} px | "
                         f"{r['points']:,} | {r['camera_model']} | {focal} | {k1} | {rot} | {pos} | {render} | "
                         f"{r['solve_seconds']:.0f} s |")
    return "\n".join(lines) + "\n"


def _measured(row) -> str:
    changed = ", ".join(f"`{path}`" for path in row.get("mlx3d_changed", []))
    code = f"`{row['commit']}`" + (f" + uncommitted changes to {changed or 'mlx3d/'}" if row.get("mlx3d_dirty") else "")
    return f"{row['date']}, {code}"


def _results_tables(rows) -> str:
    out = []
    keys = sorted({(r["method"], r["steps"]) for r in rows}, key=lambda k: (k[0] != "vanilla", k[0], k[1]))
    for method, steps in keys:
        group = sorted([r for r in rows if (r["method"], r["steps"]) == (method, steps)],
                       key=lambda r: (SCENES.index(r["scene"]) if r["scene"] in SCENES else 99, r["factor"], r["schedule"]))
        out += [f"### {method}, {steps:,} steps", "",
                "| scene | factor | image | train/test views | schedule | colour grid (exposure spread) | PSNR mean (dB) | PSNR worst (view) | SSIM mean | SSIM worst | "
                "CC-PSNR mean | CC-PSNR worst | Gaussians | train time (s) | steps/s | peak RSS (MB) | load (median) | measured |",
                "|---|---:|---|---:|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        for r in group:
            if "error" in r:
                out.append(f"| {r['scene']} | {r['factor']:g} | | | | | failed: {r['error']} | | | | | | | | | | | {_measured(r)} |")
                continue
            out.append(
                f"| {r['scene']} | {r['factor']:g} | {r['size']} | {r['train_views']}/{r['test_views']} | {r['schedule']:,} | "
                f"{_grid(r)} | {r['psnr']:.2f} | {r['psnr_worst']:.2f} ({r['worst_view']}) | {r['ssim']:.4f} | {r['ssim_worst']:.4f} | "
                f"{r['cc_psnr']:.2f} | {r['cc_psnr_worst']:.2f} | {r['gaussians']:,} | {r['seconds']:.0f} | {r['steps_per_s']:.2f} | "
                f"{r['peak_rss_mb']:.0f} | {r.get('load_median', float('nan')):.1f} | {_measured(r)} |")
        out.append("")
    return "\n".join(out)


def _grid(row) -> str:
    spread = row.get("exposure_spread")
    return row.get("grid", "off") + ("" if spread is None else f" ({spread:.3f})")


def _pictures(rows) -> str:
    out = []
    for r in sorted([r for r in rows if r.get("picture")],
                    key=lambda r: (SCENES.index(r["scene"]) if r["scene"] in SCENES else 99, r["method"], r["steps"])):
        out += [f"**{r['scene']}, {r['method']}, {r['steps']:,} steps** (factor {r['factor']:g}): held-out view "
                f"`{r['worst_view']}`, {r['psnr_worst']:.2f} dB (photo | render)", "",
                f"![{r['scene']} {r['method']} {r['steps']} steps, worst held-out view]({r['picture']})", ""]
    return "\n".join(out)


def write_page(path, results) -> None:
    notes = page_notes(path, NOTES)
    rows, captures = results["rows"], results.get("captures", {})
    machines = sorted({r["machine"] for r in rows})
    page = f"""# Realistic captures: cameras from our own SfM

Every other quality figure in these pages comes from scenes rendered with exact cameras. Here the cameras are
solved from the photos themselves, by `mlx3d poses` (`mlx3d.sfm.solve_poses`, pycolmap), as for a real capture:
rendered captures with handheld paths, lens distortion, exposure changes and motion blur, an object on a full
orbit with alpha, and a real handheld street walk (`lund`).

```sh
python bench/captures.py                    # renders and solves the captures into bench_data/captures/ (git-ignored)
python bench/real_captures.py --scenes arc,lund --methods vanilla --steps 3000 --factor 2
python bench/real_captures.py               # every scene, vanilla and mcmc, evaluated at 3,000 and 7,000 steps
```

## The captures

`bench/captures.py` builds each scene with `bench/scenes.py`'s builders and renders it with the add-on's capture
code (Cycles on the CPU, 16 samples, fixed seeds), keeps only the photos (320 × 240), and solves their cameras
with `mlx3d.sfm.solve_poses`. The true Blender cameras are kept apart in `truth.json`, only to score the solve:
after a similarity alignment of the camera centres, the largest rotation error and the largest position error
(as a percentage of the largest distance between two true camera centres).

- **arc**: a handheld arc at arm's length around `outdoor`'s four objects on textured ground; 40 photos over
  160° of azimuth, 3 units away, 22° ± 3° up, with jittered distance, height, aim and roll.
- **walk**: walking past `open_points`' plaza and objects; 40 photos along a gently curved path 1.1 units high
  with a step's bob, the camera turning to keep the objects in view as the walker passes them (forward and
  sideways motion).
- **distorted_exposure**: `arc`'s cameras as a phone gives them: Brown radial distortion k1 = −0.1 on every photo
  (resampled in numpy from a wider render), a gain of 0.55–1.6 and ±12 % white balance per photo (the ranges of the
  `exposure` scene) and a 3–5 pixel directional motion blur on every third photo. The photos training holds out
  (every 8th) keep the scene's exposure and sharpness, as in `exposure`; the distortion is on all of them.
- **object_orbit**: `object_rgba`'s house on a full orbit: 60 photos (480 × 360) on a two-turn spiral from 35°
  below to 65° above it, 2.1 units away, transparent background (RGBA). Its bricks and roof tiles are
  darkened by a noise pattern (weathering): the house as `bench/scenes.py` builds it repeats its textures
  exactly, and only 6 of 40 (320 × 240), 13 of 60 (closer) and 18 of 60 (480 × 360) of its photos registered. No points are handed over: training starts from the sparse points
  the solve triangulated.
- **lund**: 29 handheld street photos (1024 × 768, OpenSfM's example data, BSD-2), solved with `mlx3d poses`.
  No truth: registered photos and the reprojection error are what can be measured.

{_captures_table(captures)}
<!-- notes:captures -->
{notes['captures']}
<!-- /notes:captures -->

## Training on them

`bench/real_captures.py` trains each dataset as `mlx3d train DATA --eval` does: every 8th photo in name order held
out, the solved sparse points as the start, black background, `auto` behind opaque photos, one run at a time in
its own process, with the per-photo colour grid where `mlx3d train` turns it on by default (the exposure spread the
solve measures, `mlx3d.training.exposure`, above 0.03; rows named `METHOD+grid` / `METHOD-grid` force it on / off,
and rows measured before that default existed trained without it). CC-PSNR is the PSNR after the affine colour map
that best fits each render to its photo. A row
whose schedule is longer than its steps is a checkpoint of a longer run (the 3,000-step evaluation of a
7,000-step run). Each row names the commit it was measured on (`+ uncommitted mlx3d/ changes` when the trainer's
files differed from it).

Machine: {'; '.join(machines) if machines else '(no runs yet)'}.

{_results_tables(rows)}
## The worst held-out views

<!-- notes:views -->
{notes['views']}
<!-- /notes:views -->

{_pictures(rows)}"""
    with open(path, "w", encoding="utf-8") as f:
        f.write(page.rstrip() + "\n")


# ------------------------------------------------------------------ driver
def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=os.path.join("bench_data", "captures"), metavar="DIR",
                        help="the captures bench/captures.py wrote (default bench_data/captures)")
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated (default {','.join(SCENES)})")
    parser.add_argument("--methods", default="vanilla,mcmc",
                        help=f"comma-separated (default vanilla,mcmc), as mlx3d train's default (a per-photo colour grid when "
                             f"the exposure varies); METHOD{GRID} / METHOD{NO_GRID}: with the grid on / off")
    parser.add_argument("--steps", default="3000,7000", help="milestones of one run, comma-separated (default 3000,7000)")
    parser.add_argument("--factor", type=float, default=1.0, help="image downscale factor, as mlx3d train --factor (default 1)")
    parser.add_argument("--out", default=os.path.join("bench", "out", "real_captures"), metavar="DIR",
                        help="full-size worst-view PNGs (default bench/out/real_captures)")
    parser.add_argument("--markdown", default=os.path.join(DOCS, "real_captures.md"), metavar="PATH",
                        help="the page to write (default docs/benchmarks/real_captures.md)")
    parser.add_argument("--page-only", action="store_true", help="only rewrite the page from results.json")
    parser.add_argument("--child", metavar="METHOD", help=argparse.SUPPRESS)
    parser.add_argument("--scene", help=argparse.SUPPRESS)
    parser.add_argument("--data-dir", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args)
        return 0

    scenes = [s for s in args.scenes.split(",") if s]
    methods = [m for m in args.methods.split(",") if m]
    from mlx3d.training.trainer import METHODS

    for s in scenes:
        if s not in SCENES:
            parser.error(f"unknown scene {s!r}; use {', '.join(SCENES)}")
    for m in methods:
        if m.removesuffix(GRID).removesuffix(NO_GRID) not in METHODS:
            parser.error(f"unknown method {m!r}; use {', '.join(METHODS)}, each optionally with {GRID} or {NO_GRID} (the colour grid on, off)")
    try:
        milestones = _milestones(args.steps)
    except ValueError:
        parser.error(f"--steps takes comma-separated step counts, got {args.steps!r}")
    if not milestones or milestones[0] < 1:
        parser.error("--steps must be at least 1")

    results = load_results(RESULTS)
    for s in SCENES:  # the capture and solve summaries, kept with the rows
        path = os.path.join(args.data, s, "capture.json")
        if os.path.isfile(path):
            with open(path, encoding="utf-8") as f:
                results.setdefault("captures", {})[s] = json.load(f)
    if args.page_only:
        write_page(args.markdown, results)
        print(f"wrote {args.markdown}")
        return 0

    code = commit_info(ROOT)
    failed = 0
    for scene in scenes:
        data = os.path.join(args.data, scene, "data")
        if not os.path.isdir(data):
            print(f"{scene}: {data} is missing (run bench/captures.py --only {scene})", file=sys.stderr)
            failed += 1
            continue
        for method in methods:
            load = LoadSampler()
            load.start()
            cmd = [sys.executable, os.path.abspath(__file__), "--child", method, "--scene", scene, "--data-dir", data,
                   "--steps", ",".join(map(str, milestones)), "--factor", str(args.factor), "--out", args.out]
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            tail = []

            def drain() -> None:
                for line in proc.stderr:
                    sys.stderr.write(line)
                    tail[:] = (tail + [line.rstrip()])[-20:]

            reader = threading.Thread(target=drain, daemon=True)
            reader.start()
            new = [json.loads(line) for line in proc.stdout if line.startswith("{")]
            status = proc.wait()
            reader.join()
            load.stop.set()
            load.join()
            stamp = {"date": datetime.date.today().isoformat(), **code, "machine": machine_line("; one run at a time"),
                     "load_median": load.summary().get("median", float("nan"))}
            if status != 0:
                message = next((t for t in reversed(tail) if t and not t.startswith(" ")), f"exit code {status}")
                new.append({"scene": scene, "method": method, "steps": milestones[-1], "schedule": milestones[-1],
                            "factor": args.factor, "error": message.replace("|", "/")[:200]})
                failed += 1
            for row in new:
                row.update(stamp)
                if row.get("worst_png"):
                    row["picture"] = f"real_captures/{_key_name(row)}.png"
                    _small_copy(row["worst_png"], os.path.join(DOCS, row["picture"]))
                    print(f"{scene} {method}: step {row['steps']:,} PSNR {row['psnr']:.2f} dB (worst {row['psnr_worst']:.2f}, "
                          f"{row['worst_view']}), SSIM {row['ssim']:.4f}, {row['gaussians']:,} Gaussians, {row['seconds']:.0f} s",
                          file=sys.stderr, flush=True)
                key = (row["scene"], row["method"], row["steps"], row["schedule"], row["factor"])
                results["rows"] = [r for r in results["rows"]
                                   if (r["scene"], r["method"], r["steps"], r["schedule"], r["factor"]) != key] + [row]
            os.makedirs(PICTURES, exist_ok=True)
            with open(RESULTS, "w", encoding="utf-8") as f:
                json.dump(results, f, indent=1)
                f.write("\n")
            write_page(args.markdown, results)
    print(f"wrote {args.markdown} and {RESULTS}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
