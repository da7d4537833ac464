"""What the compiled kernels buy, and what reaching them through the kernel library costs: ``mlx3d._core``, the
kernel library through ctypes and the pure MLX path, same machine, same run.

    python bench/pure_path.py [--demo demo_out/dataset] [--steps 300] [--markdown PATH]

Each mode runs in a fresh process: ``core`` (the default backend 'cpu', the
C++ kernels as MLX primitives of ``mlx3d._core``), ``library``
(``MLX3D_CPU_KERNELS=library``: the same kernels, the backend 'cpu', through
``mlx3d.kernel_library``, as where ``_core`` is missing: Windows, Linux arm64,
macOS' CPU path; the library built for this machine into
build/kernels/linux-x64/) and ``pure`` (``MLX3D_NO_CORE=1``: the backend 'mlx',
MLX operations only, as where neither loads). Cases:

- garden 138,766: the real SfM points of ``shared/data/test_garden.npz`` as
  Gaussians (``bench/train_scale.py``'s set-up, SH degree 3, 648x420): the
  median time of a render (projection to image) and of a training step
  (vanilla, the density statistics gathered);
- the demo scene (``make demo`` writes its captured dataset to
  ``demo_out/dataset``; skipped with a note when it is missing): ``--steps``
  vanilla training steps from ``initial_state`` as ``mlx3d train`` starts
  them (steps/s), the held-out PSNR mean and worst view, and the median time
  of a held-out render.

The table gives the modes side by side and their ratios to ``core`` within
one run of this script, on the machine and load it prints.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from common import LoadSampler, emit, machine_line, median_ms, peak_rss_mb  # bench/ is on sys.path when run as a script

HERE = os.path.dirname(os.path.abspath(__file__))
MODES = ("core", "library", "pure")
LIBRARY = os.path.join(HERE, "..", "build", "kernels", "linux-x64")


def _garden(repeats: int) -> dict:
    import mlx.core as mx

    from mlx3d.training import GaussianTrainer, TrainerConfig
    from train_scale import _setup

    model, camera, target = _setup(138766, 1)
    render_ms = median_ms(lambda: mx.eval(model.render(camera, background=(0, 0, 0))["image"]), repeats)
    config = TrainerConfig(steps=10**6, densify_from=10**5, densify_until=10**6, sh_increase_every=0)
    trainer = GaussianTrainer(model, config, scene_extent=5.0)
    trainer.active_sh_degree = 3
    step_ms = median_ms(lambda: trainer.step(camera, target), repeats)
    return {"case": "garden 138,766 (648x420)", "render_ms": render_ms, "step_ms": step_ms, "steps_per_s": 1000.0 / step_ms}


def _demo(path: str, steps: int, repeats: int) -> dict:
    import mlx.core as mx

    from mlx3d.datasets import load_dataset
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.evaluate import evaluate, render_view
    from mlx3d.training.initial import initial_state

    dataset = load_dataset(path)
    background = (0.0, 0.0, 0.0)
    start = initial_state(dataset, TrainerConfig(steps=steps, background=background))
    trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
    t0 = time.perf_counter()
    trainer.fit(dataset, steps=steps)
    seconds = time.perf_counter() - t0
    report = evaluate(trainer.model, dataset, "test", background)
    view = dataset.test[0]
    render_ms = median_ms(lambda: mx.eval(render_view(trainer.model, dataset, view, background)[1]), repeats)
    frame = dataset.frames[view]
    return {"case": f"demo scene, {steps} steps ({frame.camera.width}x{frame.camera.height})", "render_ms": render_ms,
            "steps_per_s": steps / seconds, "psnr": report["psnr"], "psnr_worst": report["worst"]["psnr"], "gaussians": len(trainer.model)}


def child(args) -> None:
    from mlx3d import native
    from mlx3d.render import resolve_backend

    kernels = native.core().__name__ if native.available() else "none"
    if kernels != {"core": "mlx3d._core", "library": "mlx3d.kernel_library", "pure": "none"}[args.child]:
        sys.exit(f"mode {args.child} runs the kernels of {kernels}")
    rows = [_garden(args.repeats)]
    if args.demo and os.path.isdir(args.demo):
        rows.append(_demo(args.demo, args.steps, args.repeats))
    import mlx3d

    for row in rows:
        row.update(mode=args.child, backend=resolve_backend("auto"), kernels=kernels, peak_mb=peak_rss_mb(),
                   mlx3d=os.path.dirname(os.path.abspath(mlx3d.__file__)))
        print(json.dumps(row), flush=True)


def _run(mode: str, args, site: str | None = None) -> list:
    """The rows of a child process in ``mode``; ``site``: a directory holding another build of mlx3d (an unpacked
    wheel), which the child imports instead of this checkout's (``python -S``, this interpreter's packages after it)."""
    env = dict(os.environ)
    env.pop("MLX3D_NO_CORE", None)
    env.pop("MLX3D_CPU_KERNELS", None)
    if mode == "pure":
        env["MLX3D_NO_CORE"] = "1"
    if mode == "library":
        env["MLX3D_CPU_KERNELS"] = "library"
        env["MLX3D_KERNELS"] = os.path.join(LIBRARY, "libmlx3d_kernels.so")
    python = [sys.executable]
    if site:
        import sysconfig

        python.append("-S")
        env["PYTHONPATH"] = os.pathsep.join([site, sysconfig.get_path("purelib"), sysconfig.get_path("platlib")])
    cmd = python + [os.path.abspath(__file__), "--child", mode, "--steps", str(args.steps), "--repeats", str(args.repeats),
                    "--demo", args.demo or ""]
    print(f"[{mode}] {' '.join(cmd)}", file=sys.stderr, flush=True)
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=HERE)
    if out.returncode != 0:
        sys.exit(f"[{mode}] failed:\n{out.stderr[-4000:]}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def _cell(row: dict | None, key: str, fmt: str) -> str:
    return "-" if row is None or key not in row else format(row[key], fmt)


def table(results: dict, note: str) -> str:
    lines = [f"The C++ kernels inside `mlx3d._core` (backend 'cpu'), the same kernels through the kernel library "
             f"(`MLX3D_CPU_KERNELS=library`, ctypes) and the pure MLX path (`MLX3D_NO_CORE=1`, backend 'mlx'); {note}", "",
             "| case | measure | `_core` | kernel library | pure MLX | library / `_core` | pure / `_core` |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for core in results["core"]:
        other = {mode: next((r for r in results[mode] if r["case"] == core["case"]), None) for mode in ("library", "pure")}
        for key, name, fmt in (("render_ms", "render (ms)", ".0f"), ("step_ms", "training step (ms)", ".0f"),
                               ("steps_per_s", "steps/s", ".2f"), ("psnr", "held-out PSNR mean (dB)", ".2f"),
                               ("psnr_worst", "held-out PSNR worst view (dB)", ".2f")):
            if key not in core:
                continue
            costs = []
            for row in other.values():
                if row is None or key not in row:
                    costs.append("-")
                elif key in ("render_ms", "step_ms"):
                    costs.append(f"{row[key] / core[key]:.2f}x the time")
                elif key == "steps_per_s":
                    costs.append(f"{row[key] / core[key]:.2f}x the rate")
                else:
                    costs.append(f"{row[key] - core[key]:+.2f} dB")
            lines.append(f"| {core['case']} | {name} | {_cell(core, key, fmt)} | {_cell(other['library'], key, fmt)} | "
                         f"{_cell(other['pure'], key, fmt)} | {costs[0]} | {costs[1]} |")
    peaks = ", ".join(f"{mode} {rows[0]['peak_mb']:.0f} MB" for mode, rows in results.items() if rows)
    return "\n".join(lines) + f"\n\nPeak resident memory of each process (all its cases): {peaks}."


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--demo", default=os.path.join(HERE, "..", "demo_out", "dataset"), help="the demo's captured dataset ('' to skip)")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--markdown")
    p.add_argument("--child", choices=MODES, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        return child(args)
    args.demo = os.path.abspath(args.demo) if args.demo else ""
    if args.demo and not os.path.isdir(args.demo):
        print(f"note: no demo dataset at {args.demo} (run `make demo` first); the demo rows are left out", file=sys.stderr)
    subprocess.run([sys.executable, os.path.join(HERE, "..", "mlx3d", "csrc", "kernels", "build.py"), "linux-x64", "--out", LIBRARY],
                   check=True, stdout=subprocess.DEVNULL)
    sampler = LoadSampler()
    sampler.start()
    results = {mode: _run(mode, args) for mode in MODES}
    sampler.stop.set()
    sampler.join()
    emit(table(results, machine_line()) + "\n\n" + sampler.line(os.cpu_count() or 1, 1.5) + "\n", args.markdown)


if __name__ == "__main__":
    main()
