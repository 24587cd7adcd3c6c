"""Running console commands: the interactive shell (prompt_toolkit), scripts line by
line, and the context both work on (:func:`build_context`, :func:`finish_context`).

Interactive (stdin a terminal): a ``PromptSession`` with the history in
``$HOME/.local/state/hrm/console_history``, completion of command names and of each
command's arguments (joint numbers, axes, motor ids, plan files), Ctrl-C clearing the
line at the prompt and stopping every axis while the arm moves, Ctrl-D or ``quit``
ending.  An error is one line; the shell goes on.

Scripts (stdin not a terminal, or a file given): one command per line, ``#`` comments,
blank lines skipped; the first error ends the script with ``FILE:LINE: command: ...``
(exit status 2).  A script that is a regular file (named, or stdin redirected from one)
is read and checked whole before its first command runs: a later line that is not UTF-8
text, too long or badly quoted, or a line past the last allowed, is refused with nothing
run.  A named ``SCRIPT`` that is not a regular file (a FIFO would block the console
until a writer came, a device may never end) is refused without opening it.  The end
of the input is ``quit``.  Whichever way the console ends, every drive is disabled and
the session finished and closed (run record written), and the simulated box (``--sim``)
stopped.
"""

from __future__ import annotations

import argparse
import io
import os
import re
import stat
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, TextIO

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import (
    COMMANDS,
    MAX_LINE_CHARS,
    ConsoleError,
    load_commands,
    run_words,
    split_line,
)
from hrm_ctrl.errors import HrmError, interrupting_signal

HISTORY_FILE = Path(".local", "state", "hrm", "console_history")  # under $HOME
MAX_SCRIPT_LINES = 100_000  # a script longer than this is refused at that line


def script_path(text: str) -> Path:
    """The ``SCRIPT`` argument: a path that is there but is not a regular file is refused
    (one line, ``argparse.ArgumentTypeError``) without opening it, by ``os.stat``: a FIFO
    would block the opening until some writer came, a device may never end.  A missing
    or unreadable file is left to the opening (its own one line)."""
    path = Path(text)
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return path
    if not stat.S_ISREG(mode):
        kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))
        kind = next((k for test, k in kinds if test(mode)), "a device")
        raise argparse.ArgumentTypeError(f"{text}: not a regular file ({kind})")
    return path


def _out(text: str) -> None:
    print(text, flush=True)


