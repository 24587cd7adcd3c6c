"""``hrm report RUN``: the figures of a run, from its run record and CAN logs.

``RUN`` is a run record (``runs/run-....json``) or a run's name in ``--log-dir``.  The
CAN logs are read with python-can (``hrm_ctrl.formats.runlog``) and the counts mapped to
joint angles by the rope layer of the robot description with the active calibration
(``--calibrations``, ``--uncalibrated``: as ``hrm run``; a stderr line says so when the
run named another calibration).  Writes ``angles.png`` (planned vs measured joint
angles), ``tracking.png`` (tracking error and, with a tension side file, tensions over
time) and ``lateness.png`` (cycle lateness) into ``--out`` (default: ``<run>_report/``
beside the record) and prints where, with the figures' numbers (``--json``: as JSON).

Bad input is one line and exit status 2, with nothing written: an ``--out`` naming one of
the run's files (its record, CAN logs or tension file, the robot description, the
calibration store) or a path that is not a folder is refused before the CAN logs are
read (the record's own path and the tension file before anything is read), and a damaged
record or log, or a figure that cannot be written, leaves no figure behind.  The frames
each CAN log holds are compared with the counts the run record keeps: a log that misses
frames (cut, damaged, frames lost as it was written) is refused the same way, naming the
log and both counts; ``--partial`` draws the figures from what the logs hold, with a
warning line per log (and ``complete: false``, ``missing`` in the JSON summary).

>>> p = argparse.ArgumentParser(prog="hrm report")
>>> register(p)
>>> a = p.parse_args(["runs/run-1.json", "--stream", "0"])
>>> str(a.run), a.stream
('runs/run-1.json', 0)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from hrm_ctrl.cli._common import Input

HELP = "write the figures of a run (planned vs measured angles, tracking, tensions, lateness)"


def register(parser: argparse.ArgumentParser) -> None:
    from hrm_ctrl.cli._options import (
        Uncalibrated,
        add_calibration,
        add_json,
        add_log,
        add_out,
        add_robot,
    )

    parser.add_argument("run", type=Path, metavar="RUN", help="run record, or a run's name")
    add_log(parser, what="where runs are looked up by name", formats=False)
    add_out(
        parser, metavar="DIR", what="where the figures go (default <run>_report/ beside the record)"
    )
    parser.add_argument(
        "--stream", type=int, default=-1, metavar="N",
        help="which stream of the session (0 first; default the last)",
    )  # fmt: skip
    add_robot(parser)
    add_calibration(parser, Uncalibrated.MODEL)
    parser.add_argument(
        "--partial", action="store_true",
        help="draw the figures even from CAN logs that miss frames the run record counts "
        "(a cut or damaged log), with a warning line per log (default: refused)",
    )  # fmt: skip
    add_json(parser, "the summary")


def find_record(run: Path, log_dir: Path) -> Path:
    """A run record: the path given, or ``<log_dir>/<run>.json`` for a run's name."""
    from hrm_ctrl.formats.runlog import RunLogError

    # os.path: False, not OSError, for a name too long for the file system
    if run.suffix == ".json" or os.path.exists(run):
        if not os.path.isfile(run):
            raise RunLogError(f"{run}: no such run record")
        return run
    cand = log_dir / f"{run.name}.json"
    if os.path.isfile(cand):
        return cand
    raise RunLogError(f"{run}: no such run record (nor {cand})")


def out_folder(record: Path, out: Path | None) -> Path:
    """Where the figures go: ``out``, or ``<run>_report/`` beside the record."""
    return out if out is not None else record.with_name(record.stem + "_report")


def check_out(folder: Path, inputs: list[Input]) -> None:
    """Refuse (one line) an output folder that names one of ``inputs`` (or holds one
    where a figure would go), that exists and is not a folder, or whose nearest existing
    parent is not a folder; looks at paths only."""
    import os

    from hrm_ctrl.cli._common import Output, refuse_overwriting_inputs
    from hrm_ctrl.errors import HrmError
    from hrm_ctrl.formats.runplots import FIGURE_NAMES

    refuse_overwriting_inputs([Output("--out", folder, FIGURE_NAMES, folder=True)], inputs)
    if os.path.lexists(folder) and not os.path.isdir(folder):
        raise HrmError(f"--out {folder}: exists and is not a folder")
    above = next((d for d in folder.parents if os.path.lexists(d)), None)
    if above is not None and not os.path.isdir(above):  # a file where a folder would be made
        raise HrmError(f"--out {folder}: {above} is not a folder")


