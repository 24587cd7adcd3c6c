"""The one path from a plan to motor counts: the plan's steps at the control rate.

A plan is a sequence of steps, each a configuration (``alpha``, ``theta`` per joint)
at a travel along the path.  Played at ``speed_mm_per_s``, the time of each step is its
*distance along the sequence of steps* (the sum of ``|travel change|`` so far) over the
speed, so a return leg (travel going back down) plays as well as the way in.  Between
steps the joint angles are interpolated linearly and every control slot's angles go
through the rope layer (:meth:`Actuation.counts_from_angles`).  Along an ``in`` phase
travel must increase step by step, along a ``return`` phase decrease; a hand-edited plan
whose travel goes the wrong way or repeats is refused naming the step.

Everything is checked before anything is played: the joint limits at every step, the
drum travel at every step and every control slot, and the motors' speed between control
slots.  Every message names the *plan step* (``plan step 41 (travel 205.0 mm): motor
j05r2 ...``), never a control-cycle row; each row of the table remembers the step it
came from (the step being approached; a row on a step is that step's).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> a = np.zeros((3, 12)); a[1] = 0.01                         # out and back
>>> sp = plan_setpoints(act, [0.0, 2.0, 0.0], a, np.zeros((3, 12)),
...                     period_s=0.01, speed_mm_per_s=100.0, phase=["in", "in", "return"])
>>> sp.n_cycles, sp.step_of_row.tolist()
(5, [0, 1, 1, 2, 2])
>>> bool((sp.counts[2] == sp.step_counts[1]).all() and (sp.counts[-1] == sp.counts[0]).all())
True
>>> sp.label(3)
'plan step 2 (travel 0.0 mm)'
>>> plan_setpoints(act, [0.0, 2.0, 1.0], a, a, period_s=0.01, speed_mm_per_s=100.0)
... # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.errors.RopeError: plan step 2 (travel 1.0 mm): travel goes back from 2.0 mm ...
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError

MAX_PLAN_DURATION_S = 3600.0  # default longest playback (bounds the table's memory)
# The most control slots (rows) a playback may have, whatever the control rate: 3600 s at
# 100 Hz fits; the (rows, motors) int64 table is then 115 MB for 36 motors.  Checked before
# the table is allocated; rows are converted (and their motor speeds checked) _BLOCK_ROWS at
# a time, so the temporaries stay a few tens of MB.
MAX_PLAYBACK_ROWS = 400_000
_BLOCK_ROWS = 32_768
PHASES = ("in", "return")
_ON_STEP_S = 1e-9  # a control slot this close to a step's time is on that step


def interpolate_rows(t_query: np.ndarray, t_knots: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation of every column of ``rows`` (knots, m) at ``t_query``
    (clamped to the knots' range; ``t_knots`` non-decreasing).

    >>> interpolate_rows(np.array([0.0, 0.5, 2.0]), np.array([0.0, 1.0]),
    ...                  np.array([[0.0, 10.0], [1.0, 20.0]]))
    array([[ 0. , 10. ],
           [ 0.5, 15. ],
           [ 1. , 20. ]])
    """
    t_knots = np.asarray(t_knots, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.float64)
    if len(t_knots) == 1:
        return np.repeat(rows[:1], len(t_query), axis=0)
    tq = np.clip(t_query, t_knots[0], t_knots[-1])
    i = np.clip(np.searchsorted(t_knots, tq, side="right") - 1, 0, len(t_knots) - 2)
    span = t_knots[i + 1] - t_knots[i]
    w = np.where(span > 0, (tq - t_knots[i]) / np.where(span > 0, span, 1.0), 1.0)
    return rows[i] + w[:, None] * (rows[i + 1] - rows[i])


