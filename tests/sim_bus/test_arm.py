"""The simulated arm against the rope layer's forward map and the planner's FK."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hrm_ctrl.errors import SimError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from sim_bus.arm import SimArm

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
