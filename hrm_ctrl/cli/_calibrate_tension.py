"""``hrm calibrate zero`` and ``hrm calibrate stiffness``: the rope-tension routines
(issue 12), sub-commands of ``hrm calibrate`` (:mod:`hrm_ctrl.cli.calibrate` calls
:func:`register`).

Both run with the arm in its zero fixture (a jig that clamps each joint's rope disks
coaxial: the rope geometry held straight, so each rope's tension depends on its own motor
only); with ``--sim`` the simulated arm is put into its fixture (the technician lays the
arm in it), with ``--config BOX.toml`` the real arm must lie in it.  The tension board is
the configuration's ``[tension]`` port (with ``--sim`` the simulated box's board).  The
feedback watches of ``hrm run`` do not run (a slack rope is what the zero routine starts
from, and the fixture holds the arm against its ropes): the routines guard the tensions
themselves (:class:`calibration.zero.TensionGuard`).

* ``zero``: :func:`calibration.zero.pretension_and_zero`; every motor's count at the
  target tension (``--target-N``, default the pretension) becomes its zero;
* ``stiffness``: :func:`calibration.stiffness.estimate_rope_stiffness` from the active
  zero; every rope's EA.

Each starts from the active calibration for this robot (the description's values when
there is none), prints a line per rope group and a summary, and saves a new version with
its own fields replaced (``calibration.apply.updated``), or with ``--out FILE`` writes that
one file.  A refusal (a slack or snapped rope, a tension over its limit, a saturated or
invalid sensor) is one line, exit 2, nothing saved.  The zero routine may run on drives
without a calibration (it is how the first one is made: its moves are small and guarded
by the tension sensors); the stiffness routine needs one unless ``--sim`` or
``--uncalibrated``.

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm calibrate")
>>> register(p.add_subparsers(dest="calibrate"))
>>> a = p.parse_args(["zero", "--sim", "--perturb", "3", "--target-N", "25"])
>>> a.calibrate, a.sim, a.perturb, a.target_N
('zero', True, 3, 25.0)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
    add_robot,
    add_sim,
    add_stiffness_options,
    add_zero_options,
)
from hrm_ctrl.errors import CalibrationDataError, CalibrationFileError

if TYPE_CHECKING:  # the CLI starts without the calibration package
    from calibration.workflows import Saved


def _arguments(p: argparse.ArgumentParser) -> None:
    add_robot(p)
    add_calibration(p, Uncalibrated.DRIVES, when="on real drives")
    add_sim(p, arm=SimArm.PERTURB)
    add_bus(p)  # --config, --bus
    add_out(p, metavar="FILE", what="write this one calibration file")
    add_log(p)
    add_json(p, "the summary")


def register(subparsers: Any) -> None:
    """Add ``zero`` and ``stiffness`` to ``hrm calibrate``'s sub-commands."""
    p = subparsers.add_parser(
        "zero",
        help="pretension every rope in the zero fixture and record the motor zeros",
        description="pretension every rope in the zero fixture and record the motor zeros",
    )
    _arguments(p)
    add_zero_options(p)
    p.set_defaults(_run=run_zero)

    p = subparsers.add_parser(
        "stiffness",
        help="each rope's EA from tension sweeps in the zero fixture",
        description="each rope's EA from tension sweeps in the zero fixture",
    )
    _arguments(p)
    add_stiffness_options(p)
    p.set_defaults(_run=run_stiffness)


def _check(args: argparse.Namespace) -> None:
    if args.sim == (args.config is not None):
        raise CalibrationDataError(f"{args.calibrate}: give --sim or --config BOX.toml")
    if args.perturb is not None and not args.sim:
        raise CalibrationDataError("--perturb goes with --sim")
    for name in ("target_N", "tol_N", "sweep_N"):
        v = getattr(args, name, None)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise CalibrationDataError(f"--{name.replace('_', '-')} must be > 0, got {v}")


