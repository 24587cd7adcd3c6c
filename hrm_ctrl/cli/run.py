"""``hrm run``: play a plan (or a hold / a jog) on the rope-motor drives over CAN.

Loads the bus configuration (``--config``, default ``drivers/data/box.toml``)
and the robot description, refuses a bus over its load budget and a plan
outside the rope or joint limits before anything is sent, brings every drive
up (NMT, SDO, CiA 402 to operation enabled in CSP), streams the setpoints at the
control rate and disables the drives at the end.  While the drives are enabled the
tension-sensor board (when the configuration has a ``[tension]`` table) and the rope
layer's consistency check on the feedback watch the arm (``hrm_ctrl.cli._watches``):
either stops every axis, naming the rope.  Every run writes each bus's
traffic (``--log-format``: ``.blf``, ``.asc``, ``.log``, ``.trc``, ...) and a run
record JSON into ``--log-dir``; ``--bus NAME=INTERFACE:CHANNEL[@BITRATE]`` opens one bus
of the configuration elsewhere.

``--sim`` starts the simulated box (``sim_bus``) in this process on python-can
virtual buses (or, with ``--wire hrm_sim``, on the simulated wire at the configured
bitrate) instead of opening the configured interfaces; nothing else changes (the
drivers only see buses).

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
>>> str(a.plan), a.sim, a.speed
('plan.json', True, 50.0)
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    calibrations_input,
    config_input,
    load_arm,
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
    add_robot,
    add_run_controls,
    add_sim,
)
from hrm_ctrl.errors import DriverError

if TYPE_CHECKING:
    from hrm_ctrl.formats.planfile import PlanDoc

HELP = "play a plan (or hold / jog) on the CiA 402 rope-motor drives over CAN"


def register(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("plan", nargs="?", type=Path, metavar="PLAN.json", help="plan to play")
    add_bus(parser, take_over=True)  # --config, --bus, --take-over
    add_robot(parser)
    add_sim(parser, wire=True, arm=SimArm.PERTURB_OR_TRUTH)  # --sim, --wire, --perturb | --truth
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
    add_json(parser, "the summary")


def _plan_record(path: Path, plan: PlanDoc) -> dict[str, Any]:
    """What the run record keeps of the plan: file, sha256 of its bytes, format, steps."""
    from hrm_ctrl.formats.planfile import PLAN_FORMAT

    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise DriverError(f"{path}: cannot read plan file ({exc.strerror or exc})") from None
    return {
        "plan_file": str(path),
        "plan_sha256": digest,
        "plan_format": PLAN_FORMAT,
        "plan_steps": plan.n_steps,
    }


def refuse_collision(doc: PlanDoc, allow: bool, model: Any = None) -> None:
    """Refuse (one line naming step and link) a plan whose arm meets an obstacle: its
    stored clearance (``report.clearance_mm``), and the clearance recomputed against the
    environment it stores, of the stored joint centres and of the joints its angles put
    ``model``'s arm at (the robot that plays it: an edited summary or edited joint centres
    cannot hide a collision).  With ``allow`` (``--allow-collision``) a warning line on
    stderr instead."""
    from hrm_ctrl.planning.report import check_clearance, clearance_summary, plan_file_clearance

    c = plan_file_clearance(doc, model=model)
    for summary in (doc.clearance, None if c is None else clearance_summary(c)):
        if summary is None:
            continue
        if not allow:
            check_clearance(dict(summary), doc.source)
        elif summary.get("min") is not None and summary["min"] < 0.0:
            print(
                f"hrm run: warning: {doc.source}: link {summary['link']} meets an obstacle at "
                f"step {summary['step']} (clearance {summary['min']:.2f} mm); played as "
                "--allow-collision asks",
                file=sys.stderr,
            )
            return


def _source(
    args: argparse.Namespace,
    actuation: Any,
    period_s: float,
    progress: Callable[[float], None] | None = None,
) -> tuple[Any, Any, dict[str, Any]]:
    """The setpoint source the arguments ask for, the hold time (s) of a hold, and what the
    run record keeps of a plan.  A plan goes through the rope layer's one plan -> counts
    path (as in ``hrm ropes``) at the control period ``period_s`` and is played by
    :class:`drivers.sources.CountsSource`."""
    from drivers.safety.limits import MAX_SOURCE_DURATION_S
    from drivers.sources import CountsSource, HoldSource, JogSource

    chosen = [x for x in (args.plan, args.hold, args.jog) if x is not None]
    if len(chosen) != 1:
        raise DriverError("give exactly one of PLAN.json, --hold S, --jog MOTOR:COUNTS_PER_S:S")
    if args.hold is not None:
        if not (math.isfinite(args.hold) and 0 < args.hold <= MAX_SOURCE_DURATION_S):
            raise DriverError(
                f"--hold must be > 0 s and at most {MAX_SOURCE_DURATION_S:g} s, got {args.hold}"
            )
        return HoldSource(n_cycles=None), args.hold, {}
    if args.jog is not None:
        parts = str(args.jog).split(":")
        try:
            motor, vel, dur = parts[0], float(parts[1]), float(parts[2])
        except (IndexError, ValueError):
            raise DriverError(f"--jog {args.jog!r}: expected MOTOR:COUNTS_PER_S:SECONDS") from None
        if len(parts) != 3 or not (math.isfinite(dur) and dur > 0):
            raise DriverError(f"--jog {args.jog!r}: expected MOTOR:COUNTS_PER_S:SECONDS (S > 0)")
        return JogSource(actuation, motor, vel, dur), None, {}
    from hrm_ctrl.cli.ropes import setpoints_of_plan
    from hrm_ctrl.formats.planfile import read_plan

    doc = read_plan(args.plan)
    refuse_collision(doc, args.allow_collision, actuation.robot)  # before anything is sent to a bus
    plan_record = _plan_record(Path(args.plan), doc)
    sp = setpoints_of_plan(
        doc,
        actuation,
        period_s=period_s,
        speed_mm_per_s=args.speed,
        max_duration_s=MAX_SOURCE_DURATION_S,
        progress=progress,
    )
    info = {
        "plan": str(args.plan),
        "steps": sp.n_steps,
        "speed_mm_per_s": sp.speed_mm_per_s,
        "duration_s": sp.duration_s,
    }
    source = CountsSource.of_plan(actuation, sp, info=info)
    source.plan_setpoints = sp  # type: ignore[attr-defined]  # the live line's travel
    return source, None, plan_record


def run(args: argparse.Namespace) -> int:
    from drivers.bus import ensure_log_dir
    from drivers.interrupts import deferred_interrupts
    from drivers.session import DriveSession, SafetyStopError
    from drivers.sources import HoldSource, PausableSource
    from hrm_ctrl.cli._progress import ProgressBar, bring_up_with_progress
    from hrm_ctrl.cli._progress import wanted as progress_wanted
    from hrm_ctrl.cli._runcontrol import RunDisplay, RunDriver, RunScript, write_run_tensions
    from hrm_ctrl.cli._simwire import sim_listen
    from hrm_ctrl.cli._watches import feedback_watches
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.ropes.actuation import load_actuation

    if not (math.isfinite(args.speed) and args.speed > 0):
        raise DriverError(f"--speed must be > 0 mm/s, got {args.speed}")
    if not args.sim and (args.perturb is not None or args.truth is not None):
        raise DriverError("--perturb and --truth describe the simulated arm: they go with --sim")
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
    arm = load_arm(args, load_robot(args.robot), prog="hrm run", simulated=args.sim)
    actuation = arm.actuation
    config.check_motors(actuation.motor_ids)
    script = RunScript.from_args(args)  # --pause-at etc.: refused before anything is sent
    if not script.empty and args.plan is None:
        raise DriverError("--pause-at and --abort-at go with a PLAN.json")
    show = progress_wanted(args.json)
    with ProgressBar("time parameterisation", enabled=show and args.plan is not None) as bar:
        source, hold_s, plan_record = _source(args, actuation, config.control.period_s, bar)
    setpoints = getattr(source, "plan_setpoints", None)
    if setpoints is not None:  # a plan: played pausable (keys, --pause-at, --abort-at)
        source = PausableSource(source, actuation)
    if isinstance(source, HoldSource) and hold_s is not None:
        source = HoldSource(n_cycles=max(1, round(hold_s * config.control.rate_hz)))
    source.precheck(config.control.period_s)  # refuse bad setpoints before any bus opens
    ensure_log_dir(args.log_dir)  # a bad log directory: one line, before any bus opens

    sim = None
    if args.sim:
        from hrm_ctrl.cli._simwire import calibration_counts, start_in_process_sim
        from sim_bus.truth import TrueArm, read_truth

        # the simulated arm is the robot description's (links too), not the calibration's,
        # or one that differs from it (--perturb, --truth)
        physical = actuation if arm.active is None else load_actuation(arm.description)
        truth = None
        if args.perturb is not None:
            truth = TrueArm.perturbed(physical, args.perturb)
        elif args.truth is not None:
            truth = read_truth(args.truth, physical)
        arm.say_note()  # --sim without a calibration: said once every check passed
        config, sim = start_in_process_sim(
            config,
            physical,
            args.wire,
            prog="hrm run",
            truth=truth,
            initial_counts=calibration_counts(
                None if arm.active is None else arm.active.calibration, physical
            ),
        )
    else:
        arm.say_note()  # --uncalibrated without a calibration
    summary: dict[str, Any] = {}
    interrupted: str | None = None
    driver = None
    try:
        stop: SafetyStopError | None = None
        with contextlib.ExitStack() as stack:
            with deferred_interrupts():  # the session is open and entered, or not at all
                box = stack.enter_context(
                    DriveSession(
                        config,
                        actuation,
                        log_dir=args.log_dir,
                        log_suffix=f".{args.log_format}",
                        take_over=args.take_over,
                        calibration=arm.calibration_ref(),
                        allow_uncalibrated=args.uncalibrated or args.sim,
                        **sim_listen(args.sim),
                    )
                )
                box.record_extra = {
                    "plan_file": None,
                    **plan_record,
                    "source": source.__class__.__name__,
                    "simulated_box": bool(args.sim),
                }
                # tension board opened first: a bad port is refused before any NMT reset
                watches = stack.enter_context(feedback_watches(config, actuation, box, start=False))
            bring_up_with_progress(box, enabled=show)
            watches.start()  # tension, ropes
            if isinstance(source, PausableSource):
                display = RunDisplay(source, setpoints, box, actuation.robot, watches)
                bar = stack.enter_context(ProgressBar("run", enabled=show))
                driver = RunDriver(source, script, keys=show, display=display, bar=bar)
                driver.start()
            try:
                result = box.stream(source)
            except SafetyStopError as exc:
                stop = exc
                result = exc.result
            except KeyboardInterrupt:  # every axis stopped (the supervisor): say where
                interrupted = (
                    f" at {display.where_text()}" if isinstance(source, PausableSource) else ""
                )
                result = box.supervisor.last_result
            finally:
                if driver is not None:
                    driver.stop()
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
    finally:
        if sim is not None:
            sim.stop()
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
