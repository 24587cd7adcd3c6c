"""The receive path of one bus: every frame the bus delivers, sorted once.

A :class:`BusReader` (one thread per bus, in place of python-can's ``can.Notifier``:
no listener dispatch, no lock per frame) reads the bus with ``bus.recv`` and hands every
frame to the bus's :class:`BusReceiver`.  For each frame:

0. a configured node's TPDO1 (11-bit data frame) takes the short path: logged, then
   parsed straight into the monitor's arrays (:meth:`NodeMonitor.on_tpdo`); such a
   frame is never one of ours (the host never sends 0x180 + node), so the echo ledger
   is not asked; a configured node's heartbeat likewise goes straight to
   :meth:`NodeMonitor.on_heartbeat` (while listening for another master both take the
   full path below);

1. our own frame coming back (udp_multicast echoes a sender's frames) is dropped: it
   was logged when sent (:meth:`drivers.bus.BusPort.is_own_echo`, by identifier and
   data, so only frames this process sent are dropped);
2. everything else goes into the bus's CAN log: drives' frames, other masters' frames,
   error frames, remote frames, 29-bit frames;
3. error frames, remote frames and 29-bit frames are counted (CANopen is 11-bit: a
   29-bit 0x181 is never node 1's TPDO); an error frame (SocketCAN's ``CAN_ERR_*``
   classes, :mod:`drivers.protocol.can_error`) reporting bus-off or error-passive is a
   stop cause (:attr:`StopKind.BUS_ERROR`) naming the bus and the class; any other class
   is logged once per class and counted;
4. a configured node's TPDO goes straight to the monitor (the hot path);
5. a frame in the host's direction (NMT, SYNC, RPDO, SDO request, the host's
   heartbeat) that we did not send is another master's: counted by COB-ID, and when it
   addresses one of our nodes (or all of them) it is a stop cause naming the COB-ID;
6. a frame from a node we do not drive is counted by COB-ID (reported in the run
   record) and not interpreted;
7. the rest (heartbeats, EMCYs, SDO responses of our nodes) goes to canopen; a frame
   canopen cannot take is a stop cause naming the motor and the service, in one line.

What the receiver heard is kept in a :class:`BusTraffic` (bounded: at most
``MAX_TRACKED_IDS`` identifiers per kind), which the session reads for the run record
and, before resetting the drives, to tell whether another master is active.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import can
import canopen
import numpy as np

from drivers.bus import BusPort, TrafficLog, is_host_frame
from drivers.protocol import cia301
from drivers.protocol.batch import to_messages
from drivers.protocol.can_error import error_frame_verdict
from drivers.protocol.cia402 import TPDO_FEEDBACK_SIZE
from drivers.safety.causes import StopKind
from hrm_ctrl.errors import DriverError

MAX_TRACKED_IDS = 2048  # identifiers counted per kind (29-bit ids could be 2**29)
#: A batch of up to this many frames (a heartbeat, an EMCY) takes the per-frame path.
SMALL_BATCH_FRAMES = 2
_TABLE_SIZE = 0x801  # 11-bit COB-IDs, and one entry for every flagged (29-bit, RTR, error) id
log = logging.getLogger("drivers.receive")


class FrameSink(Protocol):
    """What a bus's receive path hands its frames to (a :class:`BusReceiver`)."""

    def on_message_received(self, msg: can.Message) -> None: ...


@runtime_checkable
class BatchSink(FrameSink, Protocol):
    """A :class:`FrameSink` that also takes a batch of received frames as it is (a
    :data:`drivers.protocol.batch.FRAME_DTYPE` array: :meth:`BusReceiver.on_batch`)."""

    def on_batch(self, frames: np.ndarray) -> None: ...


@runtime_checkable
class BatchReceivingBus(Protocol):
    """A bus that hands over whole datagrams of frames as record arrays, with whether they
    were received (``False``: our own, ``receive_own_messages``) (``hrm_ipc``)."""

    def recv_batches(
        self, timeout: float | None = None, max_frames: int = ...
    ) -> Sequence[tuple[np.ndarray, bool]]: ...


