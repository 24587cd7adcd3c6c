"""Time parameterisation of a plan: the motor counts of every control cycle, every rope
motor within its speed and acceleration limits and the arm's tip within a speed cap.

**The path.**  A plan is a sequence of steps, each a configuration (24 joint angles) at a
travel along the known path.  The position along the *sequence of steps* is the distance
``sigma`` (the sum of ``|travel change|`` so far, in mm; a return leg adds to it too).  The
plan is cut into *legs* where its phase changes (``in``, then ``return``): each leg starts
and ends at rest.  Within a leg the joint angles are a C2 cubic spline of ``sigma``
through every step (``not-a-knot``; two steps: a straight line), so the path passes every
plan step exactly and its curvature is finite (a piecewise-linear path has a corner at
every step, which only a stop at every step could follow with finite acceleration).  The
motor counts along it, ``q(sigma)``, go through the rope layer (exact rope lengths at the
pretension), and every control cycle's counts are the rope layer's counts of the
configuration there, so every row is one configuration of the arm.

**The time law** (TOPP-RA: Pham & Pham, "A New Approach to Time-Optimal Path
Parameterization based on Reachability Analysis", IEEE T-RO 2018; the ``toppra``
package).  With ``x = sigma_dot**2`` and ``u = sigma_ddot``, a motor's speed and
acceleration along the path are

    q_dot = q'(sigma) sigma_dot,        q_ddot = q'(sigma) u + q''(sigma) x,

so the speed limits bound ``x`` and the acceleration limits are linear in ``(u, x)``;
TOPP-RA finds the fastest ``x(sigma)`` within them on a grid of ``sigma`` (at least two
grid intervals per plan step, at most ``MAX_GRID_SPACING_MM`` apart), ``x`` linear
between gridpoints (constant ``u``).  The tip-speed cap bounds ``x`` too:
``sigma_dot <= v_tip``.  A plan's travel is the tip's path length along the known path
(the planner puts the arm's end point on the path at that travel: along the bent pipe
the end point moves 0.99987-1.0000 mm per mm of travel), so this is the tip's speed;
for a hand-made plan whose steps do not follow the path it caps the travel rate.
``q'`` and ``q''`` come from a cubic spline of the (unrounded) counts through the
gridpoints.

**Exact on the sent integers.**  TOPP-RA holds the limits at the gridpoints, and the
counts are rounded; a sampled speed ``|r[k+1] - r[k]| / T`` is at most the continuous
peak speed plus one count per period, a second difference
``|r[k+1] - 2 r[k] + r[k-1]| / T**2`` at most the peak acceleration plus two counts per
period squared.  So the plan is made for ``margin * (v - 1/T)`` and
``margin * (a - 2/T**2)`` (margin 0.95), every leg's duration rounded up to whole control
periods (time stretched by at most one period: slower is within the limits), and the
integer table checked by finite differences, from rest and to rest; a leg that still
breaks a limit anywhere between gridpoints is stretched in time by what it breaks and
sampled again (speed scales with 1/f, acceleration with 1/f**2).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> a = np.zeros((3, 12)); a[1] = 0.01; a[2] = 0.03
>>> path = step_path([0.0, 5.0, 10.0], a, np.zeros((3, 12)))
>>> tr = time_parameterise(act, path, period_s=0.01, tip_speed_mm_per_s=50.0)
>>> tr.counts.dtype.name, bool(0.2 <= tr.duration_s <= 0.35)    # 10 mm at <= 50 mm/s
('int64', True)
>>> bool((tr.counts[0] == act.counts_from_angles(a[0], np.zeros(12))).all())
True
>>> v, acc = finite_differences(tr.counts, 0.01)
>>> bool((v <= act.max_rate_counts_per_s).all() and (acc <= act.max_accel_counts_per_s2).all())
True
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError

DEFAULT_MARGIN = 0.95  # the share of the (rounding-corrected) limits a plan is made for
GRID_PER_STEP = 2  # TOPP-RA grid intervals per plan step, at least
MAX_GRID_SPACING_MM = 2.5  # and at most this far apart along the sequence of steps
END_REFINEMENTS = 10  # the grid's first and last intervals halved this often (2.4 um last)
MAX_STRETCH_TRIES = 6  # time stretches of a leg that breaks a limit between gridpoints
STRETCH_EXTRA = 1.02  # each stretch 2 % more than the worst excess asks for
_BLOCK_ROWS = 32_768  # rows mapped through the rope layer at a time


@dataclass(frozen=True, eq=False)
class StepPath:
    """The geometric path through a plan's steps (see the module docstring).

    ``distance_mm`` (S,) the position ``sigma`` of every step along the sequence of
    steps; ``legs`` the (first, last) step of every leg; ``splines`` the joint angles
    (alpha then theta) of each leg as a function of ``sigma - distance_mm[first]``.
    """

    distance_mm: np.ndarray
    travel_mm: np.ndarray
    alpha_rad: np.ndarray
    theta_rad: np.ndarray
    legs: tuple[tuple[int, int], ...]
    splines: tuple[Any, ...]

    def step_label(self, k: int) -> str:
        """``plan step 41 (travel 205.0 mm)``."""
        return f"plan step {int(k)} (travel {float(self.travel_mm[int(k)]):.1f} mm)"

    def step_approached(self, sigma_mm: Any) -> np.ndarray:
        """The plan step each position is approaching (a position on a step: that step)."""
        sig = np.asarray(sigma_mm, dtype=np.float64)
        d = self.distance_mm
        return np.minimum(np.searchsorted(d, sig - 1e-9, side="left"), d.shape[0] - 1)

    @property
    def n_steps(self) -> int:
        return int(self.distance_mm.shape[0])

    @property
    def length_mm(self) -> float:
        return float(self.distance_mm[-1])

    def leg_angles(self, leg: int, local_mm: np.ndarray) -> np.ndarray:
        """(m, 24) angles (alpha then theta) at ``local_mm`` along leg ``leg``."""
        return np.asarray(self.splines[leg](local_mm), dtype=np.float64)

    def angles_at(self, sigma_mm: Any) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, theta) (m, 12) at positions ``sigma_mm`` (m,) along the sequence of
        steps; a position on a step is that step's configuration exactly."""
        sig = np.asarray(sigma_mm, dtype=np.float64).reshape(-1)
        n = self.alpha_rad.shape[1]
        out = np.empty((sig.shape[0], 2 * n))
        d = self.distance_mm
        if not self.legs:
            out[:] = np.hstack([self.alpha_rad[0], self.theta_rad[0]])
        else:
            ends = np.array([d[last] for _first, last in self.legs])
            leg = np.minimum(np.searchsorted(ends, sig, side="left"), len(self.legs) - 1)
            for j in np.unique(leg):
                sel = leg == j
                first = self.legs[int(j)][0]
                out[sel] = self.leg_angles(int(j), sig[sel] - d[first])
        k = np.minimum(np.searchsorted(d, sig), d.shape[0] - 1)
        on = d[k] == sig
        out[on, :n] = self.alpha_rad[k[on]]
        out[on, n:] = self.theta_rad[k[on]]
        return out[:, :n], out[:, n:]


