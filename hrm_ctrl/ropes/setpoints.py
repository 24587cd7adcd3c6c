"""The one path from a plan to motor counts: the plan's steps at the control rate.

A plan is a sequence of steps, each a configuration (``alpha``, ``theta`` per joint)
at a travel along the path.  Its playback is the time-parameterised trajectory of
:mod:`hrm_ctrl.ropes.trajectory`: the joint angles a smooth (C2) spline through every
step of a leg, as a function of the distance along the sequence of steps (the sum of
``|travel change|`` so far, so a return leg plays as well as the way in, each leg from
rest to rest), timed by TOPP-RA as fast as every rope motor's speed and acceleration
limit and the tip-speed cap ``speed_mm_per_s`` allow, and every control slot's
configuration through the rope layer (:meth:`Actuation.counts_from_angles`).  Along an
``in`` phase travel must increase step by step, along a ``return`` phase decrease; a
hand-edited plan whose travel goes the wrong way or repeats is refused naming the step.

Everything is checked before anything is played: the joint limits at every step and
every control slot, the drum travel at every step and every control slot, and the
motors' speed and acceleration between control slots (finite differences of the
integer counts, from rest and to rest).  Every message names the *plan step*
(``plan step 41 (travel 205.0 mm): motor j05r2 ...``), never a control-cycle row; each
row of the table remembers the step it came from (the step being approached; a row on
a step is that step's).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> a = np.zeros((3, 12)); a[1] = 0.01                         # out and back
>>> sp = plan_setpoints(act, [0.0, 2.0, 0.0], a, np.zeros((3, 12)),
...                     period_s=0.01, speed_mm_per_s=100.0, phase=["in", "in", "return"])
>>> k = int(np.flatnonzero(sp.step_of_row == 2)[0]) - 1         # the far end, at rest
>>> bool((sp.counts[k] == sp.step_counts[1]).all() and (sp.counts[-1] == sp.counts[0]).all())
True
>>> sp.label(k + 1)
'plan step 2 (travel 0.0 mm)'
>>> plan_setpoints(act, [0.0, 2.0, 1.0], a, a, period_s=0.01, speed_mm_per_s=100.0)
... # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.errors.RopeError: plan step 2 (travel 1.0 mm): travel goes back from 2.0 mm ...
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError
from hrm_ctrl.ropes.feedforward import Feedforward
from hrm_ctrl.ropes.trajectory import StepPath, step_path, time_parameterise

MAX_PLAN_DURATION_S = 3600.0  # default longest playback (bounds the table's memory)
# The tip-speed cap of a playback unless the operator gives one (hrm ropes, run, demo):
# 50 mm/s is a tenth of the arm's length a second; the motors are then far from their
# speed limit (the bent pipe needs 2 % of it).
DEFAULT_TIP_SPEED_MM_PER_S = 50.0
# The most control slots (rows) a playback may have, whatever the control rate: 3600 s at
# 100 Hz fits; the (rows, motors) int64 table is then 115 MB for 36 motors.  Checked before
# the table is allocated; rows are converted (and their motor speeds checked) _BLOCK_ROWS at
# a time, so the temporaries stay a few tens of MB.
MAX_PLAYBACK_ROWS = 400_000
_BLOCK_ROWS = 32_768
PHASES = ("in", "return")
# With a feed-forward (hrm_ctrl.ropes.feedforward) the time law uses this share of every
# motor's speed, acceleration and jerk limit, leaving the rest to the compensation, whose
# change along the rows is smoothed over this time (a moving average three times over,
# centred: where the friction turns at a reversal the compensation changes by up to a
# millimetre of rope within a few rows, more than a motor may accelerate).
FEEDFORWARD_LIMIT_SHARE = 0.8
FEEDFORWARD_SMOOTHING_S = 0.4
# ... its other terms' (gravity, stretch, play: smooth in the pose but for the play taken
# up, a step of a few tens of counts) over this time
FEEDFORWARD_SMOOTHING_LOADS_S = 0.1
# ... and it comes in over this time at the first step, at rest, from the counts at the
# pretension (a lead-in goes to those: the rope model's tensions along a lead-in stay in
# its command band; a compensated target's hold a sagging arm up, beyond that band's reach)
FEEDFORWARD_RAMP_S = 1.0
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
    step at rest (time 0, ``time_s``) to its last at rest (``duration_s``);
    ``step_of_row`` (cycles,) the plan step each row came from; ``step_counts`` (S,
    motors) the counts at the steps themselves; ``step_time_s`` (S,) when each step is
    passed; ``sigma_mm`` (cycles,) where each row is along the sequence of steps on
    ``path``.  ``speed_mm_per_s`` is the tip-speed cap.  Arrays are read-only.
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
    sigma_mm: np.ndarray  # (cycles,) where each row is along the sequence of steps (mm)
    path: StepPath
    #: the playback without the jerk bound (TOPP-RA's laws, whole periods; s)
    law_duration_s: float = 0.0
    #: rows at the first step, at rest, that bring a feed-forward in (0 without one)
    ramp_rows: int = 0
    #: (cycles, motors) int64 what a feed-forward added to each row (None without one):
    #: ``counts - compensation_counts`` are the rows' counts at the pretension, each one
    #: configuration (what the rope-consistency watch checks a compensated run against)
    compensation_counts: np.ndarray | None = None

    @property
    def n_cycles(self) -> int:
        return int(self.counts.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.travel_mm.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1])

    @property
    def jerk_cost_s(self) -> float:
        """What the motors' jerk bound adds to the playback (s)."""
        return self.duration_s - self.law_duration_s

    def step_label(self, k: int) -> str:
        """``plan step 41 (travel 205.0 mm)``."""
        return _step_label(self.travel_mm, int(k))

    def label(self, row: int) -> str:
        """The plan step control-slot ``row`` came from, as :meth:`step_label` says it."""
        return self.step_label(int(self.step_of_row[int(row)]))

    def row_travel_mm(self) -> np.ndarray:
        """(cycles,) the travel along the known path of every row (between two steps of a
        leg, as far from the earlier step as the row is along the sequence of steps)."""
        d = self.path.distance_mm
        k = np.clip(np.searchsorted(d, self.sigma_mm, side="right") - 1, 0, d.shape[0] - 1)
        k1 = np.minimum(k + 1, d.shape[0] - 1)
        sign = np.sign(self.travel_mm[k1] - self.travel_mm[k])
        return self.travel_mm[k] + sign * (self.sigma_mm - d[k])

    def row_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, theta) (cycles, 12) of every row: the configurations ``counts`` encode."""
        return self.path.angles_at(self.sigma_mm)


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
    progress: Callable[[float], None] | None = None,
    feedforward: Feedforward | None = None,
) -> PlanSetpoints:
    """The plan's (cycles, motors) counts at the control period ``period_s``, played as
    fast as the motors' speed and acceleration limits allow with the arm's tip at most
    ``speed_mm_per_s``, with the plan step of every row.

    ``travel_mm`` (S,), ``alpha_rad`` / ``theta_rad`` (S, 12); ``phase`` (S,) ``in`` /
    ``return`` (default all ``in``).  ``where`` (e.g. the plan file) starts every message.
    ``feedforward`` (:class:`~hrm_ctrl.ropes.feedforward.Feedforward`; None: off) replaces
    every row's and step's counts by those that hold its configuration against the
    arm's loads (gravity, rope stretch, capstan friction along the rows' rope travel,
    joint play) before the limits are checked, brought in at the first step over
    :data:`FEEDFORWARD_RAMP_S` (``ramp_rows`` more rows at the start).
    Raises :class:`RopeError` for bad arguments, travel that goes the wrong way or repeats
    within a phase, or a playback longer than ``max_duration_s``, and
    :class:`RopeLimitError` for a joint, drum-travel, motor-speed or -acceleration limit,
    naming the plan step.
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
    out = actuation.rounded_outside(step_counts, alpha, theta)
    if out is not None:
        raise RopeLimitError(
            _prefixed(where, f"{_step_label(travel, out[0])}: rounded to whole counts: {out[1]}")
        )
    _check_positions(actuation, step_counts, lambda k: _step_label(travel, k), where)

    # the path through the steps, and its time law (the tip speed caps its duration from
    # below: too long a playback is refused before anything is parameterised)
    path = step_path(travel, alpha, theta, phases)
    _check_duration(path.length_mm / speed_mm_per_s, speed_mm_per_s, max_duration_s, period_s,
                    where)  # fmt: skip
    try:
        traj = time_parameterise(
            actuation if feedforward is None else _limits_share(actuation, FEEDFORWARD_LIMIT_SHARE),
            path,
            period_s=period_s,
            tip_speed_mm_per_s=speed_mm_per_s,
            max_rows=MAX_PLAYBACK_ROWS,
            progress=progress,
        )
    except RopeError as exc:
        raise type(exc)(_prefixed(where, str(exc))) from None
    _check_duration(traj.duration_s, speed_mm_per_s, max_duration_s, period_s, where)
    counts, step_of_row, t = traj.counts, traj.step_of_row, traj.time_s
    sigma, step_t, ramp = traj.sigma_mm, traj.step_time_s, 0
    added: np.ndarray | None = None
    if feedforward is not None:
        plain = counts
        counts, step_counts = _compensated(feedforward, path, sigma, counts, t, step_t, period_s)
        _check_positions(actuation, step_counts, lambda k: _step_label(travel, k), where)
        ramp = max(1, round(FEEDFORWARD_RAMP_S / period_s))
        plain_first = actuation.counts_from_angles(alpha[0], theta[0], check=False)
        s = np.arange(ramp, dtype=np.float64)[:, None] / ramp
        blend = s**3 * (10.0 - 15.0 * s + 6.0 * s**2)  # smootherstep: from and to rest
        ramp_rows = np.rint(plain_first + blend * (counts[0] - plain_first)).astype(np.int64)
        plain = np.concatenate([np.repeat(plain_first[None, :], ramp, axis=0), plain])
        counts = np.concatenate([ramp_rows, counts])
        counts.setflags(write=False)
        added = counts - plain
        added.setflags(write=False)
        step_of_row = np.concatenate([np.zeros(ramp, step_of_row.dtype), step_of_row])
        t = np.concatenate([np.arange(ramp) * period_s, t + ramp * period_s])
        sigma = np.concatenate([np.full(ramp, sigma[0]), sigma])
        step_t = step_t + ramp * period_s

    def row_label(r: int) -> str:
        return _step_label(travel, int(step_of_row[r]))

    _check_positions(actuation, counts, row_label, where)
    _check_rates(actuation, counts, period_s, travel, step_of_row, t, step_t, where)
    for arr in (step_counts, travel, alpha, theta):
        arr.setflags(write=False)
    return PlanSetpoints(
        counts=counts,
        step_of_row=step_of_row,
        time_s=t,
        step_counts=step_counts,
        step_time_s=step_t,
        travel_mm=travel,
        alpha_rad=alpha,
        theta_rad=theta,
        period_s=float(period_s),
        speed_mm_per_s=float(speed_mm_per_s),
        sigma_mm=sigma,
        path=path,
        law_duration_s=traj.law_duration_s + ramp * period_s,
        ramp_rows=ramp,
        compensation_counts=added,
    )