def _err(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def build_context(args: argparse.Namespace, prog: str) -> ConsoleContext:
    """Load the bus configuration, the robot and its active calibration, start the
    simulated box with ``--sim``; nothing is sent to a drive (that is ``connect``).  Bad
    input raises :class:`~hrm_ctrl.errors.HrmError` (one line) before anything starts."""
    from hrm_ctrl.cli._common import (
        Output,
        arm_from_args,
        calibrations_input,
        config_input,
        load_box,
        refuse_overwriting_inputs,
        robot_input,
        shipped_inputs,
    )
    from hrm_ctrl.cli._options import sim_physics
    from hrm_ctrl.model import load_robot
    from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm, start_simulated_box

    refuse_overwriting_inputs(
        [Output("--log-dir", args.log_dir, folder=True)],
        [
            robot_input(args.robot),
            config_input(args.config),
            calibrations_input(args),  # the logs into the store: only the store writes there
            *shipped_inputs(eds=True),
        ],
    )
    physics = sim_physics(args.physics, args.sim)  # a bad one refused before anything
    config = load_box(args)  # --config with the --bus overrides
    arm = arm_from_args(args, load_robot(args.robot), prog=prog, simulated=args.sim)
    config.check_motors(arm.actuation.motor_ids)
    load_commands()
    arm.say_note()
    sim = None
    if args.sim:  # the simulated arm: the description's (links too), not the calibration's
        box = SimulatedBox(simulated_arm(arm, physics=physics), args.wire)
        running = start_simulated_box(config, box, prog)
        config, sim = running.config, running.sim
    ctx = ConsoleContext(
        config=config,
        description=arm.description,
        model=arm.robot,
        actuation=arm.actuation,
        out=_out,
        err=_err,
        calibration=arm.calibration_ref(),
        active=arm.active,
        allow_uncalibrated=bool(args.uncalibrated or args.sim),
        sim=sim,
        simulated=bool(args.sim),
        runs_dir=Path(args.log_dir),
        log_suffix=f".{args.log_format}",
        take_over=bool(args.take_over),
        prog=prog,
    )
    ctx.extra["args"] = args  # the command line (calibrate show: the store, the robot)
    return ctx


def finish_context(ctx: ConsoleContext, cause: BaseException | None = None) -> None:
    """Disable every drive, finish and close the session, stop the simulated box;
    whatever fails, the rest is still done (the first error is raised at the end).  When
    a signal ends the console (``cause``), every axis is quick-stopped first
    (:func:`stop_on_signal`); a second signal waits for all of it."""
    from drivers.interrupts import deferred_interrupts
    from hrm_ctrl.cli._console.commands_session import close_session

    with deferred_interrupts():
        try:
            if cause is not None:
                stop_on_signal(ctx, cause)
            close_session(ctx)
        finally:
            if ctx.sim is not None:
                ctx.sim.stop()
                ctx.sim = None


def stop_on_signal(ctx: ConsoleContext, exc: BaseException) -> None:
    """A signal (or Ctrl-C in a script) ends the console: with drives enabled and
    holding, every axis is quick-stopped with the signal as its cause before the finish
    (a stream's own interrupt handling has already stopped it)."""
    from drivers.safety.causes import StopKind
    from drivers.safety.supervisor import Mode

    name = interrupting_signal(exc)
    session = ctx.session
    if name is not None and session is not None and session.supervisor.mode is Mode.ARMED:
        session.request_stop(StopKind.SIGNAL, f"{name}: stop requested (console)")


# ---------------------------------------------------------------------------- scripts
# A byte that is not UTF-8, as a stream decoding with ``surrogateescape`` shows it.
_UNDECODABLE = re.compile("[\udc80-\udcff]")


def bounded_lines(stream: TextIO) -> Iterator[str]:
    """The lines of ``stream``, each read with a bound (a longer line is refused by
    :func:`split_line`: the rest of it is not read into memory)."""
    while True:
        line = stream.readline(MAX_LINE_CHARS + 2)  # with its end of line, "\r\n" too
        if not line:
            return
        yield line


def script_lines(stream: TextIO, where: str) -> Iterator[str]:
    """The lines of a script, each read with a bound, each checked to be UTF-8 text: a
    byte that is not raises :class:`ConsoleError` ``WHERE:LINE: not UTF-8 text (...)``
    at its line (strict decoding would fail a whole read-ahead chunk: before earlier
    lines ran, or with no line named; stdin's own decoding lets such bytes through)."""
    try:  # undecodable bytes as lone surrogates, found line by line below
        stream.reconfigure(encoding="utf-8", errors="surrogateescape")  # type: ignore[attr-defined]
    except (AttributeError, OSError, ValueError):  # not a TextIOWrapper, or already read from
        pass
    for lineno, line in enumerate(bounded_lines(stream), start=1):
        bad = _UNDECODABLE.search(line)
        if bad is not None:
            byte = ord(bad.group()) - 0xDC00
            raise ConsoleError(
                f"{where}:{lineno}: not UTF-8 text (byte 0x{byte:02x} at column {bad.start() + 1})"
            )
        yield line


def _is_regular_file(stream: TextIO) -> bool:
    try:
        return stat.S_ISREG(os.fstat(stream.fileno()).st_mode)
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        return False


def checked_script(lines: Iterable[str], where: str) -> list[str]:
    """Every line of a script read and checked before the first runs (UTF-8 text, at most
    :data:`MAX_SCRIPT_LINES` lines of at most ``MAX_LINE_CHARS`` characters, quotes
    closed): the first bad one raises :class:`ConsoleError` ``WHERE:LINE: ...`` with
    nothing run.  Bounded: the lines are read as :func:`run_script` reads them."""
    checked: list[str] = []
    for lineno, line in enumerate(lines, start=1):
        if lineno > MAX_SCRIPT_LINES:
            raise ConsoleError(f"{where}:{lineno}: more than {MAX_SCRIPT_LINES} lines")
        try:
            split_line(line)
        except ConsoleError as exc:
            raise ConsoleError(f"{where}:{lineno}: {exc}") from None
        checked.append(line)
    return checked


def script_of(stream: TextIO, where: str) -> Iterable[str]:
    """The lines :func:`run_console` runs: a regular file's all read and checked first
    (:func:`checked_script`: nothing runs when a later line is bad), a pipe's or a
    terminal's as they come (a program may write them as it reads the console's output)."""
    lines = script_lines(stream, where)
    return checked_script(lines, where) if _is_regular_file(stream) else lines


def script_name(stream: TextIO) -> str:
    """The name of the file a script comes from: stdin redirected from a file shows as
    that file's path (``procedure.txt``), else ``stdin``."""
    name = getattr(stream, "name", None)
    if isinstance(name, str) and not name.startswith("<"):
        return name
    try:
        target = os.readlink(f"/proc/self/fd/{stream.fileno()}")
    except (OSError, ValueError, AttributeError):
        return "stdin"
    if target.startswith("/") and os.path.isfile(target):
        try:
            rel = os.path.relpath(target)
        except ValueError:
            return target
        return rel if not rel.startswith("..") else target
    return "stdin"


def run_script(ctx: ConsoleContext, lines: Iterable[str], where: str) -> None:
    """Run ``lines`` one command each; the first error raises :class:`ConsoleError`
    ``WHERE:LINE: command: ...``.  Each command is echoed (``> line``) before it runs."""
    for lineno, line in enumerate(lines, start=1):
        if lineno > MAX_SCRIPT_LINES:
            raise ConsoleError(f"{where}:{lineno}: more than {MAX_SCRIPT_LINES} lines")
        try:
            words = split_line(line)
            if not words:
                continue
            ctx.out(f"> {' '.join(words)}")
            run_words(ctx, words)
        except HrmError as exc:
            raise ConsoleError(f"{where}:{lineno}: {exc}") from None
        except KeyboardInterrupt as exc:
            from drivers.interrupts import deferred_interrupts

            with deferred_interrupts():
                stop_on_signal(ctx, exc)
            raise ConsoleError(f"{where}:{lineno}: interrupted (Ctrl-C)") from None
        if ctx.quit_requested:
            return


# ---------------------------------------------------------------------------- interactive
def history_path() -> Path:
    """``$HOME/.local/state/hrm/console_history``."""
    return Path.home() / HISTORY_FILE


def _completer(ctx: ConsoleContext) -> Any:
    from prompt_toolkit.completion import Completer, Completion

    class ConsoleCompleter(Completer):
        """Command names, then each command's own completer."""

        def get_completions(self, document: Any, complete_event: Any) -> Iterator[Any]:
            text = document.text_before_cursor
            words = text.split()
            if not words or text[-1:].isspace():
                words.append("")
            current = words[-1]
            if len(words) == 1:
                candidates = sorted(COMMANDS)
            else:
                cmd = COMMANDS.get(words[0])
                if cmd is None or cmd.complete is None:
                    return
                try:
                    candidates = cmd.complete(ctx, words)
                except (HrmError, OSError):
                    return
            for c in candidates:
                if c.startswith(current):
                    yield Completion(c, start_position=-len(current))

    return ConsoleCompleter()


def prompt_text(ctx: ConsoleContext) -> str:
    """``hrm> `` before ``connect``, then ``hrm:STATE> `` (``hrm:enabled> ``)."""
    if ctx.session is None:
        return "hrm> "
    return f"hrm:{ctx.session.state.value}> "


def run_interactive(ctx: ConsoleContext) -> None:
    """The shell at a terminal, until ``quit`` or Ctrl-D."""
    from prompt_toolkit import PromptSession
    from prompt_toolkit.history import FileHistory, InMemoryHistory

    ctx.interactive = True
    path = history_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        history: Any = FileHistory(str(path))
    except OSError as exc:
        ctx.err(f"{ctx.prog}: history not kept ({path}: {exc.strerror or exc})")
        history = InMemoryHistory()
    session: Any = PromptSession(history=history, completer=_completer(ctx))
    ctx.out(f"{ctx.prog}: 'help' lists the commands; connect, then enable, before any move")
    while not ctx.quit_requested:
        try:
            line = session.prompt(prompt_text(ctx))
        except KeyboardInterrupt:
            continue  # Ctrl-C at the prompt: the line is cleared
        except EOFError:
            return
        try:
            run_words(ctx, split_line(line))
        except HrmError as exc:
            ctx.err(f"error: {exc}")
        except KeyboardInterrupt:
            ctx.err("interrupted")


def run_console(ctx: ConsoleContext, script: TextIO | None) -> None:
    """The interactive shell (``script`` None) or a script; always finishes the context
    (a failing finish after an error is said on stderr, the first error is raised)."""
    try:
        if script is None:
            run_interactive(ctx)
        else:
            where = script_name(script)
            run_script(ctx, script_of(script, where), where)
    except BaseException as exc:
        try:
            finish_context(ctx, exc)
        except HrmError as exc:
            ctx.err(f"{ctx.prog}: while finishing: {exc}")
        raise
    finish_context(ctx)
