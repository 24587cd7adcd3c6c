"""``sim_bus.ipc.bus`` (``IpcBus``, the ``hrm_ipc`` interface): delivery, echo, batching,
filters, processes, bounds, shutdown, ``fileno``."""

from __future__ import annotations

import errno
import os
import select
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import can
import pytest

from sim_bus.ipc import (
    HEADER,
    KIND_FRAMES,
    MAGIC,
    MAX_CONNECTIONS,
    MAX_FRAMES_PER_DATAGRAM,
    RECORD,
    VERSION,
    IpcBus,
    open_ends,
)
from tests.sim_bus.ipc.ipc_rig import ROOT, child, connect_raw, drain, frame


def test_entry_point_opens_an_ipc_bus(folder: str) -> None:
    bus = can.Bus(interface="hrm_ipc", channel="ep", directory=folder, bitrate=500_000)
    try:
        assert isinstance(bus, IpcBus)
        assert bus.bitrate == 500_000
        assert bus.path.parent == Path(folder) / "hrm-ipc-ep"
        assert (bus.path.parent.stat().st_mode & 0o777) == 0o700
        assert bus.path.exists()
    finally:
        bus.shutdown()


def test_detect_available_configs_lists_open_channels(
    folder: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", folder)
    a = can.Bus(interface="hrm_ipc", channel="det")
    try:
        assert a.path.parent == Path(folder, "hrm-ipc-det")
        found = can.detect_available_configs(interfaces=["hrm_ipc"])
        assert {"interface": "hrm_ipc", "channel": "det"} in found
    finally:
        a.shutdown()


def test_every_other_end_receives_and_no_echo(three: list[IpcBus]) -> None:
    a, b, c = three
    t0 = time.time()
    a.send(frame(0x181, 6, 7))
    t1 = time.time()
    for end in (b, c):
        m = end.recv(timeout=5.0)
        assert m is not None
        assert (m.arbitration_id, bytes(m.data), m.dlc) == (0x181, bytes([7] * 6), 6)
        assert m.is_rx and m.channel == "t3"
        assert t0 <= m.timestamp <= t1  # the sender's clock at the send
        assert end.recv(timeout=0.0) is None  # exactly once
    assert a.recv(timeout=0.05) is None


def test_echo_with_receive_own_messages(folder: str) -> None:
    a = IpcBus("echo", directory=folder, receive_own_messages=True)
    b = IpcBus("echo", directory=folder)
    try:
        a.send(frame(0x201, 2, 1))
        own = a.recv(timeout=5.0)
        other = b.recv(timeout=5.0)
        assert own is not None and other is not None
        assert own.arbitration_id == other.arbitration_id == 0x201
        assert own.is_rx is False and other.is_rx is True
        assert own.timestamp == other.timestamp
        b.send(frame(0x202))  # b does not echo
        assert a.recv(timeout=5.0).arbitration_id == 0x202
        assert b.recv(timeout=0.05) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_send_many_is_one_datagram_per_peer_in_order(three: list[IpcBus]) -> None:
    a, b, c = three
    batch = [frame(0x180 + k, 6, k) for k in range(1, 19)]
    a.send_many(batch)
    s = a.stats()
    assert (s["frames_sent"], s["datagrams_sent"], s["peers"]) == (18, 2, 2)
    for end in (b, c):
        got = drain(end, 18)
        assert [m.arbitration_id for m in got] == [m.arbitration_id for m in batch]
        assert [bytes(m.data) for m in got] == [bytes(m.data) for m in batch]
        assert end.stats()["datagrams_received"] == 1
        assert end.stats()["frames_received"] == 18
    # one send per frame: one datagram per frame and peer
    for m in batch[:3]:
        a.send(m)
    assert a.stats()["datagrams_sent"] == 2 + 3 * 2


def test_batch_block_holds_this_threads_frames_only(three: list[IpcBus]) -> None:
    a, b, _c = three
    with a.batch():
        a.send(frame(0x701, 1))
        with a.batch():  # nested: joins the outer block
            a.send_many([frame(0x181, 6), frame(0x182, 6)])
        t = threading.Thread(target=lambda: a.send(frame(0x77F, 1)))
        t.start()
        t.join(30.0)
        assert a.stats()["datagrams_sent"] == 2  # the other thread's frame left at once
        assert b.recv(timeout=5.0).arbitration_id == 0x77F
        assert b.recv(timeout=0.05) is None  # this thread's frames are still held
        a.send(frame(0x183, 6))
    assert a.stats()["datagrams_sent"] == 4
    assert [m.arbitration_id for m in drain(b, 4)] == [0x701, 0x181, 0x182, 0x183]
    assert b.stats()["datagrams_received"] == 2


def test_can_filters_apply(folder: str) -> None:
    a = IpcBus("flt", directory=folder)
    b = can.Bus(
        interface="hrm_ipc",
        channel="flt",
        directory=folder,
        can_filters=[{"can_id": 0x123, "can_mask": 0x7FF, "extended": False}],
    )
    try:
        a.send_many([frame(0x122), frame(0x123), frame(0x124)])
        assert b.recv(timeout=5.0).arbitration_id == 0x123
        assert b.recv(timeout=0.05) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_long_batch_is_split_and_stays_in_order(three: list[IpcBus]) -> None:
    a, b, _c = three
    n = MAX_FRAMES_PER_DATAGRAM + 44
    a.send_many([frame(k % 0x800, 1, k % 256) for k in range(n)])
    assert a.stats()["datagrams_sent"] == 2 * 2
    got = drain(b, n)
    assert [m.arbitration_id for m in got] == [k % 0x800 for k in range(n)]
    assert b.stats()["datagrams_received"] == 2


def test_send_order_across_calls(three: list[IpcBus]) -> None:
    a, b, _c = three
    for k in range(200):
        if k % 3:
            a.send(frame(k, 1, k))
        else:
            a.send_many([frame(k, 1, k)])
    got = drain(b, 200)
    assert [m.arbitration_id for m in got] == list(range(200))


def test_a_frame_crosses_to_a_child_process_and_back(folder: str) -> None:
    parent = IpcBus("kid", directory=folder)
    p = child(folder, "echo")
    try:
        assert len(parent.peer_names()) == 1
        parent.send(frame(0x300, 3, 9))
        got = drain(parent, 3, timeout_s=30.0)
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x301, bytes([9] * 3))] * 3
        assert parent.stats()["datagrams_received"] == 1  # the child's send_many: one datagram
    finally:
        p.stdin.close()
        p.wait(30.0)
        parent.shutdown()
    assert p.returncode == 0
    assert not (Path(folder) / "hrm-ipc-kid").exists()  # both ends unlinked, folder removed


