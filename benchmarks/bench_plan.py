"""Benchmark: plan the bent pipe at lambda = 5 mm (target: whole plan <= 50 ms).

Prints JSON: steps; the whole plan (median and best of the repeats) without and
with the obstacle-clearance check; the per-step cost of the sequential part (the
warm-started modal solve of each step) and of a whole step (sequential part plus
the step's share of the batched fitting, joint angles, FK and report).

Run: ``python benchmarks/bench_plan.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine

from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    model = default_robot()
    sc = scenario("bent-pipe")
    opts = PlanOptions(step=5.0)
    plan_path(model, sc.path, opts)  # warm-up (imports, caches)
    plain: list[float] = []
    with_obstacles: list[float] = []
    plan = None
    for _ in range(args.repeats):
        t = time.perf_counter()
        plan = plan_path(model, sc.path, opts)
        plain.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        plan_path(model, sc.path, opts, scenario=sc)
        with_obstacles.append((time.perf_counter() - t) * 1e3)
    if plan is None:
        raise SystemExit("--repeats must be >= 1")
    n = len(plan.travel)
    step_ms = plan.step_time_s * 1e3  # of the last plain plan
    out = {
        "benchmark": "plan bent-pipe, lambda 5 mm",
        "steps": n,
        "repeats": args.repeats,
        "total_ms": {"median": statistics.median(plain), "best": min(plain)},
        "total_with_clearance_ms": {
            "median": statistics.median(with_obstacles),
            "best": min(with_obstacles),
        },
        "per_step_ms": {
            "median": float(np.median(step_ms)),
            "p99": float(np.percentile(step_ms, 99)),
            "note": "sequential modal solve of the step plus its even share of the batched "
            "fitting, joint angles and FK",
        },
        "target_total_ms": 50.0,
        "solver_iterations": int(plan.iterations.sum()),
        "machine": machine(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