def step_path(
    travel_mm: Any, alpha_rad: Any, theta_rad: Any, phase: Sequence[str] | None = None
) -> StepPath:
    """The path through plan steps (travel (S,), angles (S, n)), cut into legs where the
    phase changes; travel is taken as checked (monotonic within each phase).

    >>> p = step_path([0.0, 2.0, 0.0], np.zeros((3, 12)), np.zeros((3, 12)),
    ...               ["in", "in", "return"])
    >>> p.legs, p.distance_mm.tolist()
    (((0, 1), (1, 2)), [0.0, 2.0, 4.0])
    """
    travel = np.asarray(travel_mm, dtype=np.float64)
    alpha = np.asarray(alpha_rad, dtype=np.float64)
    theta = np.asarray(theta_rad, dtype=np.float64)
    s = travel.shape[0]
    phases = ("in",) * s if phase is None else tuple(phase)
    distance = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(travel)))))
    cuts = [k - 1 for k in range(1, s) if phases[k] != phases[k - 1]]
    bounds = [0, *cuts, s - 1]
    legs = tuple((a, b) for a, b in itertools.pairwise(bounds) if b > a)
    knots = np.hstack([alpha, theta])
    splines = []
    for first, last in legs:
        x = distance[first : last + 1] - distance[first]
        splines.append(CubicSpline(x, knots[first : last + 1], axis=0, bc_type="not-a-knot"))
    for arr in (distance, travel, alpha, theta):
        arr.setflags(write=False)
    return StepPath(distance, travel, alpha, theta, legs, tuple(splines))


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A plan's motor counts at the control period (read-only arrays).

    ``counts`` (rows, motors) int64, one row per control cycle from the first step at
    rest (time 0) to the last at rest (``duration_s``); ``time_s`` (rows,);
    ``sigma_mm`` (rows,) where each row is along the sequence of steps;
    ``step_of_row`` (rows,) the plan step each row came from (the step being
    approached; a row on a step is that step's); ``step_time_s`` (S,) when each step is
    passed; ``leg_rows`` the (first, last) row of each leg.
    """

    counts: np.ndarray
    time_s: np.ndarray
    sigma_mm: np.ndarray
    step_of_row: np.ndarray
    step_time_s: np.ndarray
    leg_rows: tuple[tuple[int, int], ...]
    period_s: float
    tip_speed_mm_per_s: float
    #: each leg's jerk window (s; 0: not jerk-limited)
    jerk_window_s: tuple[float, ...] = ()
    #: the legs' TOPP-RA laws, each rounded up to whole periods: the playback without the
    #: jerk bound (before any stretch)
    law_duration_s: float = 0.0

    @property
    def jerk_cost_s(self) -> float:
        """What the jerk bound adds to the playback: ``duration_s - law_duration_s``."""
        return self.duration_s - self.law_duration_s

    @property
    def n_rows(self) -> int:
        return int(self.counts.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1])


@dataclass(frozen=True)
class _Leg:
    """One leg's time law: gridpoints ``s`` (local mm), the speed ``sd`` (mm/s) along
    the path at them, and the time at which each is passed (before any stretch);
    ``q1``/``q2`` (N+1, motors) the counts' first and second derivatives along the path
    there; ``window_s`` the jerk window (the position is TOPP-RA's averaged over the
    last ``window_s``; 0: TOPP-RA's law itself)."""

    s: np.ndarray
    sd: np.ndarray
    t_grid: np.ndarray  # (N+1,) unstretched time at each gridpoint
    q1: np.ndarray
    q2: np.ndarray
    window_s: float = 0.0

    @property
    def law_duration_s(self) -> float:
        """TOPP-RA's duration (without the jerk window)."""
        return float(self.t_grid[-1])

    @property
    def duration_unstretched_s(self) -> float:
        return float(self.t_grid[-1]) + self.window_s


def finite_differences(
    counts: np.ndarray, period_s: float, *, at_rest: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Per motor, the largest speed ``|r[k+1] - r[k]| / T`` and acceleration
    ``|r[k+1] - 2 r[k] + r[k-1]| / T**2`` of an integer table (rows, motors); with
    ``at_rest`` the table is taken to start and end at rest (its first and last rows
    held before and after).

    >>> finite_differences(np.array([[0], [1], [3]]), 1.0)
    (array([2.]), array([2.]))
    """
    c = np.asarray(counts, dtype=np.int64)
    if at_rest:
        c = np.concatenate([c[:1], c, c[-1:]], axis=0)
    d1 = np.diff(c, axis=0)
    v = np.abs(d1).max(axis=0) / period_s if d1.shape[0] else np.zeros(c.shape[1])
    d2 = np.diff(d1, axis=0)
    a = np.abs(d2).max(axis=0) / period_s**2 if d2.shape[0] else np.zeros(c.shape[1])
    return v.astype(np.float64), a.astype(np.float64)


def finite_jerk(counts: np.ndarray, period_s: float, *, at_rest: bool = True) -> np.ndarray:
    """Per motor, the largest jerk ``|r[k+1] - 3 r[k] + 3 r[k-1] - r[k-2]| / T**3`` of
    an integer table (rows, motors); with ``at_rest`` the table is taken to start and end
    at rest (its first and last rows held before and after).

    >>> finite_jerk(np.array([[0], [1], [3]]), 1.0)    # 0 0 0 1 3 3 3: 1 0 -3 2
    array([3.])
    """
    c = np.asarray(counts, dtype=np.int64)
    if at_rest:
        c = np.concatenate([c[:1], c[:1], c, c[-1:], c[-1:]], axis=0)
    d3 = np.diff(c, n=3, axis=0)
    j = np.abs(d3).max(axis=0) / period_s**3 if d3.shape[0] else np.zeros(c.shape[1])
    return np.asarray(j, dtype=np.float64)


def _float_counts(act: Actuation, angles: np.ndarray) -> np.ndarray:
    """Unrounded counts at the pretension (the rope layer's affine map of the lengths)."""
    n = act.robot.n_joints
    return act.pre_c0 - act.pre_k * act.rope_lengths(angles[:, :n], angles[:, n:])


def _leg_grid(distance: np.ndarray, first: int, last: int) -> np.ndarray:
    """Gridpoints (local mm) of a leg: every step, each step interval cut into at least
    ``GRID_PER_STEP`` parts at most ``MAX_GRID_SPACING_MM`` long, finer at both ends.

    >>> g = _leg_grid(np.array([0.0, 5.0]), 0, 1)
    >>> g.size, g[:3].tolist(), float(g[-1])
    (23, [0.0, 0.00244140625, 0.0048828125], 5.0)
    """
    x = distance[first : last + 1] - distance[first]
    h = np.diff(x)
    parts = np.maximum(GRID_PER_STEP, np.ceil(h / MAX_GRID_SPACING_MM)).astype(np.int64)
    frac = [np.arange(p) / p for p in parts.tolist()]
    grid = np.concatenate([x[i] + h[i] * f for i, f in enumerate(frac)] + [x[-1:]])
    # near the ends, where the leg starts and stops, halve the spacing END_REFINEMENTS
    # times: x is linear between gridpoints, so the ramp from rest could otherwise take no
    # less than one whole grid interval, whatever the motors could do
    h0, h1 = grid[1] - grid[0], grid[-1] - grid[-2]
    halves = 0.5 ** np.arange(1, END_REFINEMENTS + 1)
    return np.unique(np.concatenate([grid, grid[0] + h0 * halves, grid[-1] - h1 * halves]))


class _GridPath:
    """The counts path as toppra sees it: derivatives precomputed at the gridpoints."""

    def __init__(self, grid: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> None:
        self._grid, self._q1, self._q2 = grid, q1, q2

    @property
    def dof(self) -> int:
        return int(self._q1.shape[1])

    @property
    def path_interval(self) -> np.ndarray:
        return np.array([self._grid[0], self._grid[-1]])

    def __call__(self, ss: Any, order: int = 0) -> np.ndarray:
        ss = np.asarray(ss, dtype=np.float64)
        if ss.shape != self._grid.shape or not np.array_equal(ss, self._grid):
            raise RopeError("time parameterisation: the path is known at its gridpoints only")
        if order == 1:
            return self._q1
        if order == 2:
            return self._q2
        raise RopeError(f"time parameterisation: no derivative of order {order} here")


def _toppra_leg(
    act: Actuation,
    path: StepPath,
    leg: int,
    v_plan: np.ndarray,
    a_plan: np.ndarray,
    v_tip: float,
    label: str,
    j_path: np.ndarray | None = None,
) -> _Leg | None:
    """TOPP-RA of one leg (rest to rest); with ``j_path`` (counts/s^3 per motor) the
    speed along the path is capped where the path's own third derivative would jerk a
    motor by more than that at it (``|d3q/ds3| sigma_dot**3 <= j_path``), and None
    returned where that cap is nowhere below the others."""
    import toppra.algorithm as ta
    import toppra.constraint as tc

    first, last = path.legs[leg]
    grid = _leg_grid(path.distance_mm, first, last)
    ang = path.leg_angles(leg, grid)
    q = CubicSpline(grid, _float_counts(act, ang), axis=0, bc_type="not-a-knot")
    q1, q2 = q(grid, 1), q(grid, 2)
    with np.errstate(divide="ignore"):
        sd_max = np.minimum(np.min(v_plan / np.abs(q1), axis=1), v_tip)
        if j_path is not None:  # d3q/ds3, constant between gridpoints: the larger side's
            mid = np.abs(q(0.5 * (grid[:-1] + grid[1:]), 3))
            q3 = np.concatenate([mid[:1], np.maximum(mid[:-1], mid[1:]), mid[-1:]])
            sd_jerk = np.min(np.cbrt(j_path / q3), axis=1)
            if not (sd_jerk < sd_max).any():
                return None
            sd_max = np.minimum(sd_max, sd_jerk)
    xbound = np.stack([np.zeros_like(sd_max), sd_max**2], axis=1)

    class _SpeedBound(tc.LinearConstraint):  # type: ignore[misc]
        """Motor speeds and the tip cap as one bound on x = sigma_dot^2 per gridpoint."""

        def compute_constraint_params(self, _path: Any, _grid: Any, *a: Any, **k: Any) -> Any:
            return None, None, None, None, None, None, xbound

    acc = tc.JointAccelerationConstraint(
        np.stack([-a_plan, a_plan], axis=1), tc.DiscretizationType.Collocation
    )
    algo = ta.TOPPRA(
        [_SpeedBound(), acc], _GridPath(grid, q1, q2), gridpoints=grid, solver_wrapper="seidel"
    )
    result = algo.compute_parameterization(0.0, 0.0)
    sd_sq = None if result[1] is None else np.asarray(result[1], dtype=np.float64)
    if sd_sq is None or not np.isfinite(sd_sq).all():
        raise RopeLimitError(f"{label}: no time law within the motors' limits (TOPP-RA failed)")
    sd = np.maximum(sd_sq, 0.0)
    sd[0] = sd[-1] = 0.0
    h = np.diff(grid)
    vsum = sd[:-1] + sd[1:]
    if not (vsum > 0.0).all():
        raise RopeLimitError(f"{label}: the time law stops inside the leg (TOPP-RA)")
    t_grid = np.concatenate(([0.0], np.cumsum(2.0 * h / vsum)))
    return _Leg(grid, sd, t_grid, q1, q2)


def _leg_label(path: StepPath, j: int) -> str:
    first, last = path.legs[j]
    return (
        f"plan steps {first}-{last} (travel {float(path.travel_mm[first]):.1f}-"
        f"{float(path.travel_mm[last]):.1f} mm)"
    )


def _law_positions(leg: _Leg, tau: np.ndarray) -> np.ndarray:
    """Local positions (mm) of TOPP-RA's law at times ``tau`` (constant acceleration
    between gridpoints: sigma_dot^2 linear in sigma)."""
    s, sd, tg = leg.s, leg.sd, leg.t_grid
    i = np.clip(np.searchsorted(tg, tau, side="right") - 1, 0, s.shape[0] - 2)
    h = s[i + 1] - s[i]
    u = (sd[i + 1] ** 2 - sd[i] ** 2) / (2.0 * h)
    dt = np.clip(tau - tg[i], 0.0, None)
    pos = s[i] + sd[i] * dt + 0.5 * u * dt * dt
    return np.clip(pos, s[i], s[i + 1])


def _law_integral(leg: _Leg, tau: np.ndarray) -> np.ndarray:
    """``int_0^tau sigma(t) dt`` (mm s) of TOPP-RA's law, at rest at 0 before ``tau = 0``
    and at its end after its duration."""
    s, sd, tg = leg.s, leg.sd, leg.t_grid
    h = np.diff(s)
    u = (sd[1:] ** 2 - sd[:-1] ** 2) / (2.0 * h)
    dtg = np.diff(tg)
    pieces = s[:-1] * dtg + sd[:-1] * dtg**2 / 2.0 + u * dtg**3 / 6.0
    cum = np.concatenate(([0.0], np.cumsum(pieces)))
    t = np.clip(tau, 0.0, tg[-1])
    i = np.clip(np.searchsorted(tg, t, side="right") - 1, 0, s.shape[0] - 2)
    dt = np.clip(t - tg[i], 0.0, dtg[i])
    inner = cum[i] + s[i] * dt + sd[i] * dt**2 / 2.0 + u[i] * dt**3 / 6.0
    return inner + s[-1] * np.clip(tau - tg[-1], 0.0, None)


def _leg_positions(leg: _Leg, tau: np.ndarray) -> np.ndarray:
    """Local positions (mm) at unstretched times ``tau``: TOPP-RA's law averaged over the
    jerk window (a moving average: speed and acceleration are averages of the law's, the
    third derivative the change of its acceleration across the window over its length)."""
    w = leg.window_s
    if w <= 0.0:
        return _law_positions(leg, tau)
    pos = (_law_integral(leg, tau) - _law_integral(leg, tau - w)) / w
    return np.clip(pos, 0.0, leg.s[-1])


def _leg_times(leg: _Leg, local: np.ndarray) -> np.ndarray:
    """Unstretched times at which local positions (mm) are passed."""
    if leg.window_s > 0.0:  # the average is increasing: bisection
        lo = np.zeros_like(local, dtype=np.float64)
        hi = np.full_like(lo, leg.duration_unstretched_s)
        for _ in range(64):
            mid = 0.5 * (lo + hi)
            below = _leg_positions(leg, mid) < local
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return hi
    s, sd, tg = leg.s, leg.sd, leg.t_grid
    i = np.clip(np.searchsorted(s, local, side="right") - 1, 0, s.shape[0] - 2)
    ds = np.clip(local - s[i], 0.0, None)
    h = s[i + 1] - s[i]
    u = (sd[i + 1] ** 2 - sd[i] ** 2) / (2.0 * h)
    root = np.sqrt(np.maximum(sd[i] ** 2 + 2.0 * u * ds, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(sd[i] + root > 0.0, 2.0 * ds / (sd[i] + root), 0.0)
    return np.minimum(tg[i] + tau, tg[-1])


def _sample_leg(
    act: Actuation, path: StepPath, j: int, leg: _Leg, stretch: float, period_s: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """(local positions, counts, periods) of one leg sampled at the control period after
    stretching its time by ``stretch`` and rounding it up to whole periods."""
    n_per = max(1, math.ceil(leg.duration_unstretched_s * stretch / period_s - 1e-9))
    f = n_per * period_s / leg.duration_unstretched_s  # >= stretch
    tau = np.arange(n_per + 1, dtype=np.float64) * period_s / f
    local = _leg_positions(leg, tau)
    local[0], local[-1] = 0.0, leg.s[-1]
    first = path.legs[j][0]
    sigma = local + path.distance_mm[first]
    counts = np.empty((sigma.shape[0], act.n_motors), dtype=np.int64)
    lim_a, lim_t = act.robot.limit_alpha, act.robot.limit_theta
    for lo in range(0, sigma.shape[0], _BLOCK_ROWS):
        a, t = path.angles_at(sigma[lo : lo + _BLOCK_ROWS])
        bad = ~((np.abs(a) < lim_a) & (np.abs(t) < lim_t)).all(axis=1)
        if bad.any():  # the spline between two steps leaves the joint limits
            r = int(np.flatnonzero(bad)[0])
            k = int(path.step_approached(sigma[lo + r]))
            try:
                act.check_angles(a[r], t[r])
            except RopeError as exc:
                raise RopeLimitError(
                    f"{path.step_label(k)}: on the way from plan step {max(k - 1, 0)}: {exc}"
                ) from None
        block = act.counts_from_angles(a, t, check=False)
        out = act.rounded_outside(block, a, t)
        if out is not None:  # the whole counts sent would cross a limit the angles keep
            k = int(path.step_approached(sigma[lo + out[0]]))
            raise RopeLimitError(
                f"{path.step_label(k)}: on the way from plan step {max(k - 1, 0)}: rounded "
                f"to whole counts: {out[1]}"
            )
        counts[lo : lo + _BLOCK_ROWS] = block
    return local, counts, n_per


def plan_limits(
    act: Actuation, period_s: float, margin: float = DEFAULT_MARGIN
) -> tuple[np.ndarray, np.ndarray]:
    """The speed and acceleration (counts/s, counts/s^2) a trajectory is planned for, so
    that its rounded, sampled table stays within the motors' limits (module docstring).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> v, a = plan_limits(load_actuation(default_robot()), 0.01)
    >>> round(float(v[0])), round(float(a[0]))
    (389025, 1926600)
    """
    v = np.asarray(act.max_rate_counts_per_s, dtype=np.float64)
    a = np.asarray(act.max_accel_counts_per_s2, dtype=np.float64)
    v_plan = margin * (v - 1.0 / period_s)
    a_plan = margin * (a - 2.0 / period_s**2)
    if not ((v_plan > 0).all() and (a_plan > 0).all()):
        i = int(np.flatnonzero(~((v_plan > 0) & (a_plan > 0)))[0])
        raise RopeLimitError(
            f"motor {act.motor_label(i)}: limits of {v[i]:g} counts/s and {a[i]:g} counts/s^2 "
            f"leave no motion in whole counts at a {period_s:g} s control period (at least "
            f"{1.0 / period_s:g} counts/s and {2.0 / period_s**2:g} counts/s^2)"
        )
    return v_plan, a_plan


def plan_jerk_limits(act: Actuation, period_s: float, margin: float = DEFAULT_MARGIN) -> np.ndarray:
    """The jerk (counts/s^3) a trajectory is planned for, so that its rounded, sampled
    table keeps the motors' jerk limits: a third difference of rounded counts is off by at
    most four counts (``margin * (j - 4/T**3)``).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> round(float(plan_jerk_limits(load_actuation(default_robot()), 0.01)[0]))
    35112000
    """
    j = np.asarray(act.max_jerk_counts_per_s3, dtype=np.float64)
    j_plan = margin * (j - 4.0 / period_s**3)
    if not (j_plan > 0).all():
        i = int(np.flatnonzero(~(j_plan > 0))[0])
        raise RopeLimitError(
            f"motor {act.motor_label(i)}: a jerk limit of {j[i]:g} counts/s^3 leaves no "
            f"motion in whole counts at a {period_s:g} s control period (at least "
            f"{4.0 / period_s**3:g} counts/s^3)"
        )
    return j_plan


# the share of a motor's jerk the path's own third derivative may take at the speed
# TOPP-RA plans (the rest: the time law's changes of acceleration, the jerk window's)
JERK_PATH_SHARE = 0.8
JERK_BINS = 20_000  # the jerk window is found on at most this many time bins of a leg


def jerk_window(leg: _Leg, j_plan: np.ndarray, period_s: float) -> float:
    """The shortest averaging window (s) found for a leg's TOPP-RA law so that every
    motor's acceleration changes by at most ``j_plan * window`` within any window (its
    jerk once averaged).  The motors' accelerations ``q' u + q'' sigma_dot**2`` at both
    ends of every grid interval, and 0 at rest before and after, are binned in time
    (at most :data:`JERK_BINS` bins, no finer than a quarter period); from the whole
    leg's range, the window shrinks while the range within it allows (each window found
    is long enough: the range within a shorter window is no larger).
    """
    s, sd, tg = leg.s, leg.sd, leg.t_grid
    u = (sd[1:] ** 2 - sd[:-1] ** 2) / (2.0 * np.diff(s))
    acc = np.concatenate(
        [
            leg.q1[:-1] * u[:, None] + leg.q2[:-1] * (sd[:-1] ** 2)[:, None],
            leg.q1[1:] * u[:, None] + leg.q2[1:] * (sd[1:] ** 2)[:, None],
        ]
    )
    times = np.concatenate([tg[:-1], tg[1:]])
    duration = float(tg[-1])
    width = max(period_s / 4.0, duration / JERK_BINS)
    n_bins = math.ceil(duration / width) + 3
    b = np.minimum((times / width).astype(np.int64) + 1, n_bins - 2)
    hi = np.zeros((n_bins, acc.shape[1]))  # bins 0 and last: at rest (acceleration 0)
    lo = np.zeros_like(hi)
    np.maximum.at(hi, b, acc)
    np.minimum.at(lo, b, acc)
    filled = np.zeros(n_bins, dtype=bool)
    filled[b] = True
    filled[0] = filled[-1] = True
    # empty bins lie inside a grid interval: the acceleration of their neighbours
    idx = np.maximum.accumulate(np.where(filled, np.arange(n_bins), 0))
    hi = np.where(filled[:, None], hi, hi[idx])
    lo = np.where(filled[:, None], lo, lo[idx])
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    window = float(np.max((hi.max(axis=0) - lo.min(axis=0)) / j_plan))
    for _ in range(8):
        size = min(math.ceil(window / width) + 2, n_bins)
        span = maximum_filter1d(hi, size, axis=0) - minimum_filter1d(lo, size, axis=0)
        shorter = float(np.max(span / j_plan))
        if shorter >= 0.98 * window:
            break
        window = shorter
    return window


def time_parameterise(
    act: Actuation,
    path: StepPath,
    *,
    period_s: float,
    tip_speed_mm_per_s: float,
    margin: float = DEFAULT_MARGIN,
    max_rows: int | None = None,
    label_of_leg: Any = None,
    progress: Callable[[float], None] | None = None,
    jerk_limited: bool = True,
) -> Trajectory:
    """The fastest playback of ``path`` at the control period within every motor's speed,
    acceleration and (``jerk_limited``) jerk limit and the tip-speed cap, each leg from
    rest to rest, as int64 counts per control cycle (module docstring).

    ``max_rows`` (if given) refuses, before the table is allocated, a playback of more
    rows (:class:`RopeError` saying how many).  ``label_of_leg(j)`` names leg j in
    messages (default: its plan steps).  Raises :class:`RopeLimitError` if no time law
    within the limits is found, or where the path between two steps leaves the joint
    limits (naming the step approached).  ``progress(fraction)`` (optional) is told the
    share of the legs time-parameterised so far.
    """
    if not (math.isfinite(period_s) and period_s > 0.0):
        raise RopeError(f"control period must be > 0 s, got {period_s}")
    if not (math.isfinite(tip_speed_mm_per_s) and tip_speed_mm_per_s > 0.0):
        raise RopeError(f"tip speed must be > 0 mm/s, got {tip_speed_mm_per_s}")
    label = label_of_leg or (lambda j: _leg_label(path, j))
    v_plan, a_plan = plan_limits(act, period_s, margin)
    j_plan = plan_jerk_limits(act, period_s, margin) if jerk_limited else None
    # averaging the law keeps its speed within the cap up to float rounding: a hair below
    v_law = tip_speed_mm_per_s * (1.0 - 1e-7) if jerk_limited else tip_speed_mm_per_s
    # per leg, TOPP-RA's law, and (jerk-limited, where it binds) one also capped in speed
    # by the path's own third derivative: whichever plays the leg sooner is kept
    options: list[list[_Leg]] = []
    for j in range(len(path.legs)):
        found = [_toppra_leg(act, path, j, v_plan, a_plan, v_law, label(j))]
        if j_plan is not None:
            j_path = JERK_PATH_SHARE * j_plan
            found.append(_toppra_leg(act, path, j, v_plan, a_plan, v_law, label(j), j_path))
        found_legs = [leg for leg in found if leg is not None]
        if j_plan is not None:
            found_legs = [dataclasses.replace(leg, window_s=jerk_window(leg, j_plan, period_s))
                          for leg in found_legs]  # fmt: skip
        options.append(found_legs)
        if progress is not None:
            progress((j + 1) / len(path.legs))
    legs = [min(found, key=lambda leg: leg.duration_unstretched_s) for found in options]
    if max_rows is not None:
        rows = 1 + sum(
            max(1, math.ceil(leg.duration_unstretched_s / period_s - 1e-9)) for leg in legs
        )
        if rows > max_rows:
            total = sum(leg.duration_unstretched_s for leg in legs)
            raise RopeError(
                f"{total:.4g} s at up to {tip_speed_mm_per_s:g} mm/s is {rows} control cycles "
                f"of {period_s:g} s, more than the {max_rows} a playback may have"
            )
    sigmas: list[np.ndarray] = []
    tables: list[np.ndarray] = []
    periods: list[int] = []
    stretches: list[float] = []
    for j in range(len(legs)):
        played = [_stretched_leg(act, path, j, leg, period_s, jerk_limited, label(j))
                  for leg in options[j]]  # fmt: skip
        best = min(range(len(played)), key=lambda i: played[i][2])
        leg = legs[j] = options[j][best]
        local, counts, n_per = played[best]
        sigmas.append(local + path.distance_mm[path.legs[j][0]])
        tables.append(counts)
        periods.append(n_per)
        stretches.append(n_per * period_s / leg.duration_unstretched_s)
    traj = _assemble(act, path, legs, sigmas, tables, periods, stretches, period_s,
                     tip_speed_mm_per_s)  # fmt: skip
    # without the jerk bound: TOPP-RA's own laws (the first option of every leg)
    law = sum(max(1, math.ceil(found[0].law_duration_s / period_s - 1e-9)) for found in options)
    return dataclasses.replace(traj, law_duration_s=law * period_s) if options else traj


def _stretched_leg(
    act: Actuation,
    path: StepPath,
    j: int,
    leg: _Leg,
    period_s: float,
    jerk_limited: bool,
    label: str,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Leg ``j`` sampled at the control period, its time law stretched until the
    integers keep every motor's speed, acceleration and (``jerk_limited``) jerk limit:
    (local positions, counts, periods)."""
    v_lim = np.asarray(act.max_rate_counts_per_s, dtype=np.float64)
    a_lim = np.asarray(act.max_accel_counts_per_s2, dtype=np.float64)
    j_lim = np.asarray(act.max_jerk_counts_per_s3, dtype=np.float64)
    stretch = 1.0
    for _ in range(MAX_STRETCH_TRIES + 1):
        local, counts, n_per = _sample_leg(act, path, j, leg, stretch, period_s)
        v, a = finite_differences(counts, period_s)
        excess = max(float(np.max(v / v_lim)), math.sqrt(float(np.max(a / a_lim))))
        if jerk_limited:
            jerk = finite_jerk(counts, period_s)
            excess = max(excess, float(np.max(jerk / j_lim)) ** (1.0 / 3.0))
        if excess <= 1.0:
            return local, counts, n_per
        stretch *= excess * STRETCH_EXTRA
    raise RopeLimitError(
        f"{label}: no sampled time law within the motors' limits after "
        f"{MAX_STRETCH_TRIES} time stretches"
    )


def _assemble(
    act: Actuation,
    path: StepPath,
    legs: list[_Leg],
    sigmas: list[np.ndarray],
    tables: list[np.ndarray],
    periods: list[int],
    stretches: list[float],
    period_s: float,
    tip_speed: float,
) -> Trajectory:
    """One table of the legs (a boundary row once), with times and plan steps."""
    d = path.distance_mm
    if not legs:  # one step: one row
        a, t = path.angles_at(d[:1])
        counts = act.counts_from_angles(a, t, check=False)
        sigma = d[:1].copy()
        leg_rows: tuple[tuple[int, int], ...] = ((0, 0),)
    else:
        counts = np.concatenate([tables[0]] + [tb[1:] for tb in tables[1:]], axis=0)
        sigma = np.concatenate([sigmas[0]] + [sg[1:] for sg in sigmas[1:]])
        bounds = np.concatenate(([0], np.cumsum(periods)))
        leg_rows = tuple((int(bounds[j]), int(bounds[j + 1])) for j in range(len(legs)))
    time_s = np.arange(counts.shape[0], dtype=np.float64) * period_s
    s = d.shape[0]
    step_of_row = path.step_approached(sigma)
    step_of_row[-1] = s - 1
    step_time = np.zeros(s)
    for j, (first, last) in enumerate(path.legs):
        local = d[first : last + 1] - d[first]
        t = _leg_times(legs[j], local) * stretches[j] + leg_rows[j][0] * period_s
        t[0], t[-1] = leg_rows[j][0] * period_s, leg_rows[j][1] * period_s
        step_time[first : last + 1] = t
    for arr in (counts, time_s, sigma, step_of_row, step_time):
        arr.setflags(write=False)
    law = sum(max(1, math.ceil(leg.law_duration_s / period_s - 1e-9)) for leg in legs)
    return Trajectory(
        jerk_window_s=tuple(leg.window_s for leg in legs),
        law_duration_s=law * period_s,
        counts=counts,
        time_s=time_s,
        sigma_mm=sigma,
        step_of_row=step_of_row,
        step_time_s=step_time,
        leg_rows=leg_rows,
        period_s=float(period_s),
        tip_speed_mm_per_s=float(tip_speed),
    )


__all__ = [
    "DEFAULT_MARGIN",
    "StepPath",
    "Trajectory",
    "finite_differences",
    "finite_jerk",
    "jerk_window",
    "plan_jerk_limits",
    "plan_limits",
    "step_path",
    "time_parameterise",
]