def receive_of(bus: can.BusABC) -> Callable[[float], can.Message | None]:
    """The bus's receive: python-can's ``BusABC.recv`` wraps the interface's
    ``_recv_internal`` with filtering and a log call per frame; a bus that
    :func:`reads_internally` is read through ``_recv_internal`` directly (the same
    frames, without that per-frame work)."""
    if not reads_internally(bus):
        return bus.recv
    internal = bus._recv_internal

    def recv(timeout_s: float) -> can.Message | None:
        msg, _filtered = internal(timeout_s)
        return msg

    return recv


def reads_internally(bus: can.BusABC) -> bool:
    """Whether a bus may be read through its interface's ``_recv_internal`` (python-can's
    hook for interfaces) in place of ``recv``: it implements the hook, does not override
    ``recv``, and has no filters (``recv`` applies them).

    >>> bus = can.Bus(interface="virtual", channel="doc-internal")
    >>> reads_internally(bus)
    True
    >>> bus.set_filters([{"can_id": 0x181, "can_mask": 0x7FF}])
    >>> reads_internally(bus)
    False
    >>> bus.shutdown()
    """
    kind = type(bus)
    return (
        kind.recv is can.BusABC.recv
        and kind._recv_internal is not can.BusABC._recv_internal
        and not bus.filters
    )


def service_of(cob_id: int) -> str:
    """The CANopen service of an 11-bit COB-ID (predefined connection set).

    >>> [service_of(x) for x in (0x000, 0x080, 0x081, 0x181, 0x201, 0x581, 0x601, 0x701)]
    ['NMT', 'SYNC', 'EMCY', 'TPDO1', 'RPDO1', 'SDO response', 'SDO request', 'heartbeat']
    """
    if cob_id == cia301.COB_NMT:
        return "NMT"
    if cob_id == cia301.COB_SYNC:
        return "SYNC"
    if cob_id == cia301.COB_TIME:
        return "TIME"
    fc = cob_id & cia301.FUNCTION_CODE_MASK
    names = {
        cia301.COB_EMCY: "EMCY",
        cia301.COB_SDO_TX: "SDO response",
        cia301.COB_SDO_RX: "SDO request",
        cia301.COB_NMT_ERROR_CONTROL: "heartbeat",
    }
    if fc in names:
        return names[fc]
    for k, base in enumerate((0x180, 0x280, 0x380, 0x480), start=1):
        if fc == base:
            return f"TPDO{k}"
    for k, base in enumerate((0x200, 0x300, 0x400, 0x500), start=1):
        if fc == base:
            return f"RPDO{k}"
    return f"function code 0x{fc:03X}"


