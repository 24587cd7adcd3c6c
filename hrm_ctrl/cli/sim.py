"""``hrm sim``: run the simulated manipulator box as its own process.

Opens every bus of the bus configuration (the drivers' ``box.toml``, read by
:func:`drivers.config.load_box_config` as the host reads it; any python-can
interface: ``udp_multicast`` here, whose ``hop_limit`` defaults to 0 so nothing
leaves the host, SocketCAN ``vcan0`` where the kernel has it), attaches a
simulated CiA 402 drive to every node, serves the tension-sensor board on a
pseudo-terminal and prints JSON lines (``ready`` with the pseudo-terminal path
first).  The process runs under :func:`drivers.realtime.process_settings`, entered
by :func:`hrm_ctrl.cli.main` like every command.  See ``docs/sim.md``.

The arm may differ from its description (issue 12): ``--truth FILE.toml`` (a truth file,
``sim_bus.truth``) or ``--perturb SEED`` (drawn within the issue's ranges; ``--max-slack
MM`` adds rope slack), and ``--write-truth FILE`` writes the truth used as a truth file
(never over an input).  ``--fixture`` starts the arm in its zero fixture (rope geometry straight),
``--tracker`` starts the laser tracker (its pseudo-terminal in ``ready`` as
``tracker_port``).

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm sim")
>>> register(p)
>>> a = p.parse_args(["--fault", "rope-snap:j05r2@3", "--duration", "10"])
>>> a.fault, a.duration
(['rope-snap:j05r2@3'], 10.0)
>>> p.parse_args(["--perturb", "7", "--tracker"]).perturb
7
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from hrm_ctrl.cli._common import (
    Input,
    Output,
    config_input,
    load_box,
    refuse_overwriting_inputs,
    robot_input,
)
from hrm_ctrl.cli._options import SimArm, add_bus, add_physics, add_robot, add_sim_arm
from hrm_ctrl.errors import SimError

HELP = "run the simulated manipulator box (CiA 402 drives, arm, tension board) on the buses"
# Slowest tension-sensor frame rate: a frame at least every second (a slower board is a
# silent one; ``--fault sensor-silent`` simulates that).  The board waits one period between
# frames, and a wait must stay within what the platform's timed waits take.
MIN_TENSION_RATE_HZ = 1.0


def register(parser: argparse.ArgumentParser) -> None:
    add_bus(parser)  # --config, --bus
    add_robot(parser)
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="SPEC",
        help="inject a fault, KIND[:ARG...][@SECONDS], e.g. rope-snap:j05r2@3, "
        "heartbeat-stop:j01r0@2, drive-fault:j03r1, drop:can0:0x181:all@1, bus-off:can1@4, "
        "sensor-garbage, sensor-silent@5 (repeatable)",
    )
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    add_physics(parser, when=None)  # --physics EFFECTS
    parser.add_argument(
        "--tension-rate",
        type=float,
        default=100.0,
        metavar="HZ",
        help="tension-sensor frame rate (default 100 Hz)",
    )
    parser.add_argument(
        "--control",
        action="store_true",
        help="read commands from stdin (fault SPEC, state, trace on|off, trace, stats, "
        "fixture on|off, tracker-lost on|off, truth, quit)",
    )
    add_sim_arm(parser, SimArm.PERTURB_OR_TRUTH, when=None)  # --perturb SEED | --truth FILE
    parser.add_argument(
        "--max-slack",
        type=float,
        default=0.0,
        metavar="MM",
        help="with --perturb: rope slack drawn in [0, MM] per rope (default 0)",
    )
    parser.add_argument(
        "--write-truth",
        type=Path,
        default=None,
        metavar="TRUTH.toml",
        help="write the truth used as a truth file (atomic; never over an input)",
    )
    parser.add_argument(
        "--fixture",
        action="store_true",
        help="start with the arm in its zero fixture (control: fixture off)",
    )
    parser.add_argument(
        "--tracker",
        action="store_true",
        help="start the laser tracker (its pseudo-terminal in 'ready' as tracker_port)",
    )
    parser.add_argument(
        "--initial-counts",
        default=None,
        metavar="COUNTS",
        help="where the motors stand at power-on, comma-separated counts in the rope layer's "
        "motor order (default all 0): a box a calibration has zeroed",
    )
    parser.add_argument(
        "--cpus",
        default=None,
        metavar="LIST",
        help="run the box on these CPUs only (taskset's list: 1, 0,2, 2-3), off the CPUs "
        "of the host's control loop, as the drives' own hardware would be",
    )
    parser.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        metavar="PRIORITY",
        help="run every box thread under SCHED_FIFO at PRIORITY (1..49, as box.toml's "
        "realtime_priority; 0: normal scheduling, the default), as the drives' firmware "
        "runs in real time; refused (exit 2) where the process may not",
    )


def run(args: argparse.Namespace) -> int:
    from drivers.realtime import REALTIME_PRIORITY_SAFE_MAX, parse_cpus, process_settings
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.ropes.actuation import load_actuation
    from sim_bus.faults import parse_fault
    from sim_bus.physics import Physics
    from sim_bus.runner import run_box_process
    from sim_bus.truth import TRUTH_SLACK_MAX_MM, TrueArm, read_truth, write_truth

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise SimError(f"--duration must be > 0 s, got {args.duration}")
    if not (MIN_TENSION_RATE_HZ <= args.tension_rate <= 10_000):  # nan fails too
        raise SimError(
            f"--tension-rate must be in [{MIN_TENSION_RATE_HZ:g}, 10000] Hz, "
            f"got {args.tension_rate}"
        )
    cpus = None if args.cpus is None else parse_cpus(args.cpus)
    if not 0 <= args.rt_priority <= REALTIME_PRIORITY_SAFE_MAX:
        raise SimError(
            f"--rt-priority must be in 0..{REALTIME_PRIORITY_SAFE_MAX}, got {args.rt_priority}"
        )
    faults = [parse_fault(f) for f in args.fault]
    physics = None if args.physics is None else Physics.of(args.physics)
    initial_counts = None if args.initial_counts is None else parse_counts(args.initial_counts)
    if args.max_slack and args.perturb is None:
        raise SimError("--max-slack needs --perturb SEED (a truth file says its own slack)")
    if not 0.0 <= args.max_slack <= TRUTH_SLACK_MAX_MM:  # nan fails too
        raise SimError(
            f"--max-slack must be in [0, {TRUTH_SLACK_MAX_MM:g}] mm, got {args.max_slack}"
        )
    refuse_overwriting_inputs(
        [Output("--write-truth", args.write_truth)],
        [
            Input("truth file", args.truth),
            robot_input(args.robot),
            config_input(args.config),
        ],
    )
    config = load_box(args)  # --config with the --bus overrides
    actuation = load_actuation(load_robot(args.robot))
    truth = None
    if args.truth is not None:
        truth = read_truth(args.truth, actuation)
    elif args.perturb is not None:
        truth = TrueArm.perturbed(actuation, args.perturb, max_slack_mm=args.max_slack)
    if args.write_truth is not None:
        write_truth(args.write_truth, truth if truth is not None else TrueArm.nominal(actuation))
    known = set(actuation.motor_ids)
    if initial_counts is not None and len(initial_counts) != len(known):
        raise SimError(f"--initial-counts: {len(initial_counts)} values for {len(known)} motors")
    buses = {b.name for b in config.buses}
    for f in faults:
        if f.kind in ("heartbeat-stop", "heartbeat-resume", "drive-fault", "jam", "rope-snap"):
            if f.args[0] not in config.motor_ids or f.args[0] not in known:
                raise SimError(f"--fault {f.kind}: no simulated drive for motor '{f.args[0]}'")
        if f.kind in ("drop", "delay", "bus-off", "bus-on") and f.args[0] not in buses:
            raise SimError(f"--fault {f.kind}: no bus '{f.args[0]}' (have {sorted(buses)})")
    # every box thread (threads inherit the policy of the thread that starts them)
    with process_settings(
        switch_interval_s=None, cpus=cpus, realtime_priority=args.rt_priority
    ) as applied:
        if args.rt_priority and not applied.realtime_granted:
            raise SimError(f"--rt-priority: {applied.realtime_refusal}")
        return run_box_process(
            config,
            actuation=actuation,
            faults=faults,
            duration_s=args.duration,
            tension_rate_hz=args.tension_rate,
            control=args.control,
            truth=truth,
            fixture=args.fixture,
            tracker=args.tracker,
            initial_counts=initial_counts,
            physics=physics,
        )


def parse_counts(text: str) -> list[int]:
    """``--initial-counts``: comma-separated integer motor counts.

    >>> parse_counts("0,-12,5000")
    [0, -12, 5000]
    >>> parse_counts("1,x")
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.SimError: --initial-counts: 'x' is not an integer count
    """
    counts = []
    for part in text.split(","):
        try:
            counts.append(int(part))
        except ValueError:
            shown = part.strip()[:20]
            raise SimError(f"--initial-counts: {shown!r} is not an integer count") from None
    return counts
