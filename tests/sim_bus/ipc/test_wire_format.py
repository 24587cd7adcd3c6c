"""``sim_bus.ipc.wire_format`` through the bus: frames round trip byte for byte, frames
classical CAN cannot carry are refused before any is sent, malformed datagrams are
counted and dropped."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim_bus.ipc import (
    HEADER,
    KIND_FRAMES,
    MAGIC,
    RECORD,
    VERSION,
    IpcBus,
    open_ends,
)
from tests.sim_bus.ipc.ipc_rig import connect_raw, drain, frame

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


def test_malformed_datagrams_are_counted_and_dropped(folder: str) -> None:
    a, b = open_ends("mal", 2, folder)
    raw = connect_raw(b.path)
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


def test_a_header_alone_does_not_wedge_the_receive_queue(folder: str) -> None:
    """A datagram of no frames was queued as an empty chunk: every recv after it raised
    (the simulated box's bus thread died of it), and such chunks escaped the queue's
    bound.  Red-team finding."""
    a, b = open_ends("empty", 2, folder)
    raw = connect_raw(b.path)
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
