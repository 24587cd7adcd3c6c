"""Capstan friction in the simulated arm: the loss across one joint by hand
(``e^(-mu beta)``), static above kinetic, and the hysteresis loop it makes (closed, its
width by a hand linearisation of one joint)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from sim_bus.arm import ArmState, SimArm
from sim_bus.capstan import friction_update
from sim_bus.physics import Effect, Physics

ACT = load_actuation(default_robot())
RT = ACT.routing
MU = 0.1
J12 = np.flatnonzero(RT.joint_of_rope == 11)  # joint 12's ropes: only they cross it


def capstan_arm() -> SimArm:
    return SimArm(ACT, noise_N=0.0, physics=Physics(frozenset({Effect.CAPSTAN}), mu_kinetic=MU))


def joint12(alpha: float) -> np.ndarray:
    a = np.zeros(12)
    a[11] = alpha
    return ACT.counts_from_angles(a, np.zeros(12))


def rotation(alpha: float, theta: float) -> np.ndarray:
    ca, sa, ct, st = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    return np.array([[ca, sa * st, sa * ct], [0.0, ct, -st], [-sa, ca * st, ca * ct]])


def crossing(m: int, alpha: float, theta: float, joint: int = 11) -> np.ndarray:
    """Rope m's crossing of a joint (frame before the joint), by hand."""
    r, phi = RT.hole_radius[m], RT.hole_angle[m]
    p = np.array([r * math.cos(phi), r * math.sin(phi), -RT.proximal_disk[joint]])
    q = np.array([r * math.cos(phi), r * math.sin(phi), RT.distal_disk[joint]])
    return rotation(alpha, theta) @ q - p


def bend(m: int, alpha: float, theta: float) -> float:
    """Rope m's bend at joint 12's proximal hole (it is anchored in the distal one)."""
    v = crossing(m, alpha, theta)
    return math.acos(v[2] / np.linalg.norm(v))


def bends_before(m: int, alpha: np.ndarray, theta: np.ndarray) -> float:
    """Rope m's bends at both holes of joints 1..11 (the loads that joint 12's friction
    puts on the ropes turn those joints a little too)."""
    total = 0.0
    for j in range(11):
        v = crossing(m, float(alpha[j]), float(theta[j]), j)
        axis = rotation(float(alpha[j]), float(theta[j]))[:, 2]
        n = np.linalg.norm(v)
        total += math.acos(min(1.0, v[2] / n)) + math.acos(min(1.0, float(axis @ v) / n))
    return total


def sweep(arm: SimArm, alphas: np.ndarray, t0: float = 0.0) -> list[ArmState]:
    return [arm.state(joint12(float(a)), t0 + 0.01 * (i + 1)) for i, a in enumerate(alphas)]


def test_the_loss_across_one_joint_is_e_to_the_minus_mu_beta() -> None:
    arm = capstan_arm()
    states = sweep(arm, np.linspace(0.0, 0.5, 101))
    s, ps = states[-1], arm.physics_state
    assert ps is not None and bool(ps.sliding[J12].all())
    before = arm.unstretched_mm(joint12(0.495))
    travel = arm.unstretched_mm(joint12(0.5)) - before
    assert s.rope_alpha is not None and s.rope_theta is not None and s.anchor_tension_N is not None
    for m in J12:
        beta = bend(int(m), float(s.rope_alpha[11]), float(s.rope_theta[11]))
        assert beta > 0.1  # a real bend
        before = bends_before(int(m), s.rope_alpha, s.rope_theta)
        assert before < 0.05 * beta  # the other joints stay nearly straight
        sign = 1.0 if travel[m] > 0 else -1.0  # paid out: the tension rises to the anchor
        assert s.anchor_tension_N[m] / s.tension_N[m] == pytest.approx(
            math.exp(sign * MU * (beta + before)), rel=1e-6
        )
    others = np.setdiff1d(np.arange(36), J12)  # bent nowhere: no loss
    assert np.allclose(s.anchor_tension_N[others], s.tension_N[others], rtol=1e-12)


