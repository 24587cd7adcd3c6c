"""One end of an ``hrm_ipc`` bus: :class:`IpcBus`, the python-can interface.

It puts the pieces of the package together: the channel's folder and this end's socket
(:mod:`~sim_bus.ipc.folder`), the other ends found there (:mod:`~sim_bus.ipc.discovery`),
the datagrams (:mod:`~sim_bus.ipc.wire_format`), sent to each peer within a short wait
(:mod:`~sim_bus.ipc.congestion`), and received into a bounded queue (the oldest frames
dropped and counted when it is full).  Semantics: :mod:`sim_bus.ipc`.
"""

from __future__ import annotations

import collections
import contextlib
import difflib
import logging
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import can
import numpy as np
from can.bus import BusState, CanProtocol

from drivers.protocol.batch import FRAME_DTYPE
from sim_bus.ipc.congestion import SEND_BUFFER_BYTES, SEND_WAIT_S, Delivery, SendBudget, deliver
from sim_bus.ipc.discovery import Peers
from sim_bus.ipc.folder import (
    CHANNEL_RE,
    FOLDER_PREFIX,
    bind,
    channel_folder,
    check_path_room,
    default_directory,
    make_folder,
)
from sim_bus.ipc.wire_format import (
    HEADER,
    MAX_DATAGRAM_BYTES,
    MAX_FRAMES_PER_DATAGRAM,
    RECORD,
    check_record,
    datagram_header,
    encode_frame,
    pack_header,
    records_valid,
)

log = logging.getLogger("sim_bus.ipc")

#: Default receive queue length (frames), about 18 s of a 36-drive bus at 100 Hz.
RX_QUEUE_FRAMES = 65_536
#: Datagrams read from one connection per wake-up (fairness between senders).
READ_BURST = 64
#: Connections an end accepts at once (the ends that send to it); one more is closed at
#: once and counted (``connections_refused``): a flood of connections cannot use up the
#: process's descriptors.
MAX_CONNECTIONS = 64
#: When accept(2) fails for want of descriptors, the listener is left unpolled this long
#: (s) instead of waking every receive at once (a busy loop).
ACCEPT_PAUSE_S = 0.1
#: The options this interface takes (an unknown option this close to one is refused as
#: misspelt: it would silently put this end on another bus).
OPTIONS = (
    "directory",
    "receive_own_messages",
    "bitrate",
    "rx_queue_size",
    "send_wait_s",
    "send_buffer_bytes",
    "can_filters",
)
#: Longest wait in shutdown() for a recv in another thread to let go (s).
SHUTDOWN_WAIT_S = 1.0


@dataclass
class _Chunk:
    """A received datagram's frames not yet taken: records ``pos`` .. ``count`` of ``data``."""

    data: bytes
    count: int
    is_rx: bool
    pos: int = 0


class _Held(threading.local):
    """The frames one thread's :meth:`IpcBus.batch` block holds (None: not in a block)."""

    records: list[bytes] | None = None


@dataclass
class _Conn:
    sock: socket.socket
    last_seq: int | None = None
    # the connecting end is a process with this one's pid (SO_PEERCRED at accept): only
    # such a connection may carry this end's own frames (receive_own_messages)
    same_process: bool = False


@dataclass
class _Counters:
    frames_sent: int = 0
    datagrams_sent: int = 0
    frames_received: int = 0
    datagrams_received: int = 0
    malformed_datagrams: int = 0
    rx_queue_dropped_frames: int = 0
    tx_dropped_frames: int = 0
    tx_waits: int = 0
    rx_sequence_gaps: int = 0
    connections_refused: int = 0
    accept_failures: int = 0


_PEERCRED = struct.Struct("3i")  # struct ucred: pid, uid, gid


def _peer_pid(sock: socket.socket) -> int:
    """The pid of the process at the other end of a connected Unix socket (0: unknown)."""
    try:
        pid, _uid, _gid = _PEERCRED.unpack(
            sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _PEERCRED.size)
        )
    except (OSError, struct.error):
        return 0
    return int(pid)


