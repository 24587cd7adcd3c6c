"""Finding the other ends of a channel: the sockets in its folder.

There is no broker: a sender connects to every ``<pid>-<n>.sock`` in the channel's folder
(:class:`Peers`).  The folder is rescanned when it changes (its mtime, size and inode),
at least every :data:`RESCAN_S`, and on the next send after a scan that fell within one
mtime tick of a change.  A socket whose connection is refused belongs to a crashed end:
its file is unlinked (only if it is still the file that refused).  A full listen backlog
is tried again on the next send.

>>> import tempfile
>>> from sim_bus.ipc.folder import bind, channel_folder, make_folder
>>> with tempfile.TemporaryDirectory() as d:
...     folder = channel_folder(d, "doc-peers")
...     make_folder(folder)
...     (s1, p1), (s2, p2) = bind(folder), bind(folder)
...     peers = Peers(folder, own_name=p1.name, include_own=False, sndbuf_bytes=65536)
...     peers.scan()
...     print(sorted(peers.by_name) == [p2.name], peers.rescans)
...     peers.close(); s1.close(); s2.close()
True 1
"""

from __future__ import annotations

import errno
import os
import socket
import time
from pathlib import Path

from sim_bus.ipc.congestion import Peer
from sim_bus.ipc.folder import SOCKET_NAME

#: The peer list is rescanned at least this often (s), and on every change of the folder.
RESCAN_S = 1.0
#: A folder changed less than this before the last scan is scanned again on the next send
#: (directory timestamps are coarse: two changes within one tick share one mtime).
MTIME_GRANULARITY_S = 0.05


class Peers:
    """The ends this one sends to, by socket name; the caller holds its send lock."""

    def __init__(self, folder: Path, own_name: str, include_own: bool, sndbuf_bytes: int) -> None:
        self.folder = folder
        self.own_name = own_name
        self.include_own = include_own  # receive_own_messages: this end sends to itself
        self.sndbuf_bytes = sndbuf_bytes
        self.by_name: dict[str, Peer] = {}
        self.sndbuf_effective = 0  # what the kernel granted on the last connection (bytes)
        self.rescans = 0
        self.stale_sockets_removed = 0
        self.peers_dropped = 0
        self._dir_key: tuple[int, int, int] | None = None
        self._scan_t = 0.0
        self._scan_mtime = 0.0

    def refresh(self) -> None:
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
            self.scan()

    def scan(self) -> None:
        """Connect to every socket in the folder not connected yet; forget vanished ones."""
        self._scan_t = time.time()
        self.rescans += 1
        try:  # sockets named as an end names its own (d_type: no stat per entry)
            names = {
                e.name
                for e in os.scandir(self.folder)
                if SOCKET_NAME.fullmatch(e.name)
                and not (e.is_symlink() or e.is_dir(follow_symlinks=False))
                and not e.is_file(follow_symlinks=False)
            }
        except OSError:
            return
        if not self.include_own:
            names.discard(self.own_name)
        for gone in set(self.by_name) - names:
            self.by_name.pop(gone).sock.close()
        for new in names - set(self.by_name):
            sock = self._connect(new)
            if sock is not None:
                self.by_name[new] = Peer(new, sock, self.sndbuf_effective)

    def _connect(self, name: str) -> socket.socket | None:
        path = self.folder / name
        sock = socket.socket(
            socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_NONBLOCK | socket.SOCK_CLOEXEC
        )
        try:  # the kernel caps it at net.core.wmem_max (what it granted is read back)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.sndbuf_bytes)
        except OSError:
            pass
        self.sndbuf_effective = sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF)
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
                self.stale_sockets_removed += 1
        except OSError:
            pass

    def drop(self, peer: Peer) -> None:
        """Forget a peer that is gone; rescan on the next send (its stale file unlinked)."""
        self.by_name.pop(peer.name, None)
        peer.sock.close()
        self.peers_dropped += 1
        self._dir_key = None

    def close(self) -> None:
        for peer in self.by_name.values():
            peer.sock.close()
        self.by_name.clear()
