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
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np

from hrm_ctrl.errors import PlanningError, UnreachableError
from hrm_ctrl.formats.planfile import MAX_PLAN_STEPS, MIN_TRAVEL_STEP_MM, PLAN_FORMAT
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.backbone import (
    Boundary,
    ModalBasis,
    backbone_points,
    solve_modal_cold,
    solve_modal_factors,
)
from hrm_ctrl.planning.environment import Environment, link_clearance
from hrm_ctrl.planning.fitting import fit_joint_centres_batch
from hrm_ctrl.planning.joint_angles import joint_angles_from_centres
from hrm_ctrl.planning.known_path import KnownPath, tangent_angles
from hrm_ctrl.planning.refine import (
    Refinement,
    RefineOptions,
    angle_margin,
    best_margin_at,
    refine_angles,
)
from hrm_ctrl.planning.report import plan_report
from hrm_ctrl.planning.scenarios import Scenario

# Bounds on what the step (lambda) and the path may ask the planner to allocate, checked
# before anything is: a plan has at most MAX_PLAN_STEPS steps (a return leg included;
# 0.1 mm steps along the whole 2007 mm arm, a plan file of ~30 MB), and holds every step's
# backbone samples (Q + 1 of the modal curve plus the path's points) at once, at most
# MAX_PLAN_SAMPLES in all: ~170 bytes a sample at the peak, measured, so ~700 MB.
# (MAX_PLAN_STEPS is the plan format's: a plan file is read with the same bound.)
MAX_PLAN_SAMPLES = 4_000_000
MIN_PLAN_STEP_MM = 10 * MIN_TRAVEL_STEP_MM  # lambda at least (steps well apart in a plan file)
# The free-parameter search (issue 10) plans each candidate at a coarser step, at least
# this (mm), and asks for at least this joint-limit margin before it calls a plan safe.
SEARCH_STEP_MM = 20.0
SAFE_MARGIN_DEG = 3.0
# A candidate replaces the given parameters only if it scores this much better (mm of
# clearance, or margin at margin_weight_mm_per_deg): the score is the paper's plan, a
# proxy of what refinement then reaches.
SEARCH_MIN_GAIN = 2.0


class FitMode(Enum):
    """How the arm is put on the backbone: the paper's fit (Sec. 3.3: joint centres on
    the backbone), or that fit refined for clearance and joint-limit margin
    (:mod:`hrm_ctrl.planning.refine`)."""

    PAPER = "paper"
    CLEARANCE = "clearance"


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
        fit: :class:`FitMode`; by default CLEARANCE when an environment is given,
            else PAPER.
        search: choose start angles, alpha_step and joint 2 by a small search
            around the given ones (:func:`choose_free_parameters`); by default when
            the fit is CLEARANCE.
        joint2_offset: turn of joint 2 about the O_1-O_3 axis from the paper's
            choice (rad; Sec. 3.3 step 4 leaves it free).
        refine: settings of the refinement (CLEARANCE).
    """

    step: float = 5.0
    alpha_step: float = 1.0
    Q: int = 200
    return_to_start: bool = False
    start_angles: tuple[float, float] | None = None
    backbone_steps: tuple[int, ...] | None = None
    fit: FitMode | None = None
    search: bool | None = None
    joint2_offset: float = 0.0
    refine: RefineOptions = field(default_factory=RefineOptions)

    def check(self) -> None:
        if not (math.isfinite(self.step) and self.step > 0.0):
            raise PlanningError(f"step must be a finite number > 0 mm, got {self.step}")
        if not (0.0 < self.alpha_step <= 1.0):
            raise PlanningError(f"alpha_step must be in (0, 1], got {self.alpha_step}")
        if self.Q < 20:
            raise PlanningError(f"Q must be >= 20 curve divisions, got {self.Q}")
        if self.fit is not None and not isinstance(self.fit, FitMode):
            raise PlanningError(f"fit must be a FitMode (paper, clearance), got {self.fit!r}")
        if not (math.isfinite(self.joint2_offset) and abs(self.joint2_offset) <= math.pi):
            raise PlanningError(
                f"joint2_offset must be a finite angle within +-pi rad, got {self.joint2_offset}"
            )
        self.refine.check()

    def fit_mode(self, environment: Environment | None) -> FitMode:
        """The fit asked for, or its default for ``environment``."""
        if self.fit is not None:
            return self.fit
        return FitMode.CLEARANCE if environment is not None else FitMode.PAPER


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
    >>> travel_schedule(2000.0, 1e-4)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.PlanningError: a 2000 mm path at steps of 0.0001 mm is 2e+07 steps, more ...
    """
    check_plan_size(length, step)
    n = _steps_in(length / step, step)
    d = np.minimum(np.arange(n + 1) * step, length)
    d[-1] = length
    return d


