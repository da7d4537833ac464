"""The kernel library called through ctypes against the same kernels inside mlx3d._core and the pure MLX path.

    python bench/kernel_library.py [--gaussians 138766] [--repeats 40] [--step-repeats 5] [--reference a5917c2]
                                   [--markdown PATH]

``mlx3d.kernel_library`` (the C library, ``mlx3d/csrc/kernels``, loaded with
ctypes: what Windows and Linux arm64 can run) and ``mlx3d._core`` (an MLX
primitive over the same C functions, in MLX's lazy graph) run the same kernel
code, so the difference is the cost of the boundary: checking and evaluating the
inputs, and allocating the outputs as MLX arrays (filled with zeros first: MLX's
Python API has no uninitialised allocation). The pure MLX expression (the
'mlx' backend, where neither exists) is timed beside them. Kernels: the SH
colour of ``--gaussians`` Gaussians at degree 3 (forward, and forward with the
backward pass of a weighted sum) and the densification statistics of one view,
on one thread and on every core. The library is built for this machine into
build/kernels/linux-x64/ (``build.py``) unless ``MLX3D_KERNELS`` names one.
Median milliseconds of ``--repeats`` runs after a warm-up, and the ratios to
``_core``, within one run of this script on the machine and load it prints.

Then the whole: a render and a training step at garden size in three fresh
processes (``bench/pure_path.py``'s garden case: ``_core``, the library with
``MLX3D_CPU_KERNELS=library``, and the pure path), ``--step-repeats`` each.
Linux's own build keeps ``_core`` (MLX primitives over the library's C
functions); ``--reference REV`` (default: the last commit before the
library, whose ``_core`` held the kernels itself) is built here as a wheel
(``git worktree``, ``pip wheel``; kept in build/reference/REV/) and its render
and training step are timed the same way beside this checkout's ``_core``
('' skips it). The page's hand-written part between ``<!-- notes:meaning -->`` and
``<!-- /notes:meaning -->`` (what the numbers mean for each platform's zip) is
kept when it is written again.
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys

import pure_path  # bench/ is on sys.path when run as a script
from common import LoadSampler, emit, machine_line, median_ms, page_notes

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _library() -> str:
    if os.environ.get("MLX3D_KERNELS"):
        return os.environ["MLX3D_KERNELS"]
    out = os.path.join(ROOT, "build", "kernels", "linux-x64")
    subprocess.run([sys.executable, os.path.join(ROOT, "mlx3d", "csrc", "kernels", "build.py"), "linux-x64", "--out", out],
                   check=True, stdout=subprocess.DEVNULL)
    return os.path.join(out, "libmlx3d_kernels.so")


#: The last commit before the kernel library: its _core held the kernels itself (the "today's _core" it is held to).
REFERENCE = "a5917c2"


def _reference_site(rev: str) -> str:
    """mlx3d as built at commit ``rev``: its wheel (built from a temporary git worktree) unpacked into
    build/reference/<rev>/site, which is returned (reused when there)."""
    import glob
    import tempfile
    import zipfile

    site = os.path.join(ROOT, "build", "reference", rev, "site")
    if os.path.isdir(os.path.join(site, "mlx3d")):
        return site
    with tempfile.TemporaryDirectory() as tmp:
        tree = os.path.join(tmp, "tree")
        subprocess.run(["git", "-C", ROOT, "worktree", "add", "--detach", tree, rev], check=True, stdout=subprocess.DEVNULL)
        try:
            subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-build-isolation", "--no-deps", "-w", tmp, tree],
                           check=True)
        finally:
            subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", tree], check=True)
        zipfile.ZipFile(glob.glob(os.path.join(tmp, "mlx3d_splat-*.whl"))[0]).extractall(site)
    return site


def reference_table(reference: dict, current: dict, rev: str) -> str:
    """The reference build's render and step against this checkout's ``_core`` (rows of ``pure_path._run``)."""
    lines = [f"| case | measure | `_core` at {rev} | `_core` now | now / {rev} |", "| --- | --- | ---: | ---: | ---: |"]
    for old in reference:
        new = next(r for r in current if r["case"] == old["case"])
        for key, name in (("render_ms", "render (ms)"), ("step_ms", "training step (ms)")):
            lines.append(f"| {old['case']} | {name} | {old[key]:.0f} | {new[key]:.0f} | {new[key] / old[key]:.2f}x the time |")
    return "\n".join(lines)


def measure(n: int, repeats: int) -> list:
    import mlx.core as mx
    import numpy as np

    from mlx3d import kernel_library, native
    from mlx3d.splatting.sh import eval_sh

    rng = np.random.default_rng(0)
    dc = mx.array(rng.normal(size=(n, 1, 3)).astype(np.float32))
    rest = mx.array(0.3 * rng.normal(size=(n, 15, 3)).astype(np.float32))
    means = mx.array(rng.normal(size=(n, 3)).astype(np.float32))
    centre = mx.array([0.3, -2.0, 1.0], dtype=mx.float32)
    w = mx.array(rng.normal(size=(n, 3)).astype(np.float32))
    visible, grad2d = rng.random(n) < 0.7, rng.normal(size=(n, 2)).astype(np.float32) * 1e-4
    radii = rng.integers(0, 40, n).astype(np.int32)
    stats = [np.zeros(n) for _ in range(3)]

    def pure_colours(a, b, m):
        return mx.maximum(eval_sh(3, mx.concatenate([a, b], axis=1), m - centre), 0.0)

    def pure_statistics():
        g = mx.array(grad2d) * mx.array([324.0, 210.0])
        out = (mx.where(mx.array(visible), mx.sqrt(mx.sum(g * g, axis=1)), 0.0), mx.array(visible).astype(mx.float32),
               mx.array(radii).astype(mx.float32))
        mx.eval(*out)

    rows = []
    for threads in (1, 0):
        ways = {"_core": lambda blocks, m, c, d, t=threads: native.core().sh_colors(blocks, m, c, d, t),
                "library": lambda blocks, m, c, d, t=threads: kernel_library.sh_colors(blocks, m, c, d, t)}
        times = {}
        for name, fn in ways.items():
            grad = mx.value_and_grad(lambda a, b, m, fn=fn: (fn([a, b], m, centre, 3) * w).sum(), argnums=(0, 1, 2))
            times[("SH colour, forward", name)] = median_ms(lambda fn=fn: mx.eval(fn([dc, rest], means, centre, 3)), repeats)
            times[("SH colour, forward and backward", name)] = median_ms(lambda grad=grad: mx.eval(grad(dc, rest, means)), repeats)
        times[("SH colour, forward", "pure")] = median_ms(lambda: mx.eval(pure_colours(dc, rest, means)), repeats)
        pure_grad = mx.value_and_grad(lambda a, b, m: (pure_colours(a, b, m) * w).sum(), argnums=(0, 1, 2))
        times[("SH colour, forward and backward", "pure")] = median_ms(lambda: mx.eval(pure_grad(dc, rest, means)), repeats)
        times[("statistics of a view", "_core")] = median_ms(
            lambda: native.core().add_screen_statistics(visible, grad2d, radii, 324.0, 210.0, *stats, threads), repeats)
        times[("statistics of a view", "library")] = median_ms(
            lambda: kernel_library.add_screen_statistics(visible, grad2d, radii, 324.0, 210.0, *stats, threads), repeats)
        times[("statistics of a view", "pure")] = median_ms(pure_statistics, repeats)
        for case in dict.fromkeys(c for c, _ in times):
            core, lib, pure = (times[(case, w)] for w in ("_core", "library", "pure"))
            rows.append((case, "1" if threads == 1 else f"all ({os.cpu_count()})", core, lib, pure))
    return rows


def table(rows, n: int) -> str:
    out = [f"| kernel ({n:,} Gaussians) | threads | `_core` (ms) | library, ctypes (ms) | pure MLX (ms) | library / `_core` | pure / `_core` |",
           "|---|---|---:|---:|---:|---:|---:|"]
    for case, threads, core, lib, pure in rows:
        out.append(f"| {case} | {threads} | {core:.2f} | {lib:.2f} | {pure:.2f} | {lib / core:.2f} | {pure / core:.1f} |")
    return "\n".join(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=138766, help="Gaussians (default 138,766: the garden's)")
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--step-repeats", type=int, default=5, help="repeats of the render and the training step")
    parser.add_argument("--reference", default=REFERENCE, help=f"a commit whose _core to time beside (default {REFERENCE}; '' skips)")
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args()
    reference_site = _reference_site(args.reference) if args.reference else None
    os.environ["MLX3D_KERNELS"] = _library()
    from mlx3d import kernel_library, native

    if not native.available() or not kernel_library.available():
        raise SystemExit(f"needs mlx3d._core and the kernel library: {kernel_library.failure() or 'mlx3d._core is not available'}")
    load = LoadSampler()
    load.start()
    rows = measure(args.gaussians, args.repeats)
    step_args = argparse.Namespace(steps=0, repeats=args.step_repeats, demo="")
    steps = {mode: pure_path._run(mode, step_args) for mode in pure_path.MODES}
    reference = pure_path._run("core", step_args, site=reference_site) if reference_site else None
    load.stop.set()
    load.join()
    summary = load.summary()
    text = "\n".join([
        "# The kernel library against `_core`", "",
        "The same C++ kernels called two ways: through `mlx3d.kernel_library` (ctypes: the C library, which is what "
        "Windows and Linux arm64 can load) and inside `mlx3d._core` (MLX primitives over the same functions), with the "
        "pure MLX expressions beside them (`python bench/kernel_library.py`; what each case runs is in its docstring). "
        "The library's extra time is its boundary: the inputs checked and evaluated, the outputs allocated as MLX arrays "
        "and filled with zeros first (MLX's Python API has no uninitialised allocation).", "",
        f"Measured {datetime.date.today().isoformat()} on {machine_line()}; library {kernel_library.build_info()}; "
        f"1-minute load average during the run: median {summary.get('median', float('nan')):.1f} on {os.cpu_count()} cores.", "",
        table(rows, args.gaussians), "",
        "## A render and a training step", "",
        f"The garden's {138766:,} Gaussians at 648x420, SH degree 3, in a fresh process per mode (`bench/pure_path.py`'s "
        f"garden case, median of {args.step_repeats}); the library built as above.", "",
        pure_path.table(steps, machine_line()), "",
        *([f"Linux's build against the `_core` before the library (commit `{args.reference}`, whose `_core` held the kernels "
           "itself; built as a wheel and run in a fresh process the same way):", "",
           reference_table(reference, steps["core"], args.reference), ""] if reference else []),
        "## What it means for each zip", "",
        "<!-- notes:meaning -->", page_notes(args.markdown or "", ("meaning",))["meaning"], "<!-- /notes:meaning -->", ""])
    emit(text, args.markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
