"""The simulated CAN wire: entry point, pacing at the bitrate, arbitration, load, faults."""

from __future__ import annotations

import contextlib
import itertools
import time
import types
import uuid
from collections.abc import Iterator

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import sim_bus.wire as wire_module
from drivers.protocol.frames import frame_bits, stuff_bit_count
from hrm_ctrl.errors import SimError
from sim_bus.wire import SimWireBus, WireConfigError, get_wire


@pytest.fixture
def pair() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    ch = f"t-{uuid.uuid4().hex[:8]}"
    a = can.Bus(interface="hrm_sim", channel=ch, bitrate=1_000_000)
    b = can.Bus(interface="hrm_sim", channel=ch, bitrate=1_000_000)
    yield a, b
    a.shutdown()
    b.shutdown()


RECV_TIMEOUT_S = 5.0  # test_frames_are_paced_at_the_bitrate: a missed wake-up shows as this


def frame(cob: int, n: int = 8) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes(range(n)), is_extended_id=False)


@contextlib.contextmanager
def one_instant(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Every frame sent inside is offered to the wire at one instant of the wire's clock.

    The wire stamps a send with ``time.monotonic()``; with the other core busy the sending
    thread can be descheduled between two sends for longer than a frame's wire time, so the
    frames would no longer be pending together.  A CAN controller whose transmit mailboxes
    are filled in one go offers them at once: this models that, and the wire runs on real
    time again after the block.
    """
    t0 = time.monotonic()
    frozen = types.SimpleNamespace(monotonic=lambda: t0, time=time.time)
    monkeypatch.setattr(wire_module, "time", frozen)
    try:
        yield
    finally:
        monkeypatch.setattr(wire_module, "time", time)


def drain(
    bus: can.BusABC, n: int, timeout_s: float = 2.0, recv_timeout_s: float = 0.1
) -> list[can.Message]:
    out = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        m = bus.recv(recv_timeout_s)
        if m is not None:
            out.append(m)
    return out


def test_entry_point_selects_the_sim_wire(pair: tuple[can.BusABC, can.BusABC]) -> None:
    a, _b = pair
    assert isinstance(a, SimWireBus)
    assert get_wire(a.channel_info.split()[2]).bitrate == 1_000_000


def test_frames_are_paced_at_the_bitrate(pair: tuple[can.BusABC, can.BusABC]) -> None:
    a, b = pair
    t0 = time.monotonic()
    for i in range(40):
        a.send(frame(0x100 + i))
    got = drain(b, 40, timeout_s=20.0, recv_timeout_s=RECV_TIMEOUT_S)
    elapsed = time.monotonic() - t0
    assert len(got) == 40
    assert elapsed >= 40 * 135e-6  # cannot be faster than the wire
    gaps = [q.timestamp - p.timestamp for p, q in itertools.pairwise(got)]
    assert all(g > 135e-6 - 1e-6 for g in gaps)  # never closer than one frame's wire time
    assert sorted(gaps)[len(gaps) // 2] == pytest.approx(135e-6, abs=1e-6)  # back to back
    # Pick-up lateness is wall-clock (threads under the interpreter lock): with both cores
    # busy 25 of 150 runs picked a frame up 50-124 ms late, so it says nothing about the
    # wire at 50 ms.  What it can tell: a receiver that slept out its whole recv timeout
    # instead of waking at the next frame's end would be >= RECV_TIMEOUT_S late, so that
    # timeout is long and the bound is a fifth of it; the pacing itself is asserted on the
    # exact timestamps above (BENCHMARKS.md)
    assert a.wire.stats()["max_delivery_late_s"] < RECV_TIMEOUT_S / 5


def test_arbitration_order_when_several_are_pending(
    pair: tuple[can.BusABC, can.BusABC], monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b = pair
    with one_instant(monkeypatch):  # all six offered at one instant (wall time: flaky)
        a.send(frame(0x700))  # onto the idle wire: occupies it first
        for cob in (0x300, 0x180, 0x600, 0x080, 0x200):
            a.send(frame(cob))
    got = drain(b, 6)
    assert [m.arbitration_id for m in got] == [0x700, 0x080, 0x180, 0x200, 0x300, 0x600]
    gaps = [q.timestamp - p.timestamp for p, q in itertools.pairwise(got)]
    assert gaps == pytest.approx([135e-6] * 5, abs=1e-6)  # back to back (float epoch stamps)


def test_overload_shows_up_as_late_frames_and_bus_load(
    pair: tuple[can.BusABC, can.BusABC], monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b = pair
    # 13.5 ms of wire time offered at once: on wall time the 100 sends took ~2 ms, and a
    # sender descheduled 2 ms more would have left the last frame under the 10 ms this
    # asserted; at one instant of the wire's clock the last frame waits exactly 99 frames
    with one_instant(monkeypatch):
        for i in range(100):
            a.send(frame(0x200 + i % 64))
    got = drain(b, 100)
    assert len(got) == 100
    stats = a.wire.stats()
    assert stats["max_queue_delay_s"] == pytest.approx(99 * 135e-6, abs=1e-9)
    assert 0.005 < a.wire.bus_load(window_s=1.0) < 0.05  # 13.5 ms busy in the last second


def test_a_nodes_transmit_queue_is_bounded(
    pair: tuple[can.BusABC, can.BusABC], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A node that offers frames faster than the wire carries them fills its transmit
    queue, as a CAN controller's: the send past TX_QUEUE_FRAMES raises, the others' sends
    and the frames already queued are untouched (the wire's pending list stayed bounded
    under a flooding node)."""
    a, b = pair
    n = wire_module.TX_QUEUE_FRAMES + 1  # the first is on the wire at once, not queued
    with one_instant(monkeypatch):
        for _ in range(n):
            a.send(frame(0x1A5))
        with pytest.raises(can.CanOperationError, match="transmit queue full"):
            a.send(frame(0x1A5), timeout=0.0)  # 0: no wait (the wire's clock stands still)
        b.send(frame(0x181))  # another node's queue is its own
    got = drain(a, 1)
    assert [m.arbitration_id for m in got] == [0x181]
    assert len(drain(b, n, timeout_s=5.0)) == n
    a.send(frame(0x1A5))  # carried: room again
    assert [m.arbitration_id for m in drain(b, 1)] == [0x1A5]


def test_a_frame_is_copied_at_send(pair: tuple[can.BusABC, can.BusABC]) -> None:
    """A sender that reuses its message object (python-can code may) has each frame
    delivered as it was at send(), also while it waits for the wire."""
    a, b = pair
    msg = can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False)
    for k in range(20):  # sent faster than the wire carries them: most wait in the queue
        msg.arbitration_id = 0x100 + k
        msg.data[0] = k
        a.send(msg)
    msg.arbitration_id, msg.data[0], msg.is_extended_id = 0x7FF, 0xEE, True
    got = drain(b, 20)
    assert [(m.arbitration_id, m.data[0]) for m in got] == [(0x100 + k, k) for k in range(20)]
    assert not any(m.is_extended_id for m in got)


