"""The box as its own process (``hrm sim``): box + tension board + fault script + control.

The process prints one JSON object per line on stdout:

* ``{"event": "ready", "tension_port": "/dev/pts/N", "buses": [...], "motors": 36, ...}``
  once every drive has sent its boot-up and the tension board runs (with the tracker,
  ``"tracker_port"`` too; ``"truth"`` names the arm's truth, ``"fixture"`` whether the
  arm starts in its zero fixture);
* ``{"event": "fault", "fault": "...", "t_s": ...}`` whenever a fault is applied;
* replies to control commands; ``{"event": "stopped", ...}`` at the end.

With ``control=True`` it reads commands from stdin, one per line:
``fault SPEC`` (see :mod:`sim_bus.faults`), ``state`` (true arm state now),
``trace on|off`` / ``trace`` (positions after every SYNC), ``stats``, ``fixture on|off``
(the zero fixture), ``tracker-lost on|off`` (the tracker loses / finds its
target), ``truth`` (the arm's truth, as a truth file's content), ``quit``.
End of stdin also stops the box, so a parent that dies takes the box with it.

Running the box changes no interpreter setting: the process entry (``hrm``, see
:func:`hrm_ctrl.cli.main`) enters :func:`drivers.realtime.process_settings`, which
lowers the GIL switch interval so the bus threads answer each SYNC promptly while the
tension board computes the arm.
"""

from __future__ import annotations

import json
import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any, TextIO

from drivers.config import BoxConfig
from hrm_ctrl.errors import HrmError
from hrm_ctrl.ropes.actuation import Actuation
from sim_bus.box import SimBox
from sim_bus.faults import Fault, apply_fault, parse_fault
from sim_bus.physics import Physics
from sim_bus.tension_board import TensionBoard
from sim_bus.truth import TrueArm
from sim_bus.wire import SimWireBus


def _emit(out: TextIO, obj: dict[str, Any]) -> None:
    out.write(json.dumps(obj, separators=(",", ":")) + "\n")
    out.flush()


def arm_state_json(box: SimBox) -> dict[str, Any]:
    s = box.arm_state()
    return {
        "event": "state",
        "t_s": s.t,
        "counts": s.counts.tolist(),
        "alpha": s.alpha.tolist(),
        "theta": s.theta.tolist(),
        "centres": s.centres.round(6).tolist(),
        "tension_N": s.tension_N.round(3).tolist(),
        "statuswords": box.statuswords(),
        "snapped": list(box.arm.snapped),
        "fixture": s.fixture,
    }


def stats_json(box: SimBox, board: TensionBoard | None) -> dict[str, Any]:
    wires = [bb.bus.wire.stats() for bb in box._buses if isinstance(bb.bus, SimWireBus)]
    return {
        "event": "stats",
        "cpu_s": box.cpu_s,
        "frames_in": {bb.name: bb.frames_in for bb in box._buses},
        "frames_out": {bb.name: bb.frames_out for bb in box._buses},
        "wires": wires,
        "tension_frames": board.frames_sent if board else 0,
        "tension_frames_dropped": board.frames_dropped if board else 0,
        "tension_errors": board.errors[-5:] if board else [],
        "events": box.events[-50:],
    }


def run_box_process(
    config: BoxConfig,
    *,
    actuation: Actuation | None = None,
    faults: Sequence[Fault] = (),
    duration_s: float | None = None,
    tension_rate_hz: float = 100.0,
    control: bool = False,
    out: TextIO = sys.stdout,
    inp: TextIO = sys.stdin,
    truth: TrueArm | None = None,
    fixture: bool = False,
    tracker: bool = False,
    initial_counts: Sequence[int] | None = None,
    physics: Physics | None = None,
) -> int:
    """Run the box until ``duration_s``, ``quit``, end of stdin (with ``control``) or
    SIGTERM/SIGINT.  ``initial_counts``: where the motors stand at power-on (the rope
    layer's order; None: 0).  Returns the exit status (0)."""
    stop = threading.Event()
    commands: queue.Queue[str | None] = queue.Queue()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    box = SimBox(
        config,
        actuation=actuation,
        truth=truth,
        initial_counts=initial_counts,
        physics=physics,
    )
    if fixture:
        box.set_straight_fixture(True)
    board = TensionBoard(box.tension_N, tension_rate_hz)
    box.start()
    try:
        board.start()
        extra: dict[str, Any] = {}
        if tracker:
            extra["tracker_port"] = box.start_tracker().port
        t0 = time.monotonic()
        _emit(
            out,
            {
                "event": "ready",
                "tension_port": board.port,
                "buses": [
                    {"name": b.name, "interface": b.interface, "channel": str(b.channel)}
                    for b in config.buses
                ],
                "motors": len(config.motor_ids),
                "motor_ids": list(box.actuation.motor_ids),
                "source": config.source,
                **extra,
                "truth": box.truth.source,
                "fixture": box.arm.fixture,
                "physics": "none" if physics is None else physics.describe(),
            },
        )
        if control:

            def read_commands() -> None:
                for line in control_lines(inp):
                    commands.put(line)
                commands.put(None)

            threading.Thread(target=read_commands, name="sim-control", daemon=True).start()
        pending = sorted(faults, key=lambda f: f.at_s or 0.0)
        while not stop.is_set():
            now = time.monotonic() - t0
            while pending and (pending[0].at_s or 0.0) <= now:
                f = pending.pop(0)
                _emit(out, {"event": "fault", "fault": apply_fault(f, box, board), "t_s": now})
            if duration_s is not None and now >= duration_s:
                break
            try:
                cmd = commands.get(timeout=0.01)
            except queue.Empty:
                continue
            if cmd is None or cmd == "quit":
                break
            try:
                later = control_command(cmd, box, board, out, now)
                if later is not None:  # fault SPEC@T: applied T s after the start
                    pending = sorted([*pending, later], key=lambda f: f.at_s or 0.0)
            except HrmError as exc:
                _emit(out, {"event": "error", "error": str(exc)})
        _emit(out, {**stats_json(box, board), "event": "stopped"})
    finally:
        board.stop()
        box.stop()
    return 0


