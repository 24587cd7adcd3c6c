"""Setpoint sources for cyclic streaming: hold, jog, plan playback.

A source is started with the drives' actual positions (counts, the rope
layer's motor order) and the control period, then asked for the setpoint of
every control slot (``setpoint(k)``, k = 0, 1, ...); ``None`` ends the run.  Sources
precompute their whole table where they can and check it against the rope
layer's limits (:meth:`Actuation.check_counts`) *before* anything is sent, so
a bad plan is refused up front; the scheduler checks every setpoint again
before sending it.

>>> src = HoldSource(n_cycles=2)
>>> src.start(np.array([5, -5]), 0.01)
>>> [src.setpoint(k) for k in range(3)]
[array([ 5, -5]), array([ 5, -5]), None]
"""

from __future__ import annotations

import math
from typing import Any, Protocol

import numpy as np

from hrm_ctrl.errors import DriverError


class SetpointError(DriverError):
    """A setpoint source cannot be built or started."""


class LimitChecker(Protocol):
    """What the sources need from the rope layer's ``Actuation``."""

    counts_min: np.ndarray
    counts_max: np.ndarray
    max_rate_counts_per_s: np.ndarray
    motor_ids: tuple[str, ...]

    def check_counts(
        self, counts: Any, previous: Any = None, dt_s: float | None = None
    ) -> None: ...

    def counts_from_angles(self, alpha: Any, theta: Any, tension_N: Any = None) -> np.ndarray: ...


class SetpointSource(Protocol):
    name: str

    def precheck(self, period_s: float) -> None: ...

    def start(self, actual_counts: np.ndarray, period_s: float) -> None: ...

    def setpoint(self, k: int) -> np.ndarray | None: ...

    def describe(self) -> dict[str, Any]: ...


class TableSource:
    """Setpoints from a precomputed (cycles, motors) table, after ``start``."""

    name = "table"

    def __init__(self) -> None:
        self.table: np.ndarray = np.zeros((0, 0), dtype=np.int64)

    def precheck(self, period_s: float) -> None:
        """Refuse what can be refused before the actual positions are known."""

    def setpoint(self, k: int) -> np.ndarray | None:
        if k >= self.table.shape[0]:
            return None
        return self.table[k]

    @property
    def n_cycles(self) -> int:
        return int(self.table.shape[0])

    def describe(self) -> dict[str, Any]:
        return {"source": self.name, "cycles": self.n_cycles}


class HoldSource(TableSource):
    """Hold the actual positions (or given counts) for ``n_cycles`` (None: 1 h)."""

    name = "hold"

    def __init__(self, n_cycles: int | None = None, counts: np.ndarray | None = None) -> None:
        super().__init__()
        self.n_cycles_wanted = n_cycles
        self.counts = None if counts is None else np.asarray(counts, dtype=np.int64)

    def precheck(self, period_s: float) -> None:
        if self.counts is not None and self.counts.ndim != 1:
            raise SetpointError("hold: counts must be one value per motor")

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        hold = np.asarray(actual_counts if self.counts is None else self.counts, dtype=np.int64)
        n = self.n_cycles_wanted if self.n_cycles_wanted is not None else int(3600 / period_s)
        self._hold = hold
        self._n = int(n)

    def setpoint(self, k: int) -> np.ndarray | None:
        return self._hold if k < self._n else None

    @property
    def n_cycles(self) -> int:
        return self._n


def ramp_table(
    start: np.ndarray,
    end: np.ndarray,
    max_rate_counts_per_s: np.ndarray,
    period_s: float,
    rate_fraction: float = 0.5,
) -> np.ndarray:
    """Linear ramp start -> end (excluding start, including end) at no more than
    ``rate_fraction`` of each motor's speed limit.

    >>> ramp_table(np.array([0, 0]), np.array([10, -4]), np.array([1000.0, 1000.0]), 0.01)
    array([[ 5, -2],
           [10, -4]])
    """
    start = np.asarray(start, dtype=np.int64)
    end = np.asarray(end, dtype=np.int64)
    delta = (end - start).astype(np.float64)
    step_max = np.asarray(max_rate_counts_per_s, dtype=np.float64) * rate_fraction * period_s
    n = int(max(1, math.ceil(float(np.max(np.abs(delta) / np.maximum(step_max, 1e-9))))))
    frac = np.arange(1, n + 1, dtype=np.float64)[:, None] / n
    return (start[None, :] + np.rint(frac * delta[None, :])).astype(np.int64)


