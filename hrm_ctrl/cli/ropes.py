"""``hrm ropes``: motor setpoints (encoder counts) for every step of a plan, and a summary.

The plan goes through the one plan -> counts path that playback (``hrm run``) uses,
:func:`hrm_ctrl.ropes.setpoints.plan_setpoints`: every step's configuration through the
rope layer (exact rope lengths, stretch at the pretension, drum and encoder), the
plan's time-parameterised trajectory at the control rate of the bus configuration
(``--config``) with the tip at most ``--speed``, checked against the joint limits, the
drum travel and the motors' speed, acceleration and jerk before anything is written.  The
CSV lists the counts of every plan step with the time ``t_s`` the playback passes it
(``--cycles``: every control cycle of the playback instead); the summary adds what
playing it takes (duration, cycles, peak motor speed, acceleration and jerk, and what the
jerk bound costs: the duration without it).  The rope layer is the
calibrated arm's: the store's active calibration for this robot description
(``--calibrations DIR``; ``--uncalibrated``: the description's values).
"""

from __future__ import annotations

import argparse
import io
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    arm_from_args,
    calibrations_input,
    config_input,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._options import (
    Uncalibrated,
    add_bus,
    add_calibration,
    add_json,
    add_out,
    add_robot,
    add_speed,
)
from hrm_ctrl.errors import HrmError, RopeError
from hrm_ctrl.files import write_atomic

# the plan -> setpoints path: the runtime layer's (re-exported under the names used here)
from hrm_ctrl.runtime.playback import setpoint_summary as summary
from hrm_ctrl.runtime.playback import setpoints_of_plan

if TYPE_CHECKING:
    from hrm_ctrl.ropes.actuation import Actuation
    from hrm_ctrl.ropes.setpoints import PlanSetpoints

HELP = "motor setpoints (encoder counts per rope motor) for every step of a plan"


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("plan", type=Path, metavar="PLAN.json", help="plan file (hrm-plan/1)")
    add_robot(p)
    add_bus(p, overrides=False, config_use="its control rate is the playback's")
    add_out(p, metavar="SETPOINTS.csv", what="write the setpoint table")
    p.add_argument(
        "--cycles", action="store_true",
        help="the table lists every control cycle of the playback, not every plan step",
    )  # fmt: skip
    add_speed(p)
    add_json(p, "the summary")
    add_calibration(p, Uncalibrated.MODEL)


def format_csv(act: Actuation, sp: PlanSetpoints, *, cycles: bool = False) -> str:
    """The setpoint table: ``t_s,step,travel_mm,<motor ids...>``, then one row per plan
    step (the time the playback passes it) or, with ``cycles``, per control cycle (the
    plan step it came from, and its travel along the path)."""
    import numpy as np

    buf = io.StringIO()
    buf.write(",".join(["t_s", "step", "travel_mm", *act.motor_ids]) + "\n")
    if cycles:
        t, step, counts = sp.time_s, sp.step_of_row, sp.counts
        travel = sp.row_travel_mm()
    else:
        t, step, counts = sp.step_time_s, np.arange(sp.n_steps), sp.step_counts
        travel = sp.travel_mm
    for k in range(counts.shape[0]):
        buf.write(
            f"{t[k]:.6f},{int(step[k])},{travel[k]:.6f},"
            + ",".join(str(int(v)) for v in counts[k])
            + "\n"
        )
    return buf.getvalue()


