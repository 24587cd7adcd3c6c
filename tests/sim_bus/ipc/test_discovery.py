"""``sim_bus.ipc.discovery``: a peer that is gone is dropped and its stale socket file
unlinked."""

from __future__ import annotations

import socket
from pathlib import Path

from sim_bus.ipc import (
    IpcBus,
)
from tests.sim_bus.ipc.ipc_rig import child, drain, frame


def test_a_dead_peer_is_dropped_and_its_stale_socket_unlinked(folder: str) -> None:
    a = IpcBus("kid", directory=folder)
    b = IpcBus("kid", directory=folder)
    p = child(folder, "idle")
    try:
        names = a.peer_names()
        assert len(names) == 2
        child_sock = next(Path(folder, "hrm-ipc-kid", n) for n in names if n != b.path.name)
        p.kill()
        p.wait(30.0)
        assert child_sock.exists()  # a killed process leaves its socket file behind
        a.send(frame(0x10))
        a.send(frame(0x11))
        s = a.stats()
        assert s["peers_dropped"] == 1
        assert s["stale_sockets_removed"] == 1
        assert not child_sock.exists()
        assert a.peer_names() == [b.path.name]
        assert [m.arbitration_id for m in drain(b, 2)] == [0x10, 0x11]  # b unaffected
    finally:
        p.kill()
        p.wait(30.0)
        a.shutdown()
        b.shutdown()


def test_a_stale_socket_file_is_unlinked_at_scan(folder: str) -> None:
    a = IpcBus("st", directory=folder)
    stale = Path(folder, "hrm-ipc-st", "999999-0.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    s.bind(str(stale))
    s.close()  # file stays, nobody listens
    try:
        assert a.peer_names() == []
        assert not stale.exists()
        assert a.stats()["stale_sockets_removed"] == 1
    finally:
        a.shutdown()
