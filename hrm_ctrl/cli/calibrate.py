"""``hrm calibrate``: the calibration store and the calibration routines (issue 12).

Sub-commands:

* ``show [--json]``: the active calibration for this robot description, every field and
  the routine's residuals;
* ``history [--json]``: every version in the store (time, routine, robot, the active
  mark; a damaged file, or a version of this robot whose ropes or values ``use`` would
  refuse, is listed with its problem);
* ``use VERSION``: make an older version active (it must load and belong to this robot,
  its values within ``calibration.apply.check_ranges``); ``use VERSION --box --config
  BOX.toml`` confirms that a calibration whose box is unknown (a file made before
  calibrations named their box) was made on this box: the drives' identities are read
  (the drives configured, never enabled) and the version saved again, as the next
  version naming this box, and made active (:func:`run_use`);
* ``kinematic DATA.csv [--estimate-frame]``: fit link lengths and joint zero offsets (and
  the instrument's frame) to a pose file (``calibration.kinematic``: header
  ``alpha_1_rad..alpha_12_rad,theta_1_rad..theta_12_rad,x_mm,y_mm,z_mm``, the commanded
  angles, true angle = commanded + offset), print the residuals before and after and each
  parameter's standard deviation, and save a new version (or, with ``--out FILE``, write
  that one file instead); data that leave the fit ill-conditioned are refused, naming the
  parameters that are not observable;
* ``kinematic --collect N (--sim [--perturb SEED] | --config BOX.toml)``: drive the arm
  through N well-spread configurations, read the laser tracker at each; the tracker's own
  frame is found first from its readings of the base plate's nests (the robot
  description's ``[base] fiducials_mm``, ``calibration.kinematic.instrument_frame``), so
  the points go into the base frame and every joint offset is observable (with a free
  frame ``alpha_offset_1`` is not); write the poses as a pose file into ``--log-dir``
  beside the run record, and fit them as above;
* ``zero``, ``stiffness``: the rope-tension routines (``hrm_ctrl.cli._calibrate_tension``);
* ``physics (--sim [--perturb SEED] [--physics EFFECTS] | --config BOX.toml)``: the link
  masses and each joint's kinetic friction coefficient from the tension board at held
  poses, the arm out of its fixture (``calibration.physics``; the payload given by
  ``--payload-kg``, else the description's), saved as the calibration's ``physics``.

Every routine starts from the active calibration for this robot (the description's values
when there is none) and saves a new version with its own fields replaced, the others
carried over (``calibration.apply.updated``).  The store is ``--calibrations DIR``, else
``$HRM_CALIBRATIONS``, else ``~/.local/share/hrm/calibrations``.

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm calibrate")
>>> register(p)
>>> a = p.parse_args(["kinematic", "poses.csv", "--estimate-frame"])
>>> a.calibrate, str(a.data), a.estimate_frame, a.collect
('kinematic', 'poses.csv', True, None)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from hrm_ctrl.cli._calibrate_tension import EXIT_NOT_USABLE, save_calibration
from hrm_ctrl.cli._calibrate_tension import register as register_tension_routines
from hrm_ctrl.cli._common import (
    Input,
    Output,
    calibrations_folder,
    calibrations_input,
    config_input,
    load_box,
    refuse_overwriting_inputs,
    robot_input,
    shipped_inputs,
)
from hrm_ctrl.cli._options import (
    SimArm,
    Uncalibrated,
    add_bus,
    add_calibration,
    add_json,
    add_log,
    add_out,
    add_physics,
    add_robot,
    add_sim,
)
from hrm_ctrl.errors import CalibrationDataError, CalibrationFileError

HELP = (
    "calibration: the store (show, history, use) and the routines (kinematic, zero, "
    "stiffness, physics)"
)
DEFAULT_SAMPLES = 10
DEFAULT_SIM_PHYSICS = "gravity,capstan"  # what the physics routine calibrates
MAX_COLLECT = 1000


def _common(p: argparse.ArgumentParser) -> None:
    add_robot(p)
    add_calibration(p)


def register(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(
        dest="calibrate", metavar="ROUTINE", required=True, parser_class=type(parser)
    )
    p = sub.add_parser("show", help="the active calibration for this robot (every field)")
    _common(p)
    add_json(p, "it")
    p.set_defaults(_run=run_show)

    p = sub.add_parser("history", help="every version in the store")
    _common(p)
    add_json(p, "it")
    p.set_defaults(_run=run_history)

    p = sub.add_parser("use", help="make VERSION the active calibration")
    p.add_argument(
        "version", type=int, metavar="VERSION",
        help="the version to activate (see hrm calibrate history)",
    )  # fmt: skip
    _common(p)
    p.add_argument(
        "--box", action="store_true",
        help="confirm that VERSION, whose box is unknown, was made on the box of --config: "
        "save it again naming that box (its drives' identities, read by SDO)",
    )  # fmt: skip
    add_bus(p)  # --config, --bus
    p.set_defaults(_run=run_use)

    p = sub.add_parser(
        "kinematic",
        help="link lengths and joint zero offsets from measured end points (least squares)",
    )
    p.add_argument("data", nargs="?", type=Path, metavar="DATA.csv", help="pose file")
    add_robot(p)
    add_calibration(p, Uncalibrated.DRIVES, when="with --collect on real drives")
    add_out(p, metavar="FILE", what="write this one calibration file")
    p.add_argument(
        "--estimate-frame", action="store_true",
        help="fit the instrument's pose too (its points are not in the base frame)",
    )  # fmt: skip
    p.add_argument(
        "--sigma-mm", type=float, default=None, metavar="MM",
        help="instrument noise per coordinate for the observability check (default 0.05; "
        "with --collect divided by the square root of --samples)",
    )  # fmt: skip
    p.add_argument(
        "--collect", type=int, default=None, metavar="N",
        help="drive the arm through N well-spread configurations and read the tracker",
    )  # fmt: skip
    add_sim(p, arm=SimArm.PERTURB, when="with --collect")
    add_bus(p)  # --config, --bus
    p.add_argument(
        "--samples", type=int, default=DEFAULT_SAMPLES, metavar="N",
        help=f"tracker readings averaged per pose (default {DEFAULT_SAMPLES})",
    )  # fmt: skip
    p.add_argument(
        "--seed", type=int, default=0, metavar="SEED",
        help="seed of the drawn configurations (default 0)",
    )  # fmt: skip
    add_log(p, what="where the run record, CAN logs and pose file go", when="with --collect")
    add_json(p, "the fit")
    p.set_defaults(_run=run_kinematic)

    register_tension_routines(sub)  # zero, stiffness

    p = sub.add_parser(
        "physics",
        help="link masses and each joint's friction from the tension board at held poses",
        description="link masses and each joint's friction from the tension board at held "
        "poses (calibration.physics; the arm out of its fixture)",
    )
    add_robot(p)
    add_calibration(p, Uncalibrated.DRIVES, when="on real drives")
    add_sim(p, arm=SimArm.PERTURB)
    add_physics(p, default=DEFAULT_SIM_PHYSICS)  # --physics EFFECTS, as hrm sim --physics
    add_bus(p)  # --config, --bus
    p.add_argument(
        "--holds", type=int, default=None, metavar="N",
        help="held poses (default 12: about 50 s)",
    )  # fmt: skip
    p.add_argument(
        "--seed", type=int, default=0, metavar="SEED",
        help="seed of the drawn poses (default 0)",
    )  # fmt: skip
    p.add_argument(
        "--payload-kg", type=float, default=None, metavar="KG",
        help="the tip payload, weighed (default the description's [physics] payload_kg): "
        "the arm's statics cannot tell it from the links' masses",
    )  # fmt: skip
    add_out(p, metavar="FILE", what="write this one calibration file")
    add_log(p)
    add_json(p, "the summary")
    p.set_defaults(_run=run_physics)


def run(args: argparse.Namespace) -> int:  # every sub-command sets its own _run
    raise CalibrationDataError("hrm calibrate: give a sub-command (show, history, use, ...)")


# ---- the store ----------------------------------------------------------------------------


def _store(args: argparse.Namespace) -> Any:
    from calibration.store import CalibrationStore

    return CalibrationStore(calibrations_folder(args.calibrations))


def _description(args: argparse.Namespace) -> Any:
    from hrm_ctrl.model import load_robot

    return load_robot(args.robot)


def calibration_dict(cal: Any, version: int | None, path: str | None) -> dict[str, Any]:
    """A calibration as JSON: the file's members (and where it is)."""
    from calibration.apply import file_sha256

    doc: dict[str, Any] = {"version": version, "path": path}
    doc.update(cal.content())
    if version is not None:
        doc["sha256"] = file_sha256(cal, version)
    return doc


