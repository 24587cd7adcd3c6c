"""``hrm demo``: the whole stack on the simulated box, end to end.

Plans a reference scenario (the bent pipe by default), writes the plan and its
figures, turns it into rope-motor setpoints, brings up the 36 simulated CiA 402
drives of the default box configuration on two CAN buses, streams the plan at the
control rate (100 Hz), and compares where the simulated arm really was with the
plan.  Everything goes to ``--out``: ``plan.json``, ``figures/*.png``, each bus's
CAN traffic (``.blf``), the run record and ``demo.json`` (the summary).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.cli._common import (
    Output,
    add_robot_argument,
    config_input,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._simwire import SIM_WIRES, start_in_process_sim
from hrm_ctrl.cli._watches import feedback_watches
from hrm_ctrl.cli.plan import format_report
from hrm_ctrl.errors import DriverError, PlanningError
from hrm_ctrl.files import write_atomic
from hrm_ctrl.planning.scenarios import SCENARIOS

HELP = "plan a scenario and play it on the simulated box over CAN (the whole stack)"
PLAN_JSON = "plan.json"
SUMMARY_JSON = "demo.json"
FIGURES_DIR = "figures"


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", choices=sorted(SCENARIOS), default="bent-pipe")
    add_robot_argument(p)
    p.add_argument("--config", type=Path, metavar="BOX.toml", help="bus configuration")
    p.add_argument("--step", type=float, default=5.0, metavar="MM", help="lambda (default 5 mm)")
    p.add_argument(
        "--speed", type=float, default=50.0, metavar="MM_S", help="tip speed (default 50 mm/s)"
    )
    p.add_argument("--return", dest="ret", action="store_true", help="back out to the start")
    p.add_argument("--wire", choices=SIM_WIRES, default="virtual", help="in-process bus kind")
    p.add_argument("--out", type=Path, default=Path("out/demo"), metavar="DIR")


def run(args: argparse.Namespace) -> int:
    from drivers.config import load_box_config
    from drivers.interrupts import deferred_interrupts
    from drivers.session import DriveSession, SafetyStopError
    from drivers.sources import CountsSource
    from hrm_ctrl.cli.ropes import setpoints_of_plan
    from hrm_ctrl.formats.planfile import PlanDoc, write_plan
    from hrm_ctrl.formats.plots import ANGLES_PNG, ARM_PNG, BACKBONE_PNG, write_plan_figures
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.report import check_limits
    from hrm_ctrl.planning.scenarios import scenario
    from hrm_ctrl.ropes.actuation import load_actuation
    from sim_bus.tracking import tracking_error

    pngs = [f"{FIGURES_DIR}/{f}" for f in (BACKBONE_PNG, ARM_PNG, ANGLES_PNG)]
    refuse_overwriting_inputs(  # before anything is read or written
        [Output("--out", args.out, [PLAN_JSON, SUMMARY_JSON, FIGURES_DIR, *pngs])],
        [
            robot_input(args.robot),
            config_input(args.config),
            *shipped_inputs(plan_schema=True, eds=True),
        ],
    )
    if not (math.isfinite(args.step) and args.step > 0.0):
        raise PlanningError(f"--step must be > 0 mm, got {args.step}")
    if not (math.isfinite(args.speed) and args.speed > 0.0):
        raise DriverError(f"--speed must be > 0 mm/s, got {args.speed}")
    # Everything that can refuse does so before anything is written or sent.
    robot = load_robot(args.robot)
    config = load_box_config(args.config)
    actuation = load_actuation(robot)
    config.check_motors(actuation.motor_ids)
    sc = scenario(args.scenario)
    plan = plan_path(robot, sc.path, PlanOptions(step=args.step, return_to_start=args.ret), sc)
    print(format_report(plan, sc.name))
    check_limits(plan)
    doc = PlanDoc.from_dict(plan.to_dict(), sc.name)
    sp = setpoints_of_plan(
        doc, actuation, period_s=config.control.period_s, speed_mm_per_s=args.speed
    )
    info = {"plan": sc.name, "steps": sp.n_steps, "speed_mm_per_s": args.speed}
    source = CountsSource(actuation, sp.counts, sp.period_s, name="plan", label=sp.label, info=info)
    source.precheck(config.control.period_s)

    out: Path = args.out
    write_plan(out / PLAN_JSON, doc)
    figures = write_plan_figures(doc, out / FIGURES_DIR)
    print(f"plan and {len(figures)} figures written to {out}")

    config, sim = start_in_process_sim(config, actuation, args.wire, prog="hrm demo")
    stop: SafetyStopError | None = None
    try:
        sim.record_trace(True)
        with contextlib.ExitStack() as stack:
            with deferred_interrupts():  # the session is open and entered, or not at all
                box = stack.enter_context(
                    DriveSession(config, actuation, log_dir=out, log_suffix=".blf")
                )
                box.record_extra = {
                    "demo": sc.name,
                    "plan_file": str(out / PLAN_JSON),
                    "wire": args.wire,
                }
                # tension board opened first: a bad port is refused before any NMT reset
                watches = stack.enter_context(feedback_watches(config, actuation, box, start=False))
            box.bring_up()
            watches.start()  # tension, ropes
            try:
                result = box.stream(source)
            except SafetyStopError as exc:
                stop, result = exc, exc.result
            box.record_extra["setpoints"] = source.describe()
        _times, counts = sim.trace()
        record_path = box.record_path
        can_logs = box.record()["can_logs"]
        bringup_s = box.bringup_s
    finally:
        sim.stop()

    lead = source.n_lead_in
    n_body = source.table.shape[0] - lead
    alpha_rows, theta_rows = sp.row_angles()
    rows = np.minimum(np.arange(n_body), sp.n_cycles - 1)  # the final hold: the last row
    planned = (alpha_rows[rows], theta_rows[rows])
    ids = actuation.motor_ids
    cols = [np.array([ids.index(m) for m in b.nodes]) for b in config.buses]
    tr = tracking_error(actuation, source.table, lead, planned, counts, cols)

    st = result.stats
    summary: dict[str, Any] = {
        "scenario": sc.name,
        "plan_report": plan.report,
        "run": {
            "completed": result.completed,
            "cycles": result.cycles,
            "bringup_s": bringup_s,
            "causes": [c.text for c in result.causes],
            "stats": st,
        },
        "tracking": tr.to_dict(),
        "wire": args.wire,
        "run_record": str(record_path),
        "can_logs": can_logs,
    }
    write_atomic(out / SUMMARY_JSON, json.dumps(summary, indent=1, default=str) + "\n")
    print(
        f"box: {len(ids)} drives on {len(config.buses)} buses ({args.wire}), "
        f"bring-up {bringup_s:.2f} s"
    )
    print(
        f"streamed {result.cycles} cycles at {config.control.rate_hz:g} Hz: "
        f"jitter p99 {1e3 * st.get('jitter_p99_s', 0.0):.3f} ms, "
        f"late cycles {st.get('late_cycles', 0)}, "
        f"missing feedback {st.get('missing_feedback_node_cycles', 0)}"
    )
    print(
        f"simulated arm vs plan: worst joint centre {tr.max_error_mm:.3f} mm off "
        f"(joint {tr.worst_joint}) over {tr.compared_cycles} of {tr.body_cycles} cycles, "
        f"drive lag {tr.median_lag_cycles:g} cycle(s) (p95 {tr.p95_lag_cycles:g})"
    )
    print(f"run record: {record_path}")
    for log in can_logs:
        print(f"CAN log: {log}")
    if stop is not None:
        print(f"hrm demo: safety stop: {stop}", file=sys.stderr)
        return 2
    return 0
