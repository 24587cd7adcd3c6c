"""The console's session commands: help, connect, disconnect, status, enable, disable,
stop, reset-fault, quit, and the simulator's ``sim`` (with ``--sim`` only).

Nothing is sent to a drive before ``connect`` (the one bring-up: NMT reset, SDO
configuration, NMT start; the drives stay up until ``disconnect`` or ``quit``), nothing
moves before ``enable``, and ``quit`` (or the end of the input) disables every drive and
finishes the session (NMT pre-operational, host heartbeat last, the run record written).
"""

from __future__ import annotations

import math
import sys
import time

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.streaming import start_watches, stop_watches, tension_sample
from hrm_ctrl.cli._console.table import (
    COMMANDS,
    ConsoleError,
    Need,
    command,
    find,
    parse_float,
    parse_int,
)

MAX_WATCH_COUNT = 100_000  # refreshes of one `status watch` at most
MIN_WATCH_PERIOD_S = 0.2  # every refresh reads every drive by SDO: not faster than this
STOP_CONFIRM_S = 2.0  # longest wait for an idle stop to show in the session state


def _no_args(name: str, args: list[str]) -> None:
    if args:
        raise ConsoleError(f"takes no arguments, got {' '.join(args)!r}")


# ---------------------------------------------------------------------------- help
def _complete_command(ctx: ConsoleContext, words: list[str]) -> list[str]:
    return sorted(COMMANDS) if len(words) <= 1 else []


@command("help", "list the commands, or show one command's usage", "help [COMMAND]",
         complete=_complete_command)  # fmt: skip
def _help(ctx: ConsoleContext, args: list[str]) -> None:
    if len(args) > 1:
        raise ConsoleError("usage: help [COMMAND]")
    if args:
        cmd = find(args[0])
        ctx.out(f"{cmd.usage}\n  {cmd.summary}")
        return
    width = max(len(n) for n in COMMANDS)
    for name in sorted(COMMANDS):
        ctx.out(f"  {name:<{width}}  {COMMANDS[name].summary}")
    ctx.out("'help COMMAND' shows its usage; Ctrl-C stops a move; quit (or Ctrl-D) ends.")


# ---------------------------------------------------------------------------- connect
@command("connect", "open the buses and bring every drive up once (NMT reset, SDO "
         "configuration, NMT start); refused when another master operates the box",
         "connect [--take-over]")  # fmt: skip
def _connect(ctx: ConsoleContext, args: list[str]) -> None:
    import contextlib

    from drivers.bus import ensure_log_dir
    from drivers.tension_sensor import TensionSensorReader
    from hrm_ctrl.runtime.box import NO_WATCHES, SessionOptions, open_box
    from hrm_ctrl.runtime.simulated import RunningSim

    if args not in ([], ["--take-over"]):
        raise ConsoleError("usage: connect [--take-over]")
    if ctx.session is not None:
        raise ConsoleError(f"connected already (session {ctx.session.state.name})")
    ensure_log_dir(ctx.runs_dir)
    if ctx.extra.get("reload_arm"):  # a calibration was saved in the last session
        reload_arm(ctx)
    options = SessionOptions(
        log_dir=ctx.runs_dir,
        log_suffix=ctx.log_suffix,
        take_over=ctx.take_over or bool(args),
        calibration=ctx.calibration,
        allow_uncalibrated=ctx.allow_uncalibrated,
        record_extra={"console": True, "simulated_box": ctx.simulated},
    )
    sim = None if ctx.sim is None else RunningSim(ctx.config, ctx.sim)  # the console's own
    stack = contextlib.ExitStack()
    # the console's watches run while the drives are enabled (start_watches)
    box = stack.enter_context(
        open_box(ctx.config, ctx.actuation, options, sim=sim, watches=NO_WATCHES, bring_up=False)
    )
    session = box.session
    session.track_emergencies()
    ctx.session = session
    ctx.extra["box"] = stack
    try:
        t = ctx.config.tension
        if t is not None:  # opened before any NMT reset: a bad port is refused first
            with session.thread_scheduling():
                ctx.extra["tension_reader"] = TensionSensorReader(
                    t.port, ctx.actuation.n_motors, baudrate=t.baudrate, stale_after_s=t.stale_s
                ).open()
        session.configure()
    except BaseException:
        close_session(ctx)
        raise
    n_buses = len(ctx.config.buses)
    ctx.out(
        f"connected: {ctx.actuation.n_motors} drives on {n_buses} bus(es) up in "
        f"{session.bringup_s:.2f} s, session {session.state.name} (enable to move)"
    )


