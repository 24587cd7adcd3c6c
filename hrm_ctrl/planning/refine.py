"""Refinement of the paper's fit for clearance and joint-limit margin (issue 10).

The paper (Sec. 3.3) puts the joint centres on the backbone, but each rigid link
between two joints is a chord that cuts the corner (``NOTES.md``).  Starting from
the paper's angles, each step's 24 joint angles ``q = (alpha_1..12, theta_1..12)``
are moved, step after step along the travel and each warm-started from the last
refined step, to solve

    maximise   c + mu * min(m, m_goal)
    subject to O_13(q) = X_i                      (the tip on the path point of step i)
               c <= c_k(q)  for every link sample k  (free distance minus link radius)
               m <= limit - |q_j|  for every angle j (joint-limit margin)
               |q_j - q_j(i-1)| <= delta          (smooth trajectories)

(c the worst clearance, capped at ``clearance_cap_mm``; m the smallest margin; delta
``max_step_change_deg`` per ``reference_step_mm`` of travel) by damped Gauss-Newton
steps (:func:`refine_step`) with analytic Jacobians: a joint's rotation about its world
axis ``w`` through its centre ``O_k`` moves a point ``p`` after it by ``w x (p - O_k)``.
A final Gauss-Newton projection puts the tip back on the path to far below
``tip_tolerance_mm`` (0.01 mm).  No step ends worse than the paper's fit at that step
(worst link clearance, capped, by the exact measure ``clearance_of``): see
:func:`refine_angles` for the passes that ensure it, and the steps that keep the input.

Without an environment the same problem is solved for the margin alone.

>>> from hrm_ctrl.model import default_robot
>>> m = default_robot()
>>> q = np.zeros(24); q[12] = 0.1                     # theta_1 = 0.1 rad
>>> O, W, C = joint_axes(m, q)
>>> Jtip = cross3(W, O[-1] - C).T                     # d tip / d q, (3, 24)
>>> h = np.zeros(24); h[3] = 1e-6                     # d tip / d alpha_4, central
>>> Of, Ob = (joint_axes(m, q + s * h)[0] for s in (1, -1))
>>> bool(np.allclose((Of[-1] - Ob[-1]) / 2e-6, Jtip[:, 3], atol=1e-5))
True
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol

import numpy as np

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.kinematics import R_BASE_PAPER, base_rows, turned_by_joint
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.backbone import solve3


class FreeSpace(Protocol):
    """What refinement needs of an environment (``hrm_ctrl.planning.environment``)."""

    def free_distance_and_gradient(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


@dataclass(frozen=True)
class RefineOptions:
    """Settings of :func:`refine_angles` (mm, degrees where named so).

    Attributes:
        max_step_change_deg: largest change of any angle between two steps (the
            constraint is kept with ``step_change_slack_deg`` to spare); per
            ``reference_step_mm`` of travel when the travel is given, scaled with each
            step's travel.
        reference_step_mm: the travel the step-change bound is stated for.
        margin_goal_deg: joint-limit margin worth trading clearance for; beyond it
            margin earns nothing.
        margin_weight_mm_per_deg: mu, clearance (mm) one degree of margin is worth
            while the margin is below its goal.
        tip_tolerance_mm: largest distance of the tip from its path point.
        samples_per_link: points on each link axis where clearance is measured.
        clearance_cap_mm: clearance beyond this earns nothing (free space).
        max_iterations: Gauss-Newton iterations per step.
        first_step_change_deg: how far step 0 may move from the paper's fit.
        band_mm: clearances within this of the worst are pushed up together.
        centring_weight: weight (relative to the worst ones' 1) of pushing the other
            clearances below worst + ``comfort_mm`` up to that level.
        damping: initial Levenberg-Marquardt damping (mm^2 per rad^2).
        trials: damped steps tried per iteration before giving up, in the first
            ``patient_iterations``; one after them.
        tolerance_mm: an iteration that gains less than this (in the score) is the last.
        repair_passes: passes that plan again from a step the exact judge found worse
            than the input, or kept the input with a jump (see :func:`refine_angles`).
        pull_steps: steps before such a jump that start from the input's angles.
    """

    max_step_change_deg: float = 2.0
    step_change_slack_deg: float = 0.05
    reference_step_mm: float = 5.0
    margin_goal_deg: float = 6.0
    margin_weight_mm_per_deg: float = 3.0
    tip_tolerance_mm: float = 0.01
    samples_per_link: int = 9
    clearance_cap_mm: float = 40.0
    max_iterations: int = 6
    first_step_change_deg: float = 20.0
    band_mm: float = 0.5
    trials: int = 3
    patient_iterations: int = 3
    tolerance_mm: float = 0.0
    repair_passes: int = 4
    pull_steps: int = 12
    centring_weight: float = 0.0
    comfort_mm: float = 6.0
    damping: float = 1e3

    def check(self) -> None:
        if not (0.1 <= self.max_step_change_deg <= 30.0):
            raise PlanningError(
                f"max_step_change_deg must be in [0.1, 30], got {self.max_step_change_deg}"
            )
        if not (0.0 <= self.step_change_slack_deg < self.max_step_change_deg):
            raise PlanningError(
                f"step_change_slack_deg must be in [0, max_step_change_deg), "
                f"got {self.step_change_slack_deg}"
            )
        if not (0.0 <= self.margin_goal_deg < 60.0):
            raise PlanningError(f"margin_goal_deg must be in [0, 60), got {self.margin_goal_deg}")
        if not (2 <= self.samples_per_link <= 65):
            raise PlanningError(f"samples_per_link must be in [2, 65], got {self.samples_per_link}")
        if not (1 <= self.max_iterations <= 1000):
            raise PlanningError(f"max_iterations must be in [1, 1000], got {self.max_iterations}")
        if not (math.isfinite(self.reference_step_mm) and self.reference_step_mm > 0.0):
            raise PlanningError(
                f"reference_step_mm must be a finite number > 0, got {self.reference_step_mm}"
            )
        if not (self.tip_tolerance_mm > 0.0):
            raise PlanningError(f"tip_tolerance_mm must be > 0, got {self.tip_tolerance_mm}")


@dataclass(frozen=True, eq=False)
class Refinement:
    """Refined angles (N, 12) and what they achieve per step.

    ``clearance_mm`` and ``paper_clearance_mm`` (N,) are the worst link clearance
    of the refined and the input angles (``inf`` without an environment);
    ``margin_deg`` (N,) the smallest joint-limit margin; ``kept_input`` the steps
    that kept the input angles; ``repair_passes`` how many passes planned steps again
    (:func:`refine_angles`); ``evaluations`` how many configurations were evaluated
    (kinematics, Jacobians and the environment); ``time_s`` the time spent.
    """

    alpha: np.ndarray
    theta: np.ndarray
    clearance_mm: np.ndarray
    paper_clearance_mm: np.ndarray
    margin_deg: np.ndarray
    tip_error_mm: np.ndarray
    kept_input: tuple[int, ...]
    iterations: np.ndarray
    repair_passes: int
    evaluations: int
    time_s: float
    time_split_s: dict[str, float]


def joint_axes(model: RobotModel, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint centres (13, 3) (:func:`hrm_ctrl.kinematics.frames`), the world rotation axes
    (24, 3) of alpha_1..12 then theta_1..12, and the centre each axis passes through
    (24, 3), for one configuration ``q = (alpha, theta)``.

    alpha_k turns about the y axis of the frame before joint k; theta_k about the x axis
    after alpha_k, which ``Rot_x(theta_k)`` keeps: frame k's x axis.  The chain of
    Eq. (3) on floats (:func:`~hrm_ctrl.kinematics.turned_by_joint`, as
    :func:`~hrm_ctrl.kinematics.frames` for one configuration), the axes read off each
    frame's rows as it is made (the refinement evaluates a few configurations a step).

    >>> from hrm_ctrl.kinematics import frames
    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> q = np.random.default_rng(3).uniform(-1.0, 1.0, 24)
    >>> O, W, C = joint_axes(m, q)
    >>> R, O2 = frames(m, q[:12], q[12:])
    >>> bool((O == O2).all() and (W[12:] == R[:, :, 0]).all() and (W[1:12] == R[:-1, :, 1]).all())
    True
    """
    n = model.n_joints
    if q.shape != (2 * n,):
        raise ValueError(f"q must have shape ({2 * n},), got {q.shape}")
    c, s = np.cos(q).tolist(), np.sin(q).tolist()
    r = _base_rows(model)
    ox, oy, oz = model.base_position.tolist()
    O = [ox, oy, oz]
    Wa = _first_axis(model).tolist()  # alpha_1's axis, then frame k's y axis for alpha_k+1
    Wt: list[float] = []  # frame k's x axis for theta_k
    for k, length in enumerate(model.links.tolist()):
        r = turned_by_joint(r, c[k], s[k], c[n + k], s[n + k])
        Wa += (r[1], r[4], r[7])
        Wt += (r[0], r[3], r[6])
        ox, oy, oz = ox + r[2] * length, oy + r[5] * length, oz + r[8] * length
        O += (ox, oy, oz)
    del Wa[3 * n :]  # frame 12's y axis turns no joint
    W = np.array(Wa + Wt).reshape(2 * n, 3)
    C = np.array(O[: 3 * n] * 2).reshape(2 * n, 3)
    return np.array(O).reshape(n + 1, 3), W, C


_base_rows = lru_cache(maxsize=8)(base_rows)  # per model: the rotation before joint 1


@lru_cache(maxsize=8)
def _first_axis(model: RobotModel) -> np.ndarray:
    """alpha_1's world axis (3,): the y axis of the frame before joint 1 (read-only)."""
    w = (model.base_rotation @ R_BASE_PAPER)[:, 1].copy()
    w.setflags(write=False)
    return w


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis (3,) of broadcastable arrays (np.cross without
    its generality, a tenth of its cost on small arrays).

    >>> cross3(np.array([1.0, 0, 0]), np.array([0.0, 1, 0])).tolist()
    [0.0, 0.0, 1.0]
    """
    return a[..., _YZX] * b[..., _ZXY] - a[..., _ZXY] * b[..., _YZX]


_YZX, _ZXY = np.array([1, 2, 0]), np.array([2, 0, 1])  # cross3's component orders


@lru_cache(maxsize=8)
def _after_mask(n: int, per_link: int = 1) -> np.ndarray:
    """(n links x per_link points, 2n angles): angle k (alpha_k or theta_k) moves link
    j's points iff k <= j (read-only)."""
    joint_of = np.r_[0:n, 0:n]
    mask = (joint_of[None, :] <= np.arange(n)[:, None]).astype(float)
    mask = np.repeat(mask, per_link, axis=0)
    mask.setflags(write=False)
    return mask


def angle_margin(model: RobotModel, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Smallest joint-limit margin (rad) of each configuration, shape (...,).

    >>> from hrm_ctrl.model import default_robot
    >>> a = np.zeros(12); a[4] = np.radians(50.0)
    >>> round(float(np.degrees(angle_margin(default_robot(), a, np.zeros(12)))), 9)
    10.0
    """
    ma = model.limit_alpha - np.abs(alpha)
    mt = model.limit_theta - np.abs(theta)
    return np.minimum(ma.min(axis=-1), mt.min(axis=-1))


def project_tip(
    model: RobotModel,
    q: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    tol: float = 1e-7,
    iterations: int = 12,
    centres: np.ndarray | None = None,
) -> np.ndarray:
    """Gauss-Newton steps of least norm that bring the tip onto ``target``, the angles
    kept within [lo, hi] (a clipped angle is frozen for the next step).  With
    ``centres`` (13, 3) the joint centres of the returned angles are written there (those
    of the last evaluation where it stopped within ``tol``).

    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> X = np.array([2000.0, 20.0, 60.0])
    >>> O = np.empty((13, 3))
    >>> q = project_tip(m, np.zeros(24), X, -np.ones(24), np.ones(24), centres=O)
    >>> tip = joint_axes(m, q)[0][-1]
    >>> float(np.linalg.norm(tip - X)) < 1e-6, bool((O[-1] == tip).all())
    (True, True)
    """
    q = np.minimum(np.maximum(q, lo), hi)
    free: np.ndarray | None = None  # None: every angle free (no indexing)
    for _ in range(iterations):
        O, W, C = joint_axes(model, q)
        e = target - O[-1]
        if math.sqrt(e @ e) < tol or (free is not None and not free.any()):
            if centres is not None:
                centres[:] = O
            return q
        J = cross3(W, O[-1] - C).T
        if free is not None:
            J = J[:, free]
        JJ = J @ J.T
        JJ.flat[::4] += 1e-12 * float(JJ.trace()) + 1e-12
        if free is None:
            moved = q + J.T @ solve3(JJ, e)
        else:
            moved = q.copy()
            moved[free] += J.T @ solve3(JJ, e)
        new = np.minimum(np.maximum(moved, lo), hi)
        clipped = new != moved
        if clipped.any():
            free = ~clipped if free is None else free & ~clipped
        q = new
    if centres is not None:
        centres[:] = joint_axes(model, q)[0]
    return q


class _StepObjective:
    """Clearances, margins and the tip of one configuration, with Jacobians."""

    def __init__(
        self,
        model: RobotModel,
        environment: FreeSpace | None,
        radius: np.ndarray,
        t: np.ndarray,
        opt: RefineOptions,
        split: dict[str, float],
    ) -> None:
        self.model, self.env, self.radius, self.t = model, environment, radius, t
        self.cap = opt.clearance_cap_mm
        self.split = split
        self.evaluations = 0
        self.last: tuple[np.ndarray, np.ndarray | None] | None = None  # refine_step's end
        n = model.n_joints
        self.lim = np.r_[np.full(n, model.limit_alpha), np.full(n, model.limit_theta)]

    def evaluate(
        self, q: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(tip, Jtip (3, 24), clearances (M,), their Jacobian (M, 24)); the last two
        None without an environment.

        The clearances are those of :func:`zoomed_link_minima`: ``samples_per_link``
        points of every link and its lowest point near the lowest sample.
        The Jacobian of a clearance at point p with gradient g is, for an angle k before
        p, ``g . (w_k x (p - C_k)) = w_k . ((p - C_k) x g)``.
        """
        t0 = time.perf_counter()
        self.evaluations += 1
        n = self.model.n_joints
        O, W, C = joint_axes(self.model, q)
        WC = cross3(W, C)
        Jtip = (cross3(W, O[-1]) - WC).T
        t1 = time.perf_counter()
        self.split["kinematics_and_jacobians"] += t1 - t0
        if self.env is None:
            return O[-1], Jtip, None, None
        P, d, g = zoomed_link_minima(self.env, O[None], self.t)
        P, d, g = P[0], d[0], g[0]
        t2 = time.perf_counter()
        self.split["environment"] += t2 - t1
        c = d - self.radius[:, None]
        near = c < self.cap  # free space (inf) and far material earn nothing
        c = np.where(near, c, self.cap)
        g = np.where(near[..., None], g, 0.0)
        Pf, gf = P.reshape(-1, 3), g.reshape(-1, 3)
        Jc = cross3(Pf, gf) @ W.T - gf @ WC.T  # (M, 24)
        Jc *= _after_mask(n, P.shape[1])
        self.split["kinematics_and_jacobians"] += time.perf_counter() - t2
        return O[-1], Jtip, c.reshape(-1), Jc

    def clearances(self, q: np.ndarray) -> np.ndarray | None:
        """The clearances of q: those :func:`refine_step` ended with when q is (to
        2e-5 rad, 0.04 mm at 2 m) where it ended, before the projection; else evaluated."""
        if self.last is not None and np.abs(self.last[0] - q).max() < 2e-5:
            return self.last[1]
        return self.evaluate(q)[2]

    def score(self, c: np.ndarray | None, q: np.ndarray, mu: float, m_goal: float) -> float:
        """phi = worst clearance (capped) + mu * min(margin, goal)."""
        m = float((self.lim - np.abs(q)).min())
        return (float(c.min()) if c is not None else 0.0) + mu * min(m, m_goal)


StepObjective = _StepObjective  # the online planner's one step (hrm_ctrl/drive/online.py)


def zoomed_link_minima(
    environment: FreeSpace, O: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, L, S + 1, 3) of every link of ``O`` (N, L + 1, 3) where the free
    distance is measured, the distances (N, L, S + 1) and their gradients: the S
    samples at the evenly spaced fractions ``t`` and, last, the lowest of the lowest
    sample and four more points at a quarter and a half sample spacing either side of it
    (a link crossing a wall's opening has a sharp minimum between samples).

    One call of the environment for any N: every link on the grid of quarter sample
    spacings (4 (S - 1) + 1 points), the samples every fourth point of it (an environment
    call costs more than the points it is asked for).

    >>> from hrm_ctrl.planning.environment import Box, Environment
    >>> env = Environment((Box(np.array([0.0, 10, 0]), np.array([4.0, 4, 4])),))
    >>> O = np.array([[[-40.0, 0, 0], [40.0, 0, 0]]])
    >>> P, d, g = zoomed_link_minima(env, O, np.linspace(0, 1, 5))
    >>> P[0, 0, -1].tolist(), float(d[0, 0, -1])          # the point nearest the box
    ([0.0, 0.0, 0.0], 8.0)
    """
    N, L, S = O.shape[0], O.shape[1] - 1, len(t)
    F, M = 4 * (S - 1) + 1, O.shape[0] * (O.shape[1] - 1)
    tf = _fine_fractions(float(t[0]), float(t[-1]), F)  # tf[4 k] = t[k]
    base, D = O[:, :-1], O[:, 1:] - O[:, :-1]
    Pf = tf[None, None, :, None] * D[:, :, None, :]
    Pf += base[:, :, None, :]
    df, gf = environment.free_distance_and_gradient(Pf)
    # every link of every configuration a row (M = N L) of the fine grid
    Pf = Pf.reshape(M, F, 3)
    df = np.asarray(df, dtype=float).reshape(M, F)
    gf = np.asarray(gf, dtype=float).reshape(M, F, 3)
    rows = np.arange(M)
    k = 4 * np.argmin(df[:, ::4], axis=1)  # (M,): the lowest sample on the fine grid
    zi = k[:, None] + _ZOOM  # (M, 4)
    np.minimum(np.maximum(zi, 0, out=zi), F - 1, out=zi)
    j = zi[rows, np.argmin(df[rows[:, None], zi], axis=1)]
    # the lowest of the four points and of the lowest sample (the first on a tie, the
    # lowest sample last)
    best = np.where(df[rows, j] <= df[rows, k], j, k)
    P = np.concatenate((Pf[:, ::4], Pf[rows, best][:, None]), axis=1)
    d = np.concatenate((df[:, ::4], df[rows, best][:, None]), axis=1)
    g = np.concatenate((gf[:, ::4], gf[rows, best][:, None]), axis=1)
    return P.reshape(N, L, S + 1, 3), d.reshape(N, L, S + 1), g.reshape(N, L, S + 1, 3)


@lru_cache(maxsize=8)
def _fine_fractions(t0: float, t1: float, F: int) -> np.ndarray:
    """:func:`zoomed_link_minima`'s grid: ``F`` evenly spaced fractions (read-only)."""
    tf = np.linspace(t0, t1, F)
    tf.setflags(write=False)
    return tf


_ZOOM = np.array([-2, -1, 1, 2])  # zoomed_link_minima's points about the lowest sample


def refine_step(
    f: _StepObjective,
    q0: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    opt: RefineOptions,
) -> tuple[np.ndarray, int]:
    """Damped Gauss-Newton ascent of phi for one step, the tip held on ``target``.

    Each iteration linearises the clearances within ``band_mm`` of the worst one
    (pushing them to worst + band) and the margins below the goal (pushing them to
    the goal, weighted by mu), solves the least-squares step subject to
    ``Jtip dq = X - tip`` (a KKT system of 24 + 3), clips it to [lo, hi], and
    keeps it only if phi grows (else the damping grows, Levenberg-Marquardt).
    """
    mu = opt.margin_weight_mm_per_deg * 180.0 / math.pi
    m_goal = math.radians(opt.margin_goal_deg)
    q = np.clip(q0, lo, hi)
    tip, Jtip, c, Jc = f.evaluate(q)
    phi = f.score(c, q, mu, m_goal)
    lam = opt.damping
    it = 0
    while it < opt.max_iterations:
        it += 1
        normal = linearised_objective(f, q, c, Jc, opt)
        if normal is None:
            break
        H, g = normal
        e = target - tip
        improved = False
        for _ in range(opt.trials if it <= opt.patient_iterations else 1):
            q_new = kkt_step(H, g, Jtip, e, lam, q, lo, hi)
            tip_n, Jtip_n, c_n, Jc_n = f.evaluate(q_new)
            phi_n = f.score(c_n, q_new, mu, m_goal)
            if phi_n > phi + 1e-9:
                gain = phi_n - phi
                q, tip, Jtip, c, Jc, phi = q_new, tip_n, Jtip_n, c_n, Jc_n, phi_n
                lam = max(lam * 0.3, 1e-3)
                improved = True
                break
            lam *= 10.0
        if not improved or gain < opt.tolerance_mm:
            break
    f.last = (q.copy(), c)
    return q, it


def linearised_objective(
    f: _StepObjective,
    q: np.ndarray,
    c: np.ndarray | None,
    Jc: np.ndarray | None,
    opt: RefineOptions,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The normal equations ``(A^T A, A^T b)`` of one Gauss-Newton iteration of
    :func:`refine_step` at ``q``: the clearances within ``band_mm`` of the worst pushed to
    worst + band (and, with ``centring_weight``, the next lowest gently to ``comfort_mm``),
    the margins below the goal pushed to the goal, weighted by mu; None when nothing is
    to be gained."""
    mu = opt.margin_weight_mm_per_deg * 180.0 / math.pi
    m_goal = math.radians(opt.margin_goal_deg)
    nq = len(q)
    rows: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    if c is not None and Jc is not None:
        tau = min(float(c.min()) + opt.band_mm, f.cap)
        act = c < tau
        rows.append(Jc[act])
        rhs.append(tau - c[act])
        if opt.centring_weight > 0.0:  # the next lowest, gently: room for later steps
            comfort = min(float(c.min()) + opt.comfort_mm, f.cap)
            rest = ~act & (c < comfort)
            rows.append(opt.centring_weight * Jc[rest])
            rhs.append(opt.centring_weight * (comfort - c[rest]))
    m = f.lim - np.abs(q)
    low = m < m_goal + 1e-3
    if low.any():
        s = np.sign(q[low])
        R = np.zeros((int(low.sum()), nq))
        R[np.arange(len(s)), np.flatnonzero(low)] = -s * mu
        rows.append(R)
        rhs.append(mu * (m_goal + 1e-3 - m[low]))
    if not rows:
        return None
    A = np.vstack(rows)
    b = np.concatenate(rhs)
    return A.T @ A, A.T @ b


def kkt_step(
    H: np.ndarray,
    g: np.ndarray,
    Jtip: np.ndarray,
    e: np.ndarray,
    lam: float,
    q: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
) -> np.ndarray:
    """The damped least-squares step of :func:`linearised_objective`'s problem subject to
    ``Jtip dq = e`` (the tip onto its target, a KKT system of 24 + 3), clipped to
    [lo, hi]."""
    nq = len(q)
    K = np.zeros((nq + 3, nq + 3))
    K[:nq, :nq] = H
    K.flat[: nq * (nq + 4) : nq + 4] += lam  # H + lam I
    K[:nq, nq:] = Jtip.T
    K[nq:, :nq] = Jtip
    sol = np.linalg.solve(K, np.concatenate((g, e)))
    return np.minimum(np.maximum(q + sol[:nq], lo), hi)


def refine_angles(
    model: RobotModel,
    alpha: np.ndarray,
    theta: np.ndarray,
    targets: np.ndarray,
    environment: FreeSpace | None,
    clearance_of: Any = None,
    options: RefineOptions | None = None,
    travel: np.ndarray | None = None,
    progress: Callable[[float], None] | None = None,
    start_only_from: int | None = None,
) -> Refinement:
    """Refine the configurations ``alpha, theta`` (N, 12), whose tips should lie on
    ``targets`` (N, 3), step by step in order (see the module docstring).

    With ``start_only_from`` the input of the steps from that one on is no plan (the
    paper's method could not reach them): each such step starts from the last refined
    step carried on at its last change, is never judged against its input, and its tip
    error is what the caller checks (the beyond-the-paper mode of the planner).

    With ``travel`` (N,) (mm) the bound on the change between steps is
    ``max_step_change_deg`` per ``reference_step_mm`` of travel; without, per step.

    ``clearance_of(O (N, 13, 3)) -> (N,)`` measures the worst link clearance of
    each step exactly, the judge of "never worse than the input" (compared capped at
    ``clearance_cap_mm``); by default the environment at ``samples_per_link`` points.
    Within a pass a step is judged by the estimate of :func:`zoomed_link_minima`; the
    whole pass is then judged exactly, and from the first step that is worse the
    steps are planned again with those steps judged exactly; a step that had to keep
    its input with a jump larger than ``max_step_change_deg`` is planned again with
    the ``pull_steps`` before it started from the input's angles (at most
    ``repair_passes`` passes in all).  A step still worse keeps its input.

    ``progress(fraction)`` (optional) is told the share of the steps of the current pass
    refined so far (a repair pass reports again from its first step).
    """
    opt = options or RefineOptions()
    opt.check()
    alpha = np.asarray(alpha, dtype=float)
    theta = np.asarray(theta, dtype=float)
    targets = np.asarray(targets, dtype=float)
    N, n = alpha.shape
    if theta.shape != alpha.shape or targets.shape != (N, 3):
        raise PlanningError(
            f"refinement needs alpha, theta (N, {n}) and targets (N, 3), got "
            f"{alpha.shape}, {theta.shape}, {targets.shape}"
        )
    split = {"kinematics_and_jacobians": 0.0, "environment": 0.0, "solver": 0.0, "checks": 0.0}
    t_all = time.perf_counter()
    radius = 0.5 * np.asarray(model.outer_diameter, dtype=float)
    t = np.linspace(0.0, 1.0, opt.samples_per_link)
    if clearance_of is None:
        clearance_of = _sampled_clearance(model, environment, radius, t)
    cap = opt.clearance_cap_mm
    Q_in = np.hstack((alpha, theta))
    O_in = _centres(model, Q_in)
    c_paper = np.asarray(clearance_of(O_in), dtype=float)
    tip_in = np.linalg.norm(O_in[:, -1] - targets, axis=1)
    free_from = N if start_only_from is None else max(1, int(start_only_from))
    c_paper[free_from:] = -math.inf
    tip_in[free_from:] = math.inf
    f = _StepObjective(model, environment, radius, t, opt, split)
    c_in_est = np.full(N, math.inf)
    if environment is not None:
        d_in = zoomed_link_minima(environment, O_in, t)[1]
        c_in_est = np.minimum(d_in - radius[None, :, None], cap).min(axis=(1, 2))
    c_in_est[free_from:] = -math.inf

    def judge(q: np.ndarray, i: int) -> tuple[float, float]:
        """(exact worst clearance of q, of the input) at step i, both capped."""
        c = float(clearance_of(_centres(model, q[None]))[0])
        return min(c, cap), min(float(c_paper[i]), cap)

    Q_out = np.empty_like(Q_in)
    iters = np.zeros(N, dtype=np.int64)
    kept: set[int] = set()
    exact: set[int] = set()
    pull: set[int] = set()
    split["checks"] += time.perf_counter() - t_all
    start, passes = 0, 0
    solve_s = 0.0
    per_step = np.ones(N)
    if travel is not None:
        travel = np.asarray(travel, dtype=float)
        if travel.shape != (N,) or not np.all(np.isfinite(travel)):
            raise PlanningError(
                f"refinement needs a finite travel (N,) = ({N},), got {travel.shape}"
            )
        per_step[1:] = np.abs(np.diff(travel)) / opt.reference_step_mm
    bound = np.radians(opt.max_step_change_deg - opt.step_change_slack_deg) * per_step
    d_max = np.radians(opt.max_step_change_deg) * per_step
    while True:
        t0 = time.perf_counter()
        jumps: list[int] = []
        for i in range(start, N):
            if i >= free_from:  # no input: carry the last steps on (a direct fit)
                Q_in[i] = Q_in[i - 1] + (Q_out[i - 1] - Q_out[i - 2] if i >= 2 else 0.0)
            q, k, keep = _refine_one(
                f, Q_in, Q_out, targets, i, bound[i], c_in_est[i], judge, i in exact, i in pull, opt
            )
            Q_out[i] = q
            if progress is not None:
                progress((i + 1) / N)
            iters[i] += k
            (kept.add if keep else kept.discard)(i)
            if keep and i > 0 and np.abs(q - Q_out[i - 1]).max() > d_max[i]:
                jumps.append(i)
        t1 = time.perf_counter()
        solve_s += t1 - t0
        c_out = np.asarray(clearance_of(_centres(model, Q_out)), dtype=float)
        worse = np.flatnonzero(np.minimum(c_out, cap) < np.minimum(c_paper, cap))
        split["checks"] += time.perf_counter() - t1
        if (len(worse) == 0 and not jumps) or passes >= opt.repair_passes:
            break
        first = min([*map(int, worse), *jumps])
        exact |= {int(i) for i in worse}
        if jumps and first == jumps[0]:  # approach the input's path in time to keep it
            pull |= set(range(max(0, first - opt.pull_steps), first + 1))
            first = max(0, first - opt.pull_steps)
        start, passes = first, passes + 1
    t_check = time.perf_counter()
    O_out = _centres(model, Q_out)
    tip_err = np.linalg.norm(O_out[:, -1] - targets, axis=1)
    tol = opt.tip_tolerance_mm
    for i in range(N):  # the last word: never worse than the input
        bad = min(c_out[i], cap) < min(c_paper[i], cap) or tip_err[i] > max(tol, tip_in[i])
        if bad or not np.isfinite(Q_out[i]).all():
            kept.add(i)
            Q_out[i] = Q_in[i]
            c_out[i], tip_err[i] = c_paper[i], tip_in[i]
    m_out = angle_margin(model, Q_out[:, :n], Q_out[:, n:])
    t_end = time.perf_counter()
    split["checks"] += t_end - t_check
    split["solver"] = solve_s - split["kinematics_and_jacobians"] - split["environment"]
    return Refinement(
        alpha=Q_out[:, :n].copy(),
        theta=Q_out[:, n:].copy(),
        clearance_mm=c_out,
        paper_clearance_mm=c_paper,
        margin_deg=np.degrees(m_out),
        tip_error_mm=tip_err,
        kept_input=tuple(sorted(kept)),
        iterations=iters,
        repair_passes=passes,
        evaluations=f.evaluations,
        time_s=t_end - t_all,
        time_split_s=split,
    )


def _refine_one(
    f: _StepObjective,
    Q_in: np.ndarray,
    Q_out: np.ndarray,
    targets: np.ndarray,
    i: int,
    bound: float,
    c_in_est: float,
    judge: Any,
    exact: bool,
    pull: bool,
    opt: RefineOptions,
) -> tuple[np.ndarray, int, bool]:
    """Step i: (angles, iterations, whether the input was kept).  With ``pull`` the
    step starts from the input's angles (clipped to the step's box) instead of the
    last step's moved by the input's change: the way back to the input's path."""
    model = f.model
    n = model.n_joints
    lim = np.r_[np.full(n, model.limit_alpha), np.full(n, model.limit_theta)]
    hard = lim - 1e-6
    if i == 0:
        d0 = math.radians(opt.first_step_change_deg)
        lo, hi = Q_in[0] - d0, Q_in[0] + d0
        guess = Q_in[0]
    else:
        lo, hi = Q_out[i - 1] - bound, Q_out[i - 1] + bound
        guess = Q_in[i] if pull else Q_out[i - 1] + (Q_in[i] - Q_in[i - 1])
    lo, hi = np.maximum(lo, -hard), np.minimum(hi, hard)
    guess = project_tip(model, guess, targets[i], lo, hi)
    q, k = refine_step(f, guess, targets[i], lo, hi, opt)
    q = project_tip(model, q, targets[i], lo, hi)
    if f.env is None:
        return q, k, False
    q, extra, keep = _not_worse(f, q, i, Q_in[i], targets[i], lo, hi, c_in_est, judge, exact, opt)
    return q, k + extra, keep


def _not_worse(
    f: _StepObjective,
    q: np.ndarray,
    i: int,
    q_in: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    c_in_est: float,
    judge: Any,
    exact: bool,
    opt: RefineOptions,
) -> tuple[np.ndarray, int, bool]:
    """Step i's result, never worse (worst clearance, capped) than the input ``q_in``
    by the estimate, or with ``exact`` by ``judge``: a worse result is refined again
    from the input (within the step's box); if that is worse too, the input is
    returned (and the flag says so)."""
    if exact:
        c_q, c_in = judge(q, i)
    else:
        c_q, c_in = _worst(f.clearances(q)), c_in_est
    if c_q >= c_in:
        return q, 0, False
    q2, k2 = refine_step(f, project_tip(f.model, q_in, target, lo, hi), target, lo, hi, opt)
    q2 = project_tip(f.model, q2, target, lo, hi)
    c2 = judge(q2, i)[0] if exact else _worst(f.clearances(q2))
    if c2 >= c_in:
        return q2, k2, False
    return q_in.copy(), k2, True


def _worst(c: np.ndarray | None) -> float:
    return math.inf if c is None else float(c.min())


def _centres(model: RobotModel, Q: np.ndarray) -> np.ndarray:
    from hrm_ctrl.kinematics import joint_centres

    n = model.n_joints
    return joint_centres(model, Q[:, :n], Q[:, n:])


def _sampled_clearance(
    model: RobotModel, environment: FreeSpace | None, radius: np.ndarray, t: np.ndarray
) -> Any:
    def clearance_of(O: np.ndarray) -> np.ndarray:
        if environment is None:
            return np.full(len(O), math.inf)
        P = O[:, :-1, None, :] + t[None, None, :, None] * (O[:, 1:] - O[:, :-1])[:, :, None, :]
        d, _ = environment.free_distance_and_gradient(P)
        return (np.asarray(d) - radius[None, :, None]).min(axis=(1, 2))

    return clearance_of


def best_margin_at(
    model: RobotModel,
    q: np.ndarray,
    target: np.ndarray,
    environment: FreeSpace | None,
    options: RefineOptions | None = None,
    lo: np.ndarray | None = None,
    hi: np.ndarray | None = None,
) -> float:
    """The largest joint-limit margin (rad) a local search finds for one step: the
    tip on ``target``, the angles within [lo, hi] (by default the joint limits) and,
    with ``environment``, the clearance kept in the score as refinement keeps it.
    Started from ``q`` (24,); -inf if the tip cannot be kept on ``target``.  It says
    why a plan's margin is what it is (:func:`hrm_ctrl.planning.planner.margin_statement`).

    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> q = np.zeros(24); q[5] = np.radians(59.0)               # alpha_6 near its limit
    >>> X = joint_axes(m, q)[0][-1]
    >>> bool(np.degrees(best_margin_at(m, q, X, None)) > 20.0)  # the arm has room elsewhere
    True
    """
    opt = options or RefineOptions()
    deep = RefineOptions(
        max_step_change_deg=opt.max_step_change_deg,
        margin_goal_deg=60.0 - 1e-6,
        margin_weight_mm_per_deg=opt.margin_weight_mm_per_deg,
        clearance_cap_mm=opt.clearance_cap_mm,
        samples_per_link=opt.samples_per_link,
        band_mm=opt.band_mm,
        max_iterations=40,
        patient_iterations=40,
        trials=4,
    )
    n = model.n_joints
    hard = np.r_[np.full(n, model.limit_alpha), np.full(n, model.limit_theta)] - 1e-6
    lo = -hard if lo is None else np.maximum(lo, -hard)
    hi = hard if hi is None else np.minimum(hi, hard)
    split = {"kinematics_and_jacobians": 0.0, "environment": 0.0}
    radius = 0.5 * np.asarray(model.outer_diameter, dtype=float)
    t = np.linspace(0.0, 1.0, deep.samples_per_link)
    f = _StepObjective(model, environment, radius, t, deep, split)
    q0 = project_tip(model, q, target, lo, hi)
    best, _ = refine_step(f, q0, target, lo, hi, deep)
    best = project_tip(model, best, target, lo, hi)
    if float(np.linalg.norm(joint_axes(model, best)[0][-1] - target)) > opt.tip_tolerance_mm:
        return -math.inf
    return float(angle_margin(model, best[:n], best[n:]))