def ignore_options(
    interface: str, channel: str, options: dict[str, Any], known: Sequence[str]
) -> None:
    """Accept the options an interface does not use, as python-can's own interfaces do
    (generic python-can code and configuration pass ``fd``, ``single_handle``,
    ``data_bitrate``...): one log line names them.  An option that looks like a misspelling
    of a ``known`` one is refused (``can.CanInitializationError``).

    >>> ignore_options("hrm_ipc", "c", {"single_handle": True}, ("directory",))
    >>> try:
    ...     ignore_options("hrm_ipc", "c", {"diretory": "/tmp"}, ("directory",))
    ... except can.CanInitializationError as exc:
    ...     print(exc)
    hrm_ipc channel 'c': unknown option diretory (did you mean directory? known: directory)
    """
    for key in sorted(options):
        close = difflib.get_close_matches(key, known, n=1, cutoff=0.8)
        if close:
            raise can.CanInitializationError(
                f"{interface} channel {channel!r}: unknown option {key} (did you mean "
                f"{close[0]}? known: {', '.join(known)})"
            )
    if options:
        what = ", ".join(f"{k}={v!r}" for k, v in sorted(options.items()))
        note = " (classical CAN only: an FD frame is refused at send)" if options.get("fd") else ""
        log.warning("%s channel %r: ignoring option(s) %s%s", interface, channel, what, note)


