"""A CAN bus between processes on one host, as a python-can interface (``hrm_ipc``).

``can.Bus(interface="hrm_ipc", channel="NAME")`` opens one end ("node") of a bus that
every process of the same user on this host can join.  There is no broker: each end
binds a Unix-domain ``SOCK_SEQPACKET`` socket ``<pid>-<n>.sock`` in the channel's
folder ``<directory>/hrm-ipc-<channel>/`` (mode 0700; ``directory`` defaults to
``$XDG_RUNTIME_DIR`` or ``/tmp``), and a sender keeps one connection to every other
end's socket.  Semantics of a CAN bus:

* every other end receives every frame, in send order per sender; the sender gets its
  own frames back only with ``receive_own_messages=True`` (then ``is_rx`` is False);
* a received frame's ``timestamp`` is the sender's ``time.time()`` at the send, its
  ``channel`` the channel name;
* :meth:`IpcBus.send_many` carries a batch (the frames of one control cycle) in ONE
  datagram per peer: one system call per peer instead of one per frame and peer;
* :meth:`IpcBus.send_batch` and :meth:`IpcBus.recv_batch` carry a batch as one NumPy
  record array (:data:`drivers.protocol.batch.FRAME_DTYPE`, the record below): the host's
  control cycle sends and receives a datagram's frames without a Python object per frame.

Why not ``udp_multicast``: it hands every frame back to its own sender, sends one
datagram per frame (msgpack-encoded), and a stalled reader loses frames silently in the
kernel.  Why sequenced packets and not datagrams: a Unix ``SOCK_DGRAM`` receiver queues
at most ``net.unix.max_dgram_qlen`` (10 by default) datagrams from unconnected senders,
less than one cycle of 18 drives; a connected ``SOCK_SEQPACKET`` pair is bounded only by
the sender's send buffer (asked for :data:`SEND_BUFFER_BYTES`).

Wire format of a datagram: header ``<2sBBHIQ`` (magic ``b"HC"``, version 1, kind 1,
frame count, per-connection sequence number, sender id) and per frame a 21-byte record
``<dIB8s`` (timestamp, id with the SocketCAN flag bits 31 extended / 30 remote / 29 error,
dlc, data padded to 8 bytes).  Bounds: :data:`MAX_FRAMES_PER_DATAGRAM` frames (a longer
``send_many`` is split), :data:`MAX_DATAGRAM_BYTES`, a receive queue of ``rx_queue_size``
frames (default :data:`RX_QUEUE_FRAMES`; when full the oldest frames are dropped and
counted).  A malformed datagram (a header alone, a record with dlc > 8, an 11-bit id over
0x7FF, a timestamp outside [0, :data:`MAX_TIMESTAMP_S`), this end's own sender id on a
connection from another process) is counted and dropped.  A peer
whose buffer is full is waited for at most ``send_wait_s`` (default :data:`SEND_WAIT_S`)
once; from then on its frames are dropped and counted without waiting until it has read
half its buffer (a stalled or slow reader never stalls the sender's control cycle again
and again).  A peer that is gone is dropped and its stale socket file unlinked.  At most
:data:`MAX_CONNECTIONS` ends send to one end at a time.  Counters: :meth:`IpcBus.stats`.

Unlike a CAN wire, the transport does not make a frame reach every end: ``IpcBus`` sends
each frame to all, but a program writing raw datagrams could address one end alone, and
the others (the host) would not see it.  The folder is private to the user, so only the
user's own programs can; a test of a foreign master sends through ``IpcBus``.

>>> import tempfile
>>> tmp = tempfile.TemporaryDirectory()
>>> a = can.Bus(interface="hrm_ipc", channel="doc", directory=tmp.name)
>>> b = can.Bus(interface="hrm_ipc", channel="doc", directory=tmp.name)
>>> a.send_many([can.Message(arbitration_id=0x181 + k, data=[k] * 2, is_extended_id=False)
...              for k in range(3)])
>>> [(hex(m.arbitration_id), bytes(m.data)) for m in (b.recv(1.0) for _ in range(3))]
[('0x181', b'\\x00\\x00'), ('0x182', b'\\x01\\x01'), ('0x183', b'\\x02\\x02')]
>>> a.stats()["datagrams_sent"], a.recv(timeout=0.01) is None    # one datagram, no echo
(1, True)
>>> a.shutdown(); b.shutdown(); a.shutdown(); tmp.cleanup()
"""

