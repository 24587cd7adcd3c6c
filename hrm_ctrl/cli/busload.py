"""``hrm busload``: each bus's worst-case load at the control rate, and the rate that fits.

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm busload")
>>> register(p)
>>> p.parse_args(["--rate", "200"]).rate
200.0
"""

from __future__ import annotations

import argparse
import json

from hrm_ctrl.cli._common import load_box
from hrm_ctrl.cli._options import add_bus, add_json
from hrm_ctrl.errors import DriverError

HELP = "print every CAN bus's worst-case load (bit stuffing included) and the highest rate"


def register(parser: argparse.ArgumentParser) -> None:
    add_bus(parser)  # --config, --bus
    parser.add_argument(
        "--rate", type=float, default=None, metavar="HZ",
        help="control rate to check (default: the configuration's)",
    )  # fmt: skip
    add_json(parser, "every bus's load")


def run(args: argparse.Namespace) -> int:
    """Exit 0 when every bus fits its load limit, 1 otherwise."""
    from drivers.busload import bus_loads
    from drivers.config import rate_problem

    if args.rate is not None and (problem := rate_problem(args.rate)) is not None:
        raise DriverError(f"--rate {args.rate:g}: {problem}")
    cfg = load_box(args)  # --config with the --bus overrides
    if args.rate is not None:
        cfg = cfg.with_control(rate_hz=args.rate)
    loads = bus_loads(cfg)
    if args.json:
        print(json.dumps([bl.to_dict() for bl in loads], indent=1))
    else:
        for bl in loads:
            verdict = "ok" if bl.fits else "OVER LIMIT"
            print(
                f"{bl.bus}: {bl.n_nodes} nodes at {bl.bitrate} bit/s, {bl.rate_hz:g} Hz: "
                f"worst-case load {100 * bl.load:.1f}% (limit {100 * bl.limit:g}%) {verdict}; "
                f"highest rate that fits {bl.max_rate_hz:g} Hz"
            )
    return 0 if all(bl.fits for bl in loads) else 1
