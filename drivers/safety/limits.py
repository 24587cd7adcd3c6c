"""Limit checks of what is sent to a motor: the rope layer's limits (a
:class:`~drivers.rope_model.MotorLimits`, e.g. the rope layer's ``Actuation``), the
motors' acceleration (second differences of the counts), the joint limits of counts
mapped back to angles and the rope tensions of a move (a
:class:`~drivers.rope_model.RopeModel`), and the longest run a source may ask for.

Nothing outside these limits is ever sent: the setpoint sources check their whole
table before a stream starts, and the control loop checks every setpoint again
before its RPDOs go out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.rope_model import ArmRopeModel, MotorLimits, RopeModel
from hrm_ctrl.errors import DriverError, HrmError


class SetpointError(DriverError):
    """A setpoint source cannot be built or started."""


MAX_SOURCE_DURATION_S = 3600.0  # longest run of any source (bounds the tables' memory)


def check_duration(what: str, duration_s: float, period_s: float) -> None:
    """Refuse a source longer than :data:`MAX_SOURCE_DURATION_S` (one-line error).

    >>> check_duration("jog j01r0", 7200.0, 0.01)
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: jog j01r0: 7200 s exceeds the longest run of 3600 s
    """
    if not (math.isfinite(duration_s) and duration_s <= MAX_SOURCE_DURATION_S + period_s):
        raise SetpointError(
            f"{what}: {duration_s:.4g} s exceeds the longest run of {MAX_SOURCE_DURATION_S:g} s"
        )


MOVE_CHECK_MAX_ROWS = 400  # rows of a move mapped through the rope model, at most
# a rope outside the band where a move starts may go this much further out on the way
# (the rope model's noise along a path: 1 count is 0.027 N on the shortest rope)
TENSION_SLACK_N = 0.1


def check_joint_limits(model: RopeModel, counts: np.ndarray, what: str) -> None:
    """Map a (rows, motors) table of counts through the rope model's
    ``angles_from_counts`` and refuse (:class:`SetpointError`, one line) when the joint
    angles leave the joint limits (a motor subset: its other motors held still)."""
    table = np.atleast_2d(np.asarray(counts, dtype=np.int64))
    try:
        alpha, theta, _res = model.angles_from_counts(table)
        model.check_angles(alpha, theta)
    except HrmError as exc:
        raise SetpointError(f"{what}: leaves the joint limits ({exc})") from None


def sampled_rows(n_rows: int, max_rows: int = MOVE_CHECK_MAX_ROWS) -> np.ndarray:
    """At most ``max_rows`` evenly spread row indices of a table, first and last included
    (the rows of a move the rope model judges: :func:`check_move`, a jog's angles).

    >>> sampled_rows(5).tolist(), sampled_rows(1000, 4).tolist()
    ([0, 1, 2, 3, 4], [0, 333, 666, 999])
    """
    n = min(n_rows, max_rows)
    return np.unique(np.rint(np.linspace(0, n_rows - 1, max(n, 1))).astype(np.int64))


def check_move(
    model: RopeModel,
    counts: np.ndarray,
    what: str,
    poses: tuple[np.ndarray, np.ndarray] | None = None,
    *,
    warm: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """The arm a move's counts give, by the rope layer's model: ``counts`` (rows, motors)
    starts with where the drives are now (not judged) and goes on with the move's rows
    (at most :data:`MOVE_CHECK_MAX_ROWS` of them, evenly spread, are mapped).

    Without ``poses`` the rows' joint angles are the rope inverse's of their counts (started
    from ``warm``, (n_joints,) alpha and theta, e.g. where the arm is, else cold), and an
    angle at or past its limit is refused only where the move takes it further out than it
    starts (near the joint-range corners the counts hardly tell the angles apart: an arm at
    58 deg can decode at 60.7); with ``poses`` (the configurations the rows were made from,
    (rows, n_joints) alpha and theta, e.g. a joint line's) they are those, their whole
    counts judged as a plan's are (``rounded_outside``), and the tensions are those with the
    arm held there (``tensions_at``).  Refused with one line (:class:`SetpointError`, naming
    the cycle of the move) when a row's joint angles leave the joint limits, no pose fits a
    row, or, with the whole rope layer (its
    :attr:`~drivers.rope_model.RopeModel.whole_arm`), a rope's modelled tension leaves the
    rope layer's ``command_tension_N`` band: counts that no pose of the arm takes up at its
    pretension strain or slacken ropes (a straight line in counts between two bent poses,
    one rope moved alone).  A rope outside the band where the move starts may stay outside
    it, but no row takes it more than :data:`TENSION_SLACK_N` further out and the move does
    not end further out than it started (moves one after another cannot creep out of the
    band).  A motor subset (``ActuationSubset``, no ``whole_arm``) gets the joint limits
    only: the other ropes are not commanded, so their tensions are unknown.

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> move = np.zeros((2, 36), dtype=np.int64); move[1, 0] = -5000   # pay out 2.3 mm
    >>> check_move(act, move, "jog j01r0 -5000 counts")   # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: jog j01r0 -5000 counts: cycle 1: rope j01r0: ... 0.00 N...
    >>> check_move(act, move[::-1], "back")   # from slack towards the pretension: taken
    """
    table = np.atleast_2d(np.asarray(counts, dtype=np.int64))
    if table.shape[0] < 2:
        return
    rows = sampled_rows(table.shape[0])
    arm = model.whole_arm
    if arm is None:  # a motor subset
        check_joint_limits(model, table[rows][1:], what)
        return
    _check_arm_move(arm, table, rows, what, poses, warm)


def _check_arm_move(
    arm: ArmRopeModel,
    table: np.ndarray,
    rows: np.ndarray,
    what: str,
    poses: tuple[np.ndarray, np.ndarray] | None,
    warm: tuple[np.ndarray, np.ndarray] | None,
) -> None:
    """:func:`check_move` with the whole arm's rope model, of the ``rows`` of ``table``."""
    n = table.shape[0] - 1
    lim_a, lim_t = arm.limit_alpha, arm.limit_theta
    if poses is None:  # the rows' poses are what the rope inverse makes of their counts
        try:
            alpha, theta, T = arm.tensions_from_counts(table[rows], *(warm or (None, None)))
        except HrmError as exc:
            raise SetpointError(f"{what}: no pose of the arm fits its counts ({exc})") from None
    else:  # the rows were made from these poses: judged as a plan's rows are
        alpha, theta = poses[0][rows], poses[1][rows]
        near = arm.rounded_outside(table[rows][1:], alpha[1:], theta[1:])
        if near is not None:
            raise SetpointError(
                f"{what}: cycle {int(rows[near[0] + 1])} of {n}: rounded to whole counts: {near[1]}"
            )
        T = arm.tensions_at(table[rows], alpha, theta)  # the arm held at its poses
    past_a, past_t = np.abs(alpha) >= lim_a, np.abs(theta) >= lim_t
    if poses is None:  # a decoded angle past its limit counts where the move takes it out
        past_a &= np.abs(alpha) > np.abs(alpha[0]) + 1e-9
        past_t &= np.abs(theta) > np.abs(theta[0]) + 1e-9
    outside = (past_a | past_t | ~np.isfinite(alpha) | ~np.isfinite(theta)).any(axis=1)
    outside[0] = False  # where the arm is: not the move's to judge
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        try:
            arm.check_angles(alpha[k], theta[k])
        except HrmError as exc:
            raise SetpointError(
                f"{what}: cycle {int(rows[k])} of {n}: leaves the joint limits ({exc})"
            ) from None
    low, high = arm.command_tension_N
    start = T[0]
    floor = np.minimum(start, low)  # a rope may not go below the band, or below its start
    ceiling = np.maximum(start, high)
    below = T < floor - TENSION_SLACK_N
    above = T > ceiling + TENSION_SLACK_N
    below[-1] |= T[-1] < floor - 1e-9  # and the move ends no further out than it began
    above[-1] |= T[-1] > ceiling + 1e-9
    bad = below | above
    if bad.any():
        r, m = (int(v) for v in np.argwhere(bad)[0])
        side = f"below {low:g} N" if below[r, m] else f"above {high:g} N"
        raise SetpointError(
            f"{what}: cycle {int(rows[r])}: rope {arm.motor_ids[m]}: the rope model's "
            f"tension {T[r, m]:.2f} N, {side} (command_tension_N of the robot description; "
            f"{start[m]:.2f} N now)"
        )


# Limits without acceleration limits (a test double, say) get these: full speed in
# 0.2 s and full acceleration in 0.05 s, the rope layer's default ratios.
FALLBACK_ACCEL_TIME_S = 0.2
FALLBACK_JERK_TIME_S = 0.05


def accel_limits(limits: MotorLimits, *, fallback: bool = True) -> np.ndarray | None:
    """The motors' acceleration limits (counts/s^2); without any (``None``), ``None``
    or (``fallback``) full speed in :data:`FALLBACK_ACCEL_TIME_S`.

    >>> class Lim:
    ...     max_rate_counts_per_s = np.array([1000.0]); max_accel_counts_per_s2 = None
    >>> accel_limits(Lim()).tolist(), accel_limits(Lim(), fallback=False)
    ([5000.0], None)
    """
    a = limits.max_accel_counts_per_s2
    if a is not None:
        return np.asarray(a, dtype=np.float64)
    if not fallback:
        return None
    return np.asarray(limits.max_rate_counts_per_s, dtype=np.float64) / FALLBACK_ACCEL_TIME_S


def jerk_limits(limits: MotorLimits) -> np.ndarray:
    """The motors' jerk limits (counts/s^3); without any (``None``), full acceleration
    (:func:`accel_limits`) in :data:`FALLBACK_JERK_TIME_S`."""
    j = limits.max_jerk_counts_per_s3
    if j is not None:
        return np.asarray(j, dtype=np.float64)
    return np.asarray(accel_limits(limits), dtype=np.float64) / FALLBACK_JERK_TIME_S


def first_too_hard(
    limits: MotorLimits, table: np.ndarray, period_s: float, previous: np.ndarray | None = None
) -> tuple[int, int, float] | None:
    """The first (row, motor, counts/s^2) whose second difference exceeds the motor's
    acceleration limit (``|r[k] - 2 r[k-1] + r[k-2]| / T**2``), or None.  With
    ``previous`` the table starts from rest there (``previous`` held one period before),
    so its first row is checked too; a checker without acceleration limits checks none.

    >>> class Lim:
    ...     max_accel_counts_per_s2 = np.array([4.0]); motor_ids = ("m0",)
    ...     def motor_label(self, i): return self.motor_ids[i]
    >>> first_too_hard(Lim(), np.array([[0], [1], [4]]), 0.5, previous=np.array([0]))
    (2, 0, 8.0)
    >>> first_too_hard(Lim(), np.array([[0], [1], [2]]), 0.5, previous=np.array([0])) is None
    True
    """
    a = accel_limits(limits, fallback=False)
    if a is None:
        return None
    t = np.asarray(table, dtype=np.int64)
    if previous is not None:
        p = np.asarray(previous, dtype=np.int64).reshape(1, -1)
        t = np.concatenate([p, p, t], axis=0)
    if t.shape[0] < 3:
        return None
    acc = np.abs(np.diff(t, n=2, axis=0)).astype(np.float64) / period_s**2
    hard = acc > a
    if not hard.any():
        return None
    k, i = (int(v) for v in np.argwhere(hard)[0])
    row = k if previous is not None else k + 2
    return row, i, float(acc[k, i])


def check_acceleration(
    limits: MotorLimits,
    table: np.ndarray,
    period_s: float,
    previous: np.ndarray | None = None,
    name_of_row: Callable[[int], str] | None = None,
) -> None:
    """Refuse (:class:`SetpointError`, one line naming the row and the motor) a table whose
    second difference exceeds a motor's acceleration limit (see :func:`first_too_hard`).
    ``name_of_row`` says what a row is (e.g. the plan step it came from); without it a
    row is the control cycle of the table it is.

    >>> class Lim:
    ...     max_accel_counts_per_s2 = np.array([4.0]); motor_ids = ("m0",)
    ...     def motor_label(self, i): return self.motor_ids[i]
    >>> check_acceleration(Lim(), np.array([[5]]), 0.5, previous=np.array([0]))
    ... # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: cycle 0: motor m0: accelerates 20 counts/s^2, more ...
    """
    hit = first_too_hard(limits, table, period_s, previous)
    if hit is None:
        return
    row, i, acc = hit
    where = f"cycle {row}" if name_of_row is None else name_of_row(row)
    raise SetpointError(f"{where}: {acceleration_text(limits, i, acc)}")


def acceleration_text(limits: MotorLimits, i: int, acc: float) -> str:
    """``motor m0: accelerates 500 counts/s^2, more than the motor's 100 counts/s^2``."""
    a = accel_limits(limits)
    lim = float(np.asarray(a)[i])
    return (
        f"motor {limits.motor_label(i)}: accelerates {acc:.0f} counts/s^2, more than the "
        f"motor's {lim:.0f} counts/s^2"
    )


def jerk_limits_of(limits: MotorLimits) -> np.ndarray | None:
    """The motors' own jerk limits (counts/s^3), or None when they have none."""
    j = limits.max_jerk_counts_per_s3
    return None if j is None else np.asarray(j, dtype=np.float64)


def first_too_jerky(
    limits: MotorLimits, table: np.ndarray, period_s: float, previous: np.ndarray | None = None
) -> tuple[int, int, float] | None:
    """The first (row, motor, counts/s^3) whose third difference exceeds the motor's jerk
    limit (``|r[k] - 3 r[k-1] + 3 r[k-2] - r[k-3]| / T**3``), or None.  With ``previous``
    the table starts from rest there (``previous`` held for three periods before), so
    its first rows are checked too; limits without jerk limits check none.

    >>> class Lim:
    ...     max_jerk_counts_per_s3 = np.array([8.0]); motor_ids = ("m0",)
    ...     def motor_label(self, i): return self.motor_ids[i]
    >>> first_too_jerky(Lim(), np.array([[0], [2], [4]]), 0.5, previous=np.array([0]))
    (1, 0, 16.0)
    >>> first_too_jerky(Lim(), np.array([[0], [1], [3]]), 0.5) is None
    True
    """
    j = jerk_limits_of(limits)
    if j is None:
        return None
    t = np.asarray(table, dtype=np.int64)
    if previous is not None:
        p = np.asarray(previous, dtype=np.int64).reshape(1, -1)
        t = np.concatenate([p, p, p, t], axis=0)
    if t.shape[0] < 4:
        return None
    jerk = np.abs(np.diff(t, n=3, axis=0)).astype(np.float64) / period_s**3
    hard = jerk > j
    if not hard.any():
        return None
    k, i = (int(v) for v in np.argwhere(hard)[0])
    row = k if previous is not None else k + 3
    return row, i, float(jerk[k, i])


def jerk_text(limits: MotorLimits, i: int, jerk: float) -> str:
    """``motor m0: jerks 5e+07 counts/s^3, more than the motor's 4.096e+07 counts/s^3``."""
    lim = float(np.asarray(limits.max_jerk_counts_per_s3)[i])
    return (
        f"motor {limits.motor_label(i)}: jerks {jerk:.4g} counts/s^3, more than the "
        f"motor's {lim:.4g} counts/s^3"
    )


def check_jerk(
    limits: MotorLimits,
    table: np.ndarray,
    period_s: float,
    previous: np.ndarray | None = None,
    name_of_row: Callable[[int], str] | None = None,
) -> None:
    """Refuse (:class:`SetpointError`, one line naming the row and the motor) a table whose
    third difference exceeds a motor's jerk limit (see :func:`first_too_jerky`).

    >>> class Lim:
    ...     max_jerk_counts_per_s3 = np.array([8.0]); motor_ids = ("m0",)
    ...     def motor_label(self, i): return self.motor_ids[i]
    >>> check_jerk(Lim(), np.array([[0], [2], [4]]), 0.5, previous=np.array([0]))
    ... # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: cycle 1: motor m0: jerks 16 counts/s^3, more ... 8 ...
    """
    hit = first_too_jerky(limits, table, period_s, previous)
    if hit is None:
        return
    row, i, jerk = hit
    where = f"cycle {row}" if name_of_row is None else name_of_row(row)
    raise SetpointError(f"{where}: {jerk_text(limits, i, jerk)}")


# The per-cycle fast test works on counts up to this size (float64 holds every integer
# up to 2**53 exactly, so the slow path's float arithmetic on them is exact as well).
_FAST_EDGE = 2**52
# Bounds of the fast test sit this much (relative) inside the limits: a setpoint whose
# change lands on a limit up to float rounding is left to the slow path.
_FAST_MARGIN = 1e-9
_INT64 = np.dtype(np.int64)


def _largest_step(
    limit: np.ndarray, scale: float, refused: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray | None:
    """Per motor the largest whole change ``c >= 0`` (``<=`` :data:`_FAST_EDGE`) the slow
    path's own arithmetic ``refused(c)`` does not refuse, with the margin; None if a motor
    has none (then the fast test is off).  ``refused`` is monotone in ``c``."""
    with np.errstate(invalid="ignore", over="ignore"):
        c = limit * scale * (1.0 - _FAST_MARGIN)
    c = np.nan_to_num(c, nan=_FAST_EDGE, posinf=_FAST_EDGE, neginf=-1.0)
    step = np.clip(np.floor(c), -1, _FAST_EDGE).astype(np.int64)
    for _ in range(4):
        bad = (step >= 0) & refused(step)
        if not bad.any():
            return None if (step < 0).any() else step
        step[bad] -= 1
    return None


class CycleLimits:
    """The control loop's check of one setpoint: position, speed (from ``previous``) and
    acceleration (the second difference with ``before``, one period earlier), built once
    from a :class:`~drivers.rope_model.MotorLimits` and the control period.

    :meth:`check` first runs a cheap test on precomputed whole-count bounds per motor
    (:meth:`passes`: a handful of NumPy calls on int64 work buffers); only a setpoint it
    does not clearly pass goes through :meth:`check_slow`, the rope layer's
    ``check_counts`` and then the acceleration check, which raise what they always did.
    The fast test is conservative: it passes a setpoint only if the slow path passes it
    too (the bounds are checked with the slow path's own float arithmetic and sit a
    little inside the limits, so a change exactly at a limit goes to the slow path).

    It trusts the protocol: ``check_counts`` refuses a setpoint outside
    ``counts_min``/``counts_max`` or moving faster than ``max_rate_counts_per_s``, and
    nothing else for a single int64 setpoint.  Limits of other shapes, not numbers (NaN:
    a double without rate limits, say), or a period that is not a positive number, get
    the slow path only; limits without acceleration limits (:func:`accel_limits`) skip
    that part, as the slow path does.  Only targets, previous and before that are int64
    arrays of one setpoint take the fast test.  The work buffers make an instance
    thread-confined (the supervisor's thread).

    >>> class Lim:
    ...     motor_ids = ("m0", "m1")
    ...     counts_min = np.array([-100, -100]); counts_max = np.array([100, 100])
    ...     max_rate_counts_per_s = np.array([1000.0, 1000.0])  # 10 counts a period
    ...     max_accel_counts_per_s2 = np.array([5e4, 5e4])  # 5 counts a period^2
    ...     max_jerk_counts_per_s3 = None
    ...     def motor_label(self, i): return self.motor_ids[i]
    ...     def check_counts(self, counts, previous=None, dt_s=None):
    ...         if np.any(np.abs(counts) > 100): raise SetpointError("outside [-100, 100]")
    >>> cyc = CycleLimits(Lim(), 0.01)
    >>> cyc.fast, cyc.step.tolist(), cyc.second.tolist()  # the limits exactly: slow path
    (True, [9, 9], [4, 4])
    >>> rest = np.array([0, 0])
    >>> cyc.passes(np.array([4, -3]), rest, rest), cyc.check(np.array([4, -3]), rest, rest)
    (True, None)
    >>> cyc.passes(np.array([5, 0]), rest, rest), cyc.check(np.array([5, 0]), rest, rest)
    (False, None)
    >>> cyc.check(np.array([6, 0]), rest, rest)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: motor m0: accelerates 60000 counts/s^2, more ... 50000 ...
    >>> cyc.check(np.array([101, 0]), np.array([99, 0]), np.array([97, 0]))
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: outside [-100, 100]
    """

    def __init__(self, limits: MotorLimits, period_s: float) -> None:
        self.limits = limits
        self.period_s = float(period_s)
        self.accel = accel_limits(limits, fallback=False)  # counts/s^2, or None
        #: whether the fast test runs at all (else every setpoint takes the slow path)
        self.fast = False
        #: per motor: position bounds, the largest change per period and (with
        #: acceleration limits) the largest second difference the fast test passes
        self.lo = self.hi = self.step = np.zeros(0, dtype=np.int64)
        self.second: np.ndarray | None = None
        rows = 2 if self.accel is None else 3
        self._shape: tuple[int, ...] = (0,)
        self._x = np.zeros((rows, 0), dtype=np.int64)
        self._bounds()
        n = self.lo.shape[0]
        self._shape = (n,)
        # rows: target - lo, target - previous + step, target - 2 previous + before +
        # second; each must lie in [0, span] (compared unsigned: one comparison a row)
        self._x = np.zeros((rows, n), dtype=np.int64)
        self._xu = self._x.view(np.uint64)
        self._rows = tuple(self._x)  # row views, made once
        self._tail = self._x[1:]
        offsets = [self.step] if self.second is None else [self.step, self.second]
        self._offset = np.array(offsets, dtype=np.int64).reshape(rows - 1, n)
        spans = [self.hi - self.lo, *(2 * o for o in offsets)]
        self._span = np.array(spans, dtype=np.int64).reshape(rows, n).view(np.uint64)
        self._out = np.zeros((rows, n), dtype=bool)  # where a row leaves its range

    def _bounds(self) -> None:
        """Fill lo, hi, step, second and ``fast`` (left off when anything is amiss)."""
        lim = self.limits
        T = self.period_s
        raw = [lim.counts_min, lim.counts_max, lim.max_rate_counts_per_s]
        if not (math.isfinite(T) and T > 0):
            return
        cmin, cmax, rate = (np.asarray(r) for r in raw)
        try:
            cmin_f, cmax_f, rate_f = (np.asarray(r, dtype=np.float64) for r in raw)
        except (TypeError, ValueError):
            return
        n = cmin_f.shape[0] if cmin_f.ndim == 1 else -1
        shapes = [cmax_f.shape, rate_f.shape, (len(lim.motor_ids),)]
        if self.accel is not None:
            shapes.append(self.accel.shape)
        if n < 1 or any(s != (n,) for s in shapes):
            return
        if np.isnan(cmin_f).any() or np.isnan(cmax_f).any() or np.isnan(rate_f).any():
            return
        lo = np.clip(np.ceil(cmin_f), -_FAST_EDGE, _FAST_EDGE + 1).astype(np.int64)
        hi = np.clip(np.floor(cmax_f), -_FAST_EDGE - 1, _FAST_EDGE).astype(np.int64)
        # the slow path's own comparisons (int64 setpoints against the raw limits)
        if (lo > hi).any() or not ((lo >= cmin).all() and (hi <= cmax).all()):
            return
        dt = np.full(1, T)  # as check_counts: the change over dt_s, against the raw rate
        step = _largest_step(rate_f, T, lambda c: np.abs(c.astype(np.float64)) / dt > rate)
        if step is None:
            return
        second = None
        if self.accel is not None:
            a = self.accel  # as the supervisor: |second difference| / T**2 > the limit
            second = _largest_step(a, T**2, lambda c: np.abs(c) / T**2 > a)
            if second is None:
                return
        self.lo, self.hi, self.step, self.second = lo, hi, step, second
        self.fast = True

    def passes(self, target: Any, previous: Any, before: Any) -> bool:
        """The fast test alone: True only if the setpoint clearly keeps every limit
        (False: take the slow path, which decides)."""
        if not self.fast:
            return False
        s, i64 = self._shape, _INT64
        if not (
            type(target) is np.ndarray
            and type(previous) is np.ndarray
            and target.dtype == i64
            and previous.dtype == i64
            and target.shape == s
            and previous.shape == s
        ):
            return False
        rows = self._rows
        np.subtract(target, self.lo, out=rows[0])
        np.subtract(target, previous, out=rows[1])
        if self.second is not None:
            if not (type(before) is np.ndarray and before.dtype == i64 and before.shape == s):
                return False
            np.subtract(rows[1], previous, out=rows[2])
            np.add(rows[2], before, out=rows[2])
        np.add(self._tail, self._offset, out=self._tail)
        # int64 wraps around, but for a target within [lo, hi] no wrapped value of the
        # other rows lands within [0, span]: only the true differences pass
        np.greater(self._xu, self._span, out=self._out)
        return not np.count_nonzero(self._out)  # (faster than .any() on small arrays)

    def check(self, target: Any, previous: Any, before: Any) -> None:
        """Raise (the rope layer's error or :class:`SetpointError`) if ``target`` breaks a
        limit, exactly as :meth:`check_slow` does; cheaply when it clearly keeps them."""
        if not self.passes(target, previous, before):
            self.check_slow(target, previous, before)

    def check_slow(self, target: Any, previous: Any, before: Any) -> None:
        """The full check: the rope layer's ``check_counts`` (position and speed from
        ``previous``), then the second difference against the acceleration limits."""
        self.limits.check_counts(target, previous=previous, dt_s=self.period_s)
        if self.accel is not None:
            t = np.asarray(target, dtype=np.int64)
            acc = np.abs(t - 2 * previous + before) / self.period_s**2
            hard = acc > self.accel
            if hard.any():
                i = int(np.flatnonzero(hard)[0])
                raise SetpointError(acceleration_text(self.limits, i, float(acc[i])))
