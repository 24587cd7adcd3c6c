"""Length -> drum -> counts and back, rope stretch, directions, offsets, ids."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.ropes.motor_map import (
    MotorConfigError,
    rope_tension_N,
    stretched_length_mm,
    unstretched_length_mm,
)
from tests.hrm_ctrl.ropes.rope_helpers import robot_with


def test_counts_per_mm_from_drum_gear_encoder(act: Actuation) -> None:
    expected = 33.0 * 4096.0 / (2 * math.pi * 10.0)
    np.testing.assert_allclose(act.motors.counts_per_mm, expected)
    np.testing.assert_allclose(act.max_rate_counts_per_s, 6000.0 / 60.0 * 4096.0)
    # +-200 mm of drum travel
    np.testing.assert_array_equal(act.counts_max, np.trunc(200.0 * expected))
    np.testing.assert_array_equal(act.counts_min, -np.trunc(200.0 * expected))


def test_shortening_a_rope_winds_counts_up(act: Actuation) -> None:
    a = np.zeros(12)
    a[0] = 0.5  # bend towards +x of the joint frame: rope j01r0 (phi = 0) shortens
    c = act.counts_from_angles(a, np.zeros(12))
    dL = act.rope_lengths(a, np.zeros(12))[0] - act.geometry.straight[0]
    assert dL < -5.0
    u_scale = 1.0 / (1.0 + act.routing.pretension_N / act.routing.stiffness_EA_N[0])
    assert c[0] == round(-dL * u_scale * act.motors.counts_per_mm[0])


def test_lengths_from_counts_round_trip(act: Actuation) -> None:
    rng = np.random.default_rng(2)
    a, t = rng.uniform(-1, 1, 12), rng.uniform(-1, 1, 12)
    for T in (None, 10.0, rng.uniform(5, 80, 36)):
        c = act.counts_from_angles(a, t, T)
        L = act.lengths_from_counts(c, T)
        # quantisation: half a count
        assert np.abs(L - act.rope_lengths(a, t)).max() <= 0.5 / act.motors.counts_per_mm[0] * 1.01


def test_stretch_correction_grows_with_tension_and_free_length(act: Actuation) -> None:
    z = np.zeros(12)
    c0 = act.counts_from_angles(z, z, 0.0)
    c1 = act.counts_from_angles(z, z, 100.0)
    # more tension: the rope stretches more, the drum winds in more
    extra_mm = (c1 - c0) / act.motors.counts_per_mm
    free = act.free_lengths(z, z)
    expected = free / (1 + 0.0 / 30000.0) - free / (1 + 100.0 / 30000.0)
    np.testing.assert_allclose(extra_mm, expected, atol=1.0 / act.motors.counts_per_mm[0])
    assert extra_mm[-1] > extra_mm[0] > 1.5  # longer free length, more stretch


def test_stretch_tension_functions_are_inverse() -> None:
    u = unstretched_length_mm(np.array([800.0, 2500.0]), np.array([10.0, 60.0]), 30000.0)
    np.testing.assert_allclose(
        stretched_length_mm(u, np.array([10.0, 60.0]), 30000.0), [800.0, 2500.0]
    )
    np.testing.assert_allclose(rope_tension_N(np.array([800.0, 2500.0]), u, 30000.0), [10.0, 60.0])
    assert float(rope_tension_N(799.0, 800.0, 30000.0)) == 0.0  # slack


def test_direction_and_offsets() -> None:
    robot = robot_with(motors={"direction": {"j03r1": -1}})
    offsets = {"j03r1": 1000, "j12r2": -5}
    a = load_actuation(robot, offsets)
    base = load_actuation(robot_with())
    x = np.full(12, 0.4), np.full(12, -0.3)
    c, c0 = a.counts_from_angles(*x), base.counts_from_angles(*x)
    i = a.motor_ids.index("j03r1")
    assert c[i] == 1000 - c0[i]
    assert c[-1] == c0[-1] - 5
    assert a.counts_min[i] == 1000 - base.counts_max[i]
    al, _, _ = a.angles_from_counts(c)
    np.testing.assert_allclose(al, x[0], atol=1e-3)


@pytest.mark.parametrize(
    ("motors", "offsets", "match"),
    [
        ({"direction": {"j13r0": -1}}, None, "unknown motor id 'j13r0'"),
        ({"direction": 2}, None, "must be \\+1 or -1"),
        ({"direction": [1] * 35}, None, "36 values"),
        ({"drum_radius_mm": 0.0}, None, "drum_radius_mm"),
        ({"gear_ratio": "x"}, None, "gear_ratio"),
        ({"torque": 1.0}, None, "unknown key 'torque'"),
        ({}, {"j01r9": 3}, "unknown motor id 'j01r9'"),
        ({}, [0] * 35, "expected 36 values"),
        ({}, {"j01r0": 1.5}, "integer count"),
    ],
)
def test_bad_motor_config(motors: dict, offsets: object, match: str) -> None:
    with pytest.raises(RopeError, match=match) as info:
        load_actuation(robot_with(motors=motors), offsets)
    assert "\n" not in str(info.value)
    if offsets is None:
        assert isinstance(info.value, MotorConfigError)


def test_acceleration_and_jerk_limits_default_and_validate(act: Actuation) -> None:
    """``max_accel_rpm_per_s`` / ``max_jerk_rpm_per_s2``: optional (a description without
    them gets 30 000 rpm/s and 600 000 rpm/s^2), per motor in counts, and validated like
    the other keys."""
    np.testing.assert_allclose(act.max_accel_counts_per_s2, 30_000.0 / 60.0 * 4096.0)
    np.testing.assert_allclose(act.max_jerk_counts_per_s3, 600_000.0 / 60.0 * 4096.0)
    assert (
        act.max_accel_counts_per_s2.shape == (36,)
        and not act.max_accel_counts_per_s2.flags.writeable
    )
    own = load_actuation(robot_with(motors={"max_accel_rpm_per_s": 6000.0, "gear_ratio": 10.0}))
    np.testing.assert_allclose(own.max_accel_counts_per_s2, 6000.0 / 60.0 * 4096.0)
    bare = load_actuation(
        robot_with(motors={"max_accel_rpm_per_s": None, "max_jerk_rpm_per_s2": None})
    )
    np.testing.assert_array_equal(bare.max_accel_counts_per_s2, act.max_accel_counts_per_s2)
    for key, value in (
        ("max_accel_rpm_per_s", -1.0),
        ("max_accel_rpm_per_s", float("inf")),
        ("max_jerk_rpm_per_s2", 0.0),
        ("max_jerk_rpm_per_s2", "fast"),
    ):
        with pytest.raises(MotorConfigError, match=rf"\[motors\]\.{key}: "):
            load_actuation(robot_with(motors={key: value}))
