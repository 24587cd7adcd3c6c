"""The console's ``calibrate``: the calibration store of this console's robot (``show``,
``history``: ``hrm calibrate show``/``history``) and the rope-tension routines over the
live session (``zero``, ``stiffness``: ``hrm calibrate zero``/``stiffness``,
``docs/calibration.md``).

The routines run on the enabled drives of this session (``enable`` first: nothing moves
without it), with the arm in its zero fixture: with ``--sim`` the console lays the
simulated arm in it for the routine and takes it out afterwards; on a real box the
operator says the arm lies in it with ``--fixture`` (refused without).  The feedback
watches are off while the routine runs (a slack rope is where the zero starts from and
the fixture holds the arm against its ropes: the routine guards the tensions itself) and
back on after.  The new version is saved in the store (active); the session keeps the
rope layer it was connected with, so a second routine is refused until ``disconnect``
and ``connect``, which drives with the new calibration.  ``hrm calibrate kinematic``
(poses with the tracker) runs outside the console.

>>> zero_args(["--target-N", "25", "--fixture"]).target_N
25.0
>>> zero_args(["--target-N", "-1"])
Traceback (most recent call last):
...
hrm_ctrl.cli._console.table.ConsoleError: --target-N must be > 0, got -1.0
"""

from __future__ import annotations

import argparse
import contextlib
import time
from typing import Any

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError, command

STORE_SUBCOMMANDS = ("show", "history")
ROUTINES = ("zero", "stiffness")
SUBCOMMANDS = STORE_SUBCOMMANDS + ROUTINES
USAGE = (
    "calibrate show|history [--json] | calibrate zero [--target-N N] [--tol-N N] "
    "[--max-travel-counts C] [--fixture] [--json] | calibrate stiffness [--sweep-N N] "
    "[--steps N] [--fixture] [--json]"
)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line, no exit
        raise ConsoleError(f"{self.prog}: {message}")


def _parser(routine: str) -> _Parser:
    """The options of ``calibrate zero`` / ``stiffness``: the routine's settings as ``hrm
    calibrate`` has them, ``--fixture`` and ``--json``."""
    from hrm_ctrl.cli._options import add_json, add_stiffness_options, add_zero_options

    p = _Parser(prog=f"calibrate {routine}", add_help=False)
    if routine == "zero":
        add_zero_options(p)
    else:
        add_stiffness_options(p)
    p.add_argument(
        "--fixture", action="store_true",
        help="the real arm lies in its zero fixture (refused without; with --sim the console "
        "lays the simulated arm in it)",
    )  # fmt: skip
    add_json(p, "the summary")
    return p


def routine_options(routine: str) -> list[str]:
    """The options of a routine, as completion proposes them."""
    return [o for a in _parser(routine)._actions for o in a.option_strings]


def _routine_args(routine: str, words: list[str]) -> argparse.Namespace:
    import math

    ns = _parser(routine).parse_args(words)
    for name in ("target_N", "tol_N", "sweep_N"):
        v = getattr(ns, name, None)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ConsoleError(f"--{name.replace('_', '-')} must be > 0, got {v}")
    steps = getattr(ns, "steps", None)
    if steps is not None and steps < 2:
        raise ConsoleError(f"--steps must be at least 2, got {steps}")
    ns.calibrate = routine
    ns.out = None  # the store, never a loose file
    return ns


def zero_args(words: list[str]) -> argparse.Namespace:
    """The options of ``calibrate zero`` (one-line :class:`ConsoleError` on bad ones)."""
    return _routine_args("zero", words)


def _complete(ctx: ConsoleContext, words: list[str]) -> list[str]:
    if len(words) <= 2:
        return list(SUBCOMMANDS)
    return routine_options(words[1]) if words[1] in ROUTINES else ["--json"]


