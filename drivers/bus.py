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
import os
import threading
import time
from pathlib import Path
from typing import Any

import can

from drivers.protocol.cia301 import (
    COB_NMT,
    COB_NMT_ERROR_CONTROL,
    COB_RPDO1,
    COB_RPDO2,
    COB_RPDO3,
    COB_RPDO4,
    COB_SDO_RX,
    COB_SYNC,
    HOST_HEARTBEAT_NODE_ID,
)
from hrm_ctrl.errors import DriverError

LOG_SUFFIXES = (".asc", ".blf")
WRITER_IDLE_S = 0.05

# COB-ID ranges the host transmits (CiA 301 predefined connection set): NMT, SYNC,
# RPDO1..4 (0x200/0x300/0x400/0x500 + node), SDO client -> server (0x600 + node).
_HOST_RANGES = (
    (COB_NMT, COB_NMT),
    (COB_SYNC, COB_SYNC),
    (COB_RPDO1, COB_RPDO1 + 0x7F),
    (COB_RPDO2, COB_RPDO2 + 0x7F),
    (COB_RPDO3, COB_RPDO3 + 0x7F),
    (COB_RPDO4, COB_RPDO4 + 0x7F),
    (COB_SDO_RX, COB_SDO_RX + 0x7F),
)


def is_host_frame(cob_id: int, host_node_id: int = HOST_HEARTBEAT_NODE_ID) -> bool:
    """Whether an 11-bit COB-ID is one the host sends (not a drive).

    >>> [is_host_frame(x) for x in (0x000, 0x080, 0x201, 0x57F, 0x601, 0x77F)]
    [True, True, True, True, True, True]
    >>> [is_host_frame(x) for x in (0x081, 0x181, 0x281, 0x581, 0x701, 0x77E)]
    [False, False, False, False, False, False]
    """
    if cob_id == COB_NMT_ERROR_CONTROL + host_node_id:
        return True
    return any(lo <= cob_id <= hi for lo, hi in _HOST_RANGES)


def ensure_log_dir(path: str | Path) -> Path:
    """Create the log directory if needed; a one-line :class:`DriverError` naming it
    when it is not a directory or cannot be created or written.

    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "file"
    >>> _ = f.write_text("")
    >>> ensure_log_dir(f)
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.DriverError: log directory ... exists and is not a directory
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise DriverError(f"log directory {p}: exists and is not a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DriverError(f"log directory {p}: cannot create it ({exc.strerror or exc})") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise DriverError(f"log directory {p}: not writable")
    return p


class BusSendError(DriverError):
    """A frame could not be sent on a bus."""


class TrafficLog(can.Listener):
    """Thread-safe python-can log of one bus: received frames (listener) and sent
    frames (:meth:`log_sent`), written by a background thread in arrival order.

    Only frames a drive sends are logged on receive: a host-direction frame coming
    back (udp_multicast echoes a sender's own frames) is dropped and counted in
    ``n_echoes``, since the host logged it when it sent it (:func:`is_host_frame`)."""

    def __init__(
        self, path: str | Path, channel: int = 1, host_node_id: int = HOST_HEARTBEAT_NODE_ID
    ) -> None:
        self.path = Path(path)
        self.channel = int(channel)  # channel number written in the log (1-based, as in CANalyzer)
        self.host_node_id = int(host_node_id)
        self.write_errors = 0
        self.first_error: str | None = None
        self.n_echoes = 0
        self._sent_heartbeat_ids: set[int] = set()
        if self.path.suffix.lower() not in LOG_SUFFIXES:
            raise DriverError(f"{self.path}: CAN log must end in {' or '.join(LOG_SUFFIXES)}")
        ensure_log_dir(self.path.parent)
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
        cob_id = msg.arbitration_id
        if not msg.is_extended_id and (
            is_host_frame(cob_id, self.host_node_id) or cob_id in self._sent_heartbeat_ids
        ):
            self.n_echoes += 1  # our own frame back (udp_multicast): logged when sent
            return
        # Interfaces name channels freely (a virtual bus: any string); logs want a number.
        msg.channel = self.channel
        self._queue.append(msg)

    def log_sent(self, msg: can.Message) -> None:
        """Record a frame the host sent (``is_rx=False``)."""
        cob_id = msg.arbitration_id
        if COB_NMT_ERROR_CONTROL < cob_id <= COB_NMT_ERROR_CONTROL + 0x7F:
            self._sent_heartbeat_ids.add(cob_id)  # the host's heartbeat, whatever its id
        msg.channel = self.channel
        self._queue.append(msg)

    def _failed(self, text: str) -> None:
        self.write_errors += 1
        if self.first_error is None:
            self.first_error = text

    def _drain(self) -> None:
        q = self._queue
        write = self._writer.on_message_received
        while q:
            msg = q.popleft()
            try:
                write(msg)
                self.n_frames += 1
            except Exception as exc:  # one bad frame must not end the log
                self._failed(f"{self.path.name}: cannot log {msg} ({exc})")

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
        if self._thread.is_alive():  # the disk hangs: do not write from two threads
            self._failed(f"{self.path.name}: writer still busy after 10 s")
            return
        self._drain()
        try:
            self._writer.stop()
        except Exception as exc:  # flush/close failed (disk full, I/O error)
            self._failed(f"{self.path.name}: cannot close ({exc})")


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
