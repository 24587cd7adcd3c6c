"""The cross-process bus ``hrm_ipc``: delivery, echo, batching, round trip, bounds, peers."""

from __future__ import annotations

import errno
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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
    remove_stale_channels,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def folder() -> Iterator[str]:
    # short: a Unix socket path is at most 107 bytes (pytest's tmp_path can be longer)
    with tempfile.TemporaryDirectory(prefix="hrm-ipc-t") as d:
        yield d


@pytest.fixture
def three(folder: str) -> Iterator[list[IpcBus]]:
    ends = open_ends("t3", 3, folder)
    yield ends
    for e in ends:
        e.shutdown()


def frame(cob: int, n: int = 8, fill: int = 0) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes([fill] * n), is_extended_id=False)


def drain(bus: IpcBus, n: int, timeout_s: float = 5.0) -> list[can.Message]:
    out: list[can.Message] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        m = bus.recv(timeout=0.2)
        if m is not None:
            out.append(m)
    return out


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


# one pair of ends for every Hypothesis example (function-scoped fixtures do not mix with @given)
_pair: list[IpcBus] = []


@pytest.fixture(scope="module")
def hyp_pair() -> Iterator[list[IpcBus]]:
    with tempfile.TemporaryDirectory(prefix="hrm-ipc-h") as d:
        _pair.extend(open_ends("hyp", 2, d))
        yield _pair
        for e in _pair:
            e.shutdown()
        _pair.clear()


@st.composite
def can_frames(draw: st.DrawFn) -> can.Message:
    ext = draw(st.booleans())
    ident = draw(st.integers(0, 0x1FFFFFFF if ext else 0x7FF))
    rtr = draw(st.booleans())
    err = draw(st.booleans())
    dlc = draw(st.integers(0, 8))
    data = b"" if rtr else draw(st.binary(min_size=dlc, max_size=dlc))
    return can.Message(
        arbitration_id=ident,
        is_extended_id=ext,
        is_remote_frame=rtr,
        is_error_frame=err,
        dlc=dlc,
        data=data,
        check=False,
    )


def test_frames_round_trip_byte_for_byte(hyp_pair: list[IpcBus]) -> None:
    _round_trip()


@settings(max_examples=60, deadline=None)
@given(st.lists(can_frames(), min_size=1, max_size=20))
def _round_trip(msgs: list[can.Message]) -> None:
    a, b = _pair
    a.send_many(msgs)
    got = drain(b, len(msgs))
    assert len(got) == len(msgs)
    for sent, m in zip(msgs, got, strict=True):
        assert m.arbitration_id == sent.arbitration_id
        assert m.is_extended_id == sent.is_extended_id
        assert m.is_remote_frame == sent.is_remote_frame
        assert m.is_error_frame == sent.is_error_frame
        assert m.dlc == sent.dlc
        assert bytes(m.data) == bytes(sent.data)
    assert b.recv(timeout=0.0) is None


def test_unsendable_frames_are_refused_before_any_is_sent(three: list[IpcBus]) -> None:
    a, b, _c = three
    bad = [
        can.Message(arbitration_id=0x800, is_extended_id=False),
        can.Message(arbitration_id=0x20000000, is_extended_id=True),
        can.Message(arbitration_id=1, data=bytes(12), is_fd=True, is_extended_id=False),
    ]
    for m in bad:
        with pytest.raises(can.CanOperationError):
            a.send_many([frame(1), m])
    assert a.stats()["frames_sent"] == 0
    assert b.recv(timeout=0.05) is None


_CHILD = textwrap.dedent(
    """
    import sys, can
    bus = can.Bus(interface="hrm_ipc", channel="kid", directory=sys.argv[1])
    print("ready", flush=True)
    if sys.argv[2] == "echo":
        m = bus.recv(timeout=20.0)
        bus.send_many([can.Message(arbitration_id=m.arbitration_id + 1, data=m.data,
                                   is_extended_id=m.is_extended_id)] * 3)
        print("sent", flush=True)
    if sys.argv[2] == "burst":
        sys.stdin.readline()  # the parent is listening
        for k in range(50):
            bus.send_many([can.Message(arbitration_id=(36 * k + i) % 0x800, data=[k, i],
                                       is_extended_id=False) for i in range(36)])
        for k in range(200):
            bus.send(can.Message(arbitration_id=k, data=[k], is_extended_id=False))
        print("sent", flush=True)
    sys.stdin.read()          # wait until the parent closes stdin (or kills us)
    bus.shutdown()
    """
)


