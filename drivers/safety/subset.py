"""Part of the box: the rope layer's limits for a subset of the rope motors.

Commissioning one joint, or a test rig with a few drives, runs the drivers on
some of the rope motors only.  :class:`ActuationSubset` presents the rope layer
(``hrm_ctrl.ropes.actuation.Actuation``) for those motors: same attribute names,
arrays sliced, and every limit check delegated to the rope layer itself (the
other motors are held at a constant in-limit value, so they never trip a check).

>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> from hrm_ctrl.model import default_robot
>>> sub = ActuationSubset(load_actuation(default_robot()), ("j01r0", "j07r0"))
>>> sub.n_motors, sub.counts_max.shape
(2, (2,))
>>> sub.check_counts(np.array([0, 10**9]))  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.ropes.actuation.RopeLimitError: motor j07r0 (joint 7, rope 0): setpoint ... counts ...
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from drivers.safety.limits import LimitChecker
from hrm_ctrl.errors import DriverError


class ActuationSubset:
    """The rope layer restricted to ``motor_ids`` (in that order)."""

    def __init__(self, actuation: Any, motor_ids: Sequence[str]) -> None:
        unknown = [m for m in motor_ids if m not in actuation.motor_ids]
        if unknown or not motor_ids:
            raise DriverError(f"motor subset: unknown or empty rope motor ids {unknown}")
        self.full: LimitChecker = actuation
        self.motor_ids = tuple(motor_ids)
        self.columns = np.array([actuation.motor_ids.index(m) for m in motor_ids])
        self.counts_min = np.asarray(actuation.counts_min)[self.columns]
        self.counts_max = np.asarray(actuation.counts_max)[self.columns]
        self.max_rate_counts_per_s = np.asarray(actuation.max_rate_counts_per_s)[self.columns]
        self._fill = np.clip(0, actuation.counts_min, actuation.counts_max).astype(np.int64)

    @property
    def n_motors(self) -> int:
        return len(self.motor_ids)

    def _expand(self, counts: Any) -> np.ndarray:
        c = np.asarray(counts)
        if c.shape[-1:] != (self.n_motors,):
            raise DriverError(f"expected {self.n_motors} motor counts, got shape {c.shape}")
        full = np.broadcast_to(self._fill, (*c.shape[:-1], self._fill.shape[0])).copy()
        full = full.astype(np.result_type(full, c))
        full[..., self.columns] = c
        return full

    def check_counts(self, counts: Any, previous: Any = None, dt_s: float | None = None) -> None:
        prev = None if previous is None else self._expand(previous)
        self.full.check_counts(self._expand(counts), previous=prev, dt_s=dt_s)

    def counts_from_angles(self, alpha: Any, theta: Any, tension_N: Any = None) -> np.ndarray:
        return np.asarray(self.full.counts_from_angles(alpha, theta, tension_N))[..., self.columns]
