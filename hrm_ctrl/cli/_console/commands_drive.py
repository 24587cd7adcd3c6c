"""The console's ``drive``: steer the tip over the live session; the body follows its trail.

The drive is the one ``hrm drive --sim`` plays (:func:`hrm_ctrl.drive.start.start_driver`,
:class:`hrm_ctrl.drive.stream.DriveSource`: a lead-in from where the drives stand to the
trail's first configuration, then the online step of every control cycle, shaped), here
on the session ``connect`` opened, with ``go_on``: a refusal of the planner holds the arm
at the last step it accepted and the drive goes on (the operator retracts or steers
elsewhere).  The keys: at a terminal the keyboard (:mod:`hrm_ctrl.drive.keymap`:
hold-to-move, ``+``/``-`` the speed cap, ``p``/space pause, ``a`` ends the drive: the tip
comes to rest within the advance ramp, then the motors; Ctrl-C quick-stops every axis as
for every move); in a script a key script (``--keys FILE``, as ``hrm drive --keys``).
The status line (travel, speed, clearance, the refusal that holds the arm, and the shape
feedback of :mod:`hrm_ctrl.drive.shape`: the arm the estimator sees against the plan and
the trail) is the progress line at a terminal; a script prints each hold as it begins.
``--save-trail FILE`` writes the trail as a path file at the end (also after a stop).
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from pathlib import Path
from typing import Any

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError, Need, command, complete_paths

DRIVE_USAGE = (
    "drive (--scenario bent-pipe|cabins | --path FILE) [--scene SCENE.toml] [--keys FILE] "
    "[--save-trail FILE] [--advance-speed MM_S] [--turn-rate DEG_S] [--accel MM_S2]"
)
MAX_KEYBOARD_DRIVE_S = 3600.0  # a drive from the keyboard ends after an hour at most
DISPLAY_PERIOD_S = 0.25


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line, no exit
        raise ConsoleError(f"{message} (usage: {DRIVE_USAGE})")


def _drive_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="drive", add_help=False)
    start = p.add_mutually_exclusive_group(required=True)
    start.add_argument("--scenario", choices=["bent-pipe", "cabins"])
    start.add_argument("--path", type=Path)
    p.add_argument("--scene", type=Path)
    p.add_argument("--keys", type=Path)
    p.add_argument("--save-trail", type=Path)
    p.add_argument("--advance-speed", type=float, default=20.0)
    p.add_argument("--turn-rate", type=float, default=11.4592)
    p.add_argument("--accel", type=float, default=40.0)
    return p


def _complete_drive(ctx: ConsoleContext, words: list[str]) -> list[str]:
    if len(words) >= 3 and words[-2] == "--scenario":
        return ["bent-pipe", "cabins"]
    if len(words) >= 3 and words[-2] in ("--path", "--keys", "--save-trail"):
        return complete_paths(words[-1], "")
    if len(words) >= 3 and words[-2] == "--scene":
        return complete_paths(words[-1], ".toml")
    return [o for a in _drive_parser()._actions for o in a.option_strings]


class _Keyboard(threading.Thread):
    """The terminal's keys into a :class:`~hrm_ctrl.drive.keymap.KeyboardSteer` (cbreak
    mode while it runs); the abort key ends the drive."""

    def __init__(self, steer: Any, source: Any) -> None:
        super().__init__(name="hrm-drive-keys", daemon=True)
        self.steer = steer
        self.source = source
        self._quit = threading.Event()

    def run(self) -> None:
        import os
        import sys

        from hrm_ctrl.cli._runcontrol import _cbreak, _key_ready, _restore

        old = _cbreak()
        try:
            while not self._quit.is_set():
                if not _key_ready(0.02):
                    continue
                text = os.read(sys.stdin.fileno(), 64).decode("utf-8", "replace")
                self.steer.feed_terminal(text, time.monotonic())
                if self.steer.aborted:
                    self.source.request_end()
        finally:
            if old is not None:
                _restore(old)

    def stop(self) -> None:
        self._quit.set()
        if self.is_alive():
            self.join(2.0)


def status_text(source: Any, shape: Any) -> str:
    """The drive's status line: the last cycle's (travel, speed, clearance, a hold) and
    the shape feedback's last sample."""
    s = source.last_status
    parts = ["lead-in" if s is None else s.line()]
    last = shape.last
    if last is not None and s is not None:
        parts.append(last.line())
    return "  ".join(parts)


class _Display(threading.Thread):
    """The status line at a terminal (the progress bar's line), and in a script each
    hold as it begins (one line)."""

    def __init__(self, ctx: ConsoleContext, source: Any, shape: Any, bar: Any) -> None:
        super().__init__(name="hrm-drive-display", daemon=True)
        self.ctx = ctx
        self.source = source
        self.shape = shape
        self.bar = bar
        self._said = 0
        self._quit = threading.Event()

    def say_holds(self) -> None:
        refusals = self.source.refusals
        while self._said < len(refusals):
            j, text = refusals[self._said]
            self._said += 1
            t = j * self.source.driver.period_s
            self.ctx.out(f"drive: HOLD at {t:.2f} s: {text}")

    def run(self) -> None:
        while not self._quit.wait(DISPLAY_PERIOD_S):
            if self.bar is not None and self.bar.enabled:
                self.bar.line(status_text(self.source, self.shape))
            else:
                self.say_holds()

    def stop(self) -> None:
        self._quit.set()
        if self.is_alive():
            self.join(2.0)
        self.say_holds()  # at a terminal the line showed them: now each on its own line


