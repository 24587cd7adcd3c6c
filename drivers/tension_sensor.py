"""Host-side reader of the rope tension-sensor board (serial line, pyserial).

The board sends one frame per sample (protocol in ``docs/sim.md``):
``A5 5A | type 01 | L | seq u16 | board time u32 µs | n u8 | flags u8 |
n x u16 tension (0.01 N, FFFF invalid) | CRC-16/CCITT-FALSE of type..payload``,
little-endian.  :class:`TensionFrameParser` turns a byte stream into samples
and resynchronises after garbage: it searches for the sync bytes, checks type,
length and CRC, and on any mismatch drops one byte and searches again (counting
what it dropped, and each loss of synchronisation once as a resync).
:class:`TensionSensorReader` reads a serial port in a thread and hands out the
newest sample; :meth:`TensionSensorReader.latest`
raises :class:`StaleTensionError` when the newest sample is older than
``stale_after_s`` (board silent, cable pulled, only garbage arriving).
:class:`TensionWatch` turns a rope below its slack threshold or above its limit, a
stale sensor, or bad data past a rate into one stop cause naming the rope or the port.

>>> p = TensionFrameParser(n_ropes=2)
>>> frame = bytes.fromhex('a55a010c0100e80300000200b80b00000618')
>>> [s.tensions_N.tolist() for s in p.feed(b'\\x00\\xa5junk' + frame)]
[[30.0, 0.0]]
>>> p.garbage_bytes, p.frames, p.resyncs, p.bad_events
(6, 1, 0, 0)
>>> _ = p.feed(b'xx' + frame + b'y' + frame)   # two garbage runs after a good frame
>>> p.resyncs, p.bad_events
(2, 2)
"""

from __future__ import annotations

import binascii
import collections
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.errors import DriverError

SYNC = b"\xa5\x5a"
FRAME_TENSION = 0x01
HEADER = struct.Struct("<HIBB")
TENSION_LSB_N = 0.01
TENSION_INVALID = 0xFFFF
DEFAULT_BAUDRATE = 921_600
BAD_RATE_WINDOW_S = 1.0  # bad data is counted over the last second


class TensionSensorError(DriverError):
    """The tension-sensor board cannot be opened or sends unusable data."""


class StaleTensionError(TensionSensorError):
    """No valid tension sample for longer than the allowed age."""


@dataclass(frozen=True)
class TensionSample:
    """One decoded frame: tensions in N (NaN where the board marks a channel invalid)."""

    seq: int
    board_time_us: int
    flags: int
    tensions_N: np.ndarray
    received_s: float  # host monotonic time of reception


def crc16_ccitt(data: bytes) -> int:
    """CRC-16/CCITT-FALSE.

    >>> hex(crc16_ccitt(b'123456789'))
    '0x29b1'
    """
    return binascii.crc_hqx(data, 0xFFFF)


class TensionFrameParser:
    """Incremental frame parser with resynchronisation (pure: bytes in, samples out)."""

    def __init__(self, n_ropes: int | None = None, max_buffer: int = 4096) -> None:
        self.n_ropes = n_ropes
        self._buf = bytearray()
        self._max = max_buffer
        self.frames = 0
        self.garbage_bytes = 0
        self.crc_errors = 0
        self.wrong_count = 0
        self.resyncs = 0  # losses of synchronisation (a garbage run, however long)
        self._in_sync = True  # the last bytes consumed were a valid frame (or nothing yet)

    @property
    def bad_events(self) -> int:
        """CRC errors + losses of synchronisation + frames with the wrong rope count."""
        return self.crc_errors + self.resyncs + self.wrong_count

    def _garbage(self, n: int) -> None:
        if n <= 0:
            return
        if self._in_sync and self.frames + self.wrong_count > 0:
            self.resyncs += 1  # garbage before the first frame is the line coming up
        self._in_sync = False
        self.garbage_bytes += n

    def feed(self, data: bytes, now_s: float | None = None) -> list[TensionSample]:
        """Add received bytes; return every complete, valid frame (in order)."""
        now = time.monotonic() if now_s is None else now_s
        buf = self._buf
        buf += data
        out: list[TensionSample] = []
        while True:
            start = buf.find(SYNC)
            if start < 0:
                keep = 1 if buf.endswith(SYNC[:1]) else 0
                self._garbage(len(buf) - keep)
                del buf[: len(buf) - keep]
                break
            if start:
                self._garbage(start)
                del buf[:start]
            if len(buf) < 4:
                break
            ftype, length = buf[2], buf[3]
            if ftype != FRAME_TENSION or length < HEADER.size or (length - HEADER.size) % 2:
                self._skip()
                continue
            total = 4 + length + 2
            if len(buf) < total:
                break
            body = bytes(buf[2 : 4 + length])
            (crc,) = struct.unpack_from("<H", buf, 4 + length)
            if crc != crc16_ccitt(body):
                self.crc_errors += 1
                self._in_sync = False  # the bytes skipped now are this error, not a resync
                self._skip()
                continue
            seq, t_us, n, flags = HEADER.unpack_from(body, 2)
            if n * 2 != length - HEADER.size:
                self._skip()
                continue
            del buf[:total]
            self._in_sync = True
            raw = np.frombuffer(body, dtype="<u2", count=n, offset=2 + HEADER.size)
            tensions = np.where(raw == TENSION_INVALID, np.nan, raw * TENSION_LSB_N)
            if self.n_ropes is not None and n != self.n_ropes:
                self.wrong_count += 1
                continue
            self.frames += 1
            out.append(TensionSample(int(seq), int(t_us), int(flags), tensions, now))
        if len(buf) > self._max:
            self._garbage(len(buf) - self._max)
            del buf[: len(buf) - self._max]
        return out

    def _skip(self) -> None:
        self._garbage(1)
        del self._buf[:1]


