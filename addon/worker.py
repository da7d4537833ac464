"""Work a modal operator runs on a worker thread: ``WorkerJob``.

A subclass does its long, Blender-free part in ``work()`` (called on the worker
thread by ``start()``); the exception it raises, Ctrl+C and cancels included, is
kept in ``error`` for the main thread to report. ``cancel()`` sets the event
that ``work`` polls (``_cancel``); ``running`` and ``wait()`` follow the thread.
"""

from __future__ import annotations

import threading


class WorkerJob:
    """Base of the add-on's background jobs (see the module doc); ``thread_name`` names the thread."""

    thread_name = "mlx3d job"

    def __init__(self):
        self.error = None
        self._cancel = threading.Event()
        self._thread = None

    def work(self):
        raise NotImplementedError

    def _work(self):
        try:
            self.work()
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            self.error = exc

    def start(self) -> None:
        """Run ``work`` on a worker thread."""
        self._thread = threading.Thread(target=self._work, name=self.thread_name, daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def cancel(self) -> None:
        self._cancel.set()

    def wait(self, timeout=None) -> bool:
        """Wait for the worker thread; True when it has finished."""
        if self._thread is not None:
            self._thread.join(timeout)
        return not self.running
