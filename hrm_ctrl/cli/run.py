"""``hrm run``: play a plan (or a hold / a jog) on the rope-motor drives over CAN.

Loads the bus configuration (``--config``, default ``drivers/data/box.toml``)
and the robot description, refuses a bus over its load budget and a plan
outside the rope or joint limits before anything is sent, brings every drive
up (NMT, SDO, CiA 402 to operation enabled in CSP), streams the setpoints at the
control rate and disables the drives at the end.  While the drives are enabled the
tension-sensor board (when the configuration has a ``[tension]`` table) and the rope
layer's consistency check on the feedback watch the arm (``hrm_ctrl.runtime.watches``):
either stops every axis, naming the rope.  Every run writes each bus's
traffic (``--log-format``: ``.blf``, ``.asc``, ``.log``, ``.trc``, ...) and a run
record JSON into ``--log-dir``; ``--bus NAME=INTERFACE:CHANNEL[@BITRATE]`` opens one bus
of the configuration elsewhere.

``--sim`` starts the simulated box (``sim_bus``) in its own process on ``hrm_ipc`` buses
(``hrm sim --control``; with ``--wire virtual`` or ``--wire hrm_sim`` in this process, on
python-can virtual buses or the simulated wire at the configured bitrate) instead of
opening the configured interfaces; nothing else changes (the drivers only see buses).
``--physics EFFECTS`` gives the simulated arm the physics ``hrm sim --physics`` does
(``all``, ``none``, ``gravity,capstan,...``; docs/sim.md).  ``--compensate`` plays the
rope lengths that hold each planned pose against the arm's loads
(``hrm_ctrl.ropes.feedforward``); the rope consistency check takes what that added off
before it checks (``hrm_ctrl.ropes.estimator.Compensation``).

Calibration (issue 12): the rope layer is built with the active calibration of the store
(``--calibrations DIR``, default ``$HRM_CALIBRATIONS`` or
``~/.local/share/hrm/calibrations``) for this robot description, and the run record names
its version.  A damaged calibration, or one for another description, is refused.  Real
drives are not enabled without a calibration unless ``--uncalibrated`` overrides that
explicitly (a stderr line says so); ``--sim`` without a stored calibration runs with the
description's values and says so on stderr (a simulated arm: the gate is for real drives).

A plan whose arm meets an obstacle of the environment it stores (negative clearance, stored
or recomputed) is refused with one line naming step and link, before anything is sent,
unless ``--allow-collision`` (then a stderr line says so).

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm run")
>>> register(p)
>>> a = p.parse_args(["plan.json", "--sim", "--speed", "50"])
>>> str(a.plan), a.sim, a.speed, a.compensate, a.physics
('plan.json', True, 50.0, False, None)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    arm_from_args,
    calibrations_input,
    config_input,
    load_box,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._options import (
    SimArm,
    Uncalibrated,
    add_bus,
    add_calibration,
    add_json,
    add_log,
    add_physics,
    add_robot,
    add_run_controls,
    add_sim,
    sim_physics,
)
from hrm_ctrl.errors import DriverError
from hrm_ctrl.runtime.playback import refuse_collision  # noqa: F401  (its old home)

if TYPE_CHECKING:
    pass

HELP = "play a plan (or hold / jog) on the CiA 402 rope-motor drives over CAN"


def register(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("plan", nargs="?", type=Path, metavar="PLAN.json", help="plan to play")
    add_bus(parser, take_over=True)  # --config, --bus, --take-over
    add_robot(parser)
    add_sim(parser, wire=True, arm=SimArm.PERTURB_OR_TRUTH, process=True)  # --sim, --wire, ...
    add_physics(parser)  # --physics EFFECTS, as hrm sim --physics
    add_calibration(parser, Uncalibrated.DRIVES)
    add_log(parser)  # --log-dir, --log-format
    add_run_controls(parser)  # --speed, --pause-at, --resume-after, --abort-at, --allow-collision
    parser.add_argument(
        "--hold", type=float, default=None, metavar="S", help="hold the actual positions S s"
    )
    parser.add_argument(
        "--jog", default=None, metavar="MOTOR:COUNTS_PER_S:S",
        help="move one rope motor at a constant speed, e.g. j01r0:20000:0.2",
    )  # fmt: skip
    parser.add_argument(
        "--compensate", action="store_true",
        help="feed-forward: command the rope lengths that hold each planned pose against "
        "gravity, rope stretch, capstan friction and joint play (the description's "
        "[physics]; off by default: an arm without those loads is bent by it)",
    )  # fmt: skip
    add_json(parser, "the summary")


def _playback(
    args: argparse.Namespace,
    actuation: Any,
    period_s: float,
    progress: Callable[[float], None] | None = None,
) -> Any:
    """The arguments' :func:`hrm_ctrl.runtime.playback.setpoint_source`."""
    from hrm_ctrl.runtime.playback import setpoint_source

    return setpoint_source(
        actuation,
        period_s,
        plan=args.plan,
        hold_s=args.hold,
        jog=args.jog,
        speed_mm_per_s=args.speed,
        allow_collision=args.allow_collision,
        progress=progress,
        compensate=args.compensate,
    )


