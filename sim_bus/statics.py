"""The arm's quasi-static equilibrium: elastic ropes holding the arm against its loads.

Rope m, of effective unstretched length ``w_m`` (drum, slack and creep) and axial rigidity
``EA_m``, must span the free length ``F_m(q) = box_m + L_m(q)`` the pose q needs (24
rope-geometric angles).  With capstan friction its tension is not uniform: a stretch of
rope carries ``T_m f`` with ``f`` the friction factor there (``sim_bus.capstan``; 1
without friction), so the rope stretches by ``T_m w_m fbar_m / EA_m`` (``fbar``: the
length-weighted mean factor) and its drum-side tension is

    T_m = max(0, EA_m (F_m(q) - w_m) / (w_m fbar_m))          (0: the rope is slack)

A rope pulls each joint it crosses with its tension there.  The joints carry the
moments of the pretension ``T0`` itself (the design's balance: the arm stands where its
ropes' lengths put it, as without physics), so what moves a joint is each rope's tension
beyond it, ``T_m f_mj - T0``: the ropes' generalised force is
``-sum_m (T_m f_mj - T0) dF_m/dq_j``; gravity's is ``Q_g`` (``sim_bus.gravity``).  The
equilibrium solves

    G(q) = -sum_m (T_m f_m - T0) (dF_m/dq) + Q_g(q) = 0

by Newton's method with the ropes' stiffness ``H = (f J)^T diag(EA / (w fbar)) J`` (J the
rope layer's Jacobian ``dL/dq``; the loads' own stiffness left out, and the loads held
within small moves: the steps converge linearly within a few iterations), warm-started
from the previous state.  Without loads or friction it is the pose at which the ropes'
elastic energy is least, the rope layer's least-squares inverse weighted by the rope
stiffnesses.

(With the whole tension instead, the arm at a uniform 30 N is unstable: the shortening
of a rope that crosses two joints bent in opposite senses cancels to first order, so
such a zig-zag is held by a joint's own three ropes while all 36 ropes' pretension,
about ``-6 mm/rad^2`` of crossing length each, folds it; the tangent stiffness of the
default arm at 30 N has eigenvalues down to -3000 N mm/rad.  A real arm of this
routing holds its pretension in the joints' structure and friction.)

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> from sim_bus.capstan import hole_geometry
>>> act = load_actuation(default_robot())
>>> holes = hole_geometry(act.routing, act.robot.links)
>>> a = np.full(12, 0.1); t = np.full(12, -0.05)
>>> T0, EA = 30.0, np.full(36, 30000.0)
>>> w = act.free_lengths(a, t) / (1.0 + T0 / EA)          # ropes at 30 N in that pose
>>> eq = solve_equilibrium(act, holes, w, EA, np.zeros(12), np.zeros(12), Loads.none(36))
>>> bool(np.abs(eq.alpha - a).max() < 1e-7), bool(np.allclose(eq.tension_N, 30.0))
(True, True)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.length import lengths_and_jacobian
from sim_bus.capstan import HoleGeometry, tension_factors, wrap_angles

MAX_STEP_RAD = 0.05  # a Newton step's largest change of one angle
TOL_RAD = 1e-6  # converged: the last step changed no angle by more (a count: 4e-5 rad)
RELOAD_RAD = 1e-3  # the loads (gravity, friction factors) evaluated again after such a move
REGULARISATION_NMM = 1.0  # N mm/rad on every axis: a joint whose ropes are all slack


@dataclass(frozen=True, eq=False)
class Loads:
    """What acts on the arm besides its ropes' pretension: ``gravity(alpha, theta)`` the
    generalised gravity forces (24,) at rope-geometric angles (None: no gravity);
    friction mobilisation ``nu`` (n,) and kinetic coefficients ``mu_kinetic`` (12,) (None:
    no friction); ``taut`` (n,) the ropes that can pull (a snapped rope cannot);
    ``pretension_N`` the tension whose moments the joints carry (a snapped rope's too: its
    joint turns away from it as the other ropes' pretension is no longer balanced)."""

    gravity: Callable[[np.ndarray, np.ndarray], np.ndarray] | None
    nu: np.ndarray | None
    mu_kinetic: np.ndarray | None
    taut: np.ndarray
    pretension_N: float = 30.0

    @classmethod
    def none(cls, n: int, pretension_N: float = 30.0) -> Loads:
        return cls(None, None, None, np.ones(n, dtype=bool), pretension_N)


@dataclass(frozen=True, eq=False)
class LoadedPose:
    """The loads evaluated at one pose ``q`` (24,): gravity forces (24,) (zeros without
    gravity) and the ropes' bends and crossings ``(beta_p, beta_d, s)`` (None without
    friction); a later solve starting within ``reload_rad`` of ``q`` reuses them."""

    q: np.ndarray
    gravity_Nmm: np.ndarray
    wraps: tuple[np.ndarray, np.ndarray, np.ndarray] | None


@dataclass(frozen=True, eq=False)
class Equilibrium:
    """The solved arm: rope-geometric angles (12,) each, drum-side and anchor tensions
    (n,) N, the gravity forces (24,) N mm there, each rope's length misfit (n,) mm (free
    length needed minus stretched length: 0 for a taut rope, > 0... < 0 slack), the
    iterations and the last step (rad)."""

    alpha: np.ndarray
    theta: np.ndarray
    tension_N: np.ndarray
    anchor_N: np.ndarray
    gravity_Nmm: np.ndarray
    residual_mm: np.ndarray
    iterations: int
    last_step_rad: float
    loaded: LoadedPose


def solve_equilibrium(
    rope: Actuation,
    holes: HoleGeometry,
    w_mm: np.ndarray,
    EA_N: np.ndarray,
    alpha0: np.ndarray,
    theta0: np.ndarray,
    loads: Loads,
    *,
    max_iter: int = 50,
    tol_rad: float = TOL_RAD,
    reload_rad: float = RELOAD_RAD,
    loaded: LoadedPose | None = None,
) -> Equilibrium:
    """The equilibrium (module docstring) from the start ``alpha0``, ``theta0``; at most
    ``max_iter`` Newton steps (the last iterate is returned if it did not converge: the
    next state continues from it).  The loads (gravity, the friction factors) are
    evaluated at the start (``loaded``, an earlier solve's, if that is within
    ``reload_rad``) and again after a move of more than ``reload_rad``: within such a
    move they are those of the pose they were evaluated at."""
    geom = rope.geometry
    box = rope.routing.box_length
    n_j = len(alpha0)
    q = np.empty(2 * n_j)
    q[0::2], q[1::2] = alpha0, theta0
    lim = np.empty(2 * n_j)
    lim[0::2], lim[1::2] = rope.robot.limit_alpha * 0.999, rope.robot.limit_theta * 0.999
    k_base = np.where(loads.taut, EA_N / w_mm, 0.0)
    ones = holes.crosses.astype(float)
    step = np.inf
    it = 0
    T = np.zeros_like(w_mm)
    anchor = np.ones_like(w_mm)
    mean = np.ones_like(w_mm)
    Qg = np.zeros_like(q)
    F = box.copy()
    cross = ones
    friction = loads.nu is not None and loads.mu_kinetic is not None
    if loaded is not None and (
        np.abs(q - loaded.q).max() > reload_rad
        or (loaded.wraps is None) == friction
        or (loads.gravity is not None) != bool(loaded.gravity_Nmm.any())
    ):
        loaded = None
    fresh = True  # the loads (or the friction's state) are new: factors to compute
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is returned)
        a, t = q[0::2], q[1::2]
        L, J, _s = lengths_and_jacobian(geom, a[None], t[None])
        F = box + L[0]
        if loaded is None or np.abs(q - loaded.q).max() > reload_rad:
            g = loads.gravity(a, t) if loads.gravity is not None else np.zeros_like(q)
            loaded = LoadedPose(q.copy(), g, wrap_angles(holes, a, t) if friction else None)
            fresh = True
        if fresh:
            fresh = False
            Qg = loaded.gravity_Nmm
            if loaded.wraps is not None and loads.nu is not None and loads.mu_kinetic is not None:
                bp, bd, s_cross = loaded.wraps
                cross, anchor, mean = tension_factors(
                    loads.nu, loads.mu_kinetic, bp, bd, s_cross, holes, box
                )
        k = k_base / mean
        T = np.maximum(k * (F - w_mm), 0.0)
        A = J[0] * np.repeat(cross, 2, axis=0).T  # (n, 24): f_mj dF_m/dq
        G = loads.pretension_N * J[0].sum(axis=0) - A.T @ T + Qg
        H = A.T @ (np.where(T > 0.0, k, 0.0)[:, None] * J[0])
        H[np.diag_indices_from(H)] += REGULARISATION_NMM
        dq = np.linalg.solve(H, G)
        step = float(np.abs(dq).max())
        if step > MAX_STEP_RAD:
            dq *= MAX_STEP_RAD / step
        q = np.clip(q + dq, -lim, lim)
        if step < tol_rad:
            break
    a, t = q[0::2].copy(), q[1::2].copy()
    stretched = w_mm * (1.0 + T * mean / EA_N)
    assert loaded is not None
    return Equilibrium(a, t, T, T * anchor, Qg, F - stretched, it, step, loaded)
