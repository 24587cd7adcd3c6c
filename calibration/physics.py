"""Friction and mass calibration (``hrm calibrate physics``, issue 38): each joint's
kinetic friction coefficient and each link's mass from the tension board at held poses,
the drives' feedback and the calibrated rope layer.

**What is measured.**  The arm, out of its fixture, is driven through ``holds`` poses
(:func:`physics_poses`): each an arc curled a little up or down and sideways, every angle
jittered, two angles bent further (the links' levers under gravity change from pose to
pose).  Each is approached by a short last move (:func:`approach_step`: a step of
``APPROACH_RAD`` or half of it on every angle, signs chosen so that every rope travels at
least ``MIN_TRAVEL_MM`` into the hold), so every rope slides into it and its friction
acts in the direction of that travel: one way at one hold, at random the other way at
the next.  At each hold, after ``SETTLE_S``, the routine keeps the drives' actual
positions (read by SDO) and the tension board's mean over ``READ_S`` (its two halves
compared: an arm still moving is not used).

**The model** is the one the simulated box's statics and the host's feed-forward share
(``docs/sim.md``, "The arm's physics"): rope m, paid out ``u_m`` (the counts through the
calibrated rope layer: zeros and EA), under the drum tension ``T_m``, spans the free
length ``F_m(q) = u_m (1 + T_m fbar_m / EA_m)`` of the pose q (rope-geometric angles), and
the joints balance

    sum_m (T_m f_mj - T0) dF_m/dq_j = Q_g,j(q + offset; masses)        (24 equations)

with ``f_mj = exp(nu_m (sum_{i<j} mu_i (beta_p + beta_d)_mi + mu_j beta_p,mj))`` the
capstan factor of rope m across joint j (``nu_m``: +1 paid out and sliding, -1 wound in;
the host follows it along the commanded rows as the box does,
:func:`hrm_ctrl.ropes.feedforward.friction_mobilisation`) and ``Q_g`` the gravity forces,
linear in the masses.  Per hold:

1. **the shape** from the ropes themselves: the 24 angles whose free lengths best fit
   the 36 stretched lengths (Gauss-Newton from the commanded angles,
   :func:`shape_from_ropes`): the arm sags by a few hundredths of a radian per joint
   under its weight, and the pretension's moments make the balance sensitive to the pose
   its Jacobian is taken at;
2. **the balance**: linear in the 12 link masses for given friction coefficients, so the
   fit (:func:`fit_physics`) solves them by least squares inside a Gauss-Newton on the 12
   ``mu`` (variable projection), over every hold at once; each hold's 24 equations are
   whitened by the board's noise through the Jacobian (a rope pulls every joint it
   crosses: their errors are correlated, generalised least squares); then the shape is
   taken again with the fitted friction's stretch (``fbar``) and the fit made once more.

**The payload is given, not fitted.**  A link's mass at its middle has the moments of
half of it at each of its two joint centres, in every pose; so the arm's statics see only
``(m_{i-1} + m_i) / 2`` at each joint centre and ``m_12 / 2 + payload`` at the tip
(link 1's other half sits on the base joint, where it moves nothing): adding ``+d, -d,
..., -d`` to the 12 link masses and ``+d/2`` to the payload changes no gravity force
(``tests/calibration/test_physics.py`` shows it).  The payload (a camera head, weighed)
anchors the split: ``payload_kg``, by default the description's ``[physics]`` value.

**Needs**: the zero and stiffness calibrations (the rope lengths and their stretch come
from the calibrated zeros and EA), the kinematic one (links, joint offsets: gravity's
levers).  The static-to-kinetic ratio and the presliding travel (which set the friction's
state on a reversal) are the description's ``[physics]`` values, not fitted.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> plan = physics_poses(act, 3, np.random.default_rng(0))
>>> plan.alpha.shape, bool(np.abs(plan.alpha).max() < act.robot.limit_alpha)
((3, 12), True)
>>> d = np.concatenate([plan.alpha - plan.approach_alpha, plan.theta - plan.approach_theta], 1)
>>> sorted(set(np.round(np.abs(d) / APPROACH_RAD, 6).ravel().tolist()))   # each angle's step
[0.5, 1.0]
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calibration.collect import move_table
from calibration.zero import BoardClock, TensionGuard, TensionReader, read_tensions
from drivers.session import DriveSession
from drivers.sources import CountsSource
from hrm_ctrl.errors import CalibrationDataError
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.feedforward import (
    ArmPhysics,
    arm_physics,
    friction_mobilisation,
    gravity_forces,
    rope_holes,
    tension_factors,
    wrap_angles,
)
from hrm_ctrl.ropes.length import lengths_and_jacobian

N_JOINTS = 12
DEFAULT_HOLDS = 12
CURL_RAD = 0.06  # each pose's bend of every joint alike, at most: the arm curled
JITTER_RAD = 0.05  # and each angle's own, at most
BEND_RAD = 0.15  # and BENT_AXES angles of each pose bent this far
BENT_AXES = 2
APPROACH_RAD = 0.05  # the last move into a hold, every angle
MIN_TRAVEL_MM = 0.18  # each rope's travel into a hold, at least (it slides after 0.15 mm)
APPROACH_TRIES = 200
SETTLE_S = 0.35  # held before the board is read: the box's equilibrium settles
READ_S = 2.5  # the board read over this long per hold (50 fresh samples at 20 Hz)
RATE_FRACTION = 0.3  # of the motor limits, the moves between holds
MIN_FRAMES = 3  # a reading window with fewer frames is refused (a board that stalled)
SHAPE_ITERATIONS = 8
SHAPE_TOL_RAD = 1e-9
FIT_ITERATIONS = 30
FIT_TOL = 1e-9  # relative change of mu that ends the Gauss-Newton
MU_BOUNDS = (0.0, 2.0)
TAUT_N = 5.0  # a hold with a rope below this is not used: a slack rope's length says nothing
MAX_TENSION_N = 100.0  # nor one above this
SETTLED_N = 0.3  # nor one whose tensions still changed by this over the hold
MIN_HOLDS = 8


@dataclass(frozen=True, eq=False)
class PosePlan:
    """The held poses (true angles, (K, 12) each) in the order they are visited, and the
    approach to each (the same shapes): the arm goes to the approach, then to the hold."""

    alpha: np.ndarray
    theta: np.ndarray
    approach_alpha: np.ndarray
    approach_theta: np.ndarray


def approach_step(
    actuation: Actuation,
    alpha: np.ndarray,
    theta: np.ndarray,
    rng: np.random.Generator,
    *,
    step_rad: float = APPROACH_RAD,
    min_travel_mm: float = MIN_TRAVEL_MM,
    tries: int = APPROACH_TRIES,
) -> tuple[np.ndarray, np.ndarray]:
    """A step ``(da, dt)`` (12,) each, every angle's ``step_rad`` or half of it either
    way, such that the move from ``q - step`` to the pose ``q`` makes every rope travel at least
    ``min_travel_mm`` (first order): each rope then slides into the hold, its friction's
    direction the direction of that travel (the best of ``tries`` draws)."""
    geo_a, geo_t = actuation.commanded_angles(alpha, theta)
    _L, J, _s = lengths_and_jacobian(actuation.geometry, geo_a[None], geo_t[None])
    Jt = J[0].T * step_rad  # (24, n): each angle's step's travel of every rope
    levels = np.array([-1.0, -0.5, 0.5, 1.0])  # each angle's step, times step_rad
    signs = rng.choice(levels, (tries, 2 * N_JOINTS))
    best = signs[int(np.argmax(np.abs(signs @ Jt).min(axis=1)))].copy()
    worst = float(np.abs(best @ Jt).min())
    for _ in range(4 * N_JOINTS):  # change the one step that raises the least travel most
        base = best @ Jt  # (n,)
        trial = np.abs(
            base[None, None, :] + (levels[None, :, None] - best[:, None, None]) * Jt[:, None, :]
        ).min(axis=2)  # (24, 4)
        i, v = np.unravel_index(int(np.argmax(trial)), trial.shape)
        if trial[i, v] <= worst:
            break
        best[i] = levels[v]
        worst = float(trial[i, v])
    if worst < min_travel_mm:
        raise CalibrationDataError(
            f"physics: no approach moves every rope {min_travel_mm:g} mm into a hold "
            f"(best {worst:.3g} mm)"
        )
    d = best * step_rad
    return d[0::2], d[1::2]


def physics_poses(
    actuation: Actuation,
    holds: int,
    rng: np.random.Generator,
    *,
    curl_rad: float = CURL_RAD,
    jitter_rad: float = JITTER_RAD,
    bend_rad: float = BEND_RAD,
    step_rad: float = APPROACH_RAD,
) -> PosePlan:
    """``holds`` held poses, each an arc: every alpha ``A + e`` and every theta ``B + e``,
    ``A`` and ``B`` uniform within ``curl_rad`` per pose, ``e`` uniform within
    ``jitter_rad`` per angle (the arm curled up and sideways: the links' levers under
    gravity vary over a wide range, which separates the masses), each approached from
    :func:`approach_step` (every rope slides into it, its friction one way or the
    other)."""
    if not (isinstance(holds, int) and 1 <= holds <= 500):
        raise CalibrationDataError(f"physics: holds must be 1..500, got {holds!r}")
    robot = actuation.robot
    la, lt = float(robot.limit_alpha), float(robot.limit_theta)
    curl = rng.uniform(-1.0, 1.0, (holds, 2)) * curl_rad
    a = curl[:, :1] + rng.uniform(-1.0, 1.0, (holds, N_JOINTS)) * jitter_rad
    t = curl[:, 1:] + rng.uniform(-1.0, 1.0, (holds, N_JOINTS)) * jitter_rad
    for k in range(holds):  # a few joints bent far: their links' levers change
        bent = rng.choice(2 * N_JOINTS, BENT_AXES, replace=False)
        angle = rng.choice([-1.0, 1.0], BENT_AXES) * bend_rad
        for axis, v in zip(bent.tolist(), angle.tolist(), strict=True):
            (a if axis % 2 == 0 else t)[k, axis // 2] = v
    np.clip(a, -0.9 * la, 0.9 * la, out=a)
    np.clip(t, -0.9 * lt, 0.9 * lt, out=t)
    da = np.empty_like(a)
    dt = np.empty_like(t)
    for k in range(holds):
        for scale in (1.0, 1.5, 2.0):  # a longer approach where the ropes travel less
            try:
                da[k], dt[k] = approach_step(actuation, a[k], t[k], rng, step_rad=scale * step_rad)
                break
            except CalibrationDataError:
                if scale == 2.0:
                    raise
    return PosePlan(a, t, a - da, t - dt)


@dataclass(frozen=True, eq=False)
class PhysicsData:
    """What the routine keeps of each hold (rows: holds, the rope layer's order): the
    commanded true angles (k, 12) each, the drives' actual counts (k, n), the mean
    tensions (k, n) N, how much they changed from the first half of the hold's frames to
    the second (k, n) N (an arm still moving) and the friction's mobilisation (k, n) as
    the drives' travel up to the hold says."""

    alpha: np.ndarray
    theta: np.ndarray
    counts: np.ndarray
    tension_N: np.ndarray
    settling_N: np.ndarray
    nu: np.ndarray

    def usable(self) -> np.ndarray:
        """The holds (k,) bool the fit takes: every rope taut and within the band the
        model holds in (:data:`TAUT_N` .. :data:`MAX_TENSION_N`), the arm at rest (no rope
        changed by more than :data:`SETTLED_N` over the hold)."""
        T = np.asarray(self.tension_N)
        return (
            (T.min(axis=1) >= TAUT_N)
            & (T.max(axis=1) <= MAX_TENSION_N)
            & (np.abs(np.asarray(self.settling_N)).max(axis=1) <= SETTLED_N)
        )

    def take(self, rows: np.ndarray) -> PhysicsData:
        return PhysicsData(*(np.asarray(v)[rows] for v in dataclasses.astuple(self)))

    def __post_init__(self) -> None:
        k, n = np.shape(self.counts)
        shapes = {np.shape(v) for v in (self.tension_N, self.settling_N, self.nu)}
        if shapes != {(k, n)} or k < 1:
            raise CalibrationDataError(
                f"physics data: counts {np.shape(self.counts)}, tensions "
                f"{np.shape(self.tension_N)} and mobilisation {np.shape(self.nu)} differ"
            )


def shape_from_ropes(
    actuation: Actuation,
    counts: np.ndarray,
    tension_N: np.ndarray,
    mean_factor: np.ndarray,
    alpha0: np.ndarray,
    theta0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The rope-geometric angles (12,) each whose free lengths best fit the ropes'
    stretched lengths ``u (1 + T fbar / EA)`` (least squares, Gauss-Newton from the
    rope-geometric ``alpha0``, ``theta0``), and the fit's rms (mm).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> a, t = np.full(12, 0.1), np.full(12, -0.05)
    >>> T = np.full(36, 35.0)
    >>> c = act.counts_from_angles(a, t, T)
    >>> a1, t1, rms = shape_from_ropes(act, c, T, np.ones(36), a * 0, t * 0)
    >>> bool(np.abs(a1 - a).max() < 1e-4 and np.abs(t1 - t).max() < 1e-4), rms < 1e-3
    (True, True)
    """
    u = actuation.unstretched_from_counts(np.asarray(counts, dtype=np.int64))
    EA = actuation.routing.stiffness_EA_N
    target = u * (1.0 + tension_N * mean_factor / EA) - actuation.routing.box_length
    q = np.empty(2 * N_JOINTS)
    q[0::2], q[1::2] = alpha0, theta0
    r = np.zeros_like(target)
    for _ in range(SHAPE_ITERATIONS):
        L, J, _s = lengths_and_jacobian(actuation.geometry, q[None, 0::2], q[None, 1::2])
        r = L[0] - target
        dq = np.linalg.lstsq(J[0], -r, rcond=None)[0]
        q += dq
        if np.abs(dq).max() < SHAPE_TOL_RAD:
            break
    L, _J, _s = lengths_and_jacobian(actuation.geometry, q[None, 0::2], q[None, 1::2])
    rms = float(np.sqrt(np.mean((L[0] - target) ** 2)))
    return q[0::2].copy(), q[1::2].copy(), rms


def gravity_basis(
    actuation: Actuation, alpha: np.ndarray, theta: np.ndarray, physics: ArmPhysics
) -> np.ndarray:
    """The gravity forces (k, 24, 13) N mm per kg of each link's mass and of the payload
    (last column), at true angles (k, 12) each: ``Q_g = basis @ (masses, payload)``."""
    k = alpha.shape[0]
    out = np.empty((k, 2 * N_JOINTS, N_JOINTS + 1))
    for i in range(N_JOINTS + 1):
        m = np.zeros(N_JOINTS)
        if i < N_JOINTS:
            m[i] = 1.0
        one = dataclasses.replace(physics, link_mass_kg=m, payload_kg=1.0 if i == N_JOINTS else 0.0)
        out[:, :, i] = gravity_forces(actuation.robot, alpha, theta, one)
    return out


@dataclass(frozen=True, eq=False)
class PhysicsFit:
    """The fitted link masses (12,) kg, payload kg and kinetic friction coefficients
    (12,), each with its standard deviation from the residuals; the balance's rms
    residual (N mm) before (the description's values) and after, the rope-shape fit's
    largest rms (mm), the number of holds used and of those dropped
    (:meth:`PhysicsData.usable`)."""

    link_mass_kg: np.ndarray
    payload_kg: float
    mu_kinetic: np.ndarray
    std_mass_kg: np.ndarray  # (12,)
    std_mu: np.ndarray
    rms_before_Nmm: float
    rms_after_Nmm: float
    shape_rms_mm: float
    n_holds: int
    n_dropped: int = 0

    def residuals(self) -> dict[str, float]:
        """What a calibration keeps of the fit."""
        return {
            "n_holds": float(self.n_holds),
            "n_holds_dropped": float(self.n_dropped),
            "balance_rms_before_Nmm": self.rms_before_Nmm,
            "balance_rms_after_Nmm": self.rms_after_Nmm,
            "shape_rms_mm": self.shape_rms_mm,
            "max_std_mass_kg": float(self.std_mass_kg.max()),
            "max_std_mu": float(self.std_mu.max()),
        }


class _Balance:
    """The per-hold quantities the balance needs at fixed shapes (module docstring)."""

    def __init__(
        self,
        actuation: Actuation,
        alpha: np.ndarray,
        theta: np.ndarray,
        data: PhysicsData,
        physics: ArmPhysics,
        payload_kg: float,
    ) -> None:
        act = actuation
        self.payload_kg = payload_kg
        self.act = act
        self.T = data.tension_N
        self.nu = data.nu
        self.T0 = float(act.routing.pretension_N)
        _L, J, _s = lengths_and_jacobian(act.geometry, alpha, theta)
        self.J = J  # (k, n, 24)
        self.holes = rope_holes(act.routing, act.robot.links)
        self.wraps = wrap_angles(self.holes, alpha, theta)
        ta, tt = alpha + act.alpha_offset_rad, theta + act.theta_offset_rad
        self.G = gravity_basis(act, ta, tt, physics)  # (k, 24, 13)
        self.pre = self.T0 * J.sum(axis=1)  # (k, 24)
        # the equations' noise: the board's (independent per rope) through the Jacobian,
        # correlated from joint to joint (a rope pulls every joint it crosses): whitened
        # by the inverse Cholesky factor of J^T J per hold (generalised least squares)
        C = np.einsum("kni,knj->kij", J, J) + np.eye(2 * N_JOINTS)
        self.whiten = np.linalg.inv(np.linalg.cholesky(C))  # (k, 24, 24) per mm

    def factors(self, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cross, mean = tension_factors(
            self.nu, mu, self.wraps, self.holes, self.act.routing.box_length
        )
        return cross, mean  # (k, 12, n), (k, n)

    def rope_moments(self, mu: np.ndarray) -> np.ndarray:
        """``sum_m T_m f_mj dF_m/dq_j - T0 sum_m dF_m/dq_j`` (k, 24)."""
        cross, _ = self.factors(mu)
        f = np.repeat(np.swapaxes(cross, -1, -2), 2, axis=-1)  # (k, n, 24)
        return np.einsum("kn,knj->kj", self.T, self.J * f) - self.pre

    def whitened(self, M: np.ndarray) -> np.ndarray:
        """``M`` (k, 24, c) with each hold's equations whitened."""
        return np.einsum("kij,kjc->kic", self.whiten, M)

    def solve(self, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The masses (13,) that best balance the ropes' moments for ``mu``, and the
        weighted residuals (k * 24,) (N per unit weight: about the board's noise)."""
        A = self.whitened(self.G[..., :N_JOINTS]).reshape(-1, N_JOINTS)
        b = self.rope_moments(mu) - self.G[..., N_JOINTS] * self.payload_kg
        b = np.einsum("kij,kj->ki", self.whiten, b).reshape(-1)
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        return np.append(x, self.payload_kg), b - A @ x


def fit_physics(
    actuation: Actuation,
    data: PhysicsData,
    *,
    physics: ArmPhysics | None = None,
    payload_kg: float | None = None,
) -> PhysicsFit:
    """The masses, payload and friction coefficients that best balance every hold of
    ``data`` (module docstring); ``actuation`` the calibrated rope layer, ``physics`` the
    description's ``[physics]`` (gravity's direction, the starting friction)."""
    act = actuation
    ph = arm_physics(act.robot) if physics is None else physics
    keep = data.usable()
    if int(keep.sum()) < MIN_HOLDS:
        raise CalibrationDataError(
            f"physics: {int(keep.sum())} of {len(keep)} holds usable (every rope "
            f"{TAUT_N:g}..{MAX_TENSION_N:g} N, settled within {SETTLED_N:g} N), at least "
            f"{MIN_HOLDS} needed"
        )
    all_holds = len(keep)
    data = data.take(np.flatnonzero(keep))
    counts = np.asarray(data.counts, dtype=np.int64)
    k = counts.shape[0]
    a0, t0 = act.commanded_angles(data.alpha, data.theta)  # rope-geometric: the start
    a0, t0 = np.array(a0, dtype=float), np.array(t0, dtype=float)
    payload = float(ph.payload_kg if payload_kg is None else payload_kg)
    mu = np.array(ph.mu_kinetic, dtype=float)
    x_desc = np.concatenate([ph.link_mass_kg, [ph.payload_kg]])
    shape_rms = 0.0
    rms_before = math.nan
    res = np.zeros(1)
    jac = np.zeros((1, 1))
    for outer in range(2):  # the shape with the friction's stretch, then the fit again
        bal0 = _Balance(act, a0, t0, data, ph, payload)
        _c, mean = bal0.factors(mu if outer else np.zeros(N_JOINTS))
        alpha = np.empty_like(a0)
        theta = np.empty_like(t0)
        shape_rms = 0.0
        for i in range(k):
            alpha[i], theta[i], rms = shape_from_ropes(
                act, counts[i], data.tension_N[i], mean[i], a0[i], t0[i]
            )
            shape_rms = max(shape_rms, rms)
        bal = _Balance(act, alpha, theta, data, ph, payload)
        if outer == 0:
            b = bal.rope_moments(ph.mu_kinetic) - bal.G @ x_desc
            rms_before = float(np.sqrt(np.mean(b**2)))
        for _it in range(FIT_ITERATIONS):
            x, res = bal.solve(mu)
            jac = np.empty((res.size, N_JOINTS))
            for j in range(N_JOINTS):
                h = 1e-6
                m2 = mu.copy()
                m2[j] += h
                jac[:, j] = (bal.solve(m2)[1] - res) / h
            step = np.linalg.lstsq(jac, -res, rcond=None)[0]
            mu = np.clip(mu + step, *MU_BOUNDS)
            if np.abs(step).max() < FIT_TOL * max(1.0, float(np.abs(mu).max())):
                break
        a0, t0 = alpha, theta
    x, res = bal.solve(mu)
    dof = max(1, res.size - 2 * N_JOINTS)
    sigma2 = float(res @ res) / dof
    A = bal.whitened(bal.G[..., :N_JOINTS]).reshape(-1, N_JOINTS)
    full = np.concatenate([A, -jac], axis=1)  # d residual / d (masses, mu)
    cov = sigma2 * np.linalg.pinv(full.T @ full)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return PhysicsFit(
        link_mass_kg=x[:N_JOINTS].copy(),
        payload_kg=float(x[N_JOINTS]),
        mu_kinetic=mu.copy(),
        std_mass_kg=std[:N_JOINTS],
        std_mu=std[N_JOINTS:],
        rms_before_Nmm=rms_before,
        rms_after_Nmm=float(np.sqrt(np.mean((bal.rope_moments(mu) - bal.G @ x) ** 2))),
        shape_rms_mm=shape_rms,
        n_holds=k,
        n_dropped=all_holds - k,
    )


def mobilisation_along(
    actuation: Actuation, rows: np.ndarray, physics: ArmPhysics | None = None
) -> np.ndarray:
    """The friction's mobilisation (rows, n) along commanded counts (rows, n), every
    control row of the routine's moves in order: the host's account of each rope's
    friction state (:func:`hrm_ctrl.ropes.feedforward.friction_mobilisation`)."""
    ph = arm_physics(actuation.robot) if physics is None else physics
    u = actuation.unstretched_from_counts(np.asarray(rows, dtype=np.int64))
    return friction_mobilisation(u, ph.presliding_mm, ph.static_ratio)


@dataclass(frozen=True, eq=False)
class PhysicsResult:
    """What :func:`calibrate_physics` measured and fitted: the plan, the data, the fit,
    and the routine's length on the host's monotonic clock (s)."""

    plan: PosePlan
    data: PhysicsData
    fit: PhysicsFit
    elapsed_s: float


def calibrate_physics(
    session: DriveSession,
    tension: TensionReader,
    actuation: Actuation,
    *,
    period_s: float,
    holds: int = DEFAULT_HOLDS,
    seed: int = 0,
    payload_kg: float | None = None,
    settle_s: float = SETTLE_S,
    read_s: float = READ_S,
    rate_fraction: float = RATE_FRACTION,
    progress: Callable[[str], None] | None = None,
) -> PhysicsResult:
    """Drive the arm (out of its fixture, the session brought up on the calibrated rope
    layer ``actuation``) through ``holds`` held poses (:func:`physics_poses` of ``seed``),
    each approached so that every rope slides into it; at each, after ``settle_s``, read
    the drives' actual positions and the tension board for ``read_s``; move back to where
    the arm started; fit (:func:`fit_physics`, the payload ``payload_kg``: the
    description's when None).  Its own tension guard runs throughout (a rope above the
    command band's top stops every axis: :class:`calibration.zero.TensionGuard`; the
    session runs without the feedback watches, whose tension watch would hold the board's
    port).  A safety stop raises what the session raises."""
    if session.actual is None:
        raise CalibrationDataError("physics: the session is not brought up (no actual counts)")
    t0 = time.monotonic()
    plan = physics_poses(actuation, holds, np.random.default_rng(seed))
    actuation.check_angles(plan.alpha, plan.theta)
    actuation.check_angles(plan.approach_alpha, plan.approach_theta)
    here = actuation.angles_from_counts(np.asarray(session.actual, dtype=np.int64))[:2]
    rows: list[np.ndarray] = []
    at_hold: list[int] = []
    counts = np.empty((holds, actuation.n_motors), dtype=np.int64)
    T = np.empty((holds, actuation.n_motors))
    settling = np.empty_like(T)
    clock = BoardClock()
    limits = np.full(actuation.n_motors, float(actuation.command_tension_N[1]))
    with TensionGuard(session, tension, limits):
        _drive(session, tension, actuation, plan, here, period_s, settle_s, read_s, clock,
               rate_fraction, rows, at_hold, counts, T, settling, progress)  # fmt: skip
    nu = mobilisation_along(actuation, np.array(rows))[at_hold]
    data = PhysicsData(plan.alpha, plan.theta, counts, T, settling, nu)
    fit = fit_physics(actuation, data, payload_kg=payload_kg)
    return PhysicsResult(plan, data, fit, time.monotonic() - t0)


def read_window(
    reader: TensionReader, motor_ids: tuple[str, ...], seconds: float, clock: BoardClock
) -> np.ndarray:
    """The mean tensions (n,) of the board's distinct frames measured within the next
    ``seconds`` (the board's own time stamps through ``clock``): however many frames a
    loaded host receives in that time (at least :data:`MIN_FRAMES`), each channel valid
    (:func:`calibration.zero.read_tensions` checks the first)."""
    first = read_tensions(reader, motor_ids, n_samples=1, clock=clock)
    start = time.monotonic()
    end = start + seconds
    rows = [first.tensions_N]
    last = None
    while time.monotonic() < end:
        s = reader.latest()
        if s.seq != last:
            last = s.seq
            if clock.measured_s(s) >= start:
                rows.append(np.asarray(s.tensions_N, dtype=float))
        time.sleep(0.002)
    t = np.stack(rows)
    if len(rows) < MIN_FRAMES or not np.isfinite(t).all():
        raise CalibrationDataError(
            f"tension sensor {reader.port}: {len(rows)} valid frames in {seconds:g} s "
            f"(at least {MIN_FRAMES})"
        )
    return t.mean(axis=0)


def _drive(
    session: DriveSession,
    tension: TensionReader,
    actuation: Actuation,
    plan: PosePlan,
    here: tuple[np.ndarray, np.ndarray],
    period_s: float,
    settle_s: float,
    read_s: float,
    clock: BoardClock,
    rate_fraction: float,
    rows: list[np.ndarray],
    at_hold: list[int],
    counts: np.ndarray,
    T: np.ndarray,
    settling: np.ndarray,
    progress: Callable[[str], None] | None,
) -> None:
    """The routine's moves and readings (:func:`calibrate_physics`), into the arrays."""
    start = here
    ids = actuation.motor_ids
    holds = len(plan.alpha)
    for k in range(holds):
        approach = (plan.approach_alpha[k], plan.approach_theta[k])
        target = (plan.alpha[k], plan.theta[k])
        first = move_table(actuation, here, approach, period_s, rate_fraction=rate_fraction)
        last = move_table(actuation, approach, target, period_s, rate_fraction=rate_fraction)
        table = np.concatenate([first, last[1:]])
        session.stream(
            CountsSource(
                actuation, table, period_s, name=f"physics calibration hold {k + 1}",
                hold_s=settle_s, info={"hold": k + 1, "of": holds},
            )
        )  # fmt: skip
        rows.extend(table)
        at_hold.append(len(rows) - 1)
        counts[k] = session.actual_positions()
        a = read_window(tension, ids, 0.5 * read_s, clock)
        b = read_window(tension, ids, 0.5 * read_s, clock)
        T[k] = 0.5 * (a + b)
        settling[k] = b - a
        here = target
        if progress is not None:
            progress(
                f"hold {k + 1}/{holds}: tensions {T[k].min():.1f} .. {T[k].max():.1f} N, "
                f"settling {np.abs(settling[k]).max():.2f} N"
            )
    back = move_table(actuation, here, start, period_s, rate_fraction=rate_fraction)
    session.stream(CountsSource(actuation, back, period_s, name="physics calibration: back"))


__all__ = [
    "PhysicsData",
    "PhysicsFit",
    "PhysicsResult",
    "PosePlan",
    "calibrate_physics",
    "fit_physics",
    "gravity_basis",
    "mobilisation_along",
    "physics_poses",
    "read_window",
    "shape_from_ropes",
]
