"""The simulated arm against the rope layer's forward map and the planner's FK."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hrm_ctrl.errors import SimError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from sim_bus.arm import SimArm
from sim_bus.truth import TrueArm

ACT: Actuation = load_actuation(default_robot())
LIMIT = 0.9 * float(ACT.robot.limit_alpha)


@settings(max_examples=25, deadline=None)
@given(
    arrays(float, 12, elements=st.floats(-LIMIT, LIMIT)),
    arrays(float, 12, elements=st.floats(-LIMIT, LIMIT)),
)
def test_true_pose_from_counts_matches_the_forward_map(a: np.ndarray, t: np.ndarray) -> None:
    counts = ACT.counts_from_angles(a, t)  # the rope layer's forward map (with stretch)
    s = SimArm(ACT, noise_N=0.0).state(counts, now=0.0)
    # counts are quantised (~2000 counts/mm): angles within 1e-3 rad, centres within 1 mm
    assert np.abs(s.alpha - a).max() < 1e-3 and np.abs(s.theta - t).max() < 1e-3
    assert np.linalg.norm(s.centres - joint_centres(ACT.robot, a, t), axis=-1).max() < 1.0
    # consistent ropes sit at their pretension
    assert np.allclose(s.tension_N, s.counts * 0 + ACT.routing.pretension_N, atol=0.5)


def test_slack_rope_loses_tension_and_a_short_one_gains() -> None:
    pre = float(ACT.routing.pretension_N)
    zero = ACT.counts_from_angles(np.zeros(12), np.zeros(12))
    for delta, sign in ((-2000, -1), (2000, 1)):  # counts count rope wound in (~2150 per mm)
        counts = zero.copy()
        counts[5] += delta  # j02r2 paid out / wound in ~1 mm
        s = SimArm(ACT, noise_N=0.0).state(counts, now=0.0)
        assert sign * (s.tension_N[5] - pre) > 1.0
        assert np.allclose(s.tension_N[:3], pre, atol=0.1)  # joint 1's ropes: unaffected
    assert np.abs(s.residual_mm[3:6]).max() > 0.1  # the inverse's residual shows the misfit


def test_snapped_rope_zero_tension_and_joint_drifts_away() -> None:
    arm = SimArm(ACT, noise_N=0.05, snap_drift_rad_per_s=0.2)
    counts = ACT.counts_from_angles(np.zeros(12), np.zeros(12))
    arm.snap("j04r1", now=0.0)
    s0 = arm.state(counts, now=0.0)
    s1 = arm.state(counts, now=1.0)
    i = ACT.motor_ids.index("j04r1")
    assert s1.tension_N[i] == 0.0
    moved = np.hypot(s1.alpha[3] - s0.alpha[3], s1.theta[3] - s0.theta[3])
    assert moved == pytest.approx(0.2, rel=1e-3)
    # it turns the way that lengthens the broken rope (the others pull)
    assert ACT.rope_lengths(s1.alpha, s1.theta)[i] > ACT.rope_lengths(s0.alpha, s0.theta)[i]
    others = [k for k in range(12) if k != 3]
    assert np.allclose(s1.alpha[others], s0.alpha[others])
    with pytest.raises(SimError, match="unknown rope motor"):
        arm.snap("j13r0", now=0.0)


# ---- the arm's truth (issue 12) ----------------------------------------------------------


def _truth(**changes: object) -> TrueArm:
    return TrueArm.nominal(ACT).replace(**changes)


def test_true_links_change_the_fk() -> None:
    links = np.asarray(ACT.robot.links, dtype=float).copy()
    links[3] += 1.5
    links[11] -= 2.0
    arm = SimArm(ACT, truth=_truth(links_mm=links), noise_N=0.0)
    a = np.full(12, 0.2)
    t = np.full(12, -0.1)
    s = arm.state(ACT.counts_from_angles(a, t), now=0.0)
    # the ropes set the angles as before; only the FK's links differ
    assert np.abs(s.alpha - a).max() < 1e-3
    want = joint_centres(dataclasses.replace(ACT.robot, links=links), s.alpha, s.theta)
    assert np.allclose(s.centres, want)
    nominal = joint_centres(ACT.robot, s.alpha, s.theta)
    assert np.linalg.norm(s.centres[-1] - nominal[-1]) > 0.5
    assert np.allclose(s.centres[:4], nominal[:4])  # links before the 4th unchanged


def test_joint_offset_shows_in_the_physical_angle() -> None:
    off_a = np.radians(np.linspace(-1.0, 1.0, 12))
    off_t = np.radians(np.linspace(0.8, -0.8, 12))
    truth = _truth(alpha_offset_rad=off_a, theta_offset_rad=off_t)
    arm = SimArm(ACT, truth=truth, noise_N=0.0)
    a = np.full(12, 0.15)
    t = np.full(12, 0.05)
    # a host with the rope geometry's zero (the ideal actuation): true = commanded + offset
    ideal = truth.ideal_actuation(ACT.robot)
    rope_geometry_zero = ACT.counts_from_angles(a, t)  # counts of phi = (a, t) at these zeros
    s = arm.state(ideal.counts_from_angles(a + off_a, t + off_t), now=0.0)
    assert np.abs(s.rope_alpha - a).max() < 1e-3 and np.abs(s.rope_theta - t).max() < 1e-3
    assert np.allclose(s.alpha - s.rope_alpha, off_a) and np.allclose(s.theta - s.rope_theta, off_t)
    assert np.abs(s.alpha - (a + off_a)).max() < 1e-3
    assert np.allclose(s.centres, joint_centres(ACT.robot, s.alpha, s.theta))
    assert np.allclose(s.tension_N, ACT.routing.pretension_N, atol=0.2)
    # the truth's motor zeros (0 here) hold the ropes at pretension with the rope geometry
    # straight, so the description's counts for (a, t) give the rope geometry (a, t) exactly
    # and the physical joints (a, t) + offset: the offset is the kinematic calibration's
    s0 = arm.state(rope_geometry_zero, now=0.0)
    assert np.abs(s0.rope_alpha - a).max() < 1e-3 and np.abs(s0.rope_theta - t).max() < 1e-3
    assert np.abs(s0.alpha - (a + off_a)).max() < 1e-3
    # counts 0 are the rope geometry straight, the links at their offsets; the fixture
    # holds the rope geometry there whatever the motors do
    zero = np.zeros(36, dtype=np.int64)
    assert np.allclose(arm.state(zero, now=0.0).alpha, off_a, atol=1e-6)
    arm.set_fixture(True)
    fixed = arm.state(ideal.counts_from_angles(a, t), now=0.0)
    assert fixed.fixture and not fixed.rope_alpha.any() and not fixed.rope_theta.any()
    assert np.allclose(fixed.alpha, off_a) and np.allclose(fixed.theta, off_t)
    assert np.allclose(fixed.centres, joint_centres(ACT.robot, off_a, off_t))


def test_the_ideal_actuation_puts_the_true_arm_where_commanded() -> None:
    truth = TrueArm.perturbed(ACT, 8)
    arm = SimArm(ACT, truth=truth, noise_N=0.0)
    a = np.full(12, 0.25)
    t = np.full(12, -0.15)
    s = arm.state(truth.ideal_actuation(ACT.robot).counts_from_angles(a, t), now=0.0)
    assert np.abs(s.alpha - a).max() < 1e-3 and np.abs(s.theta - t).max() < 1e-3
    assert np.allclose(s.tension_N, ACT.routing.pretension_N, atol=0.2)
    want = joint_centres(truth.model(ACT.robot), a, t)
    assert np.linalg.norm(s.centres - want, axis=-1).max() < 0.5
    # the description's rope layer misses it by far (+-5000 counts are ~2 mm of rope)
    s0 = arm.state(ACT.counts_from_angles(a, t), now=0.0)
    assert np.abs(s0.alpha - a).max() > 0.02


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 35), st.integers(-20_000, 20_000))
@example(0, 0, 0)
def test_fixture_tension_is_each_ropes_own(seed: int, m: int, delta: int) -> None:
    truth = TrueArm.perturbed(ACT, seed)
    arm = SimArm(ACT, truth=truth, noise_N=0.0)
    arm.set_fixture(True)
    pre = float(ACT.routing.pretension_N)
    z = truth.motor_zero_counts
    at_zero = arm.state(z, now=0.0)
    assert np.allclose(at_zero.tension_N, pre, atol=1e-9)  # the true zero: the pretension
    c = z.copy()
    c[m] += delta
    s = arm.state(c, now=0.0)
    others = np.arange(36) != m
    assert np.array_equal(s.tension_N[others], at_zero.tension_N[others])  # only its own
    # slope EA_true / u per mm of rope wound in (counts_per_mm counts per mm)
    cpm = float(ACT.motors.counts_per_mm[m])
    u = float(arm.unstretched_mm(c)[m])
    F = float(arm.required_free_mm[m])
    want = max(0.0, truth.rope_EA_N[m] * (F - u) / u)
    assert s.tension_N[m] == pytest.approx(want, rel=1e-9, abs=1e-9)
    if delta and want > 0:
        slope = (s.tension_N[m] - pre) / (delta / cpm)
        EA_over_u = truth.rope_EA_N[m] / float(arm.u0_mm[m])
        assert slope == pytest.approx(EA_over_u, rel=0.02)
    assert not s.rope_alpha.any() and not s.rope_theta.any()  # the rope geometry held straight
    assert np.array_equal(s.alpha, truth.alpha_offset_rad)  # the links at their offsets


def test_fixture_zero_tension_within_noise_of_the_pretension() -> None:
    truth = TrueArm.perturbed(ACT, 21)
    arm = SimArm(ACT, truth=truth, noise_N=0.05, seed=3)
    arm.set_fixture(True)
    t = np.array([arm.state(truth.motor_zero_counts, now=0.0).tension_N for _ in range(200)])
    pre = float(ACT.routing.pretension_N)
    assert abs(t.mean() - pre) < 0.01
    assert 0.04 < t.std() < 0.06
    # the description's zero (0 counts) is off by up to 5000 counts: far from the pretension
    off = arm.state(np.zeros(36, dtype=np.int64), now=0.0).tension_N
    assert np.abs(off - pre).max() > 5.0


def test_slack_rope_reads_zero_until_taken_up() -> None:
    m = ACT.motor_ids.index("j05r2")
    slack = np.zeros(36)
    slack[m] = 5.0
    arm = SimArm(ACT, truth=_truth(slack_mm=slack), noise_N=0.0)
    arm.set_fixture(True)
    pre = float(ACT.routing.pretension_N)
    cpm = float(ACT.motors.counts_per_mm[m])
    sign = float(ACT.motors.direction[m])  # counts grow as rope is wound in (direction +1)
    stretch_mm = float(arm.required_free_mm[m] - arm.u0_mm[m])  # ~2.5 mm at 30 N
    onset = 5.0 - stretch_mm  # wound in this far, the rope starts to carry tension
    points = (0.0, onset - 0.2, onset + 0.3, 5.0, 6.0)
    readings = {}
    for mm in points:
        c = np.zeros(36, dtype=np.int64)
        c[m] = round(sign * mm * cpm)
        s = arm.state(c, now=0.0)
        readings[mm] = float(s.tension_N[m])
        assert np.allclose(np.delete(s.tension_N, m), pre)  # the other ropes are not slack
    assert 1.0 < stretch_mm < 4.0
    assert readings[0.0] == readings[onset - 0.2] == 0.0
    assert 0.0 < readings[onset + 0.3] < pre
    assert readings[5.0] == pytest.approx(pre, abs=0.02)  # the slack taken up: the pretension
    u = float(arm.u0_mm[m])
    assert readings[6.0] - readings[5.0] == pytest.approx(arm.stiffness_EA_N[m] / u, rel=0.01)
    # on the free arm a slack rope carries less than the others (it does not pull)
    arm.set_fixture(False)
    free = arm.state(np.zeros(36, dtype=np.int64), now=0.0)
    assert free.tension_N[m] < pre - 5.0


def test_true_EA_sets_the_stretch() -> None:
    ea = np.asarray(ACT.routing.stiffness_EA_N, dtype=float) * 0.8
    arm = SimArm(ACT, truth=_truth(rope_EA_N=ea), noise_N=0.0)
    # the true zero holds every rope at its pretension whatever its EA
    s = arm.state(np.zeros(36, dtype=np.int64), now=0.0)
    assert np.allclose(s.tension_N, ACT.routing.pretension_N)
    # a softer rope gains less tension per mm wound in
    arm.set_fixture(True)
    s = arm.state(np.full(36, 1000, dtype=np.int64), now=0.0)
    stiff = SimArm(ACT, noise_N=0.0)
    stiff.set_fixture(True)
    s2 = stiff.state(np.full(36, 1000, dtype=np.int64), now=0.0)
    pre = float(ACT.routing.pretension_N)
    assert np.allclose((s.tension_N - pre) / (s2.tension_N - pre), 0.8, rtol=0.01)


def test_a_truth_for_another_rope_layer_is_refused() -> None:
    t = TrueArm.nominal(ACT)
    bad = dataclasses.replace(
        t,
        motor_ids=t.motor_ids[:-1],
        rope_EA_N=t.rope_EA_N[:-1],
        motor_zero_counts=t.motor_zero_counts[:-1],
        slack_mm=t.slack_mm[:-1],
    )
    with pytest.raises(SimError, match="motors differ"):
        SimArm(ACT, truth=bad)