def _write_file(path: Path, text: str) -> None:
    from hrm_ctrl.files import write_atomic

    try:
        write_atomic(path, text)
    except OSError as exc:
        raise CalibrationFileError(f"{path}: cannot write ({exc.strerror or exc})") from None


def _session_run(args: argparse.Namespace, prog: str, routine: Any) -> tuple[Any, Any, Any, Any]:
    """Open the store and the box (``--sim``: the simulated one, its arm in the fixture),
    bring the drives up and run ``routine(session, reader, actuation)``; return
    ``(result, base calibration, store, robot description, the box's identity)``."""
    from calibration.apply import calibrated_actuation, calibrated_model, starting_point
    from calibration.store import CalibrationStore
    from drivers.bus import ensure_log_dir
    from drivers.tension_sensor import TensionSensorReader
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.runtime.arm import Arm
    from hrm_ctrl.runtime.box import NO_WATCHES, SessionOptions, caller_scheduling, open_box
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

    store = CalibrationStore(calibrations_folder(args.calibrations))
    active_file = store.path_of(store.active()) if store.active() is not None else None
    refuse_overwriting_inputs(  # before anything is read or written
        [Output("--out", args.out), Output("--log-dir", args.log_dir, folder=True)],
        [
            robot_input(args.robot),
            Input("active calibration", active_file),
            calibrations_input(args),  # --out FILE into the store: only the store writes there
            config_input(args.config),
            *shipped_inputs(eds=True),
        ],
    )
    if args.out is None:  # checked before the first move: the result has a place to go
        store.check_can_save()
    description = load_robot(args.robot)
    config = load_box(args)  # --config with the --bus overrides
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
    if ref is not None and args.calibrate == "zero":  # every zero measured anew: any box
        ref = dataclasses.replace(ref, check_box=False)
    allow = args.sim or args.uncalibrated or args.calibrate == "zero"
    if ref is None and not allow:
        raise CalibrationFileError(
            f"{store.folder}: no calibration for this robot: run hrm calibrate zero first "
            "(or --uncalibrated to enable the drives anyway)"
        )
    if ref is None:
        print(f"{prog}: drives enabled without a calibration (this routine makes one)",
              file=sys.stderr)  # fmt: skip

    sim = None
    if args.sim:  # the simulated arm: its description, or a perturbed one, in its fixture
        sim = SimulatedBox(simulated_arm(arm, perturb=args.perturb), fixture=True)
    else:
        if config.tension is None:  # refused before any bus opens
            raise CalibrationDataError(
                f"{config.source}: no [tension] table: {args.calibrate} needs the tension sensors"
            )
        print(f"{prog}: the arm must lie in its zero fixture", file=sys.stderr)
    options = SessionOptions(
        log_dir=args.log_dir,
        log_suffix=f".{args.log_format}",
        calibration=ref,
        allow_uncalibrated=allow,
        record_extra={"routine": args.calibrate, "simulated_box": bool(args.sim)},
    )
    # no feedback watches: the routines guard the tensions themselves
    with open_box(
        config, actuation, options, sim=sim, watches=NO_WATCHES, bring_up=False, prog=prog
    ) as box:
        t = box.config.tension  # the simulated box's board, or the configured one
        # its reading thread under the session's scheduling (SCHED_FIFO where granted), as
        # the watches' readers: under normal scheduling beside two CPU burners it fell
        # 502 ms behind the board
        with box.session.thread_scheduling():
            opened = TensionSensorReader(
                t.port, actuation.n_motors, baudrate=t.baudrate, stale_after_s=t.stale_s
            ).open()
        with contextlib.closing(opened) as reader:
            box.bring_up()
            with caller_scheduling(box.session):  # what the routine computes between moves
                result = routine(box.session, reader, actuation)
    return result, base, store, description, box.session.box_identity


EXIT_NOT_USABLE = 1  # a routine ran and kept its result, which loading would refuse


