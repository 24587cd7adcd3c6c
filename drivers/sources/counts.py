"""Play a precomputed counts table (a plan's): a lead-in from the actual positions to its
first row (a line in joint space with the whole arm's rope model, else in counts), the
table, a jerk-limited stop if it ends moving, then a hold; the lead-in and the stop
checked by the rope model, the whole table against every motor limit, before anything is
sent."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from drivers.rope_model import RopeModel
from drivers.safety.limits import (
    SetpointError,
    accel_limits,
    check_duration,
    check_move,
    jerk_limits,
)
from drivers.sources.moves import at_samples, move_table, path_move, stop_table
from drivers.sources.table import LabelOfRow, TableSource, check_table, row_name
from hrm_ctrl.errors import HrmError

LEAD_IN_SPEED_FRACTION = 0.5  # a lead-in moves at no more than half of each motor's speed


class CountsSource(TableSource):
    """Play a precomputed (cycles, motors) counts ``body`` made for the control period
    ``period_s``: a lead-in from the actual positions to the body's first row (jerk-limited,
    from rest to rest, at no more than half of each motor's speed; with the whole arm's
    rope model (:attr:`~drivers.rope_model.RopeModel.whole_arm`) a straight line in the
    joint angles, its ``joint_line`` timed by :func:`path_move`, else, a motor subset, in
    counts, :func:`move_table`), the body, a jerk-limited stop
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
    >>> body = np.repeat(np.array([[0], [10], [40], [80], [110], [120], [120]]),
    ...                  act.n_motors, axis=1)
    >>> src = CountsSource(act, body, 0.01, name="plan", hold_s=0.02)
    >>> src.start(np.zeros(act.n_motors, dtype=np.int64), 0.01)
    >>> src.n_lead_in, src.n_stop, src.n_cycles, src.table[:, 0].tolist()
    (0, 0, 9, [0, 10, 40, 80, 110, 120, 120, 120, 120])
    >>> src.start(np.full(act.n_motors, -500, dtype=np.int64), 0.01)  # from elsewhere
    >>> src.n_lead_in > 0, int(src.table[src.n_lead_in - 1, 0])
    (True, 0)
    """

    def __init__(
        self,
        limits: RopeModel,
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
        cls, limits: RopeModel, setpoints: Any, *, name: str = "plan", **kw: Any
    ) -> CountsSource:
        """The source of a plan's counts (the rope layer's ``PlanSetpoints``: its counts,
        control period, row labels, and its first step's configuration for the lead-in to
        go to).  ``kw`` as for the constructor (``hold_s``, ``info``); the info gets what
        the jerk bound costs the body (``jerk_bound_cost_s``, and the body's duration
        without it, ``duration_without_jerk_bound_s``)."""
        first = (setpoints.alpha_rad[0], setpoints.theta_rad[0])
        info = {
            **dict(kw.pop("info", None) or {}),
            "duration_without_jerk_bound_s": round(float(setpoints.law_duration_s), 6),
            "jerk_bound_cost_s": round(float(setpoints.jerk_cost_s), 6),
        }
        return cls(limits, setpoints.counts, setpoints.period_s, name=name,
                   label=setpoints.label, first_pose=first, info=info, **kw)  # fmt: skip

    def _row_name(self, row: int) -> str:
        """A row of the full table (lead-in, body, hold) as a message names it."""
        n_body = self.body.shape[0]
        if row < self.n_lead_in:
            return f"lead-in to {row_name(self.label, 0)}"
        if row - self.n_lead_in >= n_body + self.n_stop:
            return f"final hold after {row_name(self.label, n_body - 1)}"
        if row - self.n_lead_in >= n_body:
            return f"stop after {row_name(self.label, n_body - 1)}"
        return row_name(self.label, row - self.n_lead_in)

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
                lambda r: row_name(self.label, r),
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
            elif (arm := self.limits.whole_arm) is not None:
                # the whole rope layer: a line in joint space
                line = arm.joint_line(actual, body[0], to_pose=self.first_pose)
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
                f"{self.name}: lead-in to {row_name(self.label, 0)}: {exc}"
            ) from None
        # the arm on the way, by the rope model: the joint limits, and (the whole arm) the
        # rope tensions, which a line in counts (a subset's lead-in, the stop) can strain
        last = row_name(self.label, body.shape[0] - 1)
        parts = (
            (actual, lead, lead_poses, f"lead-in to {row_name(self.label, 0)}"),
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
