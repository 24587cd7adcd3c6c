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

from drivers.safety.limits import (
    MAX_SOURCE_DURATION_S,
    LimitChecker,
    SetpointError,
    check_duration,
    check_joint_limits,
)

JOG_ANGLE_CHECK_STEP_COUNTS = 1000  # a jog is mapped to joint angles at least this often
JOG_ANGLE_CHECK_MAX_ROWS = 400


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
        if self.n_cycles_wanted is not None:
            check_duration("hold", self.n_cycles_wanted * period_s, period_s)

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.precheck(period_s)
        hold = np.asarray(actual_counts if self.counts is None else self.counts, dtype=np.int64)
        n = (
            self.n_cycles_wanted
            if self.n_cycles_wanted is not None
            else int(MAX_SOURCE_DURATION_S / period_s)
        )
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
        if not math.isfinite(velocity_counts_per_s) or not duration_s > 0 or not hold_s >= 0:
            raise SetpointError("jog: velocity must be finite, duration > 0 and hold >= 0")
        self.actuation = actuation
        self.motor = motor
        self.index = actuation.motor_ids.index(motor)
        self.velocity = float(velocity_counts_per_s)
        self.duration_s = float(duration_s)
        self.hold_s = float(hold_s)

    def precheck(self, period_s: float) -> None:
        """Speed within the motor's limit, travel within its range, duration within
        :data:`MAX_SOURCE_DURATION_S`, and the joint angles within the joint limits for a
        jog from the straight arm (:meth:`start` checks again from the actual positions).

        >>> from hrm_ctrl.ropes.actuation import load_actuation
        >>> from hrm_ctrl.model import default_robot
        >>> jog = JogSource(load_actuation(default_robot()), "j01r0", 1e7, 1.0)
        >>> jog.precheck(0.01)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        drivers.safety.limits.SetpointError: jog j01r0: 10000000 counts/s exceeds the motor's ...
        """
        i = self.index
        vmax = float(self.actuation.max_rate_counts_per_s[i])
        if abs(self.velocity) > vmax:
            raise SetpointError(
                f"jog {self.motor}: {self.velocity:.0f} counts/s exceeds the motor's "
                f"{vmax:.0f} counts/s"
            )
        check_duration(f"jog {self.motor}", self.duration_s + self.hold_s, period_s)
        span = int(self.actuation.counts_max[i]) - int(self.actuation.counts_min[i])
        if abs(self.velocity) * self.duration_s > span:
            raise SetpointError(
                f"jog {self.motor}: {abs(self.velocity) * self.duration_s:.0f} counts exceed the "
                f"motor's whole range of {span} counts"
            )
        n = len(self.actuation.motor_ids)
        rope_layer = getattr(self.actuation, "full", self.actuation)
        nj = int(rope_layer.robot.n_joints) if hasattr(rope_layer, "robot") else 12
        straight = np.asarray(
            self.actuation.counts_from_angles(np.zeros(nj), np.zeros(nj)), dtype=np.int64
        ).reshape(n)
        self._check_angles(straight, period_s, "from the straight arm")

    def _moved(self, actual_counts: np.ndarray, period_s: float) -> np.ndarray:
        n_move = max(1, round(self.duration_s / period_s))
        t = np.arange(1, n_move + 1, dtype=np.float64) * period_s
        return actual_counts[self.index] + np.rint(self.velocity * t).astype(np.int64)

    def _check_angles(self, actual_counts: np.ndarray, period_s: float, where: str) -> None:
        """Joint angles of the jog's rows (sampled every <= 1000 counts of travel, at most
        400 rows, first and last included) within the joint limits."""
        actual = np.asarray(actual_counts, dtype=np.int64)
        moved = self._moved(actual, period_s)
        travel = float(np.abs(moved - actual[self.index]).max())
        n = min(
            len(moved),
            max(2, math.ceil(travel / JOG_ANGLE_CHECK_STEP_COUNTS) + 1),
            JOG_ANGLE_CHECK_MAX_ROWS,
        )
        rows = np.unique(np.rint(np.linspace(0, len(moved) - 1, n)).astype(np.int64))
        table = np.repeat(actual[None, :], len(rows) + 1, axis=0)
        table[1:, self.index] = moved[rows]
        check_joint_limits(
            self.actuation, table, f"jog {self.motor} ({self.velocity:.0f} counts/s, {where})"
        )

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        check_duration(f"jog {self.motor}", self.duration_s + self.hold_s, period_s)
        actual = np.asarray(actual_counts, dtype=np.int64)
        n_hold = max(0, round(self.hold_s / period_s))
        moved = self._moved(actual, period_s)
        n_move = len(moved)
        table = np.repeat(actual[None, :], n_move + n_hold, 0)
        table[:n_move, self.index] = moved
        table[n_move:, self.index] = moved[-1]
        self.actuation.check_counts(table, previous=actual, dt_s=period_s)
        self._check_angles(actual, period_s, "from the actual positions")
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
        if not (math.isfinite(hold_s) and hold_s >= 0):
            raise SetpointError(f"{source}: hold must be >= 0 s, got {hold_s}")
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
        check_duration(f"{self.source} at {self.speed:g} mm/s", duration + self.hold_s, period_s)
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
