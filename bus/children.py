"""Child processes that never outlive the process that started them (a node, a replayed node, a load burner)."""

from __future__ import annotations

import contextlib
import ctypes
import signal
import subprocess
from collections.abc import Iterable

PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """For ``subprocess.Popen(preexec_fn=...)``: runs in the child between fork and exec; the kernel sends it
    SIGTERM when its parent ends, however the parent ends."""
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def interrupt_all(procs: Iterable[subprocess.Popen | None], timeout_s: float = 30.0) -> None:
    """Ctrl-C each process still running, in order (a launcher tears its nodes down on SIGINT); one that has not
    ended ``timeout_s`` later is killed."""
    for proc in procs:
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