class JogSource(TableSource):
    """Move one motor at a constant speed for a while, the others hold."""

    name = "jog"

    def __init__(
        self,
        actuation: LimitChecker,
        motor: str,
        velocity_counts_per_s: float,
        duration_s: float,
        hold_s: float = 0.1,
    ) -> None:
        super().__init__()
        if motor not in actuation.motor_ids:
            raise SetpointError(f"jog: unknown rope motor '{motor}'")
        if not math.isfinite(velocity_counts_per_s) or not duration_s > 0:
            raise SetpointError("jog: velocity must be finite and duration > 0")
        self.actuation = actuation
        self.motor = motor
        self.index = actuation.motor_ids.index(motor)
        self.velocity = float(velocity_counts_per_s)
        self.duration_s = float(duration_s)
        self.hold_s = float(hold_s)

    def precheck(self, period_s: float) -> None:
        """Speed within the motor's limit and travel within its range.

        >>> from hrm_ctrl.actuation import load_actuation
        >>> from hrm_ctrl.model import default_robot
        >>> jog = JogSource(load_actuation(default_robot()), "j01r0", 1e7, 1.0)
        >>> jog.precheck(0.01)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        drivers.setpoints.SetpointError: jog j01r0: 10000000 counts/s exceeds the motor's ...
        """
        i = self.index
        vmax = float(self.actuation.max_rate_counts_per_s[i])
        if abs(self.velocity) > vmax:
            raise SetpointError(
                f"jog {self.motor}: {self.velocity:.0f} counts/s exceeds the motor's "
                f"{vmax:.0f} counts/s"
            )
        span = int(self.actuation.counts_max[i]) - int(self.actuation.counts_min[i])
        if abs(self.velocity) * self.duration_s > span:
            raise SetpointError(
                f"jog {self.motor}: {abs(self.velocity) * self.duration_s:.0f} counts exceed the "
                f"motor's whole range of {span} counts"
            )

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        n_move = max(1, round(self.duration_s / period_s))
        n_hold = max(0, round(self.hold_s / period_s))
        t = np.arange(1, n_move + 1, dtype=np.float64) * period_s
        table = np.repeat(np.asarray(actual_counts, dtype=np.int64)[None, :], n_move + n_hold, 0)
        moved = actual_counts[self.index] + np.rint(self.velocity * t).astype(np.int64)
        table[:n_move, self.index] = moved
        table[n_move:, self.index] = moved[-1]
        self.actuation.check_counts(table, previous=actual_counts, dt_s=period_s)
        self.table = table

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            "motor": self.motor,
            "velocity_counts_per_s": self.velocity,
            "duration_s": self.duration_s,
            "cycles": self.n_cycles,
        }


def interpolate_rows(t_query: np.ndarray, t_knots: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation of every column of ``rows`` (knots, m) at ``t_query``.

    >>> interpolate_rows(np.array([0.0, 0.5, 2.0]), np.array([0.0, 1.0]),
    ...                  np.array([[0.0, 10.0], [1.0, 20.0]]))
    array([[ 0. , 10. ],
           [ 0.5, 15. ],
           [ 1. , 20. ]])
    """
    tq = np.clip(t_query, t_knots[0], t_knots[-1])
    i = np.clip(np.searchsorted(t_knots, tq, side="right") - 1, 0, len(t_knots) - 2)
    span = t_knots[i + 1] - t_knots[i]
    w = np.where(span > 0, (tq - t_knots[i]) / np.where(span > 0, span, 1.0), 1.0)
    return rows[i] + w[:, None] * (rows[i + 1] - rows[i])


class PlanSource(TableSource):
    """Play an ``hrm-plan/1`` plan: steps at their travel (mm) along the path, at
    ``speed_mm_per_s``, interpolated in joint angles at the control rate and turned
    into counts by the rope layer; a lead-in ramp from the actual positions to the
    plan's first setpoint and a short hold at the end."""

    name = "plan"

    def __init__(
        self,
        actuation: LimitChecker,
        plan: dict[str, Any],
        speed_mm_per_s: float = 20.0,
        hold_s: float = 0.2,
        source: str = "plan",
    ) -> None:
        super().__init__()
        if not (math.isfinite(speed_mm_per_s) and speed_mm_per_s > 0):
            raise SetpointError(f"{source}: speed must be > 0 mm/s, got {speed_mm_per_s}")
        steps = plan.get("steps") or []
        if not steps:
            raise SetpointError(f"{source}: plan has no steps")
        self.actuation = actuation
        self.source = source
        self.speed = float(speed_mm_per_s)
        self.hold_s = float(hold_s)
        travel = np.array([float(s["travel_mm"]) for s in steps])
        self.alpha = np.array([s["alpha_rad"] for s in steps], dtype=np.float64)
        self.theta = np.array([s["theta_rad"] for s in steps], dtype=np.float64)
        travel = np.maximum.accumulate(travel - travel[0])
        self.t_knots = travel / self.speed
        if len(steps) == 1:
            self.t_knots = np.array([0.0, 0.0])
            self.alpha = np.repeat(self.alpha, 2, axis=0)
            self.theta = np.repeat(self.theta, 2, axis=0)
        self.n_steps = len(steps)
        self.n_lead_in = 0

    def plan_table(self, period_s: float) -> np.ndarray:
        """(cycles, motors) counts of the plan itself, checked against every limit."""
        duration = float(self.t_knots[-1])
        n = math.floor(duration / period_s + 1e-9) + 1
        t = np.arange(n, dtype=np.float64) * period_s
        if t[-1] < duration:
            t = np.append(t, duration)
        angles = interpolate_rows(t, self.t_knots, np.hstack([self.alpha, self.theta]))
        k = self.alpha.shape[1]
        counts = np.asarray(
            self.actuation.counts_from_angles(angles[:, :k], angles[:, k:]), dtype=np.int64
        )
        self.actuation.check_counts(counts, dt_s=period_s)
        return counts

    def precheck(self, period_s: float) -> None:
        """The whole plan against every rope and joint limit."""
        self.plan_table(period_s)

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        body = self.plan_table(period_s)
        actual = np.asarray(actual_counts, dtype=np.int64)
        lead = (
            ramp_table(actual, body[0], self.actuation.max_rate_counts_per_s, period_s)
            if np.any(body[0] != actual)
            else np.zeros((0, actual.shape[0]), dtype=np.int64)
        )
        hold = np.repeat(body[-1:], max(0, round(self.hold_s / period_s)), axis=0)
        table = np.concatenate([lead, body, hold], axis=0)
        self.actuation.check_counts(table, previous=actual, dt_s=period_s)
        self.n_lead_in = int(lead.shape[0])
        self.table = table

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            "plan": self.source,
            "steps": self.n_steps,
            "speed_mm_per_s": self.speed,
            "duration_s": float(self.t_knots[-1]),
            "lead_in_cycles": self.n_lead_in,
            "cycles": self.n_cycles,
        }