def _child(folder: str, mode: str) -> subprocess.Popen[str]:
    p = subprocess.Popen(
        [sys.executable, "-c", _CHILD, folder, mode],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    ready: list[str] = []
    t = threading.Thread(target=lambda: ready.append(p.stdout.readline()), daemon=True)
    t.start()
    t.join(60.0)
    if ready != ["ready\n"]:
        p.kill()
        p.wait(10.0)
        pytest.fail(f"child did not come up: {ready!r}")
    return p


def test_a_frame_crosses_to_a_child_process_and_back(folder: str) -> None:
    parent = IpcBus("kid", directory=folder)
    p = _child(folder, "echo")
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
    p = _child(folder, "burst")
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


def test_a_dead_peer_is_dropped_and_its_stale_socket_unlinked(folder: str) -> None:
    a = IpcBus("kid", directory=folder)
    b = IpcBus("kid", directory=folder)
    p = _child(folder, "idle")
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


def test_the_folder_of_a_channel_whose_ends_were_killed_is_removed(folder: str) -> None:
    """A process killed before its shutdown leaves the channel folder with its socket;
    a live end's folder is kept, and so is a folder of another prefix."""
    p = _child(folder, "idle")
    live = IpcBus("kid-live", directory=folder)
    other = Path(folder, "hrm-ipc-other")
    other.mkdir()
    Path(other, "999999999-0.sock").touch()  # stale, but not ours to remove
    try:
        p.kill()
        p.wait(30.0)
        stale = Path(folder, "hrm-ipc-kid")
        assert [f.name for f in stale.iterdir()] == [f"{p.pid}-0.sock"]  # left behind
        assert remove_stale_channels("kid", folder) == [stale]
        assert not stale.exists()
        assert live.path.exists() and other.exists()
        assert remove_stale_channels("kid", folder) == []
    finally:
        live.shutdown()


def test_a_listening_end_under_a_pid_unknown_here_is_kept(folder: str) -> None:
    """An end of another PID namespace (its pid names no process here) still listens: its
    channel stays.  A pid too large for a pid, a stale socket: removed, no error.  A
    folder that is not private (not one IpcBus made): left alone."""
    ns = Path(folder, "hrm-ipc-ns")
    ns.mkdir(mode=0o700)
    listening = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listening.bind(str(ns / "999999999-0.sock"))
    listening.listen(1)
    huge = Path(folder, "hrm-ipc-ns-huge")
    huge.mkdir(mode=0o700)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(huge / "9999999999-0.sock"))
    stale.close()
    public = Path(folder, "hrm-ipc-ns-public")
    public.mkdir(mode=0o755)
    public.chmod(0o755)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(public / "999999999-0.sock"))
    stale.close()
    try:
        assert remove_stale_channels("ns", folder) == [huge]
        assert (ns / "999999999-0.sock").exists() and public.exists()
    finally:
        listening.close()


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


