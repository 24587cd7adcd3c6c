"""The cabins driven by a recorded key script: on the model (the online planner's
angles) and in the console on the in-process simulated box (the true arm: the rope
inverse of every SYNC's drive positions, which is where the simulated arm without physics
stands), against the trail the tip drew and the cabins' walls.

The key sequence: advance at 20 mm/s; where the scenario's path turns (its 107 deg corner
rounded to 150 mm), ``yaw_right`` held and ``pitch_down`` held on a share of the cycles (the
corner's plane is neither the tip's yaw nor its pitch plane: 0.916 of the turn is yaw,
0.402 pitch), so the trail draws the corner's arc (within 0.12 mm of the path); the
advance released where its ramp down ends at the path's end.

The goal (issue 37): the drive reaches the path's end (419.4 mm: the trail's arcs are
chords, 0.03 mm shorter than the path) without a hold, the true tip within 1 mm of the
trail and every link clear of the walls at every cycle.  Measured (the loaded 2-core
machine, on the box): no hold, the true tip within 0.03 mm of the trail (median 0.01 mm),
the least link clearance 8.87 mm (the offline refined plan, ``hrm plan --scenario
cabins``, clears by 8.5 mm where links 10-12 pass the partition's opening).  (With the
online refinement's clearance cap at the offline 40 mm the arm came within the 1 mm
margin there and held 14 times between 287 and 304 mm: ``hrm_ctrl/drive/online.py``,
"Clearance worth having".)"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.cli._console.shell import run_script
from hrm_ctrl.drive.shape import point_to_polyline
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.planning.environment import link_clearance
from hrm_ctrl.planning.known_path import load_path_csv
from hrm_ctrl.planning.scenarios import scenario
from tests.hrm_ctrl.cli.console.test_console_drive import _relaxed_box

T = 0.01
SPEED_MM_S = 20.0
ACCEL_MM_S2 = 40.0
CORNER_RADIUS_MM = 150.0


def cabins_keys() -> tuple[str, float]:
    """The key script and the turn rate (deg/s) that draw the cabins' path (module doc)."""
    A = np.array([1200.0, 100.0, 300.0])
    B = np.array([1470.0, 190.0, 300.0])
    C = np.array([1470.0, -50.0, 200.0])
    d1 = (B - A) / np.linalg.norm(B - A)
    d2 = (C - B) / np.linalg.norm(C - B)
    phi = math.acos(float(d1 @ d2))
    tangent = CORNER_RADIUS_MM * math.tan(phi / 2.0)
    # the corner's turn in the tip's frame (the trail's heading, up and left at A)
    start = Trail.starting_at(A, d1)
    up, left = start.up, np.cross(start.up, start.heading)
    axis = np.cross(d1, d2) / np.linalg.norm(np.cross(d1, d2))
    yaw, pitch = float(axis @ up), float(-(axis @ left))
    assert yaw < 0.0 and pitch < 0.0  # to the right and down
    rate = SPEED_MM_S * abs(yaw) / CORNER_RADIUS_MM  # rad/s: yaw held throughout
    duty = abs(pitch) / abs(yaw)
    s_turn = float(np.linalg.norm(B - A)) - tangent
    s_out = s_turn + CORNER_RADIUS_MM * phi
    length = s_out + float(np.linalg.norm(C - B)) - tangent
    ramp_s, ramp_mm = SPEED_MM_S / ACCEL_MM_S2, 0.5 * SPEED_MM_S**2 / ACCEL_MM_S2

    def cycle_at(mm: float) -> int:
        return round((ramp_s + (mm - ramp_mm) / SPEED_MM_S) / T)

    k0, k1, release = cycle_at(s_turn), cycle_at(s_out), cycle_at(length - ramp_mm)
    lines = ["0 advance down", f"{k0 * T:.2f} yaw_right down"]
    share, on = 0.0, False
    for k in range(k0, k1):  # pitch_down on `duty` of the cycles, spread evenly
        share += duty
        want = share >= 0.5
        share -= 1.0 if want else 0.0
        if want != on:
            lines.append(f"{k * T:.2f} pitch_down {'down' if want else 'up'}")
            on = want
    if on:
        lines.append(f"{k1 * T:.2f} pitch_down up")
    lines += [f"{k1 * T:.2f} yaw_right up", f"{release * T:.2f} advance up",
              f"{release * T + ramp_s + T:.2f} end"]  # fmt: skip
    return "\n".join(lines) + "\n", math.degrees(rate)


