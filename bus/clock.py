"""A node's clock (see :class:`Clock`)."""

from __future__ import annotations

import time


class Clock:
    """A node's clock: wall time; or the newest observed message stamp (lockstep replay); or simulated time
    (``sim``: the in-process runtime, bus.inproc, advances it; it stands for both wall and monotonic time).

    ``now_ns`` is the node clock; ``wall_ns`` and ``monotonic_ns`` are what a live node reads for receive
    times and ages (its watchdog): the real clocks, except in ``sim`` where the simulated time stands in.
    ``live`` is False only for ``stamps``: a simulated run behaves as a live one, on its own time.
    """

    MODES = ("wall", "stamps", "sim")

    def __init__(self, mode: str = "wall", start_ns: int = 0):
        if mode not in self.MODES:
            raise ValueError(f"clock must be one of {', '.join(self.MODES)}, not {mode!r}")
        self.mode = mode
        self._latest = 0
        self._sim_ns = start_ns

    @property
    def live(self) -> bool:
        return self.mode != "stamps"

    def observe(self, stamp_ns: int) -> None:
        self._latest = max(self._latest, stamp_ns)

    def advance_to(self, t_ns: int) -> None:
        """Simulated clock: move to ``t_ns`` (never back)."""
        self._sim_ns = max(self._sim_ns, t_ns)

    def now_ns(self) -> int:
        if self.mode == "sim":
            return self._sim_ns
        return time.time_ns() if self.mode == "wall" else self._latest

    def wall_ns(self) -> int:
        return self._sim_ns if self.mode == "sim" else time.time_ns()

    def monotonic_ns(self) -> int:
        return self._sim_ns if self.mode == "sim" else time.monotonic_ns()

