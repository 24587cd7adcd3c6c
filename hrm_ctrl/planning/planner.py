"""Path following with the modal backbone, Sec. 3.2, end to end.

At step i the tip has travelled ``d_i = min(i lambda, L_path)`` along the known
path (the last step lands exactly on its end, Step 5).  The backbone is the
modal curve from the base to the path's start A, of length
``L_m = L_sum - d_i alpha_step`` (Eq. 11), with start angles from the base's
mounting direction and end angles along the path's tangent at A, followed by the
travelled part of the path (Steps 2-3).  The arm is fitted onto it (Sec. 3.3),
the joint angles come from the closed-vector method (Sec. 3.4), and FK of those
angles is what the plan and its report state.  With ``return_to_start`` the arm
then backs out along the same sequence to its start configuration (Sec. 4.2).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.planning.scenarios import scenario
>>> p = plan_path(default_robot(), scenario("bent-pipe").path, PlanOptions(step=50.0))
>>> len(p.travel), p.report["tip_error_mm"] < 0.01
(15, True)
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hrm_ctrl.errors import PlanningError, UnreachableError
from hrm_ctrl.formats.planfile import PLAN_FORMAT
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.backbone import (
    Boundary,
    ModalBasis,
    backbone_points,
    solve_modal_cold,
    solve_modal_factors,
)
from hrm_ctrl.planning.fitting import fit_joint_centres_batch
from hrm_ctrl.planning.joint_angles import joint_angles_from_centres
from hrm_ctrl.planning.known_path import KnownPath, tangent_angles
from hrm_ctrl.planning.report import plan_report
from hrm_ctrl.planning.scenarios import Scenario

# Bounds on what the step (lambda) and the path may ask the planner to allocate, checked
# before anything is: a plan has at most MAX_PLAN_STEPS steps (a return leg included;
# 0.1 mm steps along the whole 2007 mm arm, a plan file of ~30 MB), and holds every step's
# backbone samples (Q + 1 of the modal curve plus the path's points) at once, at most
# MAX_PLAN_SAMPLES in all: ~170 bytes a sample at the peak, measured, so ~700 MB.
MAX_PLAN_STEPS = 20_000
MAX_PLAN_SAMPLES = 4_000_000


@dataclass(frozen=True)
class PlanOptions:
    """Planner settings (mm, rad).

    Attributes:
        step: lambda, the distance the tip travels per step (mm).
        alpha_step: alpha_step of Eq. (11), in (0, 1].
        Q: number of equal parts of the modal curve (Sec. 3.1).
        return_to_start: back out along the path to the start configuration.
        start_angles: (b1k, b1t); by default the base's mounting direction.
        backbone_steps: steps whose backbone curve the plan keeps (for figures);
            by default the first, middle and last.  Indices past the end are ignored.
    """

    step: float = 5.0
    alpha_step: float = 1.0
    Q: int = 200
    return_to_start: bool = False
    start_angles: tuple[float, float] | None = None
    backbone_steps: tuple[int, ...] | None = None

    def check(self) -> None:
        if not (math.isfinite(self.step) and self.step > 0.0):
            raise PlanningError(f"step must be a finite number > 0 mm, got {self.step}")
        if not (0.0 < self.alpha_step <= 1.0):
            raise PlanningError(f"alpha_step must be in (0, 1], got {self.alpha_step}")
        if self.Q < 20:
            raise PlanningError(f"Q must be >= 20 curve divisions, got {self.Q}")


@dataclass(eq=False)
class Plan:
    """A planned motion: one configuration per step, and its report."""

    model: RobotModel
    path: KnownPath
    options: PlanOptions
    travel: np.ndarray  # (N,) mm
    alpha: np.ndarray  # (N, 12) rad
    theta: np.ndarray  # (N, 12) rad
    joints: np.ndarray  # (N, 13, 3) FK of the angles, mm
    phase: list[str]
    iterations: np.ndarray  # (N,) LM iterations of the modal solve
    modal_a: np.ndarray  # (N, 3)
    step_time_s: np.ndarray  # (N,) planning time of each step
    backbones: dict[int, np.ndarray] = field(default_factory=dict)
    report: dict[str, Any] = field(default_factory=dict)
    scenario: Scenario | None = None

    def to_dict(self) -> dict[str, Any]:
        """The plan as an ``hrm-plan/1`` document."""
        steps = []
        for i in range(len(self.travel)):
            st: dict[str, Any] = {
                "travel_mm": float(self.travel[i]),
                "phase": self.phase[i],
                "alpha_rad": self.alpha[i].tolist(),
                "theta_rad": self.theta[i].tolist(),
                "joints_mm": self.joints[i].tolist(),
                "modal_a": self.modal_a[i].tolist(),
                "solver_iterations": int(self.iterations[i]),
            }
            if i in self.backbones:
                st["backbone_mm"] = self.backbones[i].tolist()
            steps.append(st)
        doc: dict[str, Any] = {
            "format": PLAN_FORMAT,
            "robot": self.model.to_dict(),
            "path_mm": self.path.points.tolist(),
            "options": {
                "step_mm": self.options.step,
                "alpha_step": self.options.alpha_step,
                "Q": self.options.Q,
                "return": self.options.return_to_start,
            },
            "steps": steps,
            "report": self.report,
        }
        if self.scenario is not None:
            doc["scenario"] = self.scenario.to_dict()
        return doc


def travel_schedule(length: float, step: float) -> np.ndarray:
    """Travelled distance at each step: 0, lambda, 2 lambda, ..., and exactly the
    path's end last (Step 5).

    >>> travel_schedule(12.0, 5.0).tolist()
    [0.0, 5.0, 10.0, 12.0]
    >>> travel_schedule(2000.0, 1e-6)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.PlanningError: a 2000 mm path at steps of 1e-06 mm is 2e+09 steps, more ...
    """
    check_plan_size(length, step)
    n = math.ceil(length / step - 1e-9)
    d = np.minimum(np.arange(n + 1) * step, length)
    d[-1] = length
    return d


def check_plan_size(
    length: float, step: float, *, return_to_start: bool = False, path_points: int = 0, Q: int = 0
) -> None:
    """Refuse (:class:`PlanningError`, one line) a plan of more than :data:`MAX_PLAN_STEPS`
    steps, or whose backbones would hold more than :data:`MAX_PLAN_SAMPLES` samples,
    before anything is allocated."""
    if not (math.isfinite(step) and step > 0.0):
        raise PlanningError(f"step must be a finite number > 0 mm, got {step}")
    legs = 2 if return_to_start else 1
    q = length / step  # inf when the division overflows
    if q <= MAX_PLAN_STEPS:
        n_in = math.ceil(q - 1e-9) + 1  # as travel_schedule counts them
        n, count = legs * n_in - legs + 1, str(legs * n_in - legs + 1)
    else:
        n_in, n, count = 0, math.inf, f"{legs * q:.3g}"
    if n > MAX_PLAN_STEPS:
        ret = ", there and back," if return_to_start else ""
        raise PlanningError(
            f"a {length:.6g} mm path at steps of {step:g} mm{ret} is {count} steps, more than "
            f"the {MAX_PLAN_STEPS} a plan may have"
        )
    samples = n_in * (Q + 1 + path_points)
    if samples > MAX_PLAN_SAMPLES:
        raise PlanningError(
            f"a {length:.6g} mm path of {path_points} points at steps of {step:g} mm needs "
            f"{samples:.3g} backbone samples, more than the {MAX_PLAN_SAMPLES} a plan may hold "
            "(take a larger step or fewer path points)"
        )


def plan_path(
    model: RobotModel,
    path: KnownPath,
    options: PlanOptions | None = None,
    scenario: Scenario | None = None,
) -> Plan:
    """Plan the arm along ``path`` (Sec. 3.2-3.4); see the module docstring.

    Raises :class:`UnreachableError` (naming the step) when the backbone cannot
    reach the path, :class:`PlanningError` when the arm cannot be fitted.  Joint
    limits are checked in the report, not here (see
    :func:`hrm_ctrl.planning.report.check_limits`).
    """
    opt = options or PlanOptions()
    opt.check()
    check_plan_size(
        path.length,
        opt.step,
        return_to_start=opt.return_to_start,
        path_points=len(path.points),
        Q=opt.Q,
    )
    basis = ModalBasis(opt.Q)
    X0 = model.base_position
    A = path.points[0]
    if opt.start_angles is None:
        b1k, b1t = tangent_angles(model.base_direction)
    else:
        b1k, b1t = opt.start_angles
    b2k, b2t = tangent_angles(path.tangent_at(0.0))
    b = Boundary(b1k, b1t, b2k, b2t)
    travel = travel_schedule(path.length, opt.step)
    n = len(travel)
    L_m = model.length - travel * opt.alpha_step

    # 1. The modal curves, one solve per step, each warm-started from the last
    #    (linearly extrapolated from the last two): sequential by nature.
    t_start = time.perf_counter()
    modal_a = np.empty((n, 3))
    iters = np.zeros(n, dtype=np.int64)
    step_time = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        try:
            if i == 0:
                sol = solve_modal_cold(basis, X0, A, float(L_m[0]), b)
            else:
                guess = predict_modal_factors(modal_a[:i])
                try:
                    sol = solve_modal_factors(basis, X0, A, float(L_m[i]), b, a0=guess)
                except UnreachableError:
                    if i == 1:
                        raise
                    sol = solve_modal_factors(basis, X0, A, float(L_m[i]), b, a0=modal_a[i - 1])
        except UnreachableError as exc:
            raise UnreachableError(f"step {i} (travel {travel[i]:.1f} mm): {exc}") from None
        modal_a[i] = sol.a
        iters[i] = sol.iterations
        step_time[i] = time.perf_counter() - t0
    t_solve = time.perf_counter()

    # 2. Every step's backbone: its modal curve, then the travelled path (Steps 2-3),
    #    padded at the tip so that all steps share one array.
    mode = backbone_points(basis, X0, L_m, modal_a, b)  # (n, Q+1, 3)
    curves = np.concatenate((mode, travelled_path_padded(path, travel)), axis=1)
    # 3. Fitting (Sec. 3.3), joint 2 nearest the modal curve at arc length l_1.
    f = np.clip(model.links[0] / L_m, 0.0, 1.0) * opt.Q
    k0 = np.minimum(np.floor(f).astype(np.int64), opt.Q - 1)
    w = (f - k0)[:, None]
    rows = np.arange(n)
    ref2 = (1.0 - w) * mode[rows, k0] + w * mode[rows, k0 + 1]
    O, seg = fit_joint_centres_batch(curves, model.links, ref2)
    # 4. Joint angles (Sec. 3.4), and FK of those angles for everything reported.
    alpha, theta = joint_angles_from_centres(model, O)
    t_batch = time.perf_counter()
    step_time += (t_batch - t_solve) / n  # the batched work, shared evenly
    if opt.backbone_steps is None:
        keep = sorted({0, n // 2, n - 1})
    else:
        keep = sorted({i for i in opt.backbone_steps if 0 <= i < n})
    backbones = {
        i: curves[i, : opt.Q + 1 + int(np.searchsorted(path.s, travel[i], "left"))] for i in keep
    }
    for i in keep:  # drop the padding: end the curve at the tip
        backbones[i] = np.vstack((backbones[i], O[i, -1]))
    phase = ["in"] * n
    if opt.return_to_start:
        back = np.arange(n - 2, -1, -1)
        travel = np.concatenate((travel, travel[back]))
        alpha = np.vstack((alpha, alpha[back]))
        theta = np.vstack((theta, theta[back]))
        iters = np.concatenate((iters, np.zeros(len(back), dtype=np.int64)))
        modal_a = np.vstack((modal_a, modal_a[back]))
        seg = np.vstack((seg, seg[back]))
        step_time = np.concatenate((step_time, np.zeros(len(back))))
        phase += ["return"] * len(back)
        if 0 in backbones:
            backbones[len(travel) - 1] = backbones[0]
    joints = joint_centres(model, alpha, theta)
    plan = Plan(
        model=model,
        path=path,
        options=opt,
        travel=travel,
        alpha=alpha,
        theta=theta,
        joints=joints,
        phase=phase,
        iterations=iters,
        modal_a=modal_a,
        step_time_s=step_time,
        backbones=backbones,
        scenario=scenario,
    )
    plan.report = plan_report(plan, seg, opt.Q)
    plan.report["plan_time_ms"] = (time.perf_counter() - t_start) * 1e3
    return plan


def predict_modal_factors(history: np.ndarray) -> np.ndarray:
    """Warm start for the next step: the last solutions extrapolated (quadratic
    from three, linear from two, the last one from one).

    >>> predict_modal_factors(np.array([[1.0, 0, 0], [2.0, 0, 0], [4.0, 0, 0]])).tolist()
    [7.0, 0.0, 0.0]
    """
    n = len(history)
    if n >= 3:
        return 3.0 * history[-1] - 3.0 * history[-2] + history[-3]
    if n == 2:
        return 2.0 * history[-1] - history[-2]
    return history[-1].copy()


def travelled_path_padded(path: KnownPath, travel: np.ndarray) -> np.ndarray:
    """For each travelled distance d, the path's points after A up to d, ending at
    the point of Eq. (12), padded with copies of that end point: shape (N, M, 3)
    for a path of M points.

    >>> P = KnownPath.from_points(np.array([[0, 0, 0], [3, 0, 0], [3, 4, 0]], float))
    >>> travelled_path_padded(P, np.array([1.0, 5.0]))[:, :, :2].tolist()
    [[[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]], [[3.0, 0.0], [3.0, 2.0], [3.0, 2.0]]]
    """
    M = len(path.points)
    j = np.clip(np.searchsorted(path.s, travel, side="right") - 1, 0, M - 2)
    tip = path.points_at(travel)
    c = np.arange(M)
    take = (c[None, :] + 1) <= j[:, None]
    pts = path.points[np.minimum(c + 1, M - 1)]
    return np.where(take[:, :, None], pts[None, :, :], tip[:, None, :])
