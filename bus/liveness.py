"""Whether a node is working, not just alive: retry budgets for failing hooks and a source's production watch.

A node's process can be up, its liveliness token declared, and still do nothing useful: a source whose
``poll`` raised was never polled again (one failed camera read and capture published nothing for good while
every table said "up"). The runtime (bus/node.py) uses these two pieces so that a failing hook is retried
with backoff, a node that keeps failing exits with :data:`STOPPED_WORKING_EXIT` (the launcher restarts it
and reports it), and a source that has published nothing for many of its own periods does the same.
"""

from __future__ import annotations

import math

# The exit status of a node that stopped working (hooks failing past their bound, or a silent source): the
# launcher restarts it by its restart policy and `launch --duration` reports it (tools/launch.py).
STOPPED_WORKING_EXIT = 75  # EX_TEMPFAIL: "try again" (3 is the diagnostics ticker's injected failure)
POLL_FAILURE_LIMIT = 6  # consecutive poll failures (backoff 0.05, 0.1, ... 0.8 s: ~1.6 s in all) before exiting
HANDLER_FAILURE_LIMIT = 200  # consecutive handler failures (on_message/on_frame/on_timer) before exiting
STALL_PERIODS = 50  # a source silent for this many of its own publication periods has stopped producing ...
STALL_MIN_S = 5.0  # ... and for at least this long (a consumer restarting, a pace that waits for acks)


class NodeStoppedWorking(RuntimeError):
    """Raised out of the run loop: the node must exit with STOPPED_WORKING_EXIT."""


class FailureBudget:
    """Consecutive failures of one hook: the backoff before the next try, and whether the bound is passed."""

    def __init__(self, limit: int, first_backoff_s: float = 0.05, max_backoff_s: float = 1.0):
        self.limit = limit
        self.first_backoff_s = first_backoff_s
        self.max_backoff_s = max_backoff_s
        self.streak = 0

    def failed(self) -> float:
        """Count a failure; the seconds to wait before trying again (doubling, capped)."""
        self.streak += 1
        return min(self.first_backoff_s * 2 ** (self.streak - 1), self.max_backoff_s)

    def succeeded(self) -> None:
        self.streak = 0

    @property
    def exhausted(self) -> bool:
        return self.streak >= self.limit


class ProductionWatch:
    """When a source last published, against its own period (a smoothed interval between publications).

    Armed by the first publication (a source may legitimately wait before it, e.g. for its consumers);
    :meth:`silent_s` is the silence when it exceeds ``periods`` periods and ``min_s``, else None."""

    def __init__(self, periods: int = STALL_PERIODS, min_s: float = STALL_MIN_S):
        self.periods = periods
        self.min_s = min_s
        self.last_s: float | None = None
        self.period_s = math.nan
        self.count = 0

    def published(self, now_s: float) -> None:
        if self.last_s is not None:
            gap = now_s - self.last_s
            self.period_s = gap if math.isnan(self.period_s) else 0.9 * self.period_s + 0.1 * gap
        self.last_s = now_s
        self.count += 1

    def bound_s(self) -> float:
        return max(self.min_s, self.periods * self.period_s) if not math.isnan(self.period_s) else self.min_s

    def silent_s(self, now_s: float) -> float | None:
        if self.last_s is None:
            return None
        silent = now_s - self.last_s
        return silent if silent > self.bound_s() else None
