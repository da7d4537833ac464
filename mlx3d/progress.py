"""Progress reporting for long work on the command line.

Library functions take an optional ``progress(done, total)`` callable and call
it as work advances; ``ProgressLine`` is such a callable that prints a
throttled ``label: 42% (1.3 s)`` line to stderr. Ctrl+C cancels: the CLI turns
KeyboardInterrupt into exit code 130, and files are written atomically so a
cancelled run leaves no partial output.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from typing import Callable, Optional

ProgressFn = Optional[Callable[[int, int], None]]


class ProgressLine:
    """Callable ``(done, total)`` printing a progress line at most every ``interval`` seconds."""

    def __init__(self, label: str, stream=None, interval: float = 0.5):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval
        self.start = time.perf_counter()
        self._last = -1.0
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        finished = done >= total
        if not finished and now - self._last < self.interval:
            return
        self._last = now
        pct = 100.0 * done / total if total else 100.0
        text = f"{self.label}: {pct:5.1f}% ({now - self.start:.1f} s)"
        if self._tty:
            self.stream.write("\r" + text + ("\n" if finished else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


class StageProgressLine:
    """Callable ``(stage, done, total)`` for work in named stages: a :class:`ProgressLine` per stage,
    labelled ``PREFIX: STAGE`` (e.g. ``poses: matching: 42.0% (3.1 s)``)."""

    def __init__(self, prefix: str, stream=None):
        self.prefix, self.stream, self.line = prefix, stream, None

    def __call__(self, stage: str, done: int, total: int) -> None:
        label = f"{self.prefix}: {stage}"
        if self.line is None or self.line.label != label:
            self.line = ProgressLine(label, self.stream)
        self.line(done, total)


@contextmanager
def step(label: str, stream=None):
    """Print ``label ...`` then ``done in X s`` around a block of work."""
    out = stream if stream is not None else sys.stderr
    out.write(f"{label} ...\n")
    out.flush()
    t0 = time.perf_counter()
    yield
    out.write(f"{label}: done in {time.perf_counter() - t0:.2f} s\n")
    out.flush()