from __future__ import annotations

import collections
import contextlib
import enum
import errno
import fcntl
import itertools
import os
import re
import select
import socket
import stat
import struct
import termios
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
from can.bus import BusState, CanProtocol

from drivers.protocol.batch import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE, FRAME_DTYPE, ID_MASK

#: Datagram header: magic, version, kind, frame count, sequence number, sender id.
HEADER = struct.Struct("<2sBBHIQ")
#: One frame: timestamp (s, sender's time.time()), id | flags, dlc, data padded to 8 (the
#: record of drivers.protocol.batch.FRAME_DTYPE).
RECORD = struct.Struct("<dIB8s")
MAGIC = b"HC"
VERSION = 1


class DatagramKind(enum.IntEnum):
    """What a datagram carries (the header's kind byte; only frames so far)."""

    FRAMES = 1


KIND_FRAMES = DatagramKind.FRAMES
#: Datagrams of up to this many frames are checked frame by frame, longer ones with NumPy.
SMALL_DATAGRAM_FRAMES = 4
#: Frames in one datagram (a longer send_many is split into datagrams of this many).
MAX_FRAMES_PER_DATAGRAM = 256
MAX_DATAGRAM_BYTES = HEADER.size + MAX_FRAMES_PER_DATAGRAM * RECORD.size
#: Default receive queue length (frames), about 18 s of a 36-drive bus at 100 Hz.
RX_QUEUE_FRAMES = 65_536
#: Default longest wait for a full peer in one send (s).
SEND_WAIT_S = 0.002
#: Send buffer asked for on each connection (bytes; the kernel caps it at wmem_max): what
#: a stalled reader can fall behind before frames to it are dropped.
SEND_BUFFER_BYTES = 4 * 1024 * 1024
#: Datagrams read from one connection per wake-up (fairness between senders).
READ_BURST = 64
#: The peer list is rescanned at least this often (s), and on every change of the folder.
RESCAN_S = 1.0
#: A folder changed less than this before the last scan is scanned again on the next send
#: (directory timestamps are coarse: two changes within one tick share one mtime).
MTIME_GRANULARITY_S = 0.05
CHANNEL_RE = re.compile(r"[A-Za-z0-9._-]{1,64}")
#: A frame's timestamp (the sender's ``time.time()``) must lie in [0, this): a NaN, an
#: infinity or a date past 2106 is a malformed datagram (a BLF log cannot hold it).
MAX_TIMESTAMP_S = 2.0**32
#: Connections an end accepts at once (the ends that send to it); one more is closed at
#: once and counted (``connections_refused``): a flood of connections cannot use up the
#: process's descriptors.
MAX_CONNECTIONS = 64
#: When accept(2) fails for want of descriptors, the listener is left unpolled this long
#: (s) instead of waking every receive at once (a busy loop).
ACCEPT_PAUSE_S = 0.1
LISTEN_BACKLOG = 128
#: Options python-can's configuration may add that this interface accepts and ignores.
_TOLERATED_OPTIONS = frozenset({"fd", "data_bitrate"})
#: Longest wait in shutdown() for a recv in another thread to let go (s).
SHUTDOWN_WAIT_S = 1.0
_MAX_BIND_TRIES = 1000
_MAX_SUN_PATH = 107  # bytes of a socket path (sockaddr_un.sun_path, less its NUL)

_counter = itertools.count()
_counter_lock = threading.Lock()


def default_directory() -> Path:
    """Where channel folders live unless ``directory`` is given: ``$XDG_RUNTIME_DIR`` or
    ``/tmp``.

    >>> isinstance(default_directory(), Path)
    True
    """
    return Path(os.environ.get("XDG_RUNTIME_DIR") or "/tmp")


