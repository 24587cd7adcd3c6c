"""The console's ``calibrate show|history``: the calibration store of this console's robot
(``hrm calibrate show``/``history``, ``docs/calibration.md``).  The session's rope layer
keeps the calibration it was started with (named in the run record); ``hrm calibrate
zero|stiffness|kinematic`` bring the drives up themselves: run them outside the console."""

from __future__ import annotations

import argparse

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError, command

SUBCOMMANDS = ("show", "history")


@command("calibrate", "the calibration store of this robot: the active calibration (show) or "
         "every version (history)", "calibrate show|history [--json]",
         complete=lambda ctx, words: list(SUBCOMMANDS) if len(words) == 2 else ["--json"],
         )  # fmt: skip
def _calibrate(ctx: ConsoleContext, args: list[str]) -> None:
    from hrm_ctrl.cli import calibrate

    if not args or args[0] not in SUBCOMMANDS or args[1:] not in ([], ["--json"]):
        raise ConsoleError("usage: calibrate show|history [--json]")
    given = ctx.extra.get("args")
    ns = argparse.Namespace(
        calibrations=getattr(given, "calibrations", None),
        robot=getattr(given, "robot", None),
        json=args[1:] == ["--json"],
    )
    (calibrate.run_show if args[0] == "show" else calibrate.run_history)(ns)
