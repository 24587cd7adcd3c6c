"""``hrm urdf``: write the arm as URDF (stdout, or a file with ``--out``).

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm urdf")
>>> register(p)
>>> p.parse_args(["--out", "arm.urdf"]).out
PosixPath('arm.urdf')
"""

from __future__ import annotations

import argparse
import sys

from hrm_ctrl.cli._common import Output, refuse_overwriting_inputs, robot_input
from hrm_ctrl.cli._options import add_out, add_robot

HELP = "write the arm as URDF (each universal joint as two revolute joints)"


def register(parser: argparse.ArgumentParser) -> None:
    add_robot(parser)
    add_out(parser, metavar="FILE", what="write the URDF to FILE (atomically) instead of stdout")


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.formats.urdf import robot_urdf, write_robot_urdf
    from hrm_ctrl.model import load_robot

    refuse_overwriting_inputs([Output("--out", args.out)], [robot_input(args.robot)])
    model = load_robot(args.robot)
    if args.out is None:
        sys.stdout.write(robot_urdf(model))
        return 0
    path = write_robot_urdf(model, args.out)
    print(f"wrote {path}", file=sys.stderr)
    return 0