def encode_frame(msg: can.Message, timestamp: float) -> bytes:
    """The 21-byte record of ``msg`` (raises ``can.CanOperationError`` for a frame classical
    CAN cannot carry).

    >>> msg = can.Message(arbitration_id=0x7FF, data=b"\\x01", is_extended_id=False)
    >>> r = encode_frame(msg, 1.5)
    >>> len(r), decode_frame(r)
    (21, (1.5, 2047, False, False, False, 1, b'\\x01'))
    """
    if msg.is_fd:
        raise can.CanOperationError("hrm_ipc: CAN FD frames are not supported")
    ident = int(msg.arbitration_id)
    data = bytes(msg.data) if msg.data is not None else b""
    dlc = int(msg.dlc)
    if len(data) > 8 or not 0 <= dlc <= 8:
        raise can.CanOperationError(
            f"hrm_ipc: frame 0x{ident:X} has {len(data)} data bytes, dlc {dlc} (at most 8)"
        )
    raw = ident
    if msg.is_extended_id:
        if not 0 <= ident <= ID_MASK:
            raise can.CanOperationError(f"hrm_ipc: extended id 0x{ident:X} out of range")
        raw |= FLAG_EXTENDED
    elif not 0 <= ident <= 0x7FF:
        raise can.CanOperationError(f"hrm_ipc: standard id 0x{ident:X} out of range")
    if msg.is_remote_frame:
        raw |= FLAG_REMOTE
    if msg.is_error_frame:
        raw |= FLAG_ERROR
    return RECORD.pack(timestamp, raw, dlc, data)


def decode_frame(record: bytes) -> tuple[float, int, bool, bool, bool, int, bytes] | None:
    """(timestamp, id, extended, remote, error, dlc, data) of a record, None if invalid.

    >>> decode_frame(RECORD.pack(0.0, 0x800, 0, bytes(8))) is None   # 11-bit id too big
    True
    """
    ts, raw, dlc, data = RECORD.unpack(record)
    return _check_record(ts, raw, dlc, data)


def _check_record(
    ts: float, raw: int, dlc: int, data: bytes
) -> tuple[float, int, bool, bool, bool, int, bytes] | None:
    ident = raw & ID_MASK
    ext = bool(raw & FLAG_EXTENDED)
    if dlc > 8 or (not ext and ident > 0x7FF) or not 0.0 <= ts < MAX_TIMESTAMP_S:  # NaN too
        return None
    rtr = bool(raw & FLAG_REMOTE)
    return ts, ident, ext, rtr, bool(raw & FLAG_ERROR), dlc, b"" if rtr else data[:dlc]


def _records_valid(records: np.ndarray, stamped: bool = False) -> bool:
    """Whether every record of a FRAME_DTYPE array is a classical CAN frame (dlc <= 8, an
    11-bit id unless extended, a timestamp in [0, :data:`MAX_TIMESTAMP_S`), unless
    ``stamped`` here):
    :func:`_check_record` for all of them (one by one for a few, with NumPy for more).

    >>> ok = np.zeros(5, FRAME_DTYPE); ok["id"] = [0x7FF, 0x181, FLAG_EXTENDED | ID_MASK, 0, 1]
    >>> bad = ok.copy(); bad["id"][1] = 0x800
    >>> _records_valid(ok), _records_valid(bad), _records_valid(bad[2:])
    (True, False, True)
    """
    if len(records) <= SMALL_DATAGRAM_FRAMES:
        return all(
            dlc <= 8
            and (raw & FLAG_EXTENDED or raw & ID_MASK <= 0x7FF)
            and 0.0 <= ts < MAX_TIMESTAMP_S
            for ts, raw, dlc, _data in records.tolist()
        )
    # an 11-bit frame has none of the id bits 11..28; x = id & (extended | those bits) is
    # 0 for a good 11-bit frame and >= 2**31 for an extended one: bad iff 0 < x < 2**31
    x = records["id"] & _STD_CHECK_MASK
    x -= 1  # wraps 0 to 2**32 - 1
    if int(x.min()) < FLAG_EXTENDED - 1 or int(records["dlc"].max()) > 8:
        return False
    if stamped:
        return True
    ts = records["timestamp"]  # NaN fails both comparisons
    return bool(float(ts.min()) >= 0.0 and float(ts.max()) < MAX_TIMESTAMP_S)


_STD_CHECK_MASK = np.uint32(FLAG_EXTENDED | (ID_MASK & ~0x7FF))


@dataclass
class _Chunk:
    """A received datagram's frames not yet taken: records ``pos`` .. ``count`` of ``data``."""

    data: bytes
    count: int
    is_rx: bool
    pos: int = 0


@dataclass
class _Peer:
    name: str
    sock: socket.socket
    sndbuf: int = 0  # the send buffer the kernel granted (bytes)
    seq: int = 0
    congested: bool = False  # until its unread bytes fall to half the buffer


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
    peers_dropped: int = 0
    stale_sockets_removed: int = 0
    rescans: int = 0
    connections_refused: int = 0
    accept_failures: int = 0


