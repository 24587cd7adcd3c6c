"""Benchmark of the feedback watches: their CPU and what they cost the control loop.

The bent-pipe plan (λ = 5 mm) is played at the demo's speed (50 mm/s, ~14 s, 36 drives on
2 buses at 100 Hz) on the simulated box with its tension-sensor board, once per variant
of the host's watches, the variants interleaved ``--repeats`` times (the machine's speed
drifts in phases):

* ``none``: no watch;
* ``tension``: the tension watch (every 10 ms, pyserial reader thread on the board's pty);
* ``rope``: the rope-consistency watch (the estimator every 5th period, 20 Hz);
* ``both``: both, as ``hrm run`` does.

Per run: SYNC lateness against its deadline (p50 / p99 / max), late cycles (> 2 ms), wake
lateness, period jitter, the supervisor's CPU per cycle, and per watch its CPU per
evaluation (``time.thread_time``) and its thread's CPU per control cycle.  Separately, the
consistency check alone on recorded feedback (no other thread running): CPU per
evaluation.

By default the simulated box runs in this interpreter (python-can virtual buses), as with
``hrm run --sim``; ``--sim-process`` runs it as its own process (``hrm sim``) over
udp_multicast, so the host process holds only the host's threads, as on the real box.

Run: ``python benchmarks/bench_watches.py [--repeats 2] [--sim-process]``; prints JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine
from bench_drivers import BoxProcess, ms, thread_cpu, wire_config

from drivers.config import load_box_config
from drivers.realtime import process_settings
from drivers.sources import CountsSource
from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.ropes.estimator import RopeConsistencyCheck
from hrm_ctrl.runtime.box import SessionOptions, WatchOptions, open_box
from hrm_ctrl.runtime.playback import setpoints_of_plan
from sim_bus.box import SimBox

VARIANTS = {"none": (False, False), "tension": (True, False), "rope": (False, True)}
VARIANTS["both"] = (True, True)
SPEED_MM_S = 50.0


def one_run(
    cfg: Any, act: Any, counts: np.ndarray, variant: str, trace_box: SimBox | None
) -> dict[str, Any]:
    tension, ropes = VARIANTS[variant]
    source = CountsSource(act, counts, cfg.control.period_s, name="plan")
    options = SessionOptions(allow_uncalibrated=True)  # the simulated box
    chosen = WatchOptions(tension=tension, ropes=ropes)
    with open_box(cfg, act, options, watches=chosen) as opened:
        box, watches = opened.session, opened.watches
        if trace_box is not None:
            trace_box.record_trace(True)
        cpu0 = thread_cpu()
        result = box.stream(source, raise_on_stop=False)
        cpu1 = thread_cpu()
        summary = watches.summary()
    s = result.stats
    n = max(1, result.cycles)
    threads = {
        name: round((cpu1[name] - cpu0.get(name, 0.0)) / n * 1000.0, 4)
        for name in ("hrm-supervisor", "rope-watch", "tension-watch", "tension-reader")
        if name in cpu1
    }
    rope = summary.get("rope_consistency", {})
    return {
        "variant": variant,
        "completed": result.completed,
        "cycles": result.cycles,
        "stop_causes": [x.text for x in result.causes][:3],
        "sync_lateness_ms": {
            "p50": ms(s.get("lateness_p50_s")),
            "p99": ms(s.get("lateness_p99_s")),
            "max": ms(s.get("lateness_max_s")),
        },
        "late_cycles_over_2ms": s.get("late_cycles"),
        "skipped_slots": s.get("skipped_slots"),
        "wake_lateness_p99_ms": ms(s.get("wake_lateness_p99_s")),
        "jitter_p99_ms": ms(s.get("jitter_p99_s")),
        "supervisor_cpu_per_cycle_ms": ms(s.get("cpu_per_cycle_mean_s")),
        "thread_cpu_per_cycle_ms": threads,
        "rope_evaluations": rope.get("evaluations"),
        # snapshots not taken: no clean cycle of one SYNC's feedback (watches.take_snapshot)
        "rope_missed_snapshots": rope.get("missed_snapshots"),
        "rope_cpu_per_evaluation_ms": rope.get("cpu_per_evaluation_ms"),
        "rope_max_figure": rope.get("check", {}).get("max_figure"),
        "tension_oldest_sample_ms": summary.get("tension", {}).get("oldest_sample_ms"),
    }


def check_alone(act: Any, feedback: np.ndarray, table: np.ndarray) -> dict[str, Any]:
    """The consistency check on recorded feedback, every 5th SYNC, nothing else running."""
    check = RopeConsistencyCheck(act, rate_hz=20.0)
    cpu = []
    for k in range(1, feedback.shape[0], 5):
        t0 = time.thread_time()
        check(feedback[k], table[min(k - 1, table.shape[0] - 1)])
        cpu.append(time.thread_time() - t0)
    c = np.asarray(cpu) * 1000.0
    return {
        "evaluations": len(cpu),
        "cpu_ms": {
            "p50": round(float(np.median(c)), 3),
            "p99": round(float(np.percentile(c, 99)), 3),
            "max": round(float(c.max()), 3),
        },
        "summary": check.summary(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2, help="runs of each variant")
    ap.add_argument("--sim-process", action="store_true", help="the box in its own process")
    args = ap.parse_args()

    robot = default_robot()
    act = load_actuation(robot)
    sc = scenario("bent-pipe")
    plan = plan_path(robot, sc.path, PlanOptions(step=5.0), sc)
    doc = PlanDoc.from_dict(plan.to_dict(), sc.name)
    cfg = load_box_config(None)
    sp = setpoints_of_plan(doc, act, period_s=cfg.control.period_s, speed_mm_per_s=SPEED_MM_S)
    work = Path(tempfile.mkdtemp(prefix="bench_watches_"))
    box: BoxProcess | None = None
    sim: SimBox | None = None
    if args.sim_process:  # on hrm_ipc, at the production watchdogs (as the HIL tests)
        kwargs = wire_config(work / "box_ipc.toml", cfg, "ipc")
        box = BoxProcess(work / "box_ipc.toml")
        port = box.ready["tension_port"]
        control: dict[str, Any] = {}
    else:
        tag = uuid.uuid4().hex[:8]
        kwargs = [{"interface": "virtual", "channel": f"bw-{tag}-{b.name}"} for b in cfg.buses]
        control = {"missing_tpdo_cycles": 10}
    cfg = cfg.with_bus_kwargs(kwargs).with_control(**control)
    runs: list[dict[str, Any]] = []
    feedback: np.ndarray | None = None
    try:
        if not args.sim_process:
            sim = SimBox(cfg, actuation=act).start()
            port = sim.start_tension_board().port
        cfg = cfg.with_tension(port=port, stale_s=0.35)
        for _ in range(max(1, args.repeats)):
            for variant in VARIANTS:
                runs.append(one_run(cfg, act, sp.counts, variant, sim))
                if sim is not None and feedback is None:
                    feedback = sim.trace()[1]
                    sim.record_trace(False)
    finally:
        if sim is not None:
            sim.stop()
        if box is not None:
            box.__exit__(None, None, None)
    source = CountsSource(act, sp.counts, cfg.control.period_s, name="plan")
    source.start(np.zeros(act.n_motors, dtype=np.int64), cfg.control.period_s)
    if feedback is None:  # the box ran elsewhere: its feedback is the table, one SYNC late
        feedback = np.vstack([source.table[:1], source.table])
    by_variant: dict[str, dict[str, Any]] = {}
    for v in VARIANTS:
        rs = [r for r in runs if r["variant"] == v]
        by_variant[v] = {
            "sync_lateness_p99_ms": [r["sync_lateness_ms"]["p99"] for r in rs],
            "sync_lateness_max_ms": [r["sync_lateness_ms"]["max"] for r in rs],
            "late_cycles_over_2ms": [r["late_cycles_over_2ms"] for r in rs],
            "jitter_p99_ms": [r["jitter_p99_ms"] for r in rs],
        }
    out = {
        "benchmark": "bench_watches",
        "machine": machine(),
        "setup": {
            "plan": "bent-pipe, step 5 mm",
            "speed_mm_per_s": SPEED_MM_S,
            "drives": act.n_motors,
            "buses": len(cfg.buses),
            "rate_hz": cfg.control.rate_hz,
            "box": "own process (hrm sim), udp_multicast"
            if args.sim_process
            else "this interpreter, virtual buses",
            "repeats": args.repeats,
        },
        "by_variant": by_variant,
        "runs": runs,
        "consistency_check_alone": check_alone(act, feedback, source.table),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    with process_settings():  # the process entry: GIL switch interval as `hrm` sets it
        main()