@dataclass
class BusTraffic:
    """What one bus's receiver heard besides our nodes' expected frames."""

    bus: str
    foreign: dict[int, int] = field(default_factory=dict)  # host-direction COB-ID: frames
    unconfigured: dict[int, int] = field(default_factory=dict)  # COB-ID of an unknown node
    extended: dict[int, int] = field(default_factory=dict)  # 29-bit identifier: frames
    operational_nodes: set[int] = field(default_factory=set)  # heartbeats "operational"
    pdo_nodes: set[int] = field(default_factory=set)  # nodes heard sending PDOs (listening)
    guarding_requests: int = 0  # remote frames of node guarding heard while listening
    listening: bool = False
    remote_frames: int = 0
    error_frames: int = 0
    error_classes: dict[int, int] = field(default_factory=dict)  # CAN_ERR_* bits: frames
    echoes_dropped: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def count(self, table: dict[int, int], key: int) -> None:
        with self._lock:
            if key in table or len(table) < MAX_TRACKED_IDS:
                table[key] = table.get(key, 0) + 1

    def unconfigured_counts(self) -> dict[int, int]:
        """A copy of the frames heard per COB-ID of nodes not in the configuration."""
        with self._lock:
            return dict(self.unconfigured)

    def clear_evidence(self) -> None:
        """Forget what was heard (before listening for another master)."""
        with self._lock:
            self.foreign.clear()
            self.operational_nodes.clear()
            self.pdo_nodes.clear()
            self.guarding_requests = 0

    def other_master(self) -> str | None:
        """What was heard of another master since :meth:`clear_evidence` (None: nothing):
        SYNC, NMT or RPDO/SDO requests we did not send, nodes in NMT operational, and
        (while listening) PDOs of any node or node-guarding requests."""
        with self._lock:
            heard = [
                f"{service_of(cid)} 0x{cid:03X} x{n}" for cid, n in sorted(self.foreign.items())
            ]
            nodes = sorted(self.operational_nodes)
            pdo = sorted(self.pdo_nodes)
            guarding = self.guarding_requests
        if pdo:
            heard.append(f"PDOs from {len(pdo)} node(s) ({', '.join(str(n) for n in pdo[:8])})")
        if guarding:
            heard.append(f"{guarding} node-guarding request(s)")
        if nodes:
            shown = ", ".join(str(n) for n in nodes[:8]) + (" ..." if len(nodes) > 8 else "")
            heard.append(f"{len(nodes)} node(s) in NMT operational ({shown})")
        if not heard:
            return None
        more = f" (+{len(heard) - 4} more)" if len(heard) > 4 else ""
        return f"bus {self.bus}: " + ", ".join(heard[:4]) + more

    def to_dict(self) -> dict[str, Any]:
        with self._lock:
            return {
                "bus": self.bus,
                "foreign_frames": {f"0x{k:03X}": v for k, v in sorted(self.foreign.items())},
                "unconfigured_node_frames": {
                    f"0x{k:03X}": v for k, v in sorted(self.unconfigured.items())
                },
                "extended_id_frames": {f"0x{k:08X}": v for k, v in sorted(self.extended.items())},
                "remote_frames": self.remote_frames,
                "error_frames": self.error_frames,
                "error_frame_classes": {
                    f"0x{k:03X}": v for k, v in sorted(self.error_classes.items())
                },
                "echoes_dropped": self.echoes_dropped,
            }


class _Routes(dict[int, tuple[Any, int]]):
    """A dict that counts its changes (``version``), so a lookup table built from it
    is rebuilt only when it changed."""

    version = 0

    def __setitem__(self, key: int, value: tuple[Any, int]) -> None:
        self.version += 1
        super().__setitem__(key, value)

    def __delitem__(self, key: int) -> None:
        self.version += 1
        super().__delitem__(key)

    def clear(self) -> None:
        self.version += 1
        super().clear()

    def pop(self, *args: Any) -> Any:
        self.version += 1
        return super().pop(*args)

    def popitem(self) -> tuple[int, tuple[Any, int]]:
        self.version += 1
        return super().popitem()

    def setdefault(self, *args: Any) -> Any:
        self.version += 1
        return super().setdefault(*args)

    def update(self, *args: Any, **kwargs: Any) -> None:
        self.version += 1
        super().update(*args, **kwargs)


