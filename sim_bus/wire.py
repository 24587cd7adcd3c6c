"""A simulated CAN wire at real bitrate, as a python-can interface (``hrm_sim``).

Every :class:`SimWireBus` opened with the same ``channel`` in one process is a
node on one shared :class:`SimWire`.  The wire models classical CAN:

* a frame occupies the wire for its length in bits divided by the bitrate
  (:func:`drivers.protocol.frames.frame_bits`, the bus-load budget's count too);
  the length counts worst-case bit stuffing by default (``stuffing="worst"``,
  the figure bus-load budgets use: 135 bits for 8 data bytes with an 11-bit
  id) or the exact stuff bits of the frame's real bit pattern, CRC included
  (``stuffing="exact"``);
* when the wire becomes free, the pending frame with the lowest arbitration
  key wins (11-bit id before a 29-bit id with the same base id, data before
  remote); a frame sent onto an idle wire starts at once;
* a frame is copied at ``send`` (a sender may reuse its ``can.Message``); a node's
  transmit queue holds :data:`TX_QUEUE_FRAMES`, and a send finding it full waits up to
  its ``timeout`` (None: until there is room) before it raises;
* every other node receives a frame at the end of its wire time, stamped with
  that ideal end time; the sender does not get its own frame back unless it
  asked for ``receive_own_messages=True``.  No thread runs the wire: every
  ``send`` and ``recv`` moves it forward to "now", and a node waiting in
  ``recv`` sleeps until the next frame ends.

So a cycle that offers more bits than fit shows up as frames delivered late
(``SimWire.stats()["max_queue_delay_s"]``), and ``SimWire.bus_load()`` is the
fraction of wall time the wire was busy.  Fault hooks drop or delay frames
(:meth:`SimWire.drop`, :meth:`SimWire.delay`) or take the whole wire off the
bus (:meth:`SimWire.set_bus_off`: every ``send`` raises
``can.CanOperationError``, nothing is delivered).

>>> frame_bits(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
135
>>> frame_bits(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
55
>>> a = can.Bus(interface="hrm_sim", channel="doc-wire", bitrate=1_000_000)
>>> b = can.Bus(interface="hrm_sim", channel="doc-wire", bitrate=1_000_000)
>>> a.send(can.Message(arbitration_id=0x123, data=b"\\x01\\x02", is_extended_id=False))
>>> m = b.recv(timeout=1.0)
>>> hex(m.arbitration_id), bytes(m.data)
('0x123', b'\\x01\\x02')
>>> a.recv(timeout=0.01) is None                # no echo of one's own frame
True
>>> a.shutdown(); b.shutdown()
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import can
from can.bus import BusState, CanProtocol

from drivers.protocol.frames import Stuffing, frame_bits
from hrm_ctrl.errors import SimError

FrameMatch = Callable[[can.Message], bool]


#: Frames one node may have waiting for the wire, as a CAN controller's transmit queue (a
#: SocketCAN device's ``txqueuelen`` is 10 to 1000): one more waits for room as long as the
#: send's ``timeout`` allows, then raises ``can.CanOperationError`` ("transmit queue
#: full"), instead of growing without bound.
TX_QUEUE_FRAMES = 256
#: Frames a node's receive queue holds; when full the oldest go (counted in
#: ``SimWire.stats()["rx_dropped"]``), as a receive buffer overruns.
RX_QUEUE_FRAMES = 65_536


#: Longest single wait of a send for room in its transmit queue (s): the wait is re-checked
#: at least this often (bus off, shutdown), whatever the ``timeout``.
SEND_POLL_S = 0.05


def snapshot(msg: can.Message) -> can.Message:
    """A copy of the frame ``msg`` is now (id, flags, dlc, data): what the wire carries.

    >>> m = can.Message(arbitration_id=0x181, data=b"\\x01", is_extended_id=False)
    >>> s = snapshot(m)
    >>> m.arbitration_id, m.data[0] = 0x182, 9
    >>> hex(s.arbitration_id), bytes(s.data)
    ('0x181', b'\\x01')
    """
    return can.Message(
        timestamp=msg.timestamp,
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame,
        dlc=msg.dlc,
        data=bytes(msg.data),
        check=False,
    )


class WireConfigError(SimError):
    """Two nodes disagree about a wire (bitrate), or a wire parameter is invalid."""


def arbitration_key(msg: can.Message) -> tuple[int, int, int, int, int]:
    """Sort key: the frame that wins arbitration sorts first.

    >>> std = can.Message(arbitration_id=0x100, is_extended_id=False)
    >>> ext = can.Message(arbitration_id=0x100 << 18, is_extended_id=True)
    >>> arbitration_key(std) < arbitration_key(ext)
    True
    """
    rtr = 1 if msg.is_remote_frame else 0
    if msg.is_extended_id:
        return (msg.arbitration_id >> 18, 1, 1, msg.arbitration_id & 0x3FFFF, rtr)
    return (msg.arbitration_id, rtr, 0, 0, 0)


@dataclass
class _Rule:
    kind: Literal["drop", "delay"]
    match: FrameMatch | None
    remaining: int | None
    delay_s: float = 0.0

    def applies(self, msg: can.Message) -> bool:
        if self.remaining is not None and self.remaining <= 0:
            return False
        if self.match is not None and not self.match(msg):
            return False
        if self.remaining is not None:
            self.remaining -= 1
        return True


@dataclass
class _Pending:
    t_ready: float
    seq: int
    key: tuple[int, int, int, int, int]
    msg: can.Message
    sender: SimWireBus | None
    t_sent: float


class SimWire:
    """One simulated CAN wire (see the module docstring).  Obtain it with :func:`get_wire`
    or from ``bus.wire``; it lives while at least one :class:`SimWireBus` is open on it."""

    def __init__(
        self,
        channel: str,
        bitrate: int,
        stuffing: Stuffing | str = Stuffing.WORST,
    ) -> None:
        if not isinstance(bitrate, int) or bitrate <= 0:
            raise WireConfigError(
                f"hrm_sim channel {channel!r}: bitrate must be > 0, got {bitrate}"
            )
        try:
            mode = Stuffing(stuffing)
        except ValueError:
            raise WireConfigError(
                f"hrm_sim channel {channel!r}: stuffing must be 'worst' or 'exact'"
            ) from None
        self.channel = channel
        self.bitrate = bitrate
        self.stuffing = mode
        self._cond = threading.Condition()
        self._nodes: list[SimWireBus] = []
        self._pending: list[_Pending] = []
        self._in_flight: collections.deque[tuple[float, float, _Pending]] = collections.deque()
        self._free_at = 0.0
        self._seq = 0
        self._rules: list[_Rule] = []
        self._bus_off = False
        self._busy: collections.deque[tuple[float, float]] = collections.deque()
        self._wall_offset = time.time() - time.monotonic()
        self.frames_delivered = 0
        self.frames_dropped = 0
        self.rx_dropped = 0  # frames a node's full receive queue lost
        self.bits_sent = 0
        self.max_delivery_late_s = 0.0
        self.max_queue_delay_s = 0.0
        self._late_log: collections.deque[float] | None = None

    # ----------------------------------------------------------------- faults
    def drop(self, match: FrameMatch | None = None, count: int | None = 1) -> None:
        """Lose the next ``count`` frames matching ``match`` (all frames if ``None``;
        ``count=None``: every matching frame until :meth:`clear_faults`)."""
        with self._cond:
            self._rules.append(_Rule("drop", match, count))

    def delay(self, delay_s: float, match: FrameMatch | None = None, count: int | None = 1) -> None:
        """Hold the next ``count`` matching frames back ``delay_s`` before they contend."""
        if not delay_s >= 0.0:
            raise SimError(f"hrm_sim channel {self.channel!r}: delay must be >= 0 s")
        with self._cond:
            self._rules.append(_Rule("delay", match, count, float(delay_s)))

    def set_bus_off(self, off: bool = True) -> None:
        """Take the wire off the bus (pending frames are lost, sends raise) or back on."""
        with self._cond:
            self._bus_off = bool(off)
            if off:
                self.frames_dropped += len(self._pending) + len(self._in_flight)
                self._pending.clear()
                self._in_flight.clear()
                for node in self._nodes:
                    node._tx_pending = 0
            self._cond.notify_all()

    def clear_faults(self) -> None:
        """Remove every drop/delay rule (bus-off stays as set)."""
        with self._cond:
            self._rules.clear()

    @property
    def bus_off(self) -> bool:
        return self._bus_off

    # ------------------------------------------------------------- statistics
    def bus_load(self, window_s: float = 1.0) -> float:
        """Fraction of the last ``window_s`` seconds the wire carried bits (0..1)."""
        now = time.monotonic()
        t0 = now - window_s
        busy = 0.0
        with self._cond:
            self._advance(now)
            for start, end in self._busy:
                lo, hi = max(start, t0), min(end, now)
                if hi > lo:
                    busy += hi - lo
        return busy / window_s

    def record_lateness(self, enabled: bool = True, maxlen: int = 1_000_000) -> None:
        """Keep each delivered frame's lateness (delivery - ideal end, s) for benchmarks."""
        with self._cond:
            self._late_log = collections.deque(maxlen=maxlen) if enabled else None

    def lateness_log(self) -> list[float]:
        with self._cond:
            return list(self._late_log) if self._late_log is not None else []

    def stats(self) -> dict[str, Any]:
        """Counters: frames delivered/dropped, bits, worst delivery lateness and queueing."""
        with self._cond:
            self._advance(time.monotonic())
            return {
                "channel": self.channel,
                "bitrate": self.bitrate,
                "stuffing": self.stuffing,
                "frames_delivered": self.frames_delivered,
                "frames_dropped": self.frames_dropped,
                "rx_dropped": self.rx_dropped,
                "bits_sent": self.bits_sent,
                "max_delivery_late_s": self.max_delivery_late_s,
                "max_queue_delay_s": self.max_queue_delay_s,
                "bus_off": self._bus_off,
                "nodes": len(self._nodes),
            }

    # ---------------------------------------------------------------- nodes
    def _attach(self, node: SimWireBus) -> None:
        with self._cond:
            self._nodes.append(node)

    def _detach(self, node: SimWireBus) -> bool:
        """Remove a node; True when the wire has no node left (and stops)."""
        with self._cond:
            if node in self._nodes:
                self._nodes.remove(node)
            for p in self._pending:
                if p.sender is node:
                    p.sender = None
            self._cond.notify_all()
            return not self._nodes

    def _submit(self, msg: can.Message, sender: SimWireBus, timeout: float | None) -> None:
        """Queue a copy of ``msg`` (the frame as it is now: a sender may reuse its object)
        for the wire; with the sender's transmit queue full, wait for room up to
        ``timeout`` s (None: until there is room; 0: not at all), then raise."""
        frame = snapshot(msg)
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        with self._cond:
            while True:
                now = time.monotonic()
                if self._bus_off:
                    raise can.CanOperationError(f"hrm_sim channel {self.channel!r}: bus off")
                if not sender._open:
                    raise can.CanOperationError("hrm_sim: cannot send on a closed bus")
                next_event = self._advance(now)
                if sender._tx_pending < TX_QUEUE_FRAMES:
                    break
                if deadline is not None and now >= deadline:
                    raise can.CanOperationError(
                        f"hrm_sim channel {self.channel!r}: transmit queue full "
                        f"({TX_QUEUE_FRAMES} frames waiting for the wire)"
                    )
                # the queue drains as the wire runs: wake at its next event (a bounded
                # wait; another node's send or recv may run the wire first and notify)
                waits = [max(0.0, t - now) for t in (next_event, deadline) if t is not None]
                self._cond.wait(min([SEND_POLL_S, *waits]))
            t_ready = now
            for rule in self._rules:
                if rule.applies(frame):
                    if rule.kind == "drop":
                        self.frames_dropped += 1
                        return
                    t_ready += rule.delay_s
            sender._tx_pending += 1
            self._seq += 1
            self._pending.append(
                _Pending(t_ready, self._seq, arbitration_key(frame), frame, sender, now)
            )
            self._advance(now)
            self._cond.notify_all()  # waiting receivers recompute when to wake

    # ---------------------------------------------------------------- engine
    def _schedule(self, now: float) -> float | None:
        """Commit arbitration decisions up to ``now``; return the next decision time."""
        while self._pending:
            earliest = min(p.t_ready for p in self._pending)
            slot = max(self._free_at, earliest)
            if slot > now:
                return slot
            winner = min(
                (p for p in self._pending if p.t_ready <= slot), key=lambda p: (p.key, p.seq)
            )
            self._pending.remove(winner)
            if winner.sender is not None:
                winner.sender._tx_pending -= 1
            bits = frame_bits(winner.msg, self.stuffing)
            end = slot + bits / self.bitrate
            self._free_at = end
            self.bits_sent += bits
            self.max_queue_delay_s = max(self.max_queue_delay_s, slot - winner.t_ready)
            self._in_flight.append((slot, end, winner))
            self._busy.append((slot, end))
            while self._busy and self._busy[0][1] < now - 10.0:
                self._busy.popleft()
        return None

    def _deliver(self, now: float) -> int:
        """Hand every frame whose wire time ended by ``now`` to the other nodes."""
        n = 0
        while self._in_flight and self._in_flight[0][1] <= now:
            _start, end, p = self._in_flight.popleft()
            late = now - end
            self.max_delivery_late_s = max(self.max_delivery_late_s, late)
            if self._late_log is not None:
                self._late_log.append(late)
            self.frames_delivered += 1
            n += 1
            stamp = end + self._wall_offset
            src = p.msg
            for node in self._nodes:
                own = node is p.sender
                if own and not node.receive_own_messages:
                    continue
                if len(node._rx) >= RX_QUEUE_FRAMES:  # the deque's maxlen drops the oldest
                    self.rx_dropped += 1
                node._rx.append(
                    can.Message(
                        timestamp=stamp,
                        arbitration_id=src.arbitration_id,
                        is_extended_id=src.is_extended_id,
                        is_remote_frame=src.is_remote_frame,
                        is_error_frame=src.is_error_frame,
                        dlc=src.dlc,
                        data=bytes(src.data),
                        channel=self.channel,
                        is_rx=not own,
                        check=False,
                    )
                )
        return n

    def _advance(self, now: float) -> float | None:
        """Run the wire up to ``now`` (caller holds the lock); return the time of the next
        event (a frame's end or an arbitration decision), None when the wire is idle."""
        next_slot = self._schedule(now)
        if self._deliver(now):
            self._cond.notify_all()
        times = [t for t in (next_slot,) if t is not None]
        if self._in_flight:
            times.append(self._in_flight[0][1])
        return min(times) if times else None

    def _receive(self, node: SimWireBus, timeout: float | None) -> can.Message | None:
        """Next frame for ``node``, waiting at most ``timeout`` s (None: forever).

        There is no wire thread: whichever node sends or waits runs the wire forward, and a
        waiting node sleeps exactly until the next frame ends (or a send changes the plan).
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                now = time.monotonic()
                next_event = self._advance(now)
                if node._rx:
                    return node._rx.popleft()
                if not node._open:
                    return None
                waits = [t - now for t in (next_event, deadline) if t is not None]
                if deadline is not None and deadline <= now:
                    return None
                self._cond.wait(max(0.0, min(waits)) if waits else None)


_wires: dict[str, SimWire] = {}
_wires_lock = threading.Lock()


def get_wire(channel: str) -> SimWire:
    """The wire of an open ``hrm_sim`` channel (raises :class:`SimError` if none is open)."""
    with _wires_lock:
        wire = _wires.get(str(channel))
    if wire is None:
        raise SimError(f"hrm_sim channel {channel!r} is not open")
    return wire


class SimWireBus(can.BusABC):
    """A node on a simulated CAN wire: ``can.Bus(interface="hrm_sim", channel=..., bitrate=...)``.

    Keyword arguments: ``bitrate`` (default 1 Mbit/s; every node of a channel must agree),
    ``stuffing`` (``"worst"`` default or ``"exact"``), ``receive_own_messages`` (default
    False).
    """

    def __init__(
        self,
        channel: Any = "hrm_sim0",
        bitrate: int = 1_000_000,
        stuffing: Stuffing | str = Stuffing.WORST,
        receive_own_messages: bool = False,
        can_filters: Any = None,
        **kwargs: Any,
    ) -> None:
        name = str(channel)
        with _wires_lock:
            wire = _wires.get(name)
            if wire is None:
                wire = SimWire(name, int(bitrate), stuffing)
                _wires[name] = wire
            elif wire.bitrate != int(bitrate):
                raise WireConfigError(
                    f"hrm_sim channel {name!r} runs at {wire.bitrate} bit/s, "
                    f"a node asked for {bitrate}"
                )
            self.wire = wire
            self.receive_own_messages = bool(receive_own_messages)
            self._rx: collections.deque[can.Message] = collections.deque(maxlen=RX_QUEUE_FRAMES)
            self._tx_pending = 0  # frames of this node waiting for the wire (wire's lock)
            self._open = True
            wire._attach(self)
        self.channel_info = f"hrm_sim wire {name} @ {wire.bitrate} bit/s"
        self._can_protocol = CanProtocol.CAN_20
        super().__init__(channel=name, can_filters=can_filters, **kwargs)

    @property
    def state(self) -> BusState:
        return BusState.ERROR if self.wire.bus_off else BusState.ACTIVE

    @state.setter
    def state(self, new_state: BusState) -> None:
        raise NotImplementedError("hrm_sim: the bus state follows the wire (SimWire.set_bus_off)")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Offer a copy of ``msg`` to the wire (python-can's contract): with this node's
        transmit queue full, wait for room up to ``timeout`` s (None: as long as it takes,
        0: not at all), then raise ``can.CanOperationError`` ("transmit queue full")."""
        if not self._open:
            raise can.CanOperationError("hrm_sim: cannot send on a closed bus")
        if msg.is_fd:
            raise can.CanOperationError("hrm_sim: CAN FD frames are not supported")
        self.wire._submit(msg, self, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._open:
            raise can.CanOperationError("hrm_sim: cannot receive on a closed bus")
        return self.wire._receive(self, timeout), False

    def shutdown(self) -> None:
        super().shutdown()
        if self._open:
            self._open = False
            with _wires_lock:
                if self.wire._detach(self):
                    _wires.pop(self.wire.channel, None)

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        with _wires_lock:
            return [{"interface": "hrm_sim", "channel": name} for name in _wires]
