"""Arguments several commands share."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_robot_argument(parser: argparse.ArgumentParser) -> None:
    """``--robot FILE``: the robot description replacing the one shipped with hrm."""
    parser.add_argument(
        "--robot",
        type=Path,
        default=None,
        metavar="FILE",
        help="robot description TOML (default: the one shipped with hrm)",
    )
