"""The feed-forward compensation (hrm_ctrl.ropes.feedforward): its statics against a hand
case, the plan -> counts path with and without it, and the compensated bent pipe on the
simulated arm with its physics (stepped on the simulated clock, every control cycle)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import RobotModel, default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.ropes.feedforward import Feedforward, FeedforwardError, arm_physics
from hrm_ctrl.ropes.setpoints import plan_setpoints

G = 9.81


def robot_with(physics: dict[str, Any]) -> RobotModel:
    m = default_robot()
    return dataclasses.replace(m, tables={**m.tables, "physics": physics})


def test_one_weight_held_by_hand() -> None:
    """A 100 g payload at the tip of the straight, level arm, nothing else: gravity pulls
    every alpha down by the payload's moment about its joint, ``m g (L - x_j)``.  At the
    straight arm a rope at hole angle phi, radius r, lengthens by ``-r cos(phi)`` per
    radian of alpha at every joint it crosses, and the hole's ``cos(phi)`` side is up
    (the link's x axis is the world's +z).  Taking each joint's equation minus the next
    one's, a joint's own three ropes (120 deg apart: sum cos^2 = 3/2, sum cos sin = 0)
    carry the moment of the payload over their own link, ``m g l_j``; the tensions
    nearest the pretension are then ``T = T0 + (2/3) cos(phi) m g l_j / r``.  Each rope
    is wound in by its extra stretch, ``F (1/(1 + T0/EA) - 1/(1 + T/EA))``."""
    mass = 0.1
    act = load_actuation(
        robot_with({"link_mass_kg": 0.0, "payload_kg": mass, "mu_kinetic": 0.0,
                    "backlash_deg": 0.0})
    )  # fmt: skip
    ff = Feedforward.of(act)
    z = np.zeros((1, 12))
    h = ff.holding(z, z)
    links = act.robot.links
    x = np.concatenate([[0.0], np.cumsum(links)[:-1]])  # joint centres along the arm
    hand_Q = -mass * G * (links.sum() - x)
    assert np.allclose(h.gravity_Nmm[0, 0::2], hand_Q, rtol=1e-9)
    assert np.allclose(h.gravity_Nmm[0, 1::2], 0.0, atol=1e-9)
    rt = act.routing
    j = rt.joint_of_rope
    hand_T = rt.pretension_N + (2.0 / 3.0) * np.cos(rt.hole_angle) * mass * G * links[j] / 12.0
    assert np.allclose(h.tension_N[0], hand_T, atol=1e-6)
    free = act.free_lengths(z[0], z[0])
    EA = rt.stiffness_EA_N
    wound_in = free / (1 + rt.pretension_N / EA) - free / (1 + hand_T / EA)
    plain = act.counts_from_angles(z[0], z[0])
    counts = ff.counts(z, z)[0]
    cpm = act.motors.counts_per_mm
    assert np.abs(counts - plain - np.rint(cpm * wound_in)).max() <= 1
    assert int(np.abs(counts - plain).max()) > 1000  # half a millimetre and more: it acts


def test_the_tensions_hold_the_pose_within_the_command_band() -> None:
    act = load_actuation(default_robot())
    ff = Feedforward.of(act, capstan=False, backlash=False)
    rng = np.random.default_rng(3)
    a = rng.uniform(-0.5, 0.5, (20, 12))
    t = rng.uniform(-0.5, 0.5, (20, 12))
    h = ff.holding(a, t)
    low, high = act.command_tension_N
    assert h.tension_N.min() >= low - 1e-6 and h.tension_N.max() <= high + 1e-6
    from hrm_ctrl.ropes.length import lengths_and_jacobian

    _L, J, _s = lengths_and_jacobian(act.geometry, *act.commanded_angles(a, t))
    moments = np.einsum("bnk,bn->bk", J, h.tension_N - act.routing.pretension_N)
    assert np.abs(moments - h.gravity_Nmm).max() < 0.05  # N mm: the equilibrium holds


def test_a_misspelt_physics_key_is_refused_when_the_description_loads(tmp_path: Any) -> None:
    from hrm_ctrl.errors import RobotDescriptionError
    from hrm_ctrl.model import load_robot

    p = tmp_path / "robot.toml"
    text = (
        resources_text()
        .replace("# [physics]", "[physics]")
        .replace("# payload_kg = 0.020", "payload_kgs = 0.020")
    )
    p.write_text(text)
    with pytest.raises(RobotDescriptionError, match=r"\[physics\]: unknown key 'payload_kgs'"):
        load_robot(p)
    p.write_text(text.replace("payload_kgs", "payload_kg"))
    assert arm_physics(load_robot(p)).payload_kg == 0.02  # the shipped comment, as a table


def resources_text() -> str:
    from importlib import resources

    return resources.files("hrm_ctrl.data").joinpath("robot.toml").read_text()


def test_a_bad_physics_table_is_one_line_naming_the_key() -> None:
    with pytest.raises(FeedforwardError, match=r"\[physics\]: mu_kinetic must be"):
        arm_physics(robot_with({"mu_kinetic": [0.1] * 5}))
    with pytest.raises(FeedforwardError, match=r"\[physics\]: unknown key 'mass'"):
        arm_physics(robot_with({"mass": 1.0}))
    with pytest.raises(FeedforwardError, match="gravity_dir must not be the zero vector"):
        arm_physics(robot_with({"gravity_dir": [0, 0, 0]}))


def out_and_back(act: Actuation, feedforward: Feedforward | None) -> Any:
    a = np.zeros((3, 12))
    a[1] = 0.2
    return plan_setpoints(act, [0.0, 20.0, 0.0], a, -a, period_s=0.01, speed_mm_per_s=50.0,
                          phase=["in", "in", "return"], feedforward=feedforward)  # fmt: skip


def test_no_compensation_unless_asked() -> None:
    act = load_actuation(default_robot())
    plain = out_and_back(act, None)
    a, t = plain.row_angles()
    assert np.array_equal(plain.counts, act.counts_from_angles(a, t))  # the pretension's
    comp = out_and_back(act, Feedforward.of(act))
    ca, ct = comp.row_angles()
    assert np.abs(comp.counts - act.counts_from_angles(ca, ct)).max() > 500  # it does act
    assert comp.n_cycles > plain.n_cycles + 100  # a share of the limits and a 1 s ramp-in
    assert np.array_equal(comp.counts[0], plain.counts[0])  # a lead-in goes to the plain
    assert np.abs(np.concatenate([ca[0] - a[0], ct[0] - t[0]])).max() == 0.0


def test_hrm_run_compensates_only_with_the_flag(tmp_path: Any) -> None:
    import argparse

    from hrm_ctrl.cli import run as run_cli

    p = argparse.ArgumentParser()
    run_cli.register(p)
    assert p.parse_args(["plan.json", "--sim"]).compensate is False
    assert p.parse_args(["plan.json", "--sim", "--compensate"]).compensate is True


@pytest.mark.slow
def test_the_compensated_bent_pipe_on_the_physical_arm() -> None:
    """The bent pipe there and back (the demo's motion, description's values) through the
    simulated arm with every physical effect, each cycle in time order on the simulated
    clock: the compensation brings the end point within the bound (measured 32 mm,
    BENCHMARKS.md; the issue's goal of 2 mm is not reached) from 234 mm, and within 1 mm
    with gravity alone and its own term (measured 0.3 mm), no rope slack."""
    from hrm_ctrl.formats.planfile import PlanDoc
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.scenarios import scenario
    from hrm_ctrl.runtime.playback import setpoints_of_plan
    from sim_bus.arm import SimArm
    from sim_bus.physics import Physics

    robot = default_robot()
    act = load_actuation(robot)
    sc = scenario("bent-pipe")
    plan = plan_path(robot, sc.path, PlanOptions(step=5.0, return_to_start=True), scenario=sc,
                     environment=sc.environment)  # fmt: skip
    doc = PlanDoc.from_dict(plan.to_dict(), sc.name)

    def errors(sp: Any, physics: Physics) -> tuple[np.ndarray, np.ndarray]:
        a, t = sp.row_angles()
        planned = joint_centres(robot, a, t)[:, -1]
        arm = SimArm(act, physics=physics, noise_N=0.0)
        arm.state(sp.counts[0], 0.0)
        for k in range(100):  # settle at the first row (the lead-in's end: plain), 1 s
            arm.state(sp.counts[0], 0.01 * k)
        err = np.empty(sp.n_cycles)
        tmin = np.empty(sp.n_cycles)
        for i, c in enumerate(sp.counts):
            s = arm.state(c, 1.0 + 0.01 * i)
            err[i] = np.linalg.norm(s.centres[-1] - planned[i])
            tmin[i] = s.tension_N.min()
        assert sp.ramp_rows == 100  # the feed-forward comes in over 1 s at rest
        return err[sp.ramp_rows :], tmin[sp.ramp_rows :]

    sp = setpoints_of_plan(doc, act, period_s=0.01, speed_mm_per_s=50.0, compensate=True)
    err, tmin = errors(sp, Physics.of("all"))
    assert err.max() < 40.0, err.max()  # uncompensated: 234 mm
    assert tmin.min() > 0.0  # no rope goes slack
    gravity_only = plan_setpoints(
        act, doc.travel_mm, doc.alpha_rad, doc.theta_rad, phase=doc.phase, period_s=0.01,
        speed_mm_per_s=50.0, feedforward=Feedforward.of(act, capstan=False, backlash=False),
    )  # fmt: skip
    err, tmin = errors(gravity_only, Physics.of("gravity"))
    assert err.max() < 1.0, err.max()  # uncompensated: 181 mm
    assert tmin.min() > 5.0
