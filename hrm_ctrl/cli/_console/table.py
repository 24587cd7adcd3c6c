"""The console's command table: every console command, registered once, serving the
interactive shell, scripts and one-shot use (``hrm status``).

A command is a function ``handler(ctx, args)`` taking the :class:`~.context.ConsoleContext`
and the words after the command name; it prints through ``ctx.out`` / ``ctx.err`` and
raises :class:`ConsoleError` (or any :class:`~hrm_ctrl.errors.HrmError`) for a one-line
user error.  ``needs`` says what the session must be before the handler runs
(:class:`Need`): the table refuses the command with one line otherwise.  ``complete``
(optional) proposes the word being typed: it gets every word of the line so far, the
command's name first and the (possibly empty) word being typed last (``["jog", ""]`` for
the first argument), and returns candidates; the shell keeps those that start with the
word typed.  :func:`complete_paths` proposes files (plan files: ``*.json``).

>>> @command("echo-doc", "print the words", "echo-doc WORD...")
... def _echo(ctx, args):
...     ctx.out(" ".join(args))
>>> COMMANDS["echo-doc"].usage
'echo-doc WORD...'
>>> COMMANDS["echo-doc"].needs is Need.NONE
True
>>> split_line("jog 5 theta +2  # a comment")
['jog', '5', 'theta', '+2']
>>> del COMMANDS["echo-doc"]
"""

from __future__ import annotations

import contextlib
import math
import re
import shlex
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

from hrm_ctrl.errors import HrmError

if TYPE_CHECKING:
    from hrm_ctrl.cli._console.context import ConsoleContext

MAX_LINE_CHARS = 4096  # a console line longer than this is refused (bounded parsing)

# The numbers a console argument may be: plain ASCII decimal, an optional sign (no ``_``
# separators, no other scripts' digits, no ``inf``/``nan``, no spaces; Python's int() and
# float() take all of those).
_INT_RE = re.compile(r"[+-]?[0-9]+")
_FLOAT_RE = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


class ConsoleError(HrmError):
    """A console command refused: bad arguments, wrong session state (one line)."""


class Need(Enum):
    """What a command needs before it runs."""

    NONE = "none"  # nothing: help, quit, sim, connect
    CONNECTED = "connected"  # a live drive session (``connect`` done)
    ENABLED = "enabled"  # a session whose drives are enabled (``enable`` done)


Handler = Callable[["ConsoleContext", list[str]], None]
Completer = Callable[["ConsoleContext", list[str]], list[str]]


@dataclass(frozen=True)
class Command:
    """One console command: its name, a one-line summary, its usage line, the handler,
    an optional completer of its arguments and what it needs (:class:`Need`)."""

    name: str
    summary: str
    usage: str
    handler: Handler
    complete: Completer | None = None
    needs: Need = Need.NONE


COMMANDS: dict[str, Command] = {}


def command(
    name: str,
    summary: str,
    usage: str,
    needs: Need = Need.NONE,
    complete: Completer | None = None,
) -> Callable[[Handler], Handler]:
    """Decorator registering ``handler`` as the console command ``name`` (a second
    registration of the same name is a programming error: ValueError)."""

    def register(handler: Handler) -> Handler:
        if name in COMMANDS:
            raise ValueError(f"console command {name!r} registered twice")
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"console command name {name!r}: one word")
        COMMANDS[name] = Command(name, summary, usage, handler, complete, needs)
        return handler

    return register


def split_line(line: str) -> list[str]:
    """The words of one console line (shell quoting; ``#`` starts a comment); a line
    too long (its end of line not counted) or with an open quote is refused
    (:class:`ConsoleError`)."""
    if len(line.rstrip("\r\n")) > MAX_LINE_CHARS:
        raise ConsoleError(f"line longer than {MAX_LINE_CHARS} characters")
    try:
        return shlex.split(line, comments=True)
    except ValueError as exc:
        raise ConsoleError(f"cannot read the line: {exc}") from None


def _shown(text: str) -> str:
    return repr(text if len(text) <= 40 else text[:40] + "...")


def _usage(usage: str) -> str:
    return f"; usage: {usage}" if usage else ""


def parse_int(text: str, name: str, usage: str = "") -> int:
    """The console argument ``name`` as a whole number: ASCII decimal digits with an
    optional sign, nothing else (:class:`ConsoleError` naming ``name``, and ``usage``
    when given, otherwise).

    >>> parse_int("-800", "COUNTS"), parse_int("+5", "JOINT")
    (-800, 5)
    >>> parse_int("1_000", "COUNTS")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    hrm_ctrl...ConsoleError: COUNTS: '1_000' is not a whole number (ASCII decimal digits)
    """
    if _INT_RE.fullmatch(text) is None:
        raise ConsoleError(
            f"{name}: {_shown(text)} is not a whole number (ASCII decimal digits){_usage(usage)}"
        )
    return int(text)  # at most MAX_LINE_CHARS digits: within int()'s 4300


