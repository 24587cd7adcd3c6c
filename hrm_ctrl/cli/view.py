"""``hrm view``: the 3D view of a plan or of the arm, in the browser (issue 11).

``hrm view PLAN.json`` serves a page on 127.0.0.1 (``--port``, default 0: a free port;
the URL is printed) with the plan's environment (pipe, walls and their openings, boxes),
its path and backbone, and the arm at a step chosen with a slider (``--step`` first),
every link coloured by its clearance (green, amber within 5 mm, red: collision; blue:
no environment known).  It serves until Ctrl-C (exit 0).

``hrm view --live --sim [PLAN.json]`` brings up the in-process simulated box (as ``hrm run
--sim``), plays the plan on it (or, without one, holds the arm) and shows the arm as the
host estimates it from the drives' feedback (``hrm_ctrl/cli/_live.py``: counts -> joint
angles by the rope layer, 20 poses a second), the planned arm at the slider's step beside
it, and the tip camera's frames in the panel (rendered on the host from the tip's pose,
``hrm_ctrl/view/tip_camera.py``).
``--hold S`` holds the arm S seconds after the plan (without a plan: until Ctrl-C, at most
1 h).  The run writes its CAN logs and run record into ``--log-dir`` like ``hrm
run``.  The live view of real drives is the console's ``view`` command.

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm view")
>>> register(p)
>>> a = p.parse_args(["plan.json", "--port", "0", "--step", "3"])
>>> str(a.plan), a.port, a.step, a.live
('plan.json', 0, 3, False)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    calibrations_input,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._options import (
    SimArm,
    add_allow_collision,
    add_calibration,
    add_log,
    add_robot,
    add_sim,
    add_speed,
)
from hrm_ctrl.errors import DriverError

HELP = "the plan or the live arm in 3D in the browser (served on 127.0.0.1)"
SERVE_POLL_S = 0.2  # how often the plan view's main thread looks up from its wait


def register(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("plan", nargs="?", type=Path, metavar="PLAN.json", help="plan to show")
    parser.add_argument(
        "--port", type=int, default=0, help="port on 127.0.0.1 (default 0: a free one)"
    )
    parser.add_argument("--step", type=int, default=0, help="plan step shown first (0-based)")
    add_robot(parser)
    add_calibration(parser)
    parser.add_argument(
        "--live", action="store_true",
        help="show the arm as the host estimates it from drive feedback (with --sim)",
    )  # fmt: skip
    add_sim(parser, arm=SimArm.PERTURB, when="with --live")  # --sim, --perturb
    add_speed(parser, when="with --live")
    parser.add_argument(
        "--hold", type=float, default=None, metavar="S",
        help="with --live: hold the arm S s after the plan (no plan: until Ctrl-C)",
    )  # fmt: skip
    add_log(parser, when="with --live", formats=False)
    add_allow_collision(parser, when="with --live")


def _check_args(args: argparse.Namespace) -> None:
    if not 0 <= args.port <= 65535:
        raise DriverError(f"--port must be 0..65535, got {args.port}")
    if not args.live:
        if args.plan is None:
            raise DriverError("give PLAN.json, or --live --sim [PLAN.json]")
        for flag, given in (
            ("--sim", args.sim),
            ("--perturb", args.perturb is not None),
            ("--hold", args.hold is not None),
            ("--allow-collision", args.allow_collision),
            ("--calibrations", args.calibrations is not None),
        ):
            if given:
                raise DriverError(f"{flag} goes with --live")
        return
    if not args.sim:
        raise DriverError(
            "--live needs --sim here (the live view of real drives is the console's view command)"
        )
    if not (math.isfinite(args.speed) and args.speed > 0):
        raise DriverError(f"--speed must be > 0 mm/s, got {args.speed}")
    if args.hold is not None:
        from drivers.safety.limits import MAX_SOURCE_DURATION_S

        if not (math.isfinite(args.hold) and 0 < args.hold <= MAX_SOURCE_DURATION_S):
            raise DriverError(
                f"--hold must be > 0 s and at most {MAX_SOURCE_DURATION_S:g} s, got {args.hold}"
            )


def _serve_plan(args: argparse.Namespace) -> int:
    from hrm_ctrl.formats.planfile import read_plan
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.view.server import ArmView

    refuse_overwriting_inputs([], [Input("plan file", args.plan), robot_input(args.robot)])
    model = load_robot(args.robot)
    doc = read_plan(args.plan)
    with ArmView(model, doc.environment, doc, port=args.port, step=args.step) as view:
        print(f"view: {view.url}", flush=True)
        try:
            while True:
                time.sleep(SERVE_POLL_S)
        except KeyboardInterrupt:  # Ctrl-C is how the view ends
            pass
    return 0


def _live(args: argparse.Namespace) -> int:
    from drivers.bus import ensure_log_dir
    from drivers.config import load_box_config
    from drivers.safety.limits import MAX_SOURCE_DURATION_S
    from drivers.session import SafetyStopError
    from drivers.sources import CountsSource, HoldSource
    from hrm_ctrl.cli._common import arm_from_args
    from hrm_ctrl.cli._live import start_live_view
    from hrm_ctrl.formats.planfile import read_plan
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.runtime.box import SessionOptions, open_box
    from hrm_ctrl.runtime.playback import refuse_collision, setpoints_of_plan
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

    refuse_overwriting_inputs(
        [Output("--log-dir", args.log_dir, folder=True)],
        [
            Input("plan file", args.plan),
            robot_input(args.robot),
            calibrations_input(args),  # the logs into the store: only the store writes there
            *shipped_inputs(plan_schema=True, eds=True),
        ],
    )
    config = load_box_config(None)
    arm = arm_from_args(args, load_robot(args.robot), prog="hrm view", simulated=True)
    actuation = arm.actuation
    config.check_motors(actuation.motor_ids)
    period_s = config.control.period_s
    doc = None
    sources: list[Any] = []
    if args.plan is not None:
        doc = read_plan(args.plan)
        if not 0 <= args.step < doc.n_steps:
            raise DriverError(
                f"--step must be 0..{doc.n_steps - 1} (the plan's steps), got {args.step}"
            )
        refuse_collision(doc, args.allow_collision, actuation.robot)
        sp = setpoints_of_plan(
            doc,
            actuation,
            period_s=period_s,
            speed_mm_per_s=args.speed,
            max_duration_s=MAX_SOURCE_DURATION_S,
        )
        sources.append(CountsSource.of_plan(actuation, sp))
    if args.hold is not None:
        sources.append(HoldSource(n_cycles=max(1, round(args.hold * config.control.rate_hz))))
    elif doc is None:
        sources.append(HoldSource(n_cycles=None))  # until Ctrl-C (at most an hour)
    for s in sources:
        s.precheck(period_s)
    ensure_log_dir(args.log_dir)
    arm.say_note()
    sim = SimulatedBox(simulated_arm(arm, perturb=args.perturb))
    options = SessionOptions(
        log_dir=args.log_dir,
        calibration=arm.calibration_ref(),
        allow_uncalibrated=True,
        record_extra={"source": "hrm view --live", "simulated_box": True},
    )
    env = None if doc is None else doc.environment
    stop: SafetyStopError | None = None
    live = None
    with open_box(config, actuation, options, sim=sim, bring_up=False, prog="hrm view") as box:
        live = start_live_view(
            box.session, actuation, arm.robot, env, args.port, plan=doc, step=args.step
        )
        try:
            print(f"view: {live.url}", flush=True)
            box.bring_up()
            for source in sources:
                try:
                    box.session.stream(source)
                except SafetyStopError as exc:
                    stop = exc
                    break
        finally:
            live.close()
    if live is not None:
        print(
            f"live view: {live.shown} poses shown at {live.rate_hz():.1f} Hz, "
            f"{live.skipped} skipped"
        )
        v = live.view
        cost = "" if v.tip_frames == 0 else f", {v.tip_cpu_ms():.1f} ms CPU a frame"
        print(
            f"tip camera: {v.tip_frames} frames at {v.tip_rate_hz():.1f} Hz "
            f"(rendered on the host{cost}; none without a page)"
            + ("" if v.tip_error is None else f"; stopped: {v.tip_error}")
        )
    if stop is not None:
        print(f"hrm view: {stop}", file=sys.stderr)
        return 2
    return 0


def run(args: argparse.Namespace) -> int:
    _check_args(args)
    return _live(args) if args.live else _serve_plan(args)
