"""Setpoint sources for cyclic streaming: hold, jog, and a precomputed counts table
(plan playback: the console turns a plan into counts with the rope layer's
``hrm_ctrl.ropes.setpoints`` and hands the table to :class:`CountsSource`).  The moves a
source makes itself (a lead-in from the actual positions, a jog, the stop of a table
that ends moving) are jerk-limited with Ruckig (:func:`move_table`, :func:`stop_table`),
within every motor's speed, acceleration and jerk limits, checked on the integers.

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
    accel_limits,
    acceleration_text,
    check_duration,
    check_joint_limits,
    first_too_hard,
    jerk_limits,
)
from hrm_ctrl.errors import HrmError

JOG_ANGLE_CHECK_STEP_COUNTS = 1000  # a jog is mapped to joint angles at least this often
JOG_ANGLE_CHECK_MAX_ROWS = 400
LEAD_IN_SPEED_FRACTION = 0.5  # a lead-in moves at no more than half of each motor's speed
MOVE_MARGIN = 0.95  # moves are planned for this share of the rounding-corrected limits
MOVE_RETRIES = 4  # a sampled move that still breaks a limit is planned again, slower
MOVE_SLOWDOWN = 0.8  # by this factor on its limits each time


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


def _move_limits(
    v_motor: np.ndarray, a_motor: np.ndarray, j_motor: np.ndarray, period_s: float,
    v_cap: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Limits a move is planned for, so that its rounded samples keep the motors' limits:
    a sampled speed is off by at most one count per period, a second difference by two."""
    v = MOVE_MARGIN * (np.asarray(v_motor, np.float64) - 1.0 / period_s)
    if v_cap is not None:
        v = np.minimum(v, np.asarray(v_cap, np.float64))
    a = MOVE_MARGIN * (np.asarray(a_motor, np.float64) - 2.0 / period_s**2)
    j = MOVE_MARGIN * np.asarray(j_motor, np.float64)
    if not ((v > 0).all() and (a > 0).all() and (j > 0).all()):
        raise SetpointError(
            f"move: speed, acceleration or jerk limits too small for whole counts at a "
            f"{period_s:g} s control period"
        )
    return v, a, j


def _calculate(inp: Any, n: int, what: str) -> Any:
    """Ruckig's offline trajectory for ``inp``; if the motors cannot all finish together
    (time synchronisation fails), each on its own.  A failure: one-line SetpointError."""
    from ruckig import Result, Ruckig, RuckigError, Synchronization, Trajectory

    for attempt in range(2):
        traj = Trajectory(n)
        try:
            result = Ruckig(n).calculate(inp, traj)
        except RuckigError as exc:
            result = str(exc).strip().splitlines()[0] if str(exc).strip() else "error"
        if result in (Result.Working, Result.Finished):
            return traj
        if attempt == 0:
            inp.synchronization = Synchronization.No
    raise SetpointError(f"{what}: no jerk-limited trajectory within the limits ({result})")


def _sample(trajectory: Any, n_rows: int, period_s: float, n: int) -> np.ndarray:
    """Positions of a ruckig trajectory at periods 1..n_rows (after the end: its end)."""
    out = np.empty((n_rows, n))
    end = float(trajectory.duration)
    for k in range(n_rows):
        out[k] = trajectory.at_time(min((k + 1) * period_s, end))[0]
    return out


def _within(
    rows: np.ndarray, start: np.ndarray, period_s: float, v_motor: np.ndarray,
    a_motor: np.ndarray, *, at_rest_after: bool,
) -> bool:  # fmt: skip
    """Rows after ``start`` (at rest) within the motors' speed and acceleration."""
    seq = np.concatenate([start[None], start[None], rows] + ([rows[-1:]] if at_rest_after else []))
    d1 = np.diff(seq, axis=0)
    d2 = np.diff(d1, axis=0)
    return bool(
        (np.abs(d1) <= v_motor * period_s).all() and (np.abs(d2) <= a_motor * period_s**2).all()
    )