class BusReceiver(can.Listener):
    """The receive path of one bus (see the module docstring)."""

    def __init__(
        self,
        port: BusPort,
        network: canopen.Network,
        log_: TrafficLog | None,
        node_labels: Mapping[int, str],
        report: Callable[[StopKind, str], None],
        armed: Callable[[], bool],
        host_node_id: int = cia301.HOST_HEARTBEAT_NODE_ID,
    ) -> None:
        self.port = port
        self.network = network
        self.log = log_
        self.node_labels = dict(node_labels)
        self.report = report
        self.armed = armed
        self.host_node_id = host_node_id
        self.traffic = BusTraffic(port.name)
        self.fast: dict[int, Callable[[bytes], None]] = {}
        # COB-ID of a configured node's TPDO1 -> (monitor, slot): the short path
        self.tpdo: dict[int, tuple[Any, int]] = _Routes()
        # COB-ID of a configured node's heartbeat -> (monitor, slot): short path too
        # (the monitor is the one consumer of heartbeats; canopen's NMT master is not
        # asked for the drives' states)
        self.heartbeat: dict[int, tuple[Any, int]] = {}
        self._table: np.ndarray | None = None  # self.tpdo as a lookup table (on_batch)
        self._table_version = -1
        self._monitor: Any = None

    def on_message_received(self, msg: can.Message) -> None:
        self._handle(msg, self.log)

    def on_batch(self, frames: np.ndarray) -> None:
        """The frames of a received batch (a :data:`drivers.protocol.batch.FRAME_DTYPE`
        array, from a bus with ``recv_batch``): logged as one entry, the configured nodes'
        TPDO1s straight into the monitor in a few NumPy calls (step 0 for all of them at
        once), every other frame as :meth:`on_message_received` takes it.  While
        listening for another master, or on a bus that echoes our frames, every frame
        takes the full path."""
        table = self._tpdo_table()
        if (
            len(frames) <= SMALL_BATCH_FRAMES
            or table is None
            or self.traffic.listening
            or self.port.echoes is not None
        ):
            for msg in to_messages(frames, channel=self.port.name):
                self._handle(msg, self.log)
            return
        if self.log is not None:
            self.log.log_batch(frames, is_rx=True)
        slots = table[np.minimum(frames["id"], _TABLE_SIZE - 1)]
        hit = (slots >= 0) & (frames["dlc"] == TPDO_FEEDBACK_SIZE)
        if hit.all():
            self._monitor.on_tpdo_batch(slots, frames)
            return
        if hit.any():
            self._monitor.on_tpdo_batch(slots[hit], frames[hit])
        for msg in to_messages(frames[~hit], channel=self.port.name):
            self._handle(msg, None)

    def _tpdo_table(self) -> np.ndarray | None:
        """COB-ID -> monitor slot of every configured TPDO1 (-1: none; flagged ids land
        on the last entry), rebuilt when :attr:`tpdo` changed; None when the TPDOs do not
        all go to one monitor (then every frame takes the full path)."""
        routes = self.tpdo
        version = routes.version if isinstance(routes, _Routes) else -2  # -2: a plain dict
        if version != self._table_version or version == -2:
            monitors = {id(mon) for mon, _slot in self.tpdo.values()}
            table = None
            if len(monitors) == 1:
                table = np.full(_TABLE_SIZE, -1, dtype=np.int64)
                for cid, (mon, slot) in self.tpdo.items():
                    if 0 <= cid < _TABLE_SIZE - 1:
                        table[cid] = slot
                        self._monitor = mon
            self._table, self._table_version = table, version
        return self._table

    def _handle(self, msg: can.Message, log_: TrafficLog | None) -> None:
        """Step 0-7 of the module docstring for one frame (``log_`` None: logged already)."""
        cid = msg.arbitration_id
        slot = self.tpdo.get(cid)
        if (
            slot is not None
            and not msg.is_extended_id
            and not msg.is_remote_frame
            and not msg.is_error_frame
            and not self.traffic.listening
        ):
            if log_ is not None:
                log_.on_message_received(msg)
            slot[0].on_tpdo(slot[1], msg.data)
            return
        slot = self.heartbeat.get(cid)
        if (
            slot is not None
            and not msg.is_extended_id
            and not msg.is_remote_frame
            and not msg.is_error_frame
            and not self.traffic.listening
        ):
            if log_ is not None:
                log_.on_message_received(msg)
            slot[0].on_heartbeat(slot[1], msg.data)
            return
        if self.port.is_own_echo(msg):
            self.traffic.echoes_dropped += 1
            return
        if log_ is not None:
            log_.on_message_received(msg)
        if msg.is_error_frame:
            self._error_frame(msg)
            return
        cid = msg.arbitration_id
        if msg.is_extended_id:
            self.traffic.count(self.traffic.extended, cid)
            return
        if msg.is_remote_frame:
            self.traffic.remote_frames += 1
            if self.traffic.listening:
                self.traffic.guarding_requests += 1
            return
        handler = self.fast.get(cid)
        if handler is not None or cid in self.tpdo:
            if self.traffic.listening:  # drives sending PDOs are operational: someone's
                self.traffic.pdo_nodes.add(cid & cia301.NODE_ID_MASK)
            if handler is not None:
                handler(msg.data)
            else:
                monitor, idx = self.tpdo[cid]
                monitor.on_tpdo(idx, msg.data)
            return
        if is_host_frame(cid, self.host_node_id):
            self._foreign(cid, bytes(msg.data))
            return
        nid = cid & cia301.NODE_ID_MASK
        if self.traffic.listening and service_of(cid).startswith("TPDO"):
            self.traffic.pdo_nodes.add(nid)
        if nid not in self.node_labels:
            self.traffic.count(self.traffic.unconfigured, cid)
            self._note_operational(cid, nid, msg.data)
            return
        self._note_operational(cid, nid, msg.data)
        try:
            self.network.notify(cid, msg.data, msg.timestamp)
        except Exception as exc:  # must not stop the receive thread: a stop cause instead
            log.error("bus %s: 0x%03X not handled: %r", self.port.name, cid, exc)
            self.report(
                StopKind.BAD_FRAME,
                f"{self.node_labels[nid]}: malformed {service_of(cid)} frame 0x{cid:03X} "
                f"[{bytes(msg.data).hex()}] ({type(exc).__name__}: {exc})",
            )

    def _error_frame(self, msg: can.Message) -> None:
        """An error frame (logged already): counted by its classes; bus-off and
        error-passive are a stop cause naming the bus and the class, any other class is
        logged once per bus and class combination (bus errors may flood)."""
        verdict = error_frame_verdict(msg.arbitration_id, msg.data)
        traffic = self.traffic
        first = verdict.classes not in traffic.error_classes
        traffic.count(traffic.error_classes, verdict.classes)
        text = f"bus {self.port.name}: CAN error frame 0x{verdict.classes:03X}: {verdict.text}"
        if verdict.stops:
            log.error("%s", text)
            self.report(StopKind.BUS_ERROR, text)
        elif first:
            log.warning("%s (logged once per class; every one counted and in the CAN log)", text)
        traffic.error_frames += 1  # counted once handled: a stop cause is queued by then

    def _note_operational(self, cid: int, nid: int, data: bytes | bytearray) -> None:
        if (
            cid & cia301.FUNCTION_CODE_MASK == cia301.COB_NMT_ERROR_CONTROL
            and len(data) == 1
            and data[0] & 0x7F == cia301.NMT_STATE_OPERATIONAL
        ):
            with self.traffic._lock:
                self.traffic.operational_nodes.add(nid)

    def _foreign(self, cid: int, data: bytes) -> None:
        """A host-direction frame this process did not send: another master."""
        self.traffic.count(self.traffic.foreign, cid)
        if not self.armed():
            return
        nid = cid & cia301.NODE_ID_MASK
        service = service_of(cid)
        if cid in (cia301.COB_NMT, cia301.COB_SYNC):
            target = "every node"
            if cid == cia301.COB_NMT and len(data) >= 2 and data[1] != 0:
                if data[1] not in self.node_labels:
                    return  # an NMT command for a node we do not drive
                target = self.node_labels[data[1]]
        elif nid in self.node_labels:
            target = self.node_labels[nid]
        elif cid == cia301.COB_NMT_ERROR_CONTROL + self.host_node_id:
            # the heartbeat our drives watch (0x1016): another sender keeps them going
            # when this host dies (an RPDO or SDO to node 127 is no node of ours)
            target = f"every node (the host heartbeat, node {nid})"
        else:
            return  # another master talking to a node we do not drive
        self.report(
            StopKind.FOREIGN,
            f"bus {self.port.name}: {service} 0x{cid:03X} [{data.hex()}] for {target} "
            "that this host did not send (another master on the bus)",
        )