def format_summary(s: dict[str, Any]) -> str:
    lines = [
        f"{s['steps']} steps, {len(s['motors'])} rope motors "
        "(travel: rope wound in from the zero position, + = in)",
        f"{'motor':6} {'min':>9} {'max':>9}  {'largest travel':>24}  {'largest step change':>26}",
    ]
    for m in s["motors"]:
        lines.append(
            f"{m['motor']:6} {m['min_counts']:>9} {m['max_counts']:>9}  "
            f"{m['largest_travel_mm']:>9.3f} mm @ step {m['largest_travel_step']:<5}  "
            f"{m['largest_change_counts']:>7} cts ({m['largest_change_mm']:.3f} mm) "
            f"@ {m['largest_change_step']:<5}"
        )
    worst_t = max(s["motors"], key=lambda m: abs(m["largest_travel_mm"]))
    worst_c = max(s["motors"], key=lambda m: m["largest_change_counts"])
    worst_r = max(
        s["motors"], key=lambda m: m["peak_rate_counts_per_s"] / m["rate_limit_counts_per_s"]
    )
    worst_a = max(
        s["motors"], key=lambda m: m["peak_accel_counts_per_s2"] / m["accel_limit_counts_per_s2"]
    )
    worst_j = max(
        s["motors"], key=lambda m: m["peak_jerk_counts_per_s3"] / m["jerk_limit_counts_per_s3"]
    )
    pb = s["playback"]
    lines.append(
        f"largest travel: {worst_t['motor']} {worst_t['largest_travel_mm']:.3f} mm at step "
        f"{worst_t['largest_travel_step']}; largest step change: {worst_c['motor']} "
        f"{worst_c['largest_change_counts']} counts at step {worst_c['largest_change_step']}"
    )
    lines.append(
        f"played with the tip at most {pb['speed_mm_per_s']:g} mm/s: {pb['duration_s']:.3f} s, "
        f"{pb['cycles']} control cycles of {1e3 * pb['period_s']:g} ms; fastest motor "
        f"{worst_r['motor']} {worst_r['peak_rate_counts_per_s']:.0f} counts/s "
        f"({100 * worst_r['peak_rate_counts_per_s'] / worst_r['rate_limit_counts_per_s']:.1f}% "
        f"of its limit), hardest accelerating {worst_a['motor']} "
        f"{worst_a['peak_accel_counts_per_s2']:.0f} counts/s^2 "
        f"({100 * worst_a['peak_accel_counts_per_s2'] / worst_a['accel_limit_counts_per_s2']:.1f}%)"
    )
    without = pb["duration_without_jerk_bound_s"]
    cost = pb["jerk_bound_cost_s"]
    lines.append(
        f"jerk-limited: hardest jerking {worst_j['motor']} "
        f"{worst_j['peak_jerk_counts_per_s3']:.4g} counts/s^3 "
        f"({100 * worst_j['peak_jerk_counts_per_s3'] / worst_j['jerk_limit_counts_per_s3']:.1f}%); "
        f"the jerk bound costs {cost:.3f} s ({100 * cost / without if without else 0.0:.1f}% "
        f"over {without:.3f} s without it)"
    )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from drivers.config import load_box_config
    from hrm_ctrl.formats.planfile import read_plan
    from hrm_ctrl.model import load_robot

    refuse_overwriting_inputs(  # before anything is read or written
        [Output("--out", args.out)],
        [
            Input("plan file", args.plan),
            robot_input(args.robot),
            config_input(args.config),
            calibrations_input(args),
            *shipped_inputs(plan_schema=True),
        ],
    )
    if not (math.isfinite(args.speed) and args.speed > 0.0):
        raise RopeError(f"--speed must be > 0 mm/s, got {args.speed}")
    doc = read_plan(args.plan)
    arm = arm_from_args(args, load_robot(args.robot), prog="hrm ropes")
    act = arm.actuation
    period_s = load_box_config(args.config).control.period_s
    from hrm_ctrl.cli._progress import progress_bar, wanted

    with progress_bar("time parameterisation", enabled=wanted(args.json)) as bar:
        sp = setpoints_of_plan(doc, act, period_s=period_s, speed_mm_per_s=args.speed,
                               progress=bar)  # fmt: skip
    arm.say_calibration("hrm ropes")
    s = summary(act, sp)
    if args.out is not None:
        try:
            write_atomic(args.out, format_csv(act, sp, cycles=args.cycles))
        except OSError as exc:
            raise HrmError(f"{args.out}: cannot write setpoints ({exc.strerror or exc})") from None
    print(json.dumps(s, indent=1) if args.json else format_summary(s))
    if args.out is not None and not args.json:
        print(f"setpoints written to {args.out}")
    return 0
