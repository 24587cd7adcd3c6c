"""Benchmark: planning among many obstacles that cannot matter (issue 34).

The bent pipe planned (``fit=clearance``, the default: search and refinement against the
environment) with N small boxes (20 mm cubes) scattered 1.5-3 m from the middle of the
path, none near the pipe.  Prints JSON: per N, the whole plan's CPU and wall time (median
of the repeats), with the boxes' spatial index (:class:`BoxIndex`, what the planner uses)
and, up to ``--every-box-up-to`` boxes, with every box evaluated at every point (the
algorithm before the index, for comparison); and the free distance of one plan's link
samples (12 x 33 per step) both ways.

Run: ``python benchmarks/bench_obstacles.py [--repeats N] [--every-box-up-to N]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine

from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.environment import (
    SAMPLES_PER_SEGMENT,
    Box,
    BoxIndex,
    Environment,
    Obstacle,
)
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario

BOX_MM = 20.0
SEED = 34


class EveryBoxEnvironment(Environment):
    """The same obstacles, every one evaluated at every point (no index)."""

    @property
    def _broad_phase(self) -> tuple[tuple[Obstacle, ...], tuple[BoxIndex, ...]]:  # type: ignore[override]
        return self.obstacles, ()


def far_boxes(n: int, centre: np.ndarray) -> list[Box]:
    """``n`` 20 mm cubes 1.5-3 m from ``centre`` in random directions (seeded)."""
    rng = np.random.default_rng(SEED)
    u = rng.normal(size=(n, 3))
    u *= (rng.uniform(1500.0, 3000.0, n) / np.linalg.norm(u, axis=1))[:, None]
    return [Box(centre + x, np.full(3, BOX_MM)) for x in u]


def timed(fn: Callable[[], Any], repeats: int) -> dict[str, float]:
    cpu, wall = [], []
    for _ in range(repeats):
        c, w = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return {"cpu_s": statistics.median(cpu), "wall_s": statistics.median(wall)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--counts", default="0,30,100,300,1000", help="numbers of boxes")
    ap.add_argument(
        "--every-box-up-to",
        type=int,
        default=100,
        help="plan without the index only up to this many boxes (it grows by ~0.1 s a box)",
    )
    args = ap.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats must be >= 1")
    counts = [int(v) for v in args.counts.split(",")]
    model = default_robot()
    base = scenario("bent-pipe")
    middle = base.path.points.mean(axis=0)
    opts = PlanOptions(step=5.0)
    plan_path(model, base.path, opts, scenario=base)  # warm-up (imports, caches)
    rows = []
    for n in counts:
        obstacles = (*base.environment.obstacles, *far_boxes(n, middle))
        row: dict[str, Any] = {"boxes": n}
        for name, env in (
            ("indexed", Environment(obstacles)),
            ("every_box", EveryBoxEnvironment(obstacles)),
        ):
            if name == "every_box" and n > args.every_box_up_to:
                continue
            sc = base.with_environment(env)
            row[f"plan_{name}"] = timed(
                lambda sc=sc: plan_path(model, sc.path, opts, scenario=sc), args.repeats
            )
        rows.append(row)
    # the free distance of one plan's link samples, both ways
    plan = plan_path(model, base.path, opts, scenario=base)
    O = plan.joints
    t = np.linspace(0.0, 1.0, SAMPLES_PER_SEGMENT)
    P = O[:, :-1, None, :] + t[None, None, :, None] * (O[:, 1:] - O[:, :-1])[:, :, None, :]
    distance = []
    for n in counts:
        obstacles = (*base.environment.obstacles, *far_boxes(n, middle))
        fast, slow = Environment(obstacles), EveryBoxEnvironment(obstacles)
        fast.free_distance(P[:1])  # builds the index
        entry = {
            "boxes": n,
            "points": int(np.prod(P.shape[:-1])),
            "indexed": timed(lambda e=fast: e.free_distance_and_gradient(P), args.repeats),
            "every_box": timed(lambda e=slow: e.free_distance_and_gradient(P), args.repeats),
        }
        same = np.abs(fast.free_distance(P) - slow.free_distance(P)).max()
        entry["largest_difference_mm"] = float(same)
        distance.append(entry)
    out = {
        "benchmark": "bent pipe planned among N far 20 mm boxes (fit=clearance)",
        "steps": len(plan.travel),
        "repeats": args.repeats,
        "plan": rows,
        "free_distance_of_link_samples": distance,
        "machine": machine(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
