"""Host-side reader of the laser tracker (serial line, pyserial): measured end points.

The tracker measures the arm's end point (a reflector on it) in its own frame; the
protocol (request ``MEAS``, reply ``$PT,...``) is :mod:`drivers.protocol.tracker`, its
description in ``docs/sim.md``.  :class:`TrackerReader` asks for one reading at a time and
waits for the reply line at most ``timeout_s``; :meth:`TrackerReader.measure` averages
``n`` readings.  No reply in time, a reply that does not parse (garbage, a bad checksum),
an error reply or a lost target raise one :class:`TrackerError` line naming the port
(:class:`TrackerTargetLostError` for the lost target, which a caller may retry after
re-locking the tracker).

Before each request the reader drops whatever waits in its input buffer (a reply that
came after an earlier timeout is never taken for the next one's).

Usage (``port`` a serial device, or the simulated instrument's pseudo-terminal)::

    with TrackerReader(port, timeout_s=1.0) as tracker:
        p = tracker.measure(10)         # (3,) mm, tracker frame, mean of 10 readings
"""

from __future__ import annotations

import math
import time

import numpy as np

from drivers.config import TRACKER_TIMEOUT_RANGE_S
from drivers.protocol.tracker import (
    MAX_LINE_BYTES,
    TrackerLineError,
    TrackerReply,
    make_request,
    parse_reply,
)
from hrm_ctrl.errors import DriverError

DEFAULT_BAUDRATE = 115_200
TIMEOUT_RANGE_S = TRACKER_TIMEOUT_RANGE_S  # each reply: the [tracker] table's safe range
MAX_READINGS = 10_000  # one measure() call; at ~100 readings/s a hundred seconds


class TrackerError(DriverError):
    """The laser tracker cannot be opened, does not answer, or answers unusable data."""


class TrackerTargetLostError(TrackerError):
    """The tracker answered but has lost its target (the beam is broken)."""


class TrackerReader:
    """A laser tracker on serial ``port``; opens the port at once, a context manager.

    ``timeout_s`` (in :data:`TIMEOUT_RANGE_S`) bounds the wait for each reply.
    """

    def __init__(self, port: str, timeout_s: float = 1.0, *, baudrate: int = DEFAULT_BAUDRATE):
        lo, hi = TIMEOUT_RANGE_S
        if not (isinstance(timeout_s, int | float) and lo <= timeout_s <= hi):  # NaN fails too
            raise TrackerError(
                f"tracker {port}: timeout_s must be in [{lo:g}, {hi:g}] s, got {timeout_s!r}"
            )
        import serial  # pyserial

        self.port = str(port)
        self.timeout_s = float(timeout_s)
        self.readings = 0  # replies with a point received
        self.last_seq: int | None = None
        try:
            self._serial = serial.Serial(self.port, int(baudrate), timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TrackerError(f"tracker {self.port}: cannot open ({exc})") from None

    def close(self) -> None:
        ser, self._serial = self._serial, None
        if ser is not None:
            ser.close()

    def __enter__(self) -> TrackerReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _fail(self, text: str, kind: type[TrackerError] = TrackerError) -> TrackerError:
        return kind(f"tracker {self.port}: {text}")

    def _read_line(self) -> bytes:
        """One line (up to ``\\n``), at most :data:`MAX_LINE_BYTES`, within ``timeout_s``."""
        ser = self._serial
        deadline = time.monotonic() + self.timeout_s
        buf = bytearray()
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            ser.timeout = left
            chunk = ser.read_until(b"\n", MAX_LINE_BYTES + 1 - len(buf))
            buf += chunk
            if buf.endswith(b"\n") or len(buf) > MAX_LINE_BYTES:
                return bytes(buf)
        if buf:
            raise self._fail(
                f"reply incomplete after {self.timeout_s:g} s ({len(buf)} bytes, no end of line)"
            )
        raise self._fail(f"no reply within {self.timeout_s:g} s")

    def read_one(self, fiducial: int = 0) -> TrackerReply:
        """Request one reading (of the end point, or of base nest ``fiducial`` >= 1) and
        return its reply (a point: ``point_mm`` is set)."""
        ser = self._serial
        if ser is None:
            raise self._fail("reader is closed")
        try:
            ser.reset_input_buffer()
            ser.write(make_request(fiducial))  # a bad fiducial number raises TrackerLineError
            ser.flush()
            line = self._read_line()
        except TrackerError:
            raise
        except Exception as exc:  # the port vanished (pyserial raises several kinds)
            raise self._fail(f"serial I/O failed ({exc})") from None
        try:
            reply = parse_reply(line)
        except TrackerLineError as exc:
            raise self._fail(f"bad reply ({exc})") from None
        self.last_seq = reply.seq
        if reply.error is not None:
            raise self._fail(f"refused the request (error {reply.error})")
        if reply.target_lost or reply.point_mm is None:
            raise self._fail("target lost", TrackerTargetLostError)
        self.readings += 1
        return reply

    def measure(self, n: int = 1, fiducial: int = 0) -> np.ndarray:
        """The mean of ``n`` readings (3,), mm in the tracker's frame, of the end point or
        of base nest ``fiducial``; any failed reading raises (no partial mean)."""
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_READINGS:
            raise self._fail(f"readings per measurement must be 1..{MAX_READINGS}, got {n!r}")
        total = np.zeros(3)
        for _ in range(n):
            p = self.read_one(fiducial).point_mm
            total += p  # type: ignore[operator]
        mean = total / n
        if not all(math.isfinite(float(v)) for v in mean):
            raise self._fail("readings are not finite")
        return mean