def move_table(
    start: np.ndarray,
    end: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
    speed_cap_counts_per_s: np.ndarray | None = None,
) -> np.ndarray:
    """A jerk-limited move (Ruckig, time-synchronised, offline) from ``start`` at rest to
    ``end`` at rest: the counts of every control period after ``start``, the last one
    ``end``; every sampled, rounded speed and second difference within the motors'
    limits (checked; a move that breaks one is planned again, slower).  Each motor is
    also kept below ``speed_cap_counts_per_s`` (e.g. a jog's speed).

    >>> t = move_table(np.array([0, 0]), np.array([1000, -400]), 0.01, np.full(2, 4e5),
    ...                np.full(2, 2e6), np.full(2, 4e7))
    >>> t[-1].tolist(), len(t) <= 12, bool((np.abs(np.diff(t[:, 0], 2)) <= 200).all())
    ([1000, -400], True, True)
    """
    from ruckig import InputParameter

    start = np.asarray(start, dtype=np.int64)
    end = np.asarray(end, dtype=np.int64)
    n = start.shape[0]
    if np.array_equal(start, end):
        return np.zeros((0, n), dtype=np.int64)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    v, a, j = _move_limits(v_m, a_m, max_jerk_counts_per_s3, period_s, speed_cap_counts_per_s)
    delta = (end - start).astype(np.float64)
    scale = max(float(np.abs(delta).max()), 1.0)  # Ruckig works in units of the move
    for _ in range(MOVE_RETRIES + 1):
        inp = InputParameter(n)
        inp.current_position = [0.0] * n
        inp.current_velocity = [0.0] * n
        inp.current_acceleration = [0.0] * n
        inp.target_position = (delta / scale).tolist()
        inp.target_velocity = [0.0] * n
        inp.target_acceleration = [0.0] * n
        inp.max_velocity = (v / scale).tolist()
        inp.max_acceleration = (a / scale).tolist()
        inp.max_jerk = (j / scale).tolist()
        traj = _calculate(inp, n, "move")
        n_rows = max(1, math.ceil(float(traj.duration) / period_s - 1e-9))
        if n_rows * period_s > MAX_SOURCE_DURATION_S:
            raise SetpointError(f"move: {n_rows * period_s:.4g} s exceeds the longest run")
        rows = start + np.rint(_sample(traj, n_rows, period_s, n) * scale).astype(np.int64)
        rows[-1] = end
        if _within(rows, start, period_s, v_m, a_m, at_rest_after=True):
            return rows
        v, a, j = v * MOVE_SLOWDOWN, a * MOVE_SLOWDOWN**2, j * MOVE_SLOWDOWN**3
    raise SetpointError("move: no sampled trajectory within the motors' limits")


def stop_table(
    previous: np.ndarray,
    last: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
) -> np.ndarray:
    """A jerk-limited stop (Ruckig, velocity interface) of a table that ends moving: from
    ``last`` at the speed ``(last - previous) / T`` to rest, the counts of every period
    after ``last`` (empty when it is at rest already).

    >>> t = stop_table(np.array([0]), np.array([100]), 0.01, np.full(1, 4e5),
    ...                np.full(1, 2e6), np.full(1, 4e7))
    >>> bool(t[0, 0] > 100 and (np.diff(t[-3:, 0]) >= 0).all() and t[-1, 0] == t[-2, 0])
    True
    """
    from ruckig import ControlInterface, InputParameter, Synchronization

    last = np.asarray(last, dtype=np.int64)
    vel = (last - np.asarray(previous, dtype=np.int64)).astype(np.float64) / period_s
    n = last.shape[0]
    if not vel.any():
        return np.zeros((0, n), dtype=np.int64)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    v, a, j = _move_limits(v_m, a_m, max_jerk_counts_per_s3, period_s, None)
    v = np.maximum(v, np.abs(vel))  # the speed it has (within the motors' limit: checked)
    # Ruckig works in units of the stopping distance (at most this far)
    scale = max(float(np.max(np.abs(vel) * (np.abs(vel) / a + a / j))), 1.0)
    inp = InputParameter(n)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position = [0.0] * n
    inp.current_velocity = (vel / scale).tolist()
    inp.current_acceleration = [0.0] * n
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    inp.max_velocity = (v / scale).tolist()
    inp.max_acceleration = (a / scale).tolist()
    inp.max_jerk = (j / scale).tolist()
    inp.synchronization = Synchronization.No  # every motor stops as soon as it can
    traj = _calculate(inp, n, "stop")
    n_rows = max(1, math.ceil(float(traj.duration) / period_s - 1e-9)) + 1
    return last + np.rint(_sample(traj, n_rows, period_s, n) * scale).astype(np.int64)