def _steps_in(q: float, step: float) -> int:
    """Steps after the first over a path of ``q`` steps' length: a remainder shorter than
    twice :data:`MIN_TRAVEL_STEP_MM` (or 1e-9 of a step) joins the last step, as two plan
    steps closer than that are not a plan file's (twice: the travels are rounded).

    >>> _steps_in(10.0000001 / 5.0, 5.0), _steps_in(10.01 / 5.0, 5.0), _steps_in(1e-8, 5.0)
    (2, 3, 0)
    """
    return max(0, math.ceil(q - max(1e-9, 2.0 * MIN_TRAVEL_STEP_MM / step)))


def check_plan_size(
    length: float, step: float, *, return_to_start: bool = False, path_points: int = 0, Q: int = 0
) -> None:
    """Refuse (:class:`PlanningError`, one line) a plan of more than :data:`MAX_PLAN_STEPS`
    steps, or whose backbones would hold more than :data:`MAX_PLAN_SAMPLES` samples,
    before anything is allocated."""
    if not (math.isfinite(step) and step > 0.0):
        raise PlanningError(f"step must be a finite number > 0 mm, got {step}")
    if step < MIN_PLAN_STEP_MM:  # its steps would be as close as a plan file's may be
        raise PlanningError(f"step must be at least {MIN_PLAN_STEP_MM:g} mm, got {step:g}")
    legs = 2 if return_to_start else 1
    q = length / step  # inf when the division overflows
    if q <= MAX_PLAN_STEPS:
        n_in = _steps_in(q, step) + 1  # as travel_schedule counts them
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
    environment: Environment | None = None,
    progress: Callable[[float], None] | None = None,
) -> Plan:
    """Plan the arm along ``path`` (Sec. 3.2-3.4); see the module docstring.

    With ``fit=CLEARANCE`` (the default when ``environment`` is given) the paper's
    fit is refined for the worst link clearance against ``environment`` and the
    joint-limit margin (:func:`hrm_ctrl.planning.refine.refine_angles`), and with
    ``search`` (the default for CLEARANCE) the free parameters are chosen first
    (:func:`choose_free_parameters`).  ``plan.report`` then also holds ``fit``,
    ``free_parameters``, ``refinement``, ``per_step`` and ``margin_statement``.

    Raises :class:`UnreachableError` (naming the step) when the backbone cannot
    reach the path, :class:`PlanningError` when the arm cannot be fitted.  Joint
    limits are checked in the report, not here (see
    :func:`hrm_ctrl.planning.report.check_limits`).  ``progress(fraction)`` (optional)
    is told the share of the refinement done (the long part of a refined plan).
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
    fit = opt.fit_mode(environment)
    search = opt.search if opt.search is not None else fit is FitMode.CLEARANCE
    t_start = time.perf_counter()
    choice: dict[str, Any] | None = None
    fw: _Forward | None = None
    beyond = fit is FitMode.CLEARANCE  # refinement carries on where the paper's stops
    if search:
        chosen, choice = choose_free_parameters(model, path, opt, environment)
        try:
            fw = forward_configurations(model, path, chosen, partial=beyond)
            opt = chosen
        except PlanningError:  # the coarse search found it, the fine plan did not
            choice["note"] = "the chosen parameters failed at the plan's step; kept the given"
    if fw is None:
        fw = forward_configurations(model, path, opt, partial=beyond)
    t_forward = time.perf_counter()
    alpha, theta = fw.alpha, fw.theta
    refinement: Refinement | None = None
    if fit is FitMode.CLEARANCE:
        targets = path.points_at(fw.travel)
        refinement = refine_angles(
            model,
            alpha,
            theta,
            targets,
            environment,
            clearance_of=worst_link_clearance_of(model, environment),
            options=opt.refine,
            travel=fw.travel,
            progress=progress,
            start_only_from=fw.unreached,
        )
        alpha, theta = refinement.alpha, refinement.theta
        if fw.unreached is not None:
            off = refinement.tip_error_mm[fw.unreached :]
            bad = np.flatnonzero(~(off <= opt.refine.tip_tolerance_mm))
            if len(bad):
                k = fw.unreached + int(bad[0])
                raise UnreachableError(
                    f"{fw.unreached_reason}; beyond the paper's family neither: from step {k} "
                    f"(travel {fw.travel[k]:.1f} mm) the tip stays {off[bad[0]]:.1f} mm off "
                    "the path within the joint limits and the per-step change limit"
                )
    family = paper_family_report(model, fw, alpha, theta, choice)
    travel, iters, modal_a, seg = fw.travel, fw.iterations, fw.modal_a, fw.seg
    step_time = fw.step_time_s.copy()
    if refinement is not None:
        step_time += refinement.time_s / len(travel)
    n = len(travel)
    backbones = dict(fw.backbones)
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
    t_report = time.perf_counter()
    plan.report = plan_report(plan, seg, opt.Q)
    plan.report["method"] = family
    if fit is FitMode.CLEARANCE or search:
        plan.report.update(
            refinement_report(plan, fit, choice, refinement, environment, fw.forward_time_s)
        )
    t_end = time.perf_counter()
    plan.report["plan_time_ms"] = (t_end - t_start) * 1e3
    if fit is FitMode.CLEARANCE or search:
        plan.report["time_split_ms"] = {
            "search": (choice or {}).get("time_ms", 0.0),
            "paper_plan": fw.forward_time_s * 1e3,
            "refinement": refinement.time_s * 1e3 if refinement is not None else 0.0,
            "report": (t_end - t_report) * 1e3,
            "other": (t_report - t_forward) * 1e3
            - (refinement.time_s * 1e3 if refinement is not None else 0.0),
        }
    return plan


@dataclass(frozen=True, eq=False)
class _Forward:
    """The paper's plan of the forward leg: Sec. 3.2-3.4 at every step."""

    travel: np.ndarray
    alpha: np.ndarray
    theta: np.ndarray
    seg: np.ndarray
    modal_a: np.ndarray
    iterations: np.ndarray
    step_time_s: np.ndarray
    backbones: dict[int, np.ndarray]
    forward_time_s: float
    # the first step the modal backbone could not reach (with ``partial``; the steps from
    # it on hold the last reached step's angles, a start for refinement only), else None
    unreached: int | None = None
    unreached_reason: str = ""


