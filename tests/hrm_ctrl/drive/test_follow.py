"""Follow-the-leader driving on the model (simulated clock): the bent pipe of the paper
steered by its key sequence, the retract back to the start, and the refusals that hold
the arm.

Sized down for the suite: the drive runs at 20 Hz (1 mm of travel a step at 20 mm/s),
the largest online step, instead of the box's 100 Hz (0.2 mm a step);
``benchmarks/bench_drive.py`` runs the 100 Hz drive.  The arm is the model's (the
planned angles' forward kinematics), not the simulated box's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrm_ctrl.drive.command import STOP, SteerCommand, SteerLimits
from hrm_ctrl.drive.driver import CycleStatus, Driver
from hrm_ctrl.drive.online import OnlineOptions, OnlinePlanner, RefusalKind
from hrm_ctrl.drive.script import KeyScript, bent_pipe_keys
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.environment import Box, Environment, link_clearance
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.scenarios import scenario

PERIOD_S = 0.05  # 1 mm a step at 20 mm/s
ENTRY = np.array([1200.0, 100.0, 300.0])
ALONG_X = np.array([1.0, 0.0, 0.0])


def centres(q: np.ndarray) -> np.ndarray:
    m = default_robot()
    return joint_centres(m, q[None, :12], q[None, 12:])[0]


def distance_to_polyline(p: np.ndarray, pts: np.ndarray) -> float:
    a, b = pts[:-1], pts[1:]
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * d - p, axis=1).min())


@pytest.fixture(scope="module")
def pipe_drive() -> dict[str, object]:
    """The bent pipe steered by its keys, then retracted to the start: every cycle's
    angles and travel."""
    model = default_robot()
    sc = scenario("bent-pipe")
    limits = SteerLimits(pitch_rate_rad_s=0.2, yaw_rate_rad_s=0.2)
    keys = KeyScript.parse(bent_pipe_keys(limits, period_s=PERIOD_S), "bent-pipe keys")
    P = sc.path.points
    trail = Trail.starting_at(P[0], P[1] - P[0])
    planner = OnlinePlanner(model, trail, sc.environment)
    drv = Driver(planner, limits, PERIOD_S)
    fwd_q, fwd_d, refusals = [planner.q.copy()], [planner.travel], []
    k = 0
    while k * PERIOD_S <= keys.end_s:
        s = drv.cycle(keys.command_at(k * PERIOD_S, limits))
        refusals += [s.refusal] if s.refusal else []
        fwd_q.append(planner.q.copy())
        fwd_d.append(planner.travel)
        k += 1
    back_q, back_d = [], []
    while planner.travel > 0.0 and k < 10_000:
        s = drv.cycle(SteerCommand(0.0, 0.0, -20.0))
        back_q.append(planner.q.copy())
        back_d.append(planner.travel)
        k += 1
        if s.refusal is not None:
            break
    return {
        "env": sc.environment,
        "pipe": sc.path,
        "trail": trail,
        "fwd_q": np.array(fwd_q),
        "fwd_d": np.array(fwd_d),
        "back_q": np.array(back_q),
        "back_d": np.array(back_d),
        "refusals": refusals,
        "last_refusal": s.refusal,
    }


def test_the_pipe_is_steered_through_with_the_tip_on_the_trail(pipe_drive: dict) -> None:
    assert pipe_drive["refusals"] == []
    trail: Trail = pipe_drive["trail"]
    pipe: KnownPath = pipe_drive["pipe"]
    d = pipe_drive["fwd_d"]
    assert d[-1] == pytest.approx(pipe.length, abs=1.0)  # the whole pipe
    # the trail the keys drew is the pipe's axis (within the keys' timing: 1 mm a cycle)
    worst_axis = max(distance_to_polyline(p, pipe.points) for p in trail.points)
    assert worst_axis < 5.0
    m = default_robot()
    q = pipe_drive["fwd_q"]
    O = joint_centres(m, q[:, :12], q[:, 12:])
    tip_off = [float(np.linalg.norm(O[i, -1] - trail.point_at(d[i]))) for i in range(len(d))]
    assert max(tip_off) < 1.0
    c = link_clearance(pipe_drive["env"], O, 0.5 * np.asarray(m.outer_diameter))
    assert float(c.min()) > 0.0, f"a link meets the wall: {c.min():.2f} mm"


def test_the_arm_changes_smoothly(pipe_drive: dict) -> None:
    q = pipe_drive["fwd_q"]
    d = pipe_drive["fwd_d"]
    dq = np.degrees(np.abs(np.diff(q, axis=0)).max(axis=1))
    dd = np.abs(np.diff(d))
    moving = dd > 0
    assert (dq[moving] <= 2.0 * dd[moving] / 5.0 + 1e-6).all()  # 2 deg per 5 mm at most
    assert (dq[~moving] == 0.0).all()


def test_retract_retraces_the_trail_to_the_start(pipe_drive: dict) -> None:
    m = default_robot()
    fq, fd = pipe_drive["fwd_q"], pipe_drive["fwd_d"]
    bq, bd = pipe_drive["back_q"], pipe_drive["back_d"]
    assert pipe_drive["last_refusal"] is None or pipe_drive["last_refusal"].kind is (
        RefusalKind.END_OF_LENGTH
    )
    assert bd[-1] == pytest.approx(0.0, abs=1e-9)
    Of = joint_centres(m, fq[:, :12], fq[:, 12:])
    Ob = joint_centres(m, bq[:, :12], bq[:, 12:])
    worst = 0.0
    for i in range(len(bd)):  # the forward configuration at the same travel
        j = int(np.argmin(np.abs(fd - bd[i])))
        if abs(fd[j] - bd[i]) < 1e-6:
            worst = max(worst, float(np.linalg.norm(Ob[i] - Of[j], axis=1).max()))
    assert worst < 1.0, f"the retract leaves the forward configurations by {worst:.2f} mm"
    start = np.linalg.norm(Ob[-1] - Of[0], axis=1).max()
    assert start < 1.0


def test_release_stops_within_the_deceleration() -> None:
    trail = Trail.starting_at(ENTRY, ALONG_X)
    limits = SteerLimits(accel_mm_s2=40.0)
    drv = Driver(OnlinePlanner(default_robot(), trail), limits, 0.01)
    for _ in range(60):
        drv.cycle(SteerCommand(0.0, 0.0, 20.0))
    v = [drv.speed_mm_s]
    for _ in range(60):
        drv.cycle(STOP)
        v.append(drv.speed_mm_s)
    assert np.all(np.abs(np.diff(v)) <= 40.0 * 0.01 + 1e-9)
    assert v.index(0.0) <= math.ceil(20.0 / 40.0 / 0.01)


def one_line(text: str) -> bool:
    return "\n" not in text and len(text) < 200


def drive_until_refused(drv: Driver, cmd: SteerCommand, cycles: int = 3000) -> CycleStatus:
    for _ in range(cycles):
        s = drv.cycle(cmd)
        if s.refusal is not None:
            return s
    raise AssertionError("never refused")


def test_a_steer_too_tight_holds_the_arm_with_one_line() -> None:
    trail = Trail.starting_at(ENTRY, ALONG_X)
    limits = SteerLimits(pitch_rate_rad_s=0.3, advance_mm_s=20.0)  # radius 67 mm
    drv = Driver(OnlinePlanner(default_robot(), trail), limits, 0.05)
    for _ in range(300):  # 300 mm straight: joints on the trail before the turn
        assert drv.cycle(SteerCommand(0.0, 0.0, 20.0)).refusal is None
    s = drv_status = drive_until_refused(drv, SteerCommand(0.0, -0.3, 20.0))
    r = s.refusal
    assert r.kind is RefusalKind.TOO_TIGHT and r.joint is not None
    assert r.value_deg > r.limit_deg == pytest.approx(60.0)
    assert one_line(s.line()) and f"joint {r.joint} would bend" in s.line()
    travel = drv.planner.travel
    assert drv_status.speed_mm_s == 0.0
    # holds: the same steer gains at most the last fraction of a step (the speed ramps up
    # from rest again and a shorter step may still fit), every refused cycle moves nothing
    refused = 0
    for _ in range(20):
        before = drv.q.copy()
        s2 = drv.cycle(SteerCommand(0.0, -0.3, 20.0))
        if s2.refusal is not None:
            refused += 1
            assert (drv.q == before).all() and s2.speed_mm_s == 0.0
    assert refused >= 5 and drv.planner.travel - travel < 1.0
    assert trail.length == pytest.approx(drv.planner.travel, abs=1e-6)  # no refused trail
    # backing out is still possible (straight on is not: the joints behind the tip would
    # have to pass the tight arc drawn so far)
    assert drv.cycle(SteerCommand(0.0, 0.0, -20.0)).refusal is None


def test_a_joint_limit_holds_the_arm_naming_joint_and_limit() -> None:
    trail = Trail.starting_at(ENTRY, ALONG_X)
    opt = OnlineOptions(joint_margin_deg=25.0)  # any angle beyond 35 deg is refused (joint 2
    # theta is about -45 deg at the entry)
    drv = Driver(OnlinePlanner(default_robot(), trail, options=opt), SteerLimits(), 0.05)
    s = drive_until_refused(drv, SteerCommand(0.2, 0.0, 20.0))
    r = s.refusal
    assert r.kind is RefusalKind.JOINT_LIMIT
    assert r.angle in ("alpha", "theta") and abs(r.value_deg) > 35.0
    assert r.limit_deg == pytest.approx(60.0)
    assert f"joint {r.joint} {r.angle} would reach" in s.line() and one_line(s.line())
    assert drv.planner.travel == 0.0 and drv.speed_mm_s == 0.0  # held at the start


def test_a_wall_ahead_holds_the_arm_naming_link_and_distance() -> None:
    trail = Trail.starting_at(ENTRY, ALONG_X)
    wall = Box(np.array([1300.0, 100.0, 300.0]), np.array([10.0, 200.0, 200.0]))
    opt = OnlineOptions(clearance_margin_mm=2.0)
    planner = OnlinePlanner(default_robot(), trail, Environment((wall,)), opt)
    drv = Driver(planner, SteerLimits(), 0.05)
    s = drive_until_refused(drv, SteerCommand(0.0, 0.0, 20.0))
    r = s.refusal
    assert r.kind is RefusalKind.CLEARANCE and r.link == 12
    assert 0.0 <= r.clearance_mm < 2.0
    assert one_line(s.line()) and "link 12 would come" in s.line()
    # the tip (radius 15 mm) stopped short of the wall's face at x = 1295
    assert 1295.0 - 15.0 - 2.0 - 1.5 < planner.tip[0] < 1295.0 - 15.0
    travel = planner.travel
    for _ in range(20):  # held: at most the last fraction of a step gained, never closer
        s = drv.cycle(SteerCommand(0.0, 0.0, 20.0))
        assert planner.clearance_mm >= 2.0
    assert planner.travel - travel < 1.0
    assert drv.cycle(SteerCommand(0.0, 0.0, -20.0)).refusal is None  # backing out is fine


def test_the_end_of_the_arms_length_holds_the_arm() -> None:
    trail = Trail.starting_at(np.array([1850.0, 0.0, 50.0]), ALONG_X)
    drv = Driver(OnlinePlanner(default_robot(), trail), SteerLimits(), 0.05)
    s = drive_until_refused(drv, SteerCommand(0.0, 0.0, 20.0))
    assert s.refusal.kind is RefusalKind.END_OF_LENGTH and one_line(s.line())
    assert drv.planner.travel < 2007.0 - 1850.0