def save_calibration(args: argparse.Namespace, store: Any, new: Any, description: Any) -> Saved:
    """Save ``new`` as the store's next version (active), or with ``--out FILE`` write that
    one file (numbered as the store's next): :func:`calibration.workflows.save_calibration`.

    A result that ``hrm calibrate use`` and every drive session would refuse (a value out
    of :func:`calibration.apply.check_ranges`) is still kept, the routine's work is not
    lost, but not made active: the active version stays what it was, stderr says why, and
    the command exits :data:`EXIT_NOT_USABLE` (a script does not go on to drive with the
    calibration it had as if the routine had succeeded).  ``--out`` writes such a result
    with the same stderr line.
    """
    from calibration.workflows import save_calibration as save

    saved, problem = save(store, new, description, out=args.out, write=_write_file)
    if problem is not None:
        what = args.out if args.out is not None else f"v{saved.version:04d}"
        how = "would be refused" if args.out is not None else "not made active"
        print(f"hrm calibrate: {what} {how}: {problem}", file=sys.stderr)
    return saved


def _progress(args: argparse.Namespace) -> Any:
    stream = sys.stderr if args.json else sys.stdout
    return lambda line: print(line, file=stream, flush=True)


def _run_routine(args: argparse.Namespace, build: Any, report: Any) -> int:
    """Check the options, build the routine (refusing bad ones before anything opens),
    run it on its own session, save and print (``hrm calibrate zero|stiffness``)."""
    _check(args)
    routine = build(args)
    t0 = time.monotonic()
    result, base, store, description, box = _session_run(
        args, f"hrm calibrate {args.calibrate}", routine
    )
    saved = report(args, result, base, store, t0, print, description, box=box)
    return 0 if saved.usable else EXIT_NOT_USABLE


def run_zero(args: argparse.Namespace) -> int:
    return _run_routine(args, zero_routine, report_zero)


def zero_routine(
    args: argparse.Namespace, progress: Callable[[str], None] | None = None
) -> Callable[[Any, Any, Any], Any]:
    """``routine(session, reader, actuation)`` of ``zero`` with ``args``' options
    (``target_N``, ``tol_N``, ``max_travel_counts``; checked here, before anything moves);
    ``progress`` gets a line per rope group (default: stdout, stderr with ``--json``)."""
    from calibration.zero import pretension_and_zero

    kw: dict[str, Any] = {}
    if args.tol_N is not None:
        kw["tol_N"] = args.tol_N
    if args.max_travel_counts is not None:
        if args.max_travel_counts <= 0:
            raise CalibrationDataError(
                f"--max-travel-counts must be > 0, got {args.max_travel_counts}"
            )
        kw["max_travel_counts"] = args.max_travel_counts

    def routine(box: Any, reader: Any, actuation: Any) -> Any:
        return pretension_and_zero(
            box, reader, actuation, target_N=args.target_N,
            progress=progress or _progress(args), **kw,
        )  # fmt: skip

    return routine


def report_zero(
    args: argparse.Namespace, result: Any, base: Any, store: Any, t0: float,
    out: Callable[[str], None], description: Any, *, box: Any = None,
) -> Saved:  # fmt: skip
    """Save the zero's calibration (:func:`save_calibration`), made on ``box`` (the
    session's :class:`drivers.identity.BoxIdentity`), and print its summary (``out``: one
    line each; JSON with ``args.json``); returns where it went.  A ``base`` made on
    another box lends the new version nothing (:func:`calibration.apply.for_box`)."""
    import numpy as np

    from calibration.apply import for_box
    from calibration.workflows import zero_calibration

    base, note = for_box(base, box, description)
    if note is not None:
        print(f"hrm calibrate zero: {note}", file=sys.stderr)
    zeros = {m: int(v) for m, v in zip(result.motor_ids, result.zero_counts, strict=True)}
    residuals = {**result.residuals(), "routine_s": round(result.elapsed_s, 3)}
    new = zero_calibration(base, result, residuals, box=box)
    saved = save_calibration(args, store, new, description)
    version, where = saved.version, saved.where
    shift = result.zero_shift_counts
    worst = int(np.argmax(np.abs(shift)))
    err = np.abs(result.tension_error_N)
    summary = {
        "motors": len(result.motor_ids),
        "target_N": result.target_N,
        "tol_N": result.tol_N,
        "max_abs_zero_shift_counts": int(abs(shift[worst])),
        "max_shift_motor": result.motor_ids[worst],
        "max_abs_tension_error_N": float(err.max()),
        "moves": result.moves,
        "routine_s": result.elapsed_s,
        "total_s": time.monotonic() - t0,
        "version": version,
        "file": where,
        "active": args.out is None and store.active() == version,
        "in_range": saved.usable,
        "zero_counts": zeros,
    }
    if args.json:
        out(json.dumps(summary))
    else:
        out(
            f"zero: {len(result.motor_ids)} motors at {result.target_N:g} N: max |zero - before| "
            f"{abs(int(shift[worst]))} counts ({result.motor_ids[worst]}), final tension error "
            f"max {err.max():.3f} N (tol {result.tol_N:g}), {result.moves} moves, "
            f"{result.elapsed_s:.1f} s"
        )
        out(f"calibration {where}")
    return saved


