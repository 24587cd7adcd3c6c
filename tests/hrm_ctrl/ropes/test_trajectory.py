"""Time parameterisation of plans (TOPP-RA): every motor within its speed and acceleration
limit in every control cycle, checked on the integer counts by finite differences; from
rest to rest; the tip-speed cap; the return leg."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import RopeError
from hrm_ctrl.kinematics import end_point
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError
from hrm_ctrl.ropes.setpoints import plan_setpoints
from hrm_ctrl.ropes.trajectory import (
    StepPath,
    finite_differences,
    finite_jerk,
    plan_jerk_limits,
    plan_limits,
    step_path,
    time_parameterise,
)

T = 0.01


@cache
def scenario_plan(name: str, step_mm: float = 5.0) -> tuple[np.ndarray, ...]:
    from hrm_ctrl.model import default_robot
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.scenarios import scenario

    sc = scenario(name)
    plan = plan_path(default_robot(), sc.path, PlanOptions(step=step_mm, return_to_start=True), sc)
    return plan.travel, plan.alpha, plan.theta, np.array(plan.phase)


def assert_within(act: Actuation, counts: np.ndarray) -> None:
    """Every motor, every cycle, from rest and to rest: the integers that are sent."""
    c = np.concatenate([counts[:1], counts, counts[-1:]]).astype(np.int64)
    d1 = np.diff(c, axis=0)
    d2 = np.diff(d1, axis=0)
    assert np.all(np.abs(d1) <= act.max_rate_counts_per_s * T), np.abs(d1).max()
    assert np.all(np.abs(d2) <= act.max_accel_counts_per_s2 * T**2), np.abs(d2).max()
    # the jerk: third differences, the first and last rows held twice more
    c3 = np.concatenate([counts[:1], counts[:1], counts[:1], counts, counts[-1:], counts[-1:],
                         counts[-1:]]).astype(np.int64)  # fmt: skip
    d3 = np.diff(c3, n=3, axis=0)
    assert np.all(np.abs(d3) <= act.max_jerk_counts_per_s3 * T**3), np.abs(d3).max()


@pytest.mark.parametrize("name", ["bent-pipe", "cabins"])
@pytest.mark.parametrize("speed", [50.0, 2000.0])
def test_scenario_with_return_within_every_limit(act: Actuation, name: str, speed: float) -> None:
    travel, alpha, theta, phase = scenario_plan(name)
    sp = plan_setpoints(
        act, travel, alpha, theta, phase=list(phase), period_s=T, speed_mm_per_s=speed
    )
    assert_within(act, sp.counts)
    v, a = finite_differences(sp.counts, T)
    assert np.all(v <= act.max_rate_counts_per_s) and np.all(a <= act.max_accel_counts_per_s2)
    # starts and ends at rest, on the first step, and comes back to it
    np.testing.assert_array_equal(sp.counts[0], sp.step_counts[0])
    np.testing.assert_array_equal(sp.counts[-1], sp.step_counts[-1])
    assert np.abs(sp.counts[1] - sp.counts[0]).max() <= act.max_accel_counts_per_s2.max() * T**2
    # the return leg: the far end is passed once, at rest, and the way back is played
    k_far = int(np.flatnonzero(phase == "return")[0]) - 1
    far = np.flatnonzero(sp.sigma_mm == sp.path.distance_mm[k_far])
    assert far.size == 1 and 0.3 * sp.n_cycles < far[0] < 0.7 * sp.n_cycles
    np.testing.assert_array_equal(sp.counts[far[0]], sp.step_counts[k_far])
    assert sp.step_of_row[far[0] + 1] == k_far + 1 and sp.step_of_row[-1] == len(travel) - 1
    # the tip-speed cap: along the path, and the arm's end point itself (forward
    # kinematics of every row's configuration)
    assert np.diff(sp.sigma_mm).max() <= speed * T * (1 + 1e-9)
    a_rows, t_rows = sp.row_angles()
    tip = end_point(act.robot, a_rows, t_rows)
    tip_speed = np.linalg.norm(np.diff(tip, axis=0), axis=1) / T
    assert tip_speed.max() <= speed * 1.001
    if speed == 50.0:  # the cap binds: the duration is the path at the cap, plus the ramps
        at_cap = sp.path.length_mm / speed
        assert at_cap <= sp.duration_s <= at_cap + 0.2
    else:  # the motors bind: one of them near its speed, acceleration or jerk limit, or
        # the path's own third derivative caps the speed (the cabins: 59 % of the jerk)
        j = finite_jerk(sp.counts, T)
        ratio = max((v / act.max_rate_counts_per_s).max(), (a / act.max_accel_counts_per_s2).max(),
                    (j / act.max_jerk_counts_per_s3).max())  # fmt: skip
        assert 0.5 < ratio <= 1.0


def test_rows_are_configurations_of_the_path(act: Actuation) -> None:
    """Every row is the rope layer's counts of one configuration on the path (so the rope
    consistency check sees a consistent reference), and the plan steps are on it."""
    travel, alpha, theta, phase = scenario_plan("cabins")
    path = step_path(travel, alpha, theta, list(phase))
    tr = time_parameterise(act, path, period_s=T, tip_speed_mm_per_s=50.0)
    a, t = path.angles_at(tr.sigma_mm)
    np.testing.assert_array_equal(act.counts_from_angles(a, t), tr.counts)
    a_steps, t_steps = path.angles_at(path.distance_mm)
    np.testing.assert_array_equal(a_steps, alpha)
    np.testing.assert_array_equal(t_steps, theta)
    # the spline through the steps stays close to the straight lines between them
    mid = 0.5 * (path.distance_mm[1:] + path.distance_mm[:-1])
    a_mid, _ = path.angles_at(mid)
    assert np.abs(a_mid - 0.5 * (alpha[1:] + alpha[:-1])).max() < np.deg2rad(0.5)
    assert tr.leg_rows[0][1] == tr.leg_rows[1][0] and tr.leg_rows[-1][1] == tr.n_rows - 1
    assert np.all(np.diff(tr.step_time_s) > 0) and tr.step_time_s[-1] == tr.duration_s


def test_step_times_match_the_rows(act: Actuation) -> None:
    travel, alpha, theta, phase = scenario_plan("bent-pipe", 10.0)
    sp = plan_setpoints(
        act, travel, alpha, theta, phase=list(phase), period_s=T, speed_mm_per_s=50.0
    )
    # where the rows are at each step's time, by linear interpolation of the rows
    at = np.interp(sp.step_time_s, sp.time_s, sp.sigma_mm)
    assert np.abs(at - sp.path.distance_mm).max() < 50.0 * T / 4


def small_path(n: int = 6, deg: float = 20.0) -> StepPath:
    a = np.deg2rad(deg) * np.sin(np.linspace(0, 2, n))[:, None] * np.ones((1, 12))
    return step_path(5.0 * np.arange(n), a, -a / 3)


def with_limits(act: Actuation, v: float, a: float) -> Actuation:
    n = act.n_motors
    return dataclasses.replace(
        act, max_rate_counts_per_s=np.full(n, v), max_accel_counts_per_s2=np.full(n, a)
    )


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    v=st.floats(2_000.0, 500_000.0),
    a=st.floats(5e4, 5e7),
    speed=st.floats(1.0, 2000.0),
    deg=st.floats(1.0, 40.0),
)
@example(v=2_000.0, a=5e4, speed=2000.0, deg=40.0)  # the slowest motors, the fastest cap
@example(v=500_000.0, a=5e7, speed=1.0, deg=1.0)  # the cap alone binds
def test_random_limits_hold_on_the_integers(
    act: Actuation, v: float, a: float, speed: float, deg: float
) -> None:
    lim = with_limits(act, v, a)
    tr = time_parameterise(lim, small_path(deg=deg), period_s=T, tip_speed_mm_per_s=speed)
    assert_within(lim, tr.counts)
    assert np.diff(tr.sigma_mm).max() <= speed * T * (1 + 1e-9)
    assert tr.sigma_mm[0] == 0.0 and tr.sigma_mm[-1] == 25.0


@settings(
    max_examples=20,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    v=st.floats(20_000.0, 500_000.0),
    a=st.floats(2e5, 5e7),
    j=st.floats(5e6, 1e9),
    speed=st.floats(5.0, 2000.0),
    deg=st.floats(1.0, 40.0),
    n=st.integers(2, 9),
)
@example(v=409_600.0, a=2.048e6, j=5e6, speed=2000.0, deg=40.0, n=9)  # the softest jerk
def test_random_plans_and_jerk_limits_hold_on_the_integers(
    act: Actuation, v: float, a: float, j: float, speed: float, deg: float, n: int
) -> None:
    """Random plans (steps, bend) and motor limits: speed, acceleration and jerk of every
    motor in every cycle within the limits on the integers, the tip within its cap, and
    the jerk bound's cost what is reported."""
    lim = dataclasses.replace(
        with_limits(act, v, a), max_jerk_counts_per_s3=np.full(act.n_motors, j)
    )
    tr = time_parameterise(lim, small_path(n, deg), period_s=T, tip_speed_mm_per_s=speed)
    assert_within(lim, tr.counts)
    assert np.diff(tr.sigma_mm).max() <= speed * T * (1 + 1e-9)
    assert tr.sigma_mm[0] == 0.0 and tr.sigma_mm[-1] == 5.0 * (n - 1)
    assert tr.law_duration_s > 0.0 and tr.jerk_cost_s == tr.duration_s - tr.law_duration_s
    assert all(w > 0.0 for w in tr.jerk_window_s)