class JogSource(TableSource):
    """Move one motor at a constant speed for a while, the others hold: ``velocity *
    duration`` counts, jerk-limited from rest to rest (:func:`move_table`), then
    ``hold_s`` of where it got to."""

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
        """The jogged motor's counts every period: a jerk-limited move (Ruckig) of
        ``velocity * duration_s`` counts at no more than the jog's speed, from rest to
        rest (so it takes a little longer than ``duration_s``)."""
        i = self.index
        start = int(actual_counts[i])
        end = start + round(self.velocity * self.duration_s)
        if end == start:
            return np.full(max(1, round(self.duration_s / period_s)), start, dtype=np.int64)
        lim = self.actuation
        rows = move_table(
            np.array([start]),
            np.array([end]),
            period_s,
            np.asarray(lim.max_rate_counts_per_s)[i : i + 1],
            np.asarray(accel_limits(lim))[i : i + 1],
            jerk_limits(lim)[i : i + 1],
            speed_cap_counts_per_s=np.array([abs(self.velocity)]),
        )
        return rows[:, 0]

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
        check_duration(f"jog {self.motor}", (n_move + n_hold) * period_s, period_s)
        table = np.repeat(actual[None, :], n_move + n_hold, 0)
        table[:n_move, self.index] = moved
        table[n_move:, self.index] = moved[-1]
        check_table(
            self.actuation, table, period_s, lambda r: f"row {r}", f"jog {self.motor}",
            previous=actual,
        )  # fmt: skip
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
    """``limits.check_counts`` of a (rows, motors) table at the control period, and every
    second difference within the motors' acceleration (from rest at ``previous`` when
    given: the drives hold it), the first offending row named by ``name_of_row(row)``
    (:class:`SetpointError`, one line).

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
    whole: HrmError | None = None
    try:
        limits.check_counts(table, previous=previous, dt_s=period_s)
    except HrmError as exc:
        whole = exc
    hard = first_too_hard(limits, table, period_s, previous)
    if whole is None and hard is None:
        return
    n = table.shape[0]
    lo = np.asarray(limits.counts_min)
    hi = np.asarray(limits.counts_max)
    out = np.flatnonzero(((table < lo) | (table > hi)).any(axis=1))
    seq = table if previous is None else np.vstack([np.asarray(previous)[None, :], table])
    rate = np.abs(np.diff(seq.astype(np.float64), axis=0)) / period_s
    fast = np.flatnonzero((rate > np.asarray(limits.max_rate_counts_per_s)).any(axis=1))
    first_fast = int(fast[0]) + (1 if previous is None else 0) if fast.size else n
    first_out = int(out[0]) if out.size else n
    first_hard = hard[0] if hard is not None else n
    r = min(first_out, first_fast, first_hard)
    if r >= n:  # the checker refused for another reason: say so as it did
        raise SetpointError(f"{what}: {whole}") from None
    if r not in (first_out, first_fast) and hard is not None:
        raise SetpointError(
            f"{what}: {name_of_row(r)}: {acceleration_text(limits, hard[1], hard[2])}"
        )
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
    ``period_s``: a lead-in from the actual positions to the body's first row (jerk-limited,
    from rest to rest, at no more than half of each motor's speed: :func:`move_table`),
    the body, a jerk-limited stop if the body ends moving (:func:`stop_table`), then
    ``hold_s`` of where it ended.

    ``label`` names body rows in messages (a function of the row or one string per
    row, e.g. the plan step a row came from); ``info`` goes into :meth:`describe`.  The
    body is checked against every limit in :meth:`precheck`, and the whole table again,
    from the actual positions, in :meth:`start`.

    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> from hrm_ctrl.model import default_robot
    >>> act = load_actuation(default_robot())
    >>> body = np.repeat(np.array([[0], [100], [200], [200]]), act.n_motors, axis=1)
    >>> src = CountsSource(act, body, 0.01, name="plan", hold_s=0.02)
    >>> src.start(np.zeros(act.n_motors, dtype=np.int64), 0.01)
    >>> src.n_lead_in, src.n_stop, src.n_cycles, src.table[:, 0].tolist()
    (0, 0, 6, [0, 100, 200, 200, 200, 200])
    >>> src.start(np.full(act.n_motors, -500, dtype=np.int64), 0.01)  # from elsewhere
    >>> src.n_lead_in > 0, int(src.table[src.n_lead_in - 1, 0])
    (True, 0)
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
        self.n_stop = 0
        self._checked = False

    def _row_name(self, row: int) -> str:
        """A row of the full table (lead-in, body, hold) as a message names it."""
        n_body = self.body.shape[0]
        if row < self.n_lead_in:
            return f"lead-in to {_row_name(self.label, 0)}"
        if row - self.n_lead_in >= n_body + self.n_stop:
            return f"final hold after {_row_name(self.label, n_body - 1)}"
        if row - self.n_lead_in >= n_body:
            return f"stop after {_row_name(self.label, n_body - 1)}"
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
        v = np.asarray(self.limits.max_rate_counts_per_s, dtype=np.float64)
        a = np.asarray(accel_limits(self.limits), dtype=np.float64)
        j = jerk_limits(self.limits)
        try:
            lead = move_table(
                actual,
                body[0],
                period_s,
                v,
                a,
                j,
                speed_cap_counts_per_s=LEAD_IN_SPEED_FRACTION * v,
            )
            # a body whose last change is more than holding it afterwards may take (one
            # cycle's acceleration) ends moving: it is stopped, jerk-limited
            moving = body.shape[0] > 1 and bool(
                np.any(np.abs(body[-1] - body[-2]) > a * period_s**2)
            )
            stop = (
                stop_table(body[-2], body[-1], period_s, v, a, j)
                if moving
                else np.zeros((0, actual.shape[0]), dtype=np.int64)
            )
        except SetpointError as exc:
            raise SetpointError(
                f"{self.name}: lead-in to {_row_name(self.label, 0)}: {exc}"
            ) from None
        end = stop[-1:] if stop.shape[0] else body[-1:]
        hold = np.repeat(end, max(0, round(self.hold_s / period_s)), axis=0)
        table = np.concatenate([lead, body, stop, hold], axis=0)
        self.n_lead_in = int(lead.shape[0])
        self.n_stop = int(stop.shape[0])
        check_table(self.limits, table, period_s, self._row_name, self.name, previous=actual)
        self.table = table

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            **self.info,
            "body_cycles": int(self.body.shape[0]),
            "lead_in_cycles": self.n_lead_in,
            "stop_cycles": self.n_stop,
            "cycles": self.n_cycles,
        }
