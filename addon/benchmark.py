"""Benchmark this machine from Blender: ``mlx3d bench accuracy`` in a child process.

The benchmark trains and renders for minutes (quick) to most of an hour
(full), so it runs as a separate Python process (Blender's own interpreter,
``sys.executable -m mlx3d.cli bench accuracy``) rather than inside Blender:
Blender stays responsive, its timings are not disturbed by the UI, and
cancelling is a SIGTERM (Ctrl+Break on Windows), which the command takes as
Ctrl+C: it stops and writes nothing. The child finds ``mlx3d`` and ``mlx`` through this process's
``sys.path`` (the extension's bundled wheels).

``BenchmarkJob`` starts the process, follows its progress line on stderr
(``running``, ``progress`` in thousandths, ``status``), and ``finish()``
returns the report's path or raises ``BenchmarkError`` with the command's
last error lines. No bpy here, so it can be used and tested anywhere.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
from collections import deque

MODES = ("quick", "full", "tiny")  # tiny: seconds, for tests
REPORT_NAME = "README.md"
DEFAULT_FOLDER = "mlx3d_accuracy"
_PROGRESS = re.compile(r"^bench accuracy(?: \[(?P<what>.*)\])?: +(?P<pct>\d+(?:\.\d+)?)% \(")


class BenchmarkError(RuntimeError):
    """The benchmark could not run or failed; the message says why."""


def default_folder(blend_path: str = "") -> str:
    """``mlx3d_accuracy`` next to the saved .blend file, else in the temporary folder."""
    base = os.path.dirname(os.path.abspath(blend_path)) if blend_path else tempfile.gettempdir()
    return os.path.join(base, DEFAULT_FOLDER)


def child_environment() -> dict:
    """This process's environment with its ``sys.path`` as ``PYTHONPATH``, so the child imports the same mlx3d and mlx."""
    env = dict(os.environ)
    paths = [p for p in sys.path if p and os.path.isdir(p)]
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


class BenchmarkJob:
    """``mlx3d bench accuracy`` for ``out_dir`` in ``mode`` ('quick', 'full' or 'tiny'), run as a child process."""

    def __init__(self, out_dir: str, mode: str = "quick", seed: int = 0, python: str | None = None):
        if mode not in MODES:
            raise BenchmarkError(f"mode must be one of {MODES}, got {mode!r}")
        if not out_dir:
            raise BenchmarkError("choose an output folder for the benchmark report")
        self.out_dir = os.path.abspath(out_dir)
        self.mode = mode
        self.command = [python or sys.executable, "-m", "mlx3d.cli", "bench", "accuracy", "--out", self.out_dir, "--seed", str(int(seed))]
        if mode != "full":
            self.command.append(f"--{mode}")
        self.progress = 0  # thousandths
        self.status = "starting"
        self.cancelled = False
        self._lines = deque(maxlen=40)
        self._process = None
        self._reader = None

    # -- running
    def start(self) -> None:
        kw = {}
        if os.name == "nt":  # a process group, so it can receive Ctrl+Break
            kw["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
        try:
            self._process = subprocess.Popen(self.command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                             env=child_environment(), text=True, bufsize=1, **kw)
        except OSError as exc:
            raise BenchmarkError(f"cannot start the benchmark ({self.command[0]}): {exc}") from None
        self._reader = threading.Thread(target=self._read, name="mlx3d benchmark output", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self._process.stderr:
            line = line.rstrip("\n").split("\r")[-1]
            match = _PROGRESS.match(line)
            if match:
                self.progress = int(round(10 * float(match["pct"])))
                self.status = match["what"] or self.status
            elif line.strip():
                self._lines.append(line)

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the process (and its output) to end; False when ``timeout`` passed first."""
        if self._process is None:
            return True
        try:
            self._process.wait(timeout)
        except subprocess.TimeoutExpired:
            return False
        if self._reader is not None:
            self._reader.join(5)
        return True

    def cancel(self, timeout: float = 10.0) -> None:
        """Stop the benchmark as Ctrl+C does (it then writes nothing); kill it if it does not end within ``timeout`` s."""
        self.cancelled = True
        if not self.running:
            return
        if os.name == "nt":
            self._process.send_signal(signal.CTRL_BREAK_EVENT)
        else:
            self._process.send_signal(signal.SIGTERM)  # the command takes it as Ctrl+C
        if not self.wait(timeout):
            self._process.kill()
            self.wait(timeout)

    @property
    def returncode(self):
        return None if self._process is None else self._process.poll()

    @property
    def report_path(self) -> str:
        return os.path.join(self.out_dir, REPORT_NAME)

    def finish(self) -> str:
        """The report's path once the process ended well; BenchmarkError otherwise."""
        self.wait()
        code = self.returncode
        if self.cancelled or code == 130:
            raise BenchmarkError("the benchmark was cancelled; nothing was written")
        if code != 0:
            tail = " | ".join(list(self._lines)[-3:]) or "no output"
            raise BenchmarkError(f"the benchmark failed (exit code {code}): {tail}")
        if not os.path.isfile(self.report_path):
            raise BenchmarkError(f"the benchmark ended but wrote no report into {self.out_dir}")
        return self.report_path

    def run(self, progress=None, poll: float = 0.2) -> str:
        """Start, wait (calling ``progress(done, 1000, status)`` now and then) and ``finish()``."""
        self.start()
        while not self.wait(poll):
            if progress is not None:
                progress(self.progress, 1000, self.status)
        return self.finish()
