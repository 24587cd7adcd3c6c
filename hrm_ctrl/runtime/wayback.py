"""The way back after a stop: from where the arm stands back along the path a run played,
checked against the run's environment; and the clearance of a straight move in joint space.

A run that ends early (the operator's abort, Ctrl-C, a safety stop) leaves the arm on or
near its path: at rest on it after an abort, a little past the last setpoint after a quick
stop (each axis ramps down on its own).  :func:`way_back` makes the return from where the
drives' feedback says the arm is: the row of the run's table nearest to it (in rope
counts, the pose they show; searched up to where the playback stood plus the
:data:`STOP_MARGIN_S` a quick stop may carry it), the configuration on the path there, and
the plan's steps before it in reverse order, a plan of its own (travel and phases as the
rope layer's :func:`~hrm_ctrl.ropes.setpoints.plan_setpoints` wants them: the return
of a return leg goes ``in``).  The arm joins the path with a straight move in joint space
(the lead-in of the source that plays it); the join and the path back are checked against
the environment the run's plan was made in, at every step and every
:data:`CHECK_SPACING_MM` of the path between (:class:`CollisionError` naming where).
:func:`line_clearance` checks a straight move in joint space (``home``) the same way.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.planning.environment import Box, Environment
>>> m = default_robot()
>>> near = Surroundings(Environment((Box(np.array([600.0, 0, 0]), np.array([50.0] * 3)),)),
...                     np.full(12, 15.0), "box.json")
>>> a = np.zeros((2, 12)); a[0, 0] = 0.5
>>> c = poses_clearance(m, near, a, np.zeros((2, 12)))
>>> c.least_mm < 0, c.index, c.link  # the straight arm runs through the box
(True, 1, 4)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hrm_ctrl.errors import CollisionError, RopeError

if TYPE_CHECKING:
    from hrm_ctrl.formats.planfile import PlanDoc
    from hrm_ctrl.model import RobotModel
    from hrm_ctrl.planning.environment import Environment
    from hrm_ctrl.ropes.actuation import Actuation
    from hrm_ctrl.ropes.setpoints import PlanSetpoints

STOP_MARGIN_S = 1.0  # the path searched beyond where the playback stood (a quick stop's ramp)
CHECK_SPACING_MM = 5.0  # the way back's clearance checked at least this often along it
LINE_SAMPLES = 32  # poses of a straight move in joint space checked for clearance
SAME_POINT_MM = 1e-3  # a position on the path this near a plan step is that step


@dataclass(frozen=True)
class Surroundings:
    """The environment a move is checked against: obstacles, the links' outer radii (mm)
    and where they come from (the plan file whose environment it is)."""

    environment: Environment
    radius_mm: np.ndarray
    source: str


def surroundings_of_plan(doc: PlanDoc, model: RobotModel) -> Surroundings | None:
    """The environment a plan was made in, with the larger of its robot's and ``model``'s
    link diameters (None: the plan stores none)."""
    from hrm_ctrl.planning.report import plan_outer_diameter

    env = doc.environment
    if env is None:
        return None
    radius = 0.5 * np.asarray(plan_outer_diameter(doc, model.outer_diameter), dtype=float)
    return Surroundings(env, radius, str(doc.source))


@dataclass(frozen=True)
class Clearance:
    """The least clearance (mm) of a sequence of poses, the pose (0-based) and the link
    (1-based) where it is; ``inf`` and -1 when nothing is near."""

    least_mm: float
    index: int
    link: int


def poses_clearance(
    model: RobotModel, surroundings: Surroundings, alpha: np.ndarray, theta: np.ndarray
) -> Clearance:
    """The least clearance of the arm at poses ``alpha``, ``theta`` (N, 12)."""
    from hrm_ctrl.kinematics import joint_centres
    from hrm_ctrl.planning.environment import worst_clearance

    O = joint_centres(model, np.asarray(alpha, float), np.asarray(theta, float))
    least, i, link = worst_clearance(surroundings.environment, O, surroundings.radius_mm)
    return Clearance(least, i, link)


def line_poses(
    start: tuple[np.ndarray, np.ndarray], end: tuple[np.ndarray, np.ndarray], n: int = LINE_SAMPLES
) -> tuple[np.ndarray, np.ndarray]:
    """``n + 1`` poses at equal steps of the straight line in joint space from ``start``
    to ``end`` ((alpha, theta) each (12,)), both ends included.

    >>> a, t = line_poses((np.zeros(12), np.zeros(12)), (np.ones(12), np.zeros(12)), 4)
    >>> a[:, 0].tolist()
    [0.0, 0.25, 0.5, 0.75, 1.0]
    """
    s = np.linspace(0.0, 1.0, n + 1)[:, None]
    a0, t0 = (np.asarray(x, float) for x in start)
    a1, t1 = (np.asarray(x, float) for x in end)
    return a0 + s * (a1 - a0), t0 + s * (t1 - t0)


def line_clearance(
    model: RobotModel,
    surroundings: Surroundings,
    start: tuple[np.ndarray, np.ndarray],
    end: tuple[np.ndarray, np.ndarray],
) -> tuple[Clearance, float]:
    """The least clearance along a straight move in joint space, and how far along the
    move (0..1) it is."""
    alpha, theta = line_poses(start, end)
    c = poses_clearance(model, surroundings, alpha, theta)
    return c, (c.index / LINE_SAMPLES if c.index >= 0 else 0.0)


@dataclass(frozen=True)
class WayBack:
    """A return along a run's path: the steps of its plan (``travel_mm`` (S,), angles
    (S, 12), ``phase``), the row of the run's table it joins the path at (``row``, the plan
    step being approached there ``step_label``), how far the tip is from the path there
    (``join_mm``), the least clearance of the join and of the path back (None: no
    environment known) and where the latter is; ``start_counts`` and ``start_pose``: where
    the run started (its lead-in to the plan's first step, reversed, ends the way back
    unless ``lead_out_blocked`` says where that straight move in joint space would hit)."""

    travel_mm: np.ndarray
    alpha_rad: np.ndarray
    theta_rad: np.ndarray
    phase: tuple[str, ...]
    row: int
    step_label: str
    join_mm: float
    join_clearance_mm: float | None
    clearance_mm: float | None
    least_at: str
    start_counts: np.ndarray
    start_pose: tuple[np.ndarray, np.ndarray]
    lead_out_blocked: str | None = None

    @property
    def n_steps(self) -> int:
        return int(self.travel_mm.shape[0])

    def describe(self) -> str:
        """One line: where the way back joins the path and its clearance."""
        text = f"joins the path at {self.step_label}, {self.join_mm:.1f} mm from where the tip is"
        if self.clearance_mm is None:
            return f"{text}; no environment known (clearance not checked)"
        return (
            f"{text}; least clearance {self.join_clearance_mm:.1f} mm on the join, "
            f"{self.clearance_mm:.1f} mm back along the path ({self.least_at})"
        )


def nearest_point(
    counts: np.ndarray, sigma_mm: np.ndarray, held_counts: Any, last_row: int
) -> tuple[int, float]:
    """The point of the path ``counts`` (rows, motors; row ``i`` at ``sigma_mm[i]`` along
    the steps) up to row ``last_row`` nearest to ``held_counts`` (least sum of squares of
    the count differences): the nearest row, then the nearest point of the segments to its
    neighbours (an abort stops between rows).  Returns the row and the point's sigma.

    >>> c = np.array([[0, 0], [10, 0], [20, 0], [30, 0]]); s = np.array([0.0, 1, 2, 3])
    >>> nearest_point(c, s, [24, 2], 3)
    (2, 2.4)
    >>> nearest_point(c, s, [35, 0], 1)
    (1, 1.0)
    """
    rows = np.asarray(counts, dtype=np.int64)[: max(int(last_row), 0) + 1]
    h = np.asarray(held_counts, dtype=np.int64)
    d = (rows - h[None, :]).astype(np.float64)
    i = int(np.argmin(np.einsum("ij,ij->i", d, d)))
    best, sigma = math.inf, float(sigma_mm[i])
    for j in (i - 1, i + 1):
        if not 0 <= j < rows.shape[0]:
            continue
        seg = (rows[j] - rows[i]).astype(np.float64)
        n2 = float(seg @ seg)
        t = 0.0 if n2 == 0.0 else min(1.0, max(0.0, float((h - rows[i]) @ seg) / n2))
        r = h - (rows[i] + t * seg)
        if float(r @ r) < best:
            best, sigma = float(r @ r), float(sigma_mm[i] + t * (sigma_mm[j] - sigma_mm[i]))
    return i, sigma


def _phases_of(travel: np.ndarray) -> tuple[str, ...]:
    """``in`` where travel increases, ``return`` where it decreases (each step's label is
    its change from the one before; the first as the second)."""
    if travel.shape[0] < 2:
        return ("in",) * int(travel.shape[0])
    lab = ["return" if d < 0 else "in" for d in np.diff(travel)]
    return (lab[0], *lab)


def way_back(
    act: Actuation,
    sp: PlanSetpoints,
    held_counts: Any,
    played_row: float,
    surroundings: Surroundings | None,
    *,
    start_counts: Any,
    allow_collision: bool = False,
) -> WayBack:
    """The return from ``held_counts`` (where the drives are) along the path of ``sp`` (the
    run's checked setpoints), which played up to row ``played_row`` of its table, to
    ``start_counts`` (where the run started: a straight move in joint space from the plan's
    first step, the run's lead-in reversed, which the run did not check against the
    environment: where it would hit, ``lead_out_blocked`` says so).  Raises
    :class:`RopeError` when the counts show no pose of the arm, :class:`CollisionError`
    (naming where) when the join or the path back meets an obstacle of ``surroundings``
    (with ``allow_collision``: the run was played so, and so is its way back)."""
    from hrm_ctrl.kinematics import end_point
    from hrm_ctrl.ropes.trajectory import step_path

    held = np.asarray(held_counts, dtype=np.int64)
    margin = math.ceil(STOP_MARGIN_S / sp.period_s)
    last = min(sp.n_cycles - 1, math.ceil(played_row) + margin)
    row, sigma = nearest_point(sp.counts, sp.sigma_mm, held, last)
    path = sp.path
    d = path.distance_mm
    k_near = int(np.argmin(np.abs(d - sigma)))
    if abs(float(d[k_near]) - sigma) <= SAME_POINT_MM:
        sigma = float(d[k_near])
        before = np.flatnonzero(d <= sigma)[::-1]
        alpha, theta = path.alpha_rad[before], path.theta_rad[before]
        travel = path.travel_mm[before]
    else:
        before = np.flatnonzero(d < sigma)[::-1]
        a0, t0 = path.angles_at([sigma])
        alpha = np.vstack([a0, path.alpha_rad[before]])
        theta = np.vstack([t0, path.theta_rad[before]])
        travel = np.concatenate([[np.interp(sigma, d, path.travel_mm)], path.travel_mm[before]])
    label = sp.step_label(int(sp.step_of_row[row]))
    try:
        here = act.pose_of_counts(held, "where the arm is")
    except RopeError as exc:
        raise RopeError(f"way back: {exc}") from None
    model = act.robot
    join_mm = float(np.linalg.norm(end_point(model, *here) - end_point(model, alpha[0], theta[0])))
    phase = _phases_of(travel)
    start = np.asarray(start_counts, dtype=np.int64)
    try:
        start_pose = act.pose_of_counts(start, "where the run started")
    except RopeError as exc:
        raise RopeError(f"way back: {exc}") from None
    ends = (start, start_pose)
    if surroundings is None:
        return WayBack(travel, alpha, theta, phase, row, label, join_mm, None, None, "", *ends)
    where = f"the environment of {surroundings.source}"
    join, at = line_clearance(model, surroundings, here, (alpha[0], theta[0]))
    if join.least_mm < 0.0 and not allow_collision:
        raise CollisionError(
            f"way back: the straight move from where the arm is to the path at {label} "
            f"meets an obstacle of {where} (link {join.link}, clearance "
            f"{join.least_mm:.1f} mm, {100 * at:.0f} % of the way)"
        )
    back = step_path(travel, alpha, theta, phase)
    n = max(2, math.ceil(back.length_mm / CHECK_SPACING_MM) + 1)
    s = np.unique(np.concatenate([np.linspace(0.0, back.length_mm, n), back.distance_mm]))
    a_s, t_s = back.angles_at(s)
    c = poses_clearance(model, surroundings, a_s, t_s)
    least_at = "" if c.index < 0 else f"{s[c.index]:.0f} mm back, link {c.link}"
    if c.least_mm < 0.0 and not allow_collision:
        raise CollisionError(
            f"way back: the path back from {label} meets an obstacle of {where} ({least_at}, "
            f"clearance {c.least_mm:.1f} mm)"
        )
    last, at = line_clearance(model, surroundings, (alpha[-1], theta[-1]), start_pose)
    lead_out = None
    if last.least_mm < 0.0:
        lead_out = (f"meets an obstacle of {where} (link {last.link}, clearance "
                    f"{last.least_mm:.1f} mm, {100 * at:.0f} % of the way)")  # fmt: skip
    return WayBack(travel, alpha, theta, phase, row, label, join_mm, join.least_mm, c.least_mm,
                   least_at, *ends, lead_out)  # fmt: skip


def return_setpoints(
    act: Actuation, back: WayBack, *, period_s: float, speed_mm_per_s: float, where: str
) -> PlanSetpoints:
    """The way back's counts at the control rate, timed and checked as a plan's are
    (:func:`~hrm_ctrl.ropes.setpoints.plan_setpoints`); ``where`` starts its messages."""
    from hrm_ctrl.ropes.setpoints import plan_setpoints

    return plan_setpoints(
        act,
        back.travel_mm,
        back.alpha_rad,
        back.theta_rad,
        phase=back.phase,
        period_s=period_s,
        speed_mm_per_s=speed_mm_per_s,
        where=where,
    )


def straight_home_clearance(
    act: Actuation, surroundings: Surroundings, held_counts: Sequence[int] | np.ndarray
) -> tuple[Clearance, float]:
    """The least clearance of the straight move in joint space from where ``held_counts``
    show the arm to the zero configuration (what ``home`` plays), and where along it."""
    here = act.pose_of_counts(np.asarray(held_counts, dtype=np.int64), "where the arm is")
    n = act.robot.n_joints
    return line_clearance(act.robot, surroundings, here, (np.zeros(n), np.zeros(n)))
