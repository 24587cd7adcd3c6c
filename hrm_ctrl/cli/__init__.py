"""The operator console: ``hrm COMMAND ...``.

Each command is one small module in this package exposing ``HELP`` (one line),
``register(parser)`` (adds its arguments, from the shared ones of
:mod:`hrm_ctrl.cli._options` and its own) and ``run(args) -> int``.  Commands are
discovered, so adding a module adds a command.  A command module imports at its top only
what ``HELP`` and ``register`` need, nothing heavy (numpy, scipy, python-can, ...): those
are imported where used.  ``hrm`` registers a command's arguments only when that command
is parsed, so ``hrm --version`` and ``hrm --help`` import no command's libraries
(``benchmarks/bench_startup.py``).  Every :class:`HrmError` becomes a
one-line message on stderr and exit status 2: no traceback, no partial output.  A
closed stdout (``hrm plan ... | head -1``) ends the command quietly with status 141
(128 + SIGPIPE, as a shell reports for other tools a closed pipe ends).

:func:`main` is the process entry of ``hrm`` (host and ``hrm sim`` alike): it runs the
command under :func:`drivers.realtime.process_settings` (GIL switch interval 0.2 ms;
1 ms for a command that runs the simulated box in this interpreter, ``hrm demo`` and
``--sim``: :data:`hrm_ctrl.cli._simwire.SIM_SWITCH_INTERVAL_S`), the one place the
process's interpreter settings change.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import pkgutil
import select
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from hrm_ctrl.errors import HrmError, SignalInterrupt

EXIT_ERROR = 2
EXIT_CLOSED_PIPE = 141  # 128 + SIGPIPE: the status a shell reports for a tool a closed pipe ended


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are a single line."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message}\n")


def _version() -> str:
    """The installed package's version (``importlib.metadata``; ``unknown`` when hrm runs
    from a tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hrm")
    except PackageNotFoundError:
        return "unknown (not installed)"


class _VersionAction(argparse._VersionAction):
    """``--version``: the version is looked up when asked for (``importlib.metadata`` is
    not imported to build the parser)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        self.version = f"hrm {_version()}"
        super().__call__(parser, namespace, values, option_string)


def _commands() -> list[str]:
    pkg = importlib.import_module("hrm_ctrl.cli")
    return sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))


class _Commands(argparse._SubParsersAction):  # type: ignore[type-arg]
    """``hrm``'s sub-commands: a command's arguments are registered (its ``register()``
    called) when the command is parsed, not before, so that ``hrm --help`` and ``hrm
    --version`` import nothing a command's options need (its choices and defaults)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._unregistered: dict[str, Callable[[argparse.ArgumentParser], None]] = {}

    def add_command(
        self, name: str, help: str, register: Callable[[argparse.ArgumentParser], None]
    ) -> argparse.ArgumentParser:
        """Add the command ``name``; ``register`` adds its arguments when it is parsed."""
        p = self.add_parser(name, help=help, description=help)
        self._unregistered[name] = register
        return p

    def register(self, name: str) -> None:
        """Add the arguments of command ``name`` now (once)."""
        register = self._unregistered.pop(name, None)
        if register is not None:
            register(self._name_parser_map[name])

    def register_all(self) -> None:
        """Add the arguments of every command not registered yet."""
        for name in list(self._unregistered):
            self.register(name)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        self.register(values[0])
        super().__call__(parser, namespace, values, option_string)