def test_a_burst_from_another_process_arrives_complete_and_in_order(folder: str) -> None:
    parent = IpcBus("kid", directory=folder)
    p = child(folder, "burst")
    try:
        p.stdin.write("go\n")
        p.stdin.flush()
        got = drain(parent, 50 * 36 + 200, timeout_s=60.0)
        assert [m.arbitration_id for m in got] == [k % 0x800 for k in range(1800)] + list(
            range(200)
        )
        assert [bytes(m.data) for m in got[:36]] == [bytes([0, i]) for i in range(36)]
        s = parent.stats()
        assert s["datagrams_received"] == 50 + 200
        assert s["rx_sequence_gaps"] == 0 and s["rx_queue_dropped_frames"] == 0
    finally:
        p.stdin.close()
        p.wait(30.0)
        parent.shutdown()
    assert p.returncode == 0


_FORGER = textwrap.dedent(
    """
    import socket, sys
    s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    s.connect(sys.argv[1])
    s.settimeout(5.0)
    for x in sys.argv[2:]:
        s.send(bytes.fromhex(x))
    s.close()
    """
)


def test_another_process_claiming_this_ends_sender_id_is_dropped(folder: str) -> None:
    """Frames carrying an end's own sender id count as its own (``is_rx`` False, a Tx in
    a CAN log) only on a connection from its own process; from another process they are
    a forgery, counted malformed.  Red-team finding: a forged id showed as Tx."""
    a, b = open_ends("forge", 2, folder)
    try:
        rec = RECORD.pack(1.0, 0x181, 1, b"\x01" + bytes(7))
        forged = HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 1, 1, b._sender_id) + rec
        honest = HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 1, 2, 7) + rec
        subprocess.run(
            [sys.executable, "-c", _FORGER, str(b.path), forged.hex(), honest.hex()],
            check=True,
            timeout=60,
        )
        got = drain(b, 1)
        assert [(m.arbitration_id, m.is_rx) for m in got] == [(0x181, True)]
        assert b.stats()["malformed_datagrams"] == 1
        assert b.recv(timeout=0.05) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_connections_past_the_cap_are_closed_and_counted(folder: str) -> None:
    """A flood of idle connections cannot use up the end's descriptors (past the cap
    each is closed at once); frames from an accepted end still arrive."""
    a, b = open_ends("flood", 2, folder)
    extra = MAX_CONNECTIONS + 10
    raws: list[socket.socket] = []
    try:
        a.send(frame(0x180, 1))  # a connects to b (and stays: one of the cap)
        assert [m.arbitration_id for m in drain(b, 1)] == [0x180]
        for _ in range(extra):
            raws.append(connect_raw(b.path))
        a.send(frame(0x181, 1))
        assert [m.arbitration_id for m in drain(b, 1)] == [0x181]
        s = b.stats()
        assert s["connections"] == MAX_CONNECTIONS
        assert s["connections_refused"] == extra + 1 - MAX_CONNECTIONS
        closed = 0
        for r in raws:  # those refused read end-of-file
            r.setblocking(False)
            try:
                closed += r.recv(1) == b""
            except BlockingIOError:
                pass
        assert closed == extra + 1 - MAX_CONNECTIONS
    finally:
        for r in raws:
            r.close()
        a.shutdown()
        b.shutdown()