def reload_arm(ctx: ConsoleContext) -> None:
    """The robot model, rope layer and calibration from the store's active version (after
    a ``calibrate`` saved one); the simulated arm stays what it is."""
    from hrm_ctrl.cli._common import arm_from_args

    given = ctx.extra.get("args")
    arm = arm_from_args(given, ctx.description, prog=ctx.prog, simulated=ctx.simulated)
    ctx.config.check_motors(arm.actuation.motor_ids)
    ctx.model, ctx.actuation = arm.robot, arm.actuation
    ctx.calibration, ctx.active = arm.calibration_ref(), arm.active
    ctx.extra.pop("reload_arm", None)
    version = "the description's values" if arm.active is None else f"v{arm.active.version:04d}"
    ctx.out(f"calibration: {version}")


def close_session(ctx: ConsoleContext) -> None:
    """Finish (every drive disabled, NMT pre-operational, host heartbeat off) and close
    the session (run record written); errors of the finish are raised after the close."""
    from hrm_ctrl.cli._console.commands_view import close_view

    session = ctx.session
    if session is None:
        return
    stop_watches(ctx)
    box = ctx.extra.pop("box")
    try:
        try:
            close_view(ctx)
        finally:
            box.close()  # open_box: every drive disabled, then the run record written
    finally:
        ctx.session = None
        ctx.extra.pop("calibrated_version", None)
        reader = ctx.extra.pop("tension_reader", None)
        if reader is not None:
            reader.close()
        ctx.last_run = session.record_path


@command("disconnect", "disable every drive, NMT pre-operational, close the buses and "
         "write the run record", "disconnect", needs=Need.CONNECTED)  # fmt: skip
def _disconnect(ctx: ConsoleContext, args: list[str]) -> None:
    _no_args("disconnect", args)
    close_session(ctx)
    ctx.out(f"disconnected: run record {ctx.last_run}")


# ---------------------------------------------------------------------------- status
def _fmt(value: object, width: int, spec: str = "") -> str:
    text = "-" if value is None else format(value, spec)
    return f"{text:>{width}}"


def format_status(st: object, actuation: object) -> list[str]:
    """The lines of a :class:`drivers.status.SessionStatus`."""
    lines = [
        f"session {st.state}  calibration {st.calibration}  "
        f"({'read by SDO' if st.by_sdo else 'from the feedback'})"
    ]
    lines.append(
        f"{'motor':<6} {'bus':<5} {'node':>4}  {'NMT':<15} {'CiA 402':<22} {'position':>9} "
        f"{'held':>9} {'f.err':>6} {'tension':>8} {'hb age':>7}  last EMCY"
    )
    for n in st.nodes:
        fe = n.following_error_counts
        age = None if n.heartbeat_age_s is None else round(n.heartbeat_age_s * 1000)
        lines.append(
            f"{n.motor:<6} {n.bus:<5} {n.node_id:>4}  {n.nmt_state or '-':<15} "
            f"{n.state402 or '-':<22} {_fmt(n.position_counts, 9)} {_fmt(n.target_counts, 9)} "
            f"{_fmt(fe, 6)} {_fmt(n.tension_N, 6, '.1f')} N {_fmt(age, 4)} ms  "
            f"{n.last_emcy or '-'}"
        )
    for b in st.buses:
        lines.append(
            f"bus {b.name}: {b.bitrate / 1000:g} kbit/s, load {100 * b.load:.1f} % (limit "
            f"{100 * b.load_limit:.0f} %), sent {b.frames_sent}, error frames {b.error_frames}, "
            f"foreign frames {b.foreign_frames}, log lost {b.log_frames_lost}"
            + (f", {b.state}" if b.state else "")
            + (f"; link {b.link}" if b.link else "")
        )
    faulted = [n.motor for n in st.faulted]
    if faulted:
        lines.append(f"in FAULT: {', '.join(faulted)}")
    for cause in st.stop_causes:
        lines.append(f"stopped: {cause}")
    return lines


