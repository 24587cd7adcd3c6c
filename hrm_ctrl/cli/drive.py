"""``hrm drive``: steer the tip, the body follows its trail (follow the leader, issue 37).

The keys come from a key script (``--keys FILE``: ``T_S KEY down|up`` a line,
:mod:`hrm_ctrl.drive.script`) played on the simulated clock against the arm's model;
every cycle is the online step of :mod:`hrm_ctrl.drive.online` through
:class:`hrm_ctrl.drive.driver.Driver`.  The status line goes to stderr when it changes
(a refusal, a hold) and every second; the summary to stdout.  The trail can be saved
as a path file (``--save-trail``) that ``hrm plan --path`` plans.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from hrm_ctrl.cli._common import Input, Output, refuse_overwriting_inputs, robot_input
from hrm_ctrl.cli._options import add_json, add_robot

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
    p.add_argument("--speed", type=float, default=20.0, help="advance cap, mm/s (default 20)")
    p.add_argument(
        "--turn-rate", type=float, default=11.4592, metavar="DEG_S",
        help="yaw and pitch rate cap at full speed, deg/s (default 11.46: a radius of "
        "100 mm at 20 mm/s)",
    )  # fmt: skip
    p.add_argument("--accel", type=float, default=40.0, help="advance ramp, mm/s^2 (40)")
    p.add_argument("--period", type=float, default=0.01, help="control period, s (0.01)")
    add_robot(p)
    add_json(p, "the summary")


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.drive.command import SteerLimits
    from hrm_ctrl.drive.driver import CycleStatus, Driver, run_scripted
    from hrm_ctrl.drive.online import OnlinePlanner
    from hrm_ctrl.drive.script import KeyScript
    from hrm_ctrl.drive.trail import Trail
    from hrm_ctrl.formats.scene import read_scene
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.planning.known_path import load_path_csv
    from hrm_ctrl.planning.scenarios import scenario

    refuse_overwriting_inputs(
        [Output("--save-trail", args.save_trail)],
        [
            Input("key script", args.keys),
            Input("path file", args.path),
            Input("scene file", args.scene),
            robot_input(args.robot),
        ],
    )
    rate = math.radians(args.turn_rate) if math.isfinite(args.turn_rate) else args.turn_rate
    limits = SteerLimits(rate, rate, args.speed, args.accel)
    keys = KeyScript.read(args.keys)
    robot = load_robot(args.robot)
    env = read_scene(args.scene) if args.scene is not None else None
    if args.scenario:
        sc = scenario(args.scenario)
        env = env if env is not None else sc.environment
        P = sc.path.points
        trail = Trail.starting_at(P[0], P[1] - P[0])
    else:
        trail = Trail.from_path(load_path_csv(args.path))
    planner = OnlinePlanner(robot, trail, env)
    driver = Driver(planner, limits, args.period)
    every = max(1, round(1.0 / args.period))
    last: list[str | None] = [None]

    def show(k: int, s: CycleStatus) -> None:
        text = None if s.refusal is None else s.refusal.text
        if text != last[0] or k % every == 0:
            print(f"hrm drive: t {k * args.period:7.2f} s  {s.line()}", file=sys.stderr)
        last[0] = text

    end = keys.end_s if math.isfinite(keys.end_s) else (keys.events[-1].t_s if keys.events else 0)
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