def test_shutdown_is_idempotent_and_unlinks(folder: str) -> None:
    a, b = open_ends("sd", 2, folder)
    path = a.path
    a.shutdown()
    a.shutdown()
    assert not path.exists()
    with pytest.raises(can.CanOperationError):
        a.send(frame(1))
    with pytest.raises(can.CanOperationError):
        a.recv(timeout=0.0)
    b.send(frame(2))  # b notices a is gone without an error
    assert b.peer_names() == []
    assert b.folder.is_dir()  # b still lives in it
    b.shutdown()
    b.shutdown()
    assert not b.folder.exists()  # the last end took the folder along
    c = IpcBus("sd", directory=folder)  # and the next one makes it again
    assert c.folder.is_dir() and c.path.exists()
    c.shutdown()


def test_shutdown_wakes_a_recv_waiting_in_another_thread(folder: str) -> None:
    (a,) = open_ends("wake", 1, folder)
    result: list[object] = []

    def wait() -> None:
        try:
            result.append(a.recv(timeout=60.0))
        except can.CanOperationError as exc:
            result.append(exc)

    t = threading.Thread(target=wait, daemon=True)
    t.start()
    time.sleep(0.05)
    a.shutdown()
    t.join(30.0)
    assert not t.is_alive()
    assert len(result) == 1 and isinstance(result[0], can.CanOperationError)


def test_recv_timeout_is_honoured(folder: str) -> None:
    a, b = open_ends("to", 2, folder)
    try:
        t = time.monotonic()
        assert b.recv(timeout=0.0) is None
        assert b.recv(timeout=0.2) is None
        elapsed = time.monotonic() - t
        assert 0.2 <= elapsed < 5.0
        # a waiting recv wakes for a frame sent from another thread
        threading.Timer(0.05, lambda: a.send(frame(0x77))).start()
        m = b.recv(timeout=10.0)
        assert m is not None and m.arbitration_id == 0x77
    finally:
        a.shutdown()
        b.shutdown()


