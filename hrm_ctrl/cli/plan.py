"""``hrm plan``: plan the arm along a scenario or a path file and report on it."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.cli._common import (
    Input,
    Output,
    arm_from_args,
    calibrations_input,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._options import (
    Uncalibrated,
    add_allow_collision,
    add_calibration,
    add_json,
    add_out,
    add_robot,
    add_step,
)
from hrm_ctrl.errors import HrmError, PlanningError

if TYPE_CHECKING:
    from hrm_ctrl.planning.known_path import KnownPath
    from hrm_ctrl.planning.planner import Plan
    from hrm_ctrl.planning.scenarios import Scenario

HELP = "plan the arm along a scenario or a path file (Sec. 3 of the paper) and report on it"


def register(p: argparse.ArgumentParser) -> None:
    from hrm_ctrl.planning.planner import FitMode
    from hrm_ctrl.planning.scenarios import SCENARIOS

    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", choices=sorted(SCENARIOS), help="a reference scenario")
    src.add_argument("--path", type=Path, metavar="FILE", help="CSV path file (header x,y,z; mm)")
    src.add_argument(
        "--scan",
        type=Path,
        metavar="FILE",
        help="point cloud of a pipe's inner wall (.ply/.csv/.npy): plan along its centre line, "
        "inside that pipe",
    )
    add_robot(p)
    add_step(p)
    p.add_argument("--alpha-step", type=float, default=1.0, help="alpha_step of Eq. 11 (0, 1]")
    p.add_argument("--return", dest="ret", action="store_true", help="back out to the start")
    p.add_argument(
        "--fit",
        choices=[m.value for m in FitMode],
        help="paper: the paper's joint fitting; clearance (default): refined for the largest "
        "clearance where an environment is known and joint-limit margin everywhere",
    )
    p.add_argument(
        "--round-corners",
        type=float,
        metavar="MM",
        help="round every corner of a --path or --scan polyline to this radius",
    )
    add_out(p, metavar="PLAN.json", what="write the plan file")
    p.add_argument("--plot", type=Path, metavar="DIR", help="write figures (PNG) to DIR")
    p.add_argument(
        "--plot-steps",
        metavar="I,J,...",
        help="steps to draw in 3D (default: first, middle, last), e.g. 0,60,135",
    )
    p.add_argument(
        "--allow-violations",
        action="store_true",
        help="write the plan even if it breaks a joint limit",
    )
    p.add_argument(
        "--scene",
        type=Path,
        metavar="SCENE.toml",
        help="environment from a scene file (with --scenario: instead of the scenario's)",
    )
    add_allow_collision(p, "write the plan")
    add_json(p, "the report")
    add_calibration(p, Uncalibrated.MODEL)  # the calibrated link lengths (issue 12)


def make_plan(args: argparse.Namespace) -> Plan:
    """Load the inputs named by the arguments and plan (no output written)."""
    from hrm_ctrl.formats.scene import read_scene
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.planning.conditioning import check_path, round_corners
    from hrm_ctrl.planning.environment import Environment, Pipe
    from hrm_ctrl.planning.known_path import load_path_csv
    from hrm_ctrl.planning.planner import FitMode, PlanOptions, plan_path
    from hrm_ctrl.planning.scenarios import Scenario, scenario

    if not (math.isfinite(args.step) and args.step > 0.0):
        raise PlanningError(f"--step must be a finite number > 0 mm, got {args.step}")
    arm = arm_from_args(args, load_robot(args.robot), prog="hrm plan")
    robot = arm.robot  # the calibrated link lengths
    env = read_scene(args.scene) if args.scene is not None else None
    sc: Scenario | None = None
    if args.round_corners is not None and args.scenario:
        raise PlanningError(
            "--round-corners rounds a --path or --scan polyline (a scenario's path and "
            "obstacles are drawn for each other)"
        )
    if args.scenario:
        sc = scenario(args.scenario)
        if env is not None:
            sc = sc.with_environment(env)
        path: KnownPath = sc.path
    elif args.scan is not None:
        from hrm_ctrl.planning.scan import path_and_pipe_from_scan

        path, axis, d = path_and_pipe_from_scan(args.scan, start_near=robot.base_position)
        obstacles = (Pipe(axis, d), *(env.obstacles if env is not None else ()))
        sc = Scenario(
            name=Path(args.scan).name,
            path=path,
            environment=Environment(obstacles),
            description=f"scan {args.scan}: a pipe of inner diameter {d:.1f} mm",
        )
    else:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            path = load_path_csv(args.path)
        for w in caught:
            print(f"hrm plan: warning: {w.message}", file=sys.stderr)
        if env is not None:  # a path file through a scene: planned as a scenario of its own
            sc = Scenario(
                name=Path(args.path).name,
                path=path,
                environment=env,
                description=f"path file {args.path} in scene {args.scene}",
            )
    if args.round_corners is not None:
        if not (math.isfinite(args.round_corners) and args.round_corners > 0.0):
            raise PlanningError(
                f"--round-corners must be a radius > 0 mm, got {args.round_corners}"
            )
        path = round_corners(path, args.round_corners)
        if sc is not None:
            sc = dataclasses.replace(sc, path=path)
    check = check_path(robot, path)
    if not check.ok:
        print(f"hrm plan: warning: {check.message()}", file=sys.stderr)
    steps = parse_plot_steps(args.plot_steps)
    opts = PlanOptions(
        step=args.step,
        alpha_step=args.alpha_step,
        return_to_start=args.ret,
        backbone_steps=steps,
        fit=FitMode(args.fit) if args.fit else FitMode.CLEARANCE,  # the margin by default
    )
    environment = sc.environment if sc is not None else None
    from hrm_ctrl.cli._progress import progress_bar, wanted

    refined = opts.fit_mode(environment) is FitMode.CLEARANCE
    with progress_bar("refinement", enabled=refined and wanted(args.json)) as bar:
        plan = plan_path(robot, path, opts, scenario=sc, environment=environment, progress=bar)
    arm.say_calibration("hrm plan")
    if steps is not None and steps[-1] >= len(plan.travel):
        raise PlanningError(
            f"--plot-steps: step {steps[-1]} is past the plan's last step {len(plan.travel) - 1}"
        )
    return plan


def parse_plot_steps(text: str | None) -> tuple[int, ...] | None:
    """``"0,60,135"`` -> ``(0, 60, 135)``; None stays None.

    >>> parse_plot_steps("60, 0,135")
    (0, 60, 135)
    """
    if text is None:
        return None
    from hrm_ctrl.formats.planfile import MAX_PLAN_STEPS

    shown = repr(text) if len(text) <= 40 else f"{text[:30]!r}... ({len(text)} characters)"
    try:
        steps = sorted({int(t) for t in text.split(",") if t.strip()})
    except ValueError:
        raise PlanningError(
            f"--plot-steps: expected step numbers like 0,60,135, got {shown}"
        ) from None
    if not steps or steps[0] < 0:
        raise PlanningError(f"--plot-steps: expected step numbers >= 0, got {shown}")
    if steps[-1] > MAX_PLAN_STEPS:
        raise PlanningError(
            f"--plot-steps: {shown} names a step past the {MAX_PLAN_STEPS} a plan may have"
        )
    return tuple(steps)


def format_report(plan: Plan, name: str) -> str:
    """The report as lines a person reads."""
    r: dict[str, Any] = plan.report
    o = plan.options
    ret = ", with return" if o.return_to_start else ""
    rows = [
        (
            "tip error vs path",
            f"max {r['tip_error_mm']:.3g} mm; at the end {r['end_error_mm']:.3g} mm",
        ),
        ("joints in the path", f"max {r['joints_off_path_mm']:.3g} mm off the path"),
        (
            "links in the path",
            f"max {r['links_off_path_mm']:.2f} mm off the path (links are chords of the path)",
        ),
    ]
    v = r["first_violation"]
    if v is None:
        rows.append(
            ("joint-limit margin", f"{r['joint_limit_margin_deg']:.2f} deg (all within limits)")
        )
    else:
        rows.append(
            (
                "joint limit BROKEN",
                f"first at step {v['step']} (travel {v['travel_mm']:.1f} mm): "
                f"joint {v['joint']} {v['angle']} = {v['deg']:.2f} deg",
            )
        )
    mc = r["max_angle_change_deg"]
    rows.append(
        ("largest step change", f"{mc['deg']:.2f} deg (step {mc['step']}, joint {mc['joint']})")
    )
    it = r["solver_iterations"]
    rows.append(("solver iterations", f"{it['total']} in all, at most {it['max_per_step']} a step"))
    if "clearance_mm" in r:
        c = r["clearance_mm"]
        if c["min"] is None:
            rows.append(("clearance", "no link meets an obstacle"))
        else:
            verdict = "clear" if c["min"] >= 0 else "COLLISION: the link meets an obstacle"
            rows.append(
                (
                    "clearance",
                    f"{c['min']:.2f} mm at step {c['step']}, link {c['link']} ({verdict})",
                )
            )
    if "fit" in r:
        fit = r["fit"]
        ref = r.get("refinement")
        if isinstance(ref, dict) and ref.get("paper_clearance_min_mm") is not None:
            fit += f" (the paper's fit: clearance {ref['paper_clearance_min_mm']:.2f} mm)"
        rows.append(("fit", fit))
    fp = r.get("free_parameters")
    if isinstance(fp, dict) and fp.get("searched"):
        k, t = fp["start_angles_deg"]
        rows.append(
            (
                "free parameters",
                f"start angles ({k:.1f}, {t:.1f}) deg, alpha_step {fp['alpha_step']:g}, "
                f"joint-2 turn {fp['joint2_offset_deg']:.1f} deg "
                f"(best of {fp['candidates']} candidates)",
            )
        )
    if "margin_statement" in r:
        rows.append(("margin", r["margin_statement"]))
    method = r.get("method")
    if isinstance(method, dict):
        rows.append(("method", method["text"]))
    rows.append(("planning time", f"{r['plan_time_ms']:.1f} ms"))
    head = (
        f"plan: {name}: {r['steps']} steps over {r['path_length_mm']:.2f} mm "
        f"(step {o.step:g} mm, alpha_step {o.alpha_step:g}{ret})"
    )
    return "\n".join([head, *(f"  {k:<22}  {v}" for k, v in rows)])


def refuse_outputs_over_inputs(args: argparse.Namespace) -> None:
    """``--out`` and ``--plot`` (the directory and its figures) name no file read."""
    figures: tuple[str, ...] = ()
    if args.plot is not None:
        from hrm_ctrl.formats.plots import ANGLES_PNG, ARM_PNG, BACKBONE_PNG, CLEARANCE_PNG

        figures = (BACKBONE_PNG, ARM_PNG, ANGLES_PNG, CLEARANCE_PNG)
    refuse_overwriting_inputs(
        [Output("--out", args.out), Output("--plot", args.plot, figures)],
        [
            Input("path file", args.path),
            Input("scene file", args.scene),
            Input("point cloud", args.scan),
            robot_input(args.robot),
            calibrations_input(args),
            *shipped_inputs(plan_schema=True),
            *getattr(args, "extra_inputs", ()),  # the console's script, when run from one
        ],
    )


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.formats.planfile import PlanDoc, write_plan
    from hrm_ctrl.planning.report import check_clearance, check_limits

    refuse_outputs_over_inputs(args)  # before anything is read or written
    plan = make_plan(args)
    name = args.scenario or str(args.path or args.scan)
    if args.json:
        print(json.dumps(plan.report, indent=2))
    else:
        print(format_report(plan, name))
    if args.allow_collision:
        warn_collision(plan)
    else:
        check_clearance(plan.report.get("clearance_mm"), name)  # raises: nothing written
    if not args.allow_violations:
        check_limits(plan)  # raises: nothing written
    if not (args.out or args.plot):
        return 0  # nothing to write: the plan file's document is not made
    doc = PlanDoc.from_dict(plan.to_dict(), str(args.out or name))
    figures: list[Path] = []
    made_plot_dir = bool(args.plot) and not args.plot.exists()
    if args.plot:  # the figures first: if they fail, no plan file is left either
        from hrm_ctrl.formats.plots import write_plan_figures

        figures = write_plan_figures(doc, args.plot, plan.options.backbone_steps)
    if args.out:
        try:
            write_plan(args.out, doc)
        except HrmError:
            for f in figures:
                f.unlink(missing_ok=True)
            if made_plot_dir:  # the folder --plot made is gone again (if nothing else is in it)
                with contextlib.suppress(OSError):
                    args.plot.rmdir()
            raise
    for f in figures:
        print(f"figure written to {f}")
    if args.out:
        print(f"plan written to {args.out}")
    return 0


def warn_collision(plan: Plan) -> None:
    """One warning line on stderr when a link meets an obstacle of the scenario (a plan
    written with ``--allow-collision``)."""
    c = plan.report.get("clearance_mm")
    if c and c["min"] is not None and c["min"] < 0.0:
        print(
            f"hrm plan: warning: link {c['link']} meets an obstacle at step {c['step']} "
            f"(clearance {c['min']:.2f} mm); accepted as --allow-collision asks",
            file=sys.stderr,
        )
