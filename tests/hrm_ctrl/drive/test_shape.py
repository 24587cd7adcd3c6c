"""Shape feedback (:mod:`hrm_ctrl.drive.shape`): the rope estimator on the feedback a
simulated arm gives (its counts and its tension board's tensions) sees the arm on the
trail where the arm is on it, and off it by what the arm really sags where the arm's
physics (gravity, ``sim_bus.physics``) pulls it off; the watch thread samples only once
the drive has begun."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hrm_ctrl.drive.command import SteerCommand, SteerLimits
from hrm_ctrl.drive.shape import ShapeFeedback, ShapeWatch, point_to_polyline
from hrm_ctrl.drive.start import DriveStart, start_driver
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from sim_bus.arm import SimArm
from sim_bus.physics import Physics

T = 0.01


def _drive_with_feedback(physics: Physics | None) -> list[tuple[float, float]]:
    """2.5 s into the bent pipe at 20 mm/s on the model; every 0.1 s the simulated arm's
    state at the step's counts (its tensions with the board's noise) into the shape
    feedback: (estimated tip off the trail, true tip off the trail) per sample, mm."""
    act = load_actuation(default_robot())
    arm = SimArm(act, physics=physics)
    drv = start_driver(act.robot, DriveStart(scenario="bent-pipe"), SteerLimits(), T)
    fb = ShapeFeedback(act, rate_hz=10.0)
    out = []
    for k in range(250):
        drv.cycle(SteerCommand(0.0, 0.0, 20.0))
        if k % 10 == 9:
            p = drv.planner
            counts = act.counts_from_angles(p.alpha, p.theta)
            state = arm.state(counts, k * T)
            trail = np.array(p.trail.points)
            s = fb.update(counts, state.tension_N, p.alpha, p.theta, trail, p.travel)
            assert s.tensions
            out.append((s.tip_from_trail_mm, point_to_polyline(state.centres[-1], trail)))
    return out


def test_the_arm_on_the_trail_is_seen_on_it() -> None:
    got = np.array(_drive_with_feedback(None))
    assert got[:, 1].max() < 0.05  # the simulated arm is where its ropes put it
    # the estimate: within the tension board's noise (0.05 N) through the ropes' stretch
    assert got[:, 0].max() < 0.5, got[:, 0]


def test_an_arm_sagging_under_gravity_is_seen_off_the_trail() -> None:
    got = np.array(_drive_with_feedback(Physics.of("gravity")))
    assert got[:, 1].min() > 100.0  # held out horizontally, the arm sags: the true tip
    # the estimator sees it from the tensions (the ropes that hold the arm up stretch)
    assert got[:, 0].min() > 100.0
    assert np.abs(got[:, 0] - got[:, 1]).max() < 5.0, got


def test_the_watch_samples_only_once_the_drive_has_begun() -> None:
    act = load_actuation(default_robot())
    a, t = np.full(12, 0.05), np.full(12, -0.02)
    counts = act.counts_from_angles(a, t)
    shape = ShapeFeedback(act)
    trail = shape.centres(a, t)[-2:]
    driving: list[bool] = [False]

    def plan() -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        return (a, t, trail, 10.0) if driving[0] else None

    watch = ShapeWatch(lambda: (counts, None), plan, shape, period_s=0.01)
    assert watch.sample() is None and watch.samples == 0  # the lead-in: nothing compared
    driving[0] = True
    watch.start()
    deadline = time.monotonic() + 30.0
    while watch.samples < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    watch.stop()
    assert not watch.is_alive()
    s = watch.summary()
    assert s["samples"] >= 3 and s["error"] is None and s["tensions"] is False
    assert s["tip_from_trail_mm"]["max"] < 0.05 and s["shape_mm"]["max"] < 0.05
    assert watch.last is not None
    assert "off the trail" in watch.last.line()


@pytest.mark.parametrize(
    ("p", "want"),
    [((1.0, 1.0, 0.0), 1.0), ((-3.0, 4.0, 0.0), 5.0), ((5.0, 0.0, 2.0), 2.0)],
)
def test_point_to_polyline(p: tuple[float, float, float], want: float) -> None:
    pts = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [6.0, 0.0, 0.0]])
    assert point_to_polyline(np.array(p), pts) == pytest.approx(want)
