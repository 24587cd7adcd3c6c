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
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    calibrations_input,
    config_input,
    load_arm,
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

if TYPE_CHECKING:
    from hrm_ctrl.formats.planfile import PlanDoc
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


def setpoints_of_plan(
    doc: PlanDoc,
    act: Actuation,
    *,
    period_s: float,
    speed_mm_per_s: float,
    max_duration_s: float | None = None,
    progress: Callable[[float], None] | None = None,
) -> PlanSetpoints:
    """The plan's checked counts at the control rate for this arm: what ``hrm ropes``
    reports and ``hrm run`` plays (``max_duration_s`` None:
    :data:`hrm_ctrl.ropes.setpoints.MAX_PLAN_DURATION_S`).  Refuses a plan made for other
    link lengths; every message starts with the plan file."""
    from hrm_ctrl.ropes.setpoints import MAX_PLAN_DURATION_S, plan_setpoints

    if max_duration_s is None:
        max_duration_s = MAX_PLAN_DURATION_S
    doc.check_robot(act.robot)
    return plan_setpoints(
        act,
        doc.travel_mm,
        doc.alpha_rad,
        doc.theta_rad,
        phase=doc.phase,
        period_s=period_s,
        speed_mm_per_s=speed_mm_per_s,
        max_duration_s=max_duration_s,
        where=doc.source,
        progress=progress,
    )


def summary(act: Actuation, sp: PlanSetpoints) -> dict[str, Any]:
    """Largest travel and step-to-step change per motor (counts and mm of rope) over the
    plan's steps, and the playback at the control rate (duration, cycles, peak motor
    speed and acceleration: finite differences of the counts sent, from and to rest)."""
    import numpy as np

    from hrm_ctrl.ropes.trajectory import finite_differences, finite_jerk

    travel, counts = sp.travel_mm, sp.step_counts
    cpm = act.motors.counts_per_mm
    rates, accels = finite_differences(sp.counts, sp.period_s)
    jerks = finite_jerk(sp.counts, sp.period_s)
    j_limit = np.asarray(act.max_jerk_counts_per_s3, dtype=np.float64)
    limit = np.asarray(act.max_rate_counts_per_s, dtype=np.float64)
    a_limit = np.asarray(act.max_accel_counts_per_s2, dtype=np.float64)
    rel = counts - act.motors.zero_offsets_counts
    k_travel = np.abs(rel).argmax(axis=0)
    diff = np.abs(np.diff(counts, axis=0)) if counts.shape[0] > 1 else np.zeros((1, act.n_motors))
    k_diff = diff.argmax(axis=0)
    motors = []
    for i, mid in enumerate(act.motor_ids):
        motors.append(
            {
                "motor": mid,
                "min_counts": int(counts[:, i].min()),
                "max_counts": int(counts[:, i].max()),
                "largest_travel_counts": int(rel[k_travel[i], i]),
                "largest_travel_mm": float(act.motors.direction[i] * rel[k_travel[i], i] / cpm[i]),
                "largest_travel_step": int(k_travel[i]),
                "largest_change_counts": int(diff[k_diff[i], i]),
                "largest_change_mm": float(diff[k_diff[i], i] / cpm[i]),
                "largest_change_step": int(k_diff[i]) + 1 if counts.shape[0] > 1 else 0,
                "peak_rate_counts_per_s": float(rates[i]),
                "rate_limit_counts_per_s": float(limit[i]),
                "peak_accel_counts_per_s2": float(accels[i]),
                "accel_limit_counts_per_s2": float(a_limit[i]),
                "peak_jerk_counts_per_s3": float(jerks[i]),
                "jerk_limit_counts_per_s3": float(j_limit[i]),
            }
        )
    return {
        "steps": int(counts.shape[0]),
        "motors": motors,
        "travel_mm": [float(travel[0]), float(travel[-1])],
        "playback": {
            "speed_mm_per_s": sp.speed_mm_per_s,
            "period_s": sp.period_s,
            "duration_s": round(sp.duration_s, 9),
            "cycles": sp.n_cycles,
            # the jerk bound's cost: the playback without it (TOPP-RA alone) and the difference
            "duration_without_jerk_bound_s": round(sp.law_duration_s, 9),
            "jerk_bound_cost_s": round(sp.jerk_cost_s, 9),
        },
    }


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
    arm = load_arm(args, load_robot(args.robot), prog="hrm ropes")
    act = arm.actuation
    period_s = load_box_config(args.config).control.period_s
    from hrm_ctrl.cli._progress import progress_bar, wanted

    with progress_bar("time parameterisation", enabled=wanted(args.json)) as bar:
        sp = setpoints_of_plan(doc, act, period_s=period_s, speed_mm_per_s=args.speed,
                               progress=bar)  # fmt: skip
    arm.say_note()
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