def forward_configurations(
    model: RobotModel, path: KnownPath, opt: PlanOptions, partial: bool = False
) -> _Forward:
    """The paper's configurations of the forward leg (modal curve, fit, angles).

    With ``partial``, a step the modal backbone cannot reach (after the first) ends the
    paper's plan there: the later steps repeat the last reached step's configuration
    (``unreached`` names the first of them), for refinement to carry on from."""
    t_start = time.perf_counter()
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
    modal_a = np.empty((n, 3))
    iters = np.zeros(n, dtype=np.int64)
    step_time = np.zeros(n)
    unreached: int | None = None
    reason = ""
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
            reason = f"step {i} (travel {travel[i]:.1f} mm): {exc}"
            if not partial or i < 2:
                raise UnreachableError(reason) from None
            unreached = i
            break
        modal_a[i] = sol.a
        iters[i] = sol.iterations
        step_time[i] = time.perf_counter() - t0
    t_solve = time.perf_counter()
    if unreached is not None:  # the steps beyond: the last reached one's, for refinement
        modal_a[unreached:] = modal_a[unreached - 1]
        L_m = L_m.copy()
        L_m[unreached:] = L_m[unreached - 1]
        reached_travel = travel.copy()
        reached_travel[unreached:] = travel[unreached - 1]
    else:
        reached_travel = travel

    # 2. Every step's backbone: its modal curve, then the travelled path (Steps 2-3),
    #    padded at the tip so that all steps share one array.
    mode = backbone_points(basis, X0, L_m, modal_a, b)  # (n, Q+1, 3)
    curves = np.concatenate((mode, travelled_path_padded(path, reached_travel)), axis=1)
    # 3. Fitting (Sec. 3.3), joint 2 nearest the modal curve at arc length l_1,
    #    turned about the O_1-O_3 axis by joint2_offset.
    f = np.clip(model.links[0] / L_m, 0.0, 1.0) * opt.Q
    k0 = np.minimum(np.floor(f).astype(np.int64), opt.Q - 1)
    w = (f - k0)[:, None]
    rows = np.arange(n)
    ref2 = (1.0 - w) * mode[rows, k0] + w * mode[rows, k0 + 1]
    O, seg = fit_joint_centres_batch(curves, model.links, ref2)
    if opt.joint2_offset != 0.0:
        O[:, 1] = turn_about_axis(O[:, 1], O[:, 0], O[:, 2], opt.joint2_offset)
    # 4. Joint angles (Sec. 3.4).
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
    if unreached is not None:
        seg[unreached:] = -1  # no joint of these steps is fitted onto the path
        backbones = {i: b for i, b in backbones.items() if i < unreached}
    return _Forward(
        travel=travel,
        alpha=alpha,
        theta=theta,
        seg=seg,
        modal_a=modal_a,
        iterations=iters,
        step_time_s=step_time,
        backbones=backbones,
        forward_time_s=time.perf_counter() - t_start,
        unreached=unreached,
        unreached_reason=reason,
    )


