"""``hrm console``: the operator console over one live drive session (issue 11).

``hrm console [--sim | --config BOX.toml] [--robot FILE] [SCRIPT]``: at a terminal an
interactive shell (history, help, completion); with stdin not a terminal, or a
``SCRIPT`` file, the commands line by line, stopping at the first error (exit status 2,
``FILE:LINE: command: ...``).  The drives are brought up once (``connect``) and stay up
between commands; nothing moves before ``enable``; ``quit`` and the end of the input
disable every drive and finish the session.  The commands: ``docs/console.md``
(``help`` lists them).

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm console")
>>> register(p)
>>> a = p.parse_args(["--sim", "proc.txt"])
>>> a.sim, str(a.script)
(True, 'proc.txt')
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "interactive operator console over one live drive session (scripts on stdin too)"


def register(parser: argparse.ArgumentParser) -> None:
    from hrm_ctrl.cli._console.shell import script_path
    from hrm_ctrl.cli._options import add_console_box

    parser.add_argument(
        "script", nargs="?", type=script_path, default=None, metavar="SCRIPT",
        help="run the commands of this file (default: stdin when it is not a terminal)",
    )  # fmt: skip
    add_console_box(parser)


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.cli._console.shell import build_context, run_console
    from hrm_ctrl.cli._console.table import ConsoleError

    script = None
    if args.script is not None:
        try:
            script = open(args.script, encoding="utf-8", errors="strict")
        except OSError as exc:
            raise ConsoleError(f"{args.script}: cannot read ({exc.strerror or exc})") from None
    elif not sys.stdin.isatty():
        script = sys.stdin
    try:
        ctx = build_context(args, "hrm console")
        ctx.script_path = _script_file(script)
        try:
            run_console(ctx, script)
        except UnicodeDecodeError as exc:
            raise ConsoleError(f"{args.script or 'stdin'}: not UTF-8 text ({exc.reason})") from None
    finally:
        if script is not None and script is not sys.stdin:
            script.close()
    return 0


def _script_file(script: object) -> Path | None:
    """The regular file a script is read from (named, or stdin redirected from one: its
    descriptor's path), the console's commands never write over it; None for a pipe or a
    terminal."""
    import os
    import stat

    try:
        fd = script.fileno()  # type: ignore[attr-defined]
        if stat.S_ISREG(os.fstat(fd).st_mode):
            return Path(os.readlink(f"/proc/self/fd/{fd}"))  # the file's own path
    except (AttributeError, OSError, ValueError):
        pass
    return None