def wait_quiet_listen(receivers: list[BusReceiver], listen_s: float) -> str | None:
    """Listen ``listen_s`` on every bus for another master (see
    :meth:`BusTraffic.other_master`); return what was heard, or None."""
    for r in receivers:
        r.traffic.clear_evidence()
        r.traffic.listening = True
    try:
        time.sleep(listen_s)
    finally:
        for r in receivers:
            r.traffic.listening = False
    heard = [h for r in receivers if (h := r.traffic.other_master()) is not None]
    return "; ".join(heard) if heard else None


RECV_TIMEOUT_S = 0.1  # how often a reader looks whether it is asked to stop


class BusReader:
    """The receive thread of one bus: ``bus.recv`` in a loop, every frame to the bus's
    :class:`BusReceiver` (what ``can.Notifier`` did, without its per-frame listener
    dispatch and lock).  A failure of the bus (or a bug in the receiver) ends the
    thread and is kept in :attr:`exception`, which the supervisor reports as a stop
    cause (and canopen's ``Network.check`` raises); :meth:`stop` ends it.

    >>> import can
    >>> bus = can.Bus(interface="virtual", channel="doc-reader")
    >>> got = []
    >>> class Sink:
    ...     def on_message_received(self, msg):
    ...         got.append(msg.arbitration_id)
    >>> reader = BusReader(bus, Sink(), name="doc")
    >>> other = can.Bus(interface="virtual", channel="doc-reader")
    >>> other.send(can.Message(arbitration_id=0x181, data=b"\\x01", is_extended_id=False))
    >>> t_end = time.monotonic() + 5.0
    >>> while not got and time.monotonic() < t_end:
    ...     time.sleep(0.01)
    >>> reader.stop(1.0); other.shutdown(); bus.shutdown()
    >>> [hex(x) for x in got], reader.exception
    (['0x181'], None)
    """

    def __init__(
        self, bus: can.BusABC, receiver: FrameSink, name: str, timeout_s: float = RECV_TIMEOUT_S
    ) -> None:
        self.bus = bus
        self.receiver = receiver
        self.timeout_s = float(timeout_s)
        self._exception: BaseException | None = None
        self.n_frames = 0
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=f"hrm-rx-{name}", daemon=True)
        self._thread.start()

    def _recv(self) -> Callable[[float], can.Message | None]:
        return receive_of(self.bus)

    def _run(self) -> None:
        recv = self._recv()
        handle = self.receiver.on_message_received
        timeout_s = self.timeout_s
        n = 0
        try:
            while not self._stopped:
                msg = recv(timeout_s)
                # a frame that comes in while the reader is being stopped is not handled
                # (the log and the monitor may be closed behind stop())
                if msg is not None and not self._stopped:
                    n += 1
                    handle(msg)
                    if n & 0x3FF == 0:
                        self.n_frames = n
        except BaseException as exc:  # kept for the supervisor: a RECEIVE stop cause
            # (BaseException too: a SystemExit raised in a handler ends the thread as
            # surely as an OSError of the bus; a failure while stopping is the close)
            if not self._stopped:
                self._exception = exc
                log.error("receive thread %s ended: %r", self._thread.name, exc)
        self.n_frames = n

    @property
    def exception(self) -> BaseException | None:
        """Why the thread ended unasked (None: alive, or ended by :meth:`stop`): the
        failure of the bus or the receiver, or a :class:`DriverError` when it ended
        without one.  The supervisor's watchdogs read it every cycle."""
        exc = self._exception
        if exc is None and not self._stopped and not self._thread.is_alive():
            exc = DriverError(f"receive thread {self._thread.name} ended unasked")
        return exc

    @exception.setter
    def exception(self, exc: BaseException | None) -> None:
        self._exception = exc

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 5.0) -> None:
        """End the thread (waits at most ``timeout`` s; idempotent)."""
        self._stopped = True
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