def _unread_bytes(sock: socket.socket) -> int:
    """Bytes sent on ``sock`` that its reader has not taken yet (``SIOCOUTQ``); 0 when the
    kernel does not say."""
    try:
        raw = fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
    except OSError:
        return 0
    return int(struct.unpack("i", raw)[0])


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


def _is_gone(exc: OSError) -> bool:
    return exc.errno in (
        errno.EPIPE,
        errno.ECONNRESET,
        errno.ECONNREFUSED,
        errno.ENOENT,
        errno.ENOTCONN,
    )


class IpcBus(can.BusABC):
    """One end of a cross-process bus: ``can.Bus(interface="hrm_ipc", channel=NAME)``.

    Keyword arguments: ``directory`` (folder holding the channel folders, default
    :func:`default_directory`), ``receive_own_messages`` (default False), ``bitrate``
    (accepted, informational: nothing is paced), ``rx_queue_size`` (frames, default
    :data:`RX_QUEUE_FRAMES`), ``send_wait_s`` (longest wait for a full peer per send, default
    :data:`SEND_WAIT_S`).  Opening fails with ``can.CanInitializationError`` naming the
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
        unknown = sorted(set(kwargs) - _TOLERATED_OPTIONS)
        if unknown:  # a misspelt option would silently put this end on another bus
            raise can.CanInitializationError(
                f"hrm_ipc channel {name!r}: unknown option {', '.join(unknown)} (known: "
                "directory, receive_own_messages, bitrate, rx_queue_size, send_wait_s, "
                "send_buffer_bytes, can_filters)"
            )
        if kwargs.get("fd"):
            raise can.CanInitializationError(
                f"hrm_ipc channel {name!r}: CAN FD is not supported (fd must be false)"
            )
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
        self._closed = True  # until the sockets exist (shutdown() is safe on a failed open)
        self._send_wait_s = wait
        self._rx_max = rx_queue_size
        self.receive_own_messages = bool(receive_own_messages)
        self.bitrate = bitrate
        self.folder = Path(directory if directory is not None else default_directory())
        self.folder = self.folder / f"hrm-ipc-{name}"
        # checked before the folder is made, so that a refused end leaves nothing behind:
        # the name _bind will use, with room for a counter of 6 digits (_bind checks again)
        longest = self.folder / f".{os.getpid()}-{10**6 - 1}.tmp"
        if len(os.fsencode(longest)) > _MAX_SUN_PATH:
            raise can.CanInitializationError(
                f"hrm_ipc: socket paths under {self.folder} would be longer than "
                f"{_MAX_SUN_PATH} bytes (pass a shorter directory=)"
            )
        self._make_folder()
        self._sender_id = int.from_bytes(os.urandom(8), "little")
        self._listener, self.path = self._bind()
        try:
            self._setup(name, can_filters)
        except BaseException:
            self._closed = True
            self._listener.close()
            self.path.unlink(missing_ok=True)
            for name_ in ("_epoll", "_event_fd"):
                obj = getattr(self, name_, None)
                if isinstance(obj, int):
                    os.close(obj)
                elif obj is not None:
                    obj.close()
            raise

    def _setup(self, name: str, can_filters: Any) -> None:
        self._own_name = self.path.name
        self._epoll = select.epoll()
        self._epoll.register(self._listener.fileno(), select.EPOLLIN)
        self._conns: dict[int, _Conn] = {}
        self._rx: collections.deque[_Chunk] = collections.deque()
        self._rx_len = 0  # frames in the receive queue
        # readable while frames wait in the queue (once fileno() was asked for) or on shutdown
        self._event_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._epoll.register(self._event_fd, select.EPOLLIN)
        self._fileno_used = False
        self._event_set = False
        self._peers: dict[str, _Peer] = {}
        self._dir_key: tuple[int, int, int] | None = None
        self._scan_t = 0.0
        self._scan_mtime = 0.0
        self._tx_lock = threading.Lock()
        self._sndbuf_effective = 0  # what the kernel granted on the last connection (bytes)
        self._local = threading.local()  # .records: frames held by batch() in this thread
        self._rx_lock = threading.RLock()
        self._n = _Counters()
        self._accept_paused_until: float | None = None  # listener out of epoll until then
        self._accept_lock = threading.Lock()  # the pause, against the re-arming timer
        self._closed = False
        self.channel_info = f"hrm_ipc {name} ({self.path})"
        self._can_protocol = CanProtocol.CAN_20
        super().__init__(channel=name, can_filters=can_filters)
        with self._tx_lock:
            self._scan()

    # ------------------------------------------------------------------ open
    def _make_folder(self) -> None:
        folder = self.folder
        try:
            folder.parent.mkdir(parents=True, exist_ok=True)
            try:
                folder.mkdir(mode=0o700)
            except FileExistsError:
                pass
            st = os.lstat(folder)
        except OSError as exc:
            raise can.CanInitializationError(
                f"hrm_ipc: cannot create channel folder {folder} ({exc.strerror})"
            ) from None
        if not stat.S_ISDIR(st.st_mode):
            raise can.CanInitializationError(f"hrm_ipc: {folder} is not a directory")
        if st.st_uid != os.geteuid() or st.st_mode & 0o077:
            raise can.CanInitializationError(
                f"hrm_ipc: {folder} must be a private folder of this user (mode 0700; it is "
                f"uid {st.st_uid}'s, mode {stat.S_IMODE(st.st_mode):04o}): remove it, or set "
                "XDG_RUNTIME_DIR or pass directory= for a folder of your own"
            )

    def _bind(self) -> tuple[socket.socket, Path]:
        """Bind and listen under a hidden name, then link the socket to ``<pid>-<n>.sock``:
        a peer never sees a socket file nobody listens on yet (it would take it for a stale
        one and unlink it), and an existing name is never replaced."""
        pid = os.getpid()
        for _ in range(_MAX_BIND_TRIES):
            with _counter_lock:
                n = next(_counter)
            path = self.folder / f"{pid}-{n}.sock"
            tmp = self.folder / f".{pid}-{n}.tmp"
            if len(os.fsencode(tmp)) > _MAX_SUN_PATH:
                raise can.CanInitializationError(
                    f"hrm_ipc: socket path {tmp} is longer than {_MAX_SUN_PATH} bytes "
                    "(pass a shorter directory=)"
                )
            sock = socket.socket(
                socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_NONBLOCK | socket.SOCK_CLOEXEC
            )
            try:
                try:
                    sock.bind(os.fspath(tmp))
                except OSError as exc:
                    if exc.errno == errno.EADDRINUSE:
                        sock.close()
                        continue  # left over by an earlier process with this pid: next n
                    if exc.errno == errno.ENOENT:  # the last end removed the empty folder
                        sock.close()
                        self._make_folder()
                        continue
                    raise
                try:
                    sock.listen(LISTEN_BACKLOG)
                    os.link(tmp, path)
                except FileExistsError:
                    sock.close()
                    continue
                finally:
                    tmp.unlink(missing_ok=True)
            except OSError as exc:
                sock.close()
                raise can.CanInitializationError(
                    f"hrm_ipc: cannot bind {path} ({exc.strerror})"
                ) from None
            return sock, path
        raise can.CanInitializationError(f"hrm_ipc: no free socket name in {self.folder}")

    # ------------------------------------------------------------------ peers
    def _refresh_peers(self) -> None:
        """Rescan the folder if it changed (or may have changed within one mtime tick)."""
        try:
            st = os.stat(self.folder)
        except OSError:
            return
        key = (st.st_mtime_ns, st.st_size, st.st_ino)
        now = time.time()
        if (
            key != self._dir_key
            or now - self._scan_t > RESCAN_S
            or self._scan_t - self._scan_mtime < MTIME_GRANULARITY_S
        ):
            self._dir_key = key
            self._scan_mtime = st.st_mtime_ns * 1e-9
            self._scan()

    def _scan(self) -> None:
        """Connect to every socket in the folder not connected yet; forget vanished ones."""
        self._scan_t = time.time()
        self._n.rescans += 1
        try:  # sockets named as an end names its own (d_type: no stat per entry)
            names = {
                e.name
                for e in os.scandir(self.folder)
                if _SOCKET_NAME.fullmatch(e.name)
                and not (e.is_symlink() or e.is_dir(follow_symlinks=False))
                and not e.is_file(follow_symlinks=False)
            }
        except OSError:
            return
        if not self.receive_own_messages:
            names.discard(self._own_name)
        for gone in set(self._peers) - names:
            self._peers.pop(gone).sock.close()
        for new in names - set(self._peers):
            sock = self._connect(new)
            if sock is not None:
                self._peers[new] = _Peer(new, sock, self._sndbuf_effective)

    def _connect(self, name: str) -> socket.socket | None:
        path = self.folder / name
        sock = socket.socket(
            socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_NONBLOCK | socket.SOCK_CLOEXEC
        )
        for opt in (getattr(socket, "SO_SNDBUFFORCE", None), socket.SO_SNDBUF):
            if opt is None:
                continue
            try:  # FORCE passes net.core.wmem_max where allowed (CAP_NET_ADMIN)
                sock.setsockopt(socket.SOL_SOCKET, opt, self._sndbuf)
                break
            except OSError:
                continue
        self._sndbuf_effective = sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF)
        ino = -1
        try:
            ino = os.stat(path).st_ino
            sock.connect(os.fspath(path))
            return sock
        except OSError as exc:
            sock.close()
            if exc.errno == errno.ECONNREFUSED:  # nobody listens: a crashed end's file
                self._unlink_stale(path, ino)
            elif exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                self._dir_key = None  # backlog full: try again on the next send
            return None

    def _unlink_stale(self, path: Path, ino: int) -> None:
        try:
            if os.stat(path).st_ino == ino:  # still the file that refused (not a new end's)
                path.unlink()
                self._n.stale_sockets_removed += 1
        except OSError:
            pass

    def _drop_peer(self, peer: _Peer) -> None:
        self._peers.pop(peer.name, None)
        peer.sock.close()
        self._n.peers_dropped += 1
        self._dir_key = None  # rescan on the next send: a stale file gets unlinked

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
        pending = getattr(self._local, "records", None)
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
        if getattr(local, "records", None) is not None:
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
        pending = getattr(self._local, "records", None)
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
        if not _records_valid(frames, stamped=True):
            raise can.CanOperationError(
                "hrm_ipc: a frame of the batch has more than 8 data bytes or an id out of range"
            )
        pending = getattr(self._local, "records", None)
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
            self._refresh_peers()
            deadline = None
            for peer in list(self._peers.values()):
                peer.seq = (peer.seq + 1) & 0xFFFFFFFF
                data = HEADER.pack(MAGIC, VERSION, KIND_FRAMES, n, peer.seq, self._sender_id)
                data += body
                try:
                    try:
                        peer.sock.send(data, socket.MSG_NOSIGNAL)
                    except BlockingIOError:
                        if peer.congested or budget <= 0.0:
                            raise
                        if deadline is None:
                            deadline = time.monotonic() + budget
                        self._n.tx_waits += 1
                        left = deadline - time.monotonic()
                        if left <= 0.0 or not self._wait_writable(peer.sock, left):
                            raise
                        peer.sock.send(data, socket.MSG_NOSIGNAL)
                except BlockingIOError:
                    peer.congested = True
                    self._n.tx_dropped_frames += n
                    continue
                except OSError as exc:
                    if _is_gone(exc):
                        self._drop_peer(peer)
                        continue
                    raise can.CanOperationError(
                        f"hrm_ipc channel {self.channel_info}: send failed ({exc.strerror})"
                    ) from None
                if peer.congested and _unread_bytes(peer.sock) <= peer.sndbuf // 2:
                    peer.congested = False  # a reader that keeps its buffer full is not
                    # waited for again on every send: only once it has caught up
                self._n.datagrams_sent += 1
            self._n.frames_sent += n

    @staticmethod
    def _wait_writable(sock: socket.socket, timeout_s: float) -> bool:
        p = select.poll()
        p.register(sock.fileno(), select.POLLOUT)
        return bool(p.poll(max(0, round(timeout_s * 1000.0 + 0.5))))

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
        size = len(data)
        if size < HEADER.size or size > MAX_DATAGRAM_BYTES:
            n.malformed_datagrams += 1
            return
        magic, version, kind, count, seq, sender = HEADER.unpack_from(data)
        if (
            magic != MAGIC
            or version != VERSION
            or kind != KIND_FRAMES
            or count == 0  # a header alone carries nothing (and would stick in the queue)
            or size != HEADER.size + count * RECORD.size
        ):
            n.malformed_datagrams += 1
            return
        if not _records_valid(np.frombuffer(data, FRAME_DTYPE, count, HEADER.size)):
            n.malformed_datagrams += 1
            return
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
        checked = _check_record(raw_ts, raw, raw_dlc, payload)
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
            "peers": len(self._peers),
            "peers_dropped": n.peers_dropped,
            "stale_sockets_removed": n.stale_sockets_removed,
            "rescans": n.rescans,
            "connections": len(self._conns),
            "connections_refused": n.connections_refused,
            "accept_failures": n.accept_failures,
            "send_buffer_bytes": self._sndbuf_effective,
            "rx_queued": self._rx_len,
        }

    def peer_names(self) -> list[str]:
        """Socket names of the ends this one currently sends to."""
        with self._tx_lock:
            self._refresh_peers()
            return sorted(self._peers)

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
            for peer in self._peers.values():
                peer.sock.close()
            self._peers.clear()
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
            {"interface": "hrm_ipc", "channel": e.name[len("hrm-ipc-") :]}
            for e in entries
            if e.name.startswith("hrm-ipc-") and e.is_dir(follow_symlinks=False)
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


_SOCKET_NAME = re.compile(r"([0-9]{1,10})-[0-9]{1,20}\.sock")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # gone, or no pid at all
        return False
    except OSError:  # EPERM (another user's: not ours to judge) and the like
        return True
    try:  # a zombie (killed, not yet reaped) is gone too
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rpartition(b")")[2].split()[:1] != [b"Z"]
    except OSError:
        return True


def _nobody_listens(path: Path) -> bool:
    """Whether the socket file ``path`` is stale: a connection to it is refused (what
    :meth:`IpcBus._connect` takes for a crashed end).  Anything else (accepted, a full
    backlog, another error): not known to be stale."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_NONBLOCK)
    try:
        sock.connect(os.fspath(path))
    except ConnectionRefusedError:
        return True
    except OSError:
        return False
    finally:
        sock.close()
    return False