def format_calibration(cal: Any, description: Any, version: int, path: str) -> str:
    """The human-readable ``show``: header, a line per joint, per motor, the residuals."""
    lines = [
        f"calibration v{version:04d} (active): {cal.routine.value}, "
        f"{cal.created_utc.isoformat(timespec='seconds')}",
        f"file {path}",
        f"robot description {cal.robot_sha256[:12]}… ({description.source})",
        f"box: {box_text(cal.box)}",
        f"{'joint':>5} {'link mm':>10} {'(descr.)':>9} {'alpha offset deg':>17} "
        f"{'theta offset deg':>17}",
    ]
    for j in range(len(cal.links_mm)):
        lines.append(
            f"{j + 1:>5} {cal.links_mm[j]:>10.4f} {description.links[j]:>9.3f} "
            f"{math.degrees(cal.alpha_offset_rad[j]):>17.5f} "
            f"{math.degrees(cal.theta_offset_rad[j]):>17.5f}"
        )
    lines.append(f"{'motor':>6} {'zero counts':>12} {'EA N':>10}")
    for m in cal.motor_ids:
        ea = cal.rope_EA_N.get(m)
        lines.append(f"{m:>6} {cal.motor_zero_counts[m]:>12} {'' if ea is None else f'{ea:10.1f}'}")
    ph = cal.physics
    if ph is None:
        lines.append("physics: none calibrated (the description's [physics] values)")
    else:
        lines.append(f"physics: payload {1000 * ph.payload_kg:.2f} g (given)")
        lines.append(f"{'joint':>5} {'link mass g':>12} {'mu kinetic':>11}")
        for j in range(len(ph.link_mass_kg)):
            lines.append(f"{j + 1:>5} {1000 * ph.link_mass_kg[j]:>12.3f} {ph.mu_kinetic[j]:>11.4f}")
    res = ", ".join(f"{k} {v:.6g}" for k, v in cal.residuals.items()) or "none"
    lines.append(f"residuals: {res}")
    return "\n".join(lines)


