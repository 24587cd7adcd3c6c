"""The drive as a setpoint source (:class:`hrm_ctrl.drive.stream.DriveSource`), played as
the session plays it (start from the drives' positions, then slot after slot), without a
box: a wall ahead refuses a step and the motors stop from the speed they have within
their speed, acceleration and jerk limits, then hold, and the source ends."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.safety.limits import SetpointError
from hrm_ctrl.drive.command import SteerCommand, SteerLimits
from hrm_ctrl.drive.driver import Driver
from hrm_ctrl.drive.online import OnlineOptions, OnlinePlanner
from hrm_ctrl.drive.stream import DriveSource
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.environment import Box, Environment
from hrm_ctrl.ropes.actuation import load_actuation

T = 0.01
ENTRY = np.array([1200.0, 100.0, 300.0])


def played(src: DriveSource, actual: np.ndarray) -> np.ndarray:
    src.precheck(T)
    src.start(actual, T)
    rows = []
    k = 0
    while (row := src.setpoint(k)) is not None:
        rows.append(row.copy())
        k += 1
        assert k < src.n_cycles
    return np.array(rows)


def test_a_wall_ahead_stops_the_motors_within_their_limits_and_holds() -> None:
    act = load_actuation(default_robot())
    wall = Box(np.array([1240.0, 100.0, 300.0]), np.array([10.0, 200.0, 200.0]))
    trail = Trail.starting_at(ENTRY, np.array([1.0, 0.0, 0.0]))
    planner = OnlinePlanner(act.robot, trail, Environment((wall,)), OnlineOptions())
    drv = Driver(planner, SteerLimits(), T)
    src = DriveSource(drv, act, lambda t: SteerCommand(0.0, 0.0, 20.0), 5.0)
    straight = act.counts_from_angles(np.zeros(12), np.zeros(12))
    rows = played(src, straight)
    assert src.refusals and "link 12 would come" in src.refusals[0][1]
    assert src.stop_reason == src.refusals[0][1]
    # the tip (radius 15 mm) stopped short of the wall's face at x = 1235 (1 mm margin)
    assert 1235.0 - 15.0 - 1.0 - 1.0 < planner.tip[0] < 1235.0 - 15.0
    seq = np.vstack([np.repeat(straight[None, :], 3, axis=0), rows]).astype(np.float64)
    assert np.all(np.abs(np.diff(seq, axis=0)) <= act.max_rate_counts_per_s * T)
    assert np.all(np.abs(np.diff(seq, n=2, axis=0)) <= act.max_accel_counts_per_s2 * T**2)
    assert np.all(np.abs(np.diff(seq, n=3, axis=0)) <= act.max_jerk_counts_per_s3 * T**3)
    # it was moving when refused, stopped, and held at rest to the end
    moving = np.flatnonzero(np.abs(np.diff(rows, axis=0)).max(axis=1) > 0)
    assert moving[-1] + 1 < rows.shape[0] - round(0.2 / T)
    assert src.cycles < round(5.0 / T)  # no online step after the refusal
    # the stop's overshoot past the last configuration sent is small (rope mm)
    last_planned = act.counts_from_angles(planner.alpha, planner.theta)
    overshoot_mm = np.abs(rows[-1] - last_planned) / act.motors.counts_per_mm
    assert overshoot_mm.max() < 1.0


def test_a_driver_for_another_period_is_refused_before_anything_is_sent() -> None:
    act = load_actuation(default_robot())
    trail = Trail.starting_at(ENTRY, np.array([1.0, 0.0, 0.0]))
    drv = Driver(OnlinePlanner(act.robot, trail), SteerLimits(), 0.05)
    src = DriveSource(drv, act, lambda t: SteerCommand(), 1.0)
    with pytest.raises(SetpointError, match=r"driver's period is 0\.05 s"):
        src.precheck(T)


def test_the_setpoints_keep_the_tip_on_the_trail_through_the_first_bend() -> None:
    """The shaping smooths every motor alike: the arm the setpoints make (the rope
    inverse of each setpoint) has its tip on the trail, every motor within its limits.
    (Ruckig alone, each motor chasing the online step, put it up to 4.3 mm off.)"""
    from hrm_ctrl.drive.script import KeyScript, bent_pipe_keys
    from hrm_ctrl.drive.shape import point_to_polyline
    from hrm_ctrl.drive.start import DriveStart, start_driver
    from hrm_ctrl.kinematics import end_point

    act = load_actuation(default_robot())
    limits = SteerLimits(pitch_rate_rad_s=0.2)
    keys = KeyScript.parse(bent_pipe_keys(limits), "bent pipe keys")
    drv = start_driver(act.robot, DriveStart(scenario="bent-pipe"), limits, T)
    end_s = 14.0  # 270 mm: the first bend and some of the straight after it
    src = DriveSource(drv, act, lambda t: keys.command_at(t, limits), end_s)
    rows = played(src, act.counts_from_angles(np.zeros(12), np.zeros(12)))
    assert src.refusals == [] and drv.planner.travel > 250.0
    body = rows[src.n_lead_in :: 5].astype(np.float64)
    alpha, theta, _ = act.angles_from_counts(body)
    tips = end_point(act.robot, alpha, theta)
    trail = np.array(drv.planner.trail.points)
    off = max(point_to_polyline(p, trail) for p in tips)
    assert off < 0.1, off
    seq = rows.astype(np.float64)
    assert np.all(np.abs(np.diff(seq, axis=0)) <= act.max_rate_counts_per_s * T)
    assert np.all(np.abs(np.diff(seq, n=2, axis=0)) <= act.max_accel_counts_per_s2 * T**2)
    assert np.all(np.abs(np.diff(seq, n=3, axis=0)) <= act.max_jerk_counts_per_s3 * T**3)
