"""The arm's statics against hand cases: one joint holding a known weight (its ropes'
moment and the whole arm's sag, by a small-angle compliance written out here)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from sim_bus.arm import SimArm
from sim_bus.gravity import gravity_forces
from sim_bus.physics import Effect, Physics

ACT = load_actuation(default_robot())
G = 9.81
MASS_KG = 0.1  # on link 12 only


def weight_on_link_12(mass_kg: float = MASS_KG) -> SimArm:
    masses = np.zeros(12)
    masses[11] = mass_kg
    physics = Physics(frozenset({Effect.GRAVITY}), link_mass_kg=masses, payload_kg=0.0)
    return SimArm(ACT, noise_N=0.0, physics=physics)


def straight_counts() -> np.ndarray:
    return ACT.counts_from_angles(np.zeros(12), np.zeros(12))


def test_no_physics_and_no_effect_are_the_arm_without_physics() -> None:
    c = ACT.counts_from_angles(np.full(12, 0.1), np.full(12, -0.05))
    plain = SimArm(ACT, noise_N=0.0).state(c, 0.0)
    none = SimArm(ACT, noise_N=0.0, physics=Physics.of("none"))
    assert none.physics is None
    assert np.array_equal(none.state(c, 0.0).centres, plain.centres)
    # physics on, but no load: the ropes' equilibrium is the rope layer's pose
    sensor = SimArm(ACT, noise_N=0.0, physics=Physics.of("sensor", sensor_drift_N_per_sqrt_s=0))
    s = sensor.state(c, 0.0)
    assert np.abs(s.centres - plain.centres).max() < 1e-3
    assert np.abs(s.tension_N - 30.0).max() < 0.05


def test_one_joint_holds_a_known_weight_its_ropes_moment_by_hand() -> None:
    s = weight_on_link_12().state(straight_counts(), 0.0)
    rt = ACT.routing
    ropes = np.flatnonzero(rt.joint_of_rope == 11)  # joint 12's three ropes
    phi, r = rt.hole_angle[ropes], rt.hole_radius[ropes]
    # about alpha_12 a rope's lever is r cos(phi) on the straight arm (ds/dalpha =
    # -r cos phi); what the tension beyond the pretension holds is m g l12 / 2
    extra = s.tension_N[ropes] - rt.pretension_N
    moment = float(np.sum(extra * r * np.cos(phi)))
    want = MASS_KG * G * float(ACT.robot.links[11]) / 2.0
    assert moment == pytest.approx(want, rel=0.02)
    # no load about theta_12 (the arm lies level)
    assert abs(float(np.sum(extra * r * np.sin(phi)))) < 0.02 * want
    # the sag is downwards, and the end point stays in the arm's vertical plane
    assert s.centres[-1, 2] < -0.5 and abs(s.centres[-1, 1]) < 1e-6


def test_the_arm_sags_as_a_small_angle_compliance_by_hand_says() -> None:
    """Small-angle crossing ``s = d - r (alpha cos phi - theta sin phi)``: each rope's
    length Jacobian, its stiffness ``EA / w``; the weight's moment about every joint's
    alpha axis ``-m g (x_c - x_j)``; the angles ``(J^T K J)^-1 Q``; the tip's drop
    ``sum_j alpha_j (x_tip - x_j)``."""
    rt = ACT.routing
    links = np.asarray(ACT.robot.links, float)
    n = rt.n_ropes
    J = np.zeros((n, 24))
    for m in range(n):
        for j in range(int(rt.joint_of_rope[m]) + 1):
            J[m, 2 * j] = -rt.hole_radius[m] * math.cos(rt.hole_angle[m])
            J[m, 2 * j + 1] = rt.hole_radius[m] * math.sin(rt.hole_angle[m])
    EA = np.broadcast_to(rt.stiffness_EA_N, (n,))
    free_straight = rt.box_length + ACT.geometry.straight
    w = free_straight / (1.0 + rt.pretension_N / EA)
    K = EA / w
    x_joint = np.concatenate([[0.0], np.cumsum(links)])  # O_1 .. O_13 along +x0
    x_weight = x_joint[11] + links[11] / 2.0
    Q = np.zeros(24)
    Q[0::2] = -MASS_KG * G * (x_weight - x_joint[:12])
    dq = np.linalg.solve(J.T @ (K[:, None] * J), Q)
    drop = float(np.sum(dq[0::2] * (x_joint[12] - x_joint[:12])))
    s = weight_on_link_12().state(straight_counts(), 0.0)
    assert drop < -1.0  # millimetres: worth a test
    assert float(s.centres[-1, 2]) == pytest.approx(drop, rel=0.03)
    assert np.abs(s.alpha - dq[0::2]).max() < 0.02 * np.abs(dq[0::2]).max()
    assert np.abs(s.theta).max() < 1e-6  # level: no theta


def test_gravity_along_the_arm_bends_nothing_and_twice_the_weight_sags_twice() -> None:
    down = Physics(
        frozenset({Effect.GRAVITY}),
        link_mass_kg=0.02,
        payload_kg=0.02,
        gravity_dir=(1.0, 0.0, 0.0),  # the base turned so that the arm hangs down
    )
    s = SimArm(ACT, noise_N=0.0, physics=down).state(straight_counts(), 0.0)
    assert np.abs(s.centres[-1] - [2007.0, 0.0, 0.0]).max() < 1e-6
    one = weight_on_link_12(0.05).state(straight_counts(), 0.0).centres[-1, 2]
    two = weight_on_link_12(0.10).state(straight_counts(), 0.0).centres[-1, 2]
    assert two == pytest.approx(2.0 * one, rel=0.02)  # linear while no rope goes slack


def test_gravity_forces_by_hand_on_a_bent_arm() -> None:
    """The moment about a joint's axes of a payload at the tip, from the joint centres and
    frames of the FK written out: finite differences of the payload's potential."""
    robot = ACT.robot
    rng = np.random.default_rng(3)
    a, t = rng.uniform(-0.5, 0.5, 12), rng.uniform(-0.5, 0.5, 12)
    g = np.array([0.0, 0.0, -G])
    Q = gravity_forces(robot, a, t, np.zeros(12), 0.3, g)
    from hrm_ctrl.kinematics import end_point

    def potential(q: np.ndarray) -> float:
        return -0.3 * float(g @ end_point(robot, q[0::2], q[1::2]))

    q = np.empty(24)
    q[0::2], q[1::2] = a, t
    h = 1e-6
    num = np.array([(potential(q - h * e) - potential(q + h * e)) / (2 * h) for e in np.eye(24)])
    assert np.allclose(Q, num, rtol=1e-5, atol=1e-4)