def box_text(box: Any) -> str:
    """The box a calibration was made on, one line (``box unknown`` for an old file)."""
    if box is None:
        return "unknown (made before calibrations named their box: hrm calibrate use N --box)"
    return box.describe()


def run_show(args: argparse.Namespace) -> int:
    from calibration.apply import active_for

    store = _store(args)
    description = _description(args)
    active = active_for(store, description)
    if active is None:
        raise CalibrationFileError(f"{store.folder}: no active calibration")
    if args.json:
        print(json.dumps(calibration_dict(active.calibration, active.version, active.path)))
    else:
        print(format_calibration(active.calibration, description, active.version, active.path))
    return 0


def run_history(args: argparse.Namespace) -> int:
    from calibration.apply import check_belongs, robot_sha256

    store = _store(args)
    description = _description(args)
    mine = robot_sha256(description)
    rows = []
    for h in store.history():
        cal, problem = h.calibration, h.problem
        if cal is not None and cal.robot_sha256 == mine:
            try:  # what ``use`` and every drive session would refuse (ropes, ranges)
                check_belongs(description, cal, str(h.path))
            except CalibrationFileError as exc:
                problem = str(exc)
        rows.append(
            {
                "version": h.version,
                "active": h.active,
                "path": str(h.path),
                "created_utc": None if cal is None else cal.created_utc.isoformat(),
                "routine": None if cal is None else cal.routine.value,
                "robot_sha256": None if cal is None else cal.robot_sha256,
                "this_robot": None if cal is None else cal.robot_sha256 == mine,
                "box": None if cal is None or cal.box is None else cal.box.to_dict(),
                "box_text": None if cal is None else box_text(cal.box).split(" (")[0],
                "problem": problem,
            }
        )
    from hrm_ctrl.cli import one_line

    pointer = store.active_problem()
    if args.json:
        doc = {"store": str(store.folder), "versions": rows, "active_problem": pointer}
        print(json.dumps(doc))
        return 0
    if pointer is not None:  # listed all the same: ``use N`` repairs it
        print(f"  active pointer refused: {one_line(pointer)} (hrm calibrate use N sets it)")
    if not rows:
        print(f"{store.folder}: no calibration yet")
        return 0
    for r in rows:
        mark = "*" if r["active"] else " "
        if r["problem"] is not None:
            print(f"{mark} v{r['version']:04d}  refused: {one_line(r['problem'])}")
            continue
        robot = r["robot_sha256"][:12] + "…" + ("" if r["this_robot"] else " (another robot)")
        print(
            f"{mark} v{r['version']:04d}  {r['created_utc'][:19]}Z  {r['routine']:<9}  "
            f"robot {robot}  box: {r['box_text']}"
        )
    return 0


