"""The simulated CAN wire: entry point, pacing at the bitrate, arbitration, load, faults."""

from __future__ import annotations

import itertools
import time
import uuid
from collections.abc import Iterator

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


def frame(cob: int, n: int = 8) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes(range(n)), is_extended_id=False)


def drain(bus: can.BusABC, n: int, timeout_s: float = 2.0) -> list[can.Message]:
    out = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        m = bus.recv(0.1)
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
    got = drain(b, 40)
    elapsed = time.monotonic() - t0
    assert len(got) == 40
    assert elapsed >= 40 * 135e-6  # cannot be faster than the wire
    gaps = [q.timestamp - p.timestamp for p, q in itertools.pairwise(got)]
    assert all(g > 135e-6 - 1e-6 for g in gaps)  # never closer than one frame's wire time
    assert sorted(gaps)[len(gaps) // 2] == pytest.approx(135e-6, abs=1e-6)  # back to back
    # pick-up lateness is wall-clock (threads under the interpreter lock): a sanity bound
    # only; the pacing itself is asserted on the exact timestamps above (BENCHMARKS.md)
    assert a.wire.stats()["max_delivery_late_s"] < 0.05


def test_arbitration_order_when_several_are_pending(pair: tuple[can.BusABC, can.BusABC]) -> None:
    a, b = pair
    a.send(frame(0x700))  # occupies the wire first
    for cob in (0x300, 0x180, 0x600, 0x080, 0x200):
        a.send(frame(cob))
    ids = [m.arbitration_id for m in drain(b, 6)]
    assert ids == [0x700, 0x080, 0x180, 0x200, 0x300, 0x600]


def test_overload_shows_up_as_late_frames_and_bus_load(
    pair: tuple[can.BusABC, can.BusABC],
) -> None:
    a, b = pair
    for i in range(100):  # 13.5 ms of wire time offered at once
        a.send(frame(0x200 + i % 64))
    got = drain(b, 100)
    assert len(got) == 100
    stats = a.wire.stats()
    assert stats["max_queue_delay_s"] > 0.010
    assert 0.005 < a.wire.bus_load(window_s=1.0) < 0.05  # 13.5 ms busy in the last second


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
