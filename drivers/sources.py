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
from enum import Enum
from typing import Any, Protocol

import numpy as np

from drivers.safety.limits import (
    MAX_SOURCE_DURATION_S,
    LimitChecker,
    SetpointError,
    accel_limits,
    acceleration_text,
    check_duration,
    check_move,
    first_too_hard,
    jerk_limits,
    maps_joints,
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

    @property
    def n_cycles(self) -> int: ...  # cycles at most (the session's wait for the end)


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


def at_samples(x: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """``samples`` (K + 1, m) interpolated linearly at fractional sample indices ``x``.

    >>> at_samples(np.array([0.0, 0.5, 2.0]), np.array([[0.0], [10.0], [30.0]])).ravel()
    array([ 0.,  5., 30.])
    """
    pts = np.asarray(samples, dtype=np.float64)
    k_steps = pts.shape[0] - 1
    i = np.clip(np.asarray(x).astype(np.int64), 0, max(k_steps - 1, 0))
    w = (np.asarray(x) - i)[:, None]
    if k_steps == 0:
        return np.repeat(pts, len(i), axis=0)
    return pts[i] + w * (pts[i + 1] - pts[i])


def path_move(
    samples: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
    speed_cap_counts_per_s: np.ndarray | None = None,
    what: str = "move",
) -> tuple[np.ndarray, np.ndarray]:
    """A jerk-limited move along a path in counts, from rest at its first sample to rest
    at its last: ``samples`` (K + 1, motors) at equal steps of the path parameter ``s``
    in [0, 1], linear between samples (e.g. the rope layer's ``Actuation.joint_line``).
    ``s`` is timed by Ruckig within ``D_m ds/dt <= v_m``, ``D_m d2s/dt2 <= a_m`` and
    ``D_m d3s/dt3 <= j_m`` for every motor (``D_m`` its largest ``|dc_m/ds|``).  Returns
    the counts of every control period after the first sample, the last one the last
    sample, and where each row is along the path (its fractional sample index, 0 .. K:
    what else was sampled along it, e.g. a joint line's poses, :func:`at_samples`); each
    sampled, rounded speed and second difference checked against the motors' limits (a
    move that breaks one is timed again, slower).

    >>> line = np.linspace(0.0, 1.0, 9)[:, None] * np.array([[1000.0, -400.0]])
    >>> t, x = path_move(line, 0.01, np.full(2, 4e5), np.full(2, 2e6), np.full(2, 4e7))
    >>> t[-1].tolist(), bool((np.abs(np.diff(t[:, 0], 2)) <= 200).all()), float(x[-1])
    ([1000, -400], True, 8.0)
    """
    from ruckig import InputParameter

    pts = np.asarray(samples, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] < 2 or not np.isfinite(pts).all():
        raise SetpointError(f"{what}: a path needs 2 or more finite samples, got {pts.shape}")
    k_steps = pts.shape[0] - 1
    start = np.rint(pts[0]).astype(np.int64)
    end = np.rint(pts[-1]).astype(np.int64)
    slope = np.abs(np.diff(pts, axis=0)).max(axis=0) * k_steps  # D_m, counts per unit s
    moving = slope > 0.0
    if not moving.any():
        return np.zeros((0, pts.shape[1]), dtype=np.int64), np.zeros(0)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    v, a, j = _move_limits(v_m, a_m, max_jerk_counts_per_s3, period_s, speed_cap_counts_per_s)
    v_s = float((v[moving] / slope[moving]).min())
    a_s = float((a[moving] / slope[moving]).min())
    j_s = float((j[moving] / slope[moving]).min())
    for _ in range(MOVE_RETRIES + 1):
        inp = InputParameter(1)
        inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
        inp.target_position, inp.target_velocity, inp.target_acceleration = [1.0], [0.0], [0.0]
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v_s], [a_s], [j_s]
        traj = _calculate(inp, 1, what)
        n_rows = max(1, math.ceil(float(traj.duration) / period_s - 1e-9))
        if n_rows * period_s > MAX_SOURCE_DURATION_S:
            raise SetpointError(f"{what}: {n_rows * period_s:.4g} s exceeds the longest run")
        x = np.clip(_sample(traj, n_rows, period_s, 1)[:, 0], 0.0, 1.0) * k_steps
        x[-1] = k_steps
        rows = np.rint(at_samples(x, pts)).astype(np.int64)
        rows[-1] = end
        if _within(rows, start, period_s, v_m, a_m, at_rest_after=True):
            return rows, x
        v_s, a_s, j_s = v_s * MOVE_SLOWDOWN, a_s * MOVE_SLOWDOWN**2, j_s * MOVE_SLOWDOWN**3
    raise SetpointError(f"{what}: no sampled trajectory within the motors' limits")


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
        label: str | None = None,
    ) -> None:
        super().__init__()
        self.label = label  # names the jog in messages (default: motor and speed)
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
        if self.label:
            what = f"{self.label} ({where})"
        else:
            what = f"jog {self.motor} ({self.velocity:.0f} counts/s, {where})"
        pose_of = getattr(self.actuation, "pose_of_counts", None)
        warm = None
        if pose_of is not None:  # the inverse starts where the arm is (not cold: corners)
            try:
                warm = pose_of(actual, "where the arm is")
            except HrmError as exc:
                raise SetpointError(f"{what}: {exc}") from None
        check_move(self.actuation, table, what, warm=warm)

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
            self.actuation, table, period_s, lambda r: f"cycle {r} ({r * period_s:.2f} s)",
            f"jog {self.motor}",
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
    """A body row as a message names it: by its label (a plan step), else as the control
    cycle of the table it is."""
    if label is None:
        return f"cycle {row}"
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
    from rest to rest, at no more than half of each motor's speed; with the whole rope
    layer a straight line in the joint angles, ``Actuation.joint_line`` timed by
    :func:`path_move`, else in counts, :func:`move_table`), the body, a jerk-limited stop
    if the body ends moving (:func:`stop_table`), then ``hold_s`` of where it ended.  The
    lead-in and the stop are checked by the rope model (:func:`check_move`).

    ``label`` names body rows in messages (a function of the row or one string per
    row, e.g. the plan step a row came from); ``info`` goes into :meth:`describe`;
    ``first_pose`` (alpha, theta), the configuration the first row was made from (a
    plan's first step), is where the lead-in goes (else the rope inverse's of the row).  The
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
        first_pose: tuple[Any, Any] | None = None,
    ) -> None:
        super().__init__()
        self.name = name
        self.first_pose = first_pose
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

    @classmethod
    def of_plan(
        cls, limits: LimitChecker, setpoints: Any, *, name: str = "plan", **kw: Any
    ) -> CountsSource:
        """The source of a plan's counts (the rope layer's ``PlanSetpoints``: its counts,
        control period, row labels, and its first step's configuration for the lead-in to
        go to).  ``kw`` as for the constructor (``hold_s``, ``info``)."""
        first = (setpoints.alpha_rad[0], setpoints.theta_rad[0])
        return cls(limits, setpoints.counts, setpoints.period_s, name=name,
                   label=setpoints.label, first_pose=first, **kw)  # fmt: skip

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
        cap = LEAD_IN_SPEED_FRACTION * v
        lead_poses = None  # the configurations of the lead-in rows, where known
        try:
            if np.array_equal(actual, body[0]):  # the drives hold the first row already
                lead = np.zeros((0, actual.shape[0]), dtype=np.int64)
            elif (line_of := getattr(self.limits, "joint_line", None)) is not None:
                # the whole rope layer: a line in joint space
                line = line_of(actual, body[0], to_pose=self.first_pose)
                lead, x = path_move(line.counts, period_s, v, a, j, cap, "lead-in")
                lead_poses = (
                    np.vstack([line.alpha[:1], at_samples(x, line.alpha)]),
                    np.vstack([line.theta[:1], at_samples(x, line.theta)]),
                )
            else:  # a motor subset: the other ropes are not moved, no pose to go by
                lead = move_table(actual, body[0], period_s, v, a, j, speed_cap_counts_per_s=cap)
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
        except HrmError as exc:  # SetpointError, or the rope layer's RopeLimitError
            raise SetpointError(
                f"{self.name}: lead-in to {_row_name(self.label, 0)}: {exc}"
            ) from None
        # the arm on the way, by the rope model: the joint limits, and (the whole arm) the
        # rope tensions, which a line in counts (a subset's lead-in, the stop) can strain
        if maps_joints(self.limits):
            last = _row_name(self.label, body.shape[0] - 1)
            parts = (
                (actual, lead, lead_poses, f"lead-in to {_row_name(self.label, 0)}"),
                (body[-1], stop, None, f"stop after {last}"),
            )
            for before, part, poses, what in parts:
                if part.shape[0]:
                    table = np.vstack([before, part])
                    check_move(self.limits, table, f"{self.name}: {what}", poses)
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


