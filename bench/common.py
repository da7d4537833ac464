"""Helpers shared by the benchmark scripts (run as ``python bench/NAME.py``)."""

from __future__ import annotations

import os
import resource
import statistics
import sys
import threading
import time


def rss_kib() -> tuple[int, int]:
    """(current RSS, peak RSS) of this process in KiB (peak only, as both, where /proc is missing)."""
    cur = peak = 0
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    cur = int(line.split()[1])
                elif line.startswith("VmHWM:"):
                    peak = int(line.split()[1])
    except OSError:  # not Linux: ru_maxrss is in bytes on macOS
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        if sys.platform == "darwin":
            peak //= 1024
        cur = peak
    return cur, peak


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MB (VmHWM on Linux, ru_maxrss elsewhere)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024.0 / (1024.0 if sys.platform == "darwin" else 1.0)  # bytes on macOS, KiB on Linux


def median_ms(fn, repeats: int) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` in milliseconds, after one warm-up call (first-call
    allocations and compilation)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * sorted(times)[len(times) // 2]


NO_NOTES = "(Not described yet.)"


def page_notes(path: str, names) -> dict:
    """The hand-written parts of a benchmark page that its script writes again: {name: the text between
    ``<!-- notes:NAME -->`` and ``<!-- /notes:NAME -->``}, ``NO_NOTES`` where the page or the block is missing."""
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except OSError:
        text = ""
    notes = {}
    for name in names:
        start_mark, end_mark = f"<!-- notes:{name} -->", f"<!-- /notes:{name} -->"
        start, end = text.find(start_mark), text.find(end_mark)
        notes[name] = text[start + len(start_mark):end].strip() if 0 <= start < end else NO_NOTES
    return notes


def emit(table: str, markdown_path: str | None) -> None:
    """Print a markdown table and, when asked, write it to ``markdown_path``."""
    print(table)
    if markdown_path:
        os.makedirs(os.path.dirname(os.path.abspath(markdown_path)), exist_ok=True)
        with open(markdown_path, "w") as f:
            f.write(table)


def machine_line(suffix: str = "") -> str:
    """CPU, cores, memory, platform, Python, MLX and render backend, then ``suffix``."""
    from mlx3d.report.accuracy import machine_info

    m = machine_info()
    memory = f", {m['memory_gb']:.0f} GB memory" if m.get("memory_gb") else ""
    return (f"{m['cpu']} ({m['machine']}, {m['cores']} cores{memory}), {m['platform']}; Python {m['python']}, MLX {m['mlx']} "
            f"({m['mlx_device']}), render backend {m['backend']}{suffix}")


class LoadSampler(threading.Thread):
    """Samples the 1-minute load average every ``every`` seconds while a benchmark runs (``start()``,
    then ``stop.set()`` and ``join()``)."""

    def __init__(self, every: float = 5.0):
        super().__init__(daemon=True)
        self.every, self.samples, self.stop = every, [], threading.Event()

    def sample(self) -> None:
        try:
            self.samples.append(os.getloadavg()[0])
        except (OSError, AttributeError):
            pass

    def run(self) -> None:
        self.sample()
        while not self.stop.wait(self.every):
            self.sample()

    def summary(self) -> dict:
        s = self.samples
        return {"n": len(s), "median": statistics.median(s), "min": min(s), "max": max(s)} if s else {"n": 0}

    def line(self, cores: int, shared_above: float, note: str = "") -> str:
        """The load during the run; a median above ``shared_above`` (more than the benchmark's own
        load) is called out as a shared machine, followed by ``note``."""
        load = self.summary()
        if not load["n"]:
            return "load average not available"
        text = f"1-minute load average during the run: median {load['median']:.1f}, range {load['min']:.1f}-{load['max']:.1f} on {cores} cores"
        if load["median"] > shared_above:
            text += f" (a shared machine: other processes ran beside the benchmark, so times are slower and noisier than on an idle one{note})"
        return text


def train_to_milestones(trainer, dataset, milestones, label: str):
    """Train ``trainer`` on ``dataset`` up to each step count of ``milestones`` in turn, printing a progress line
    (step, loss, training PSNR, Gaussians, seconds) every tenth of the last; yields (milestone, seconds trained)."""
    trained, done, started = 0.0, 0, [0.0]
    every = max(milestones[-1] // 10, 1)

    def progress(i: int, total: int, info: dict) -> None:
        step = done + i
        if step % every == 0:
            print(f"[{label}] step {step:,}/{milestones[-1]:,}  loss {info['loss']:.4f}  train PSNR {info['psnr']:.2f}  "
                  f"{info['num_gaussians']:,} Gaussians  ({trained + time.perf_counter() - started[0]:.0f} s)",
                  file=sys.stderr, flush=True)

    for milestone in milestones:
        started[0] = time.perf_counter()
        trainer.fit(dataset, steps=milestone - done, progress=progress)
        trained += time.perf_counter() - started[0]
        done = milestone
        yield milestone, trained


def held_out_metrics(model, dataset, background) -> dict:
    """``mlx3d.training.evaluate.evaluate`` on the test split as the benchmark rows hold it: means, worst views,
    colour-corrected figures, the time it took and every view's own figures (``per_view``)."""
    from mlx3d.training.evaluate import evaluate

    start = time.perf_counter()
    report = evaluate(model, dataset, "test", background)
    views = report["views"]
    return {
        "views": len(views), "psnr": report["psnr"], "psnr_worst": report["worst"]["psnr"], "worst_view": report["worst"]["name"],
        "ssim": report["ssim"], "ssim_worst": min(v["ssim"] for v in views),
        "cc_psnr": report["cc_psnr"], "cc_psnr_worst": report["cc_worst"]["cc_psnr"], "cc_worst_view": report["cc_worst"]["name"],
        "cc_ssim": report["cc_ssim"], "eval_seconds": time.perf_counter() - start, "per_view": views,
    }


def load_results(path: str) -> dict:
    """A benchmark's results file, ``{"rows": [...], "captures": {...}}``; empty ones when it is missing or unreadable."""
    import json

    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (OSError, ValueError):
        return {"rows": [], "captures": {}}


def commit_info(root: str) -> dict:
    """The commit measured (``commit``), and whether ``mlx3d/`` differed from it (``mlx3d_dirty``, ``mlx3d_changed``)."""
    import subprocess

    def git(*cmd):
        return subprocess.run(["git", *cmd], cwd=root, capture_output=True, text=True).stdout

    dirty = [line[3:] for line in git("status", "--porcelain", "--", "mlx3d").splitlines() if line.strip()]
    return {"commit": git("rev-parse", "--short=10", "HEAD").strip(), "mlx3d_dirty": bool(dirty), "mlx3d_changed": sorted(dirty)}


def parse_only(parser, text, choices, what: str) -> tuple:
    """The names in the comma-separated ``text`` of an ``--only`` option (every one of ``choices`` when it is
    empty); an unknown name is a usage error naming ``what`` they are (``scene``, ``capture``)."""
    only = tuple(choices) if not text else tuple(s.strip() for s in text.split(",") if s.strip())
    unknown = [s for s in only if s not in choices]
    if unknown:
        parser.error(f"unknown {what}(s) {', '.join(unknown)}; choose from {', '.join(choices)}")
    return only