def paper_family_report(
    model: RobotModel,
    fw: _Forward,
    alpha: np.ndarray,
    theta: np.ndarray,
    choice: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The report's ``method``: whether the paper's family (Sec. 3: the modal backbone,
    joints on it, with the parameters planned with) follows the path within the joint
    limits, and if not whether the plan (``alpha, theta``, forward leg) goes beyond it:
    ``paper_family_follows``, ``paper_family_failure`` (why not, or None),
    ``beyond_paper_family``, ``given_parameters_follow`` (with a search: whether the
    given parameters' paper plan at the search's step kept the limits), ``text``."""
    reached = len(fw.travel) if fw.unreached is None else fw.unreached
    m = angle_margin(model, fw.alpha[:reached], fw.theta[:reached])
    failure: str | None = None
    if fw.unreached is not None:
        failure = f"its modal backbone cannot reach the path's start at {fw.unreached_reason}"
    elif float(m.min()) <= 0.0:
        i = int(np.argmin(m))
        j = int(
            np.argmin(
                np.minimum(
                    model.limit_alpha - np.abs(fw.alpha[i]), model.limit_theta - np.abs(fw.theta[i])
                )
            )
        )
        name, v = (
            ("alpha", fw.alpha[i, j])
            if model.limit_alpha - abs(fw.alpha[i, j]) <= model.limit_theta - abs(fw.theta[i, j])
            else ("theta", fw.theta[i, j])
        )
        first = int(np.flatnonzero(m <= 0.0)[0])
        failure = (
            f"its fit breaks joint {j + 1} {name} ({math.degrees(float(v)):.1f} deg at step {i}, "
            f"travel {fw.travel[i]:.1f} mm; first broken at step {first})"
        )
    within = bool(float(angle_margin(model, alpha, theta).min()) > 0.0)
    beyond = failure is not None and within
    given_ok: bool | None = None
    if choice is not None:
        gm = choice.get("given_margin_deg")
        given_ok = gm is not None and gm > 0.0
    if failure is None:
        text = "the paper's family (modal backbone, Sec. 3)"
        if given_ok is False and choice is not None:
            k, t = choice["start_angles_deg"]
            text += (
                f", with the searched parameters (start angles ({k:.1f}, {t:.1f}) deg, "
                f"alpha_step {choice['alpha_step']:g}, joint-2 turn "
                f"{choice['joint2_offset_deg']:.1f} deg): with the given ones it "
                + (
                    "cannot reach the path"
                    if choice.get("given_margin_deg") is None
                    else f"breaks the joint limits ({choice['given_margin_deg']:.1f} deg)"
                )
            )
    elif beyond:
        text = (
            f"beyond the paper's family: {failure}; all 24 angles fitted with the tip on "
            "the path, started from the paper's steps"
        )
    else:
        text = f"the paper's family fails: {failure}"
    return {
        "paper_family_follows": failure is None,
        "paper_family_failure": failure,
        "beyond_paper_family": beyond,
        "given_parameters_follow": given_ok,
        "text": text,
    }


def turn_about_axis(P: np.ndarray, A: np.ndarray, B: np.ndarray, phi: float) -> np.ndarray:
    """Points P (N, 3) turned by phi (rad) about the axes A -> B (N, 3) (Rodrigues).

    >>> turn_about_axis(np.array([[1.0, 1, 0]]), np.zeros((1, 3)), np.array([[1.0, 0, 0]]),
    ...                 np.pi / 2).round(12).tolist()
    [[1.0, 0.0, 1.0]]
    """
    k = B - A
    k = k / np.linalg.norm(k, axis=1, keepdims=True)
    v = P - A
    kv = np.einsum("ij,ij->i", k, v)[:, None]
    c, s = math.cos(phi), math.sin(phi)
    return A + v * c + np.cross(k, v) * s + k * kv * (1.0 - c)


def worst_link_clearance_of(model: RobotModel, environment: Environment | None) -> Any:
    """``O (N, 13, 3) -> (N,)``: the worst link clearance of each step (mm) against
    ``environment`` (:func:`hrm_ctrl.planning.environment.link_clearance`); +inf
    without one."""
    radius = 0.5 * np.asarray(model.outer_diameter, dtype=float)

    def clearance_of(O: np.ndarray) -> np.ndarray:
        if environment is None:
            return np.full(len(O), math.inf)
        return link_clearance(environment, O, radius).min(axis=1)

    return clearance_of


def sampled_worst_clearance(
    model: RobotModel, environment: Environment | None, O: np.ndarray, samples: int = 9
) -> float:
    """The worst clearance (mm) of ``O`` (N, 13, 3) at ``samples`` points per link: a
    quick estimate (:func:`link_clearance` finds the exact minimum)."""
    if environment is None:
        return math.inf
    t = np.linspace(0.0, 1.0, samples)
    P = O[:, :-1, None, :] + t[None, None, :, None] * (O[:, 1:] - O[:, :-1])[:, :, None, :]
    d = environment.free_distance(P) - 0.5 * np.asarray(model.outer_diameter)[None, :, None]
    return float(d.min())


def choose_free_parameters(
    model: RobotModel, path: KnownPath, opt: PlanOptions, environment: Environment | None
) -> tuple[PlanOptions, dict[str, Any]]:
    """Issue 10: the free parameters of the paper's method chosen by a small search.

    Three rounds, each keeping the best so far: the modal curve's start angles
    (b1k, b1t), the given ones and 12 deg either way in K and in T (only directions
    within the base joint's reach: at most ``limit - margin goal`` from the base's
    axis), then alpha_step (the given one, 0.98, 0.95), then the turn of joint 2
    about O_1-O_3 (0, +-15 deg): at most 9 candidates.  Each candidate is the paper's
    plan at a step of at least :data:`SEARCH_STEP_MM`, scored by its worst link
    clearance (capped, sampled) plus ``margin_weight_mm_per_deg`` times its
    joint-limit margin up to the goal (both of :class:`RefineOptions`).
    Candidates the method cannot follow are skipped; the given parameters stay
    unless the best candidate scores :data:`SEARCH_MIN_GAIN` more.

    Returns the options to plan with (``search`` off) and what the search found.
    """
    t0 = time.perf_counter()
    ro = opt.refine
    goal = ro.margin_goal_deg
    coarse = replace(
        opt,
        step=max(opt.step, SEARCH_STEP_MM),
        return_to_start=False,
        backbone_steps=(),
        fit=FitMode.PAPER,
        search=False,
    )
    tried: list[dict[str, Any]] = []

    def score(cand: PlanOptions) -> float:
        try:
            fw = forward_configurations(model, path, cand)
        except PlanningError:
            tried.append({"ok": False})
            return -math.inf
        O = joint_centres(model, fw.alpha, fw.theta)
        m = float(np.degrees(angle_margin(model, fw.alpha, fw.theta).min()))
        c = sampled_worst_clearance(model, environment, O)
        value = (min(c, ro.clearance_cap_mm) if math.isfinite(c) else 0.0) + (
            ro.margin_weight_mm_per_deg * min(m, goal)
        )
        tried.append({"ok": True, "margin_deg": m, "clearance_mm": c, "score": value})
        return value

    if opt.start_angles is None:
        K0, T0 = tangent_angles(model.base_direction)
    else:
        K0, T0 = opt.start_angles
    base_dir = np.asarray(model.base_direction, dtype=float)
    reach = min(model.limit_alpha, model.limit_theta) - math.radians(goal)
    d = math.radians(12.0)
    starts = []
    for dK, dT in ((-d, 0.0), (d, 0.0), (0.0, -d), (0.0, d)):
        K, T = K0 + dK, T0 + dT
        u = np.array([math.sin(K) * math.cos(T), math.cos(K) * math.cos(T), math.sin(T)])
        if math.acos(max(-1.0, min(1.0, float(u @ base_dir)))) <= reach:
            starts.append({"start_angles": (K, T)})
    alphas = [{"alpha_step": a} for a in (0.98, 0.95) if a < opt.alpha_step]
    turns = [{"joint2_offset": math.radians(v)} for v in (-15.0, 15.0)]
    best_opt = replace(coarse, start_angles=(K0, T0))
    best = score(best_opt)
    given = best
    for round_ in (starts, alphas, turns):
        round_best = best_opt
        for change in round_:
            cand = replace(best_opt, **change)
            v = score(cand)
            if v > best:
                best, round_best = v, cand
        best_opt = round_best
    if not best > given + SEARCH_MIN_GAIN:  # the score is a proxy: move only for a clear gain
        best_opt, best = replace(coarse, start_angles=(K0, T0)), given
    chosen = replace(
        opt,
        start_angles=best_opt.start_angles,
        alpha_step=best_opt.alpha_step,
        joint2_offset=best_opt.joint2_offset,
        search=False,
    )
    ok = [t for t in tried if t["ok"]]
    K, T = chosen.start_angles or (K0, T0)
    info: dict[str, Any] = {
        "searched": True,
        "start_angles_deg": [math.degrees(K), math.degrees(T)],
        "alpha_step": chosen.alpha_step,
        "joint2_offset_deg": math.degrees(chosen.joint2_offset),
        "candidates": len(tried),
        # the given parameters' paper plan at the search's step: its margin, None if the
        # modal backbone could not follow the path
        "given_margin_deg": tried[0].get("margin_deg"),
        "candidates_followed": len(ok),
        "score": best if math.isfinite(best) else None,
        "given_score": given if math.isfinite(given) else None,
        "search_step_mm": coarse.step,
        "time_ms": (time.perf_counter() - t0) * 1e3,
    }
    return chosen, info


def refinement_report(
    plan: Plan,
    fit: FitMode,
    choice: dict[str, Any] | None,
    refinement: Refinement | None,
    environment: Environment | None,
    paper_time_s: float,
) -> dict[str, Any]:
    """The report's issue-10 entries: ``fit``, ``free_parameters``, ``refinement``,
    ``per_step`` (clearance, joint-limit margin, largest angle change into each step)
    and ``margin_statement``."""
    model = plan.model
    n = len(plan.travel)
    m_deg = np.degrees(angle_margin(model, plan.alpha, plan.theta))
    change = np.zeros(n)
    if n > 1:
        change[1:] = np.degrees(
            np.maximum(
                np.abs(np.diff(plan.alpha, axis=0)), np.abs(np.diff(plan.theta, axis=0))
            ).max(axis=1)
        )
    out: dict[str, Any] = {"fit": fit.value}
    if choice is not None:
        out["free_parameters"] = choice
    else:
        K, T = plan.options.start_angles or tangent_angles(model.base_direction)
        out["free_parameters"] = {
            "searched": False,
            "start_angles_deg": [math.degrees(K), math.degrees(T)],
            "alpha_step": plan.options.alpha_step,
            "joint2_offset_deg": math.degrees(plan.options.joint2_offset),
        }
    per: dict[str, Any] = {
        "joint_limit_margin_deg": m_deg.tolist(),
        "max_angle_change_deg": change.tolist(),
    }
    if refinement is not None:
        c = refinement.clearance_mm
        c_in = refinement.paper_clearance_mm
        n_in = len(c)
        clear_all = c if n == n_in else np.concatenate((c, c[np.arange(n_in - 2, -1, -1)]))
        per["clearance_mm"] = [float(v) if math.isfinite(v) else None for v in clear_all]
        fin, fin_in = np.isfinite(c), np.isfinite(c_in)
        out["refinement"] = {
            "environment": environment is not None,
            "paper_clearance_min_mm": float(c_in[fin_in].min()) if fin_in.any() else None,
            "clearance_min_mm": float(c[fin].min()) if fin.any() else None,
            "clearance_min_step": int(np.argmin(np.where(fin, c, np.inf))) if fin.any() else -1,
            "margin_deg": float(refinement.margin_deg.min()),
            "tip_error_mm": float(refinement.tip_error_mm.max()),
            "steps_kept_paper_fit": list(refinement.kept_input),
            "repair_passes": refinement.repair_passes,
            "evaluations": refinement.evaluations,
            "iterations": {
                "total": int(refinement.iterations.sum()),
                "max_per_step": int(refinement.iterations.max()),
            },
            "time_ms": refinement.time_s * 1e3,
            "time_split_ms": {k: v * 1e3 for k, v in refinement.time_split_s.items()},
            "paper_plan_ms": paper_time_s * 1e3,
        }
    out["per_step"] = per
    out["margin_statement"] = margin_statement(plan, environment)
    return out


def margin_statement(plan: Plan, environment: Environment | None = None) -> str:
    """One line on the plan's joint-limit margin against :data:`SAFE_MARGIN_DEG`, and
    when it is less, what binds the joint (:func:`margin_reason`)."""
    fwd = np.array([ph == "in" for ph in plan.phase])
    m = np.where(fwd, angle_margin(plan.model, plan.alpha, plan.theta), np.inf)
    i = int(np.argmin(m))
    ma = plan.model.limit_alpha - np.abs(plan.alpha[i])
    mt = plan.model.limit_theta - np.abs(plan.theta[i])
    if ma.min() <= mt.min():
        j, name = int(np.argmin(ma)), "alpha"
    else:
        j, name = int(np.argmin(mt)), "theta"
    deg = math.degrees(float(m[i]))
    where = f"step {i}, joint {j + 1} {name}"
    if deg >= SAFE_MARGIN_DEG:
        return f"joint-limit margin {deg:.2f} deg (>= {SAFE_MARGIN_DEG:g} deg), least at {where}"
    return (
        f"no plan with >= {SAFE_MARGIN_DEG:g} deg joint-limit margin found: the best has "
        f"{deg:.2f} deg at {where}: {margin_reason(plan, i, environment)}"
    )


def margin_reason(plan: Plan, i: int, environment: Environment | None) -> str:
    """Why step ``i`` has no more joint-limit margin: a local search of that step alone
    (:func:`hrm_ctrl.planning.refine.best_margin_at`), the tip on its path point, first
    with every angle free within its limits and no obstacle (if that finds less than
    :data:`SAFE_MARGIN_DEG`, the path itself forces the joint), then with the environment
    (the clearance binds), else the per-step change limit from the step before (the
    refinement is greedy along the travel and reached the step too late to turn the
    joint away)."""
    model, ro = plan.model, plan.options.refine
    q = np.r_[plan.alpha[i], plan.theta[i]]
    target = plan.path.points_at(plan.travel[i : i + 1])[0]
    at = f"travel {plan.travel[i]:.1f} mm"
    free = math.degrees(best_margin_at(model, q, target, None, ro))
    if free == -math.inf:
        return (
            f"the path forces it: a search finds no configuration within the joint limits "
            f"with the tip on the path at {at}"
        )
    if free < SAFE_MARGIN_DEG:
        return (
            f"the path forces it: with the tip on the path at {at} and every angle free "
            f"within its limits, a search finds at most {free:.2f} deg there"
        )
    if environment is not None:
        clear = math.degrees(best_margin_at(model, q, target, environment, ro))
        if clear < SAFE_MARGIN_DEG:
            return (
                f"the environment binds it: clear of the obstacles a search finds at most "
                f"{clear:.2f} deg at {at} ({free:.2f} deg without them)"
            )
    step = ro.max_step_change_deg - ro.step_change_slack_deg
    return (
        f"the per-step change limit ({step:g} deg per {ro.reference_step_mm:g} mm of travel) "
        f"binds it: {free:.2f} deg exists at {at} with the angles free, but the fit, greedy "
        f"along the travel, cannot turn the joints there in time from step {max(i - 1, 0)}"
    )


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
