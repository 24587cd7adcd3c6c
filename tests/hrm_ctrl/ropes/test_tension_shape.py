"""The tension-based shape estimate (hrm_ctrl.ropes.tension_shape) on the simulated arm
with its physics: the friction tracked from the commanded travel is the arm's, and the
rope-held pose it reads from the tension board is the arm's within a milliradian where the
feed-forward alone leaves it several off."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.ropes.feedforward import Feedforward, friction_step
from hrm_ctrl.ropes.tension_shape import TensionShape


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-0.2, 0.2), min_size=1, max_size=30))
def test_the_tracked_friction_is_the_simulated_arms(travel: list[float]) -> None:
    """The host's presliding law steps as the box's does (sim_bus.capstan)."""
    from sim_bus.capstan import friction_update

    nu_h = nu_s = np.zeros(1)
    sl_h = sl_s = np.zeros(1, dtype=bool)
    for d in travel:
        du = np.array([d])
        nu_h, sl_h = friction_step(nu_h, sl_h, du, 0.05, 1.5)
        nu_s, sl_s = friction_update(nu_s, sl_s, du, 0.05, 1.5)
        assert nu_h[0] == nu_s[0] and sl_h[0] == sl_s[0]


def _held_pose(effects: str, noise_N: float) -> tuple[float, float, float]:
    """(the estimate's error max, mrad; its mean over the cycles' estimates, mrad; the
    end point of the mean against the arm's, mm) over 30 cycles at a bent pose the
    feed-forward holds (rope-held angles: the play is not the ropes')."""
    from sim_bus.arm import SimArm
    from sim_bus.physics import Physics

    act = load_actuation(default_robot())
    ff = Feedforward.of(act)
    a = np.linspace(0.02, 0.12, 12)
    t = np.linspace(-0.05, 0.03, 12)
    ha, ht = ff.held_angles(a[None], t[None])
    c = ff.counts(a[None], t[None])[0]
    arm = SimArm(act, physics=Physics.of(effects), noise_N=noise_N)
    shape = TensionShape(ff)
    shape.reset(c)
    ga, gt = act.commanded_angles(ha[0], ht[0])
    est, total = 0.0, np.zeros(24)
    for i in range(30):
        s = arm.state(c, 0.01 * i)
        dq = shape.step(c, s.tension_N, ha[0], ht[0])
        assert s.rope_alpha is not None and s.rope_theta is not None
        true = np.empty(24)
        true[0::2], true[1::2] = s.rope_alpha - ga, s.rope_theta - gt
        est = max(est, float(np.abs(dq - true).max()))
        total += dq
    mean = total / 30
    tip = joint_centres(act.robot, ha[0] + mean[0::2], ht[0] + mean[1::2])[-1]
    true_tip = joint_centres(act.robot, s.rope_alpha, s.rope_theta)[-1]
    return 1e3 * est, 1e3 * float(np.abs(mean - true).max()), float(np.linalg.norm(tip - true_tip))


def test_the_shape_of_a_held_pose_with_every_effect() -> None:
    """One cycle's estimate is as good as the tension board's noise (0.05 N: 3 um of
    stretch, about a milliradian in the rope layer's least observable direction); their
    mean over 0.3 s puts the end point within a fifth of a millimetre of the arm's."""
    est, mean, tip_mm = _held_pose("all", 0.05)
    assert est < 2.0, est
    assert mean < 0.3, mean
    assert tip_mm < 0.2, tip_mm


def test_the_shape_under_gravity_alone_without_noise() -> None:
    est, _mean, tip_mm = _held_pose("gravity", 0.0)
    assert est < 0.3, est
    assert tip_mm < 0.1, tip_mm