def run_use(args: argparse.Namespace) -> int:
    """``use VERSION``, or with ``--box`` confirm an old calibration on a box.

    ``--box`` is the one way a calibration whose box is unknown reaches real drives: the
    operator says it was made on this box, the drives' identities are read from it and the
    calibration is saved again as the next version naming them (the old file is never
    changed); a calibration that names its box already is refused (a replaced drive is
    calibrated anew, not confirmed)."""
    from calibration.apply import check_belongs, robot_sha256

    store = _store(args)
    description = _description(args)
    path = str(store.path_of(args.version))
    cal = store.load(args.version)
    check_belongs(description, cal, path)
    if not args.box:
        if args.config is not None or args.bus:
            raise CalibrationDataError("use: --config and --bus go with --box")
        store.use(args.version, robot_sha256(description))
        print(f"active: v{args.version:04d} ({store.path_of(args.version)})")
        return 0
    if cal.box is not None:
        raise CalibrationDataError(
            f"{path}: names its box already ({cal.box.describe()}): --box confirms only a "
            "calibration whose box is unknown"
        )
    if args.config is None:
        raise CalibrationDataError("use --box: give --config BOX.toml, the box to confirm it on")
    refuse_overwriting_inputs([], [robot_input(args.robot), config_input(args.config)])
    import dataclasses

    from calibration.apply import calibrated_actuation
    from hrm_ctrl.runtime.box import identify_box

    config = load_box(args)
    actuation = calibrated_actuation(description, cal)
    config.check_motors(actuation.motor_ids)
    store.check_can_save()  # before the box is touched
    box = identify_box(config, actuation, prog="hrm calibrate use")
    version = store.save(dataclasses.replace(cal, box=box))
    print(
        f"active: v{version:04d} ({store.path_of(version)}): v{args.version:04d} confirmed "
        f"on this box ({box.describe()})"
    )
    return 0


# ---- the kinematic routine ----------------------------------------------------------------


def fit_report(fit: Any) -> dict[str, Any]:
    """The fit as JSON: residuals, every parameter with its standard deviation."""
    return {
        "n_poses": fit.n_poses,
        "rms_before_mm": fit.rms_before_mm,
        "max_before_mm": fit.max_before_mm,
        "rms_after_mm": fit.rms_after_mm,
        "max_after_mm": fit.max_after_mm,
        "sigma_mm": fit.sigma_mm,
        "params": dict(fit.params),
        "std": dict(fit.std),
        "fixed": dict(fit.fixed),
        "links_mm": fit.links_mm.tolist(),
    }


def format_fit(fit: Any) -> str:
    """Residuals before and after, then each parameter and its standard deviation."""
    from calibration.kinematic import ALPHA_NAMES, FRAME_NAMES, LINK_NAMES, THETA_NAMES

    def cell(name: str, scale: float, digits: int) -> str:
        if name in fit.fixed:
            return f"{'fixed':>{digits + 14}}"
        v, s = fit.params[name] * scale, fit.std[name] * scale
        return f"{v:>+{digits + 5}.{digits}f} ± {s:<{digits + 2}.{digits}f}"

    deg = math.degrees(1.0)
    lines = [
        f"{fit.n_poses} poses: residual rms {fit.rms_before_mm:.4f} mm (max "
        f"{fit.max_before_mm:.4f}) before, {fit.rms_after_mm:.4f} mm (max "
        f"{fit.max_after_mm:.4f}) after; sigma {fit.sigma_mm:.4f} mm per coordinate",
        f"{'joint':>5} {'link correction mm':>22} {'alpha offset deg':>22} "
        f"{'theta offset deg':>22}",
    ]
    for j in range(len(LINK_NAMES)):
        lines.append(
            f"{j + 1:>5} {cell(LINK_NAMES[j], 1.0, 4)} {cell(ALPHA_NAMES[j], deg, 4)} "
            f"{cell(THETA_NAMES[j], deg, 4)}"
        )
    if fit.frame_rotation is not None:
        frame = ", ".join(
            f"{n} {fit.params[n]:.6g} ± {fit.std[n]:.2g}" for n in FRAME_NAMES if n in fit.std
        )
        lines.append(f"instrument frame (rad, mm): {frame}")
    for name, why in fit.fixed.items():
        lines.append(f"{name} fixed: {why}")
    return "\n".join(lines)


