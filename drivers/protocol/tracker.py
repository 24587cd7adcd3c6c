"""The laser tracker's serial protocol: request and reply lines (pure builders and parsers).

An ASCII line protocol on a serial line (a pseudo-terminal for the simulated instrument,
``sim_bus/tracker.py``; the host's reader is ``drivers/tracker.py``).  The host sends one
request line, the instrument answers one reply line:

* request ``MEAS\\n`` (a trailing ``\\r`` is ignored): measure the target (the end point)
  once; ``MEAS F<k>\\n`` (k = 1..16): measure the base plate's reference nest k instead
  (the robot description's ``[base] fiducials_mm``, an instrument's way of finding its own
  frame);
* reply ``$PT,<seq>,<x_mm>,<y_mm>,<z_mm>,<status>*<cs>\\r\\n``: ``seq`` the instrument's
  reply counter (decimal, 0..65535, +1 per reply, wraps), the point in the tracker's own
  frame in mm with exactly 4 decimals (``-?\\d{1,7}\\.\\d{4}``), ``status`` two hex digits
  of flags (bit 0: target lost, the coordinates are then empty; other bits reserved, 0),
  ``cs`` the XOR of every byte between ``$`` and ``*`` as two upper-case hex digits (NMEA
  style);
* reply ``$ER,<seq>,<code>*<cs>\\r\\n`` for a request the instrument does not know
  (``code`` upper-case letters, e.g. ``BADCMD``).

A reply line is at most :data:`MAX_LINE_BYTES` bytes, ``\\r\\n`` included.

>>> make_point_line(7, [1.5, -2.25, 3000.0])
b'$PT,7,1.5000,-2.2500,3000.0000,00*1E\\r\\n'
>>> r = parse_reply(b'$PT,7,1.5000,-2.2500,3000.0000,00*1E\\r\\n')
>>> r.seq, r.point_mm.tolist(), r.target_lost
(7, [1.5, -2.25, 3000.0], False)
>>> make_point_line(8, None, STATUS_TARGET_LOST)
b'$PT,8,,,,01*11\\r\\n'
>>> parse_reply(b'$PT,7,1.5000,-2.2500,3000.0000,00*1F\\r\\n')
Traceback (most recent call last):
drivers.protocol.tracker.TrackerLineError: checksum 1F, the line's bytes give 1E
"""

from __future__ import annotations

import enum
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.errors import DriverError

REQUEST_MEASURE = b"MEAS\n"
MAX_FIDUCIAL = 16
MAX_LINE_BYTES = 96  # "$PT,65535," + 3 x "-1234567.1234," + "FF*FF\r\n" = 60 bytes
MAX_REQUEST_BYTES = 32
SEQ_MODULO = 65536
MAX_COORDINATE_MM = 9_999_999.9999  # what 7 integer digits hold
STATUS_OK = 0x00
STATUS_TARGET_LOST = 0x01
STATUS_KNOWN = STATUS_TARGET_LOST  # other bits are reserved (0)

_COORD = r"-?\d{1,7}\.\d{4}"
_POINT = re.compile(rf"PT,(\d{{1,5}}),(?:({_COORD}),({_COORD}),({_COORD})|,,),([0-9A-F]{{2}})")
_ERROR = re.compile(r"ER,(\d{1,5}),([A-Z]{1,16})")


class TrackerLineError(DriverError):
    """A tracker line that is not a valid reply (or request) of the protocol."""


class Request(enum.Enum):
    """What a request line asks for."""

    MEASURE = "MEAS"


@dataclass(frozen=True)
class TrackerReply:
    """One parsed reply: ``point_mm`` (3,) in the tracker's frame, or None when the target
    is lost; ``error`` the code of an ``$ER`` reply (then no point)."""

    seq: int
    point_mm: np.ndarray | None
    status: int
    error: str | None = None

    @property
    def target_lost(self) -> bool:
        return bool(self.status & STATUS_TARGET_LOST)


def checksum(body: bytes) -> int:
    """XOR of the bytes (between ``$`` and ``*``).

    >>> hex(checksum(b"ER,1,BADCMD"))
    '0x2b'
    """
    cs = 0
    for byte in body:
        cs ^= byte
    return cs


def _line(body: str) -> bytes:
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{checksum(raw):02X}".encode("ascii") + b"\r\n"


def _seq(seq: int) -> int:
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise TrackerLineError(f"sequence number must be an integer >= 0, got {seq!r}")
    return seq % SEQ_MODULO


def make_point_line(
    seq: int, point_mm: Sequence[float] | np.ndarray | None, status: int = STATUS_OK
) -> bytes:
    """The ``$PT`` reply for a point (mm, tracker frame) or, with the target-lost flag,
    none (``point_mm`` None)."""
    if not 0 <= status <= 0xFF:
        raise TrackerLineError(f"status must be one byte, got {status!r}")
    lost = bool(status & STATUS_TARGET_LOST)
    if lost or point_mm is None:
        if not lost:
            raise TrackerLineError("a reply without a point must carry the target-lost flag")
        coords = ",,"
    else:
        p = np.asarray(point_mm, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)) or np.abs(p).max() > MAX_COORDINATE_MM:
            raise TrackerLineError(
                f"point must be 3 finite coordinates within {MAX_COORDINATE_MM:g} mm, got {p!r}"
            )
        coords = ",".join(f"{float(v):.4f}" for v in p)
        coords = coords.replace("-0.0000", "0.0000")
    return _line(f"PT,{_seq(seq)},{coords},{status:02X}")


