"""A discrete PID controller driven by message stamps (seed 000 §3.2: "PID ... integrated with the
kinematic model of the Mecanum wheels"; seed 001 §III-D: PID keeping x at a set value and y at 0).

Time comes only from the ``t_ns`` argument (integer nanoseconds of the message stamp), never from
the wall clock, so a replay of the same messages produces bit-identical outputs.

Form::

    u = kp·e + I + D,            I ← clamp(I + ki·e·dt, ±integral_limit)
    D ← D + a·(kd·de/dt − D),    a = dt / (derivative_tau_s + dt)      (first-order low-pass)
    u ← clamp(u, ±output_limit)

* The derivative acts on the error. The follow controller's set-points (target distance, zero
  bearing) are constant, so this equals derivative-on-measurement (negated) and there is no
  set-point kick; the low-pass tames the pixel jitter of detector boxes.
* The first call after construction/``reset()`` has no previous error: it returns ``kp·e`` only
  (no derivative kick, nothing integrated because dt is unknown).
* Anti-windup: the integral term is clamped to ``±integral_limit`` (output units), and it is not
  grown further while the output is saturated in the direction the error pushes (conditional
  integration), so it unwinds as soon as the error changes sign.
* A stamp that does not advance (duplicate/out-of-order message) integrates nothing and keeps the
  previous derivative value.
"""

from __future__ import annotations

import logging
import math

log = logging.getLogger(__name__)


class PID:
    """PID controller; ``update(error, t_ns)`` returns the clamped control output."""

    def __init__(
        self,
        kp: float,
        ki: float = 0.0,
        kd: float = 0.0,
        output_limit: float = math.inf,
        integral_limit: float = math.inf,
        derivative_tau_s: float = 0.05,
    ) -> None:
        for name, value in (("kp", kp), ("ki", ki), ("kd", kd), ("derivative_tau_s", derivative_tau_s)):
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"PID {name} must be finite and >= 0, got {value!r}")
        for name, value in (("output_limit", output_limit), ("integral_limit", integral_limit)):
            if math.isnan(value) or value <= 0:
                raise ValueError(f"PID {name} must be > 0 (math.inf for none), got {value!r}")
        self.kp = float(kp)
        self.ki = float(ki)
        self.kd = float(kd)
        self.output_limit = float(output_limit)
        self.integral_limit = float(integral_limit)
        self.derivative_tau_s = float(derivative_tau_s)
        self.reset()

    def reset(self) -> None:
        """Forget all history (integral, previous error/stamp, filtered derivative)."""
        self.integral = 0.0
        self.derivative = 0.0
        self._prev_error: float | None = None
        self._prev_t_ns: int | None = None

    def update(self, error: float, t_ns: int, integrate: bool = True) -> float:
        """Advance the controller to ``t_ns`` with a new ``error``; return the clamped output.

        ``integrate=False`` freezes the integral for this step (e.g. while the target is only
        predicted, not observed).
        """
        error = float(error)
        if not math.isfinite(error):
            raise ValueError(f"PID error must be finite, got {error!r}")
        t_ns = int(t_ns)
        dt = 0.0
        if self._prev_t_ns is not None:
            dt = (t_ns - self._prev_t_ns) * 1e-9
            if dt <= 0.0:
                log.debug("PID: stamp %d does not advance past %d; not integrating", t_ns, self._prev_t_ns)
                dt = 0.0
        p = self.kp * error
        if dt > 0.0 and self._prev_error is not None:
            raw = self.kd * (error - self._prev_error) / dt
            alpha = dt / (self.derivative_tau_s + dt)
            self.derivative += alpha * (raw - self.derivative)
        if dt > 0.0 and integrate and self.ki > 0.0:
            unclamped = p + self.integral + self.derivative
            # Conditional integration: do not wind up further while saturated in the error's direction.
            saturated = abs(unclamped) >= self.output_limit and unclamped * error > 0.0
            if not saturated:
                limit = self.integral_limit
                self.integral = min(max(self.integral + self.ki * error * dt, -limit), limit)
        if dt > 0.0 or self._prev_t_ns is None:
            self._prev_t_ns = t_ns
            self._prev_error = error
        out = p + self.integral + self.derivative
        return min(max(out, -self.output_limit), self.output_limit)