@command("calibrate", "the calibration store (show, history) and, on the enabled drives "
         "with the arm in its zero fixture, the rope-tension routines (zero, stiffness)",
         USAGE, complete=_complete)  # fmt: skip
def _calibrate(ctx: ConsoleContext, args: list[str]) -> None:
    from hrm_ctrl.cli import calibrate

    if not args or args[0] not in SUBCOMMANDS:
        raise ConsoleError(f"usage: {USAGE}")
    if args[0] in ROUTINES:
        _run_routine(ctx, args[0], _routine_args(args[0], args[1:]))
        return
    if args[1:] not in ([], ["--json"]):
        raise ConsoleError("usage: calibrate show|history [--json]")
    given = ctx.extra.get("args")
    ns = argparse.Namespace(
        calibrations=getattr(given, "calibrations", None),
        robot=getattr(given, "robot", None),
        json=args[1:] == ["--json"],
    )
    (calibrate.run_show if args[0] == "show" else calibrate.run_history)(ns)


def _run_routine(ctx: ConsoleContext, routine: str, ns: argparse.Namespace) -> None:
    """Check everything, then run ``routine`` on the session's enabled drives."""
    from calibration.apply import nominal_calibration
    from calibration.store import CalibrationStore
    from hrm_ctrl.cli import _calibrate_tension as tension_cli
    from hrm_ctrl.cli._common import calibrations_folder
    from hrm_ctrl.cli._console.streaming import start_watches, stop_watches

    name = f"calibrate {routine}"
    if ctx.session is None or not ctx.enabled:
        raise ConsoleError(f"{name}: enable the drives first (connect, enable)")
    saved = ctx.extra.get("calibrated_version")
    if saved is not None:
        raise ConsoleError(
            f"{name}: calibration v{saved:04d} was saved in this session: disconnect and "
            "connect to drive with it first"
        )
    reader = ctx.extra.get("tension_reader")
    if ctx.config.tension is None or reader is None:
        raise ConsoleError(f"{name}: no [tension] table in the bus configuration: the "
                           "routine needs the tension sensors")  # fmt: skip
    if ctx.sim is None and not ns.fixture:
        raise ConsoleError(f"{name}: the arm must lie in its zero fixture: say so with "
                           "--fixture")  # fmt: skip
    given = ctx.extra.get("args")
    store = CalibrationStore(calibrations_folder(getattr(given, "calibrations", None)))
    # the base is the calibration this session drives with (its zeros are what the
    # routine moves from), not whatever the store holds now
    base = (
        ctx.active.calibration if ctx.active is not None else nominal_calibration(ctx.description)
    )
    if ns.out is None:  # checked before the first move: the result has a place to go
        store.check_can_save()
    build = tension_cli.zero_routine if routine == "zero" else tension_cli.stiffness_routine
    run = build(ns, progress=ctx.out)
    t0 = time.monotonic()
    stop_watches(ctx)
    fixture = ctx.sim.set_straight_fixture if ctx.sim is not None else None
    try:
        if fixture is not None:
            fixture(True)
            ctx.out(f"{name}: the simulated arm lies in its zero fixture")
        result = run(ctx.session, reader, ctx.actuation)
    finally:
        if fixture is not None:
            with contextlib.suppress(Exception):
                fixture(False)
        if ctx.enabled:
            start_watches(ctx)
    report = tension_cli.report_zero if routine == "zero" else tension_cli.report_stiffness
    box = ctx.session.box_identity
    version = report(ns, result, base, store, t0, ctx.out, ctx.description, box=box).version
    if store.active() != version:  # kept, not made active (out of range): nothing changes
        ctx.out(f"{name}: v{version:04d} is not active: the session and the store keep "
                "the calibration they had")  # fmt: skip
        return
    ctx.extra["calibrated_version"] = version
    ctx.extra["reload_arm"] = True
    ctx.out(f"{name}: the session keeps its rope layer: disconnect and connect to drive with "
            f"v{version:04d}")  # fmt: skip
