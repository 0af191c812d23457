"""Work a node does after its output is out, on a worker thread below the loop's CPU priority.

A node that publishes first and then does bookkeeping (a model's training step, a file write) still spends that
CPU at its own priority, beside the loop's other nodes: on a two-core computer a 20-30 ms burst every few frames
is enough to make the detector skip frames. ``BackgroundJob`` runs such work on a thread ``nice_increment``
steps nicer than the node, so it takes CPU the loop leaves idle.

The order of results stays the one a synchronous call gives: ``wait()`` (called by ``submit`` and by the node
before its next step) returns only once the job is done; while the node waits, the worker is raised back to the
node's priority where the system permits it (lowering a nice value needs root or CAP_SYS_NICE), so a loaded
machine does not keep the node waiting on its own low-priority work.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

NICEST = 19


def _set_thread_nice(tid: int, nice: int) -> bool:
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)  # Linux: a thread id is a task of its own
        return True
    except (PermissionError, OSError):
        return False


class BackgroundJob:
    """One job at a time on a daemon thread at the node's nice + ``nice_increment``."""

    def __init__(self, name: str, nice_increment: int = 10) -> None:
        self.name = name
        self.nice_increment = int(nice_increment)
        self._job: Callable[[], None] | None = None
        self._error: BaseException | None = None
        self._busy = False
        self._boosted = False  # raised to the node's priority while the node waits on this job
        self._cond = threading.Condition()
        self._node_nice = os.getpriority(os.PRIO_PROCESS, 0)
        self._tid: int | None = None
        self._thread = threading.Thread(target=self._run, name=f"{name}-background", daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None]) -> None:
        """Run ``job`` in the background once the previous one is done (its error, if any, is raised here)."""
        self.wait()
        with self._cond:
            self._job, self._busy = job, True
            self._cond.notify_all()

    def wait(self) -> None:
        """Return when no job is running; re-raise the last job's exception."""
        with self._cond:
            if self._busy and self._tid is not None and not self._boosted:
                self._boosted = _set_thread_nice(self._tid, self._node_nice)  # the node now waits on it
            while self._busy:
                self._cond.wait()
            error, self._error = self._error, None
        if error is not None:
            raise error

    def _run(self) -> None:
        self._tid = threading.get_native_id()
        low = min(self._node_nice + self.nice_increment, NICEST)
        while True:
            with self._cond:
                while self._job is None:
                    self._cond.wait()
                job, self._job = self._job, None
                if not self._boosted:
                    _set_thread_nice(self._tid, low)
            try:
                job()
            except BaseException as exc:  # handed to the node's thread by wait()
                with self._cond:
                    self._error = exc
            with self._cond:
                self._busy = self._boosted = False
                self._cond.notify_all()