def test_receive_queue_is_bounded_drop_oldest(folder: str) -> None:
    a = IpcBus("rq", directory=folder)
    b = IpcBus("rq", directory=folder, rx_queue_size=10)
    try:
        a.send_many([frame(k, 1) for k in range(15)])
        a.send_many([frame(0x100 + k, 1) for k in range(10)])
        first = b.recv(timeout=5.0)  # reads what the socket has: both datagrams
        rest = drain(b, 9, timeout_s=1.0)
        ids = [m.arbitration_id for m in [first, *rest]]
        assert ids == [0x100 + k for k in range(10)]
        assert b.stats()["rx_queue_dropped_frames"] == 15
    finally:
        a.shutdown()
        b.shutdown()


def test_fileno_readable_while_a_frame_waits(folder: str) -> None:
    a, b = open_ends("fd", 2, folder)
    try:
        fd = b.fileno()
        assert select.select([fd], [], [], 0.0)[0] == []
        a.send_many([frame(1), frame(2), frame(3)])
        assert select.select([fd], [], [], 5.0)[0] == [fd]
        assert b.recv(timeout=0.0).arbitration_id == 1
        assert select.select([fd], [], [], 0.0)[0] == [fd]  # two still queued
        assert [b.recv(0.0).arbitration_id for _ in range(2)] == [2, 3]
        assert select.select([fd], [], [], 0.0)[0] == []
    finally:
        a.shutdown()
        b.shutdown()


class _ListenerOutOfDescriptors:
    """An end's listening socket whose first ``accept`` fails as with no descriptor left."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.failures = 1

    def fileno(self) -> int:
        return self._sock.fileno()

    def accept(self) -> tuple[socket.socket, object]:
        if self.failures:
            self.failures -= 1
            raise OSError(errno.EMFILE, "Too many open files")
        return self._sock.accept()

    def close(self) -> None:
        self._sock.close()


def test_a_listener_paused_by_a_failed_accept_wakes_a_fileno_waiter(folder: str) -> None:
    """accept(2) without descriptors rests the listener 0.1 s; it was re-armed only inside
    a receive, so a user waiting on ``fileno()`` for a connection pending meanwhile never
    woke.  Red-team finding."""
    (b,) = open_ends("pause", 1, folder)
    b._listener = _ListenerOutOfDescriptors(b._listener)  # type: ignore[assignment]
    (a,) = open_ends("pause", 1, folder)
    try:
        fd = b.fileno()
        a.send(frame(0x181, 1))  # a connects to b: the listener is readable
        assert select.select([fd], [], [], 5.0)[0] == [fd]
        assert b.recv(timeout=0.0) is None  # the accept failed: the listener rests
        assert b.stats()["accept_failures"] == 1
        assert select.select([fd], [], [], 5.0)[0] == [fd]  # re-armed without a receive
        got = b.recv(timeout=1.0)
        assert got is not None and got.arbitration_id == 0x181
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.slow  # a whole `hrm sim` start (about 8 s on the loaded 2-core machine)
def test_hrm_sim_refuses_a_misspelt_option_in_one_line(folder: str) -> None:
    box = Path(folder, "box.toml")
    text = (ROOT / "drivers/data/box.toml").read_text()
    text = text.replace('interface = "socketcan"', 'interface = "hrm_ipc"')
    box.write_text(
        text
        + f'\n[buses.can0.options]\ndiretory = "{folder}"\n'
        + f'\n[buses.can1.options]\ndirectory = "{folder}"\n'
    )
    r = subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.cli", "sim", "--config", str(box), "--duration", "1"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "unknown option diretory" in lines[0] and "can0" in lines[0]
    assert "Traceback" not in r.stderr


def test_child_killed_mid_wait_does_not_hang_the_test(folder: str) -> None:
    """A child that never answers: the parent's recv returns on its timeout."""
    parent = IpcBus("kid", directory=folder)
    p = child(folder, "idle")
    try:
        parent.send(frame(0x5))
        assert parent.recv(timeout=0.1) is None
    finally:
        os.kill(p.pid, signal.SIGKILL)
        p.wait(30.0)
        parent.shutdown()