def test_a_plan_over_the_jerk_limit_is_refused_naming_step_and_motor(
    act: Actuation, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The check of the integers catches a time law that breaks the jerk limit (here
    TOPP-RA's own, without the jerk bound: 2.7 times the limit along the bent pipe): one
    line naming the plan steps and the motor."""
    import functools

    from hrm_ctrl.ropes import setpoints

    travel, alpha, theta, phase = scenario_plan("bent-pipe")
    unbounded = functools.partial(time_parameterise, jerk_limited=False)
    monkeypatch.setattr(setpoints, "time_parameterise", unbounded)
    with pytest.raises(RopeLimitError) as info:
        plan_setpoints(act, travel, alpha, theta, phase=list(phase), period_s=T,
                       speed_mm_per_s=50.0, where="bent.json")  # fmt: skip
    msg = str(info.value)
    assert msg.startswith("bent.json: plan step") and "\n" not in msg
    assert ": motor j" in msg and "counts/s^3, more than the motor's 4.096e+07 counts/s^3" in msg


def test_limits_too_small_for_whole_counts_are_refused(act: Actuation) -> None:
    with pytest.raises(RopeLimitError, match=r"leave no motion in whole counts at a 0\.01 s"):
        plan_limits(with_limits(act, 400_000.0, 15_000.0), T)
    v, a = plan_limits(act, T)
    assert np.all(v < act.max_rate_counts_per_s) and np.all(a < act.max_accel_counts_per_s2)
    soft = dataclasses.replace(act, max_jerk_counts_per_s3=np.full(act.n_motors, 3.9e6))
    with pytest.raises(RopeLimitError, match=r"jerk limit of 3\.9e\+06 counts/s\^3 leaves no"):
        plan_jerk_limits(soft, T)
    assert np.all(plan_jerk_limits(act, T) < act.max_jerk_counts_per_s3)


def test_one_step_is_one_row_and_too_many_rows_are_refused(act: Actuation) -> None:
    one = step_path([3.0], np.zeros((1, 12)), np.zeros((1, 12)))
    tr = time_parameterise(act, one, period_s=T, tip_speed_mm_per_s=10.0)
    assert tr.n_rows == 1 and tr.duration_s == 0.0
    with pytest.raises(RopeError, match="more than the 10 a playback may have"):
        time_parameterise(act, small_path(), period_s=T, tip_speed_mm_per_s=10.0, max_rows=10)
