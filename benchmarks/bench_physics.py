"""Benchmark: what the simulated arm's physics does to today's stack, and the compensation.

The demo's motion (issue 38 item 2): the reference scenario planned with the robot
description's values (``hrm demo --no-calibrate``: the host's model is the arm's), at the
demo's tip speed and the control period of 10 ms, with return.  The motors are taken
exactly where the host commands them (the drives reach a setpoint within one cycle:
their lag is not the subject), after a lead-in from the straight arm (2 s, straight in
counts) and a 1 s hold, and the arm's physics (``sim_bus.physics``) is stepped through
every cycle in time order (``SimArm.state``, as the box's tension board does at 100 Hz).
Once with no physics, once with every effect, once with each effect alone; each of those
once with the counts as planned and once with the feed-forward compensation
(``hrm_ctrl.ropes.feedforward``: every term on, the description's ``[physics]``; the host
does not know which effects the box has).

Per run: the rows (of the plan) at which a sensor reads outside the shipped tension
watch's band, 5-150 N (the watch would stop the run at the first); the true end point's
distance to the scenario's path (what ``hrm demo`` reports as ``end_point_vs_path``) max
and rms, there (up to the plan's turning point) and back;
its distance from the planned end point (the FK of the commanded configuration: what the
physics alone moves it by) max and rms; where it ends after returning; the arm state's
CPU (``time.thread_time``) per cycle, median and p99.

With ``--shape`` the compensated runs also read the arm's shape from the tension board
every cycle (``hrm_ctrl.ropes.tension_shape``, the friction tracked from the commanded
travel; its error against the simulated arm's rope-held angles max and median from the
ramp-in on, and its CPU per cycle); with ``--loop-gain G,...`` they close the loop on it
(each cycle the counts move by ``-G J dq`` of rope length, at most 0.01 mm per rope per
cycle; 0: the estimate alone), one run per gain.

Run: ``python benchmarks/bench_physics.py [--scenario bent-pipe] [--effects all,gravity]
[--counts plain,compensated] [--terms gravity,capstan,backlash] [--shape]
[--loop-gain 0,0.05]``; prints JSON (``feedforward_s``: the compensation's CPU, planning
without it subtracted).
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

from drivers.realtime import process_settings
from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.ropes.feedforward import Feedforward
from hrm_ctrl.ropes.setpoints import (
    DEFAULT_TIP_SPEED_MM_PER_S,
    FEEDFORWARD_RAMP_S,
    plan_setpoints,
)
from hrm_ctrl.ropes.tension_shape import TensionShape
from hrm_ctrl.runtime.playback import setpoints_of_plan
from sim_bus.arm import SimArm
from sim_bus.physics import Effect, Physics

PERIOD_S = 0.01
LEAD_IN_CYCLES = 200
HOLD_CYCLES = 100
VARIANTS = ("none", "all", *(e.value for e in Effect))
WATCH_N = (5.0, 150.0)  # the shipped tension watch (drivers/data/box.toml [tension])
RAMP_CYCLES = round(FEEDFORWARD_RAMP_S / PERIOD_S)
LOOP_RATE_MM = 0.01  # the closed loop's change per rope per cycle at most (1 mm/s)
TERMS = ("gravity", "capstan", "backlash")  # the feed-forward's (hrm_ctrl.ropes.feedforward)


def motion(
    name: str, speed: float, terms: frozenset[str] | None = None
) -> tuple[Any, np.ndarray, np.ndarray, int, float, np.ndarray]:
    """(the scenario, every cycle's counts (lead-in, hold, plan), the planned end point
    of each plan row, the index of the plan's first row (after a feed-forward's ramp-in),
    the compensation's CPU s, every cycle's rope-held target angles (cycles, 2, 12));
    ``terms``: the feed-forward's terms (None: no compensation)."""
    robot = default_robot()
    act = load_actuation(robot)
    sc = scenario(name)
    plan = plan_path(
        robot,
        sc.path,
        PlanOptions(step=5.0, return_to_start=True),
        scenario=sc,
        environment=sc.environment,
    )
    doc = PlanDoc.from_dict(plan.to_dict(), sc.name)
    t0 = time.process_time()
    sp = setpoints_of_plan(doc, act, period_s=PERIOD_S, speed_mm_per_s=speed)
    cpu = -(time.process_time() - t0)  # the compensation's: the difference of the two
    if terms is not None:
        t0 = time.process_time()
        ff = Feedforward.of(act, **{t: t in terms for t in TERMS})
        sp = plan_setpoints(act, doc.travel_mm, doc.alpha_rad, doc.theta_rad, phase=doc.phase,
                            period_s=PERIOD_S, speed_mm_per_s=speed, feedforward=ff)  # fmt: skip
        cpu += time.process_time() - t0
    a, t = sp.row_angles()
    planned_tip = joint_centres(robot, a, t)[:, -1]
    on = {t: t in (terms or TERMS) for t in TERMS}
    ha, ht = Feedforward.of(act, **on).held_angles(a, t)  # what the shape estimate aims at
    held = np.stack([ha, ht], axis=1)
    held = np.concatenate([np.repeat(held[:1], LEAD_IN_CYCLES + HOLD_CYCLES, 0), held])
    straight = act.counts_from_angles(np.zeros(12), np.zeros(12)).astype(float)
    first = sp.counts[0].astype(float)
    f = np.linspace(0.0, 1.0, LEAD_IN_CYCLES)[:, None]
    lead = np.rint(straight + f * (first - straight)).astype(np.int64)
    hold = np.repeat(sp.counts[:1], HOLD_CYCLES, axis=0)
    counts = np.vstack([lead, hold, sp.counts])
    ramp = sp.ramp_rows  # the feed-forward's ramp-in at rest: measured from its end
    return sc, counts, planned_tip[ramp:], LEAD_IN_CYCLES + HOLD_CYCLES + ramp, cpu, held


