"""The operator console: ``hrm COMMAND ...``.

Each command is one small module in this package exposing ``HELP`` (one line),
``register(parser)`` (adds its arguments) and ``run(args) -> int``.  Commands are
discovered, so adding a module adds a command.  Every :class:`HrmError` becomes a
one-line message on stderr and exit status 2: no traceback, no partial output.

:func:`main` is the process entry of ``hrm`` (host and ``hrm sim`` alike): it runs the
command under :func:`drivers.realtime.process_settings` (GIL switch interval 0.2 ms),
the one place the process's interpreter settings change.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence
from typing import NoReturn

from drivers.realtime import process_settings
from hrm_ctrl.errors import HrmError

EXIT_ERROR = 2


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are a single line."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message}\n")


def _commands() -> list[str]:
    pkg = importlib.import_module("hrm_ctrl.cli")
    return sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog="hrm", description="Rope-driven hyper-redundant manipulator console"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    sub.required = True
    for name in _commands():
        mod = importlib.import_module(f"hrm_ctrl.cli.{name}")
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.register(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with process_settings():
            return int(args._run(args) or 0)
    except HrmError as exc:
        print(f"hrm {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"hrm {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
