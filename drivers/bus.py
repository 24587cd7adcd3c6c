"""A bus port: sends frames under a lock and taps every frame into the bus's CAN log.

Each bus of the box is wrapped in a :class:`BusPort`.  Frames the host sends go through
its one send path (:meth:`BusPort.send`, :meth:`BusPort.send_many`,
:meth:`BusPort.send_batch`; a failed send raises :class:`BusSendError`, a
:class:`DriverError` naming the bus); frames it receives reach the bus's
:class:`drivers.canlog.TrafficLog` as a ``can.Listener``.  A bus that sends several
frames in one call (:class:`BatchSendingBus`, :class:`RecordSendingBus`: ``hrm_ipc``)
gets a cycle's frames in one call.

>>> bus = can.Bus(interface="virtual", channel="doc-port")
>>> port = BusPort("can0", bus)
>>> port.send_many([can.Message(arbitration_id=0x80, is_extended_id=False)] * 2)
>>> port.n_sent, isinstance(bus, BatchSendingBus)
(2, False)
>>> bus.shutdown()
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import can
import numpy as np

from drivers.canlog import (
    LOG_FORMAT_DURABILITY,
    LOG_FORMATS_ALWAYS,
    LogEntry,
    TrafficLog,
    ensure_log_dir,
    log_formats,
)
from drivers.protocol.batch import to_messages
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

__all__ = [  # the CAN log's names, from drivers.canlog, where callers have found them
    "ECHOING_INTERFACES",
    "LOG_FORMATS_ALWAYS",
    "LOG_FORMAT_DURABILITY",
    "BatchSendingBus",
    "BusPort",
    "BusSendError",
    "EchoLedger",
    "LogEntry",
    "RecordSendingBus",
    "TrafficLog",
    "ensure_log_dir",
    "is_host_frame",
    "log_formats",
]


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


class BusSendError(DriverError):
    """A frame could not be sent on a bus."""


EchoKey = tuple[int, bool, bool, bytes]
ECHO_WINDOW_S = 2.0  # an echo of our own frame comes back within this, or never
MAX_PENDING_ECHOES = 16384  # 36 frames x 100 Hz x 2 s = 7,200 in flight at most
ECHOING_INTERFACES = frozenset({"udp_multicast"})  # deliver a sender's frames back to it


def echo_key(msg: can.Message) -> EchoKey:
    """What identifies a frame on the wire: identifier, its format, RTR, the data."""
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, bytes(msg.data))


class EchoLedger:
    """The frames this process sent on one bus and that the bus will deliver back to it
    (udp_multicast does; virtual, SocketCAN without ``receive_own_messages`` and
    ``hrm_sim`` do not): an echo is recognised by identifier and data and taken off
    once; anything else received, even with a host-direction COB-ID, is someone else's.

    >>> led = EchoLedger()
    >>> m = can.Message(arbitration_id=0x201, data=bytes([15, 0]), is_extended_id=False)
    >>> led.add(m, now=0.0)
    >>> led.take(m, now=0.01), led.take(m, now=0.02)    # our echo once, then a stranger's
    (True, False)
    >>> sync = can.Message(arbitration_id=0x080, is_extended_id=False)
    >>> got = []
    >>> for k in range(1000):                           # 10 s of SYNCs, echoed 5 ms later
    ...     led.add(sync, now=k * 0.01)
    ...     got.append(led.take(sync, now=k * 0.01 + 0.005))
    >>> all(got), led.take(sync, now=10.0)
    (True, False)
    """

    def __init__(self) -> None:
        self._pending: dict[EchoKey, collections.deque[float]] = {}
        self._order: collections.deque[tuple[float, EchoKey]] = collections.deque()
        self._lock = threading.Lock()
        self.n_echoes = 0

    def add(self, msg: can.Message, now: float) -> None:
        key = echo_key(msg)
        with self._lock:
            self._expire(now)
            if len(self._order) >= MAX_PENDING_ECHOES:
                self._pop_oldest()
            self._pending.setdefault(key, collections.deque()).append(now)
            self._order.append((now, key))

    def discard(self, msg: can.Message) -> None:
        """A frame that was not sent after all (the send failed)."""
        key = echo_key(msg)
        with self._lock:
            times = self._pending.get(key)
            if times:
                times.pop()
                if not times:
                    del self._pending[key]

    def take(self, msg: can.Message, now: float) -> bool:
        """Whether ``msg`` is the echo of a frame we sent (then it is taken off)."""
        key = echo_key(msg)
        with self._lock:
            self._expire(now)
            times = self._pending.get(key)
            if not times:
                return False
            times.popleft()
            if not times:
                del self._pending[key]
            self.n_echoes += 1
            return True

    def _pop_oldest(self) -> None:
        """Forget the oldest frame sent, unless its echo already came back (then the
        key's oldest pending time is later than this entry's)."""
        t, key = self._order.popleft()
        times = self._pending.get(key)
        if times and times[0] <= t:
            times.popleft()
            if not times:
                del self._pending[key]

    def _expire(self, now: float) -> None:
        while self._order and now - self._order[0][0] > ECHO_WINDOW_S:
            self._pop_oldest()


@runtime_checkable
class BatchSendingBus(Protocol):
    """A bus that sends several frames in one call, in order (``hrm_ipc``: one datagram
    per peer)."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None: ...

    def send_many(self, msgs: Sequence[can.Message], timeout: float | None = None) -> None: ...


@runtime_checkable
class RecordSendingBus(BatchSendingBus, Protocol):
    """A :class:`BatchSendingBus` that also sends a record array of frames
    (:data:`drivers.protocol.batch.FRAME_DTYPE`) as it is, stamping the records with the
    send time in place (``hrm_ipc``: no Python object per frame)."""

    def send_batch(self, frames: np.ndarray, timeout: float | None = None) -> None: ...