def run_stiffness(args: argparse.Namespace) -> int:
    return _run_routine(args, stiffness_routine, report_stiffness)


def stiffness_routine(
    args: argparse.Namespace, progress: Callable[[str], None] | None = None
) -> Callable[[Any, Any, Any], Any]:
    """``routine(session, reader, actuation)`` of ``stiffness`` with ``args``' options
    (``sweep_N``, ``steps``); ``progress`` as :func:`zero_routine`'s."""
    from calibration.stiffness import estimate_rope_stiffness

    kw: dict[str, Any] = {}
    if args.sweep_N is not None:
        kw["sweep_N"] = args.sweep_N
    if args.steps is not None:
        kw["steps"] = args.steps

    def routine(box: Any, reader: Any, actuation: Any) -> Any:
        return estimate_rope_stiffness(
            box, reader, actuation, progress=progress or _progress(args), **kw
        )

    return routine


def report_stiffness(
    args: argparse.Namespace, result: Any, base: Any, store: Any, t0: float,
    out: Callable[[str], None], description: Any, *, box: Any = None,
) -> Saved:  # fmt: skip
    """Save the stiffness's calibration and print its summary; returns where it went."""
    import numpy as np

    from calibration.workflows import stiffness_calibration

    ea = {m: float(v) for m, v in zip(result.motor_ids, result.EA_N, strict=True)}
    residuals = {**result.residuals(), "routine_s": round(result.elapsed_s, 3)}
    new = stiffness_calibration(base, result, residuals)
    saved = save_calibration(args, store, new, description)
    version, where = saved.version, saved.where
    rel = result.EA_sigma_N / result.EA_N
    change = result.EA_N / result.before_EA_N - 1.0
    worst = int(np.nanargmax(np.abs(change)))
    summary = {
        "ropes": len(result.motor_ids),
        "max_rel_sigma_EA": float(np.nanmax(rel)),
        "max_rel_change_EA": float(abs(change[worst])),
        "max_change_rope": result.motor_ids[worst],
        "max_fit_rms_N": float(np.nanmax(result.fit_rms_N)),
        "moves": result.moves,
        "routine_s": result.elapsed_s,
        "total_s": time.monotonic() - t0,
        "version": version,
        "file": where,
        "active": args.out is None and store.active() == version,
        "in_range": saved.usable,
        "rope_EA_N": ea,
    }
    if args.json:
        out(json.dumps(summary))
    else:
        out(
            f"stiffness: {len(result.motor_ids)} ropes: EA {result.EA_N.min():.0f} .. "
            f"{result.EA_N.max():.0f} N, sigma at most {100 * np.nanmax(rel):.2f} %, largest "
            f"change {100 * change[worst]:+.1f} % ({result.motor_ids[worst]}), "
            f"{result.moves} moves, {result.elapsed_s:.1f} s"
        )
        out(f"calibration {where}")
    return saved
