"""Sending to a peer that does not keep up: one short wait, then drops, counted.

A sender keeps one connection to every other end.  A peer whose send buffer is full is
waited for at most the send's budget (``send_wait_s``, default :data:`SEND_WAIT_S`, shared
by all the peers of one send: :class:`SendBudget`) once; from then on it is *congested*
and its datagrams are dropped without waiting until it has read half its buffer
(:func:`deliver`): a stalled or slow reader never stalls the sender's control cycle again
and again.  A peer that is gone is reported so (:attr:`Delivery.GONE`) for the caller to
drop.

>>> a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
>>> a.setblocking(False)
>>> peer = Peer("b", a, sndbuf=a.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF))
>>> deliver(peer, b"x", SendBudget(0.0)), b.recv(10)
(<Delivery.SENT: 1>, b'x')
>>> a.close(); b.close()
"""

from __future__ import annotations

import enum
import errno
import fcntl
import select
import socket
import struct
import termios
import time
from dataclasses import dataclass

#: Default longest wait for a full peer in one send (s).
SEND_WAIT_S = 0.002
#: Send buffer asked for on each connection (bytes; the kernel caps it at wmem_max): what
#: a stalled reader can fall behind before frames to it are dropped.
SEND_BUFFER_BYTES = 4 * 1024 * 1024


@dataclass
class Peer:
    """The connection to another end."""

    name: str
    sock: socket.socket
    sndbuf: int = 0  # the send buffer the kernel granted (bytes)
    seq: int = 0
    congested: bool = False  # until its unread bytes fall to half the buffer


class Delivery(enum.Enum):
    """What became of a datagram sent to a peer."""

    SENT = 1
    DROPPED = 2  # the peer's buffer is full: dropped (counted by the caller)
    GONE = 3  # the peer has closed or crashed: to be dropped


class SendBudget:
    """The wait one send may spend on full peers, all of them together: it starts at the
    first wait (``budget_s`` 0: never wait)."""

    def __init__(self, budget_s: float) -> None:
        self.budget_s = budget_s
        self.deadline: float | None = None
        self.waits = 0  # waits begun (counted as the bus's tx_waits)

    def wait_writable(self, sock: socket.socket) -> bool:
        """Wait for ``sock`` to take a datagram within what is left; whether it does."""
        if self.budget_s <= 0.0:
            return False
        if self.deadline is None:
            self.deadline = time.monotonic() + self.budget_s
        self.waits += 1
        left = self.deadline - time.monotonic()
        return left > 0.0 and writable_within(sock, left)


def writable_within(sock: socket.socket, timeout_s: float) -> bool:
    """Whether ``sock`` becomes writable within ``timeout_s``."""
    p = select.poll()
    p.register(sock.fileno(), select.POLLOUT)
    return bool(p.poll(max(0, round(timeout_s * 1000.0 + 0.5))))


def unread_bytes(sock: socket.socket) -> int:
    """Bytes sent on ``sock`` that its reader has not taken yet (``SIOCOUTQ``); 0 when the
    kernel does not say."""
    try:
        raw = fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
    except OSError:
        return 0
    return int(struct.unpack("i", raw)[0])


def is_gone(exc: OSError) -> bool:
    """Whether a send's error says the peer is gone (closed, crashed, its file removed)."""
    return exc.errno in (
        errno.EPIPE,
        errno.ECONNRESET,
        errno.ECONNREFUSED,
        errno.ENOENT,
        errno.ENOTCONN,
    )


def deliver(peer: Peer, data: bytes, budget: SendBudget) -> Delivery:
    """Send one datagram to ``peer``: a full peer that is not congested is waited for
    within ``budget`` once, then it is congested and dropped until it has caught up.  An
    ``OSError`` other than the peer being gone is raised."""
    sock = peer.sock
    try:
        try:
            sock.send(data, socket.MSG_NOSIGNAL)
        except BlockingIOError:
            if peer.congested or not budget.wait_writable(sock):
                raise
            sock.send(data, socket.MSG_NOSIGNAL)
    except BlockingIOError:
        peer.congested = True
        return Delivery.DROPPED
    except OSError as exc:
        if is_gone(exc):
            return Delivery.GONE
        raise
    if peer.congested and unread_bytes(sock) <= peer.sndbuf // 2:
        peer.congested = False  # a reader that keeps its buffer full is not waited for
        # again on every send: only once it has caught up
    return Delivery.SENT