def pollable(bus: can.BusABC) -> bool:
    """Whether a bus gives a descriptor that is readable while a frame waits (SocketCAN,
    udp_multicast, ``hrm_ipc``; python-can's ``virtual`` does not).

    >>> import can
    >>> bus = can.Bus(interface="virtual", channel="doc-pollable")
    >>> pollable(bus)
    False
    >>> bus.shutdown()
    """
    try:
        return bus.fileno() >= 0
    except (NotImplementedError, can.CanError, OSError, ValueError):
        return False


class BusPoller:
    """The receive path of one bus without a thread of its own: the supervisor's thread
    waits on :meth:`fileno` (beside its deadline) and calls :meth:`poll`, which hands every
    frame waiting to the bus's :class:`BusReceiver`.  One thread then owns the whole cycle:
    no hand-over of the interpreter lock between a reader and the supervisor for every
    datagram (BENCHMARKS.md).  Same face as :class:`BusReader` (``exception``, ``alive``,
    ``n_frames``, ``stop``): a failure of the bus or the receiver is kept in
    :attr:`exception` and is a stop cause.

    >>> import can
    >>> bus = can.Bus(interface="udp_multicast", channel="239.74.0.9", port=43219,
    ...               hop_limit=0)
    >>> got = []
    >>> class Sink:
    ...     def on_message_received(self, msg):
    ...         got.append(msg.arbitration_id)
    >>> poller = BusPoller(bus, Sink(), name="doc")
    >>> poller.poll(), got, poller.exception
    (0, [], None)
    >>> poller.stop(); bus.shutdown()
    """

    #: frames handled per :meth:`poll` at most (the rest at the next one: a flood cannot
    #: hold the control cycle)
    MAX_FRAMES_PER_POLL = 512

    def __init__(self, bus: can.BusABC, receiver: FrameSink, name: str) -> None:
        self.bus = bus
        self.receiver = receiver
        self.name = f"hrm-rx-{name}"
        self._fd = bus.fileno()
        self._recv = receive_of(bus)
        # a bus that hands over whole datagrams (hrm_ipc), unfiltered, to a receiver that
        # takes batches: no Python object per frame
        self._recv_batch: Callable[[float, int], Sequence[tuple[np.ndarray, bool]]] | None = None
        self._on_batch: Callable[[np.ndarray], None] | None = None
        if (
            isinstance(bus, BatchReceivingBus)
            and not bus.filters
            and isinstance(receiver, BatchSink)
        ):
            self._recv_batch, self._on_batch = bus.recv_batches, receiver.on_batch
        self._exception: BaseException | None = None
        self._stopped = False
        self.n_frames = 0

    def fileno(self) -> int:
        return self._fd

    def poll(self) -> int:
        """Hand every frame waiting (at most :data:`MAX_FRAMES_PER_POLL`) to the receiver;
        return how many.  A failure ends the poller (kept in :attr:`exception`)."""
        if self._stopped or self._exception is not None:
            return 0
        recv = self._recv
        handle = self.receiver.on_message_received
        n = 0
        try:
            recv_batch, on_batch = self._recv_batch, self._on_batch
            if recv_batch is not None and on_batch is not None:  # what is queued, one wait
                for frames, is_rx in recv_batch(0.0, self.MAX_FRAMES_PER_POLL):
                    n += len(frames)
                    if is_rx:
                        on_batch(frames)
                    else:  # our own frames (receive_own_messages): the echo path
                        for msg in to_messages(frames, channel=self.bus.channel, is_rx=False):
                            handle(msg)
            else:
                while n < self.MAX_FRAMES_PER_POLL:
                    msg = recv(0.0)
                    if msg is None:
                        break
                    n += 1
                    handle(msg)
        except BaseException as exc:  # a RECEIVE stop cause, as a reader thread's end
            if not self._stopped:
                self._exception = exc
                log.error("receive path %s ended: %r", self.name, exc)
        self.n_frames += n
        return n

    @property
    def exception(self) -> BaseException | None:
        return self._exception

    @exception.setter
    def exception(self, exc: BaseException | None) -> None:
        self._exception = exc

    @property
    def alive(self) -> bool:
        return not self._stopped and self._exception is None

    def stop(self, timeout: float = 5.0) -> None:
        """No more frames are handled (idempotent; ``timeout`` as :meth:`BusReader.stop`)."""
        self._stopped = True
