"""Benchmark: the online step of follow-the-leader driving (target: p99 <= 2 ms a step,
with the clearance fit).

Steers the tip through the paper's bent pipe by its key sequence
(:func:`hrm_ctrl.drive.script.bent_pipe_keys`, 20 mm/s, 100 Hz: 0.2 mm a step) with the
pipe as the environment, and times every online step (``OnlinePlanner.step``: modal
solve, paper fit, clearance refinement, checks) in wall time and in the CPU time of the
thread; prints JSON with the percentiles, where the time goes (the mean of each part of
:class:`~hrm_ctrl.drive.online.StepTimes`; the environment's free distances and the tip's
projection are parts of the refinement) and,
in the same run, the offline planner's per-step figure (``plan_path`` of the same pipe at
lambda = 5 mm, paper fit and refined) and the 1-minute load.

Run: ``python benchmarks/bench_drive.py [--repeats N] [--no-clearance]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine

from hrm_ctrl.drive.command import SteerLimits
from hrm_ctrl.drive.driver import Driver
from hrm_ctrl.drive.online import OnlinePlanner
from hrm_ctrl.drive.script import KeyScript, bent_pipe_keys
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import FitMode, PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario

PERIOD_S = 0.01
# StepTimes' parts; environment and projection are parts of refine
PARTS = ("modal", "fit", "refine", "checks", "environment", "projection")


def drive_once(clearance: bool) -> dict[str, list[float]]:
    """One drive through the pipe; per step: wall and CPU ms, and the parts (wall ms)."""
    model = default_robot()
    sc = scenario("bent-pipe")
    limits = SteerLimits(pitch_rate_rad_s=0.2, yaw_rate_rad_s=0.2)
    keys = KeyScript.parse(bent_pipe_keys(limits, period_s=PERIOD_S), "bent-pipe keys")
    P = sc.path.points
    trail = Trail.starting_at(P[0], P[1] - P[0])
    planner = OnlinePlanner(model, trail, sc.environment if clearance else None)
    drv = Driver(planner, limits, PERIOD_S)
    out: dict[str, list[float]] = {k: [] for k in ("wall", "cpu", *PARTS, "clearance")}
    step = planner.step

    def timed(d: float) -> object:  # the planner's own step, timed
        t0, c0 = time.perf_counter(), time.thread_time()
        r = step(d)
        c1, t1 = time.thread_time(), time.perf_counter()
        out["wall"].append((t1 - t0) * 1e3)
        out["cpu"].append((c1 - c0) * 1e3)
        tm = planner.times
        for k in PARTS:
            out[k].append(getattr(tm, k) * 1e3)
        out["clearance"].append(planner.clearance_mm)
        return r

    planner.step = timed  # type: ignore[method-assign]
    k = 0
    while k * PERIOD_S <= keys.end_s:
        s = drv.cycle(keys.command_at(k * PERIOD_S, limits))
        if s.refusal is not None:
            raise SystemExit(f"refused at cycle {k}: {s.refusal.text}")
        k += 1
    return out


def percentiles(v: list[float]) -> dict[str, float]:
    a = np.asarray(v)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p90": round(float(np.percentile(a, 90)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
    }


def offline_per_step() -> dict[str, float]:
    """The offline planner on the same pipe at lambda = 5 mm: ms per step."""
    model = default_robot()
    sc = scenario("bent-pipe")
    out = {}
    for name, fit in (("paper_fit", FitMode.PAPER), ("refined", FitMode.CLEARANCE)):
        opts = PlanOptions(step=5.0, fit=fit)
        t = time.perf_counter()
        plan = plan_path(model, sc.path, opts, scenario=sc)
        out[f"{name}_ms_per_step"] = round((time.perf_counter() - t) * 1e3 / len(plan.travel), 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-clearance", action="store_true", help="the paper fit alone")
    args = ap.parse_args()
    load_before = machine()["load_1min"]
    runs = [drive_once(not args.no_clearance) for _ in range(max(1, args.repeats))]
    merged = {k: [x for r in runs for x in r[k]] for k in runs[0]}
    print(
        json.dumps(
            {
                "benchmark": "drive: online step through the bent pipe, 0.2 mm a step",
                "clearance_fit": not args.no_clearance,
                "steps": len(merged["wall"]),
                "step_wall_ms": percentiles(merged["wall"]),
                "step_cpu_ms": percentiles(merged["cpu"]),
                "mean_parts_wall_ms": {k: round(float(np.mean(merged[k])), 3) for k in PARTS},
                "worst_clearance_mm": round(float(np.min(merged["clearance"])), 3),
                "offline_planner": offline_per_step(),
                "load_1min_before": load_before,
                "machine": machine(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
