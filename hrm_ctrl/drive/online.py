"""The online step of follow-the-leader driving: the arm fitted onto modal segment + trail.

Every control cycle (or every advance of at most ``max_step_mm``, 1 mm) the planner
puts the arm where the paper puts it for the travelled distance ``d`` (Sec. 3.2): the
modal curve from the base to the trail's start ``A`` with length ``L - d`` (its factors
warm-started from the last steps, :func:`hrm_ctrl.planning.planner.predict_modal_factors`,
solved by :func:`hrm_ctrl.planning.backbone.solve_modal_factors`), then the trail from
``A`` up to ``d``, the joints fitted onto that backbone
(:func:`hrm_ctrl.planning.fitting.fit_joint_centres_on_segments`) and their angles
(:func:`hrm_ctrl.planning.joint_angles.joint_angles_from_centres`).  Where an environment
is known the angles are then refined for clearance and joint-limit margin (elsewhere for
the margin alone; ``refine_steps=False`` keeps the paper's fit) as the offline planner
refines them (:mod:`hrm_ctrl.planning.refine`: the tip held on the trail, every
angle within ``max_step_change_deg`` per 5 mm of travel of the last step), starting from
the last step moved by the paper fit's change, with a few Gauss-Newton iterations a step
(``refine_iterations``): the warm start leaves little to do.

**Clearance worth having.**  The refinement is greedy along the travel: it looks no
further than the step, and one iteration at every 0.2 mm of travel (at 100 Hz) climbs
much further than the offline plan's few iterations per 5 mm.  Online, clearance beyond
15 mm earns nothing (the offline cap is 40 mm): away from walls the arm keeps the paper
fit's shape changes, the trail's own shape, and turns off them only for a link that comes
within 15 mm of the environment.  With the offline cap, through the cabins steered by
keys, the arm centred its links in the entrance's opening (19 mm instead of the offline
plan's 9), turned 18 deg off the paper fit doing so, and had no way back within the
step's change limit (2 deg per 5 mm) when links 10-12 reached the partition's opening:
they came within the 1 mm margin at 287 mm of travel, where the offline plan clears
them by 8.5 mm.

**The way back.**  Every step taken beyond the farthest travel so far is recorded; a step
back over the recorded travel (retracting, or advancing again over it) replays the recorded
configurations, linearly interpolated between the two around it, as the offline plan's
return leg replays its forward steps: the arm retraces the shapes it came in with (the
refinement, greedy along the travel, would otherwise take another way back).  Cutting the
trail for a new branch (:meth:`OnlinePlanner.forget_beyond`) drops the records beyond.

**Refusals.**  A step is checked before it is taken; a failed check returns a
:class:`Refusal` (its kind, one line for the operator, and the numbers: which joint,
which limit, how close) and leaves the planner where it was, so the arm holds:

- ``END_OF_LENGTH``: the modal segment cannot be shorter (the arm is stretched from its
  base to ``A``), or the trail's start is reached when retracting;
- ``TOO_TIGHT``: a joint on the trail would have to bend more than it can in every
  direction (``planning/conditioning.py``'s rule, ``φ = arccos(cos α cos θ) <= φ_max``,
  applied to the joints fitted onto the trail);
- ``JOINT_LIMIT``: an angle would come within ``joint_margin_deg`` of its limit;
- ``CLEARANCE``: a link would come closer than ``clearance_margin_mm`` to the
  environment (sampled link clearance, :func:`hrm_ctrl.planning.refine.zoomed_link_minima`);
- ``FIT``: the refined fit cannot hold the tip on the trail within the step's change.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.drive.trail import Trail
>>> m = default_robot()
>>> trail = Trail.starting_at(np.array([1200.0, 100.0, 300.0]), np.array([1.0, 0.0, 0.0]))
>>> p = OnlinePlanner(m, trail)
>>> trail.extend(5.0, 0.0, 0.0)
>>> p.step_to(5.0) is None, round(float(np.linalg.norm(p.tip - [1205.0, 100, 300])), 6)
(True, 0.0)
>>> r = p.step_to(-1.0)
>>> r.kind.value, p.travel
('end_of_length', 0.0)
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.errors import PlanningError, UnreachableError
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.backbone import (
    Boundary,
    ModalBasis,
    backbone_points,
    solve_modal_cold,
    solve_modal_factors,
)
from hrm_ctrl.planning.conditioning import bend_limit, joint_bend
from hrm_ctrl.planning.environment import Environment
from hrm_ctrl.planning.fitting import fit_joint_centres_on_segments
from hrm_ctrl.planning.joint_angles import joint_angles_from_centres
from hrm_ctrl.planning.known_path import tangent_angles
from hrm_ctrl.planning.planner import predict_modal_factors
from hrm_ctrl.planning.refine import (
    RefineOptions,
    StepObjective,
    joint_axes,
    kkt_step,
    linearised_objective,
    project_tip,
    refine_step,
)


class RefusalKind(StrEnum):
    """Why the arm holds instead of taking a step."""

    END_OF_LENGTH = "end_of_length"
    TOO_TIGHT = "too_tight"
    JOINT_LIMIT = "joint_limit"
    CLEARANCE = "clearance"
    FIT = "fit"


@dataclass(frozen=True)
class Refusal:
    """A refused step: its kind, one line for the status line, and the numbers."""

    kind: RefusalKind
    text: str
    travel_mm: float
    joint: int | None = None  # 1-based
    angle: str | None = None  # "alpha", "theta" or "bend"
    value_deg: float | None = None
    limit_deg: float | None = None
    link: int | None = None  # 1-based
    clearance_mm: float | None = None


@dataclass(frozen=True)
class OnlineOptions:
    """Settings of the online step (mm, degrees where named so)."""

    Q: int = 200
    max_step_mm: float = 1.0
    joint_margin_deg: float = 0.5
    clearance_margin_mm: float = 1.0
    # one damped Gauss-Newton iteration a step (two evaluations): the warm start leaves
    # little to do at <= 1 mm a step; clearance beyond 15 mm earns nothing (module doc:
    # the arm keeps the paper fit's shape changes until a link comes that close)
    refine: RefineOptions = field(
        default_factory=lambda: RefineOptions(
            max_iterations=1, trials=1, patient_iterations=0, clearance_cap_mm=15.0
        )
    )
    tip_tolerance_mm: float = 0.05  # the refined tip's distance from the trail point
    # the modal segment keeps this much more than the straight line from the base to the
    # trail's start: near full stretch its shape changes faster than a step may turn a joint
    length_margin_mm: float = 2.0
    # refine every step (for clearance where an environment is known, for joint-limit
    # margin everywhere, as ``hrm plan`` does); False: the paper's fit alone
    refine_steps: bool = True

    def __post_init__(self) -> None:
        from hrm_ctrl.drive.command import DriveError

        if not (2 <= self.Q <= 2000):
            raise DriveError(f"online step: Q must be in [2, 2000], got {self.Q}")
        if not (0.0 < self.max_step_mm <= 5.0):
            raise DriveError(f"online step: max_step_mm must be in (0, 5], got {self.max_step_mm}")
        if not (0.0 <= self.joint_margin_deg < 30.0):
            raise DriveError(
                f"online step: joint_margin_deg must be in [0, 30), got {self.joint_margin_deg}"
            )
        if not (math.isfinite(self.clearance_margin_mm) and self.clearance_margin_mm >= 0.0):
            raise DriveError(
                f"online step: clearance_margin_mm must be >= 0, got {self.clearance_margin_mm}"
            )


@dataclass
class StepTimes:
    """Seconds spent per part of the last step (where the time goes): the modal solve,
    the paper's fit (backbone, joint centres, angles, the conditioning rule), the
    refinement and the checks; of the refinement, the environment's free distances at the
    link samples (``environment``) and the projection of the tip back onto the trail
    (``projection``)."""

    modal: float = 0.0
    fit: float = 0.0
    refine: float = 0.0
    checks: float = 0.0
    environment: float = 0.0
    projection: float = 0.0

    @property
    def total(self) -> float:
        return self.modal + self.fit + self.refine + self.checks


class OnlinePlanner:
    """The arm along a trail, one step at a time (see the module).

    ``travel`` is the tip's distance along the trail; ``q`` the committed angles
    ``(alpha_1..12, theta_1..12)``.  :meth:`step_to` moves to a new travel (split into
    steps of at most ``max_step_mm``) or refuses; the trail may grow between calls.
    """

    def __init__(
        self,
        model: RobotModel,
        trail: Trail,
        environment: Environment | None = None,
        options: OnlineOptions | None = None,
        travel_mm: float = 0.0,
    ) -> None:
        self.model = model
        self.trail = trail
        self.env = environment if environment is not None and environment.obstacles else None
        self.opt = options or OnlineOptions()
        n = model.n_joints
        self.n = n
        self.basis = ModalBasis(self.opt.Q)
        self.X0 = np.asarray(model.base_position, dtype=float)
        self.A = trail.start
        self._gap = float(np.linalg.norm(self.A - self.X0))  # base to the trail's start
        b1k, b1t = tangent_angles(model.base_direction)
        b2k, b2t = tangent_angles(trail.start_tangent())
        self.boundary = Boundary(b1k, b1t, b2k, b2t)
        self.lim = np.r_[np.full(n, model.limit_alpha), np.full(n, model.limit_theta)]
        self.hard = self.lim - math.radians(self.opt.joint_margin_deg)  # refused beyond
        self.box = self.lim - 1e-6  # the refinement's box, as the offline refinement's
        self.phi_max = bend_limit(model)
        self.radius = 0.5 * np.asarray(model.outer_diameter, dtype=float)
        self._t = np.linspace(0.0, 1.0, self.opt.refine.samples_per_link)
        self._split: dict[str, float] = {
            "kinematics_and_jacobians": 0.0,
            "environment": 0.0,
            "solver": 0.0,
            "checks": 0.0,
        }
        # the refinement's objective: clearance and margin, or the margin alone
        self._objective = StepObjective(
            model, self.env, self.radius, self._t, self.opt.refine, self._split
        )
        # work buffers: the backbone (modal curve + trail), its size grows with the trail
        self._curve = np.empty((self.opt.Q + 1 + 1024, 3))
        self._tip_target = np.empty(3)
        self._centres = np.empty((model.n_joints + 1, 3))  # the refined step's joint centres
        self.times = StepTimes()
        self._env_s = self._projection_s = 0.0  # of the last refinement
        self.steps = 0
        # the start: travel_mm, the paper's fit, refined with a wide box where an
        # environment is known
        a_hist = np.zeros((0, 3))
        L_m = model.length - travel_mm
        sol = self._solve_cold(L_m, travel_mm)
        if isinstance(sol, Refusal):
            raise PlanningError(sol.text)
        a_hist = sol.a[None, :]
        fit = self._paper_fit(travel_mm, sol.a, L_m)
        if isinstance(fit, Refusal):
            raise PlanningError(fit.text)
        q_paper, _O, _seg = fit
        q = q_paper
        if self.opt.refine_steps:
            wide = math.radians(self.opt.refine.first_step_change_deg)
            lo = np.maximum(q_paper - wide, -self.box)
            hi = np.minimum(q_paper + wide, self.box)
            target = trail.point_at(travel_mm)
            q = project_tip(model, q_paper, target, lo, hi)
            q, _ = refine_step(self._objective, q, target, lo, hi, RefineOptions(max_iterations=20))
            q = project_tip(model, q, target, lo, hi)
        self.travel = float(travel_mm)
        self.q = q
        self.q_paper = q_paper
        self.a_hist = a_hist
        self.clearance_mm = self._clearance(q)[0]
        # the way back: every committed step of the travel drawn so far (travel, q,
        # paper's q, modal factors, clearance), replayed when the tip goes back over it
        self._hist_n = 0
        self._hist_d = np.empty(4096)
        self._hist_q = np.empty((4096, 4 * n + 3 + 1))
        self._record()

    # read-outs
    @property
    def alpha(self) -> np.ndarray:
        return self.q[: self.n]

    @property
    def theta(self) -> np.ndarray:
        return self.q[self.n :]

    @property
    def tip(self) -> np.ndarray:
        return joint_axes(self.model, self.q)[0][-1]

    def centres(self) -> np.ndarray:
        """Joint centres O_1..O_13 of the committed angles (13, 3)."""
        return joint_axes(self.model, self.q)[0]

    # the step
    def step_to(self, travel_mm: float) -> Refusal | None:
        """Move to ``travel_mm`` along the trail in steps of at most ``max_step_mm``;
        stop at the first refused step (returned; the planner stays at the last step
        taken), else None."""
        target = float(travel_mm)
        while True:
            gap = target - self.travel
            if abs(gap) <= 1e-12:
                return None
            d = self.travel + max(-self.opt.max_step_mm, min(self.opt.max_step_mm, gap))
            refusal = self.step(d)
            if refusal is not None:
                return refusal

    def step(self, travel_mm: float) -> Refusal | None:
        """One online step to ``travel_mm`` (within ``max_step_mm`` of the last); None
        when taken, else the refusal (nothing changed)."""
        t0 = time.perf_counter()
        d = float(travel_mm)
        if 0.0 <= d <= self._hist_d[self._hist_n - 1] and self._hist_n >= 2:
            self._replay(d)
            self.times = StepTimes(0.0, 0.0, 0.0, time.perf_counter() - t0)
            return None
        if d < 0.0:
            return Refusal(
                RefusalKind.END_OF_LENGTH,
                f"at the trail's start (travel {self.travel:.1f} mm): nothing to retract",
                self.travel,
            )
        if d > self.trail.length + 1e-9:
            return Refusal(
                RefusalKind.END_OF_LENGTH,
                f"travel {d:.1f} mm is past the trail's end ({self.trail.length:.1f} mm)",
                self.travel,
            )
        L_m = self.model.length - d
        gap = self._gap
        if L_m <= gap + self.opt.length_margin_mm:
            return self._end_of_length(d, L_m, gap)
        guess = predict_modal_factors(self.a_hist)
        try:
            sol = solve_modal_factors(self.basis, self.X0, self.A, L_m, self.boundary, a0=guess)
        except UnreachableError:
            try:
                sol = solve_modal_factors(
                    self.basis, self.X0, self.A, L_m, self.boundary, a0=self.a_hist[-1]
                )
            except UnreachableError as exc:
                return Refusal(
                    RefusalKind.END_OF_LENGTH,
                    f"the arm's length ends here (travel {d:.1f} mm): {exc}",
                    self.travel,
                )
        t1 = time.perf_counter()
        fit = self._paper_fit(d, sol.a, L_m)
        t2 = time.perf_counter()
        if isinstance(fit, Refusal):
            self.times = StepTimes(t1 - t0, t2 - t1, 0.0, 0.0)
            return fit
        q_paper, _O, seg = fit
        refusal = self._too_tight(d, q_paper, seg)
        if refusal is not None:
            return refusal
        q = q_paper
        t3 = t2
        clearance: tuple[float, int] = (math.inf, 0)
        if self.opt.refine_steps:
            refined = self._refined(d, q_paper)
            t3 = time.perf_counter()
            if isinstance(refined, Refusal):
                self.times = StepTimes(t1 - t0, t2 - t1, t3 - t2, 0.0)
                return refined
            q, clearance = refined
        refusal = self._limits(d, q, clearance)
        t4 = time.perf_counter()
        self.times = StepTimes(t1 - t0, t2 - t1, t3 - t2, t4 - t3, self._env_s, self._projection_s)
        if refusal is not None:
            return refusal
        # commit
        self.travel = d
        self.q = q
        self.q_paper = q_paper
        self.a_hist = np.vstack((self.a_hist[-2:], sol.a[None, :]))
        self.clearance_mm = clearance[0]
        self.steps += 1
        self._record()
        return None

    # the way back
    def _record(self) -> None:
        """Keep the committed step (a travel beyond every recorded one)."""
        k = self._hist_n
        if k and self.travel <= self._hist_d[k - 1]:
            return
        if k == len(self._hist_d):
            self._hist_d = np.concatenate((self._hist_d, np.empty(k)))
            self._hist_q = np.concatenate((self._hist_q, np.empty_like(self._hist_q)))
        n2 = 2 * self.n
        row = self._hist_q[k]
        row[:n2] = self.q
        row[n2 : 2 * n2] = self.q_paper
        row[2 * n2 : 2 * n2 + 3] = self.a_hist[-1]
        row[-1] = self.clearance_mm
        self._hist_d[k] = self.travel
        self._hist_n = k + 1

    def _replay(self, d: float) -> None:
        """The recorded steps at travel ``d``, linearly interpolated between the two
        around it (0.2-1 mm apart): the arm retraces the configurations it came with."""
        D = self._hist_d[: self._hist_n]
        j = min(max(int(np.searchsorted(D, d, side="right")) - 1, 0), self._hist_n - 2)
        w = (d - D[j]) / (D[j + 1] - D[j])
        # the angles and modal factors (the clearance, inf without an environment, apart)
        row = (1.0 - w) * self._hist_q[j, :-1] + w * self._hist_q[j + 1, :-1]
        n2 = 2 * self.n
        self.travel = d
        self.q = row[:n2].copy()
        self.q_paper = row[n2 : 2 * n2].copy()
        a = row[2 * n2 : 2 * n2 + 3]
        self.a_hist = np.vstack((self._hist_q[max(j - 1, 0), 2 * n2 : 2 * n2 + 3], a))
        self.clearance_mm = float(min(self._hist_q[j, -1], self._hist_q[j + 1, -1]))
        self.steps += 1

    def forget_beyond(self, travel_mm: float) -> None:
        """Drop the recorded steps beyond ``travel_mm`` (the trail is cut there: a new
        branch is drawn from it)."""
        D = self._hist_d[: self._hist_n]
        self._hist_n = max(1, int(np.searchsorted(D, travel_mm, side="right")))

    # parts
    def _solve_cold(self, L_m: float, d: float) -> Refusal | object:
        gap = self._gap
        if L_m <= gap * (1.0 + 1e-6):
            return self._end_of_length(d, L_m, gap)
        try:
            return solve_modal_cold(self.basis, self.X0, self.A, L_m, self.boundary)
        except UnreachableError as exc:
            return Refusal(RefusalKind.END_OF_LENGTH, f"cannot start here: {exc}", d)

    def _end_of_length(self, d: float, L_m: float, gap: float) -> Refusal:
        return Refusal(
            RefusalKind.END_OF_LENGTH,
            f"end of the arm's length at travel {d:.1f} mm: {L_m:.1f} mm left for the "
            f"{gap:.1f} mm from the base to the trail's start (margin "
            f"{self.opt.length_margin_mm:g} mm)",
            self.travel,
        )

    def _backbone(self, d: float, a: np.ndarray, L_m: float) -> np.ndarray:
        """The modal curve then the trail up to ``d`` (into the work buffer)."""
        Q1 = self.opt.Q + 1
        trail = self.trail
        k = trail.count_before(d)  # trail points before d: A (k >= 1 for d > 0) ...
        m = Q1 + max(k - 1, 0) + (1 if d > 0.0 else 0)
        if m > len(self._curve):
            self._curve = np.empty((2 * m, 3))
        c = self._curve
        c[:Q1] = backbone_points(self.basis, self.X0, L_m, a, self.boundary)
        if k > 1:
            c[Q1 : Q1 + k - 1] = trail.points[1:k]
        if d > 0.0:
            trail.point_at(d, out=c[m - 1])
        return c[:m]

    def _paper_fit(
        self, d: float, a: np.ndarray, L_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | Refusal:
        curve = self._backbone(d, a, L_m)
        try:
            O, seg = fit_joint_centres_on_segments(curve, self.model.links)
        except PlanningError as exc:
            return Refusal(RefusalKind.FIT, f"no fit at travel {d:.1f} mm: {exc}", self.travel)
        alpha, theta = joint_angles_from_centres(self.model, O)
        return np.concatenate((alpha, theta)), O, seg

    def _too_tight(self, d: float, q: np.ndarray, seg: np.ndarray) -> Refusal | None:
        """The conditioning rule on the joints fitted onto the trail (joints 2..12)."""
        n = self.n
        on_trail = seg[1:n] >= self.opt.Q  # joints 2..12 on the trail's segments
        if not on_trail.any():
            return None
        bend = joint_bend(q[1:n], q[n + 1 :])
        bad = on_trail & (bend > self.phi_max)
        if not bad.any():
            return None
        j = int(np.argmax(np.where(bad, bend, -1.0)))
        return Refusal(
            RefusalKind.TOO_TIGHT,
            f"steer too tight at travel {d:.1f} mm: joint {j + 2} would bend "
            f"{math.degrees(bend[j]):.2f} deg, more than the {math.degrees(self.phi_max):.0f} "
            "it can bend in any direction",
            self.travel,
            joint=j + 2,
            angle="bend",
            value_deg=math.degrees(float(bend[j])),
            limit_deg=math.degrees(self.phi_max),
        )

    def _refined(
        self, d: float, q_paper: np.ndarray
    ) -> tuple[np.ndarray, tuple[float, int]] | Refusal:
        """The clearance refinement of one step, warm-started from the last step moved by
        the paper fit's change: one evaluation of the clearances (and the tip) with their
        Jacobians there, one damped Gauss-Newton step of the offline refinement's problem
        (:func:`~hrm_ctrl.planning.refine.linearised_objective`,
        :func:`~hrm_ctrl.planning.refine.kkt_step`), the tip projected back onto the trail.
        The clearance it returns (worst, link) is the linear prediction at the new angles
        from that evaluation (the step moves the angles by at most a few hundredths of a
        degree); the next step's evaluation measures it again."""
        f = self._objective
        ro = self.opt.refine
        step = abs(d - self.travel) / ro.reference_step_mm
        bound = math.radians(ro.max_step_change_deg - ro.step_change_slack_deg) * step
        lo = np.maximum(self.q - bound, -self.box)
        hi = np.minimum(self.q + bound, self.box)
        target = self.trail.point_at(d, out=self._tip_target)
        guess = np.clip(self.q + (q_paper - self.q_paper), lo, hi)
        env_s = self._split["environment"]
        tip, Jtip, c, Jc = f.evaluate(guess)
        self._env_s = self._split["environment"] - env_s
        q = guess
        normal = linearised_objective(f, guess, c, Jc, ro)
        if normal is not None:
            q = kkt_step(normal[0], normal[1], Jtip, target - tip, ro.damping, guess, lo, hi)
        t0 = time.perf_counter()
        O = self._centres
        q = project_tip(self.model, q, target, lo, hi, tol=1e-4, iterations=3, centres=O)
        self._projection_s = time.perf_counter() - t0
        err = float(np.linalg.norm(O[-1] - target))
        if err > self.opt.tip_tolerance_mm:
            return Refusal(
                RefusalKind.FIT,
                f"the arm cannot follow at travel {d:.1f} mm: within "
                f"{math.degrees(bound):.2f} deg a step the tip stays {err:.2f} mm off the trail",
                self.travel,
            )
        if c is None or Jc is None:
            return q, (math.inf, 0)
        c_new = c + Jc @ (q - guess)
        k = int(np.argmin(c_new))
        return q, (float(c_new[k]), k // (len(c_new) // self.n) + 1)

    def _clearance(self, q: np.ndarray) -> tuple[float, int]:
        """Worst sampled link clearance of ``q`` (one evaluation) and its link (1-based);
        inf, 0 without an environment."""
        if self.env is None:
            return math.inf, 0
        c = self._objective.evaluate(q)[2]
        if c is None:
            return math.inf, 0
        k = int(np.argmin(c))
        return float(c[k]), k // (len(c) // self.n) + 1

    def _limits(self, d: float, q: np.ndarray, clearance: tuple[float, int]) -> Refusal | None:
        n = self.n
        over = np.abs(q) - self.hard
        j = int(np.argmax(over))
        if over[j] > 0.0:
            name = "alpha" if j < n else "theta"
            joint = j % n + 1
            limit = math.degrees(float(self.lim[j]))
            return Refusal(
                RefusalKind.JOINT_LIMIT,
                f"joint {joint} {name} would reach {math.degrees(float(q[j])):.1f} deg at travel "
                f"{d:.1f} mm: within {self.opt.joint_margin_deg:g} deg of its limit "
                f"{limit:.0f}",
                self.travel,
                joint=joint,
                angle=name,
                value_deg=math.degrees(float(q[j])),
                limit_deg=limit,
            )
        c, link = clearance
        if c < self.opt.clearance_margin_mm:
            return Refusal(
                RefusalKind.CLEARANCE,
                f"link {link} would come {c:.1f} mm from the environment at travel {d:.1f} mm "
                f"(margin {self.opt.clearance_margin_mm:g} mm)",
                self.travel,
                link=link,
                clearance_mm=c,
            )
        return None
