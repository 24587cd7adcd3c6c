"""The EKF converges on noisy feedback of a moving arm and flags an offset rope."""

from __future__ import annotations

import numpy as np
import pytest

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.estimator import RopeStateEstimator

DT = 0.01


def truth(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = k * DT
    ph = np.arange(12)
    a = 0.5 * np.sin(0.5 * t + 0.3 * ph)
    th = 0.4 * np.cos(0.4 * t + 0.2 * ph)
    return a, th, 0.25 * np.cos(0.5 * t + 0.3 * ph), -0.16 * np.sin(0.4 * t + 0.2 * ph)


def run(act: Actuation, steps: int, fault: tuple[str, float, int] | None = None, seed: int = 3):
    rng = np.random.default_rng(seed)
    est = RopeStateEstimator(act, rate_hz=1.0 / DT, count_noise=3.0)
    a, t, _, _ = truth(0)
    noise = lambda: rng.normal(0.0, 3.0, act.n_motors).round().astype(np.int64)  # noqa: E731
    est.initialise(act.counts_from_angles(a, t) + noise())
    outs = []
    for k in range(1, steps):
        a, t, _, _ = truth(k)
        c = act.counts_from_angles(a, t) + noise()
        if fault is not None and k >= fault[2]:
            c[act.motor_ids.index(fault[0])] += round(fault[1] * act.motors.counts_per_mm[0])
        outs.append((k, est.update(c)))
    return outs


def test_converges_on_noisy_feedback_and_tracks_rates(act: Actuation) -> None:
    outs = run(act, 300)
    for k, out in outs[150:]:
        a, t, ra, rt = truth(k)
        assert np.abs(out.alpha - a).max() < 1e-3
        assert np.abs(out.theta - t).max() < 1e-3
        assert out.flagged == () and out.flagged_joint is None
    k, out = outs[-1]
    _, _, ra, rt = truth(k)
    assert np.abs(out.alpha_rate - ra).max() < 0.05
    assert np.abs(out.theta_rate - rt).max() < 0.05
    assert out.consistency.max() < 2.0


def test_starts_from_a_wrong_guess_and_converges(act: Actuation) -> None:
    est = RopeStateEstimator(act)
    a, t, _, _ = truth(0)
    c = act.counts_from_angles(a, t)
    est.initialise(act.counts_from_angles(a + 0.05, t - 0.05))
    for _ in range(60):
        out = est.update(c)
    assert np.abs(out.alpha - a).max() < 1e-3


@pytest.mark.parametrize("offset_mm", [1.0, -2.0])
def test_flags_the_joint_of_an_offset_rope(act: Actuation, offset_mm: float) -> None:
    outs = run(act, 160, fault=("j05r1", offset_mm, 100))
    before = [o for k, o in outs if k < 100]
    after = [o for k, o in outs if k >= 102]
    assert all(o.flagged == () for o in before)
    assert all(o.flagged_joint == 5 for o in after)
    assert all("j05r1" in o.flagged for o in after)
    assert all(set(o.flagged) <= {"j05r0", "j05r1", "j05r2"} for o in after)


def test_four_ropes_name_the_faulty_rope_pair(act4: Actuation) -> None:
    outs = run(act4, 140, fault=("j08r2", 1.0, 100))
    after = [o for k, o in outs if k >= 102]
    assert all(o.flagged_joint == 8 and "j08r2" in o.flagged for o in after)
    assert all(len(o.flagged) <= 2 for o in after)


def test_bad_use(act: Actuation) -> None:
    est = RopeStateEstimator(act)
    with pytest.raises(RopeError, match="initialise"):
        est.update(np.zeros(36, dtype=np.int64))
    with pytest.raises(RopeError, match="rate_hz"):
        RopeStateEstimator(act, rate_hz=0.0)
    with pytest.raises(RopeError, match="model_noise_mm"):
        RopeStateEstimator(act, model_noise_mm=float("nan"))
    est.initialise(np.zeros(36, dtype=np.int64))
    with pytest.raises(RopeError, match="36 motor counts"):
        est.update(np.zeros(35, dtype=np.int64))