def _snapshot(ctx: ConsoleContext) -> object:
    return ctx.session.status_snapshot(tension_sample(ctx))


@command("status", "every drive (NMT, CiA 402, position, following error, tension, heartbeat "
         "age, last EMCY), every bus, the session; 'status watch' refreshes it in place",
         "status [watch [PERIOD_S [COUNT]]]", needs=Need.CONNECTED,
         complete=lambda ctx, words: ["watch"] if len(words) <= 2 else [])  # fmt: skip
def _status(ctx: ConsoleContext, args: list[str]) -> None:
    if not args:
        for line in format_status(_snapshot(ctx), ctx.actuation):
            ctx.out(line)
        return
    if args[0] != "watch" or len(args) > 3:
        raise ConsoleError("usage: status [watch [PERIOD_S [COUNT]]]")
    usage = "status watch [PERIOD_S [COUNT]]"
    period_s = parse_float(args[1], "PERIOD_S", usage) if len(args) > 1 else 1.0
    count = parse_int(args[2], "COUNT", usage) if len(args) > 2 else None
    if not (math.isfinite(period_s) and MIN_WATCH_PERIOD_S <= period_s <= 3600):
        raise ConsoleError(f"PERIOD_S must be in [{MIN_WATCH_PERIOD_S:g}, 3600] s")
    if count is None and not ctx.interactive:
        raise ConsoleError("in a script, give the number of refreshes: status watch PERIOD_S N")
    if count is not None and not 1 <= count <= MAX_WATCH_COUNT:
        raise ConsoleError(f"COUNT must be in [1, {MAX_WATCH_COUNT}]")
    in_place = ctx.interactive and sys.stdout.isatty()
    k = 0
    try:
        while count is None or k < count:
            lines = format_status(_snapshot(ctx), ctx.actuation)
            if in_place:
                sys.stdout.write("\x1b[H\x1b[2J")  # cursor home, clear: refresh in place
            for line in lines:
                ctx.out(line)
            if in_place:
                ctx.out(f"(every {period_s:g} s; Ctrl-C ends)")
            k += 1
            if count is None or k < count:
                time.sleep(period_s)
    except KeyboardInterrupt:
        if not ctx.interactive:
            raise  # in a script Ctrl-C ends the script (and stops every axis), as elsewhere
        ctx.out("")  # at the prompt it ends the watch


# ---------------------------------------------------------------------------- power
@command("enable", "every drive to OPERATION_ENABLED at its actual position (nothing moves), "
         "supervised; the tension and rope watches start", "enable",
         needs=Need.CONNECTED)  # fmt: skip
def _enable(ctx: ConsoleContext, args: list[str]) -> None:
    _no_args("enable", args)
    session = ctx.session
    if session.enabled:
        raise ConsoleError("the drives are enabled already")
    if session.state.name in ("STOPPED", "FAULT"):
        raise ConsoleError(
            f"session {session.state.name} after a stop: reset-fault (or disable) first"
        )
    session.enable()
    start_watches(ctx)
    ctx.out(f"enabled: {ctx.actuation.n_motors} drives OPERATION_ENABLED, holding")


@command("disable", "every drive disabled (power stage off) by SDO; after a stop too",
         "disable", needs=Need.CONNECTED)  # fmt: skip