def remove_stale_channels(
    prefix: str, directory: str | os.PathLike[str] | None = None
) -> list[Path]:
    """Remove the folders of channels named ``prefix...`` whose ends are all gone (left by
    processes killed before their :meth:`IpcBus.shutdown`): this user's private folder,
    every entry a ``<pid>-<n>.sock`` of no process here whose connection is refused.  The
    pid alone does not decide (a process of another PID namespace sharing the folder has
    a pid that means nothing here); a folder with any other entry (a socket being bound),
    with none, or with a socket that accepts is left alone.  The folders removed.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     dead = Path(d, "hrm-ipc-x-dead"); dead.mkdir(mode=0o700)
    ...     s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ...     s.bind(str(dead / "999999999-0.sock")); s.close()   # bound, never listened
    ...     live = open_ends("x-live", 1, d)[0]
    ...     [p.name for p in remove_stale_channels("x-", d)], live.path.exists()
    ...     live.shutdown()
    (['hrm-ipc-x-dead'], True)
    """
    base = Path(directory) if directory is not None else default_directory()
    removed: list[Path] = []
    try:
        folders = [e for e in os.scandir(base) if e.name.startswith("hrm-ipc-" + prefix)]
    except OSError:
        return removed
    for entry in folders:
        folder = Path(entry.path)
        try:
            st = os.lstat(folder)
            names = os.listdir(folder)
        except OSError:
            continue
        if (
            not stat.S_ISDIR(st.st_mode)
            or st.st_uid != os.geteuid()
            or st.st_mode & 0o077  # not a folder IpcBus made: not ours to judge
            or not names
        ):
            continue
        matches = [_SOCKET_NAME.fullmatch(n) for n in names]
        if any(m is None for m in matches):
            continue
        if any(m is not None and _pid_alive(int(m.group(1))) for m in matches):
            continue
        if not all(_nobody_listens(folder / n) for n in names):
            continue
        try:
            for name in names:
                os.unlink(folder / name)
            folder.rmdir()
        except OSError:
            continue
        removed.append(folder)
    return removed


__all__ = [
    "MAX_DATAGRAM_BYTES",
    "MAX_FRAMES_PER_DATAGRAM",
    "IpcBus",
    "decode_frame",
    "default_directory",
    "encode_frame",
    "open_ends",
    "remove_stale_channels",
]
