"""``hrm box check``: every drive's device file against what hrm needs, before any bus opens;
``hrm box export --lely DIR``: the box as Lely ``dcfgen`` configurations
(:mod:`drivers.lely_export`); ``hrm box check --lely-bus BUS.yml``: such a configuration
read back (:mod:`drivers.lely_bus`).

One line per drive: ``MOTOR: FILE: ok: ...`` with the PDO layout hrm will use, or one
line per refusal naming the object (``j03r1: 605.3150.68-B-EK-2-60.eds: no cyclic
synchronous position mode (0x6502 = 0x25: PP, PV, HM)``); exit status 2 when any drive is
refused.  The check itself is :mod:`drivers.device_check`; ``hrm run`` and every command
that opens a box run it first (:func:`hrm_ctrl.runtime.box.open_box`).

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm box")
>>> register(p)
>>> args = p.parse_args(["check", "--json"])
>>> args.action, args.json, args.config, args.lely_bus
('check', True, None, [])
>>> p.parse_args(["export", "--lely", "out"]).lely
PosixPath('out')
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hrm_ctrl.cli._common import load_box
from hrm_ctrl.cli._options import add_bus, add_json

HELP = (
    "check every drive's device file (EDS/DCF) against what hrm needs, offline; export the "
    "box for Lely's dcfgen"
)

EXIT_REFUSED = 2


def register(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = actions.add_parser(
        "check",
        help="what each drive's device file allows against what hrm needs, and the PDO "
        "layout hrm will use (exit 2 when a drive is refused)",
    )
    add_bus(check, overrides=False)  # --config
    check.add_argument(
        "--lely-bus", action="append", type=Path, default=[], metavar="BUS.yml",
        help="check a Lely dcfgen bus.yml (one bus; repeatable) instead of --config: its "
        "nodes, device files (dcf), node ids, heartbeats, SDO writes and sync_period",
    )  # fmt: skip
    add_json(check, "every drive's verdict")
    export = actions.add_parser(
        "export",
        help="write the box as Lely dcfgen configurations: DIR/BUS/bus.yml and the device "
        "files they name (a box hrm box check refuses is not exported)",
    )
    add_bus(export, overrides=False)  # --config
    export.add_argument(
        "--lely", type=Path, required=True, metavar="DIR", help="the folder to write into"
    )


def run(args: argparse.Namespace) -> int:
    """Exit 0 when every drive's device file offers what hrm needs, 2 otherwise."""
    from drivers.config import BusConfigError
    from drivers.device_check import check_box

    if args.action == "export":
        from drivers.lely_export import export_lely

        for path in export_lely(load_box(args), args.lely):
            print(path)
        return 0

    if args.lely_bus:
        if args.config is not None:
            raise BusConfigError("give --config or --lely-bus, not both")
        from drivers.lely_bus import load_lely_buses

        config = load_lely_buses(args.lely_bus)
    else:
        config = load_box(args)
    report = check_box(config)
    if args.json:
        print(json.dumps(report.to_dict(), indent=1))
    else:
        for line in report.lines():
            print(line)
    return EXIT_REFUSED if report.refused else 0