def _limits_share(act: Actuation, share: float) -> Actuation:
    """``act`` with ``share`` of every motor's speed, acceleration and jerk limit."""
    return dataclasses.replace(
        act,
        max_rate_counts_per_s=act.max_rate_counts_per_s * share,
        max_accel_counts_per_s2=act.max_accel_counts_per_s2 * share,
        max_jerk_counts_per_s3=act.max_jerk_counts_per_s3 * share,
    )


def smoothed_rows(rows: np.ndarray, width: int, passes: int = 3) -> np.ndarray:
    """Every column of ``rows`` (rows, m) averaged over ``width`` rows centred on each,
    ``passes`` times (the ends held: the table starts and ends at rest).

    >>> smoothed_rows(np.array([[0.0], [0.0], [3.0], [0.0], [0.0]]), 3, 1)[:, 0].tolist()
    [0.0, 1.0, 1.0, 1.0, 0.0]
    """
    out = np.asarray(rows, dtype=np.float64)
    if width <= 1 or out.shape[0] < 2:
        return out.copy()
    half = width // 2
    for _ in range(passes):
        padded = np.concatenate([np.repeat(out[:1], half, 0), out, np.repeat(out[-1:], half, 0)])
        c = np.cumsum(np.concatenate([np.zeros((1, out.shape[1])), padded]), axis=0)
        out = (c[2 * half + 1 :] - c[: -2 * half - 1]) / (2 * half + 1)
    return out


