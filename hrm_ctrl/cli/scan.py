"""``hrm scan``: a pipe's centre line and inner diameter from a scan of its inner wall."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

from hrm_ctrl.cli._common import Input, Output, refuse_overwriting_inputs, robot_input
from hrm_ctrl.cli._options import add_json, add_out, add_robot
from hrm_ctrl.errors import PathFileError
from hrm_ctrl.files import write_atomic

if TYPE_CHECKING:
    from hrm_ctrl.planning.scan import ScanFit

HELP = (
    "fit a pipe's centre line and inner diameter to a scan of its inner wall "
    "(PLY, CSV x,y,z or NPY; mm) and write the centre line as a path file"
)


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, metavar="FILE", help="point cloud: .ply, .csv or .npy (mm)")
    add_out(
        p, metavar="PATH.csv",
        what="write the centre line as a path file (x,y,z) for hrm plan --path",
    )  # fmt: skip
    add_robot(p)  # the path starts at the end nearest the robot's base
    add_json(p, "the fit")


def format_fit(fit: ScanFit, name: str) -> str:
    """The fit as lines a person reads."""
    rows = [
        (
            "inner diameter",
            f"{fit.inner_diameter:.2f} mm (slices spread {fit.diameter_spread:.2f} mm)",
        ),
        ("centre line", f"{fit.axis_length:.1f} mm, {len(fit.axis)} points, {fit.n_slices} slices"),
        (
            "inliers",
            f"{fit.inlier_fraction * 100:.1f} % of {fit.n_points} points within "
            f"{fit.inlier_band:.2f} mm of the wall ({fit.n_outliers} outliers rejected)",
        ),
        ("wall residual", f"rms {fit.rms:.3f} mm, p95 {fit.p95:.3f} mm (inliers)"),
        ("fit time", f"{fit.timings_s.get('total', math.nan) * 1e3:.0f} ms"),
    ]
    return "\n".join([f"scan: {name}", *(f"  {k:<16}  {v}" for k, v in rows)])


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.planning.known_path import path_csv
    from hrm_ctrl.planning.scan import read_scan

    refuse_overwriting_inputs(
        [Output("--out", args.out)],
        [Input("point cloud", args.file), robot_input(args.robot)],
    )
    robot = load_robot(args.robot)
    fit = read_scan(args.file)
    path = fit.path(robot.base_position, source=f"scan {args.file}")
    if args.out is not None:
        try:
            write_atomic(args.out, path_csv(path))
        except OSError as exc:
            raise PathFileError(f"{args.out}: cannot write path file ({exc})") from None
    if args.json:
        doc = {"file": str(args.file), **fit.to_dict()}
        doc["start_mm"] = path.points[0].tolist()
        doc["end_mm"] = path.points[-1].tolist()
        doc["out"] = None if args.out is None else str(args.out)
        print(json.dumps(doc, indent=2))
    else:
        print(format_fit(fit, str(args.file)))
        if args.out is not None:
            print(f"centre line written to {args.out}")
    return 0
