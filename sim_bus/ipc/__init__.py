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

The package, one module per concept: :mod:`~sim_bus.ipc.wire_format` (the datagram: a
header and 21-byte frame records), :mod:`~sim_bus.ipc.folder` (the channel's private
folder, binding an end's socket), :mod:`~sim_bus.ipc.discovery` (finding the other ends),
:mod:`~sim_bus.ipc.congestion` (a peer that does not keep up), :mod:`~sim_bus.ipc.cleanup`
(folders left by killed processes) and :mod:`~sim_bus.ipc.bus` (:class:`IpcBus`).

Bounds: :data:`MAX_FRAMES_PER_DATAGRAM` frames (a longer
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

>>> import can, tempfile
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

from sim_bus.ipc.bus import MAX_CONNECTIONS, RX_QUEUE_FRAMES, IpcBus, open_ends
from sim_bus.ipc.cleanup import remove_stale_channels
from sim_bus.ipc.congestion import SEND_WAIT_S
from sim_bus.ipc.folder import default_directory
from sim_bus.ipc.wire_format import (
    HEADER,
    KIND_FRAMES,
    MAGIC,
    MAX_DATAGRAM_BYTES,
    MAX_FRAMES_PER_DATAGRAM,
    MAX_TIMESTAMP_S,
    RECORD,
    VERSION,
    decode_frame,
    encode_frame,
)

__all__ = [
    "HEADER",
    "KIND_FRAMES",
    "MAGIC",
    "MAX_CONNECTIONS",
    "MAX_DATAGRAM_BYTES",
    "MAX_FRAMES_PER_DATAGRAM",
    "MAX_TIMESTAMP_S",
    "RECORD",
    "RX_QUEUE_FRAMES",
    "SEND_WAIT_S",
    "VERSION",
    "IpcBus",
    "decode_frame",
    "default_directory",
    "encode_frame",
    "open_ends",
    "remove_stale_channels",
]
