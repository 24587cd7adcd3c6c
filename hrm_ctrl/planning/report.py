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

from hrm_ctrl.errors import JointLimitError
from hrm_ctrl.planning.scenarios import SAMPLES_PER_LINK

if TYPE_CHECKING:  # the planner imports this module to fill in its report
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
    - solver iterations; ``clearance_mm`` against the scenario's obstacles.
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
        worst, where_step, where_link = plan.scenario.clearance(
            plan.joints, 0.5 * model.outer_diameter
        )
        report["clearance_mm"] = {
            "min": None if math.isinf(worst) else worst,
            "step": where_step,
            "link": where_link,
        }
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