class IpcBus(can.BusABC):
    """One end of a cross-process bus: ``can.Bus(interface="hrm_ipc", channel=NAME)``.

    Keyword arguments: ``directory`` (folder holding the channel folders, default
    :func:`default_directory`), ``receive_own_messages`` (default False), ``bitrate``
    (accepted, informational: nothing is paced), ``rx_queue_size`` (frames, default
    :data:`RX_QUEUE_FRAMES`), ``send_wait_s`` (longest wait for a full peer per send, default
    :data:`SEND_WAIT_S`).  Other options (python-can's generic ``fd``, ``single_handle``,
    ``data_bitrate``...) are accepted and ignored, named in a log line
    (:func:`ignore_options`); one that looks like a misspelt option of this list is
    refused.  Opening fails with ``can.CanInitializationError`` naming the
    channel or path (bad channel name, folder not a private directory of this user, socket
    path too long).
    """

    def __init__(
        self,
        channel: Any = "hrm_ipc0",
        directory: str | os.PathLike[str] | None = None,
        receive_own_messages: bool = False,
        bitrate: int | None = None,
        rx_queue_size: int = RX_QUEUE_FRAMES,
        send_wait_s: float = SEND_WAIT_S,
        send_buffer_bytes: int = SEND_BUFFER_BYTES,
        can_filters: Any = None,
        **kwargs: Any,
    ) -> None:
        name = str(channel)
        ignore_options("hrm_ipc", name, kwargs, OPTIONS)
        if not CHANNEL_RE.fullmatch(name):
            raise can.CanInitializationError(
                f"hrm_ipc: channel {name!r} must be 1-64 characters of A-Z a-z 0-9 . _ -"
            )
        if (
            isinstance(rx_queue_size, bool)
            or not isinstance(rx_queue_size, int)
            or not (1 <= rx_queue_size <= 10_000_000)
        ):
            raise can.CanInitializationError(
                f"hrm_ipc channel {name!r}: rx_queue_size must be 1..10000000, "
                f"got {rx_queue_size!r}"
            )
        try:
            wait = float(send_wait_s)
        except (TypeError, ValueError):
            wait = -1.0
        if not 0.0 <= wait <= 1.0:
            raise can.CanInitializationError(
                f"hrm_ipc channel {name!r}: send_wait_s must be 0..1 s, got {send_wait_s!r}"
            )
        self.channel = name
        if (
            isinstance(send_buffer_bytes, bool)
            or not isinstance(send_buffer_bytes, int)
            or not (4096 <= send_buffer_bytes <= 1 << 30)
        ):
            raise can.CanInitializationError(
                f"hrm_ipc channel {name!r}: send_buffer_bytes must be 4096..2**30, "
                f"got {send_buffer_bytes!r}"
            )
        self._sndbuf = send_buffer_bytes
        self._epoll: select.epoll | None = None  # made by _setup (closed if it fails)
        self._event_fd: int | None = None
        self._closed = True  # until the sockets exist (shutdown() is safe on a failed open)
        self._send_wait_s = wait
        self._rx_max = rx_queue_size
        self.receive_own_messages = bool(receive_own_messages)
        self.bitrate = bitrate
        self.folder = channel_folder(directory, name)
        check_path_room(self.folder)  # before the folder is made: a refused end leaves nothing
        make_folder(self.folder)
        self._sender_id = int.from_bytes(os.urandom(8), "little")
        self._listener, self.path = bind(self.folder)
        try:
            self._setup(name, can_filters)
        except BaseException:
            self._closed = True
            self._listener.close()
            self.path.unlink(missing_ok=True)
            if self._epoll is not None:
                self._epoll.close()
            if self._event_fd is not None:
                os.close(self._event_fd)
            raise

    def _setup(self, name: str, can_filters: Any) -> None:
        self._epoll = epoll = select.epoll()
        epoll.register(self._listener.fileno(), select.EPOLLIN)
        self._conns: dict[int, _Conn] = {}
        self._rx: collections.deque[_Chunk] = collections.deque()
        self._rx_len = 0  # frames in the receive queue
        # readable while frames wait in the queue (once fileno() was asked for) or on shutdown
        self._event_fd = event_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        epoll.register(event_fd, select.EPOLLIN)
        self._fileno_used = False
        self._event_set = False
        self._peers = Peers(self.folder, self.path.name, self.receive_own_messages, self._sndbuf)
        self._tx_lock = threading.Lock()
        self._local = _Held()  # frames held by batch() in this thread
        self._rx_lock = threading.RLock()
        self._n = _Counters()
        self._accept_paused_until: float | None = None  # listener out of epoll until then
        self._accept_lock = threading.Lock()  # the pause, against the re-arming timer
        self._closed = False
        self.channel_info = f"hrm_ipc {name} ({self.path})"
        self._can_protocol = CanProtocol.CAN_20
        super().__init__(channel=name, can_filters=can_filters)
        with self._tx_lock:
            self._peers.scan()

    # ------------------------------------------------------------------ send
    @property
    def state(self) -> BusState:
        return BusState.ACTIVE

    @state.setter
    def state(self, new_state: BusState) -> None:
        raise NotImplementedError("hrm_ipc: the bus state cannot be set")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to every other end (one datagram per peer; inside :meth:`batch`,
        at the end of the block)."""
        record = encode_frame(msg, time.time())
        pending = self._local.records
        if pending is not None:
            pending.append(record)
            return
        self._transmit([record], timeout)

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """Frames this thread sends inside the block leave together at its end, one datagram
        per peer (other threads' sends are not held back; nested blocks join the outer one).

        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     a, b = open_ends("doc-batch", 2, d)
        ...     with a.batch():
        ...         for k in range(5):
        ...             a.send(can.Message(arbitration_id=k, is_extended_id=False))
        ...     print(a.stats()["datagrams_sent"], [b.recv(1.0).arbitration_id for _ in range(5)])
        ...     a.shutdown(); b.shutdown()
        1 [0, 1, 2, 3, 4]
        """
        local = self._local
        if local.records is not None:
            yield
            return
        local.records = []
        try:
            yield
        finally:
            records, local.records = local.records, None
            for k in range(0, len(records), MAX_FRAMES_PER_DATAGRAM):
                self._transmit(records[k : k + MAX_FRAMES_PER_DATAGRAM], None)

    def send_many(self, msgs: Sequence[can.Message], timeout: float | None = None) -> None:
        """Send frames in order, :data:`MAX_FRAMES_PER_DATAGRAM` per datagram: a control
        cycle's frames in ONE datagram per peer.  Every frame is checked before any is sent."""
        now = time.time()
        records = [encode_frame(m, now) for m in msgs]
        pending = self._local.records
        if pending is not None:
            pending.extend(records)
            return
        for k in range(0, len(records), MAX_FRAMES_PER_DATAGRAM):
            self._transmit(records[k : k + MAX_FRAMES_PER_DATAGRAM], timeout)

    def send_batch(self, frames: np.ndarray, timeout: float | None = None) -> None:
        """Send a :data:`~drivers.protocol.batch.FRAME_DTYPE` array as :meth:`send_many`
        sends frames (stamped with ``time.time()`` now, in place), its bytes as they are;
        a record classical CAN cannot carry refuses the whole batch."""
        if frames.dtype != FRAME_DTYPE or frames.ndim != 1:
            raise can.CanOperationError("hrm_ipc: send_batch takes a 1-D FRAME_DTYPE array")
        frames["timestamp"] = time.time()
        if not records_valid(frames, stamped=True):
            raise can.CanOperationError(
                "hrm_ipc: a frame of the batch has more than 8 data bytes or an id out of range"
            )
        pending = self._local.records
        if pending is not None:
            body = frames.tobytes()
            size = RECORD.size
            pending.extend(body[k : k + size] for k in range(0, len(body), size))
            return
        for k in range(0, len(frames), MAX_FRAMES_PER_DATAGRAM):
            part = frames[k : k + MAX_FRAMES_PER_DATAGRAM]
            self._transmit_body(part.tobytes(), len(part), timeout)

    def _transmit(self, records: list[bytes], timeout: float | None) -> None:
        if records:
            self._transmit_body(b"".join(records), len(records), timeout)

    def _transmit_body(self, body: bytes, n: int, timeout: float | None) -> None:
        if self._closed:
            raise can.CanOperationError("hrm_ipc: cannot send on a closed bus")
        budget = self._send_wait_s if timeout is None else min(self._send_wait_s, timeout)
        with self._tx_lock:
            if self._closed:
                raise can.CanOperationError("hrm_ipc: cannot send on a closed bus")
            peers = self._peers
            peers.refresh()
            wait = SendBudget(budget)
            n_sent = 0
            try:
                for peer in list(peers.by_name.values()):
                    peer.seq = (peer.seq + 1) & 0xFFFFFFFF
                    data = pack_header(n, peer.seq, self._sender_id) + body
                    try:
                        delivery = deliver(peer, data, wait)
                    except OSError as exc:
                        raise can.CanOperationError(
                            f"hrm_ipc channel {self.channel_info}: send failed ({exc.strerror})"
                        ) from None
                    if delivery is Delivery.SENT:
                        n_sent += 1
                    elif delivery is Delivery.DROPPED:
                        self._n.tx_dropped_frames += n
                    else:
                        peers.drop(peer)
            finally:
                self._n.tx_waits += wait.waits
                self._n.datagrams_sent += n_sent
            self._n.frames_sent += n

    # --------------------------------------------------------------- receive
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        with self._rx_lock:
            try:
                if self._rx_len or self._wait_rx(timeout):
                    return self._pop(), False
                return None, False
            finally:
                if not self._closed:
                    self._sync_event()

    def recv_batch(self, timeout: float | None = None) -> tuple[np.ndarray, bool] | None:
        """The frames of the oldest datagram still queued (those :meth:`recv` has not taken
        yet) as a read-only :data:`~drivers.protocol.batch.FRAME_DTYPE` array over the
        datagram's bytes, with ``is_rx`` (False: our own, ``receive_own_messages``); None
        when nothing came within ``timeout``.  The bus's filters are not applied (ask
        :meth:`recv` on a filtered bus).

        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     a, b = open_ends("doc-rb", 2, d)
        ...     a.send_many([can.Message(arbitration_id=0x181 + k, data=[k], is_extended_id=False)
        ...                  for k in range(3)])
        ...     frames, is_rx = b.recv_batch(1.0)
        ...     print([hex(i) for i in frames["id"]], frames["data"][:, 0].tolist(), is_rx,
        ...           b.recv_batch(0.0))
        ...     a.shutdown(); b.shutdown()
        ['0x181', '0x182', '0x183'] [0, 1, 2] True None
        """
        with self._rx_lock:
            try:
                if not (self._rx_len or self._wait_rx(timeout)):
                    return None
                chunk = self._rx.popleft()
                self._rx_len -= chunk.count - chunk.pos
            finally:
                if not self._closed:
                    self._sync_event()
            frames = np.frombuffer(
                chunk.data,
                dtype=FRAME_DTYPE,
                count=chunk.count - chunk.pos,
                offset=HEADER.size + chunk.pos * RECORD.size,
            )
            return frames, chunk.is_rx

    def recv_batches(
        self, timeout: float | None = None, max_frames: int = RX_QUEUE_FRAMES
    ) -> list[tuple[np.ndarray, bool]]:
        """:meth:`recv_batch` for every datagram queued after one wait (at most about
        ``max_frames`` frames: whole datagrams, the one that reaches it included); empty
        when nothing came within ``timeout``.

        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     a, b = open_ends("doc-rbs", 2, d)
        ...     for k in range(3):
        ...         a.send(can.Message(arbitration_id=0x701 + k, data=[5], is_extended_id=False))
        ...     print([[hex(i) for i in f["id"]] for f, _rx in b.recv_batches(1.0)])
        ...     a.shutdown(); b.shutdown()
        [['0x701'], ['0x702'], ['0x703']]
        """
        out: list[tuple[np.ndarray, bool]] = []
        with self._rx_lock:
            try:
                if not (self._rx_len or self._wait_rx(timeout)):
                    return out
                n = 0
                while self._rx and n < max_frames:
                    chunk = self._rx.popleft()
                    k = chunk.count - chunk.pos
                    self._rx_len -= k
                    n += k
                    out.append(
                        (
                            np.frombuffer(
                                chunk.data,
                                dtype=FRAME_DTYPE,
                                count=k,
                                offset=HEADER.size + chunk.pos * RECORD.size,
                            ),
                            chunk.is_rx,
                        )
                    )
            finally:
                if not self._closed:
                    self._sync_event()
        return out

    def _wait_rx(self, timeout: float | None) -> bool:
        """Wait (under the receive lock) until a frame is queued; False after ``timeout``."""
        if self._closed:
            raise can.CanOperationError("hrm_ipc: cannot receive on a closed bus")
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        while True:
            now = time.monotonic()
            left = -1.0 if deadline is None else max(0.0, deadline - now)
            paused = self._accept_paused_until
            if paused is not None:  # accept(2) lacked descriptors: the listener waits
                if now >= paused:
                    self._rearm_listener()
                else:
                    left = paused - now if left < 0.0 else min(left, paused - now)
            try:
                events = self._epoll.poll(left)
            except (OSError, ValueError):
                if self._closed:
                    raise can.CanOperationError("hrm_ipc: bus closed while receiving") from None
                raise
            if self._closed:
                raise can.CanOperationError("hrm_ipc: bus closed while receiving")
            for fd, _ev in events:
                if fd == self._listener.fileno():
                    self._accept()
                elif fd in self._conns:
                    self._read(fd)
            if self._rx_len:
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False

    def _accept(self) -> None:
        while True:
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # EMFILE, ENFILE, ENOBUFS: stop polling the listener a while
                self._n.accept_failures += 1
                with self._accept_lock:
                    self._epoll.unregister(self._listener.fileno())
                    self._accept_paused_until = time.monotonic() + ACCEPT_PAUSE_S
                # re-armed by a receive that comes later, or by this timer: a user who
                # waits on fileno() calls no receive until the descriptor is readable
                timer = threading.Timer(ACCEPT_PAUSE_S, self._rearm_listener)
                timer.daemon = True
                timer.start()
                return
            if len(self._conns) >= MAX_CONNECTIONS:
                sock.close()
                self._n.connections_refused += 1
                continue
            sock.setblocking(False)
            fd = sock.fileno()
            self._conns[fd] = _Conn(sock, same_process=_peer_pid(sock) == os.getpid())
            self._epoll.register(fd, select.EPOLLIN)
            self._read(fd)  # the sender may have written before we accepted

    def _rearm_listener(self) -> None:
        """Poll the listener again after :data:`ACCEPT_PAUSE_S` (receive or timer thread)."""
        with self._accept_lock:
            if self._closed or self._accept_paused_until is None:
                return
            self._accept_paused_until = None
            try:
                self._epoll.register(self._listener.fileno(), select.EPOLLIN)
            except (OSError, ValueError):  # closed meanwhile
                pass

    def _close_conn(self, fd: int) -> None:
        conn = self._conns.pop(fd, None)
        if conn is None:
            return
        try:
            self._epoll.unregister(fd)
        except OSError:
            pass
        conn.sock.close()

    def _read(self, fd: int) -> None:
        conn = self._conns[fd]
        for _ in range(READ_BURST):
            try:
                data = conn.sock.recv(MAX_DATAGRAM_BYTES + 1)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self._close_conn(fd)
                return
            if not data:  # the sender closed its end
                self._close_conn(fd)
                return
            self._decode(data, conn)

    def _decode(self, data: bytes, conn: _Conn) -> None:
        n = self._n
        header = datagram_header(data)
        if header is None:
            n.malformed_datagrams += 1
            return
        count, seq, sender = header
        if conn.last_seq is not None:
            gap = (seq - conn.last_seq - 1) & 0xFFFFFFFF
            n.rx_sequence_gaps += gap
        conn.last_seq = seq
        n.datagrams_received += 1
        n.frames_received += count
        is_rx = sender != self._sender_id
        if not is_rx and not conn.same_process:  # another process claims to be this end
            n.malformed_datagrams += 1
            return
        rx = self._rx
        chunk = _Chunk(data, count, is_rx)
        over = self._rx_len + count - self._rx_max
        if over > 0:  # the oldest frames go
            n.rx_queue_dropped_frames += over
            while over > 0 and rx:
                head = rx[0]
                k = min(over, head.count - head.pos)
                head.pos += k
                self._rx_len -= k
                over -= k
                if head.pos == head.count:
                    rx.popleft()
            chunk.pos = over  # the datagram alone is longer than the queue
        rx.append(chunk)
        self._rx_len += count - chunk.pos

    def _sync_event(self) -> None:
        """At the end of a receive: the descriptor of :meth:`fileno` is readable while
        frames stay queued (datagrams are only read inside a receive, so the queue
        changes nowhere else; two system calls per datagram saved)."""
        if not self._fileno_used:
            return
        if self._rx_len:
            if not self._event_set:
                os.eventfd_write(self._event_fd, 1)
                self._event_set = True
        elif self._event_set:
            try:
                os.eventfd_read(self._event_fd)
            except BlockingIOError:
                pass
            self._event_set = False

    def _pop(self) -> can.Message:
        head = self._rx[0]
        raw_ts, raw, raw_dlc, payload = RECORD.unpack_from(
            head.data, HEADER.size + head.pos * RECORD.size
        )
        head.pos += 1
        if head.pos == head.count:
            self._rx.popleft()
        self._rx_len -= 1
        is_rx = head.is_rx
        checked = check_record(raw_ts, raw, raw_dlc, payload)
        if checked is None:  # checked when it came in
            raise can.CanOperationError("hrm_ipc: a queued frame is malformed")
        ts, ident, ext, rtr, err, dlc, data = checked
        return can.Message(
            timestamp=ts,
            arbitration_id=ident,
            is_extended_id=ext,
            is_remote_frame=rtr,
            is_error_frame=err,
            dlc=dlc,
            data=data,
            channel=self.channel,
            is_rx=is_rx,
            check=False,
        )

    def fileno(self) -> int:
        """A descriptor that is readable while a frame waits (for ``select`` / asyncio)."""
        with self._rx_lock:
            if self._closed:
                raise can.CanOperationError("hrm_ipc: bus is closed")
            if not self._fileno_used:
                self._fileno_used = True
                if self._rx_len and not self._event_set:
                    os.eventfd_write(self._event_fd, 1)
                    self._event_set = True
            return self._epoll.fileno()

    # ------------------------------------------------------------- bookkeeping
    def stats(self) -> dict[str, Any]:
        """Counters of this end: frames and datagrams sent and received, drops (receive
        queue full, peer full), sequence gaps seen, malformed datagrams, peers."""
        n = self._n
        return {
            "channel": self.channel_info,
            "frames_sent": n.frames_sent,
            "datagrams_sent": n.datagrams_sent,
            "frames_received": n.frames_received,
            "datagrams_received": n.datagrams_received,
            "malformed_datagrams": n.malformed_datagrams,
            "rx_queue_dropped_frames": n.rx_queue_dropped_frames,
            "rx_sequence_gaps": n.rx_sequence_gaps,
            "tx_dropped_frames": n.tx_dropped_frames,
            "tx_waits": n.tx_waits,
            "peers": len(self._peers.by_name),
            "peers_dropped": self._peers.peers_dropped,
            "stale_sockets_removed": self._peers.stale_sockets_removed,
            "rescans": self._peers.rescans,
            "connections": len(self._conns),
            "connections_refused": n.connections_refused,
            "accept_failures": n.accept_failures,
            "send_buffer_bytes": self._peers.sndbuf_effective,
            "rx_queued": self._rx_len,
        }

    def peer_names(self) -> list[str]:
        """Socket names of the ends this one currently sends to."""
        with self._tx_lock:
            self._peers.refresh()
            return sorted(self._peers.by_name)

    def shutdown(self) -> None:
        """Close every socket and unlink this end's socket file (the last end removes the
        channel folder); safe to call twice.  A
        ``recv`` waiting in another thread wakes and raises ``can.CanOperationError``."""
        if self._closed:
            return
        self._closed = True
        super().shutdown()
        try:
            self.path.unlink()
            self.folder.rmdir()  # the last end takes the folder along (fails if not empty)
        except OSError:
            pass
        with self._tx_lock:
            self._peers.close()
        os.eventfd_write(self._event_fd, 1)  # wake a waiting recv
        locked = self._rx_lock.acquire(timeout=SHUTDOWN_WAIT_S)
        try:
            for fd in list(self._conns):
                self._close_conn(fd)
            self._listener.close()
            self._epoll.close()
            os.close(self._event_fd)
        finally:
            if locked:
                self._rx_lock.release()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        base = default_directory()
        try:
            entries = list(os.scandir(base))
        except OSError:
            return []
        return [
            {"interface": "hrm_ipc", "channel": e.name[len(FOLDER_PREFIX) :]}
            for e in entries
            if e.name.startswith(FOLDER_PREFIX) and e.is_dir(follow_symlinks=False)
        ]


def open_ends(
    channel: str, count: int, directory: str | os.PathLike[str] | None = None, **kwargs: Any
) -> list[IpcBus]:
    """``count`` ends of one channel in this process (tests, tools).

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     ends = open_ends("doc-ends", 3, d)
    ...     ends[0].send(can.Message(arbitration_id=5, data=b"x", is_extended_id=False))
    ...     print([bytes(e.recv(1.0).data) for e in ends[1:]])
    ...     for e in ends: e.shutdown()
    [b'x', b'x']
    """
    ends: list[IpcBus] = []
    try:
        for _ in range(count):
            ends.append(IpcBus(channel, directory=directory, **kwargs))
    except BaseException:
        for e in ends:
            e.shutdown()
        raise
    return ends
