"""Whether a node is working, not just alive: retry budgets for failing hooks and a source's production watch.

A node's process can be up, its liveliness token declared, and still do nothing useful: a source whose
``poll`` raises and is never polled again publishes nothing for good after one failed camera read, while every
table says "up". The runtime (bus/node_host.py) uses these two pieces so that a failing hook is retried
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
STALL_SHOWN_PERIODS = 10  # node tables show a source "stalled" after this many of its periods of silence ...
STALL_SHOWN_MIN_S = 1.0  # ... and at least this long: well before it is restarted


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

    def shown_bound_s(self) -> float:
        """The silence after which node tables show the source stalled (before :meth:`bound_s` restarts it)."""
        if math.isnan(self.period_s):
            return STALL_SHOWN_MIN_S
        return max(STALL_SHOWN_MIN_S, STALL_SHOWN_PERIODS * self.period_s)

    def silent_s(self, now_s: float) -> float | None:
        if self.last_s is None:
            return None
        silent = now_s - self.last_s
        return silent if silent > self.bound_s() else None


# What a source's status says of it (NodeStatus extra["source"]), and node tables show (bus/health.py node_state).
SOURCE_PRODUCING = "producing"
SOURCE_STALLED = "stalled"  # polled, but silent past its production bound (or stuck that long in one poll)
SOURCE_FINISHED = "finished"  # its poll said "never again": every frame of its source was published


class SourceActivity:
    """Whether a node is a source (its poll asks to be called again) and, for one, what it is doing: a source that
    publishes nothing must not look like one that works, whether its poll keeps returning, blocks (a camera read
    that never returns) or it has not published since it started."""

    def __init__(self) -> None:
        self.is_source = False
        self.polling = False
        self.expected_since_s: float | None = None  # since when it should publish (its first poll, or a hold's end)
        self.poll_since_s: float | None = None  # when the poll running now started

    def poll_started(self, now_s: float) -> None:
        self.poll_since_s = now_s
        if self.expected_since_s is None:
            self.expected_since_s = now_s

    def poll_ended(self, delay_s: float | None, now_s: float, holding: bool = False) -> None:
        """After a poll that returned ``delay_s``; ``holding``: the source holds its first publication on purpose
        (capture waits for its consumers), so its silence counts from when it stops holding."""
        self.poll_since_s = None
        self.polling = delay_s is not None
        self.is_source = self.is_source or self.polling
        if holding:
            self.expected_since_s = now_s

    def state(self, watch: ProductionWatch, now_s: float) -> str | None:
        """SOURCE_PRODUCING, SOURCE_STALLED or SOURCE_FINISHED; None for a node that is no source."""
        if not self.is_source:
            return None
        if not self.polling and self.poll_since_s is None:
            return SOURCE_FINISHED
        bound_s = watch.shown_bound_s()
        silent_since = watch.last_s if watch.last_s is not None else self.expected_since_s
        stuck = self.poll_since_s is not None and now_s - self.poll_since_s > bound_s
        if stuck or (silent_since is not None and now_s - silent_since > bound_s):
            return SOURCE_STALLED
        return SOURCE_PRODUCING