def _compensated(
    ff: Feedforward,
    path: StepPath,
    sigma: np.ndarray,
    counts: np.ndarray,
    t: np.ndarray,
    step_t: np.ndarray,
    period_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The rows' counts with the feed-forward added (its change along the rows smoothed:
    the friction's share over :data:`FEEDFORWARD_SMOOTHING_S`, the rest over
    :data:`FEEDFORWARD_SMOOTHING_LOADS_S`; in time order: the friction's direction is the
    rows' rope travel, at the first row the ramp-in's, from the counts at the
    pretension) and every step's (the row at the step's time)."""
    a, th = path.angles_at(sigma)
    held = ff.counts(a, th)
    motors = ff.actuation.motors
    ramp = motors.unstretched_from_counts(held[0]) - motors.unstretched_from_counts(counts[0])
    beyond = ff.physics.presliding_mm * ff.physics.static_ratio  # the ramp slides the rope
    if (np.abs(ramp) > beyond).any():
        first = np.where(np.abs(ramp) > beyond, np.sign(ramp), np.nan)  # else: as planned
        held = ff.counts(a, th, first)
    short = max(1, round(FEEDFORWARD_SMOOTHING_LOADS_S / period_s))
    if ff.capstan:  # the friction's share smoothed over the longer time, the rest less
        loads = dataclasses.replace(ff, capstan=False).counts(a, th)
        width = max(1, round(FEEDFORWARD_SMOOTHING_S / period_s))
        offset = smoothed_rows(loads - counts, short) + smoothed_rows(held - loads, width)
    else:
        offset = smoothed_rows(held - counts, short)
    out = counts + np.rint(offset).astype(np.int64)
    at = np.clip(np.searchsorted(t, np.asarray(step_t) - _ON_STEP_S), 0, len(t) - 1)
    steps = out[at]
    out.setflags(write=False)
    return out, steps


def _check_duration(
    duration: float, speed: float, max_duration_s: float, period_s: float, where: str | None
) -> None:
    if not duration <= max_duration_s + period_s:
        raise RopeError(
            _prefixed(
                where,
                f"{duration:.4g} s at {speed:g} mm/s exceeds the longest run of "
                f"{max_duration_s:g} s",
            )
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
    """Every change from one control slot to the next within the motors' speed, every
    change of that speed within their acceleration and every change of that within their
    jerk, from rest and to rest (the time law makes it so; this checks the integers that
    are sent); the first offending change is named by the plan steps it moves through."""
    c = np.concatenate([counts[:1], counts, counts[-1:]], axis=0)  # at rest before, after
    r = 0  # rows of c: the change ending at row r of c is the first offending one
    jerk_at = -1  # the row of counts whose third difference is the first too big
    for lo in range(0, c.shape[0] - 1, _BLOCK_ROWS):
        block = c[lo : lo + _BLOCK_ROWS + 2]
        d1 = np.diff(block, axis=0).astype(np.float64)
        fast = (np.abs(d1) / period_s > act.max_rate_counts_per_s).any(axis=1)
        hard = np.zeros_like(fast)
        d2 = np.diff(d1, axis=0)
        hard[1:] = (np.abs(d2) / period_s**2 > act.max_accel_counts_per_s2).any(axis=1)
        bad = fast | hard
        if bad.any():
            r = lo + int(np.flatnonzero(bad)[0]) + 1
            break
    if r == 0:
        jerk_at = _first_jerk(act, counts, period_s)
        if jerk_at < 0:
            return
        r = jerk_at + 1
    if jerk_at >= 0:
        row = min(jerk_at, counts.shape[0] - 1)
        j = int(step_of_row[max(row - 1, 0)])
        label = _steps_label(travel, j, int(step_of_row[row]))
        c3 = np.concatenate([counts[:1]] * 3 + [counts] + [counts[-1:]] * 3, axis=0)
        d3 = np.abs(np.diff(c3[jerk_at : jerk_at + 4], n=3, axis=0))[0] / period_s**3
        i = int(np.argmax(d3 / act.max_jerk_counts_per_s3))
        raise RopeLimitError(
            _prefixed(
                where,
                f"{label}: motor {act.motor_label(i)}: jerks {d3[i]:.4g} counts/s^3, more than "
                f"the motor's {float(act.max_jerk_counts_per_s3[i]):.4g} counts/s^3",
            )
        )
    row = min(max(r - 1, 0), counts.shape[0] - 1)  # back to rows of counts
    prev = max(row - 1, 0)
    j = int(step_of_row[prev])
    first = j + 1 if abs(step_time[j] - t[prev]) <= _ON_STEP_S else j
    label = _steps_label(travel, min(first, int(step_of_row[row])), int(step_of_row[row]))
    lo = max(row - 2, 0)
    _raise_labelled(
        where, label, act.check_counts, counts[lo : row + 1], previous=None, dt_s=period_s
    )


def _first_jerk(act: Actuation, counts: np.ndarray, period_s: float) -> int:
    """The first row of a rest-to-rest table (rows held three periods before and after)
    whose third difference ``r[k] - 3 r[k-1] + 3 r[k-2] - r[k-3]`` exceeds a motor's
    jerk limit (index into the table padded with two held rows before: clipped by the
    caller), or -1."""
    j_lim = np.asarray(act.max_jerk_counts_per_s3, dtype=np.float64) * period_s**3
    n = counts.shape[0]
    for lo in range(0, n + 3, _BLOCK_ROWS):
        idx = np.arange(lo, min(lo + _BLOCK_ROWS + 3, n + 6))
        block = counts[np.clip(idx - 3, 0, n - 1)].astype(np.int64)
        d3 = np.abs(np.diff(block, n=3, axis=0))
        bad = (d3 > j_lim).any(axis=1)
        if bad.any():
            return lo + int(np.flatnonzero(bad)[0])
    return -1


__all__ = [
    "DEFAULT_TIP_SPEED_MM_PER_S",
    "MAX_PLAN_DURATION_S",
    "MAX_PLAYBACK_ROWS",
    "PHASES",
    "PlanSetpoints",
    "interpolate_rows",
    "plan_setpoints",
]