def test_static_friction_above_kinetic_a_rope_sticks_then_slides() -> None:
    nu, sliding = np.zeros(1), np.zeros(1, dtype=bool)
    seen = []
    for _ in range(10):  # 0.01 mm at a time, presliding 0.05 mm, mu_s = 1.5 mu_k
        nu, sliding = friction_update(nu, sliding, np.array([0.01]), 0.05, 1.5)
        seen.append((round(float(nu[0]), 6), bool(sliding[0])))
    assert seen[:7] == [(round(0.2 * (i + 1), 6), False) for i in range(7)]  # sticking
    assert seen[7:] == [(1.0, True)] * 3  # broke away at 1.5, slides at the kinetic 1
    nu, sliding = friction_update(nu, sliding, np.zeros(1), 0.05, 1.5)  # at rest: holds
    assert (float(nu[0]), bool(sliding[0])) == (1.0, False)
    nu, sliding = friction_update(nu, sliding, np.array([-0.01]), 0.05, 1.5)  # reversed
    assert (round(float(nu[0]), 6), bool(sliding[0])) == (0.8, False)


def hand_deflection(alpha: float, going_up: bool) -> float:
    """Joint 12's friction deflection by hand, linearised over the whole arm: each rope's
    drum tension ``T0 + k J.d`` (``J`` its length's gradient: small-angle ``-r cos phi``,
    ``r sin phi`` at the straight joints 1..11, the exact crossing's at joint 12;
    ``k = EA/w``); joint 12's ropes pull joint 12 with ``f`` times that (``f =
    e^(nu mu beta)``: wound in ``nu = -1``, paid out ``+1``; the other joints straight:
    no friction); the moments balance for ``d = -(sum k J_f J^T)^-1 sum T0 (f - 1) g``
    (``J_f``: J with joint 12's columns times f, ``g`` those columns alone)."""
    T0 = RT.pretension_N
    EA = np.broadcast_to(RT.stiffness_EA_N, (RT.n_ropes,))
    w = (RT.box_length + ACT.geometry.straight) / (1.0 + T0 / EA)
    A = np.zeros((24, 24))
    b = np.zeros(24)
    h = 1e-7
    for m in range(RT.n_ropes):
        k_m = int(RT.joint_of_rope[m])
        J = np.zeros(24)
        for j in range(min(k_m + 1, 11)):
            J[2 * j] = -RT.hole_radius[m] * math.cos(RT.hole_angle[m])
            J[2 * j + 1] = RT.hole_radius[m] * math.sin(RT.hole_angle[m])
        Jf = J.copy()
        if k_m == 11:
            s0 = np.linalg.norm(crossing(m, alpha, 0.0))
            J[22] = (np.linalg.norm(crossing(m, alpha + h, 0.0)) - s0) / h
            J[23] = (np.linalg.norm(crossing(m, alpha, h)) - s0) / h
            paid_out = (J[22] > 0) == going_up  # going up the rope lengthens where ds/da > 0
            f = math.exp((1.0 if paid_out else -1.0) * MU * bend(m, alpha, 0.0))
            Jf[22:] = f * J[22:]
            b[22:] += T0 * (f - 1.0) * J[22:]
        A += EA[m] / w[m] * np.outer(Jf, J)
    return float(-np.linalg.solve(A, b)[22])


def test_hysteresis_loop_closes_with_the_width_a_hand_linearisation_gives() -> None:
    arm = capstan_arm()
    amp, step = 0.4, 0.004
    up = np.arange(0.0, amp, step)
    cycle = np.concatenate([np.arange(amp, -amp, -step), np.arange(-amp, amp, step)])
    commanded = np.concatenate([up, cycle, cycle])
    states = sweep(arm, commanded)
    err = np.array([s.alpha[11] for s in states]) - commanded
    n0, n = len(up), len(cycle)
    first, second = err[n0 : n0 + n], err[n0 + n :]
    assert np.abs(second - first).max() < 1e-6  # the loop closes: the same loop again
    at = 0.2
    i_down = int(np.argmin(np.abs(cycle[: n // 2] - at)))
    i_up = n // 2 + int(np.argmin(np.abs(cycle[n // 2 :] - at)))
    width = float(second[i_down] - second[i_up])
    want = hand_deflection(at, going_up=False) - hand_deflection(at, going_up=True)
    assert width > 1e-3  # about a tenth of a degree: a loop, not noise
    assert width == pytest.approx(want, rel=0.1)
    # no friction without a bend: the loop pinches where the joint is straight
    i_zero = int(np.argmin(np.abs(cycle)))
    assert abs(float(second[i_zero])) < 0.1 * width