def build_parser(*, every_command: bool = False) -> OneLineParser:
    """``hrm``'s parser.  A command's arguments are added when the command is parsed;
    with ``every_command``, every command's are added at once (a parser to walk)."""
    parser = OneLineParser(
        prog="hrm", description="Rope-driven hyper-redundant manipulator console"
    )
    parser.add_argument(
        "--version", action=_VersionAction,
        help="print hrm's version (the installed package's) and exit",
    )  # fmt: skip
    sub = parser.add_subparsers(
        dest="command", metavar="COMMAND", parser_class=OneLineParser, action=_Commands
    )
    sub.required = True
    for name in _commands():
        mod = importlib.import_module(f"hrm_ctrl.cli.{name}")
        p = sub.add_command(name, mod.HELP, mod.register)
        p.set_defaults(_run=mod.run)
    if every_command:
        sub.register_all()
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; return its exit status.  A closed stdout (``hrm ... | head``) ends
    the command quietly with :data:`EXIT_CLOSED_PIPE`, as a closed pipe ends other tools:
    no traceback, nothing more written (what the command had not done yet stays undone)."""
    try:
        try:
            return _main(argv)
        finally:
            if sys.stdout is not None:
                sys.stdout.flush()  # a closed pipe shows here, not at interpreter exit
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        _stdout_to_devnull()
        return EXIT_CLOSED_PIPE


def _stdout_closed() -> bool:
    """Whether stdout is a pipe (or socket, terminal) whose reading end is gone."""
    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        events = poller.poll(0)
    except (AttributeError, OSError, ValueError):  # no real stdout (e.g. captured)
        return False
    return any(ev & (select.POLLERR | select.POLLHUP) for _fd, ev in events)


def _stdout_to_devnull() -> None:
    """Point stdout at /dev/null, so that nothing buffered fails again at exit."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)


def _switch_interval_s(args: argparse.Namespace) -> float:
    """The GIL switch interval of this command: the simulated box in this interpreter
    (``hrm demo`` or ``--sim`` with an in-process ``--wire``) gets the longer one of
    ``_simwire``."""
    if args.command == "demo" or getattr(args, "sim", False):  # else no simulator imported
        from hrm_ctrl.cli._simwire import PROCESS_WIRE, SIM_SWITCH_INTERVAL_S

        if getattr(args, "wire", PROCESS_WIRE) != PROCESS_WIRE:
            return SIM_SWITCH_INTERVAL_S
    from drivers.realtime import SWITCH_INTERVAL_S

    return SWITCH_INTERVAL_S


# Libraries whose own log records (canopen logs every aborted SDO transfer at ERROR) would
# reach stderr through logging's last-resort handler: hrm reports what failed in its one
# error line and in the run record, so theirs are not printed.
QUIET_LIBRARY_LOGGERS = ("canopen",)


def _quiet_library_logging() -> None:
    import logging

    for name in QUIET_LIBRARY_LOGGERS:
        logger = logging.getLogger(name)
        if not logger.handlers:
            logger.addHandler(logging.NullHandler())


def one_line(text: str) -> str:
    """An error message as one line: a line break or other control character in it (a
    path given with one, say) is shown escaped.

    >>> one_line("t\\nlinks_mm = 5.toml: truth file not found")
    't\\\\nlinks_mm = 5.toml: truth file not found'
    """
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _quiet_library_logging()
    from drivers.realtime import process_settings
    from hrm_ctrl.cli._signals import signals_as_interrupts

    try:
        with process_settings(_switch_interval_s(args)), signals_as_interrupts():
            return int(args._run(args) or 0)
    except HrmError as exc:
        print(f"hrm {args.command}: error: {one_line(str(exc))}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        if exc.errno != errno.ENAMETOOLONG:
            raise
        # a path argument too long for the file system, met where no check named it
        # first: still one line naming it (its start), not a traceback
        name = str(exc.filename) if exc.filename is not None else "a path"
        shown = name if len(name) <= 60 else f"{name[:60]}... ({len(name)} characters)"
        print(f"hrm {args.command}: error: {shown}: file name too long", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"hrm {args.command}: interrupted", file=sys.stderr)
        return 130
    except SignalInterrupt as exc:
        print(f"hrm {args.command}: stopped by {exc.signal_name}", file=sys.stderr)
        return 128 + exc.signal_number


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
