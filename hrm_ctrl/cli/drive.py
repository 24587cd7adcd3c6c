"""``hrm drive``: steer the tip, the body follows its trail (follow the leader, issue 37).

The keys come from a key script (``--keys FILE``: ``T_S KEY down|up`` a line,
:mod:`hrm_ctrl.drive.script`) played on the simulated clock against the arm's model;
every cycle is the online step of :mod:`hrm_ctrl.drive.online` through
:class:`hrm_ctrl.drive.driver.Driver`.  The status line goes to stderr when it changes
(a refusal, a hold) and every second; the summary to stdout.  The trail can be saved
as a path file (``--save-trail``) that ``hrm plan --path`` plans.

``--sim`` drives the simulated box (opened as every entry point opens it:
:func:`hrm_ctrl.runtime.box.open_box`, in its own process unless ``--wire`` says
otherwise): the online step of every control cycle goes to the drives through
:class:`hrm_ctrl.drive.stream.DriveSource` (a lead-in to the trail's first configuration
as a plan's, the rope layer's checked counts, jerk-limited shaping; a refusal stops the
motors within their limits and the drive ends holding there).  The control period is the
box's; the CAN logs and the run record go into ``--log-dir``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    arm_from_args,
    calibrations_input,
    config_input,
    load_box,
    refuse_overwriting_inputs,
    robot_input,
)
from hrm_ctrl.cli._options import (
    SimArm,
    add_bus,
    add_calibration,
    add_json,
    add_log,
    add_physics,
    add_robot,
    add_sim,
)

HELP = "steer the arm's tip by keys; the body follows the trail the tip draws"


def register(p: argparse.ArgumentParser) -> None:
    start = p.add_mutually_exclusive_group(required=True)
    start.add_argument(
        "--scenario", choices=["bent-pipe", "cabins"],
        help="start at the scenario's entry, in its environment",
    )  # fmt: skip
    start.add_argument(
        "--path", type=Path, metavar="FILE",
        help="start on a path file (header x,y,z; mm): the trail so far",
    )  # fmt: skip
    p.add_argument("--scene", type=Path, metavar="SCENE.toml", help="the environment")
    p.add_argument(
        "--keys", type=Path, required=True, metavar="FILE",
        help="key script: 'T_S KEY down|up' a line (keys: advance, retract, yaw_left, "
        "yaw_right, pitch_up, pitch_down; 'T_S end' ends the drive)",
    )  # fmt: skip
    p.add_argument("--save-trail", type=Path, metavar="FILE", help="write the trail (path file)")
    p.add_argument(
        "--advance-speed", type=float, default=20.0, metavar="MM_S",
        help="advance cap of the tip, mm/s (default 20)",
    )  # fmt: skip
    p.add_argument(
        "--turn-rate", type=float, default=11.4592, metavar="DEG_S",
        help="yaw and pitch rate cap at full speed, deg/s (default 11.46: a radius of "
        "100 mm at 20 mm/s)",
    )  # fmt: skip
    p.add_argument(
        "--accel", type=float, default=40.0, metavar="MM_S2", help="advance ramp, mm/s^2 (40)"
    )
    p.add_argument(
        "--period", type=float, default=0.01, metavar="S", help="control period, s (0.01)"
    )
    add_robot(p)
    add_sim(p, wire=True, arm=SimArm.NONE, process=True)
    add_bus(p, overrides=False)
    add_calibration(p)
    add_physics(p)  # --physics EFFECTS, as hrm sim --physics
    add_log(p, when="with --sim")
    add_json(p, "the summary")


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.drive.command import DriveError, SteerLimits
    from hrm_ctrl.drive.driver import CycleStatus, run_scripted
    from hrm_ctrl.drive.script import KeyScript
    from hrm_ctrl.drive.start import DriveStart, start_driver
    from hrm_ctrl.model import load_robot

    outputs = [Output("--save-trail", args.save_trail)]
    inputs = [
        Input("key script", args.keys),
        Input("path file", args.path),
        Input("scene file", args.scene),
        robot_input(args.robot),
    ]
    if args.sim:
        outputs.append(Output("--log-dir", args.log_dir, folder=True))
        inputs += [config_input(args.config), calibrations_input(args)]
    refuse_overwriting_inputs(outputs, inputs)
    rate = math.radians(args.turn_rate) if math.isfinite(args.turn_rate) else args.turn_rate
    limits = SteerLimits(rate, rate, args.advance_speed, args.accel)
    keys = KeyScript.read(args.keys)
    robot = load_robot(args.robot)
    arm = None
    period_s = args.period
    if args.physics is not None and not args.sim:
        raise DriveError("--physics goes with --sim")
    physics = None
    if args.physics is not None:
        from sim_bus.physics import Physics

        physics = Physics.of(args.physics)  # a bad one refused before any bus opens
    if args.sim:
        config = load_box(args)
        arm = arm_from_args(args, robot, prog="hrm drive", simulated=True)
        config.check_motors(arm.actuation.motor_ids)
        robot = arm.actuation.robot
        period_s = config.control.period_s
    start = DriveStart(scenario=args.scenario, path=args.path, scene=args.scene)
    driver = start_driver(robot, start, limits, period_s)
    trail = driver.planner.trail
    end = keys.end_s if math.isfinite(keys.end_s) else (keys.events[-1].t_s if keys.events else 0)
    if arm is not None:
        return _drive_box(args, config, arm, driver, keys, limits, float(end), trail, physics)
    every = max(1, round(1.0 / args.period))
    last: list[str | None] = [None]

    def show(k: int, s: CycleStatus) -> None:
        text = None if s.refusal is None else s.refusal.text
        if text != last[0] or k % every == 0:
            print(f"hrm drive: t {k * args.period:7.2f} s  {s.line()}", file=sys.stderr)
        last[0] = text

    summary = run_scripted(driver, lambda t: keys.command_at(t, limits), float(end), on_status=show)
    if args.save_trail is not None:
        trail.save(args.save_trail)
    if args.json:
        print(json.dumps(summary.to_dict(), indent=1))
    else:
        c = summary.worst_clearance_mm
        print(
            f"drove {summary.cycles} cycles: travel {summary.travel_mm:.1f} mm, trail "
            f"{summary.trail_length_mm:.1f} mm, {len(summary.refusals)} refusal(s)"
            + ("" if math.isinf(c) else f", worst clearance {c:.2f} mm")
        )
        if args.save_trail is not None:
            print(f"trail written to {args.save_trail}")
    return 0


def _drive_box(
    args: argparse.Namespace,
    config: Any,
    arm: Any,
    driver: Any,
    keys: Any,
    limits: Any,
    end_s: float,
    trail: Any,
    physics: Any,
) -> int:
    """``--sim``: the drive streamed to the simulated box; the summary with the run's
    outcome, its run record and CAN logs."""
    from dataclasses import replace

    from drivers.bus import ensure_log_dir
    from drivers.session import SafetyStopError
    from hrm_ctrl.drive.shape import ShapeFeedback, ShapeWatch, box_feedback, drive_plan
    from hrm_ctrl.drive.stream import DriveSource
    from hrm_ctrl.runtime.box import SessionOptions, open_box
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

    source = DriveSource(driver, arm.actuation, lambda t: keys.command_at(t, limits), end_s)
    source.precheck(config.control.period_s)  # before any bus opens
    ensure_log_dir(args.log_dir)
    arm.say_calibration("hrm drive")
    options = SessionOptions(
        log_dir=args.log_dir,
        log_suffix=f".{args.log_format}",
        calibration=arm.calibration_ref(),
        allow_uncalibrated=True,
        record_extra={"source": "DriveSource", "simulated_box": True},
    )
    sim_arm = replace(simulated_arm(arm, perturb=None, truth_file=None), physics=physics)
    sim = SimulatedBox(sim_arm, args.wire)
    stop: SafetyStopError | None = None
    with open_box(config, arm.actuation, options, sim=sim, prog="hrm drive") as opened:
        box = opened.session
        shape = ShapeWatch(
            box_feedback(box, opened.watches), drive_plan(source), ShapeFeedback(arm.actuation)
        )
        shape.start()
        try:
            result = box.stream(source)
        except SafetyStopError as exc:
            stop, result = exc, exc.result
        finally:
            shape.stop()
        box.record_extra["setpoints"] = source.describe()
        box.record_extra["shape"] = shape.summary()
    record = box.record()
    log_errors = [str(e) for e in record["can_log_errors"]]
    if args.save_trail is not None:
        trail.save(args.save_trail)
    d = source.summary().to_dict()
    d.update(
        outcome="stopped" if stop is not None else "completed",
        completed=result.completed,
        box_cycles=result.cycles,
        lead_in_cycles=source.n_lead_in,
        stop_reason=source.stop_reason,
        shaping_lag_counts=source.shaping_lag_counts,
        shape=shape.summary(),
        causes=[x.text for x in result.causes],
        run_record=str(box.record_path),
        can_logs=record["can_logs"],
        can_log_errors=log_errors,
    )
    if args.json:
        print(json.dumps(d, indent=1))
    else:
        print(
            f"drove the box {d['cycles']} cycles: travel {d['travel_mm']:.1f} mm, "
            f"{len(d['refusals'])} refusal(s); run record: {d['run_record']}"
        )
        sh = d["shape"]
        if sh["samples"]:
            print(
                f"shape feedback ({sh['samples']} samples, the rope estimator"
                f"{' with tensions' if sh['tensions'] else ''}): tip off the trail at most "
                f"{sh['tip_from_trail_mm']['max']:.2f} mm, the arm off the plan at most "
                f"{sh['shape_mm']['max']:.2f} mm"
            )
    status = 0
    if stop is not None:
        print(f"hrm drive: {stop}", file=sys.stderr)
        status = 2
    if source.stop_reason is not None:
        print(f"hrm drive: held: {source.stop_reason}", file=sys.stderr)
    if log_errors:
        print(f"hrm drive: error: CAN log incomplete: {log_errors[0]}", file=sys.stderr)
        status = 2
    return status