class BusPort:
    """One opened CAN bus of the box: a name, a send lock, an optional log tap, and
    (on a bus that delivers our own frames back) the ledger of frames sent.

    One send path: every frame goes out through :meth:`_send` (stamped, entered in the
    echo ledger, sent in one call on a :class:`BatchSendingBus` or frame by frame,
    counted and logged as sent), except a record array on a :class:`RecordSendingBus`
    without echoes, which :meth:`send_batch` hands over as it is."""

    def __init__(
        self, name: str, bus: can.BusABC, log: TrafficLog | None = None, echoes: bool = False
    ) -> None:
        self.name = name
        self.bus = bus
        self.log = log
        self.echoes = EchoLedger() if echoes else None
        self._lock = threading.Lock()
        self.n_sent = 0
        self._many: BatchSendingBus | None = bus if isinstance(bus, BatchSendingBus) else None
        # records go out as they are where no echo must be told from a stranger's frame
        self._records: RecordSendingBus | None = (
            bus if isinstance(bus, RecordSendingBus) and not echoes else None
        )

    def is_own_echo(self, msg: can.Message) -> bool:
        """Whether a received frame is one this process sent, coming back."""
        return self.echoes is not None and self.echoes.take(msg, time.monotonic())

    def send(self, msg: can.Message, timeout_s: float = 0.05) -> None:
        """Send one frame; raise :class:`BusSendError` naming the bus and the frame."""
        self._send([msg], timeout_s, keep_going=False)

    def send_many(
        self, msgs: Sequence[can.Message], timeout_s: float = 0.05, keep_going: bool = False
    ) -> None:
        """Send frames in order under one lock acquisition: in one call of a
        :class:`BatchSendingBus` (``hrm_ipc``: one datagram per peer), else frame by
        frame.  ``keep_going`` (a quick stop's burst, frame by frame): a frame that fails
        does not hold back the ones after it, ``timeout_s`` bounds the whole batch (not
        each frame), and the failures are raised together after the last frame."""
        self._send(msgs, timeout_s, keep_going)

    def send_batch(
        self, frames: np.ndarray, timeout_s: float = 0.05, keep_going: bool = False
    ) -> None:
        """Send a batch of frames (a :data:`drivers.protocol.batch.FRAME_DTYPE` array, its
        timestamps set here) in order: as one record array on a :class:`RecordSendingBus`
        (no Python object per frame), else as ``can.Message`` objects (:meth:`send_many`).
        Logged as sent.  ``keep_going``: see :meth:`send_many`."""
        records = self._records
        if records is None:
            self._send(to_messages(frames, is_rx=False), timeout_s, keep_going)
            return
        try:  # the bus stamps the frames with the send time (what the log gets too)
            with self._lock:
                records.send_batch(frames, timeout=timeout_s)
                self.n_sent += len(frames)
                if self.log is not None:
                    self.log.log_batch(frames, is_rx=False)
        except (can.CanError, OSError, ValueError) as exc:
            raise BusSendError(f"bus {self.name}: send failed ({exc})") from None

    def _send(self, msgs: Sequence[can.Message], timeout_s: float, keep_going: bool) -> None:
        """The send path of frames as messages, under the lock: each frame stamped
        (``time.time()``, ``is_rx=False``) and entered in the echo ledger before it goes
        (the echo may beat the return) and taken out again when its send fails; sent in
        one call of a :class:`BatchSendingBus` (unless ``keep_going``), else frame by frame
        (each waits up to ``timeout_s`` and the first failure ends the batch; with
        ``keep_going`` every frame is tried, all within ``timeout_s``, the failures raised
        together at the end); what went out counted and logged.  A failure names the bus,
        and the frame when one frame was sent or ``keep_going`` names the failed ones."""
        now = time.time()
        echoes = self.echoes
        mono = time.monotonic()
        log_ = self.log
        many = self._many
        failed: list[str] = []
        with self._lock:
            for msg in msgs:
                msg.timestamp = now
                msg.is_rx = False
                if echoes is not None:
                    echoes.add(msg, mono)
            if many is not None and len(msgs) > 1:
                try:
                    many.send_many(msgs, timeout=timeout_s)
                except BaseException as exc:
                    if echoes is not None:
                        for msg in msgs:
                            echoes.discard(msg)
                    if isinstance(exc, can.CanError | OSError | ValueError):
                        raise BusSendError(f"bus {self.name}: send failed ({exc})") from None
                    raise
                self.n_sent += len(msgs)
                if log_ is not None:
                    for msg in msgs:
                        log_.log_sent(msg)
                return
            deadline = mono + timeout_s
            for k, msg in enumerate(msgs):
                wait_s = max(0.0, deadline - time.monotonic()) if keep_going else timeout_s
                try:
                    self.bus.send(msg, timeout=wait_s)
                except BaseException as exc:
                    refused = isinstance(exc, can.CanError | OSError | ValueError)
                    stop = not (keep_going and refused)  # the frames after it are not sent
                    if echoes is not None:
                        for m in msgs[k:] if stop else (msg,):
                            echoes.discard(m)
                    if not refused:
                        raise
                    if stop:
                        what = f"send of 0x{msg.arbitration_id:03X}" if len(msgs) == 1 else "send"
                        raise BusSendError(f"bus {self.name}: {what} failed ({exc})") from None
                    failed.append(f"0x{msg.arbitration_id:03X} ({exc})")
                    continue
                self.n_sent += 1
                if log_ is not None:
                    log_.log_sent(msg)
        if failed:
            more = f" (+{len(failed) - 1} more)" if len(failed) > 1 else ""
            raise BusSendError(f"bus {self.name}: send of {failed[0]} failed{more}")