#: a control line longer than this is refused (one error event), not read into memory
MAX_CONTROL_LINE_CHARS = 4096
_SHOWN_CHARS = 40  # of an unknown command word, in its error event


def control_lines(inp: TextIO) -> Iterator[str]:
    """The control channel's lines, stripped, each read with a bound: a longer line is
    skipped in bounded pieces and given as :data:`TOO_LONG` instead.

    >>> import io
    >>> list(control_lines(io.StringIO("state\\n" + "x" * 5000 + "\\nquit\\n")))
    ['state', '\\x00too-long', 'quit']
    """
    while True:
        line = inp.readline(MAX_CONTROL_LINE_CHARS + 1)
        if not line:
            return
        if len(line) > MAX_CONTROL_LINE_CHARS and not line.endswith("\n"):
            while line and not line.endswith("\n"):  # the rest of it, piece by piece
                line = inp.readline(MAX_CONTROL_LINE_CHARS + 1)
            yield TOO_LONG
            continue
        yield line.strip()


TOO_LONG = "\x00too-long"  # what control_lines gives for a line over the bound


def control_command(
    cmd: str, box: SimBox, board: TensionBoard, out: TextIO, now: float
) -> Fault | None:
    """Carry out one control command of ``hrm sim --control`` (``fault SPEC[@T]``,
    ``state``, ``stats``, ``fixture on|off``, ``tracker-lost on|off``, ``truth``,
    ``trace [on|off]``) on ``box`` and its tension ``board`` at ``now`` s after the box
    started, writing its JSON event lines to ``out``: the box process's handler, and a box
    in another's process answers the same way.  A ``fault SPEC@T`` whose time is still to
    come is returned (the caller applies it then)."""
    if cmd == TOO_LONG:
        too_long = f"control line longer than {MAX_CONTROL_LINE_CHARS} characters"
        _emit(out, {"event": "error", "error": too_long})
        return None
    word, _, rest = cmd.partition(" ")
    if word == "fault":
        f = parse_fault(rest)
        if f.at_s is not None and f.at_s > now:
            _emit(out, {"event": "fault_scheduled", "fault": rest, "at_s": f.at_s, "t_s": now})
            return f
        _emit(out, {"event": "fault", "fault": apply_fault(f, box, board), "t_s": now})
    elif word == "state":
        _emit(out, arm_state_json(box))
    elif word == "stats":
        _emit(out, stats_json(box, board))
    elif word in ("fixture", "tracker-lost"):
        if rest not in ("on", "off"):
            _emit(out, {"event": "error", "error": f"usage: {word} on|off"})
        elif word == "fixture":
            box.set_straight_fixture(rest == "on")
            _emit(out, {"event": "fixture", "on": rest == "on", "t_s": now})
        else:
            box.tracker_lose_target(rest == "on")
            _emit(out, {"event": "tracker", "target_lost": rest == "on", "t_s": now})
    elif word == "truth":
        _emit(out, {"event": "truth", "source": box.truth.source, **box.truth.to_dict()})
    elif word == "trace":
        if rest in ("on", "off"):
            box.record_trace(rest == "on")
            _emit(out, {"event": "trace", "recording": rest == "on"})
        else:
            times, counts = box.trace()
            _emit(out, {"event": "trace", "t_s": times.tolist(), "counts": counts.tolist()})
    elif word:
        shown = word if len(word) <= _SHOWN_CHARS else word[:_SHOWN_CHARS] + "..."
        _emit(out, {"event": "error", "error": f"unknown command '{shown}'"})
    return None