def _raw(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    s.connect(str(path))
    return s


def test_malformed_datagrams_are_counted_and_dropped(folder: str) -> None:
    a, b = open_ends("mal", 2, folder)
    raw = _raw(b.path)
    try:
        good = RECORD.pack(1.0, 0x123, 1, b"\x01" + bytes(7))
        hdr = HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 1, 1, 42)
        bad = [
            b"x",  # shorter than a header
            HEADER.pack(b"XX", VERSION, KIND_FRAMES, 1, 1, 42) + good,  # magic
            HEADER.pack(MAGIC, 99, KIND_FRAMES, 1, 1, 42) + good,  # version
            HEADER.pack(MAGIC, VERSION, 7, 1, 1, 42) + good,  # kind
            HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 2, 1, 42) + good,  # count vs size
            hdr + good[:-1],  # truncated record
            hdr + RECORD.pack(1.0, 0x123, 9, bytes(8)),  # dlc 9
            hdr + RECORD.pack(1.0, 0x800, 1, bytes(8)),  # 11-bit id too big
            hdr + RECORD.pack(float("nan"), 0x123, 1, bytes(8)),  # timestamp
            hdr + RECORD.pack(float("inf"), 0x123, 1, bytes(8)),  # a BLF log cannot hold
            hdr + RECORD.pack(1e12, 0x20000123, 0, bytes(8)),  # an error frame in year 33658
            hdr + RECORD.pack(-1.0, 0x123, 1, bytes(8)),  # before 1970
            HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 0, 1, 42),  # a header alone
            HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 5, 1, 42)  # NumPy's check: one bad ts
            + good * 4
            + RECORD.pack(float("inf"), 0x123, 1, bytes(8)),
            bytes(70_000),  # larger than any datagram
        ]
        for d in bad:
            raw.send(d)
        raw.send(hdr + good)  # a well-formed one from the same sender still gets through
        a.send(frame(0x124, 1))
        got = drain(b, 2)
        assert sorted(m.arbitration_id for m in got) == [0x123, 0x124]
        assert b.stats()["malformed_datagrams"] == len(bad)
        assert b.recv(timeout=0.05) is None
    finally:
        raw.close()
        a.shutdown()
        b.shutdown()


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


def test_a_header_alone_does_not_wedge_the_receive_queue(folder: str) -> None:
    """A datagram of no frames was queued as an empty chunk: every recv after it raised
    (the simulated box's bus thread died of it), and such chunks escaped the queue's
    bound.  Red-team finding."""
    a, b = open_ends("empty", 2, folder)
    raw = _raw(b.path)
    try:
        raw.settimeout(5.0)
        for _ in range(20):  # 5 at a time: a few fit in b's socket queue unread
            for _ in range(5):
                raw.send(HEADER.pack(MAGIC, VERSION, KIND_FRAMES, 0, 1, 42))
            assert b.recv(timeout=0.01) is None
        a.send(frame(0x181, 2))
        got = drain(b, 1)
        assert [m.arbitration_id for m in got] == [0x181]
        assert b.stats()["malformed_datagrams"] == 100
        assert b.stats()["rx_queued"] == 0
    finally:
        raw.close()
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
            raws.append(_raw(b.path))
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


@pytest.mark.parametrize(
    ("channel", "words"),
    [("", "channel"), ("a/b", "channel"), ("x" * 65, "channel")],
)
def test_bad_channel_is_refused(folder: str, channel: str, words: str) -> None:
    with pytest.raises(can.CanInitializationError, match=words):
        IpcBus(channel, directory=folder)


def test_unsafe_or_long_folder_is_refused(folder: str) -> None:
    open_dir = Path(folder, "hrm-ipc-pub")
    open_dir.mkdir(mode=0o755)
    open_dir.chmod(0o755)
    private = r"private folder of this user \(mode 0700; it is uid \d+'s, mode 0755\)"
    with pytest.raises(can.CanInitializationError, match=private):
        IpcBus("pub", directory=folder)
    Path(folder, "hrm-ipc-file").write_text("")
    with pytest.raises(can.CanInitializationError, match="not a directory"):
        IpcBus("file", directory=folder)
    deep = Path(folder, "d" * 90)
    with pytest.raises(can.CanInitializationError, match="107"):
        IpcBus("long", directory=deep)
    assert not deep.exists()  # refused before any folder was made
    with pytest.raises(can.CanInitializationError, match="rx_queue_size"):
        IpcBus("q", directory=folder, rx_queue_size=0)
    with pytest.raises(can.CanInitializationError, match="unknown option diretory"):
        can.Bus(interface="hrm_ipc", channel="q", diretory=folder)
    with pytest.raises(can.CanInitializationError, match="FD"):
        can.Bus(interface="hrm_ipc", channel="q", directory=folder, fd=True)
    assert list(Path(folder).glob("*/*.sock")) == []  # nothing left by the refused opens


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
    p = _child(folder, "idle")
    try:
        parent.send(frame(0x5))
        assert parent.recv(timeout=0.1) is None
    finally:
        os.kill(p.pid, signal.SIGKILL)
        p.wait(30.0)
        parent.shutdown()