def _refuse_writing_over_inputs(ctx: ConsoleContext, a: argparse.Namespace) -> None:
    from hrm_ctrl.cli._common import Input, Output, refuse_overwriting_inputs

    refuse_overwriting_inputs(
        [Output("--save-trail", a.save_trail)],
        [
            Input("key script", a.keys),
            Input("path file", a.path),
            Input("scene file", a.scene),
            Input("console script", ctx.script_path),
        ],
    )


@command("drive", "steer the tip (keys at a terminal, --keys FILE in a script); the body "
         "follows the trail the tip draws; a refusal holds the arm and the drive goes on; "
         "a ends it", DRIVE_USAGE, needs=Need.ENABLED, complete=_complete_drive)  # fmt: skip
def _drive(ctx: ConsoleContext, args: list[str]) -> None:
    from hrm_ctrl.cli._console.streaming import play
    from hrm_ctrl.cli._progress import ProgressBar
    from hrm_ctrl.drive.command import SteerLimits
    from hrm_ctrl.drive.keymap import KeyboardSteer
    from hrm_ctrl.drive.script import KeyScript
    from hrm_ctrl.drive.shape import ShapeFeedback, ShapeWatch, box_feedback, drive_plan
    from hrm_ctrl.drive.start import DriveStart, start_driver
    from hrm_ctrl.drive.stream import DriveSource

    a = _drive_parser().parse_args(args)
    keyboard = a.keys is None
    if keyboard and not ctx.interactive:
        raise ConsoleError("drive: in a script the keys come from a key script: give --keys FILE")
    _refuse_writing_over_inputs(ctx, a)
    rate = math.radians(a.turn_rate) if math.isfinite(a.turn_rate) else a.turn_rate
    limits = SteerLimits(rate, rate, a.advance_speed, a.accel)
    period_s = ctx.config.control.period_s
    start = DriveStart(scenario=a.scenario, path=a.path, scene=a.scene)
    driver = start_driver(ctx.actuation.robot, start, limits, period_s)
    steer = None
    if keyboard:
        steer = KeyboardSteer(limits)
        kb = steer
        end_s = MAX_KEYBOARD_DRIVE_S

        def command_at(t_s: float) -> Any:
            return kb.command(time.monotonic())

    else:
        keys = KeyScript.read(a.keys)
        end_s = keys.end_s if math.isfinite(keys.end_s) else (
            keys.events[-1].t_s if keys.events else 0.0)  # fmt: skip

        def command_at(t_s: float) -> Any:
            return keys.command_at(t_s, limits)

    source = DriveSource(driver, ctx.actuation, command_at, float(end_s), go_on=True)
    source.precheck(period_s)
    shape = ShapeWatch(
        box_feedback(ctx.session, ctx.watches), drive_plan(source), ShapeFeedback(ctx.actuation)
    )
    what = "drive"
    if keyboard:
        ctx.out("drive: w/s advance/retract, arrows (h j k l) steer, held; + - speed; p pause; "
                "a ends the drive; Ctrl-C stops every axis")  # fmt: skip
    stop: ConsoleError | None = None
    with ProgressBar(what, enabled=ctx.interactive) as bar:
        display = _Display(ctx, source, shape, bar)
        reader = None if steer is None else _Keyboard(steer, source)
        shape.start()
        display.start()
        if reader is not None:
            reader.start()
        try:
            play(ctx, source, what)
        except ConsoleError as exc:
            stop = exc
        finally:
            if reader is not None:
                reader.stop()
            shape.stop()
            display.stop()
            _note_drive(ctx, source, shape, a)
            if a.save_trail is not None:
                driver.planner.trail.save(a.save_trail)
    _say_summary(ctx, source, shape, a)
    if stop is not None:
        raise stop


def _note_drive(ctx: ConsoleContext, source: Any, shape: Any, a: argparse.Namespace) -> None:
    """What the session's run record keeps of a console drive (``console_drives``)."""
    drives = ctx.session.record_extra.setdefault("console_drives", [])
    drives.append({
        "start": a.scenario or str(a.path),
        "keys": None if a.keys is None else str(a.keys),
        **source.describe(),
        "summary": source.summary().to_dict(),
        "shape": shape.summary(),
    })  # fmt: skip


def _say_summary(ctx: ConsoleContext, source: Any, shape: Any, a: argparse.Namespace) -> None:
    s = source.summary()
    c = s.worst_clearance_mm
    ctx.out(
        f"drive: {s.cycles} cycles, travel {s.travel_mm:.1f} mm, trail {s.trail_length_mm:.1f} "
        f"mm, {len(s.refusals)} hold(s)"
        + ("" if math.isinf(c) else f", worst clearance {c:.2f} mm")
    )
    sh = shape.summary()
    if sh["samples"]:
        ctx.out(
            f"drive: shape feedback ({sh['samples']} samples, the rope estimator"
            f"{' with tensions' if sh['tensions'] else ''}): tip off the trail at most "
            f"{sh['tip_from_trail_mm']['max']:.2f} mm (last {sh['tip_from_trail_mm']['last']:.2f}"
            f"), the arm off the plan at most {sh['shape_mm']['max']:.2f} mm"
        )
    if sh["error"]:
        ctx.err(f"drive: {sh['error']}")
    if a.save_trail is not None:
        ctx.out(f"drive: trail written to {a.save_trail}")
