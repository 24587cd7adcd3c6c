"""Limit checks of what is sent to a motor: the rope layer's limits (the
:class:`LimitChecker` protocol the rope layer's ``Actuation`` satisfies), the joint
limits of counts mapped back to angles, and the longest run a source may ask for.

Nothing outside these limits is ever sent: the setpoint sources check their whole
table before a stream starts, and the control loop checks every setpoint again
before its RPDOs go out.
"""

from __future__ import annotations

import math
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
    """What the sources need from the rope layer's ``Actuation``."""

    counts_min: np.ndarray
    counts_max: np.ndarray
    max_rate_counts_per_s: np.ndarray
    motor_ids: tuple[str, ...]

    def check_counts(
        self, counts: Any, previous: Any = None, dt_s: float | None = None
    ) -> None: ...

    def counts_from_angles(self, alpha: Any, theta: Any, tension_N: Any = None) -> np.ndarray: ...
