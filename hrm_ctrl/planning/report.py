"""The figures every plan states, and the joint-limit check on them.

:func:`hrm_ctrl.planning.planner.plan_path` stores :func:`plan_report` in
``Plan.report`` once the plan's configurations are known; :func:`check_limits`
is what the console calls before it writes a plan.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.planning.planner import PlanOptions, plan_path
>>> from hrm_ctrl.planning.scenarios import scenario
>>> p = plan_path(default_robot(), scenario("bent-pipe").path, PlanOptions(step=50.0))
>>> first_violation(p) is None, p.report["first_violation"] is None
(True, True)
>>> check_limits(p)
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from hrm_ctrl.errors import CollisionError, JointLimitError, PlanFileError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.environment import Environment, link_clearance
from hrm_ctrl.planning.scenarios import SAMPLES_PER_LINK

SAME_JOINTS_MM = 1e-6  # stored joint centres this near their angles' are the same arm

if TYPE_CHECKING:  # the planner imports this module to fill in its report
    from hrm_ctrl.formats.planfile import PlanDoc
    from hrm_ctrl.planning.planner import Plan


def plan_report(plan: Plan, seg: np.ndarray, Q: int) -> dict[str, Any]:
    """The figures every plan states (mm and degrees):

    - ``tip_error_mm``: largest distance of the FK end point from the path point
      it should be at; ``end_error_mm``: from the path's end at the last forward step;
    - ``joints_off_path_mm``: largest distance from the path of a joint centre
      that has entered it; ``links_off_path_mm``: of any point of a link with both
      ends on the path (chords cut corners, ``NOTES.md``);
    - ``joint_limit_margin_deg`` and ``first_violation`` (step, joint, angle);
    - ``max_angle_change_deg`` between consecutive steps, with where;
    - solver iterations; ``clearance_mm`` against the scenario's environment
      (:func:`clearance_summary`).
    """
    model, path = plan.model, plan.path
    n = len(plan.travel)
    target = path.points_at(plan.travel)
    tip_err = np.linalg.norm(plan.joints[:, -1] - target, axis=1)
    fwd_last = max(i for i in range(n) if plan.phase[i] == "in")
    end_err = float(np.linalg.norm(plan.joints[fwd_last, -1] - path.points[-1]))

    on_path = seg >= Q  # joints fitted onto the path part of the backbone
    joints_off = float(path.distance_to(plan.joints[on_path]).max()) if on_path.any() else 0.0
    link_on = on_path[:, :-1] & on_path[:, 1:]
    links_off = 0.0
    if link_on.any():
        s_idx, l_idx = np.nonzero(link_on)
        t = np.linspace(0.0, 1.0, SAMPLES_PER_LINK)
        P0 = plan.joints[s_idx, l_idx]
        P1 = plan.joints[s_idx, l_idx + 1]
        pts = P0[:, None, :] + t[None, :, None] * (P1 - P0)[:, None, :]
        links_off = float(path.distance_to(pts).max())

    lim_a, lim_t = model.limit_alpha, model.limit_theta
    margin_a = lim_a - np.abs(plan.alpha)
    margin_t = lim_t - np.abs(plan.theta)
    margin = float(np.degrees(min(margin_a.min(), margin_t.min())))
    violation = first_violation(plan)

    if n > 1:
        da = np.abs(np.diff(plan.alpha, axis=0))
        dt = np.abs(np.diff(plan.theta, axis=0))
        both = np.maximum(da, dt)
        k, j = np.unravel_index(int(np.argmax(both)), both.shape)
        max_change = {
            "deg": float(np.degrees(both[k, j])),
            "step": int(k + 1),
            "joint": int(j + 1),
        }
    else:
        max_change = {"deg": 0.0, "step": 0, "joint": 0}

    report: dict[str, Any] = {
        "steps": n,
        "path_length_mm": path.length,
        "tip_error_mm": float(tip_err.max()),
        "end_error_mm": end_err,
        "joints_off_path_mm": joints_off,
        "links_off_path_mm": links_off,
        "joint_limit_margin_deg": margin,
        "first_violation": violation,
        "max_angle_change_deg": max_change,
        "solver_iterations": {
            "total": int(plan.iterations.sum()),
            "max_per_step": int(plan.iterations.max()),
        },
    }
    if plan.scenario is not None:
        c = link_clearance(plan.scenario.environment, plan.joints, 0.5 * model.outer_diameter)
        report["clearance_mm"] = clearance_summary(c)
    return report


def first_violation(plan: Plan) -> dict[str, Any] | None:
    """The first step and joint whose angle leaves the open interval (-limit, limit)."""
    bad_a = np.abs(plan.alpha) >= plan.model.limit_alpha
    bad_t = np.abs(plan.theta) >= plan.model.limit_theta
    bad = bad_a | bad_t
    if not bad.any():
        return None
    i, j = map(int, np.argwhere(bad)[0])
    name, value = ("alpha", plan.alpha[i, j]) if bad_a[i, j] else ("theta", plan.theta[i, j])
    return {
        "step": i,
        "travel_mm": float(plan.travel[i]),
        "joint": j + 1,
        "angle": name,
        "deg": float(np.degrees(value)),
    }


def check_limits(plan: Plan) -> None:
    """Raise :class:`JointLimitError` naming step, joint and angle if any limit breaks."""
    v = plan.report.get("first_violation") or first_violation(plan)
    if v is not None:
        raise JointLimitError(
            f"joint limit broken at step {v['step']} (travel {v['travel_mm']:.1f} mm): "
            f"joint {v['joint']} {v['angle']} = {v['deg']:.2f} deg"
        )


def clearance_summary(c: np.ndarray) -> dict[str, Any]:
    """The report's ``clearance_mm`` of a (N, 12) link clearance (mm, negative = collision):
    ``min`` with its 0-based ``step`` and 1-based ``link`` (``None``, -1, 0 when no link is
    near an obstacle), ``per_step`` (the worst link of each step, ``None`` where none is near)
    and ``per_step_link``.

    >>> s = clearance_summary(np.array([[3.0, 2.0], [4.0, -1.5], [np.inf, np.inf]]))
    >>> s["min"], s["step"], s["link"], s["per_step"], s["per_step_link"]
    (-1.5, 1, 2, [2.0, -1.5, None], [2, 2, 0])
    """
    c = np.asarray(c, dtype=float)
    if c.size == 0 or not np.isfinite(c).any():
        worst, step, link = None, -1, 0
    else:
        i, j = np.unravel_index(int(np.argmin(c)), c.shape)
        worst, step, link = float(c[i, j]), int(i), int(j) + 1
    per = c.min(axis=1) if c.size else np.zeros(0)
    per_link = np.where(np.isfinite(per), np.argmin(c, axis=1) + 1 if c.size else 0, 0)
    return {
        "min": worst,
        "step": step,
        "link": link,
        "per_step": [float(v) if math.isfinite(v) else None for v in per],
        "per_step_link": [int(v) for v in per_link],
    }


def plan_file_clearance(
    doc: PlanDoc, outer_diameter: np.ndarray | None = None, model: RobotModel | None = None
) -> np.ndarray | None:
    """(S, 12) link clearance of a plan read from a file against the environment it stores
    (``None`` when it stores none): link outer diameters from ``outer_diameter`` (mm), else
    :func:`plan_outer_diameter` (the plan's robot's, the larger of it and ``model``'s).
    With ``model`` (the robot that plays the plan), each step's worse of the stored joint
    centres and those its stored angles put ``model``'s joints at (Eq. 4): joint centres
    edited away from an obstacle do not hide it.  (Where the two agree to
    :data:`SAME_JOINTS_MM`, the stored clearance less their distance, measured once.)

    >>> from hrm_ctrl.formats.planfile import PlanDoc
    >>> from hrm_ctrl.model import default_robot
    >>> doc = {"format": "hrm-plan/1", "robot": {"links_mm": [100.0] * 12},
    ...        "path_mm": [[0, 0, 0], [1, 0, 0]], "report": {}, "steps": [{"travel_mm": 0,
    ...        "alpha_rad": [0.0] * 12, "theta_rad": [0.0] * 12,
    ...        "joints_mm": [[0.0, 0.0, 5000.0]] * 13}],
    ...        "scenario": {"environment": {"box": [{"centre_mm": [0, 0, 0],
    ...                                              "size_mm": [50, 50, 50]}]}}}
    >>> bool(plan_file_clearance(PlanDoc.from_dict(doc)).min() > 0)  # the stored joints
    True
    >>> m = default_robot()
    >>> bool(plan_file_clearance(PlanDoc.from_dict(doc), model=m).min() < 0)  # the angles
    True
    """
    env: Environment | None = doc.environment
    if env is None:
        return None
    if outer_diameter is None:  # the plan's robot's, checked; the larger where both are known
        outer_diameter = plan_outer_diameter(doc, None if model is None else model.outer_diameter)
    radius = 0.5 * np.asarray(outer_diameter, dtype=float)
    c = link_clearance(env, doc.joints_mm, radius)
    if model is not None:
        O = joint_centres(model, doc.alpha_rad, doc.theta_rad)
        dev = np.linalg.norm(O - doc.joints_mm, axis=2).max(axis=1)  # (S,) mm
        moved = dev > SAME_JOINTS_MM
        # the free distance is 1-Lipschitz: a link whose ends moved by dev is at most dev
        # nearer; steps moved farther are measured again
        c[~moved] -= dev[~moved, None]
        if moved.any():
            c[moved] = np.minimum(c[moved], link_clearance(env, O[moved], radius))
    return c


def plan_outer_diameter(doc: PlanDoc, known: np.ndarray | None = None) -> np.ndarray:
    """(12,) link outer diameters (mm) a plan file's robot states (``outer_diameter_mm``: a
    number or 12 numbers, each finite and > 0; where it states none, ``known``, else 30 mm,
    ``NOTES.md``), at least ``known`` (the robot's own).  Raises :class:`PlanFileError`
    naming the key otherwise.

    >>> from hrm_ctrl.formats.planfile import PlanDoc
    >>> doc = {"format": "hrm-plan/1", "robot": {"links_mm": [100.0] * 12,
    ...        "outer_diameter_mm": -30}, "path_mm": [[0, 0, 0], [1, 0, 0]], "report": {},
    ...        "steps": [{"travel_mm": 0, "alpha_rad": [0.0] * 12, "theta_rad": [0.0] * 12,
    ...        "joints_mm": [[0.0, 0.0, 0.0]] * 13}]}
    >>> plan_outer_diameter(PlanDoc.from_dict(doc, "p.json"))
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.PlanFileError: p.json: robot.outer_diameter_mm: expected a number > 0 \
or an array of 12 of them, got -30
    """
    od = doc.robot_extra.get("outer_diameter_mm")
    if od is None:
        return np.full(12, 30.0) if known is None else np.array(known, dtype=float)
    values = od if isinstance(od, list | tuple) else [od]
    ok = len(values) in (1, 12) and all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
        for v in values
    )
    if not ok:
        text = repr(od) if len(repr(od)) <= 40 else repr(od)[:37] + "..."
        raise PlanFileError(
            f"{doc.source}: robot.outer_diameter_mm: expected a number > 0 or an array of 12 "
            f"of them, got {text}"
        )
    stated = np.broadcast_to(np.asarray(values, dtype=float), (12,))
    return np.array(stated if known is None else np.maximum(stated, known))


def check_clearance(summary: dict[str, Any] | None, where: str) -> None:
    """Raise :class:`CollisionError` (one line naming step and link) when a clearance
    summary (:func:`clearance_summary`) is negative.

    >>> check_clearance({"min": -2.5, "step": 7, "link": 9}, "plan bent-pipe")
    ... # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.CollisionError: plan bent-pipe: link 9 meets an obstacle at step 7 ...
    """
    if not summary or summary.get("min") is None or summary["min"] >= 0.0:
        return
    raise CollisionError(
        f"{where}: link {summary['link']} meets an obstacle at step {summary['step']} "
        f"(clearance {summary['min']:.2f} mm); pass --allow-collision to accept it"
    )
