"""Time parameterisation speed: a plan -> the counts of every control cycle (TOPP-RA).

Run ``python benchmarks/bench_trajectory.py [--repeats N]``; prints one JSON object.
Target (issue 10): time parameterisation <= 100 ms for the bent pipe (lambda = 5 mm,
with the return leg: 271 steps, 36 motors).  Timed: ``step_path`` + ``time_parameterise``
(the splines, the counts path and its derivatives on the grid, TOPP-RA per leg, the
sampling at 100 Hz through the rope layer and the finite-difference check of the integer
table), and the whole ``plan_setpoints`` (with its step and row checks) besides.  Medians
and 99th percentiles of wall-clock repetitions, after one warm-up (toppra's import).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine

from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.ropes.setpoints import DEFAULT_TIP_SPEED_MM_PER_S, plan_setpoints
from hrm_ctrl.ropes.trajectory import (
    finite_differences,
    step_path,
    time_parameterise,
)

TARGET_MS = 100.0
PERIOD_S = 0.01


def stats(ms: list[float]) -> dict[str, Any]:
    a = np.asarray(ms)
    med = float(np.median(a))
    return {
        "median_ms": round(med, 2),
        "min_ms": round(float(a.min()), 2),
        "p99_ms": round(float(np.percentile(a, 99)), 2),
        "target_ms": TARGET_MS,
        "meets_target": med <= TARGET_MS,
    }


def bench(name: str, speed: float, repeats: int) -> dict[str, Any]:
    robot = default_robot()
    act = load_actuation(robot)
    sc = scenario(name)
    plan = plan_path(robot, sc.path, PlanOptions(step=5.0, return_to_start=True), sc)
    phase = list(plan.phase)

    def parameterise() -> Any:
        path = step_path(plan.travel, plan.alpha, plan.theta, phase)
        return time_parameterise(act, path, period_s=PERIOD_S, tip_speed_mm_per_s=speed)

    def setpoints() -> Any:
        return plan_setpoints(
            act, plan.travel, plan.alpha, plan.theta, phase=phase, period_s=PERIOD_S,
            speed_mm_per_s=speed,
        )  # fmt: skip

    tr = parameterise()  # warm-up
    setpoints()
    t_param, t_all = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        parameterise()
        t1 = time.perf_counter()
        setpoints()
        t2 = time.perf_counter()
        t_param.append((t1 - t0) * 1e3)
        t_all.append((t2 - t1) * 1e3)
    v, a = finite_differences(tr.counts, PERIOD_S)
    return {
        "scenario": name,
        "steps": len(plan.travel),
        "legs": len(tr.leg_rows),
        "tip_speed_cap_mm_per_s": speed,
        "cycles": tr.n_rows,
        "duration_s": round(tr.duration_s, 3),
        "duration_at_the_cap_s": round(float(np.abs(np.diff(plan.travel)).sum()) / speed, 3),
        # what the motors' jerk bound costs (issue 39's goal: at most 15 % longer)
        "duration_without_jerk_bound_s": round(tr.law_duration_s, 3),
        "jerk_bound_cost_pct": round(100.0 * tr.jerk_cost_s / tr.law_duration_s, 1),
        "peak_speed_of_limit": round(float((v / act.max_rate_counts_per_s).max()), 4),
        "peak_accel_of_limit": round(float((a / act.max_accel_counts_per_s2).max()), 4),
        "time_parameterisation": stats(t_param),
        "plan_setpoints_whole": stats(t_all),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    out = {
        "benchmark": "trajectory",
        "machine": machine(),
        "period_s": PERIOD_S,
        "runs": [
            bench("bent-pipe", DEFAULT_TIP_SPEED_MM_PER_S, args.repeats),
            bench("cabins", DEFAULT_TIP_SPEED_MM_PER_S, args.repeats),
            bench("bent-pipe", 500.0, args.repeats),
            bench("bent-pipe", 2000.0, args.repeats),  # the motors' limits bind
        ],
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