def report(
    record: Path, actuation: Any, out: Path | None, stream: int = -1, *, partial: bool = False
) -> tuple[dict[str, Any], list[Path]]:
    """Read the run, write its figures; (summary, figure paths).  A figure that cannot be
    written is one line (:class:`~hrm_ctrl.errors.HrmError`) and leaves none behind.

    CAN logs that miss frames the run record counts (:func:`~hrm_ctrl.formats.runlog.
    missing_frames`: a cut or damaged log, frames lost as it was written) are refused, one
    line naming the log and both counts, unless ``partial``: then the figures are drawn
    from what the logs hold and the summary's ``missing`` says what is not there
    (``complete`` False; None where the record keeps no counts)."""
    from hrm_ctrl.errors import HrmError
    from hrm_ctrl.formats.runlog import RunLogError, missing_frames, read_run
    from hrm_ctrl.formats.runplots import run_analysis, write_run_figures

    log = read_run(record)
    missing = missing_frames(log)
    if missing and not partial:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise RunLogError(f"{missing[0]}{more}: no figures (--partial draws what the logs hold)")
    analysis = run_analysis(log, actuation, stream)
    folder = out_folder(record, out)
    name = log.record.get("run")
    # a record's text is shown as a name only when it prints as one line of a name
    name = (
        name
        if isinstance(name, str) and name.isprintable() and 0 < len(name) <= 200
        else record.stem
    )
    try:
        figures = write_run_figures(analysis, folder, title=name)
    except OSError as exc:
        where = exc.filename if exc.filename is not None else folder
        raise HrmError(
            f"--out {folder}: cannot write the figures ({where}: {exc.strerror or exc})"
        ) from None
    summary = {
        "run": name,
        "record": str(record),
        "stream": stream,
        "streams": len(log.streams),
        "complete": None if missing is None else not missing,
        "missing": missing or [],
        **analysis.summary(),
        "figures": [str(p) for p in figures],
    }
    return summary, figures


def _version(v: object) -> str:
    """A record's calibration version as one short line (an int, else its repr, cut).

    >>> _version(3), _version("\\n\\nx")
    ('3', "'\\\\n\\\\nx'")
    """
    if isinstance(v, int) and not isinstance(v, bool):
        return str(v)
    return ascii(v)[:40]


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.cli._common import Input, arm_from_args, calibrations_input, robot_input
    from hrm_ctrl.cli._progress import ProgressBar, wanted
    from hrm_ctrl.formats.runlog import log_paths, read_record, tension_path
    from hrm_ctrl.model import load_robot

    record = find_record(args.run, args.log_dir)
    folder = out_folder(record, args.out)
    inputs = [
        Input("run record", record),
        Input("tension file", tension_path(record)),
        robot_input(args.robot),
        calibrations_input(args),
    ]
    check_out(folder, inputs)  # before anything is read
    doc = read_record(record)
    check_out(folder, [Input("CAN log", p) for p in log_paths(record, doc)])  # it names them
    arm = arm_from_args(args, load_robot(args.robot), prog="hrm report")
    with ProgressBar("report", enabled=wanted(args.json)) as bar:
        summary, _figs = report(record, arm.actuation, folder, args.stream, partial=args.partial)
        bar(1.0)
    for line in summary["missing"]:  # with --partial only: else refused above
        print(
            f"hrm report: warning: {line}: figures drawn from what the log holds", file=sys.stderr
        )
    if summary["complete"] is None:
        print(
            f"hrm report: note: {record}: the run record does not count its CAN logs' "
            "frames: a cut log cannot be told",
            file=sys.stderr,
        )
    ran = doc.get("calibration")
    used = None if arm.active is None else arm.calibration_ref()
    if isinstance(ran, dict) and (used is None or ran.get("sha256") != used.sha256):
        print(  # once the report is written: an error would be the only line
            f"hrm report: note: the run used calibration version {_version(ran.get('version'))}, "
            "the angles are mapped with "
            + ("the description's values" if used is None else f"version {used.version}"),
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps(summary, indent=1))
        return 0
    print(f"run {summary['run']}: {summary['cycles']} cycles, {summary['duration_s']:.2f} s")
    for key, label, unit in (
        ("max_angle_error_deg", "largest joint-angle error", "deg"),
        ("max_tip_error_mm", "largest tip error", "mm"),
        ("max_sync_lateness_ms", "largest SYNC lateness", "ms"),
    ):
        v = summary[key]
        print(f"{label}: {'-' if v is None else f'{v:.3f}'} {unit}")
    for f in summary["figures"]:
        print(f"figure: {f}")
    return 0