def make_error_line(seq: int, code: str) -> bytes:
    """The ``$ER`` reply (``code``: 1-16 upper-case letters).

    >>> make_error_line(1, "BADCMD")
    b'$ER,1,BADCMD*2B\\r\\n'
    """
    if not re.fullmatch(r"[A-Z]{1,16}", code):
        raise TrackerLineError(f"error code must be 1-16 upper-case letters, got {code!r}")
    return _line(f"ER,{_seq(seq)},{code}")


def parse_reply(line: bytes) -> TrackerReply:
    """Parse one reply line (with or without its ``\\r\\n``); anything else raises
    :class:`TrackerLineError` with one line saying why (no bytes echoed past 40)."""
    if len(line) > MAX_LINE_BYTES:
        raise TrackerLineError(f"line of {len(line)} bytes, longer than {MAX_LINE_BYTES}")
    raw = line[:-1] if line.endswith(b"\n") else line
    raw = raw[:-1] if raw.endswith(b"\r") else raw
    shown = repr(raw[:40]) + ("..." if len(raw) > 40 else "")
    if not raw.startswith(b"$") or len(raw) < 4 or raw[-3:-2] != b"*":
        raise TrackerLineError(f"not a reply line ($...*CS): {shown}")
    body, cs_text = raw[1:-3], raw[-2:]
    if not re.fullmatch(rb"[0-9A-F]{2}", cs_text):
        raise TrackerLineError(f"checksum digits must be two upper-case hex digits: {shown}")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise TrackerLineError(f"not a reply line (bytes that are not ASCII): {shown}") from None
    cs = int(cs_text, 16)
    if cs != checksum(body):
        raise TrackerLineError(
            f"checksum {cs_text.decode()}, the line's bytes give {checksum(body):02X}"
        )
    m = _POINT.fullmatch(text)
    if m is not None:
        seq = int(m.group(1))
        status = int(m.group(5), 16)
        if seq >= SEQ_MODULO:
            raise TrackerLineError(f"sequence number {seq} beyond {SEQ_MODULO - 1}")
        if status & ~STATUS_KNOWN:
            raise TrackerLineError(f"status {status:02X} sets reserved bits")
        lost = bool(status & STATUS_TARGET_LOST)
        if m.group(2) is None:
            if not lost:
                raise TrackerLineError("a reply without coordinates must flag the target lost")
            return TrackerReply(seq, None, status)
        if lost:
            raise TrackerLineError("a target-lost reply must not carry coordinates")
        p = np.array([float(m.group(k)) for k in (2, 3, 4)])
        return TrackerReply(seq, p, status)
    m = _ERROR.fullmatch(text)
    if m is not None:
        seq = int(m.group(1))
        if seq >= SEQ_MODULO:
            raise TrackerLineError(f"sequence number {seq} beyond {SEQ_MODULO - 1}")
        return TrackerReply(seq, None, STATUS_OK, error=m.group(2))
    raise TrackerLineError(f"not a $PT or $ER reply: {shown}")


def make_request(fiducial: int = 0) -> bytes:
    """The request line: the end point (``fiducial`` 0) or base nest ``fiducial`` (1..16).

    >>> make_request(), make_request(3)
    (b'MEAS\\n', b'MEAS F3\\n')
    """
    if isinstance(fiducial, bool) or not isinstance(fiducial, int):
        raise TrackerLineError(f"fiducial must be an integer, got {fiducial!r}")
    if fiducial == 0:
        return REQUEST_MEASURE
    if not 1 <= fiducial <= MAX_FIDUCIAL:
        raise TrackerLineError(f"fiducial {fiducial} outside 1..{MAX_FIDUCIAL}")
    return f"MEAS F{fiducial}\n".encode("ascii")


def parse_request_target(line: bytes) -> int | None:
    """What a request measures: 0 the end point, k base nest k; None if not a request.

    >>> parse_request_target(b"MEAS\\r\\n"), parse_request_target(b"MEAS F2\\n")
    (0, 2)
    >>> parse_request_target(b"MEAS F0\\n"), parse_request_target(b"MEAS F17\\n")
    (None, None)
    """
    text = line.rstrip(b"\r\n")
    if text == b"MEAS":
        return 0
    m = re.fullmatch(rb"MEAS F(\d{1,2})", text)
    if m is None or not 1 <= int(m.group(1)) <= MAX_FIDUCIAL:
        return None
    return int(m.group(1))


def parse_request(line: bytes) -> Request | None:
    """The request a line asks for (``\\n`` / ``\\r\\n`` stripped), None if unknown.

    >>> parse_request(b"MEAS\\r\\n"), parse_request(b"HELLO\\n")
    (<Request.MEASURE: 'MEAS'>, None)
    """
    text = line.rstrip(b"\r\n")
    for r in Request:
        if text == r.value.encode("ascii"):
            return r
    return None