def test_the_keys_draw_the_cabins_path_on_the_model(tmp_path: Path) -> None:
    from hrm_ctrl.drive.command import SteerLimits
    from hrm_ctrl.drive.script import KeyScript

    text, rate_deg = cabins_keys()
    keys = KeyScript.parse(text, "cabins keys")
    rate = math.radians(rate_deg)
    limits = SteerLimits(rate, rate, SPEED_MM_S, ACCEL_MM_S2)
    trail = Trail.starting_at(np.array([1200.0, 100.0, 300.0]), np.array([270.0, 90.0, 0.0]))
    v, k = 0.0, 0
    while k * T <= keys.end_s:  # the driver's ramp and growth, without the arm
        c = keys.command_at(k * T, limits)
        dv = ACCEL_MM_S2 * T
        v += max(-dv, min(dv, c.advance_mm_s - v))
        if v > 0.0:
            trail.extend(v * T, c.yaw_rate_rad_s / SPEED_MM_S, c.pitch_rate_rad_s / SPEED_MM_S)
        k += 1
    path = scenario("cabins").path.points
    off = max(point_to_polyline(p, path) for p in trail.points)
    assert off < 1.0, off  # the trail is the scenario's path
    assert trail.length == pytest.approx(419.43, abs=0.3)


@pytest.mark.slow  # ~6 s of CPU: 2100 online steps with the clearance fit
def test_cabins_by_keys_on_the_model() -> None:
    """The drive's planner under the key script at the box's 100 Hz (0.2 mm a step at
    20 mm/s), without the box: through to the path's end with no hold, the tip on the
    trail and every link beyond the clearance margin at every cycle (measured: least
    8.26 mm)."""
    from hrm_ctrl.drive.command import SteerLimits
    from hrm_ctrl.drive.driver import run_scripted
    from hrm_ctrl.drive.script import KeyScript
    from hrm_ctrl.drive.start import DriveStart, start_driver
    from hrm_ctrl.model import default_robot

    text, rate_deg = cabins_keys()
    keys = KeyScript.parse(text, "cabins keys")
    rate = math.radians(rate_deg)
    limits = SteerLimits(rate, rate, SPEED_MM_S, ACCEL_MM_S2)
    model = default_robot()
    drv = start_driver(model, DriveStart(scenario="cabins"), limits, T)
    q, tip_target = [], []

    def keep(_k: int, _s: object) -> None:
        q.append(drv.q.copy())
        tip_target.append(drv.planner.trail.point_at(drv.planner.travel))

    summary = run_scripted(drv, lambda t: keys.command_at(t, limits), keys.end_s, on_status=keep)
    sc = scenario("cabins")
    assert summary.refusals == ()  # no hold
    assert summary.travel_mm == pytest.approx(sc.path.length, abs=0.1)  # the path's end
    Q = np.array(q)
    O = joint_centres(model, Q[:, :12], Q[:, 12:])
    tip_off = np.linalg.norm(O[:, -1] - np.array(tip_target), axis=1)
    assert tip_off.max() < 0.05  # the planner's tolerance
    c = link_clearance(sc.environment, O, 0.5 * np.asarray(model.outer_diameter))
    margin = drv.planner.opt.clearance_margin_mm
    assert float(c.min()) > margin, float(c.min())  # every link, every cycle


@pytest.mark.slow  # ~50 s: a 21 s drive on the in-process box, every SYNC checked
def test_cabins_by_keys_on_the_simulated_box(make_ctx, tmp_path: Path) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    text, rate_deg = cabins_keys()
    keys = tmp_path / "cabins_keys.txt"
    keys.write_text(text)
    trail_file = tmp_path / "trail.csv"
    run_script(ctx, ["connect", "enable"], "test")
    ctx.sim.record_trace(True)
    run_script(ctx, [f"drive --scenario cabins --keys {keys} --turn-rate {rate_deg:.9f} "
                     f"--save-trail {trail_file}"], "test")  # fmt: skip
    _t, positions = ctx.sim.trace()
    ctx.sim.record_trace(False)
    d = ctx.session.record_extra["console_drives"][-1]
    assert d["stop_reason"] is None
    # the true arm at every SYNC of the drive after its lead-in (which starts at the first
    # SYNC the drives moved at, from the straight arm that reaches through the entrance wall)
    act = ctx.actuation
    moved = int(np.flatnonzero(np.abs(positions - positions[0]).max(axis=1) > 0)[0])
    body = positions[moved + d["lead_in_cycles"] :].astype(np.float64)
    alpha, theta, _ = act.angles_from_counts(body)
    O = joint_centres(act.robot, alpha, theta)
    clearance = link_clearance(
        scenario("cabins").environment, O, 0.5 * np.asarray(act.robot.outer_diameter)
    )
    least = float(clearance.min())
    trail = load_path_csv(trail_file).points
    tip_off = np.array([point_to_polyline(o[-1], trail) for o in O])
    print(f"cabins by keys on the box: {len(d['refusals'])} holds, travel "
          f"{d['travel_mm']:.1f} mm; true tip off the trail max {tip_off.max():.2f} mm, "
          f"median {np.median(tip_off):.2f} mm; least link clearance {least:.2f} mm")  # fmt: skip
    assert d["refusals"] == []  # no hold
    # to the path's end (the trail's arcs are chords, a little shorter than the path's)
    assert d["travel_mm"] == pytest.approx(scenario("cabins").path.length, abs=0.1)
    assert least > 0.0  # every link clear of the walls at every SYNC
    assert tip_off.max() < 1.0  # the goal: the true tip within 1 mm of the trail
