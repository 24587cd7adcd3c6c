"""The simulated tension-sensor board: one tension per rope, framed, on a pseudo-terminal.

The board streams frames at ``rate_hz`` (default 100 Hz) on the master side of
a pseudo-terminal; the host opens the slave path (:attr:`TensionBoard.port`)
with pyserial exactly as it would open a USB serial adapter.  The protocol
(specified in ``docs/sim.md``; the host parser is ``drivers/tension_sensor.py``):

====== ==== ===============================================================
offset size field (little-endian)
====== ==== ===============================================================
0      2    sync ``A5 5A``
2      1    frame type ``01`` (tension sample)
3      1    payload length L = 8 + 2·n
4      2    sequence number (u16, wraps)
6      4    board time (u32, µs, wraps)
10     1    n, number of ropes
11     1    flags (bit 0: a channel saturated, bit 1: a channel invalid)
12     2·n  tension of rope k (u16, 0.01 N; ``FFFF`` = channel invalid)
4+L    2    CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 2 .. 3+L
====== ==== ===============================================================

>>> make_tension_frame(1, 1000, [30.0, 0.0]).hex()
'a55a010c0100e80300000200b80b00000618'
>>> crc16_ccitt(b"123456789") == 0x29B1
True
"""

from __future__ import annotations

import binascii
import os
import struct
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np

from hrm_ctrl.errors import SimError
from sim_bus.pty_device import PtyDevice

SYNC = b"\xa5\x5a"
FRAME_TENSION = 0x01
HEADER = struct.Struct("<HIBB")  # seq, board time µs, n, flags
TENSION_LSB_N = 0.01
TENSION_INVALID = 0xFFFF
FLAG_SATURATED = 0x01
FLAG_INVALID = 0x02
MAX_ROPES = (255 - HEADER.size) // 2


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor): the
    standard library's ``binascii.crc_hqx`` (C; the bitwise loop it replaced cost the
    board ~50 us a frame in the interpreter the host shares)."""
    return binascii.crc_hqx(data, crc)


def make_tension_frame(
    seq: int, board_time_us: int, tensions_N: Sequence[float] | np.ndarray, flags: int = 0
) -> bytes:
    """One tension frame (see the module docstring); NaN tensions are sent invalid."""
    t = np.asarray(tensions_N, dtype=float)
    if t.ndim != 1 or not 1 <= t.size <= MAX_ROPES:
        raise SimError(f"tension frame needs 1..{MAX_ROPES} ropes, got shape {t.shape}")
    raw = np.round(np.nan_to_num(t, nan=-1.0) / TENSION_LSB_N)
    invalid = ~np.isfinite(t) | (t < 0)
    saturated = raw >= TENSION_INVALID
    raw = np.clip(raw, 0, TENSION_INVALID - 1).astype("<u2")
    raw[invalid] = TENSION_INVALID
    flags |= (FLAG_SATURATED if saturated.any() else 0) | (FLAG_INVALID if invalid.any() else 0)
    payload = HEADER.pack(seq & 0xFFFF, board_time_us & 0xFFFFFFFF, t.size, flags) + raw.tobytes()
    body = bytes((FRAME_TENSION, len(payload))) + payload
    return SYNC + body + struct.pack("<H", crc16_ccitt(body))


class TensionBoard(PtyDevice):
    """A board thread writing frames from ``source()`` (tensions, N) to a pseudo-terminal.

    Fault hooks: :meth:`set_silent` (stops sending), :meth:`inject_garbage` (random
    bytes between frames), :meth:`corrupt_frames` (next frames with a bad CRC).
    """

    THREAD_NAME = "tension-board"

    def __init__(
        self,
        source: Callable[[], np.ndarray],
        rate_hz: float = 100.0,
        *,
        seed: int = 0,
    ) -> None:
        if not 0 < rate_hz <= 10_000:
            raise SimError(f"tension board rate must be in (0, 10000] Hz, got {rate_hz!r}")
        super().__init__()
        self.source = source
        self.rate_hz = float(rate_hz)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._silent = False
        self._garbage_bytes = 0
        self._garbage_continuous = False
        self._corrupt = 0
        self.frames_sent = 0
        self.frames_dropped = 0
        self.errors: list[str] = []

    # ------------------------------------------------------------ faults
    def set_silent(self, silent: bool = True) -> None:
        """The board goes quiet (or talks again)."""
        with self._lock:
            self._silent = silent

    def inject_garbage(self, n_bytes: int = 64, continuous: bool = False) -> None:
        """Write ``n_bytes`` random bytes before the next frame (each frame if continuous)."""
        with self._lock:
            self._garbage_bytes = int(n_bytes)
            self._garbage_continuous = continuous

    def corrupt_frames(self, count: int = 1) -> None:
        """The next ``count`` frames go out with a wrong CRC."""
        with self._lock:
            self._corrupt = int(count)

    # ------------------------------------------------------------ engine
    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        t0 = time.monotonic()
        k = 0
        while not self._stop.is_set():
            k += 1
            deadline = t0 + k * period
            delay = deadline - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                break
            if delay < -period:  # fell behind: skip, keep the schedule
                k = int((time.monotonic() - t0) / period)
            with self._lock:
                silent = self._silent
                garbage = self._garbage_bytes
                if not self._garbage_continuous:
                    self._garbage_bytes = 0
                corrupt = self._corrupt > 0
                self._corrupt = max(0, self._corrupt - 1)
            if silent:
                continue
            try:
                tensions = np.asarray(self.source(), dtype=float)
                frame = make_tension_frame(k, int((time.monotonic() - t0) * 1e6), tensions)
            except Exception as exc:  # the board keeps running; the host sees silence
                if len(self.errors) < 100:
                    self.errors.append(repr(exc))
                continue
            if corrupt:
                frame = frame[:-1] + bytes(((frame[-1] ^ 0x5A),))
            if garbage:
                frame = self._rng.integers(0, 256, garbage, dtype=np.uint8).tobytes() + frame
            try:
                os.write(self._master, frame)
                self.frames_sent += 1
            except (BlockingIOError, OSError):
                self.frames_dropped += 1  # nobody reading: the line buffer is full