def _source(
    args: argparse.Namespace,
    actuation: Any,
    period_s: float,
    progress: Callable[[float], None] | None = None,
) -> tuple[Any, Any, dict[str, Any]]:
    """The setpoint source the arguments ask for, the hold time (s) of a hold, and what the
    run record keeps of a plan."""
    p = _playback(args, actuation, period_s, progress)
    return p.source, p.hold_s, p.plan_record


def run(args: argparse.Namespace) -> int:
    from drivers.bus import ensure_log_dir
    from drivers.session import SafetyStopError
    from drivers.sources import HoldSource, PausableSource
    from hrm_ctrl.cli._progress import ProgressBar, bring_up_with_progress
    from hrm_ctrl.cli._progress import wanted as progress_wanted
    from hrm_ctrl.cli._runcontrol import RunDisplay, RunDriver, RunScript, write_run_tensions
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.runtime.box import SessionOptions, WatchOptions, open_box
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

    if not (math.isfinite(args.speed) and args.speed > 0):
        raise DriverError(f"--speed must be > 0 mm/s, got {args.speed}")
    if not args.sim and (args.perturb is not None or args.truth is not None):
        raise DriverError("--perturb and --truth describe the simulated arm: they go with --sim")
    physics = sim_physics(args.physics, args.sim)  # a bad one refused before anything is read
    refuse_overwriting_inputs(  # before anything is read or written
        [Output("--log-dir", args.log_dir, folder=True)],
        [
            Input("plan file", args.plan),
            Input("truth file", args.truth),
            robot_input(args.robot),
            config_input(args.config),
            calibrations_input(args),  # the logs into the store: only the store writes there
            *shipped_inputs(plan_schema=True, eds=True),
        ],
    )
    config = load_box(args)  # --config with the --bus overrides
    arm = arm_from_args(args, load_robot(args.robot), prog="hrm run", simulated=args.sim)
    actuation = arm.actuation
    config.check_motors(actuation.motor_ids)
    script = RunScript.from_args(args)  # --pause-at etc.: refused before anything is sent
    if not script.empty and args.plan is None:
        raise DriverError("--pause-at and --abort-at go with a PLAN.json")
    show = progress_wanted(args.json)
    with ProgressBar("time parameterisation", enabled=show and args.plan is not None) as bar:
        playback = _playback(args, actuation, config.control.period_s, bar)
    source, hold_s, setpoints = playback.source, playback.hold_s, playback.setpoints
    if setpoints is not None:  # a plan: played pausable (keys, --pause-at, --abort-at)
        source = PausableSource(source, actuation)
    if isinstance(source, HoldSource) and hold_s is not None:
        source = HoldSource(n_cycles=max(1, round(hold_s * config.control.rate_hz)))
    source.precheck(config.control.period_s)  # refuse bad setpoints before any bus opens
    ensure_log_dir(args.log_dir)  # a bad log directory: one line, before any bus opens

    sim = None
    if args.sim:  # the simulated arm: the description's, or one that differs from it
        sim = SimulatedBox(
            simulated_arm(arm, perturb=args.perturb, truth_file=args.truth, physics=physics),
            args.wire,
        )
    arm.say_calibration(
        "hrm run"
    )  # --sim or --uncalibrated without a calibration: said once all checks passed
    options = SessionOptions(
        log_dir=args.log_dir,
        log_suffix=f".{args.log_format}",
        take_over=args.take_over,
        calibration=arm.calibration_ref(),
        allow_uncalibrated=args.uncalibrated or args.sim,
        record_extra={
            "plan_file": None,
            **playback.plan_record,
            "source": source.__class__.__name__,
            "simulated_box": bool(args.sim),
        },
    )
    interrupted: str | None = None
    driver = None
    stop: SafetyStopError | None = None
    bring_up = lambda session: bring_up_with_progress(session, enabled=show)  # noqa: E731
    # a compensated plan: the rope consistency watch takes what the feed-forward added off
    watches = WatchOptions(compensation=playback.compensation)
    with open_box(
        config, actuation, options, sim=sim, watches=watches, bring_up=bring_up, prog="hrm run"
    ) as opened:
        box = opened.session
        if isinstance(source, PausableSource):
            display = RunDisplay(source, setpoints, box, actuation.robot, opened.watches)
            with ProgressBar("run", enabled=show) as bar:
                driver = RunDriver(source, script, keys=show, display=display, bar=bar)
                driver.start()
                result, stop, interrupted = _stream(box, source, driver, display)
        else:
            result, stop, interrupted = _stream(box, source, None, None)
        box.record_extra["setpoints"] = source.describe()
        if driver is not None:
            box.record_extra["run_control"] = [
                {"action": a, "fraction": round(f, 4)} for a, f in driver.events
            ]
    record = box.record()
    log_errors = [str(e) for e in record["can_log_errors"]]
    tension_file = write_run_tensions(driver, box.record_path, actuation.motor_ids)
    if interrupted is not None and result is None:
        print(f"hrm run: interrupted{interrupted}: every axis stopped", file=sys.stderr)
        return 130
    outcome = "completed"
    if interrupted is not None:
        outcome = "interrupted"
    elif stop is not None:
        outcome = "stopped"
    elif isinstance(source, PausableSource) and source.state.value == "aborted":
        outcome = "aborted"
    summary = {
        "outcome": outcome,
        "completed": result.completed,
        "cycles": result.cycles,
        "bringup_s": box.bringup_s,
        "causes": [x.text for x in result.causes],
        "stats": result.stats,
        "run_record": str(box.record_path),
        "tension_file": None if tension_file is None else str(tension_file),
        "can_logs": record["can_logs"],
        "can_log_errors": log_errors,
    }
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        st = summary["stats"]
        print(f"bring-up: {summary['bringup_s']:.3f} s")
        print(
            f"cycles: {summary['cycles']}  jitter p99: {1e3 * st.get('jitter_p99_s', 0):.3f} ms"
            f"  late cycles: {st.get('late_cycles', 0)}"
            f"  missing feedback: {st.get('missing_feedback_node_cycles', 0)}"
        )
        print(f"run record: {summary['run_record']}")
    status = 0
    if interrupted is not None:
        print(f"hrm run: interrupted{interrupted}: every axis stopped", file=sys.stderr)
        return 130
    if summary["outcome"] == "aborted":
        where = source.describe().get("abort_reason") or "aborted"
        print(
            f"hrm run: {where}: stopped on the path at {display.where_text()}",
            file=sys.stderr if args.json else sys.stdout,
        )
    if stop is not None:
        print(f"hrm run: {stop}", file=sys.stderr)
        status = 2
    if log_errors:
        more = f" (+{len(log_errors) - 1} more log(s))" if len(log_errors) > 1 else ""
        print(
            f"hrm run: error: CAN log incomplete: {log_errors[0]}{more}; see {box.record_path}",
            file=sys.stderr,
        )
        status = 2
    return status


def _stream(box: Any, source: Any, driver: Any, display: Any) -> tuple[Any, Any, str | None]:
    """Stream ``source`` on the session ``box``: ``(result, safety stop or None, where an
    interrupt stopped it or None)``; the run driver (keys, run script) stops afterwards."""
    from drivers.session import SafetyStopError

    stop = interrupted = None
    try:
        result = box.stream(source)
    except SafetyStopError as exc:
        stop = exc
        result = exc.result
    except KeyboardInterrupt:  # every axis stopped (the supervisor): say where
        interrupted = "" if display is None else f" at {display.where_text()}"
        result = box.supervisor.last_result
    finally:
        if driver is not None:
            driver.stop()
    return result, stop, interrupted
