"""Feed-forward compensation: the rope lengths that hold each planned pose against its loads.

Without it the rope layer commands every rope at its pretension ``T0`` for the pose
(:meth:`Actuation.counts_from_angles`): a rope-driven arm held out then sags under its
weight, its ropes stretch more where they hold it up and lose tension where they bend
through the joints.  This module computes, from what a host knows (the robot
description's rope layer and its ``[physics]`` table: link masses, payload, gravity
direction, friction coefficients, joint play; the calibration's EA and zero offsets),
for every planned pose ``q`` (true angles):

* the generalised gravity forces ``Q_g(q)`` (24,) N mm of the link masses (each at its
  link's middle) and the tip payload (:func:`gravity_forces`);
* each rope's friction factors where it bends through the joints' holes (the capstan law,
  ``T_out = T_in e^(-mu beta)``, the sign from the direction the rope travels along the
  planned sequence, static above kinetic from rest and on a reversal:
  :func:`friction_mobilisation`, :func:`tension_factors`);
* the drum tensions ``T`` (n,) that hold the pose, the joints carrying the moments of the
  pretension itself (the design's balance: with the loads gone the arm stands where its
  ropes' lengths at ``T0`` put it).  With ``f_mj`` the factor of rope m across joint j and
  ``A = f J`` (J the rope layer's Jacobian ``dL/dq``) the equilibrium is

      A^T T = T0 J^T 1 + Q_g(q)                        (24 equations, n = 36 tensions)

  and of its solutions the one nearest the pretension (least squares; ropes that would
  leave the command band are held at its edge and the others take up the rest,
  :func:`holding_tensions`);
* the unstretched length that spans the pose's free length ``F(q)`` at that tension,
  ``u = F / (1 + T fbar / EA)`` (``fbar`` the length-weighted mean factor along the rope:
  its stretch), and so the counts;
* with joint play, the pose commanded so that the play, taken up on the side gravity
  pulls (or dragged along by the ropes' motion where gravity does not load an axis), puts
  the joint where it was planned.

It is the plan -> counts path's option (``plan_setpoints(..., feedforward=...)``, ``hrm
run --compensate``), off by default: with no load on the arm (the simulated box without
physics) it bends the arm by what it would hold up.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> ff = Feedforward.of(load_actuation(default_robot()))
>>> ff.physics.payload_kg, round(float(ff.physics.link_mass_kg.sum()), 3)
(0.02, 0.24)
>>> z = np.zeros((1, 12))
>>> h = ff.holding(z, z)
>>> c = np.cumsum(ff.actuation.robot.links) - ff.actuation.robot.links / 2   # link middles
>>> hand = 9.81 * (0.02 * c.sum() + 0.02 * 2007.0)     # alpha_1 of the level arm, by hand
>>> round(float(h.gravity_Nmm[0, 0]), 1), round(-float(hand), 1)
(-2879.7, -2879.7)
>>> bool(h.tension_N.min() > 10.0 and h.tension_N.max() < 120.0)
True
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError
from hrm_ctrl.kinematics import R_BASE_PAPER, frames, joint_rotation
from hrm_ctrl.model import RobotModel
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.length import lengths_and_jacobian
from hrm_ctrl.ropes.routing import RopeRouting

G_M_PER_S2 = 9.81
# The [physics] table's defaults: the design's estimates for an arm of this size (2007 mm,
# 30 mm across, 1 mm steel ropes through PTFE-lined holes; sources in docs/sim.md,
# "Defaults"), the values the simulated box's physics has by default.
DEFAULT_PHYSICS: dict[str, Any] = {
    "link_mass_kg": 0.020,
    "payload_kg": 0.020,
    "gravity_dir": [0.0, 0.0, -1.0],  # in the plan's frame: the arm along +x0 held level
    "mu_kinetic": 0.10,
    "static_ratio": 1.5,
    "presliding_mm": 0.05,
    "backlash_deg": 0.2,
    "backlash_torque_Nmm": 2.0,
}
TRAVEL_AT_REST_MM = 1e-6  # a rope moved less than this between two rows is at rest
BLOCK_ROWS = 2048  # rows evaluated at once (the Jacobians of a block: 14 MB)
# N per N mm: the equilibrium's misfit weighed against the tensions' distance from the
# pretension where the band binds (a misfit of 0.001 N mm costs what 1 N does)
EQUILIBRIUM_WEIGHT = 1e3


class FeedforwardError(RopeError):
    """The ``[physics]`` table is malformed, or no rope tensions within the command band
    hold a planned pose."""


@dataclass(frozen=True, eq=False)
class ArmPhysics:
    """The arm's physical constants as the host knows them (kg, N, mm, rad; read-only):
    link masses (12,), payload at the end point, gravity's unit direction (3,) in the
    plan's frame and its magnitude, kinetic friction coefficient per joint (12,), the
    static one's ratio to it, the rope travel that mobilises the friction from rest, the
    total play of each joint axis (12,) and the gravity moment that takes it up."""

    link_mass_kg: np.ndarray
    payload_kg: float
    gravity_dir: np.ndarray
    g_m_per_s2: float
    mu_kinetic: np.ndarray
    static_ratio: float
    presliding_mm: float
    backlash_rad: np.ndarray
    backlash_torque_Nmm: float

    @property
    def gravity_N_per_kg(self) -> np.ndarray:
        return self.gravity_dir * self.g_m_per_s2


def arm_physics(robot: RobotModel) -> ArmPhysics:
    """The ``[physics]`` table of ``robot`` (every key optional, :data:`DEFAULT_PHYSICS`):
    ``link_mass_kg`` (a number or 12), ``payload_kg``, ``gravity_dir`` (3 numbers, the
    plan's frame), ``mu_kinetic`` (a number or 12), ``static_ratio`` (>= 1),
    ``presliding_mm`` (> 0), ``backlash_deg`` (a number or 12), ``backlash_torque_Nmm``.
    A bad value is one :class:`FeedforwardError` line naming the key.

    >>> from hrm_ctrl.model import default_robot
    >>> import dataclasses
    >>> m = default_robot()
    >>> arm_physics(m).mu_kinetic[:2].tolist()
    [0.1, 0.1]
    >>> bad = dataclasses.replace(m, tables={**m.tables, "physics": {"payload_kg": -1}})
    >>> arm_physics(bad)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hrm_ctrl.ropes.feedforward.FeedforwardError: <...>: [physics]: payload_kg must be ... got -1
    """
    where = f"{robot.source}: [physics]"
    raw = robot.tables.get("physics", {})
    if not isinstance(raw, Mapping):
        raise FeedforwardError(f"{where} must be a table")
    unknown = sorted(set(raw) - set(DEFAULT_PHYSICS))
    if unknown:
        raise FeedforwardError(f"{where}: unknown key {unknown[0]!r}")
    doc = {**DEFAULT_PHYSICS, **raw}
    n = robot.n_joints

    def values(key: str, shape: tuple[int, ...], low: float, high: float) -> np.ndarray:
        v = doc[key]
        try:
            a = np.array(np.broadcast_to(np.asarray(v, dtype=float), shape))
        except (TypeError, ValueError):
            raise FeedforwardError(
                f"{where}: {key} must be a number or {shape[0]} numbers, got {v!r}"
            ) from None
        if isinstance(v, bool) or not (np.isfinite(a).all() and (a >= low).all()):
            raise FeedforwardError(f"{where}: {key} must be a number >= {low:g}, got {v!r}")
        if not (a <= high).all():
            raise FeedforwardError(f"{where}: {key} must be at most {high:g}, got {v!r}")
        a.setflags(write=False)
        return a

    g = values("gravity_dir", (3,), -1e3, 1e3)
    norm = float(np.linalg.norm(g))
    if norm == 0.0:
        raise FeedforwardError(f"{where}: gravity_dir must not be the zero vector")
    g = g / norm
    g.setflags(write=False)
    ratio = float(values("static_ratio", (), 1.0, 10.0))
    presliding = float(values("presliding_mm", (), 0.0, 10.0))
    if presliding <= 0.0:
        raise FeedforwardError(f"{where}: presliding_mm must be > 0, got {presliding!r}")
    back = np.radians(values("backlash_deg", (n,), 0.0, 10.0))
    back.setflags(write=False)
    return ArmPhysics(
        link_mass_kg=values("link_mass_kg", (n,), 0.0, 1e3),
        payload_kg=float(values("payload_kg", (), 0.0, 1e3)),
        gravity_dir=g,
        g_m_per_s2=G_M_PER_S2,
        mu_kinetic=values("mu_kinetic", (n,), 0.0, 2.0),
        static_ratio=ratio,
        presliding_mm=presliding,
        backlash_rad=back,
        backlash_torque_Nmm=float(values("backlash_torque_Nmm", (), 0.0, 1e6)),
    )


def gravity_forces(
    model: RobotModel, alpha: np.ndarray, theta: np.ndarray, physics: ArmPhysics
) -> np.ndarray:
    """Generalised gravity forces (..., 24) N mm on the true joint angles (..., 12): on
    each axis through joint centre ``O_j`` the moment of every weight beyond the joint,
    ``a . sum_{i >= j} (c_i - O_j) x m_i g``, columns (alpha_1, theta_1, alpha_2, ...).

    One joint holding a known weight (a hand case): 1 kg at the middle of link 12 only,
    the arm level: alpha_12 carries ``9.81 N x 68 mm``, pulling it down.

    >>> import dataclasses
    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot(); p = arm_physics(m)
    >>> mass = np.zeros(12); mass[11] = 1.0
    >>> p1 = dataclasses.replace(p, link_mass_kg=mass, payload_kg=0.0)
    >>> Q = gravity_forces(m, np.zeros(12), np.zeros(12), p1)
    >>> round(float(Q[22]), 2), round(9.81 * 136 / 2, 2), bool(np.allclose(Q[1::2], 0.0))
    (-667.08, 667.08, True)
    """
    R, O = frames(model, alpha, theta)  # (..., 12, 3, 3), (..., 13, 3)
    m = physics.link_mass_kg
    centres = 0.5 * (O[..., :-1, :] + O[..., 1:, :])
    moment = m[:, None] * centres
    moment[..., -1, :] += physics.payload_kg * O[..., -1, :]
    mass_beyond = np.cumsum(m[::-1])[::-1] + physics.payload_kg
    moment_beyond = np.flip(np.cumsum(np.flip(moment, -2), axis=-2), -2)
    lever = moment_beyond - mass_beyond[:, None] * O[..., :-1, :]
    torque = np.cross(lever, physics.gravity_N_per_kg)
    before = np.empty_like(R)
    before[..., 0, :, :] = model.base_rotation @ R_BASE_PAPER
    before[..., 1:, :, :] = R[..., :-1, :, :]
    ca, sa = np.cos(alpha), np.sin(alpha)
    axis_theta = before[..., :, 0] * ca[..., None] - before[..., :, 2] * sa[..., None]
    Q = np.empty((*alpha.shape[:-1], 2 * alpha.shape[-1]))
    Q[..., 0::2] = np.einsum("...ja,...ja->...j", torque, before[..., :, 1])
    Q[..., 1::2] = np.einsum("...ja,...ja->...j", torque, axis_theta)
    return Q


@dataclass(frozen=True, eq=False)
class Holes:
    """Every rope's holes at every joint (docs/ropes.md): ``p`` (12, n, 3) in the frame
    before the joint, ``q`` (12, n, 3) after it, ``crosses`` and ``anchor`` (12, n),
    ``in_link`` (12, n) the rope's length inside the link beyond the joint."""

    p: np.ndarray
    q: np.ndarray
    crosses: np.ndarray
    anchor: np.ndarray
    in_link: np.ndarray


def rope_holes(routing: RopeRouting, links_mm: np.ndarray) -> Holes:
    """The holes of ``routing`` on links ``links_mm`` (12,)."""
    n_j = int(routing.proximal_disk.shape[0])
    joints = np.arange(n_j)[:, None]
    k = routing.joint_of_rope[None, :]
    p = np.zeros((n_j, routing.n_ropes, 3))
    p[..., 0] = routing.hole_radius * np.cos(routing.hole_angle)
    p[..., 1] = routing.hole_radius * np.sin(routing.hole_angle)
    q = p.copy()
    p[..., 2] = -routing.proximal_disk[:, None]
    q[..., 2] = routing.distal_disk[:, None]
    gap = np.asarray(links_mm, float) - routing.distal_disk
    gap[:-1] -= routing.proximal_disk[1:]
    return Holes(p, q, joints <= k, joints == k, gap[:, None] * (joints < k))


def wrap_angles(
    holes: Holes, alpha: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(beta_p, beta_d, s)`` (..., 12, n): each rope's bend (rad) at the proximal and the
    distal hole of every joint it crosses (0 elsewhere and at its anchor) and the
    crossing's length (mm), at the rope geometry's (commanded) angles (..., 12).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.routing import routing_from_model
    >>> m = default_robot(); h = rope_holes(routing_from_model(m), m.links)
    >>> a = np.zeros(12); a[0] = 0.4
    >>> bp, bd, s = wrap_angles(h, a, np.zeros(12))
    >>> round(float(bp[0, 3] + bd[0, 3]), 6), round(float(bp[0, 0]), 6)   # passing; anchored
    (0.4, 0.2)
    """
    R = joint_rotation(alpha, theta)  # (..., 12, 3, 3)
    v = np.einsum("...jab,jmb->...jma", R, holes.q) - holes.p
    s = np.sqrt(np.einsum("...jma,...jma->...jm", v, v))
    safe = np.where(s > 0.0, s, 1.0)
    cos_p = v[..., 2] / safe
    cos_d = np.einsum("...ja,...jma->...jm", R[..., :, :, 2], v) / safe
    beta_p = np.where(holes.crosses, np.arccos(np.clip(cos_p, -1.0, 1.0)), 0.0)
    beta_d = np.where(holes.crosses & ~holes.anchor, np.arccos(np.clip(cos_d, -1.0, 1.0)), 0.0)
    return beta_p, beta_d, s * holes.crosses


def tension_factors(
    nu: np.ndarray,
    mu_kinetic: np.ndarray,
    wraps: tuple[np.ndarray, np.ndarray, np.ndarray],
    holes: Holes,
    box_mm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(crossing, mean)``: the tension across every joint's crossing (..., 12, n) as a
    multiple of the drum tension, ``exp(nu sum mu beta)`` over the bends before it, and
    the length-weighted mean factor along the whole free rope (..., n) (its stretch).
    ``nu`` (..., n): the friction's mobilisation (+1 paid out and sliding, -1 wound in).

    The capstan law across one joint by hand: a rope of joint 12 wound in (nu = -1) over
    joint 12's bend of 0.5 rad arrives at its anchor with ``e^(-0.1 x 0.25)``.

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.routing import routing_from_model
    >>> m = default_robot(); rt = routing_from_model(m); h = rope_holes(rt, m.links)
    >>> a = np.zeros(12); a[11] = 0.5
    >>> w = wrap_angles(h, a, np.zeros(12))
    >>> c, mean = tension_factors(-np.ones(36), np.full(12, 0.1), w, h, rt.box_length)
    >>> round(float(c[11, 33]), 6), round(float(np.exp(-0.1 * w[0][11, 33])), 6)
    (0.97531, 0.97531)
    """
    beta_p, beta_d, s = wraps
    mu = mu_kinetic[:, None]
    bends = mu * (beta_p + beta_d)
    before = np.cumsum(bends, axis=-2) - bends
    nu_ = nu[..., None, :]
    crossing = np.exp(nu_ * (before + mu * beta_p))
    beyond = np.exp(nu_ * (before + bends))
    total = box_mm + s.sum(axis=-2) + holes.in_link.sum(axis=0)
    weighted = box_mm + (s * crossing).sum(axis=-2) + (holes.in_link * beyond).sum(axis=-2)
    return crossing * holes.crosses, weighted / total


def friction_mobilisation(
    unstretched_mm: np.ndarray,
    presliding_mm: float,
    static_ratio: float,
    first: np.ndarray | None = None,
) -> np.ndarray:
    """The friction's mobilisation (rows, n) along a sequence of drum lengths (rows, n):
    a rope sliding one way (paid out: +1, wound in: -1) keeps it; from rest or on a
    reversal it sticks, and the mobilisation follows the travel by ``travel /
    presliding_mm`` up to the static ``static_ratio``, where it breaks away to the kinetic
    1; at rest it keeps what it had.  At the first row each rope slides the way ``first``
    (n,) says (+1, -1; 0: at rest, no friction mobilised), by default (None, NaN) the way
    it first travels.

    >>> u = np.array([[0.0], [0.01], [0.02], [0.5], [0.49], [0.40]])
    >>> friction_mobilisation(u, 0.05, 1.5)[:, 0].round(3).tolist()
    [1.0, 1.0, 1.0, 1.0, 0.8, -1.0]
    """
    u = np.asarray(unstretched_mm, dtype=float)
    rows, n = u.shape
    travel = np.diff(u, axis=0)
    moving = np.abs(travel) > TRAVEL_AT_REST_MM
    ahead = np.sign(travel[moving.argmax(axis=0), np.arange(n)]) if rows > 1 else 0.0
    default = np.where(moving.any(axis=0), ahead, 0.0)
    first = default if first is None else np.where(np.isnan(first), default, first)
    out = np.empty_like(u)
    nu = first.copy()
    sliding = first != 0.0
    out[0] = nu
    for r in range(rows - 1):
        nu, sliding = friction_step(nu, sliding, travel[r], presliding_mm, static_ratio)
        out[r + 1] = nu
    return out


def friction_step(
    nu: np.ndarray,
    sliding: np.ndarray,
    travel_mm: np.ndarray,
    presliding_mm: float,
    static_ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Each rope's friction mobilisation and sliding flag (n,) each after a drum travel
    ``travel_mm`` (n,; > 0 paid out): one step of :func:`friction_mobilisation`.  A rope
    moved less than :data:`TRAVEL_AT_REST_MM` keeps its mobilisation and is at rest: it
    sticks when it moves again, either way (the simulated box's law, ``sim_bus.capstan``).

    >>> nu, s = friction_step(np.array([1.0, 1.0]), np.array([True, True]),
    ...                       np.array([0.01, -0.01]), 0.05, 1.5)
    >>> nu.round(3).tolist(), s.tolist()     # keeps sliding; reversed: sticks
    ([1.0, 0.8], [True, False])
    >>> nu, s = friction_step(nu, s, np.zeros(2), 0.05, 1.5)          # at rest
    >>> friction_step(nu, s, np.array([0.01, 0.01]), 0.05, 1.5)[0].round(3).tolist()
    [1.2, 1.0]
    """
    mv = np.abs(travel_mm) > TRAVEL_AT_REST_MM
    d = np.sign(travel_mm)
    keeps = sliding & mv & (d == np.sign(nu))
    trial = nu + travel_mm / presliding_mm
    breaks = ~keeps & mv & (np.abs(trial) >= static_ratio)
    new = np.where(keeps | breaks, d, np.clip(trial, -static_ratio, static_ratio))
    return np.where(mv, new, nu), keeps | breaks


def play_taken_up(
    gravity_Nmm: np.ndarray, commanded: np.ndarray, backlash_rad: np.ndarray, torque_Nmm: float
) -> np.ndarray:
    """Where each axis stands in its play (rows, 24) (true minus rope-held angle) along a
    sequence of commanded rope-held angles (rows, 24) under gravity moments (rows, 24):
    on the side gravity pulls where it loads the axis by more than ``torque_Nmm``, else
    dragged by the ropes' motion (the play operator).

    >>> g = np.array([[-50.0, 0.0], [-50.0, 0.0], [0.0, 0.0]])
    >>> q = np.array([[0.0, 0.0], [0.0, 0.02], [0.0, 0.03]])
    >>> play_taken_up(g, q, np.array([0.01]), 2.0).tolist()      # one joint: its 2 axes
    [[-0.005, 0.0], [-0.005, -0.005], [-0.005, -0.005]]
    """
    half = 0.5 * np.repeat(backlash_rad, 2)
    out = np.empty_like(commanded)
    play = np.zeros(commanded.shape[1])
    prev = commanded[0]
    for r in range(commanded.shape[0]):
        dragged = np.clip(play - (commanded[r] - prev), -half, half)
        g = gravity_Nmm[r]
        play = np.where(np.abs(g) > torque_Nmm, np.sign(g) * half, dragged)
        out[r] = play
        prev = commanded[r]
    return out


@dataclass(frozen=True, eq=False)
class Holding:
    """What holds a sequence of poses (rows): drum tensions (rows, n) N, each rope's mean
    friction factor along it (rows, n), the gravity forces (rows, 24) N mm, the
    unstretched lengths that span the poses at those tensions (rows, n) mm and the
    rope-held (commanded) true angles (rows, 12) each (the planned ones less the play)."""

    tension_N: np.ndarray
    mean_factor: np.ndarray
    gravity_Nmm: np.ndarray
    unstretched_mm: np.ndarray
    alpha: np.ndarray
    theta: np.ndarray


@dataclass(frozen=True, eq=False)
class Feedforward:
    """The feed-forward of one arm: its rope layer (the calibration's EA and zero offsets
    in it), its physics, which terms are on (``gravity``: the holding tensions and the
    stretch; ``capstan``: the friction factors; ``backlash``: the play), and how many
    times the friction's direction is evaluated again from the compensated lengths."""

    actuation: Actuation
    physics: ArmPhysics
    holes: Holes
    gravity: bool = True
    capstan: bool = True
    backlash: bool = True

    @classmethod
    def of(
        cls,
        actuation: Actuation,
        *,
        gravity: bool = True,
        capstan: bool = True,
        backlash: bool = True,
    ) -> Feedforward:
        """The feed-forward of ``actuation``'s arm, its physics from the robot description
        (:func:`arm_physics`)."""
        robot = actuation.robot
        return cls(
            actuation,
            arm_physics(robot),
            rope_holes(actuation.routing, robot.links),
            gravity,
            capstan,
            backlash,
        )

    def holding(
        self, alpha: np.ndarray, theta: np.ndarray, nu: np.ndarray | None = None
    ) -> Holding:
        """The tensions and lengths that hold the planned true poses (rows, 12) each, the
        friction mobilised by ``nu`` (rows, n) (None: none), the play taken up as
        :func:`play_taken_up` says along the rows."""
        act = self.actuation
        a = np.atleast_2d(np.asarray(alpha, dtype=float))
        t = np.atleast_2d(np.asarray(theta, dtype=float))
        rows = a.shape[0]
        n = act.n_motors
        ph = self.physics
        if self.gravity:
            Qg = np.concatenate(
                [gravity_forces(act.robot, a[i : i + BLOCK_ROWS], t[i : i + BLOCK_ROWS], ph)
                 for i in range(0, rows, BLOCK_ROWS)]
            )  # fmt: skip
        else:
            Qg = np.zeros((rows, 2 * act.n_joints))
        ca, ct = self._held(a, t, Qg)
        geo_a, geo_t = act.commanded_angles(ca, ct)
        T = np.empty((rows, n))
        mean = np.ones((rows, n))
        u = np.empty((rows, n))
        T0 = float(act.routing.pretension_N)
        low, high = act.command_tension_N
        EA = act.routing.stiffness_EA_N
        box = act.routing.box_length
        friction = self.capstan and nu is not None and bool(ph.mu_kinetic.any())
        for lo in range(0, rows, BLOCK_ROWS):
            sl = slice(lo, min(lo + BLOCK_ROWS, rows))
            L, J, _s = lengths_and_jacobian(act.geometry, geo_a[sl], geo_t[sl])
            A = J
            if friction:
                assert nu is not None
                wraps = wrap_angles(self.holes, geo_a[sl], geo_t[sl])
                cross, mean[sl] = tension_factors(nu[sl], ph.mu_kinetic, wraps, self.holes, box)
                A = J * np.repeat(np.swapaxes(cross, -1, -2), 2, axis=-1)
            b = T0 * J.sum(axis=1) + Qg[sl]
            T[sl] = _nearest_tensions(A, b, T0, low, high)
            u[sl] = (box + L) / (1.0 + T[sl] * mean[sl] / EA)
        for arr in (T, mean, Qg, u):
            arr.setflags(write=False)
        return Holding(T, mean, Qg, u, np.asarray(ca), np.asarray(ct))

    def held_angles(self, alpha: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rope-held (commanded) true angles (rows, 12) each of a planned sequence of
        true poses (rows, 12), in time order: the play taken up as
        :func:`play_taken_up` says (the poses themselves without the play term)."""
        a = np.atleast_2d(np.asarray(alpha, dtype=float))
        t = np.atleast_2d(np.asarray(theta, dtype=float))
        if not (self.backlash and self.gravity and self.physics.backlash_rad.any()):
            return a, t
        Qg = np.concatenate(
            [gravity_forces(self.actuation.robot, a[i : i + BLOCK_ROWS], t[i : i + BLOCK_ROWS],
                            self.physics) for i in range(0, a.shape[0], BLOCK_ROWS)]
        )  # fmt: skip
        return self._held(a, t, Qg)

    def _held(self, a: np.ndarray, t: np.ndarray, Qg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ph = self.physics
        if not (self.backlash and self.gravity and ph.backlash_rad.any()):
            return a, t
        held = np.empty((a.shape[0], 2 * a.shape[1]))
        held[:, 0::2], held[:, 1::2] = a, t
        play = play_taken_up(Qg, held, ph.backlash_rad, ph.backlash_torque_Nmm)
        return a - play[:, 0::2], t - play[:, 1::2]

    def unstretched(
        self, alpha: np.ndarray, theta: np.ndarray, first: np.ndarray | None = None
    ) -> Holding:
        """What holds a commanded sequence of true poses (rows, 12) each, in time order:
        the friction mobilised as the planned rope travel says (:func:`friction_mobilisation`
        of the lengths at the pretension; ``first``: how each rope arrived at the first
        row).  Not of the compensated lengths' own travel:
        where a rope nearly stops or reverses, the compensation's own change decides its
        direction, and the friction it then foresees changes that change by up to a
        millimetre; evaluated again and again it does not settle (measured on the bent
        pipe), nor row by row (a sticking rope's tension follows its sub-micrometre travel:
        the commanded counts chatter past the motors' acceleration limit)."""
        act = self.actuation
        a = np.atleast_2d(np.asarray(alpha, dtype=float))
        t = np.atleast_2d(np.asarray(theta, dtype=float))
        ph = self.physics
        if not (self.capstan and ph.mu_kinetic.any()):
            return self.holding(a, t, None)
        u = act.motors.unstretched_from_counts(act.counts_from_angles(a, t, check=False))
        nu = friction_mobilisation(u, ph.presliding_mm, ph.static_ratio, first)
        return self.holding(a, t, nu)

    def counts(
        self, alpha: np.ndarray, theta: np.ndarray, first: np.ndarray | None = None
    ) -> np.ndarray:
        """Motor counts (rows, n) int64 that hold the commanded sequence of true poses
        (rows, 12) each (:meth:`unstretched`), checked against the drum travel."""
        act = self.actuation
        held = self.unstretched(alpha, theta, first).unstretched_mm
        c = act.motors.counts_from_unstretched(held)
        if not ((c >= act.counts_min).all() and (c <= act.counts_max).all()):
            act.check_counts(c)
        return c


def _nearest_tensions(
    A: np.ndarray, b: np.ndarray, T0: float, low: float, high: float
) -> np.ndarray:
    """Per row the tensions (rows, n) nearest ``T0`` with ``A^T T = b`` (A (rows, n, 24),
    b (rows, 24)), each within ``[low, high]``: the least-squares solution where it keeps
    every rope in the band, else the bounded least squares of the equilibrium (weighted
    :data:`EQUILIBRIUM_WEIGHT`) and the distance from ``T0`` (where no tensions in the
    band hold the pose, the least misfit)."""
    At = np.swapaxes(A, -1, -2)
    r = b - T0 * A.sum(axis=1)
    y = np.linalg.solve(At @ A, r[..., None])[..., 0]
    T = T0 + np.einsum("bnk,bk->bn", A, y)
    bad = np.flatnonzero(((T < low) | (T > high)).any(axis=1))
    if bad.size:
        from scipy.optimize import lsq_linear

        n = T.shape[1]
        eye = np.eye(n)
        for i in bad:
            M = np.vstack([EQUILIBRIUM_WEIGHT * At[i], eye])
            rhs = np.concatenate([EQUILIBRIUM_WEIGHT * b[i], np.full(n, T0)])
            T[i] = lsq_linear(M, rhs, bounds=(low, high), method="bvls").x
    return T


__all__ = [
    "DEFAULT_PHYSICS",
    "ArmPhysics",
    "Feedforward",
    "FeedforwardError",
    "Holding",
    "arm_physics",
    "friction_mobilisation",
    "friction_step",
    "gravity_forces",
    "play_taken_up",
    "rope_holes",
    "tension_factors",
    "wrap_angles",
]
