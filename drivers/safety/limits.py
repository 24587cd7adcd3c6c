"""Limit checks of what is sent to a motor: the rope layer's limits (the
:class:`LimitChecker` protocol the rope layer's ``Actuation`` satisfies), the motors'
acceleration (second differences of the counts), the joint limits of counts mapped back
to angles, and the longest run a source may ask for.

Nothing outside these limits is ever sent: the setpoint sources check their whole
table before a stream starts, and the control loop checks every setpoint again
before its RPDOs go out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

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


def check_joint_limits(actuation: Any, counts: np.ndarray, what: str) -> None:
    """Map a (rows, motors) table of counts through the rope layer's
    ``angles_from_counts`` and refuse (:class:`SetpointError`, one line) when the joint
    angles leave the joint limits or the counts correspond to no configuration.

    ``actuation`` is the rope layer or an ``ActuationSubset`` (``full`` + ``columns``:
    the other motors are taken at 0 counts, clipped to their limits)."""
    full = actuation
    table = np.atleast_2d(np.asarray(counts, dtype=np.int64))
    if not hasattr(full, "angles_from_counts"):
        full = getattr(actuation, "full", None)
        cols = getattr(actuation, "columns", None)
        if full is None or cols is None or not hasattr(full, "angles_from_counts"):
            raise SetpointError(f"{what}: the rope layer cannot map counts to joint angles")
        fill = np.clip(0, full.counts_min, full.counts_max).astype(np.int64)
        expanded = np.repeat(fill[None, :], table.shape[0], axis=0)
        expanded[:, cols] = table
        table = expanded
    try:
        alpha, theta, _res = full.angles_from_counts(table)
        full.check_angles(alpha, theta)
    except HrmError as exc:
        raise SetpointError(f"{what}: leaves the joint limits ({exc})") from None


class LimitChecker(Protocol):
    """What the sources need from the rope layer's ``Actuation`` (its
    ``max_accel_counts_per_s2`` and ``max_jerk_counts_per_s3`` too: read through
    :func:`accel_limits` and :func:`jerk_limits`, which also take them from the full rope
    layer of a motor subset)."""

    counts_min: np.ndarray
    counts_max: np.ndarray
    max_rate_counts_per_s: np.ndarray
    motor_ids: tuple[str, ...]

    def check_counts(
        self, counts: Any, previous: Any = None, dt_s: float | None = None
    ) -> None: ...

    def counts_from_angles(self, alpha: Any, theta: Any, tension_N: Any = None) -> np.ndarray: ...


# A checker without acceleration limits (a test double, say) gets these: full speed in
# 0.2 s and full acceleration in 0.05 s, the rope layer's default ratios.
FALLBACK_ACCEL_TIME_S = 0.2
FALLBACK_JERK_TIME_S = 0.05


def _limit_of(limits: Any, name: str) -> np.ndarray | None:
    value = getattr(limits, name, None)
    if value is None:  # a subset of the rope motors: the full rope layer's, sliced
        full, cols = getattr(limits, "full", None), getattr(limits, "columns", None)
        if full is not None and cols is not None and getattr(full, name, None) is not None:
            value = np.asarray(getattr(full, name))[np.asarray(cols)]
    return None if value is None else np.asarray(value, dtype=np.float64)


def accel_limits(limits: Any, *, fallback: bool = True) -> np.ndarray | None:
    """The motors' acceleration limits (counts/s^2) of a checker; without any, ``None``
    or (``fallback``) full speed in :data:`FALLBACK_ACCEL_TIME_S`.

    >>> class Lim:
    ...     max_rate_counts_per_s = np.array([1000.0])
    >>> accel_limits(Lim()).tolist(), accel_limits(Lim(), fallback=False)
    ([5000.0], None)
    """
    a = _limit_of(limits, "max_accel_counts_per_s2")
    if a is None and fallback:
        a = np.asarray(limits.max_rate_counts_per_s, dtype=np.float64) / FALLBACK_ACCEL_TIME_S
    return a


def jerk_limits(limits: Any) -> np.ndarray:
    """The motors' jerk limits (counts/s^3) of a checker (fallback: full acceleration in
    :data:`FALLBACK_JERK_TIME_S`)."""
    j = _limit_of(limits, "max_jerk_counts_per_s3")
    if j is None:
        j = np.asarray(accel_limits(limits), dtype=np.float64) / FALLBACK_JERK_TIME_S
    return j


def _motor_name(limits: Any, i: int) -> str:
    label = getattr(limits, "motor_label", None)
    return str(label(i)) if callable(label) else str(limits.motor_ids[i])


def first_too_hard(
    limits: Any, table: np.ndarray, period_s: float, previous: np.ndarray | None = None
) -> tuple[int, int, float] | None:
    """The first (row, motor, counts/s^2) whose second difference exceeds the motor's
    acceleration limit (``|r[k] - 2 r[k-1] + r[k-2]| / T**2``), or None.  With
    ``previous`` the table starts from rest there (``previous`` held one period before),
    so its first row is checked too; a checker without acceleration limits checks none.

    >>> class Lim:
    ...     max_accel_counts_per_s2 = np.array([4.0]); motor_ids = ("m0",)
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
    limits: Any,
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


def acceleration_text(limits: Any, i: int, acc: float) -> str:
    """``motor m0: accelerates 500 counts/s^2, more than the motor's 100 counts/s^2``."""
    a = accel_limits(limits)
    lim = float(np.asarray(a)[i])
    return (
        f"motor {_motor_name(limits, i)}: accelerates {acc:.0f} counts/s^2, more than the "
        f"motor's {lim:.0f} counts/s^2"
    )