def parse_float(text: str, name: str, usage: str = "") -> float:
    """The console argument ``name`` as a finite number: ASCII decimal (``+2``, ``-1.5``,
    ``.5``, ``1e-3``), nothing else (:class:`ConsoleError` naming ``name``, and ``usage``
    when given, otherwise).

    >>> parse_float("+2", "DEG"), parse_float("-.5", "DEG"), parse_float("1e1", "DEG")
    (2.0, -0.5, 10.0)
    >>> parse_float("nan", "DEG")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    hrm_ctrl...ConsoleError: DEG: 'nan' is not a number (ASCII decimal, e.g. -1.5)
    """
    if _FLOAT_RE.fullmatch(text) is None:
        raise ConsoleError(
            f"{name}: {_shown(text)} is not a number (ASCII decimal, e.g. -1.5){_usage(usage)}"
        )
    value = float(text)
    if not math.isfinite(value):
        raise ConsoleError(f"{name}: {_shown(text)} is too large{_usage(usage)}")
    return value


def find(name: str) -> Command:
    """The command ``name`` (an unambiguous prefix too), or :class:`ConsoleError`."""
    if name in COMMANDS:
        return COMMANDS[name]
    matches = sorted(n for n in COMMANDS if n.startswith(name))
    if len(matches) == 1:
        return COMMANDS[matches[0]]
    if matches:
        raise ConsoleError(f"{name}: ambiguous command ({', '.join(matches)})")
    raise ConsoleError(f"{name}: unknown command (try 'help')")


def load_commands() -> dict[str, Command]:
    """Import every ``commands_*`` module of the console package (each registers its
    commands on import) and return the table."""
    import importlib
    import pkgutil

    import hrm_ctrl.cli._console as pkg

    for mod in sorted(m.name for m in pkgutil.iter_modules(pkg.__path__)):
        if mod.startswith("commands_"):
            importlib.import_module(f"hrm_ctrl.cli._console.{mod}")
    return COMMANDS


def check_needs(ctx: ConsoleContext, cmd: Command) -> None:
    """Refuse (:class:`ConsoleError`, one line) a command whose :class:`Need` the session
    does not meet; nothing is sent."""
    if cmd.needs is Need.NONE:
        return
    if ctx.session is None:
        raise ConsoleError("not connected (connect first)")
    if cmd.needs is Need.ENABLED and not ctx.enabled:
        session = ctx.session
        state = session.state.name
        if state in ("STOPPED", "FAULT"):
            causes = session.idle_causes or (session.results[-1].causes if session.results else [])
            why = f": {causes[0].text}" if causes else ""
            raise ConsoleError(
                f"session {state} after a stop{why} (reset-fault or disable, then enable)"
            )
        raise ConsoleError(f"the drives are not enabled (session {state}; enable first)")


def command_scheduling(ctx: ConsoleContext) -> contextlib.AbstractContextManager[object]:
    """The scheduling a command runs at: with a session open,
    :func:`hrm_ctrl.runtime.box.caller_scheduling` (one below the session's threads when
    they run under ``SCHED_FIFO``), else the console's own."""
    from hrm_ctrl.runtime.box import caller_scheduling

    if ctx.session is None:
        return contextlib.nullcontext()
    return caller_scheduling(ctx.session)


def run_words(ctx: ConsoleContext, words: list[str]) -> None:
    """Run one command line already split into words (empty: nothing).  Errors propagate
    as :class:`~hrm_ctrl.errors.HrmError` with the command's name in front."""
    if not words:
        return
    cmd = find(words[0])
    try:
        check_needs(ctx, cmd)
        with command_scheduling(ctx):
            cmd.handler(ctx, words[1:])
    except ConsoleError as exc:
        raise ConsoleError(f"{cmd.name}: {exc}") from None
    except HrmError as exc:
        raise ConsoleError(f"{cmd.name}: {exc}") from None


def complete_paths(prefix: str, suffix: str = ".json", limit: int = 200) -> list[str]:
    """File names starting with ``prefix`` that end with ``suffix`` (and folders, with a
    trailing ``/``), for a command's completer (e.g. plan files); at most ``limit``.

    >>> import tempfile, pathlib, os
    >>> d = pathlib.Path(tempfile.mkdtemp()); _ = (d / "a.json").write_text("{}")
    >>> _ = (d / "b.txt").write_text(""); (d / "sub").mkdir()
    >>> sorted(os.path.basename(p.rstrip("/")) for p in complete_paths(str(d) + "/"))
    ['a.json', 'sub']
    """
    import glob
    import os

    found: list[str] = []
    for path in sorted(glob.glob(glob.escape(os.path.expanduser(prefix)) + "*")):
        if os.path.isdir(path):
            found.append(path + "/")
        elif path.endswith(suffix):
            found.append(path)
        if len(found) >= limit:
            break
    return found
