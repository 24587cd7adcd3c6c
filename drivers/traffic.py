"""A bus port: sends frames under a lock and taps every frame into a python-can log.

Each bus of the box is wrapped in a :class:`BusPort`.  Frames the host sends go
through :meth:`BusPort.send` (a failed send raises :class:`BusSendError`, a
:class:`DriverError` naming the bus); frames it receives reach the
:class:`TrafficLog` as a ``can.Listener``.  The log is written by a background
thread so the control cycle never waits for the disk; any format ``can.Logger``
knows works (``.asc`` and ``.blf`` are the usual ones, read back by
``can.LogReader``).

>>> import tempfile, pathlib
>>> path = pathlib.Path(tempfile.mkdtemp()) / "doc.asc"
>>> log = TrafficLog(path)
>>> log.on_message_received(can.Message(arbitration_id=0x181, data=b"\\x01", timestamp=1.0))
>>> log.stop()
>>> [hex(m.arbitration_id) for m in can.LogReader(path)]
['0x181']
"""

from __future__ import annotations

import collections
import threading
import time
from pathlib import Path
from typing import Any

import can

from hrm_ctrl.errors import DriverError

LOG_SUFFIXES = (".asc", ".blf")
WRITER_IDLE_S = 0.05


class BusSendError(DriverError):
    """A frame could not be sent on a bus."""


class TrafficLog(can.Listener):
    """Thread-safe python-can log of one bus: received frames (listener) and sent
    frames (:meth:`log_sent`), written by a background thread in arrival order."""

    def __init__(self, path: str | Path, channel: int = 1) -> None:
        self.path = Path(path)
        self.channel = int(channel)  # channel number written in the log (1-based, as in CANalyzer)
        self.write_errors = 0
        self.first_error: str | None = None
        if self.path.suffix.lower() not in LOG_SUFFIXES:
            raise DriverError(f"{self.path}: CAN log must end in {' or '.join(LOG_SUFFIXES)}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._writer: Any = can.Logger(str(self.path))
        except (OSError, ValueError) as exc:
            raise DriverError(f"{self.path}: cannot open CAN log ({exc})") from None
        self._queue: collections.deque[can.Message] = collections.deque()
        self._wake = threading.Event()
        self._stopping = False
        self.n_frames = 0
        self._thread = threading.Thread(
            target=self._run, name=f"canlog-{self.path.name}", daemon=True
        )
        self._thread.start()

    def on_message_received(self, msg: can.Message) -> None:
        # Interfaces name channels freely (a virtual bus: any string); logs want a number.
        msg.channel = self.channel
        self._queue.append(msg)

    def log_sent(self, msg: can.Message) -> None:
        """Record a frame the host sent (``is_rx=False``)."""
        msg.channel = self.channel
        self._queue.append(msg)

    def _drain(self) -> None:
        q = self._queue
        write = self._writer.on_message_received
        while q:
            msg = q.popleft()
            try:
                write(msg)
                self.n_frames += 1
            except Exception as exc:  # one bad frame must not end the log
                self.write_errors += 1
                if self.first_error is None:
                    self.first_error = f"{self.path.name}: cannot log {msg} ({exc})"

    def _run(self) -> None:
        while not self._stopping:
            self._wake.wait(WRITER_IDLE_S)
            self._wake.clear()
            self._drain()
        self._drain()

    def stop(self) -> None:
        """Write everything queued and close the file (idempotent)."""
        if self._stopping:
            return
        self._stopping = True
        self._wake.set()
        self._thread.join(timeout=10.0)
        self._drain()
        self._writer.stop()


class BusPort:
    """One opened CAN bus of the box: a name, a send lock and an optional log tap."""

    def __init__(self, name: str, bus: can.BusABC, log: TrafficLog | None = None) -> None:
        self.name = name
        self.bus = bus
        self.log = log
        self._lock = threading.Lock()
        self.n_sent = 0

    def send(self, msg: can.Message, timeout_s: float = 0.05) -> None:
        """Send one frame; raise :class:`BusSendError` naming the bus on failure."""
        msg.timestamp = time.time()
        msg.is_rx = False
        try:
            with self._lock:
                self.bus.send(msg, timeout=timeout_s)
        except (can.CanError, OSError, ValueError) as exc:
            raise BusSendError(
                f"bus {self.name}: send of 0x{msg.arbitration_id:03X} failed ({exc})"
            ) from None
        self.n_sent += 1
        if self.log is not None:
            self.log.log_sent(msg)

    def send_many(self, msgs: list[can.Message], timeout_s: float = 0.05) -> None:
        """Send frames in order under one lock acquisition."""
        now = time.time()
        try:
            with self._lock:
                for msg in msgs:
                    msg.timestamp = now
                    msg.is_rx = False
                    self.bus.send(msg, timeout=timeout_s)
                    self.n_sent += 1
                    if self.log is not None:
                        self.log.log_sent(msg)
        except (can.CanError, OSError, ValueError) as exc:
            raise BusSendError(f"bus {self.name}: send failed ({exc})") from None