def _check_kinematic_args(args: argparse.Namespace) -> None:
    if args.collect is None:
        if args.data is None:
            raise CalibrationDataError("kinematic: give DATA.csv or --collect N")
        for flag, given in (("--sim", args.sim), ("--perturb", args.perturb is not None)):
            if given:
                raise CalibrationDataError(f"kinematic: {flag} goes with --collect N")
        return
    if args.data is not None:
        raise CalibrationDataError("kinematic: give DATA.csv or --collect N, not both")
    if not 1 <= args.collect <= MAX_COLLECT:
        raise CalibrationDataError(f"--collect must be 1..{MAX_COLLECT} poses, got {args.collect}")
    if not (args.sim or args.config is not None):
        raise CalibrationDataError("--collect needs --sim or --config BOX.toml")
    if args.perturb is not None and not args.sim:
        raise CalibrationDataError("--perturb goes with --sim")
    if not 1 <= args.samples <= 10_000:
        raise CalibrationDataError(f"--samples must be 1..10000, got {args.samples}")


def run_kinematic(args: argparse.Namespace) -> int:
    from calibration.apply import starting_point
    from calibration.kinematic import fit_kinematics, read_pose_csv

    _check_kinematic_args(args)
    if args.sigma_mm is not None and not (math.isfinite(args.sigma_mm) and args.sigma_mm > 0):
        raise CalibrationDataError(f"--sigma-mm must be > 0, got {args.sigma_mm}")
    store = _store(args)
    inputs = [
        Input("pose file", args.data),
        robot_input(args.robot),
        Input("calibration store's pointer", store.folder / "active"),
        *(Input(f"calibration v{v:04d}", store.path_of(v)) for v in store.versions()),
        calibrations_input(args),  # --out FILE into the store: only the store writes there
    ]
    outputs = [Output("--out", args.out)]
    if args.collect is not None:
        inputs += [config_input(args.config), *shipped_inputs(eds=True)]
        outputs.append(Output("--log-dir", args.log_dir, folder=True))
    refuse_overwriting_inputs(outputs, inputs)  # before anything is read or written
    description = _description(args)
    sim_box = None
    if args.collect is not None and args.sim:  # a calibration of another truth: not used
        from hrm_ctrl.runtime.arm import simulated_box_identity

        sim_box = simulated_box_identity(description, perturb=args.perturb)
    base, active, note = starting_point(store, description, sim_box)

    estimate_frame = args.estimate_frame
    sigma_mm = 0.05 if args.sigma_mm is None else args.sigma_mm
    if args.collect is None:
        data = read_pose_csv(args.data)
    else:
        if args.out is None:  # checked before the first move: the result has a place to go
            store.check_can_save()
        data, pose_file = _collect(args, description, base, active)
        print(f"poses written to {pose_file}")
        # the points are in the base frame: the tracker's frame was found from the base nests
        if args.sigma_mm is None:
            sigma_mm /= math.sqrt(args.samples)
    fit = fit_kinematics(
        description,
        data.alpha_rad,
        data.theta_rad,
        data.points_mm,
        estimate_frame=estimate_frame,
        sigma_mm=sigma_mm,
    )
    from calibration.workflows import kinematic_calibration

    new = kinematic_calibration(base, fit)
    if note is not None:  # what the new version starts from, once there is one
        print(f"hrm calibrate kinematic: {note}", file=sys.stderr)
    saved = save_calibration(args, store, new, description)
    if args.json:
        active = args.out is None and store.active() == saved.version
        doc = {
            "fit": fit_report(fit),
            "version": saved.version,
            "file": saved.where,
            "active": active,
            "in_range": saved.usable,
        }
        print(json.dumps(doc))
    else:
        print(format_fit(fit))
        print(f"calibration {saved.where}")
    return 0 if saved.usable else EXIT_NOT_USABLE


