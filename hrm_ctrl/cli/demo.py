"""``hrm demo``: the whole stack on the simulated box, end to end.

The simulated box starts with a *perturbed* true arm (``--perturb SEED``: link lengths
±2 mm, joint zero offsets ±1°, rope EA ±20 %, motor zeros ±5000 counts; see
``sim_bus/truth.py``), as a real arm differs from its drawing.  The demo then does what a
technician and an operator would, on one simulated box (in its own process, as ``--sim``
starts it: ``--wire hrm_ipc``, the default; ``virtual`` or ``hrm_sim``: in this one):

1. **pretension and zero** (``calibration.zero``): the arm lies in its straight parking
   tube; every rope is brought to its pretension on the tension sensors and each motor's
   count recorded as its zero;
2. **kinematic calibration** (``calibration.collect``, ``calibration.kinematic``): the arm
   leaves the tube, is driven through ``--poses`` well-spread configurations, the laser
   tracker measures its end point at each, and the link lengths, joint zero offsets and
   the tracker's frame are fitted by least squares;
3. **plan** the scenario (the bent pipe by default) with the calibrated model (the
   clearance fit of issue 10), write the plan and its figures;
4. **play** it forward and back (``--no-return``: forward only) at the control rate
   (100 Hz) on the 36 drives of two CAN buses, with the calibrated rope layer, and
   compare where the simulated arm really was with the plan.

Each calibration step saves a version in ``--out``/``calibrations`` (the store of
``docs/calibration.md``); each drive session writes its run record and CAN logs into
``--out``.  The end point's error against the path is reported with the calibration
(the run) and without it: the same scenario planned and mapped to counts with the robot
description's values, put through the simulated arm's physics (not played: with motor
zeros 5000 counts off, the ropes would be far from their pretension).  ``--no-calibrate``
plays on an unperturbed arm with the description's values (the demo before issue 12).
Everything goes to ``--out``: ``plan.json``, ``figures/*.png``, ``calibrations/``, each
session's CAN traffic (``.blf``) and run record, ``poses.csv`` and ``demo.json`` (the
summary; an earlier demo's files of these names are removed first).  A run that does not
finish (a safety stop) is said first (``FAILED: ...``, on stdout and stderr; ``outcome``
and ``failure`` open ``demo.json``), its figures are not printed, and the exit status is 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.cli._common import (
    Output,
    config_input,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._options import (
    SimArm,
    add_bus,
    add_out,
    add_robot,
    add_sim_arm,
    add_speed,
    add_step,
    add_wire,
)
from hrm_ctrl.errors import CalibrationDataError, DriverError, PlanningError
from hrm_ctrl.files import write_atomic

if TYPE_CHECKING:
    import numpy as np

HELP = (
    "calibrate a perturbed simulated arm, plan a scenario with the calibrated model and play "
    "it over CAN (the whole stack)"
)
PLAN_JSON = "plan.json"
SUMMARY_JSON = "demo.json"
POSES_CSV = "poses.csv"
FIGURES_DIR = "figures"
CALIBRATIONS_DIR = "calibrations"
DEFAULT_PERTURB_SEED = 1
DEFAULT_POSES = 20
MAX_POSES = 200
COLLECT_SETTLE_S = 0.15  # the simulated drives settle within a cycle
COLLECT_RATE_FRACTION = 0.9  # of the motor limits (hrm calibrate: 0.5)


def register(p: argparse.ArgumentParser) -> None:
    from hrm_ctrl.planning.scenarios import SCENARIOS

    p.add_argument(
        "--scenario", choices=sorted(SCENARIOS), default="bent-pipe",
        help="the reference scenario to plan and play (default bent-pipe)",
    )  # fmt: skip
    add_robot(p)
    add_bus(p, overrides=False)  # the demo's buses are the in-process box's
    add_step(p)
    add_speed(p)
    p.add_argument(
        "--return", dest="ret", action=argparse.BooleanOptionalAction, default=True,
        help="back out to the start after reaching the end (default: yes)",
    )  # fmt: skip
    add_sim_arm(p, SimArm.PERTURB, when=None, seed=DEFAULT_PERTURB_SEED)
    p.add_argument(
        "--poses", type=int, default=DEFAULT_POSES, metavar="N",
        help=f"configurations of the kinematic calibration (default {DEFAULT_POSES})",
    )  # fmt: skip
    p.add_argument(
        "--no-calibrate", dest="calibrate", action="store_false",
        help="an unperturbed arm, no calibration: plan and play with the description's values",
    )  # fmt: skip
    add_wire(p, when=None, process=True)
    add_out(
        p, metavar="DIR", what="where everything is written (default out/demo)",
        default=Path("out/demo"),
    )  # fmt: skip


def _say(text: str) -> None:
    print(text, flush=True)


@contextlib.contextmanager
def _session(
    running: Any, actuation: Any, out: Path, name: str, ref: Any, *, watch: bool,
    ropes: bool = True,
) -> Iterator[Any]:  # fmt: skip
    """A drive session on the running simulated box, brought up (and its feedback watches
    running when ``watch``: tension, and rope consistency unless not ``ropes``); finished
    and closed on leaving.  The block runs at ``caller_scheduling`` (what it computes
    between moves and the tracker's replies it reads: beside the session's threads)."""
    from hrm_ctrl.runtime.box import (
        NO_WATCHES,
        SessionOptions,
        WatchOptions,
        caller_scheduling,
        open_box,
    )

    options = SessionOptions(
        log_dir=out,
        log_suffix=".blf",
        run_name=name,
        calibration=ref,
        allow_uncalibrated=True,  # the simulated box; the first calibration
    )
    watches = WatchOptions(ropes=ropes) if watch else NO_WATCHES
    with open_box(running.config, actuation, options, sim=running, watches=watches) as box:
        with caller_scheduling(box.session):
            yield box.session


def calibrate_on_box(
    args: argparse.Namespace, description: Any, running: Any, truth: Any, store: Any
) -> tuple[Any, int, dict[str, Any]]:
    """Pretension and zero in the fixture, then the kinematic calibration out of it
    (:func:`calibration.workflows.zero_then_kinematic`) on the ``running`` simulated box
    (:class:`~hrm_ctrl.runtime.simulated.RunningSim`) of the arm ``truth``
    (:class:`sim_bus.truth.TrueArm`); each saved as a version of ``store``.  Returns the
    calibration, its version and a summary."""
    import numpy as np

    from calibration.kinematic import format_pose_csv
    from calibration.workflows import zero_then_kinematic
    from drivers.tension_sensor import TensionSensorReader
    from drivers.tracker import TrackerReader
    from hrm_ctrl.cli.calibrate import format_fit
    from hrm_ctrl.runtime.simulated import sim_thread_scheduling

    out: Path = args.out
    config, sim = running.config, running.sim
    t, tr = config.tension, config.tracker

    def open_session(act: Any, name: str, ref: Any, watch: bool) -> Any:
        # the rope-consistency watch left out while collecting, as hrm calibrate kinematic
        return _session(running, act, out, f"demo-{name}", ref, watch=watch, ropes=False)

    true_zero = np.asarray(truth.motor_zero_counts, dtype=float)
    zero_err: list[float] = []

    def on_zero(zr: Any, v_zero: int, t_zero: float) -> None:
        err = np.abs(np.asarray(zr.zero_counts, dtype=float) - true_zero)
        zero_err.append(float(err.max()))
        _say(
            f"  {len(zr.motor_ids)} motor zeros in {t_zero:.1f} s ({zr.moves} moves): largest "
            f"change {int(np.abs(zr.zero_shift_counts).max())} counts, error against the "
            f"simulated truth at most {err.max():.0f} counts; saved as v{v_zero:04d}"
        )

    @contextlib.contextmanager
    def tension_reader() -> Iterator[TensionSensorReader]:
        # its thread scheduled as the session's (beside CPU burners a reader of normal
        # priority fell more than the staleness limit behind the board)
        with sim_thread_scheduling(config):
            opened = TensionSensorReader(
                t.port, len(config.motor_ids), baudrate=t.baudrate, stale_after_s=t.stale_s
            ).open()
        with contextlib.closing(opened) as reader:
            yield reader

    done = zero_then_kinematic(
        description,
        store,
        open_session,
        tension_reader,
        lambda: TrackerReader(tr.port, tr.timeout_s, baudrate=tr.baudrate),
        leave_fixture=lambda: sim.set_straight_fixture(False),
        poses=args.poses,
        period_s=config.control.period_s,
        samples=4,
        sigma_mm=0.05,
        say=_say,
        on_zero=on_zero,
        settle_s=COLLECT_SETTLE_S,
        rate_fraction=COLLECT_RATE_FRACTION,
    )
    data, fit, cal = done.poses, done.fit, done.calibration
    write_atomic(out / POSES_CSV, format_pose_csv(data.alpha_rad, data.theta_rad, data.points_mm))
    link_err = np.abs(np.asarray(cal.links_mm) - np.asarray(truth.links_mm))
    _say(format_fit(fit).splitlines()[0])
    _say(
        f"  kinematic calibration in {done.kinematic_s:.1f} s: link lengths within "
        f"{link_err.max():.3f} mm of the simulated truth; saved as v{done.version:04d} (active)"
    )
    zr = done.zero
    summary = {
        "zero": {
            "version": done.zero_version,
            "seconds": done.zero_s,
            "moves": zr.moves,
            "max_error_vs_truth_counts": zero_err[0],
            "max_tension_error_N": float(np.abs(zr.tension_error_N).max()),
        },
        "kinematic": {
            "version": done.version,
            "seconds": done.kinematic_s,
            "poses": args.poses,
            "rms_before_mm": fit.rms_before_mm,
            "rms_after_mm": fit.rms_after_mm,
            "max_link_error_vs_truth_mm": float(link_err.max()),
        },
    }
    return cal, done.version, summary


def end_point_errors(arm: Any, counts: np.ndarray, path: Any) -> np.ndarray:
    """Distance (mm) from the simulated arm's true end point to ``path`` for each row of
    motor ``counts`` (``arm``: the simulated arm's physics, a :class:`sim_bus.arm.SimArm`
    of the box's truth, out of its fixture)."""
    import numpy as np

    tips = np.array([arm.state(c, 0.0).centres[-1] for c in counts])
    return np.asarray(path.distance_to(tips), dtype=float)


def _plan(robot: Any, sc: Any, args: argparse.Namespace) -> Any:
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.report import check_clearance, check_limits

    plan = plan_path(
        robot,
        sc.path,
        PlanOptions(step=args.step, return_to_start=args.ret),
        scenario=sc,
        environment=sc.environment,
    )
    check_limits(plan)
    check_clearance(plan.report.get("clearance_mm"), sc.name)
    return plan


def _remove_stale_outputs(out: Path, names: list[str]) -> None:
    """The files a demo writes into ``out``, left by an earlier demo, removed before this
    one writes any: a demo that stops half-way leaves none of another's beside its own
    (an earlier ``demo.json`` would tell of a run that is not this one)."""
    gone = []
    for name in names:
        path = out / name
        if path.is_file():
            path.unlink()
            gone.append(name)
    if gone:
        print(f"hrm demo: an earlier demo's outputs removed from {out}: {', '.join(gone)}",
              file=sys.stderr)  # fmt: skip


def _check_args(args: argparse.Namespace) -> None:
    if not (math.isfinite(args.step) and args.step > 0.0):
        raise PlanningError(f"--step must be > 0 mm, got {args.step}")
    if not (math.isfinite(args.speed) and args.speed > 0.0):
        raise DriverError(f"--speed must be > 0 mm/s, got {args.speed}")
    if not 1 <= args.poses <= MAX_POSES:
        raise CalibrationDataError(f"--poses must be 1..{MAX_POSES}, got {args.poses}")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from calibration.apply import calibrated_actuation, calibrated_model
    from calibration.store import CalibrationStore
    from calibration.workflows import calibration_ref
    from drivers.config import load_box_config
    from drivers.session import SafetyStopError
    from drivers.sources import CountsSource
    from hrm_ctrl.cli.plan import format_report
    from hrm_ctrl.formats.planfile import PlanDoc, write_plan
    from hrm_ctrl.formats.plots import (
        ANGLES_PNG,
        ARM_PNG,
        BACKBONE_PNG,
        CLEARANCE_PNG,
        write_plan_figures,
    )
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.planning.scenarios import scenario
    from hrm_ctrl.ropes.actuation import load_actuation
    from hrm_ctrl.runtime.playback import setpoints_of_plan
    from hrm_ctrl.runtime.simulated import SimulatedArm, SimulatedBox, running_box
    from sim_bus.arm import SimArm
    from sim_bus.tracking import tracking_error
    from sim_bus.truth import TrueArm

    t_start = time.monotonic()
    pngs = [f"{FIGURES_DIR}/{f}" for f in (BACKBONE_PNG, ARM_PNG, ANGLES_PNG, CLEARANCE_PNG)]
    refuse_overwriting_inputs(  # before anything is read or written
        [
            Output(
                "--out",
                args.out,
                [PLAN_JSON, SUMMARY_JSON, POSES_CSV, FIGURES_DIR, CALIBRATIONS_DIR, *pngs],
            )
        ],
        [
            robot_input(args.robot),
            config_input(args.config),
            *shipped_inputs(plan_schema=True, eds=True),
        ],
    )
    _check_args(args)
    # Everything that can refuse does so before anything is written or sent.
    description = load_robot(args.robot)
    config = load_box_config(args.config)
    nominal = load_actuation(description)
    config.check_motors(nominal.motor_ids)
    sc = scenario(args.scenario)
    plan_nominal = _plan(description, sc, args)  # the description's values: planned first
    _remove_stale_outputs(args.out, [SUMMARY_JSON, PLAN_JSON, POSES_CSV, *pngs])
    truth = TrueArm.perturbed(nominal, args.perturb) if args.calibrate else None
    out: Path = args.out

    simulated = SimulatedBox(
        SimulatedArm(nominal, truth), args.wire, tracker=args.calibrate, fixture=args.calibrate
    )
    stop: SafetyStopError | None = None
    calib: dict[str, Any] | None = None
    # the box in its own process (--wire hrm_ipc, the default) or in this one
    with running_box(config, simulated, prog="hrm demo") as running:
        config, sim = running.config, running.sim
        if args.calibrate:
            _say(
                f"simulated arm: seed {args.perturb}: links up to "
                f"{np.abs(truth.links_mm - description.links).max():.2f} mm off, joint zero "
                f"offsets up to {np.degrees(np.abs(np.r_[truth.alpha_offset_rad, truth.theta_offset_rad]).max()):.2f} deg, "  # noqa: E501
                f"motor zeros up to {np.abs(truth.motor_zero_counts).max()} counts, rope EA "
                f"{100 * (np.abs(truth.rope_EA_N / nominal.routing.stiffness_EA_N - 1)).max():.0f} %"  # noqa: E501
            )
            store = CalibrationStore(out / CALIBRATIONS_DIR)
            cal, version, calib = calibrate_on_box(args, description, running, truth, store)
            robot = calibrated_model(description, cal)
            actuation = calibrated_actuation(description, cal)
            ref = calibration_ref(store, version)
            plan = _plan(robot, sc, args)
        else:
            robot, actuation, ref, plan = description, nominal, None, plan_nominal
        print(format_report(plan, sc.name))
        doc = PlanDoc.from_dict(plan.to_dict(), sc.name)
        sp = setpoints_of_plan(
            doc, actuation, period_s=config.control.period_s, speed_mm_per_s=args.speed
        )
        info = {"plan": sc.name, "steps": sp.n_steps, "speed_mm_per_s": args.speed}
        source = CountsSource.of_plan(actuation, sp, info=info)
        source.precheck(config.control.period_s)
        write_plan(out / PLAN_JSON, doc)
        figures = write_plan_figures(doc, out / FIGURES_DIR)
        _say(f"plan and {len(figures)} figures written to {out}")

        sim.record_trace(True)
        with _session(running, actuation, out, "demo-run", ref, watch=True) as box:
            box.record_extra.update(
                {
                    "demo": sc.name,
                    "plan_file": str(out / PLAN_JSON),
                    "wire": args.wire,
                    "simulated_truth_seed": args.perturb if args.calibrate else None,
                }
            )
            try:
                result = box.stream(source)
            except SafetyStopError as exc:
                stop, result = exc, exc.result
            box.record_extra["setpoints"] = source.describe()
            can_logs = box.record()["can_logs"]
            bringup_s = box.bringup_s
        record_path = box.record_path  # written as the session closed
        _times, counts = sim.trace()

    lead = source.n_lead_in
    n_body = source.table.shape[0] - lead
    alpha_rows, theta_rows = sp.row_angles()
    rows = np.minimum(np.arange(n_body), sp.n_cycles - 1)  # the final hold: the last row
    planned = (alpha_rows[rows], theta_rows[rows])
    ids = actuation.motor_ids
    cols = [np.array([ids.index(m) for m in b.nodes]) for b in config.buses]
    tr = tracking_error(actuation, source.table, lead, planned, counts, cols)

    # the end point against the path: with the calibration (what was played, at every plan
    # step) and without it (the same scenario with the description's values), through the
    # simulated arm's physics (the box's truth, here: the box has stopped)
    physics = SimArm(nominal, truth=truth)
    steps_cal = actuation.counts_from_angles(plan.alpha, plan.theta)
    err_cal = end_point_errors(physics, steps_cal, sc.path)
    played = counts[lead:]  # the trace after the lead-in: the plan itself
    played = played[:: max(1, len(played) // 400)]
    err_run = end_point_errors(physics, played, sc.path) if len(played) else np.zeros(0)
    steps_nom = nominal.counts_from_angles(plan_nominal.alpha, plan_nominal.theta)
    err_nom = end_point_errors(physics, steps_nom, sc.path)
    end_point = {
        "calibrated_steps_max_mm": float(err_cal.max()),
        "calibrated_steps_rms_mm": float(np.sqrt(np.mean(err_cal**2))),
        "played_max_mm": float(err_run.max()) if len(err_run) else None,
        "uncalibrated_steps_max_mm": float(err_nom.max()),
        "uncalibrated_steps_rms_mm": float(np.sqrt(np.mean(err_nom**2))),
    }

    st = result.stats
    failure = None if stop is None else (
        f"the run did not finish: safety stop after {result.cycles} of "
        f"{source.n_cycles} cycles: {stop}"
    )  # fmt: skip
    summary: dict[str, Any] = {
        "outcome": "done" if failure is None else "failed",
        "failure": failure,
        "scenario": sc.name,
        "plan_report": plan.report,
        "calibration": calib,
        "end_point_vs_path": end_point,
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
        "seconds": time.monotonic() - t_start,
    }
    write_atomic(out / SUMMARY_JSON, json.dumps(summary, indent=1, default=str) + "\n")
    if failure is not None:  # said first, and no figures of a run that did not finish
        print(f"hrm demo: FAILED: {failure}", file=sys.stderr, flush=True)
        print(f"FAILED: {failure}")
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
    if failure is not None:
        print("figures of the run not shown: it did not finish (demo.json keeps what was measured)")
        print(f"run record: {record_path}")
        for log in can_logs:
            print(f"CAN log: {log}")
        print(f"demo took {summary['seconds']:.1f} s")
        return 2
    print(
        f"simulated arm vs plan: worst joint centre {tr.max_error_mm:.3f} mm off "
        f"(joint {tr.worst_joint}) over {tr.compared_cycles} of {tr.body_cycles} cycles, "
        f"drive lag {tr.median_lag_cycles:g} cycle(s) (p95 {tr.p95_lag_cycles:g})"
    )
    label = "with the calibration" if args.calibrate else "with the description's values"
    played_text = (
        "not played" if end_point["played_max_mm"] is None
        else f"{end_point['played_max_mm']:.3f} mm while playing"
    )  # fmt: skip
    print(
        f"end point vs path ({label}): at most {end_point['calibrated_steps_max_mm']:.3f} mm "
        f"over the plan steps, {played_text}"
    )
    if args.calibrate:
        print(
            "end point vs path without the calibration (the description's values through the "
            f"simulated arm, not played): at most {end_point['uncalibrated_steps_max_mm']:.1f} "
            f"mm, rms {end_point['uncalibrated_steps_rms_mm']:.1f} mm"
        )
    print(f"run record: {record_path}")
    for log in can_logs:
        print(f"CAN log: {log}")
    print(f"demo took {summary['seconds']:.1f} s")
    return 0
