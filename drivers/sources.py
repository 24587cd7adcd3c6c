"""Setpoint sources for cyclic streaming: hold, jog, and a precomputed counts table
(plan playback: the console turns a plan into counts with the rope layer's
``hrm_ctrl.ropes.setpoints`` and hands the table to :class:`CountsSource`).

A source is started with the drives' actual positions (counts, the rope
layer's motor order) and the control period, then asked for the setpoint of
every control slot (``setpoint(k)``, k = 0, 1, ...); ``None`` ends the run.  Sources
precompute their whole table where they can and check it against the rope
layer's limits (:meth:`Actuation.check_counts`) *before* anything is sent, so
a bad plan is refused up front; the supervisor checks every setpoint again
before sending it.

>>> src = HoldSource(n_cycles=2)
>>> src.start(np.array([5, -5]), 0.01)
>>> [src.setpoint(k) for k in range(3)]
[array([ 5, -5]), array([ 5, -5]), None]
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from drivers.safety.limits import (
    MAX_SOURCE_DURATION_S,
    LimitChecker,
    SetpointError,
    check_duration,
    check_joint_limits,
)
from hrm_ctrl.errors import HrmError

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


LabelOfRow = Callable[[int], str] | Sequence[str]


def _row_name(label: LabelOfRow | None, row: int) -> str:
    if label is None:
        return f"row {row}"
    return label(row) if callable(label) else str(label[row])


def check_table(
    limits: LimitChecker,
    table: np.ndarray,
    period_s: float,
    name_of_row: Callable[[int], str],
    what: str,
    previous: np.ndarray | None = None,
) -> None:
    """``limits.check_counts`` of a (rows, motors) table at the control period, the first
    offending row named by ``name_of_row(row)`` (:class:`SetpointError`, one line).

    >>> class Lim:
    ...     counts_min = np.array([-10]); counts_max = np.array([10])
    ...     max_rate_counts_per_s = np.array([1e9]); motor_ids = ("m0",)
    ...     def check_counts(self, counts, previous=None, dt_s=None):
    ...         if np.any(np.abs(counts) > 10): raise SetpointError("m0 outside [-10, 10]")
    >>> check_table(Lim(), np.array([[0], [11]]), 0.01, lambda r: f"plan step {7 * r}", "plan")
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: plan: plan step 7: m0 outside [-10, 10]
    """
    try:
        limits.check_counts(table, previous=previous, dt_s=period_s)
        return
    except HrmError as exc:
        whole = exc
    lo = np.asarray(limits.counts_min)
    hi = np.asarray(limits.counts_max)
    out = np.flatnonzero(((table < lo) | (table > hi)).any(axis=1))
    seq = table if previous is None else np.vstack([np.asarray(previous)[None, :], table])
    rate = np.abs(np.diff(seq.astype(np.float64), axis=0)) / period_s
    fast = np.flatnonzero((rate > np.asarray(limits.max_rate_counts_per_s)).any(axis=1))
    first_fast = int(fast[0]) + (1 if previous is None else 0) if fast.size else table.shape[0]
    first_out = int(out[0]) if out.size else table.shape[0]
    r = min(first_out, first_fast)
    if r >= table.shape[0]:  # the checker refused for another reason: say so as it did
        raise SetpointError(f"{what}: {whole}") from None
    try:
        if r == first_out:
            limits.check_counts(table[r])
        else:
            prev = seq[r - 1] if previous is None else seq[r]
            limits.check_counts(table[r], previous=prev, dt_s=period_s)
    except HrmError as exc:
        raise SetpointError(f"{what}: {name_of_row(r)}: {exc}") from None
    raise SetpointError(f"{what}: {name_of_row(r)}: {whole}")


class CountsSource(TableSource):
    """Play a precomputed (cycles, motors) counts ``body`` made for the control period
    ``period_s``: a lead-in ramp from the actual positions to the body's first row (at
    no more than half of each motor's speed), the body, then ``hold_s`` of its last row.

    ``label`` names body rows in messages (a function of the row or one string per
    row, e.g. the plan step a row came from); ``info`` goes into :meth:`describe`.  The
    body is checked against every limit in :meth:`precheck`, and the whole table again,
    from the actual positions, in :meth:`start`.

    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> from hrm_ctrl.model import default_robot
    >>> act = load_actuation(default_robot())
    >>> body = np.repeat(np.arange(3)[:, None] * 100, act.n_motors, axis=1)
    >>> src = CountsSource(act, body, 0.01, name="plan", hold_s=0.02)
    >>> src.start(np.zeros(act.n_motors, dtype=np.int64), 0.01)
    >>> src.n_lead_in, src.n_cycles, src.table[:, 0].tolist()
    (0, 5, [0, 100, 200, 200, 200])
    """

    def __init__(
        self,
        limits: LimitChecker,
        body: np.ndarray,
        period_s: float,
        *,
        name: str = "counts",
        label: LabelOfRow | None = None,
        hold_s: float = 0.2,
        info: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.name = name
        if not (math.isfinite(hold_s) and hold_s >= 0):
            raise SetpointError(f"{name}: hold must be >= 0 s, got {hold_s}")
        if not (math.isfinite(period_s) and period_s > 0):
            raise SetpointError(f"{name}: control period must be > 0 s, got {period_s}")
        arr = np.asarray(body)
        n = len(limits.motor_ids)
        if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] != n or arr.dtype.kind not in "iu":
            raise SetpointError(
                f"{name}: counts must be an integer table (cycles >= 1, {n} motors), got "
                f"{arr.dtype} {arr.shape}"
            )
        if label is not None and not callable(label) and len(label) != arr.shape[0]:
            raise SetpointError(f"{name}: {len(label)} row labels for {arr.shape[0]} rows")
        self.limits = limits
        self.body = arr.astype(np.int64, copy=False)
        self.period_s = float(period_s)
        self.label = label
        self.hold_s = float(hold_s)
        self.info = dict(info or {})
        self.n_lead_in = 0
        self._checked = False

    def _row_name(self, row: int) -> str:
        """A row of the full table (lead-in, body, hold) as a message names it."""
        n_body = self.body.shape[0]
        if row < self.n_lead_in:
            return f"lead-in to {_row_name(self.label, 0)}"
        if row - self.n_lead_in >= n_body:
            return f"final hold at {_row_name(self.label, n_body - 1)}"
        return _row_name(self.label, row - self.n_lead_in)

    def _check_period(self, period_s: float) -> None:
        if abs(period_s - self.period_s) > 1e-9 * self.period_s:
            raise SetpointError(
                f"{self.name}: counts made for a {self.period_s:g} s control period, "
                f"the control period is {period_s:g} s"
            )

    def precheck(self, period_s: float) -> None:
        """The period the body was made for, the duration, and the body against every
        rope limit (the joint limits were the rope layer's to check when it was made)."""
        self._check_period(period_s)
        n_hold = round(self.hold_s / period_s)
        check_duration(self.name, (self.body.shape[0] + n_hold) * period_s, period_s)
        if not self._checked:
            check_table(
                self.limits,
                self.body,
                period_s,
                lambda r: _row_name(self.label, r),
                self.name,
            )
            self._checked = True

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.precheck(period_s)
        body = self.body
        actual = np.asarray(actual_counts, dtype=np.int64)
        lead = (
            ramp_table(actual, body[0], self.limits.max_rate_counts_per_s, period_s)
            if np.any(body[0] != actual)
            else np.zeros((0, actual.shape[0]), dtype=np.int64)
        )
        hold = np.repeat(body[-1:], max(0, round(self.hold_s / period_s)), axis=0)
        table = np.concatenate([lead, body, hold], axis=0)
        self.n_lead_in = int(lead.shape[0])
        check_table(self.limits, table, period_s, self._row_name, self.name, previous=actual)
        self.table = table

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            **self.info,
            "body_cycles": int(self.body.shape[0]),
            "lead_in_cycles": self.n_lead_in,
            "cycles": self.n_cycles,
        }