# ---------------------------------------------------------------- pause / resume / abort
PAUSE_RAMP_S = 0.5  # a pause or a resume changes the playback rate by 1 in about this long
MAX_PAUSE_S = 600.0  # a run paused longer in all than this is aborted (at rest: at once)
MAX_PLAYED_ROWS = 360_000  # setpoints a pausable source keeps for a way back (1 h at 100 Hz)
MAX_OFF_PATH_COUNTS = 2.0  # a setpoint may leave the interpolated path by this much (rounding)


class PlayState(Enum):
    """Where a :class:`PausableSource` is (its operator's view)."""

    PLAYING = "playing"
    PAUSING = "pausing"
    PAUSED = "paused"
    RESUMING = "resuming"
    ABORTING = "aborting"
    ABORTED = "aborted"
    DONE = "done"


class PausableSource:
    """A table source (e.g. :class:`CountsSource`) played at a variable rate along its
    own path, so that the operator can pause, resume and abort it: :meth:`pause` slows
    the playback down to rest (the arm stops *on the path*, every rope consistent),
    :meth:`resume` speeds it up again, :meth:`abort` stops it on the path and then ends
    the stream.  Thread-safe: the requests come from another thread than the control
    loop's (keyboard, console); each is one assignment the loop reads.

    Every cycle the playback position ``s`` (a fractional row of the inner table)
    advances by the rate ``r`` (rows per cycle, about 0..1) and the setpoint is the table
    linearly interpolated at ``s``, rounded, and kept within the window of setpoints the
    supervisor accepts (speed from the last setpoint, second difference against the
    acceleration limit, in its own terms) by at most :data:`MAX_OFF_PATH_COUNTS` (the
    rounding of a table that brakes at a motor's limit).  The rate moves toward its target
    by at most ``period_s / ramp_s`` a cycle, by less (or not at all that cycle) where
    that would leave the path further, so a pause waits for a point of the table that
    lets it slow down.  At rate 1 on whole rows the setpoints are the inner table's rows.

    >>> class Lim:
    ...     motor_ids = ("m0",); max_rate_counts_per_s = np.array([1e4])
    ...     max_accel_counts_per_s2 = np.array([1e6]); counts_min = np.array([-10**6])
    ...     counts_max = np.array([10**6])
    ...     def check_counts(self, counts, previous=None, dt_s=None): pass
    >>> body = np.arange(0, 2001, 20).reshape(-1, 1)  # 20 counts a cycle
    >>> src = PausableSource(CountsSource(Lim(), body, 0.01, hold_s=0.0), Lim(), ramp_s=0.1)
    >>> src.start(np.array([0]), 0.01)
    >>> out = [src.setpoint(k) for k in range(30)]
    >>> src.pause()
    >>> out += [src.setpoint(k) for k in range(30, 80)]
    >>> src.state.value, int(out[-1][0]) == int(out[-2][0])
    ('paused', True)
    >>> src.resume()
    >>> k = 80
    >>> while (p := src.setpoint(k)) is not None: out.append(p); k += 1
    >>> src.state.value, int(out[-1][0])
    ('done', 2000)
    >>> d2 = np.diff(np.array([[0], [0]] + out)[:, 0], 2)
    >>> bool((np.abs(d2) <= 1e6 * 0.01**2).all())
    True
    """

    name = "pausable"

    def __init__(
        self,
        inner: TableSource,
        limits: LimitChecker,
        *,
        ramp_s: float = PAUSE_RAMP_S,
        max_pause_s: float = MAX_PAUSE_S,
    ) -> None:
        if not (math.isfinite(ramp_s) and ramp_s > 0):
            raise SetpointError(f"pause ramp must be > 0 s, got {ramp_s}")
        if not (math.isfinite(max_pause_s) and max_pause_s >= 0):
            raise SetpointError(f"longest pause must be >= 0 s, got {max_pause_s}")
        self.max_pause_s = float(max_pause_s)
        self.paused_cycles = 0
        self.abort_reason: str | None = None
        self.inner = inner
        self.name = inner.name
        self.limits = limits
        self.ramp_s = float(ramp_s)
        self._target = 1.0
        self._abort = False
        self.state = PlayState.PLAYING
        self.position = 0.0  # fractional row of the inner table (read by the console)
        self.rate = 1.0
        self.held_cycles = 0  # cycles the rate could not move toward its target
        self._table = np.zeros((0, 0), dtype=np.int64)
        self._k = -1
        self._out: np.ndarray | None = None
        self._played: list[np.ndarray] = []
        self.played_complete = True  # False: more than MAX_PLAYED_ROWS, no way back kept

    # the operator's requests (any thread)
    # The requests only set the target rate (and the abort flag, set before the target:
    # the loop never sees a target of 0 from an abort without the flag); the loop's thread
    # alone writes ``state``, from the target and where the playback is.
    def pause(self) -> None:
        """Slow down to rest on the path (no-op once aborting or done)."""
        if not self._abort and self.state is not PlayState.DONE:
            self._target = 0.0

    def resume(self) -> None:
        """Speed up again after :meth:`pause` (no-op once aborting)."""
        if not self._abort:
            self._target = 1.0

    def abort(self, reason: str = "aborted by the operator") -> None:
        """Stop on the path, then end the stream (the rest of the table is not played)."""
        if not self._abort and self.state not in (PlayState.ABORTED, PlayState.DONE):
            self.abort_reason = reason
            self._abort = True
            self._target = 0.0

    @property
    def requested(self) -> str:
        """What was asked last: ``play``, ``pause`` or ``abort`` (the keys' toggle)."""
        return "abort" if self._abort else "pause" if self._target == 0.0 else "play"

    # the source protocol (the control loop's thread)
    def precheck(self, period_s: float) -> None:
        self.inner.precheck(period_s)

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.inner.start(actual_counts, period_s)
        self._table = np.asarray(self.inner.table, dtype=np.int64)
        self._period_s = float(period_s)
        self._actual = np.asarray(actual_counts, dtype=np.int64)
        self._v = np.asarray(self.limits.max_rate_counts_per_s, np.float64)
        acc = accel_limits(self.limits, fallback=False)
        self._a = None if acc is None else np.asarray(acc, np.float64)
        self._dr = period_s / self.ramp_s
        # the highest rate off whole rows (see _candidates): 6 counts of room below the
        # smallest acceleration limit's second difference
        a_min = math.inf if self._a is None else float(np.min(self._a)) * period_s**2
        self._cap = 1.0 if not math.isfinite(a_min) else max(0.5, 1.0 - 6.0 / a_min)
        self.position, self.rate, self._k, self._out = 0.0, 1.0, -1, None
        self._prev = self._before = self._actual
        self._played = [self._actual.astype(np.int32)]
        self.played_complete = True

    @property
    def n_cycles(self) -> int:
        """Cycles at most: at full rate, plus the longest pause and two ramps (what the
        session's wait for the stream's end allows for)."""
        rows = int(self._table.shape[0]) if self._table.size else self.inner.n_cycles
        extra = (self.max_pause_s + 2 * self.ramp_s) / getattr(self, "_period_s", 0.01)
        return rows + math.ceil(extra)

    @property
    def n_rows(self) -> int:
        return int(self._table.shape[0])

    def _at(self, s: float) -> np.ndarray:
        i = min(math.floor(s), self._table.shape[0] - 1)
        f = s - i
        if f <= 0.0 or i + 1 >= self._table.shape[0]:
            return self._table[i]
        a, b = self._table[i], self._table[i + 1]
        return np.rint(a + f * (b - a).astype(np.float64)).astype(np.int64)

    def setpoint(self, k: int) -> np.ndarray | None:
        if k == self._k:
            return self._out
        n = self._table.shape[0]
        if n == 0:
            return None
        if k == 0:
            out: np.ndarray | None = self._table[0]
        elif self.state in (PlayState.ABORTED, PlayState.DONE):
            out = None
        else:
            out = self._advance(n)
        if out is not None:
            self._before, self._prev = self._prev, out
            if len(self._played) < MAX_PLAYED_ROWS:
                self._played.append(np.asarray(out, dtype=np.int32))
            else:
                self.played_complete = False
        self._k, self._out = k, out
        return out

    def way_back(self) -> np.ndarray:
        """The setpoints played so far, backwards (from where the arm stands, at rest, to
        where it started), with every stretch at rest shortened to two rows: the table of
        a return along the same path within the same limits (a speed or second difference
        reversed is the same size).  Empty when nothing was played or more than
        :data:`MAX_PLAYED_ROWS` were (no way back kept)."""
        if not self.played_complete or len(self._played) < 2:
            return np.zeros((0, self._table.shape[1] if self._table.ndim == 2 else 0), np.int64)
        rows = np.array(self._played, dtype=np.int64)
        same = np.all(rows[1:] == rows[:-1], axis=1)
        keep = np.ones(len(rows), dtype=bool)
        keep[2:] = ~(same[1:] & same[:-1])  # a row equal to the two before it goes
        return rows[keep][::-1].copy()

    def _candidates(self, target: float) -> tuple[int, np.ndarray]:
        """Rates to try this cycle: first choices (the rate a nominal step toward the
        target gives; near full rate the one that lands on a whole row, the table itself
        from then on), then rates around the current one, finer and finer.  Off whole rows
        the rate stays at most ``_cap`` (a little below 1): there the table's own second
        difference, interpolated, is at most the rate times the motor's limit, and the
        room left takes the rounding."""
        r0, dr, s = self.rate, self._dr, self.position
        whole = s == math.floor(s)
        cap = self._cap
        want = r0 + max(-dr, min(dr, target - r0))
        up = whole and target == 1.0 and want > cap and r0 >= 1.0 - dr
        first = [1.0 if up else min(cap, max(0.0, want))]
        if target == 1.0 and not whole and r0 >= cap - dr:
            snap = math.ceil(s) - s
            if r0 - dr <= snap <= min(1.0, r0 + dr):
                first.insert(0, snap)
        rest = np.concatenate([r0 + np.linspace(-w, w, 33) for w in (dr, dr / 16, dr / 256)])
        rest = rest[(rest >= 0.0) & (rest <= cap)]
        if whole and r0 == 1.0:
            rest = np.concatenate([[1.0], rest])
        return len(first), np.concatenate([np.array(first), rest])

    def _advance(self, n: int) -> np.ndarray | None:
        end = float(n - 1)
        if self.position >= end and self._target == 1.0:
            self.state = PlayState.DONE
            return None
        target = self._target
        pos = self.position
        if target == self.rate == 0.0 and self.state is PlayState.PAUSED and not self._abort:
            x = self._prev  # at rest on the path: nothing to compute
            rates, c = np.array([0.0]), 0
        elif target == self.rate == 1.0 and pos == math.floor(pos):
            # playing the table as it is: its next row (checked against the window)
            x = self._table[min(int(pos) + 1, n - 1)]
            lo, hi = self._window()
            rates, c = np.array([1.0]), 0
            if not ((x >= lo) & (x <= hi)).all():  # cannot happen for a checked table
                raise SetpointError(f"{self.name}: row {int(pos) + 1} outside the limits")
        else:
            n_first, rates = self._candidates(target)
            # the first choices alone first (most cycles: one row of the table)
            xs, over = self._try(rates[:n_first], end, n)
            ok = np.flatnonzero(over <= 0.0)
            if ok.size:
                c = int(ok[0])
            else:
                xs, over = self._try(rates, end, n)
                ok = np.flatnonzero(over <= 0.0)
                if ok.size == 0:
                    c = int(np.argmin(over))
                else:  # the feasible rate nearest to the nominal step
                    c = int(ok[np.argmin(np.abs(rates[ok] - rates[n_first - 1]))])
            x = xs[c]
        r = float(rates[c])
        if r == self.rate and r != target:
            self.held_cycles += 1
        self.rate = r
        self.position = min(end, self.position + r)
        aborting = self._abort
        if r == 0.0 and target == 0.0 and np.array_equal(x, self._prev):
            self.paused_cycles += 1
            if self.paused_cycles * self._period_s > self.max_pause_s and not aborting:
                self.abort(f"paused longer than {self.max_pause_s:g} s")
                aborting = True
            self.state = PlayState.ABORTED if aborting else PlayState.PAUSED
        elif target == 0.0:
            self.state = PlayState.ABORTING if aborting else PlayState.PAUSING
        elif r >= 1.0:
            self.state = PlayState.PLAYING
        else:
            self.state = PlayState.RESUMING
        return x

    def _try(self, rates: np.ndarray, end: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Candidate setpoints at ``rates`` (the path interpolated, rounded, kept within
        the supervisor's window) and how far each had to leave the path beyond
        :data:`MAX_OFF_PATH_COUNTS` (<= 0: acceptable)."""
        s_new = np.minimum(end, self.position + rates)
        i = np.minimum(np.floor(s_new).astype(np.int64), n - 1)
        j = np.minimum(i + 1, n - 1)
        f = (s_new - i)[:, None]
        t = self._table
        path = t[i] + f * (t[j] - t[i]).astype(np.float64)
        lo, hi = self._window()
        xs = np.clip(np.rint(path).astype(np.int64), lo, hi)
        over = np.max(np.abs(xs - path), axis=1) - MAX_OFF_PATH_COUNTS
        if not (lo <= hi).all():  # no setpoint within the limits at all (not for a table)
            over[:] = np.inf
        return xs, over

    def _window(self) -> tuple[np.ndarray, np.ndarray]:
        """The integer setpoints of each motor the supervisor accepts next: the speed from
        the last setpoint and the second difference within the motors' limits (checked in
        the supervisor's own terms, counts/s and counts/s^2)."""
        T = self._period_s
        prev, before = self._prev, self._before
        v = np.floor(self._v * T).astype(np.int64)
        v -= (v.astype(np.float64) / T > self._v).astype(np.int64)
        lo, hi = prev - v, prev + v
        if self._a is not None:
            A = np.floor(self._a * T**2).astype(np.int64)
            A -= (A.astype(np.float64) / T**2 > self._a).astype(np.int64)
            mid = 2 * prev - before
            lo, hi = np.maximum(lo, mid - A), np.minimum(hi, mid + A)
        lo = np.maximum(lo, np.asarray(self.limits.counts_min, dtype=np.int64))
        hi = np.minimum(hi, np.asarray(self.limits.counts_max, dtype=np.int64))
        return lo, hi

    def describe(self) -> dict[str, Any]:
        d = dict(self.inner.describe())
        d.update(
            pausable=True,
            play_state=self.state.value,
            stopped_at_row=round(self.position, 3),
            paused_s=round(self.paused_cycles * getattr(self, "_period_s", 0.0), 3),
            abort_reason=self.abort_reason,
            rows=self.n_rows,
        )
        return d