def _disable(ctx: ConsoleContext, args: list[str]) -> None:
    _no_args("disable", args)
    session = ctx.session
    if session.state.name == "READY":
        ctx.out("disabled already (session READY)")
        return
    stop_watches(ctx)
    session.disable()
    ctx.out("disabled: every drive READY_TO_SWITCH_ON (power stage off)")


@command("stop", "quick stop of every axis now (also when idle); the session goes STOPPED",
         "stop", needs=Need.CONNECTED)  # fmt: skip
def _stop(ctx: ConsoleContext, args: list[str]) -> None:
    from drivers.safety.causes import StopKind

    _no_args("stop", args)
    session = ctx.session
    if not session.enabled:
        ctx.out(f"nothing to stop: the drives are not enabled (session {session.state.name})")
        return
    session.request_stop(StopKind.OPERATOR, "stop (console)")
    deadline = time.monotonic() + STOP_CONFIRM_S
    while session.enabled and time.monotonic() < deadline:
        time.sleep(0.01)
    stop_watches(ctx)
    if session.enabled:
        raise ConsoleError(f"no stop confirmed within {STOP_CONFIRM_S:g} s")
    ctx.out(f"stopped: every axis quick-stopped (session {session.state.name}); "
            "disable or reset-fault, then enable")  # fmt: skip


@command("reset-fault", "show why the box stopped, fault-reset the drives in FAULT and "
         "disable every drive (then enable)", "reset-fault", needs=Need.CONNECTED)  # fmt: skip
def _reset_fault(ctx: ConsoleContext, args: list[str]) -> None:
    _no_args("reset-fault", args)
    session = ctx.session
    if session.state.name not in ("STOPPED", "FAULT", "READY"):
        raise ConsoleError(
            f"session {session.state.name}: only after a stop (stop first to reset a drive)"
        )
    stop_watches(ctx)
    st = session.status_snapshot(tension_sample(ctx))
    for cause in st.stop_causes:
        ctx.out(f"cause: {cause}")
    for n in st.faulted:
        ctx.out(f"cause: {n.motor} in {n.state402}, last EMCY: {n.last_emcy or 'none'}")
    reset = session.reset_fault()
    what = ", ".join(reset) if reset else "no drive was in FAULT"
    ctx.out(f"reset: {what}; every drive disabled (session {session.state.name}); enable next")


@command("quit", "disable every drive, finish the session and leave the console", "quit")
def _quit(ctx: ConsoleContext, args: list[str]) -> None:
    _no_args("quit", args)
    ctx.quit_requested = True


# ---------------------------------------------------------------------------- sim
def _complete_sim(ctx: ConsoleContext, words: list[str]) -> list[str]:
    if len(words) <= 2:
        return ["fault", "reset"]
    if len(words) == 3 and words[1] == "fault":
        from sim_bus.faults import KINDS

        return sorted(f"{k}:{m}" for k in ("drive-fault", "jam", "rope-snap", "heartbeat-stop")
                      for m in ctx.actuation.motor_ids) + sorted(KINDS)  # fmt: skip
    return []


@command("sim", "the simulated box (--sim only): inject a fault as 'hrm sim --fault' does "
         "(docs/sim.md), or undo every fault", "sim fault SPEC | sim reset",
         complete=_complete_sim)  # fmt: skip
def _sim(ctx: ConsoleContext, args: list[str]) -> None:
    from sim_bus.faults import parse_fault

    if ctx.sim is None:
        raise ConsoleError("only with --sim (the simulated box)")
    if args == ["reset"]:
        args = ["fault", "reset"]
    if len(args) != 2 or args[0] != "fault":
        raise ConsoleError("usage: sim fault SPEC | sim reset")
    fault = parse_fault(args[1])
    if fault.at_s is not None:
        raise ConsoleError(f"{args[1]}: a delayed fault (@T) is for hrm sim --fault")
    ctx.out(f"sim: {ctx.sim.fault(args[1])}")