def run(
    variant: str,
    sc: Any,
    counts: np.ndarray,
    planned: np.ndarray,
    start: int,
    held: np.ndarray | None = None,
    loop_gain: float = 0.0,
    loop_rate_mm: float = LOOP_RATE_MM,
    terms: frozenset[str] = frozenset(TERMS),
) -> dict[str, Any]:
    """One run through the arm; with ``held`` (cycles, 2, 12) the tension-based shape
    estimate (:class:`TensionShape`) runs every cycle from the feed-forward's ramp-in
    (scored against the simulated arm's rope-held angles), and with ``loop_gain`` > 0
    each cycle's counts are corrected by ``-loop_gain J dq`` (rope lengths, at most
    ``loop_rate_mm`` per rope per cycle) accumulated from its estimates; the estimate's
    friction and play as the feed-forward's ``terms`` say."""
    act = load_actuation(default_robot())
    physics = Physics.of(variant.replace("+", ","))
    arm = SimArm(act, physics=physics)
    tips = np.empty((len(counts), 3))
    cpu = np.empty(len(counts))
    tensions = np.empty((len(counts), len(counts[0])))
    on = {t: t in terms for t in TERMS}
    shape = TensionShape(Feedforward.of(act, **on)) if held is not None else None
    est_err: list[float] = []
    est_cpu: list[float] = []
    du = np.zeros(act.n_motors)
    to_counts = -act.motors.direction * act.motors.counts_per_mm
    ramp_start = start - RAMP_CYCLES if held is not None else start
    commanded = np.empty(counts.shape, dtype=np.int64)
    for i, c in enumerate(counts):
        c = c + np.rint(to_counts * du).astype(np.int64) if loop_gain > 0.0 else c
        commanded[i] = c
        t0 = time.thread_time()
        s = arm.state(c, i * PERIOD_S)
        cpu[i] = time.thread_time() - t0
        tips[i], tensions[i] = s.centres[-1], s.tension_N
        if shape is not None and held is not None:
            if i == 0:
                shape.reset(c)
            t0 = time.thread_time()
            dq = shape.step(c, s.tension_N, held[i, 0], held[i, 1])
            if loop_gain > 0.0 and i >= ramp_start:
                du -= np.clip(loop_gain * (shape.jacobian @ dq), -loop_rate_mm, loop_rate_mm)
            if i >= ramp_start:
                est_cpu.append(time.thread_time() - t0)
                ga, gt = act.commanded_angles(held[i, 0], held[i, 1])
                ps = arm.physics_state
                if ps is not None:  # the simulator's truth: for the score only
                    true = np.empty(24)
                    true[0::2], true[1::2] = ps.alpha - ga, ps.theta - gt
                    est_err.append(float(np.abs(dq - true).max()))
    tensions = tensions[start:]
    body = tips[start:]
    to_path = np.asarray(sc.path.distance_to(body), dtype=float)
    to_plan = np.linalg.norm(body - planned, axis=1)
    turn = int(np.argmax(np.linalg.norm(planned - planned[0], axis=1)))  # farthest along
    there, back = to_path[: turn + 1], to_path[turn:]

    def mm(x: np.ndarray | float) -> float:
        return round(float(x), 3)

    out: dict[str, Any] = {
        "physics": physics.describe(),
        "tension_min_max_N": [mm(tensions.min()), mm(tensions.max())],
        "rows_outside_watch": int(
            ((tensions.min(axis=1) < WATCH_N[0]) | (tensions.max(axis=1) > WATCH_N[1])).sum()
        ),
        "path_there_max_mm": mm(there.max()),
        "path_back_max_mm": mm(back.max()),
        "path_rms_mm": mm(np.sqrt(np.mean(to_path**2))),
        "from_plan_max_mm": mm(to_plan.max()),
        "from_plan_rms_mm": mm(np.sqrt(np.mean(to_plan**2))),
        "end_after_return_mm": mm(to_plan[-1]),
        "sag_at_start_mm": mm(planned[0, 2] - body[0, 2]),
        "state_cpu_median_ms": mm(1e3 * np.median(cpu[start:])),
        "state_cpu_p99_ms": mm(1e3 * np.percentile(cpu[start:], 99)),
    }
    if est_err:
        out["shape_error_max_mrad"] = mm(1e3 * max(est_err))
        out["shape_error_median_mrad"] = mm(1e3 * float(np.median(est_err)))
    if est_cpu:
        out["shape_step_cpu_median_ms"] = mm(1e3 * np.median(est_cpu))
        out["shape_step_cpu_p99_ms"] = mm(1e3 * np.percentile(est_cpu, 99))
    if loop_gain > 0.0:
        step = np.diff(commanded[start - RAMP_CYCLES :].astype(float), axis=0)
        out["loop_gain"] = loop_gain
        out["max_rate_counts_per_s"] = round(float(np.abs(step).max() / PERIOD_S))
        out["max_accel_counts_per_s2"] = round(
            float(np.abs(np.diff(step, axis=0)).max() / PERIOD_S**2)
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bent-pipe")
    ap.add_argument("--speed", type=float, default=DEFAULT_TIP_SPEED_MM_PER_S)
    ap.add_argument(
        "--effects",
        default=",".join(VARIANTS),
        help="variants, comma-separated (none, all, gravity+capstan, ...)",
    )
    ap.add_argument(
        "--counts", default="plain,compensated", help="plain, compensated or both, comma-separated"
    )
    ap.add_argument(
        "--terms", default=",".join(TERMS), help="the feed-forward's terms, comma-separated"
    )
    ap.add_argument(
        "--shape",
        action="store_true",
        help="compensated runs: the tension-based shape estimate every cycle",
    )
    ap.add_argument(
        "--loop-gain",
        default="",
        help="compensated runs: closed-loop gains to try, comma-separated (implies --shape)",
    )
    args = ap.parse_args(argv)
    gains = [float(g) for g in args.loop_gain.split(",") if g.strip()]
    variants = [v.strip() for v in args.effects.split(",") if v.strip()]
    modes = [v.strip() for v in args.counts.split(",") if v.strip()]
    rows = []
    with process_settings():
        for mode in modes:
            terms = frozenset(t.strip() for t in args.terms.split(",") if t.strip())
            sc, counts, planned, start, ff_s, held = motion(
                args.scenario, args.speed, terms if mode == "compensated" else None
            )
            shape = mode == "compensated" and (args.shape or bool(gains))
            for v in variants:
                for g in gains if mode == "compensated" and gains else [0.0]:
                    rows.append({"counts": mode, **run(v, sc, counts, planned, start,
                                                       held if shape else None, g,
                                                       terms=terms)})  # fmt: skip
                    if mode == "compensated":
                        rows[-1]["feedforward_terms"] = ",".join(t for t in TERMS if t in terms)
                        rows[-1]["feedforward_s"] = round(ff_s, 3)
    out = {
        "benchmark": "physics",
        "machine": machine(),
        "scenario": args.scenario,
        "speed_mm_per_s": args.speed,
        "cycles": int(len(counts) - start),
        "runs": rows,
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
