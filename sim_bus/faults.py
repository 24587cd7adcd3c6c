"""Fault scripts for the simulated box: one text form for tests, ``hrm sim --fault`` and
the ``hrm sim`` control channel.

A fault is ``KIND[:ARG...][@T]``; ``@T`` (seconds after start, at most a day) delays
it, else it applies at once.  Every number is bounded (:data:`MAX_FRAME_COUNT`,
:data:`MAX_DELAY_MS`, :data:`MAX_GARBAGE_BYTES`, ...): a spec beyond a bound is a one-line
:class:`FaultSpecError`, never a fault that holds a frame for ever:

=========================== =====================================================
``heartbeat-stop:MOTOR``    the drive of rope motor MOTOR stops its heartbeat
``heartbeat-resume:MOTOR``  ... and resumes it
``drive-fault:MOTOR``       the drive faults with a following error (EMCY 0x8611)
``jam:MOTOR``               the motor stalls (faults once its target moves away)
``rope-snap:MOTOR``         the rope breaks: tension 0, its joint drifts
``drop:BUS[:COBID[:N]]``    lose N frames (default 1, ``all``) with COB-ID (or any)
``delay:BUS:MS[:COBID[:N]]`` hold N frames back MS milliseconds
``bus-off:BUS``             the bus goes off; ``bus-on:BUS`` brings it back
``sensor-garbage[:BYTES]``  the tension board sends garbage before every frame
``sensor-corrupt[:N]``      the next N frames carry a wrong CRC
``sensor-silent``           the tension board goes quiet; ``sensor-resume`` talks again
``clear``                   remove frame faults and sensor garbage / corruption
``reset``                   undo every fault (frames, buses, drives, ropes, sensor)
=========================== =====================================================

>>> parse_fault("drop:can0:0x181:all@2.5")
Fault(kind='drop', args=('can0', '0x181', 'all'), at_s=2.5)
>>> parse_fault("rope-snap:j05r2").at_s is None
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hrm_ctrl.errors import SimError
from sim_bus.box import SimBox
from sim_bus.tension_board import TensionBoard

#: kind -> (min args, max args)
KINDS: dict[str, tuple[int, int]] = {
    "heartbeat-stop": (1, 1),
    "heartbeat-resume": (1, 1),
    "drive-fault": (1, 1),
    "jam": (1, 1),
    "rope-snap": (1, 1),
    "drop": (1, 3),
    "delay": (2, 4),
    "bus-off": (1, 1),
    "bus-on": (1, 1),
    "sensor-garbage": (0, 1),
    "sensor-corrupt": (0, 1),
    "sensor-silent": (0, 0),
    "sensor-resume": (0, 0),
    "clear": (0, 0),
    "reset": (0, 0),
}


#: garbage bytes before each tension frame at most (made for every frame: more than this
#: per frame is not a different fault)
MAX_GARBAGE_BYTES = 65_536
#: frames with a wrong CRC at most (a counter: ~4 months of frames at 100 a second)
MAX_CORRUPT_FRAMES = 10**9
#: frames a drop or delay fault takes at most (``all`` for every one)
MAX_FRAME_COUNT = 10**9
#: a frame held back this long at most (every timeout of the stack, heartbeat, SDO,
#: missing TPDO, has fired long before: a longer hold is a ``drop``)
MAX_DELAY_MS = 60_000.0
#: ``@T`` at most (a day after the start: longer than a simulated box is run)
MAX_AT_S = 86_400.0


class FaultSpecError(SimError):
    """A fault script entry is malformed."""


@dataclass(frozen=True)
class Fault:
    kind: str
    args: tuple[str, ...]
    at_s: float | None


def has_control_character(text: str) -> bool:
    """Whether ``text`` holds a control character (a newline would end a command line).

    >>> has_control_character("reset"), has_control_character("reset\\nquit")
    (False, True)
    """
    return any(c < " " or c == "\x7f" for c in text)


def parse_fault(text: str) -> Fault:
    """Parse ``KIND[:ARG...][@T]`` (see the module docstring)."""
    if has_control_character(text):  # a newline would start another command
        raise FaultSpecError(f"fault {text!r}: control character in the spec")
    spec = text.strip()
    at: float | None = None
    if "@" in spec:
        spec, _, when = spec.rpartition("@")
        try:
            at = float(when)
        except ValueError:
            raise FaultSpecError(f"fault '{text}': time after @ must be seconds") from None
        if not math.isfinite(at) or at < 0:
            raise FaultSpecError(f"fault '{text}': time after @ must be >= 0 s")
        if at > MAX_AT_S:
            raise FaultSpecError(f"fault '{text}': time after @ must be 0..{MAX_AT_S:g} s")
    kind, *args = spec.split(":")
    if kind not in KINDS:
        raise FaultSpecError(f"fault '{text}': unknown kind '{kind}' (known: {', '.join(KINDS)})")
    lo, hi = KINDS[kind]
    if not lo <= len(args) <= hi:
        raise FaultSpecError(f"fault '{text}': '{kind}' takes {lo}..{hi} argument(s)")
    fault = Fault(kind, tuple(args), at)
    _numbers(fault, text)
    return fault


def _int(value: str, what: str, text: str) -> int:
    try:
        return int(value, 0)
    except ValueError:
        raise FaultSpecError(f"fault '{text}': {what} must be an integer, got '{value}'") from None


def _count(value: str | None, text: str) -> int | None:
    if value is None:
        return 1
    if value == "all":
        return None
    n = _int(value, "count", text)
    if not 1 <= n <= MAX_FRAME_COUNT:
        raise FaultSpecError(f"fault '{text}': count must be 1..{MAX_FRAME_COUNT} or 'all'")
    return n


def _numbers(f: Fault, text: str) -> tuple[int | None, int | None, float]:
    """(cob id, count, delay s) of a drop/delay fault, validated."""
    cob: int | None = None
    count: int | None = 1
    delay_s = 0.0
    if f.kind == "drop":
        if len(f.args) > 1:
            cob = _int(f.args[1], "COB-ID", text)
        count = _count(f.args[2] if len(f.args) > 2 else None, text)
    elif f.kind == "delay":
        try:
            delay_ms = float(f.args[1])
        except ValueError:
            raise FaultSpecError(f"fault '{text}': delay must be milliseconds") from None
        if not math.isfinite(delay_ms) or delay_ms < 0:
            raise FaultSpecError(f"fault '{text}': delay must be >= 0 ms")
        if delay_ms > MAX_DELAY_MS:
            raise FaultSpecError(
                f"fault '{text}': delay must be 0..{MAX_DELAY_MS:g} ms (a longer hold: drop)"
            )
        delay_s = delay_ms / 1000.0
        if len(f.args) > 2:
            cob = _int(f.args[2], "COB-ID", text)
        count = _count(f.args[3] if len(f.args) > 3 else None, text)
    elif f.kind in ("sensor-garbage", "sensor-corrupt") and f.args:
        n = _int(f.args[0], "count", text)
        top = MAX_GARBAGE_BYTES if f.kind == "sensor-garbage" else MAX_CORRUPT_FRAMES
        if not 0 <= n <= top:
            raise FaultSpecError(f"fault '{text}': count must be in 0..{top}")
    if cob is not None and not 0 <= cob <= 0x7FF:
        raise FaultSpecError(f"fault '{text}': COB-ID must be in 0..0x7FF")
    return cob, count, delay_s


def apply_fault(fault: Fault, box: SimBox, board: TensionBoard | None = None) -> str:
    """Apply one fault now; returns a one-line description."""
    k, a = fault.kind, fault.args
    text = f"{k}:{':'.join(a)}" if a else k
    cob, count, delay_s = _numbers(fault, text)
    match = None if cob is None else (lambda m, c=cob: m.arbitration_id == c)
    if k == "heartbeat-stop":
        box.stop_heartbeat(a[0], True)
    elif k == "heartbeat-resume":
        box.stop_heartbeat(a[0], False)
    elif k == "drive-fault":
        box.fault_drive(a[0])
    elif k == "jam":
        box.jam(a[0])
    elif k == "rope-snap":
        box.snap_rope(a[0])
    elif k == "drop":
        box.drop_frames(a[0], match, count)
    elif k == "delay":
        box.delay_frames(a[0], delay_s, match, count)
    elif k in ("bus-off", "bus-on"):
        box.set_bus_off(a[0], k == "bus-off")
    elif k == "reset":
        box.reset_faults()
        if board is not None:
            board.inject_garbage(0)
            board.corrupt_frames(0)
            board.set_silent(False)
    elif k == "clear":
        box.clear_frame_faults()
        if board is not None:
            board.inject_garbage(0)
            board.corrupt_frames(0)
    else:
        if board is None:
            raise FaultSpecError(f"fault '{text}': no tension board in this box")
        if k == "sensor-garbage":
            board.inject_garbage(int(a[0], 0) if a else 64, continuous=True)
        elif k == "sensor-corrupt":
            board.corrupt_frames(int(a[0], 0) if a else 1)
        elif k == "sensor-silent":
            board.set_silent(True)
        elif k == "sensor-resume":
            board.set_silent(False)
    return text