def test_send_waits_for_room_as_long_as_its_timeout_allows(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """python-can's send contract on a full transmit queue: ``timeout=0`` raises at once, a
    timeout waits that long and raises ``CanOperationError``, ``None`` blocks until a frame
    has left the wire.  A 100 bit/s wire carries one frame in 1.35 s, so the queue stays
    full through the timed wait."""
    monkeypatch.setattr(wire_module, "TX_QUEUE_FRAMES", 2)
    ch = f"t-{uuid.uuid4().hex[:8]}"
    a = can.Bus(interface="hrm_sim", channel=ch, bitrate=100)
    b = can.Bus(interface="hrm_sim", channel=ch, bitrate=100)
    try:
        t0 = time.monotonic()
        for k in range(3):  # one on the wire, two queued
            a.send(frame(0x200 + k))
        first_end = t0 + frame_bits(frame(0x200)) / 100
        with pytest.raises(can.CanOperationError, match="transmit queue full"):
            a.send(frame(0x210), timeout=0.0)
        start = time.monotonic()
        with pytest.raises(can.CanOperationError, match="transmit queue full"):
            a.send(frame(0x211), timeout=0.2)
        assert time.monotonic() - start >= 0.2
        assert time.monotonic() < first_end  # (the queue was full all along)
        a.send(frame(0x212))  # None: until the first frame has left the wire
        assert time.monotonic() >= first_end
        assert [m.arbitration_id for m in drain(b, 1, timeout_s=10.0)] == [0x200]
    finally:
        a.shutdown()
        b.shutdown()


def test_a_nodes_receive_queue_is_bounded_drop_oldest(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(wire_module, "RX_QUEUE_FRAMES", 8)
    ch = f"t-{uuid.uuid4().hex[:8]}"
    a = can.Bus(interface="hrm_sim", channel=ch)
    b = can.Bus(interface="hrm_sim", channel=ch)  # never reads until the end
    try:
        for i in range(20):
            a.send(frame(0x100 + i))
        time.sleep(20 * 135e-6 + 0.05)
        assert a.wire.stats()["rx_dropped"] == 12
        assert [m.arbitration_id for m in drain(b, 8)] == [0x100 + i for i in range(12, 20)]
        assert b.recv(0.01) is None
    finally:
        a.shutdown()
        b.shutdown()


def test_no_echo_unless_asked() -> None:
    ch = f"t-{uuid.uuid4().hex[:8]}"
    a = can.Bus(interface="hrm_sim", channel=ch, receive_own_messages=True)
    b = can.Bus(interface="hrm_sim", channel=ch)
    try:
        b.send(frame(0x123))
        assert b.recv(0.05) is None
        a.send(frame(0x124))
        assert [m.arbitration_id for m in drain(a, 2)] == [0x123, 0x124]
    finally:
        a.shutdown()
        b.shutdown()


def test_drop_delay_and_bus_off(pair: tuple[can.BusABC, can.BusABC]) -> None:
    a, b = pair
    w = a.wire
    w.drop(lambda m: m.arbitration_id == 0x181, count=2)
    for cob in (0x181, 0x181, 0x181, 0x182):
        a.send(frame(cob))
    assert [m.arbitration_id for m in drain(b, 2)] == [0x181, 0x182]
    w.delay(0.05, lambda m: m.arbitration_id == 0x183)
    t0 = time.monotonic()
    a.send(frame(0x183))
    a.send(frame(0x184))
    got = drain(b, 2)
    assert [m.arbitration_id for m in got] == [0x184, 0x183]
    assert time.monotonic() - t0 >= 0.05
    w.set_bus_off(True)
    assert a.state == can.BusState.ERROR
    with pytest.raises(can.CanOperationError, match="bus off"):
        a.send(frame(0x185))
    w.set_bus_off(False)
    a.send(frame(0x186))
    assert drain(b, 1)[0].arbitration_id == 0x186


def test_bitrate_mismatch_is_refused(pair: tuple[can.BusABC, can.BusABC]) -> None:
    a, _b = pair
    with pytest.raises(WireConfigError, match="500000"):
        can.Bus(interface="hrm_sim", channel=a.wire.channel, bitrate=500_000)
    with pytest.raises(SimError, match="not open"):
        get_wire("no-such-wire")


def test_worst_case_bits_known_values() -> None:
    assert frame_bits(frame(0x181, 8)) == 135
    assert frame_bits(frame(0x181, 6)) == 115  # 82 + 20 stuff + 13
    ext = can.Message(arbitration_id=0x18FF0000, data=bytes(8), is_extended_id=True)
    assert frame_bits(ext) == 160  # 118 + 29 + 13
    assert stuff_bit_count([1, 1, 1, 1, 1, 0, 0, 0]) == 1  # the stuff bit 0 joins the run
    assert stuff_bit_count([1, 1, 1, 1, 1, 0, 0, 0, 0]) == 2


@settings(max_examples=100, deadline=None)
@given(
    st.integers(0, 0x7FF),
    st.binary(min_size=0, max_size=8),
)
def test_exact_stuffing_between_unstuffed_and_worst_case(cob: int, data: bytes) -> None:
    m = can.Message(arbitration_id=cob, data=data, is_extended_id=False)
    unstuffed = 34 + 8 * len(data) + 13
    assert unstuffed <= frame_bits(m, "exact") <= frame_bits(m, "worst")