class TensionSensorReader:
    """Reads the board on ``port`` in a thread; :meth:`latest` gives the newest sample.

    Every wait is bounded: the port is read with ``read_timeout_s``; ``latest``
    never blocks.  Use as a context manager.
    """

    def __init__(
        self,
        port: str,
        n_ropes: int,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        stale_after_s: float = 0.05,
        read_timeout_s: float = 0.01,
    ) -> None:
        if not stale_after_s > 0:
            raise TensionSensorError(f"stale_after_s must be > 0, got {stale_after_s!r}")
        self.port = port
        self.n_ropes = int(n_ropes)
        self.baudrate = int(baudrate)
        self.stale_after_s = float(stale_after_s)
        self.read_timeout_s = float(read_timeout_s)
        self.parser = TensionFrameParser(self.n_ropes)
        self._latest: TensionSample | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serial: object | None = None
        self.lost_frames = 0
        self.read_error: str | None = None

    def open(self) -> TensionSensorReader:
        import serial  # pyserial

        try:
            ser = serial.Serial(self.port, self.baudrate, timeout=self.read_timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TensionSensorError(f"tension sensor {self.port}: cannot open ({exc})") from None
        ser.reset_input_buffer()
        self._serial = ser
        self._thread = threading.Thread(target=self._run, name="tension-reader", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._serial is not None:
            self._serial.close()  # type: ignore[attr-defined]
            self._serial = None

    def __enter__(self) -> TensionSensorReader:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        ser = self._serial
        last_seq: int | None = None
        while not self._stop.is_set():
            try:
                data = ser.read(max(1, ser.in_waiting))  # type: ignore[attr-defined]
            except Exception as exc:  # port vanished: report through latest()
                self.read_error = str(exc)
                return
            if not data:
                continue
            for s in self.parser.feed(data):
                if last_seq is not None:
                    self.lost_frames += (s.seq - last_seq - 1) & 0xFFFF
                last_seq = s.seq
                with self._lock:
                    self._latest = s

    def latest(self, now_s: float | None = None) -> TensionSample:
        """The newest valid sample; :class:`StaleTensionError` if it is too old or missing."""
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            s = self._latest
        if self.read_error is not None:
            raise TensionSensorError(f"tension sensor {self.port}: read failed ({self.read_error})")
        if s is None:
            raise StaleTensionError(
                f"tension sensor {self.port}: no valid frame yet "
                f"({self.parser.garbage_bytes} garbage bytes, {self.parser.crc_errors} CRC errors)"
            )
        age = now - s.received_s
        if age > self.stale_after_s:
            raise StaleTensionError(
                f"tension sensor {self.port}: newest frame is {age * 1000:.0f} ms old "
                f"(limit {self.stale_after_s * 1000:.0f} ms)"
            )
        return s


def check_tensions(
    sample: TensionSample, motor_ids: tuple[str, ...] | list[str], min_N: float, max_N: float
) -> str | None:
    """One-line reason when a rope's tension is invalid or outside [min_N, max_N], else None.

    >>> s = TensionSample(0, 0, 0, np.array([30.0, 0.2]), 0.0)
    >>> check_tensions(s, ["j01r0", "j01r1"], 5.0, 200.0)
    'rope j01r1: tension 0.2 N below 5 N (slack or broken)'
    """
    t = sample.tensions_N
    if t.shape != (len(motor_ids),):
        return f"tension sample has {t.size} ropes, expected {len(motor_ids)}"
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        return f"rope {motor_ids[int(bad[0])]}: tension channel invalid"
    low = np.flatnonzero(t < min_N)
    if low.size:
        i = int(low[0])
        return f"rope {motor_ids[i]}: tension {t[i]:.1f} N below {min_N:g} N (slack or broken)"
    high = np.flatnonzero(t > max_N)
    if high.size:
        i = int(high[0])
        return f"rope {motor_ids[i]}: tension {t[i]:.1f} N above {max_N:g} N"
    return None


class TensionWatch:
    """Watchdog thread: every ``period_s`` it checks the reader's newest sample and calls
    ``on_fault(text)`` once (then stops) when the data is stale, a tension is outside
    ``[min_N, max_N]`` (the text names the rope), or the board's bad data (CRC errors,
    losses of synchronisation, wrong-size frames: :attr:`TensionFrameParser.bad_events`)
    exceeds ``max_bad_per_s`` over the last :data:`BAD_RATE_WINDOW_S` (``None``: not
    checked).  ``grace_s`` after :meth:`start` a missing first frame is not yet a fault.
    """

    def __init__(
        self,
        reader: TensionSensorReader,
        motor_ids: tuple[str, ...] | list[str],
        on_fault: Callable[[str], None],
        *,
        min_N: float = 5.0,
        max_N: float = 500.0,
        max_bad_per_s: float | None = None,
        period_s: float = 0.01,
        grace_s: float = 0.5,
    ) -> None:
        self.reader = reader
        self.motor_ids = tuple(motor_ids)
        self.on_fault = on_fault
        self.min_N, self.max_N = float(min_N), float(max_N)
        self.max_bad_per_s = None if max_bad_per_s is None else float(max_bad_per_s)
        self.period_s = float(period_s)
        self.grace_s = float(grace_s)
        self.fault: str | None = None
        self.checks = 0
        self.min_seen_N = math.inf
        self.max_seen_N = -math.inf
        self.max_age_s = 0.0
        self._bad: collections.deque[tuple[float, int]] = collections.deque()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> TensionWatch:
        self._thread = threading.Thread(target=self._run, name="tension-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread.ident is not None:  # it did start
            self._thread.join(timeout=1.0)

    def bad_rate_problem(self, now: float) -> str | None:
        """Why the board's bad data is past the rate (one line), else None."""
        if self.max_bad_per_s is None:
            return None
        p = self.reader.parser
        total = p.bad_events
        self._bad.append((now, total))
        while self._bad and self._bad[0][0] < now - BAD_RATE_WINDOW_S:
            self._bad.popleft()
        n = total - self._bad[0][1]
        if n <= self.max_bad_per_s * BAD_RATE_WINDOW_S:
            return None
        return (
            f"tension sensor {self.reader.port}: {n} bad frames or garbage runs in the last "
            f"{BAD_RATE_WINDOW_S:g} s (limit {self.max_bad_per_s:g}/s; {p.crc_errors} CRC "
            f"errors, {p.garbage_bytes} garbage bytes so far)"
        )

    def check(self, now: float, started: float) -> str | None:
        """One check (the thread's work): a one-line fault, or None."""
        self.checks += 1
        text = self.bad_rate_problem(now)
        if text is not None:
            return text
        try:
            sample = self.reader.latest(now)
        except TensionSensorError as exc:
            if now - started < self.grace_s and self.reader.read_error is None:
                return None  # the first frames may still be on their way
            return str(exc)
        self.max_age_s = max(self.max_age_s, now - sample.received_s)
        t = sample.tensions_N
        if t.size and np.isfinite(t).all():
            self.min_seen_N = min(self.min_seen_N, float(t.min()))
            self.max_seen_N = max(self.max_seen_N, float(t.max()))
        return check_tensions(sample, self.motor_ids, self.min_N, self.max_N)

    def _run(self) -> None:
        t_start = time.monotonic()
        while not self._stop.wait(self.period_s):
            try:
                text = self.check(time.monotonic(), t_start)
            except Exception as exc:  # a watch that cannot look any more stops every axis
                text = f"tension watch failed: {exc!r}"
            if text is not None:
                self.fault = text
                self.on_fault(text)
                return

    def summary(self) -> dict[str, object]:
        """What the run record keeps: thresholds, traffic, extremes seen, the fault."""
        p = self.reader.parser
        return {
            "port": self.reader.port,
            "min_N": self.min_N,
            "max_N": self.max_N,
            "stale_s": self.reader.stale_after_s,
            "max_bad_per_s": self.max_bad_per_s,
            "checks": self.checks,
            "frames": p.frames,
            "lost_frames": self.reader.lost_frames,
            "crc_errors": p.crc_errors,
            "resyncs": p.resyncs,
            "wrong_count": p.wrong_count,
            "garbage_bytes": p.garbage_bytes,
            "lowest_N": self.min_seen_N if math.isfinite(self.min_seen_N) else None,
            "highest_N": self.max_seen_N if math.isfinite(self.max_seen_N) else None,
            "oldest_sample_ms": round(self.max_age_s * 1000.0, 3),
            "fault": self.fault,
        }