def _collect(args: argparse.Namespace, description: Any, base: Any, active: Any) -> Any:
    """Drive the arm through ``args.collect`` configurations and read the tracker; return
    the poses and the pose file written into the log folder.  Every pose is kept as it is
    measured (``calibration.collect.PoseJournal``, in the log folder): the same command
    after a stop resumes from them."""
    from calibration.collect import PoseJournal, journal_key

    prog = "hrm calibrate kinematic"
    alpha, theta = _collect_targets(args, description)
    arm_id = f"sim, perturb {args.perturb}" if args.sim else "real box"
    key = journal_key(alpha, theta, str(args.robot), arm_id,
                      "no calibration" if active is None else active.sha256)  # fmt: skip
    journal = PoseJournal(Path(args.log_dir) / f"collect-{key}.json", key, args.collect)
    if len(journal):
        print(f"{prog}: resuming: {len(journal)} of {args.collect} poses kept in "
              f"{journal.path}", file=sys.stderr)  # fmt: skip
    else:
        print(f"{prog}: poses kept in {journal.path} as they are measured", file=sys.stderr)
    try:
        data, pose_file = _collect_rest(args, description, base, active, alpha, theta, journal)
    except BaseException:
        if len(journal):
            print(f"{prog}: {len(journal)} of {args.collect} poses kept in {journal.path}: "
                  "the same command resumes from them", file=sys.stderr)  # fmt: skip
        raise
    journal.remove()
    return data, pose_file


def _collect_targets(args: argparse.Namespace, description: Any) -> Any:
    """The configurations of ``--collect N --seed S``, in the order they are visited."""
    import numpy as np

    from calibration.collect import travel_order
    from calibration.kinematic import spread_configurations

    rng = np.random.default_rng(args.seed)
    alpha, theta = spread_configurations(description, args.collect, rng)
    order = travel_order(alpha, theta)  # short moves: the same poses
    return alpha[order], theta[order]


