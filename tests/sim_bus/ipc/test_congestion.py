"""``sim_bus.ipc.congestion``: a full peer costs one short wait, then its frames are
dropped and counted until it has caught up."""

from __future__ import annotations

import os
import socket

from sim_bus.ipc import (
    MAX_FRAMES_PER_DATAGRAM,
    IpcBus,
)
from tests.sim_bus.ipc.ipc_rig import frame


def test_a_full_peer_costs_one_short_wait_then_drops_counted(folder: str) -> None:
    a = IpcBus("full", directory=folder, send_wait_s=0.002, send_buffer_bytes=65_536)
    b = IpcBus("full", directory=folder)  # never reads until the end
    assert a.peer_names() == [b.path.name]
    assert 65_536 <= a.stats()["send_buffer_bytes"] <= 4 * 65_536  # Linux doubles it
    try:
        batch = [frame(k % 0x800, 8) for k in range(MAX_FRAMES_PER_DATAGRAM)]
        sends = 0
        while a.stats()["tx_dropped_frames"] == 0 and sends < 100_000:
            a.send_many(batch)
            sends += 1
        assert a.stats()["tx_dropped_frames"] == len(batch)
        for _ in range(20):  # congested: dropped at once, no further wait
            a.send_many(batch)
        s = a.stats()
        assert s["tx_waits"] == 1
        assert s["tx_dropped_frames"] == 21 * len(batch)
        delivered = s["datagrams_sent"]
        assert delivered == sends - 1
        # the reader catches up: everything sent arrives, the gap is seen, sending resumes
        n = 0
        while b.recv(timeout=0.5) is not None:
            n += 1
        assert n == delivered * len(batch)
        a.send(frame(0x7FF))
        assert b.recv(timeout=5.0).arbitration_id == 0x7FF
        assert b.stats()["rx_sequence_gaps"] == 21
    finally:
        a.shutdown()
        b.shutdown()


def test_a_reader_that_keeps_its_buffer_full_is_not_waited_for_again(folder: str) -> None:
    """A slow reader taking one datagram now and then made every send wait ``send_wait_s``
    again (a send that went through cleared the congestion): a red-team end reading one
    datagram per cycle made the host's SYNC p99 4.6 ms late.  Congestion now lasts until
    the peer has read half its buffer."""
    a = IpcBus("slow", directory=folder, send_wait_s=0.002, send_buffer_bytes=65_536)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)  # an end that reads
    listener.bind(str(a.folder / f"{os.getpid()}-999999.sock"))  # one datagram at a time
    listener.listen()
    listener.settimeout(5.0)
    try:
        batch = [frame(k % 0x800, 8) for k in range(MAX_FRAMES_PER_DATAGRAM)]
        a.send_many(batch)  # a connects to it
        slow, _ = listener.accept()
        slow.settimeout(5.0)
        sends = 0
        while a.stats()["tx_dropped_frames"] == 0 and sends < 100_000:
            a.send_many(batch)
            sends += 1
        assert a.stats()["tx_waits"] == 1
        for _ in range(5):  # it reads one datagram, the sender fills its place
            assert len(slow.recv(1 << 16)) > 0
            a.send_many(batch)
            a.send_many(batch)
        assert a.stats()["tx_waits"] == 1  # not 6
        slow.setblocking(False)
        try:  # it catches up: delivered again
            while slow.recv(1 << 16):
                pass
        except BlockingIOError:
            pass
        dropped = a.stats()["tx_dropped_frames"]
        a.send(frame(0x7FF))
        assert a.stats()["tx_dropped_frames"] == dropped
        slow.close()
    finally:
        listener.close()
        a.shutdown()


def test_a_sends_wait_is_shared_and_a_congested_peer_is_not_waited_for() -> None:
    """Two full peers in one send: both waited for within the one budget (a deadline set
    at the first wait), both dropped and congested; a congested peer is not waited for on
    the next send, and is taken again once its reader has caught up."""
    from sim_bus.ipc.congestion import Delivery, Peer, SendBudget, deliver

    pairs = [socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET) for _ in range(2)]
    try:
        peers = []
        for k, (mine, _theirs) in enumerate(pairs):
            mine.setblocking(False)
            mine.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
            peers.append(Peer(f"p{k}", mine, mine.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF)))
            while True:  # fill its buffer
                try:
                    mine.send(bytes(512))
                except BlockingIOError:
                    break
        budget = SendBudget(0.02)
        assert [deliver(p, bytes(512), budget) for p in peers] == [Delivery.DROPPED] * 2
        assert budget.waits == 2 and budget.deadline is not None
        assert all(p.congested for p in peers)
        again = SendBudget(0.02)
        assert deliver(peers[0], bytes(512), again) is Delivery.DROPPED and again.waits == 0
        theirs = pairs[0][1]
        theirs.setblocking(False)
        while True:  # the reader catches up
            try:
                theirs.recv(4096)
            except BlockingIOError:
                break
        assert deliver(peers[0], bytes(512), again) is Delivery.SENT
        assert not peers[0].congested
    finally:
        for a, b in pairs:
            a.close()
            b.close()
