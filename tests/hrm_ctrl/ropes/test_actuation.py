"""Limits: joint angles, drum travel, motor speed; refusals name step, joint and rope."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError, load_actuation
from hrm_ctrl.ropes.inverse import RopeInverseError
from tests.hrm_ctrl.ropes.rope_helpers import robot_with


def test_contract_attributes(act: Actuation) -> None:
    assert act.n_motors == 36 and len(act.motor_ids) == 36
    assert act.motor_ids[0] == "j01r0" and act.motor_ids[-1] == "j12r2"
    assert act.joint_of_motor.tolist() == [k for k in range(12) for _ in range(3)]
    for arr in (act.counts_min, act.counts_max):
        assert arr.dtype == np.int64 and arr.shape == (36,)
    assert np.all(act.counts_min < 0) and np.all(act.counts_max > 0)
    assert act.max_rate_counts_per_s.shape == (36,)
    with pytest.raises(ValueError):
        act.counts_min[0] = 5  # read-only


def test_zero_offsets_shift_counts_and_limits() -> None:
    a = load_actuation(robot_with(), np.arange(36) * 100)
    c = a.counts_from_angles(np.zeros(12), np.zeros(12))
    assert c.tolist() == (np.arange(36) * 100).tolist()
    assert a.counts_max[5] - 500 == load_actuation(robot_with()).counts_max[5]


@pytest.mark.parametrize(
    ("joint", "name", "value"),
    [
        (3, "alpha", np.nan),
        (7, "theta", np.deg2rad(60.0)),
        (11, "alpha", -1.2),
        (0, "theta", np.inf),
    ],
)
def test_bad_angles_are_refused_naming_the_joint(
    act: Actuation, joint: int, name: str, value: float
) -> None:
    a, t = np.zeros(12), np.zeros(12)
    (a if name == "alpha" else t)[joint] = value
    with pytest.raises(RopeLimitError, match=f"joint {joint + 1}: {name}"):
        act.counts_from_angles(a, t)


def test_bad_angles_in_a_table_name_the_step(act: Actuation) -> None:
    a, t = np.zeros((5, 12)), np.zeros((5, 12))
    t[3, 9] = 1.1
    with pytest.raises(RopeLimitError, match="step 3: joint 10: theta"):
        act.counts_from_angles(a, t)


def test_check_counts_position_limit_names_motor_and_step(act: Actuation) -> None:
    table = np.zeros((4, 36), dtype=np.int64)
    table[2, 7] = act.counts_max[7] + 1
    with pytest.raises(RopeLimitError, match=r"step 2: motor j03r1 \(joint 3, rope 1\)"):
        act.check_counts(table)
    single = np.zeros(36, dtype=np.int64)
    single[0] = act.counts_min[0] - 1
    with pytest.raises(RopeLimitError, match="motor j01r0") as info:
        act.check_counts(single)
    assert "step" not in str(info.value)
    act.check_counts(np.stack([act.counts_min, act.counts_max]))  # limits themselves are fine


def test_check_counts_rate(act: Actuation) -> None:
    prev = np.zeros(36, dtype=np.int64)
    nxt = prev.copy()
    nxt[30] = int(act.max_rate_counts_per_s[30] * 0.01) + 2
    with pytest.raises(RopeLimitError, match=r"motor j11r0.*faster"):
        act.check_counts(nxt, previous=prev, dt_s=0.01)
    act.check_counts(nxt, previous=prev, dt_s=0.02)
    table = np.stack([prev, prev, nxt])
    with pytest.raises(RopeLimitError, match="step 2: motor j11r0"):
        act.check_counts(table, dt_s=0.01)
    with pytest.raises(RopeError, match="dt_s"):
        act.check_counts(table, dt_s=0.0)
    with pytest.raises(RopeError, match="dt_s"):
        act.check_counts(table, dt_s=[0.01])


def test_drum_travel_limit_refuses_a_configuration() -> None:
    small = load_actuation(robot_with(motors={"travel_in_mm": 20.0, "travel_out_mm": 20.0}))
    a, t = np.zeros(12), np.zeros(12)
    a[:] = 0.5  # every joint bent the same way: ropes near phi = 0 shorten by ~5 mm per joint
    with pytest.raises(RopeLimitError, match=r"motor j\d\dr\d .*outside.*drum travel 20 mm in"):
        small.counts_from_angles(a, t)
    small.counts_from_angles(a, t, check=False)  # the caller may opt out (e.g. a simulator)
    # the default drum fits the whole joint range
    big = load_actuation(robot_with())
    lim = np.deg2rad(59.99)
    corners = np.array([[sa, tt] for sa in (-lim, lim) for tt in (-lim, lim)])
    for sa, tt in corners:
        big.counts_from_angles(np.full(12, sa), np.full(12, tt))


def test_bad_tension(act: Actuation) -> None:
    with pytest.raises(RopeError, match="tension"):
        act.counts_from_angles(np.zeros(12), np.zeros(12), -1.0)
    with pytest.raises(RopeError, match="tension"):
        act.angles_from_counts(np.zeros(36, dtype=np.int64), np.nan)


angles = st.lists(st.floats(-0.87, 0.87), min_size=24, max_size=24)  # within +-50 deg


#: A move of one rope this small (0.47 mm of rope) keeps the model's answer near its first
#: order, where winding a rope in cannot lower its tension (nor paying it out raise it).
SMALL_MOVE_COUNTS = 1000
#: Over larger moves the least-misfit pose can swing through a joint whose other two ropes
#: pull nearly opposite (a rope singularity of the 3-rope joint, e.g. joint 8 at alpha 29
#: deg, theta -43 deg): there the rope's tension stays where it was, within this much (N;
#: -0.21 N the worst of about 30 000 random moves of up to 6000 counts).
LARGE_MOVE_SLACK_N = 1.0

_J8_NEAR_SINGULAR = [0.0] * 7 + [0.5] + [0.0] * 11 + [-0.75] + [0.0] * 4


@settings(max_examples=25, deadline=None)
@given(q=angles, motor=st.integers(0, 35), delta=st.integers(-6000, 6000))
@example(q=[0.0] * 24, motor=0, delta=-2000)
@example(q=_J8_NEAR_SINGULAR, motor=21, delta=3741)  # found by Hypothesis: tension unchanged
@example(  # found by Hypothesis: the counts have no pose within the model (no convergence)
    q=[0.0] * 7 + [0.703125] + [0.0] * 11 + [-0.75] + [0.0] * 4, motor=21, delta=5288
)
@example(q=_J8_NEAR_SINGULAR, motor=21, delta=SMALL_MOVE_COUNTS)
def test_modelled_tensions(act: Actuation, q: list[float], motor: int, delta: int) -> None:
    """Counts made from angles carry the pretension on every rope; paying one rope out
    lowers its tension (winding it in raises it), never below 0 N, over small moves; over
    large ones the tension moves that way or stays (a rope singularity), and the model may
    find no pose at all (RopeInverseError); the pose the model
    finds is the one the counts were made from."""
    a, t = np.array(q[:12]), np.array(q[12:])
    c = act.counts_from_angles(a, t)
    alpha, theta, tension = act.tensions_from_counts(c)
    assert np.abs(tension - act.routing.pretension_N).max() < 0.1
    assert np.abs(alpha - a).max() < 1e-4 and np.abs(theta - t).max() < 1e-4
    moved = c.copy()
    moved[motor] += delta
    small = abs(delta) <= SMALL_MOVE_COUNTS
    try:
        after = act.tensions_from_counts(moved, alpha, theta)[2]  # warm: as the box does
    except RopeInverseError:
        assert not small, "no pose for a small move of one rope"
        return
    assert (after >= 0.0).all()
    wound_in = delta * int(act.motors.direction[motor]) > 0
    if delta != 0 and after[motor] > 0.0:
        gain = (after[motor] - tension[motor]) * (1.0 if wound_in else -1.0)
        if small:
            assert gain > -1e-3, (after[motor], tension[motor])
        else:
            assert gain > -LARGE_MOVE_SLACK_N, (after[motor], tension[motor])


@settings(max_examples=30, deadline=None)
@given(joint=st.integers(0, 11), theta=st.booleans(), eps_deg=st.floats(1e-7, 1e-2))
@example(joint=0, theta=False, eps_deg=1e-6)  # the red-team's 59.999999 deg: 60.0014 sent
def test_whole_counts_never_cross_a_joint_limit(
    act: Actuation, joint: int, theta: bool, eps_deg: float
) -> None:
    """Angles just inside a joint limit: either their rounded counts map back inside the
    limits, or ``rounded_outside`` names the row (a plan with it is refused)."""
    q = np.zeros((2, 24))
    q[1, 12 * theta + joint] = math.radians(60.0 - eps_deg)
    a, t = q[:, :12], q[:, 12:]
    c = act.counts_from_angles(a, t)
    back_a, back_t, _res = act.angles_from_counts(c, None, a, t)
    inside = bool((np.abs(back_a) < act.robot.limit_alpha).all()) and bool(
        (np.abs(back_t) < act.robot.limit_theta).all()
    )
    out = act.rounded_outside(c, a, t)
    assert (out is None) == inside, out
    if out is not None:
        assert out[0] == 1 and f"joint {joint + 1}: " in out[1]
