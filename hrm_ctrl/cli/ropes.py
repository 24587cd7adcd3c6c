"""``hrm ropes``: motor setpoints (encoder counts) for every step of a plan, and a summary.

Every step's configuration goes through the rope layer (exact rope lengths,
stretch at the pretension, drum and encoder); the whole table is checked
against the joint limits, the drum travel and, at the given travel speed along
the path, the motors' speed before anything is written.
"""

from __future__ import annotations

import argparse
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.cli._common import add_robot_argument
from hrm_ctrl.errors import HrmError, RopeError
from hrm_ctrl.files import write_atomic
from hrm_ctrl.formats.planfile import read_plan
from hrm_ctrl.model import load_robot
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError, load_actuation

HELP = "motor setpoints (encoder counts per rope motor) for every step of a plan"


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("plan", type=Path, metavar="PLAN.json", help="plan file (hrm-plan/1)")
    add_robot_argument(p)
    p.add_argument("--out", type=Path, metavar="SETPOINTS.csv", help="write the setpoint table")
    p.add_argument(
        "--speed",
        type=float,
        default=10.0,
        metavar="MM_PER_S",
        help="travel speed of the arm along the path, for the motor-speed check (default 10)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def plan_angles(plan: dict[str, Any], act: Actuation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(travel (N,), alpha (N, 12), theta (N, 12)) of a validated plan for this arm."""
    links = np.asarray(plan["robot"]["links_mm"], dtype=float)
    if not np.allclose(links, act.robot.links, rtol=0.0, atol=1e-6):
        raise RopeError(
            f"plan was made for links {links.tolist()} mm, the robot description "
            f"({act.robot.source}) has {act.robot.links.tolist()} mm"
        )
    steps = plan["steps"]
    travel = np.array([s["travel_mm"] for s in steps], dtype=float)
    alpha = np.array([s["alpha_rad"] for s in steps], dtype=float)
    theta = np.array([s["theta_rad"] for s in steps], dtype=float)
    return travel, alpha, theta


def setpoint_table(
    act: Actuation, travel: np.ndarray, alpha: np.ndarray, theta: np.ndarray, speed_mm_s: float
) -> np.ndarray:
    """Checked counts (N, n) for a plan's steps; :class:`RopeLimitError` names step, joint, rope."""
    if not (math.isfinite(speed_mm_s) and speed_mm_s > 0.0):
        raise RopeError(f"--speed must be > 0 mm/s, got {speed_mm_s}")
    counts = act.counts_from_angles(alpha, theta)  # checks angles and drum travel per step
    if counts.shape[0] > 1:
        dt = np.maximum(np.abs(np.diff(travel)), 1e-9) / speed_mm_s
        act.check_counts(counts, dt_s=dt)
    return counts


def summary(act: Actuation, travel: np.ndarray, counts: np.ndarray) -> dict[str, Any]:
    """Largest travel and step-to-step change per motor (counts and mm of rope)."""
    cpm = act.motors.counts_per_mm
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
            }
        )
    return {
        "steps": int(counts.shape[0]),
        "motors": motors,
        "travel_mm": [float(travel[0]), float(travel[-1])],
    }


def format_csv(act: Actuation, travel: np.ndarray, counts: np.ndarray) -> str:
    """The setpoint table: ``step,travel_mm,<motor ids...>`` then one row per step."""
    buf = io.StringIO()
    buf.write(",".join(["step", "travel_mm", *act.motor_ids]) + "\n")
    for k in range(counts.shape[0]):
        buf.write(f"{k},{travel[k]:.6f}," + ",".join(str(int(v)) for v in counts[k]) + "\n")
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
    lines.append(
        f"largest travel: {worst_t['motor']} {worst_t['largest_travel_mm']:.3f} mm at step "
        f"{worst_t['largest_travel_step']}; largest step change: {worst_c['motor']} "
        f"{worst_c['largest_change_counts']} counts at step {worst_c['largest_change_step']}"
    )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    plan = read_plan(args.plan)
    act = load_actuation(load_robot(args.robot))
    travel, alpha, theta = plan_angles(plan, act)
    try:
        counts = setpoint_table(act, travel, alpha, theta, args.speed)
    except RopeLimitError as exc:
        raise RopeLimitError(f"{args.plan}: {exc}") from None
    s = summary(act, travel, counts)
    if args.out is not None:
        try:
            write_atomic(args.out, format_csv(act, travel, counts))
        except OSError as exc:
            raise HrmError(f"{args.out}: cannot write setpoints ({exc.strerror or exc})") from None
    print(json.dumps(s, indent=1) if args.json else format_summary(s))
    if args.out is not None and not args.json:
        print(f"setpoints written to {args.out}")
    return 0
