"""Jog: one motor at a constant speed for a while, the others hold, jerk-limited from rest
to rest; checked against the motors' limits and, by the rope model, the joint limits
and (the whole arm) the rope tensions, before anything is sent."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from drivers.rope_model import RopeModel
from drivers.safety.limits import (
    MOVE_CHECK_MAX_ROWS,
    SetpointError,
    accel_limits,
    check_duration,
    check_move,
    jerk_limits,
    sampled_rows,
)
from drivers.sources.moves import move_table
from drivers.sources.table import TableSource, check_table
from hrm_ctrl.errors import HrmError

JOG_ANGLE_CHECK_STEP_COUNTS = 1000  # a jog is mapped to joint angles at least this often


class JogSource(TableSource):
    """Move one motor at a constant speed for a while, the others hold: ``velocity *
    duration`` counts, jerk-limited from rest to rest (:func:`move_table`), then
    ``hold_s`` of where it got to."""

    name = "jog"

    def __init__(
        self,
        actuation: RopeModel,
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
        nj = self.actuation.n_joints
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
        :data:`~drivers.safety.limits.MOVE_CHECK_MAX_ROWS` rows, first and last included)
        within the joint limits, and (the whole arm) its ropes' tensions
        (:func:`~drivers.safety.limits.check_move`)."""
        actual = np.asarray(actual_counts, dtype=np.int64)
        moved = self._moved(actual, period_s)
        travel = float(np.abs(moved - actual[self.index]).max())
        every = max(2, math.ceil(travel / JOG_ANGLE_CHECK_STEP_COUNTS) + 1)
        rows = sampled_rows(len(moved), min(every, MOVE_CHECK_MAX_ROWS))
        table = np.repeat(actual[None, :], len(rows) + 1, axis=0)
        table[1:, self.index] = moved[rows]
        if self.label:
            what = f"{self.label} ({where})"
        else:
            what = f"jog {self.motor} ({self.velocity:.0f} counts/s, {where})"
        arm = self.actuation.whole_arm
        warm = None
        if arm is not None:  # the inverse starts where the arm is (not cold: corners)
            try:
                warm = arm.pose_of_counts(actual, "where the arm is")
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