def _collect_rest(
    args: argparse.Namespace,
    description: Any,
    base: Any,
    active: Any,
    alpha: Any,
    theta: Any,
    journal: Any,
) -> Any:
    """The poses ``journal`` does not keep yet, collected (each kept as it is measured);
    return all the poses and the pose file."""
    import numpy as np

    from calibration.apply import calibrated_actuation, calibrated_model
    from calibration.kinematic import PoseData, format_pose_csv
    from calibration.workflows import collect_in_base_frame, tracker_frame
    from drivers.bus import ensure_log_dir
    from drivers.tracker import TrackerReader
    from hrm_ctrl.cli._progress import ProgressBar, bring_up_with_progress, wanted
    from hrm_ctrl.files import write_atomic
    from hrm_ctrl.runtime.arm import Arm
    from hrm_ctrl.runtime.box import SessionOptions, WatchOptions, caller_scheduling, open_box
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

    prog = "hrm calibrate kinematic"
    config = load_box(args)  # --config with the --bus overrides
    actuation = calibrated_actuation(description, base)
    config.check_motors(actuation.motor_ids)
    actuation.check_angles(alpha, theta)
    ensure_log_dir(args.log_dir)
    k0 = len(journal)
    if k0 == args.collect:  # every pose kept: nothing to drive
        data = journal.kept
        pose_file = journal.path.with_name(f"{journal.path.stem}-poses.csv")
        write_atomic(pose_file, format_pose_csv(data.alpha_rad, data.theta_rad, data.points_mm))
        return data, pose_file
    arm = Arm(description, calibrated_model(description, base), active, rope_layer=actuation)
    ref = arm.calibration_ref()
    if ref is None and args.uncalibrated:
        print(f"{prog}: --uncalibrated: drives enabled without a calibration", file=sys.stderr)
    elif ref is None and args.sim:
        print(
            f"{prog}: --sim: no calibration: the robot description's values (a simulated arm)",
            file=sys.stderr,
        )
    sim = None
    if args.sim:  # the simulated arm: its description, or a perturbed one
        sim = SimulatedBox(simulated_arm(arm, perturb=args.perturb), tracker=True)
    elif config.tracker is None:  # refused before any bus opens
        raise CalibrationDataError(
            f"{config.source}: no [tracker] table: --collect needs the laser tracker"
        )
    options = SessionOptions(
        log_dir=args.log_dir,
        log_suffix=f".{args.log_format}",
        calibration=ref,
        allow_uncalibrated=args.uncalibrated or args.sim,
        record_extra={"routine": "kinematic", "poses": args.collect},
    )
    # The rope-consistency watch is left out while collecting: on the in-process simulated
    # box its figure jumps on fast moves (one collection in three stopped falsely;
    # docs/calibration.md).  The tension watch runs.
    watches = WatchOptions(ropes=False)
    with (
        open_box(
            config, actuation, options, sim=sim, watches=watches, bring_up=False, prog=prog
        ) as box,
    ):
        tracker = box.config.tracker  # the simulated box's, or the configured one
        session = box.session
        with (
            TrackerReader(tracker.port, tracker.timeout_s, baudrate=tracker.baudrate) as reader,
            caller_scheduling(session),  # the poses' moves computed, the tracker read
        ):
            show = wanted(getattr(args, "json", False))
            box.bring_up(lambda s: bring_up_with_progress(s, enabled=show))
            with ProgressBar("calibration poses", enabled=show) as bar:

                def progress(k: int, n: int, p: np.ndarray) -> None:
                    k, n = k + k0, n + k0  # the poses kept before count too
                    text = f"pose {k}/{n}: {p[0]:.3f} {p[1]:.3f} {p[2]:.3f} mm"
                    if show:
                        bar(k / n)
                        bar.line(text)
                    else:
                        print(text, file=sys.stderr)

                frame = tracker_frame(reader, description)

                def keep(_k: int, a: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
                    journal.add(a, t, frame.to_base(p[None, :])[0])

                print(
                    f"tracker frame from {len(description.base_fiducials)} base nests: fit "
                    f"{frame.rms_mm:.3f} mm rms",
                    file=sys.stderr,
                )
                data, _ = collect_in_base_frame(
                    session,
                    actuation,
                    reader,
                    description,
                    alpha[k0:],
                    theta[k0:],
                    period_s=box.config.control.period_s,
                    frame=frame,
                    samples=args.samples,
                    source=f"{session.run_name} (collected)",
                    progress=progress,
                    on_pose=keep,
                )
        if k0:  # the poses kept before, then these (all in the journal now)
            kept = journal.kept
            data = PoseData(kept.alpha_rad, kept.theta_rad, kept.points_mm, data.source)
        pose_file = Path(args.log_dir) / f"{session.run_name}-poses.csv"
        write_atomic(pose_file, format_pose_csv(data.alpha_rad, data.theta_rad, data.points_mm))
        session.record_extra["pose_file"] = str(pose_file)
    return data, pose_file


# ---- the physics routine ------------------------------------------------------------------


def _check_physics_args(args: argparse.Namespace) -> Any:
    """The routine's options checked before anything opens; the simulated arm's physics
    (None without --sim)."""
    from calibration.physics import MIN_HOLDS

    if args.sim == (args.config is not None):
        raise CalibrationDataError("physics: give --sim or --config BOX.toml")
    if args.perturb is not None and not args.sim:
        raise CalibrationDataError("--perturb goes with --sim")
    if args.physics != DEFAULT_SIM_PHYSICS and not args.sim:
        raise CalibrationDataError("--physics goes with --sim")
    if args.holds is not None and not MIN_HOLDS <= args.holds <= 500:
        raise CalibrationDataError(f"--holds must be {MIN_HOLDS}..500, got {args.holds}")
    kg = args.payload_kg
    if kg is not None and not (math.isfinite(kg) and 0.0 <= kg <= 1000.0):
        raise CalibrationDataError(f"--payload-kg must be 0..1000, got {kg}")
    if not args.sim:
        return None
    from sim_bus.physics import Physics

    return Physics.of(args.physics)  # a bad one refused here, one line


def run_physics(args: argparse.Namespace) -> int:
    """``hrm calibrate physics``: the routine on its own session, saved as a version."""
    import dataclasses
    import time
    from contextlib import closing

    from calibration.apply import calibrated_actuation, calibrated_model, starting_point
    from calibration.physics import DEFAULT_HOLDS, calibrate_physics
    from calibration.workflows import physics_calibration
    from drivers.bus import ensure_log_dir
    from drivers.tension_sensor import TensionSensorReader
    from hrm_ctrl.runtime.arm import Arm
    from hrm_ctrl.runtime.box import NO_WATCHES, SessionOptions, caller_scheduling, open_box
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

    prog = "hrm calibrate physics"
    physics = _check_physics_args(args)
    t0 = time.monotonic()
    store = _store(args)
    active_file = store.path_of(store.active()) if store.active() is not None else None
    refuse_overwriting_inputs(  # before anything is read or written
        [Output("--out", args.out), Output("--log-dir", args.log_dir, folder=True)],
        [
            robot_input(args.robot),
            Input("active calibration", active_file),
            calibrations_input(args),
            config_input(args.config),
            *shipped_inputs(eds=True),
        ],
    )
    if args.out is None:  # checked before the first move: the result has a place to go
        store.check_can_save()
    description = _description(args)
    config = load_box(args)
    sim_box = None
    if args.sim:  # known before it starts: a calibration of another truth is not used
        from hrm_ctrl.runtime.arm import simulated_box_identity

        sim_box = simulated_box_identity(description, perturb=args.perturb)
    base, active, note = starting_point(store, description, sim_box)
    if note is not None:
        print(f"{prog}: {note}", file=sys.stderr)
    actuation = calibrated_actuation(description, base)
    config.check_motors(actuation.motor_ids)
    ensure_log_dir(args.log_dir)
    arm = Arm(description, calibrated_model(description, base), active, rope_layer=actuation)
    ref = arm.calibration_ref()
    allow = args.sim or args.uncalibrated
    if ref is None and not allow:
        raise CalibrationFileError(
            f"{store.folder}: no calibration for this robot: run hrm calibrate zero, "
            "stiffness and kinematic first (or --uncalibrated to enable the drives anyway)"
        )
    sim = None
    if args.sim:  # the simulated arm out of its fixture, with its physics
        sim = SimulatedBox(dataclasses.replace(simulated_arm(arm, perturb=args.perturb),
                                               physics=physics))  # fmt: skip
    elif config.tension is None:  # refused before any bus opens
        raise CalibrationDataError(
            f"{config.source}: no [tension] table: physics needs the tension sensors"
        )
    options = SessionOptions(
        log_dir=args.log_dir,
        log_suffix=f".{args.log_format}",
        calibration=ref,
        allow_uncalibrated=allow,
        record_extra={"routine": "physics", "simulated_box": bool(args.sim)},
    )
    out = sys.stderr if args.json else sys.stdout
    # no feedback watches: the routine guards the tensions itself (its own reader)
    with open_box(
        config, actuation, options, sim=sim, watches=NO_WATCHES, bring_up=False, prog=prog
    ) as box:
        t = box.config.tension
        with box.session.thread_scheduling():
            opened = TensionSensorReader(
                t.port, actuation.n_motors, baudrate=t.baudrate, stale_after_s=t.stale_s
            ).open()
        with closing(opened) as reader:
            box.bring_up()
            with caller_scheduling(box.session):
                result = calibrate_physics(
                    box.session, reader, actuation, period_s=box.config.control.period_s,
                    holds=DEFAULT_HOLDS if args.holds is None else args.holds,
                    seed=args.seed, payload_kg=args.payload_kg,
                    progress=lambda line: print(line, file=out, flush=True),
                )  # fmt: skip
    fit = result.fit
    residuals = {**fit.residuals(), "routine_s": round(result.elapsed_s, 3)}
    new = physics_calibration(base, fit, residuals)
    saved = save_calibration(args, store, new, description)
    summary = {
        "link_mass_kg": fit.link_mass_kg.tolist(),
        "payload_kg": fit.payload_kg,
        "mu_kinetic": fit.mu_kinetic.tolist(),
        "std_mass_kg": fit.std_mass_kg.tolist(),
        "std_mu": fit.std_mu.tolist(),
        "holds": fit.n_holds,
        "holds_dropped": fit.n_dropped,
        "balance_rms_before_Nmm": fit.rms_before_Nmm,
        "balance_rms_after_Nmm": fit.rms_after_Nmm,
        "routine_s": result.elapsed_s,
        "total_s": time.monotonic() - t0,
        "version": saved.version,
        "file": saved.where,
        "active": args.out is None and store.active() == saved.version,
        "in_range": saved.usable,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"physics: {fit.n_holds} holds ({fit.n_dropped} dropped), link masses "
            f"{1000 * fit.link_mass_kg.min():.1f} .. {1000 * fit.link_mass_kg.max():.1f} g "
            f"(payload {1000 * fit.payload_kg:.1f} g, given), friction "
            f"{fit.mu_kinetic.min():.3f} .. {fit.mu_kinetic.max():.3f}; balance rms "
            f"{fit.rms_before_Nmm:.2f} -> {fit.rms_after_Nmm:.2f} N mm; {result.elapsed_s:.1f} s"
        )
        print(f"calibration {saved.where}")
    return 0 if saved.usable else EXIT_NOT_USABLE