@dataclass(frozen=True, eq=False)
class PlanSetpoints:
    """A plan's motor counts at the control rate, checked against every rope-layer limit.

    ``counts`` (cycles, motors) int64, one row per control slot from the plan's first
    step (time 0) to its last (``duration_s``); ``step_of_row`` (cycles,) the plan step
    each row came from; ``step_counts`` (S, motors) the counts at the steps themselves;
    ``step_time_s`` (S,) when each step is reached.  Arrays are read-only.
    """

    counts: np.ndarray
    step_of_row: np.ndarray
    time_s: np.ndarray
    step_counts: np.ndarray
    step_time_s: np.ndarray
    travel_mm: np.ndarray
    alpha_rad: np.ndarray
    theta_rad: np.ndarray
    period_s: float
    speed_mm_per_s: float

    @property
    def n_cycles(self) -> int:
        return int(self.counts.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.travel_mm.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.step_time_s[-1])

    def step_label(self, k: int) -> str:
        """``plan step 41 (travel 205.0 mm)``."""
        return _step_label(self.travel_mm, int(k))

    def label(self, row: int) -> str:
        """The plan step control-slot ``row`` came from, as :meth:`step_label` says it."""
        return self.step_label(int(self.step_of_row[int(row)]))

    def row_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, theta) (cycles, 12) of every row: the configurations ``counts`` encode."""
        n = self.alpha_rad.shape[1]
        ang = interpolate_rows(
            self.time_s, self.step_time_s, np.hstack([self.alpha_rad, self.theta_rad])
        )
        return ang[:, :n], ang[:, n:]


def _step_label(travel: np.ndarray, k: int) -> str:
    return f"plan step {k} (travel {float(travel[k]):.1f} mm)"


def _steps_label(travel: np.ndarray, first: int, last: int) -> str:
    if first >= last:
        return _step_label(travel, last)
    return (
        f"plan steps {first}-{last} (travel {float(travel[first]):.1f}-"
        f"{float(travel[last]):.1f} mm)"
    )


def _prefixed(where: str | None, text: str) -> str:
    return f"{where}: {text}" if where else text


def _raise_labelled(where: str | None, label: str, check: Any, *args: Any, **kw: Any) -> None:
    """Run the rope layer's check ``check(*args, **kw)`` on the one offending row and raise
    its message under ``label``."""
    try:
        check(*args, **kw)
    except RopeError as exc:
        raise RopeLimitError(_prefixed(where, f"{label}: {exc}")) from None
    raise RopeLimitError(_prefixed(where, f"{label}: outside the rope layer's limits"))


def _check_travel(travel: np.ndarray, phase: Sequence[str], where: str | None) -> None:
    """Travel increases step by step along ``in`` and decreases along ``return``."""
    if len(travel) < 2:
        return
    ret = np.array([p == "return" for p in phase], dtype=bool)
    change = np.diff(travel) * np.where(ret[1:], -1.0, 1.0)
    bad = np.flatnonzero(~(change > 0.0))
    if bad.size == 0:
        return
    k = int(bad[0]) + 1
    name = "return" if ret[k] else "in"
    prev = f"{float(travel[k - 1]):.1f} mm (plan step {k - 1})"
    what = (
        f"travel repeats {prev}"
        if travel[k] == travel[k - 1]
        else f"travel goes {'up' if name == 'return' else 'back'} from {prev}"
    )
    raise RopeError(_prefixed(where, f"{_step_label(travel, k)}: {what} within the '{name}' phase"))


def plan_setpoints(
    actuation: Actuation,
    travel_mm: Any,
    alpha_rad: Any,
    theta_rad: Any,
    *,
    period_s: float,
    speed_mm_per_s: float,
    phase: Sequence[str] | None = None,
    max_duration_s: float = MAX_PLAN_DURATION_S,
    where: str | None = None,
) -> PlanSetpoints:
    """The plan's (cycles, motors) counts at the control period ``period_s``, played at
    ``speed_mm_per_s`` along the sequence of steps, with the plan step of every row.

    ``travel_mm`` (S,), ``alpha_rad`` / ``theta_rad`` (S, 12); ``phase`` (S,) ``in`` /
    ``return`` (default all ``in``).  ``where`` (e.g. the plan file) starts every message.
    Raises :class:`RopeError` for bad arguments, travel that goes the wrong way or repeats
    within a phase, or a playback longer than ``max_duration_s``, and
    :class:`RopeLimitError` for a joint, drum-travel or motor-speed limit, naming the plan
    step.
    """
    if not (math.isfinite(period_s) and period_s > 0.0):
        raise RopeError(_prefixed(where, f"control period must be > 0 s, got {period_s}"))
    if not (math.isfinite(speed_mm_per_s) and speed_mm_per_s > 0.0):
        raise RopeError(_prefixed(where, f"speed must be > 0 mm/s, got {speed_mm_per_s}"))
    travel = np.asarray(travel_mm, dtype=np.float64)
    alpha = np.asarray(alpha_rad, dtype=np.float64)
    theta = np.asarray(theta_rad, dtype=np.float64)
    n_j = actuation.robot.n_joints
    s = travel.shape[0] if travel.ndim == 1 else -1
    if s < 1 or alpha.shape != (s, n_j) or theta.shape != (s, n_j):
        raise RopeError(
            _prefixed(
                where,
                f"plan steps must be travel (S,) and angles (S, {n_j}) with S >= 1, got "
                f"{travel.shape}, {alpha.shape}, {theta.shape}",
            )
        )
    if not (np.isfinite(travel).all() and np.isfinite(alpha).all() and np.isfinite(theta).all()):
        raise RopeError(_prefixed(where, "plan steps must be finite numbers"))
    phases = ("in",) * s if phase is None else tuple(str(p) for p in phase)
    if len(phases) != s or not set(phases) <= set(PHASES):
        raise RopeError(_prefixed(where, f"phase must be {s} of {PHASES}, got {phase!r}"))
    _check_travel(travel, phases, where)

    # the steps themselves: joint limits, then drum travel
    lim_a, lim_t = actuation.robot.limit_alpha, actuation.robot.limit_theta
    bad = ~((np.abs(alpha) < lim_a) & (np.abs(theta) < lim_t)).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        _raise_labelled(where, _step_label(travel, k), actuation.check_angles, alpha[k], theta[k])
    step_counts = actuation.counts_from_angles(alpha, theta, check=False)
    _check_positions(actuation, step_counts, lambda k: _step_label(travel, k), where)

    # time along the sequence of steps, and the control slots
    distance = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(travel)))))
    step_time = distance / speed_mm_per_s
    duration = float(step_time[-1])
    if not duration <= max_duration_s + period_s:
        raise RopeError(
            _prefixed(
                where,
                f"{duration:.4g} s at {speed_mm_per_s:g} mm/s exceeds the longest run of "
                f"{max_duration_s:g} s",
            )
        )
    cycles = duration / period_s
    if not cycles < MAX_PLAYBACK_ROWS - 1:
        raise RopeError(
            _prefixed(
                where,
                f"{duration:.4g} s at {speed_mm_per_s:g} mm/s is {cycles:.4g} control cycles of "
                f"{period_s:g} s, more than the {MAX_PLAYBACK_ROWS} a playback may have",
            )
        )
    n = math.floor(cycles + 1e-9) + 1
    t = np.minimum(np.arange(n, dtype=np.float64) * period_s, duration)
    if duration > 0.0 and (duration - t[-1] > _ON_STEP_S or n == 1):
        t = np.append(t, duration)  # the last row is the last step, however short the run
    knots = np.hstack([alpha, theta])
    counts = np.empty((t.shape[0], actuation.n_motors), dtype=np.int64)
    for lo in range(0, t.shape[0], _BLOCK_ROWS):
        ang = interpolate_rows(t[lo : lo + _BLOCK_ROWS], step_time, knots)
        counts[lo : lo + _BLOCK_ROWS] = actuation.counts_from_angles(
            ang[:, :n_j], ang[:, n_j:], check=False
        )
    del knots
    step_of_row = np.minimum(np.searchsorted(step_time, t - _ON_STEP_S, side="left"), s - 1)
    step_of_row[-1] = s - 1  # at the duration: the last step

    def row_label(r: int) -> str:
        return _step_label(travel, int(step_of_row[r]))

    _check_positions(actuation, counts, row_label, where)
    _check_rates(actuation, counts, period_s, travel, step_of_row, t, step_time, where)
    for arr in (counts, step_of_row, t, step_counts, step_time, travel, alpha, theta):
        arr.setflags(write=False)
    return PlanSetpoints(
        counts=counts,
        step_of_row=step_of_row,
        time_s=t,
        step_counts=step_counts,
        step_time_s=step_time,
        travel_mm=travel,
        alpha_rad=alpha,
        theta_rad=theta,
        period_s=float(period_s),
        speed_mm_per_s=float(speed_mm_per_s),
    )


def _check_positions(act: Actuation, counts: np.ndarray, label: Any, where: str | None) -> None:
    """Every row within the drum travel; the first one outside is named by ``label(row)``."""
    out = (counts < act.counts_min) | (counts > act.counts_max)
    if out.any():
        r = int(np.flatnonzero(out.any(axis=1))[0])
        _raise_labelled(where, label(r), act.check_counts, counts[r])


def _check_rates(
    act: Actuation,
    counts: np.ndarray,
    period_s: float,
    travel: np.ndarray,
    step_of_row: np.ndarray,
    t: np.ndarray,
    step_time: np.ndarray,
    where: str | None,
) -> None:
    """Every change from one control slot to the next within the motors' speed; the first
    too fast one is named by the plan steps it moves through."""
    r = 0  # the change from row r - 1 to row r is the first too fast one
    for lo in range(0, counts.shape[0] - 1, _BLOCK_ROWS):
        block = counts[lo : lo + _BLOCK_ROWS + 1]
        rate = np.abs(np.diff(block, axis=0)).astype(np.float64) / period_s
        fast = (rate > act.max_rate_counts_per_s).any(axis=1)
        if fast.any():
            r = lo + int(np.flatnonzero(fast)[0]) + 1
            break
    if r == 0:
        return
    j = int(step_of_row[r - 1])
    first = j + 1 if abs(step_time[j] - t[r - 1]) <= _ON_STEP_S else j
    label = _steps_label(travel, min(first, int(step_of_row[r])), int(step_of_row[r]))
    _raise_labelled(
        where, label, act.check_counts, counts[r], previous=counts[r - 1], dt_s=period_s
    )


__all__ = [
    "MAX_PLAN_DURATION_S",
    "MAX_PLAYBACK_ROWS",
    "PHASES",
    "PlanSetpoints",
    "interpolate_rows",
    "plan_setpoints",
]
