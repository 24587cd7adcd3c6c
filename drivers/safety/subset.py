"""Part of the box: the rope layer's model for a subset of the rope motors.

Commissioning one joint, or a test rig with a few drives, runs the drivers on
some of the rope motors only.  :class:`ActuationSubset` presents the rope layer
(``hrm_ctrl.ropes.actuation.Actuation``) for those motors as a
:class:`~drivers.rope_model.RopeModel`: same names, arrays sliced, and every check and
mapping delegated to the rope layer itself with the other motors held at a constant
in-limit value (0 counts, clipped to their limits), so they never trip a check.  It has
no model of the whole arm (:attr:`whole_arm` is None): the other ropes are not commanded.

>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> from hrm_ctrl.model import default_robot
>>> sub = ActuationSubset(load_actuation(default_robot()), ("j01r0", "j07r0"))
>>> sub.n_motors, sub.counts_max.shape, sub.motor_label(1), sub.whole_arm is None
(2, (2,), 'j07r0 (joint 7, rope 0)', True)
>>> sub.check_counts(np.array([0, 10**9]))  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.ropes.actuation.RopeLimitError: motor j07r0 (joint 7, rope 0): setpoint ... counts ...
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from drivers.rope_model import RopeModel
from hrm_ctrl.errors import DriverError


class ActuationSubset:
    """The rope layer ``full`` restricted to ``motor_ids`` (in that order)."""

    def __init__(self, full: RopeModel, motor_ids: Sequence[str]) -> None:
        unknown = [m for m in motor_ids if m not in full.motor_ids]
        if unknown or not motor_ids:
            raise DriverError(f"motor subset: unknown or empty rope motor ids {unknown}")
        self.full = full
        self.motor_ids: tuple[str, ...] = tuple(motor_ids)
        cols = np.array([full.motor_ids.index(m) for m in motor_ids], dtype=np.int64)
        self.columns = cols
        self.counts_min = np.asarray(full.counts_min)[cols]
        self.counts_max = np.asarray(full.counts_max)[cols]
        self.max_rate_counts_per_s = np.asarray(full.max_rate_counts_per_s)[cols]
        accel, jerk = full.max_accel_counts_per_s2, full.max_jerk_counts_per_s3
        self.max_accel_counts_per_s2 = None if accel is None else np.asarray(accel)[cols]
        self.max_jerk_counts_per_s3 = None if jerk is None else np.asarray(jerk)[cols]
        self._fill = np.clip(0, full.counts_min, full.counts_max).astype(np.int64)

    @property
    def n_motors(self) -> int:
        return len(self.motor_ids)

    @property
    def n_joints(self) -> int:
        return self.full.n_joints

    @property
    def whole_arm(self) -> None:
        """None: the other ropes are not commanded (see the module docstring)."""
        return None

    def motor_label(self, i: int) -> str:
        return self.full.motor_label(int(self.columns[i]))

    def expand(self, counts: ArrayLike) -> np.ndarray:
        """Counts (..., n of the subset) as the full rope layer's (..., all motors), the
        other motors at their fill value.

        >>> from hrm_ctrl.ropes.actuation import load_actuation
        >>> from hrm_ctrl.model import default_robot
        >>> sub = ActuationSubset(load_actuation(default_robot()), ("j01r1",))
        >>> sub.expand(np.array([[7], [8]]))[:, :3].tolist()
        [[0, 7, 0], [0, 8, 0]]
        """
        c = np.asarray(counts)
        if c.shape[-1:] != (self.n_motors,):
            raise DriverError(f"expected {self.n_motors} motor counts, got shape {c.shape}")
        full = np.broadcast_to(self._fill, (*c.shape[:-1], self._fill.shape[0])).copy()
        full = full.astype(np.result_type(full, c))
        full[..., self.columns] = c
        return full

    def check_counts(
        self, counts: ArrayLike, previous: ArrayLike | None = None, dt_s: ArrayLike | None = None
    ) -> None:
        prev = None if previous is None else self.expand(previous)
        self.full.check_counts(self.expand(counts), previous=prev, dt_s=dt_s)

    def counts_from_angles(
        self, alpha: ArrayLike, theta: ArrayLike, tension_N: ArrayLike | None = None
    ) -> np.ndarray:
        return np.asarray(self.full.counts_from_angles(alpha, theta, tension_N))[..., self.columns]

    def angles_from_counts(self, counts: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The full rope layer's angles of ``counts`` with the other motors at their fill
        value; the residual of the subset's ropes."""
        alpha, theta, residual = self.full.angles_from_counts(self.expand(counts))
        return alpha, theta, np.asarray(residual)[..., self.columns]

    def check_angles(self, alpha: ArrayLike, theta: ArrayLike) -> None:
        self.full.check_angles(alpha, theta)
