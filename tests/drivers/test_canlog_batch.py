"""Batches in the CAN log (``TrafficLog.log_batch``): a batch is queued as one entry, in
order with the single frames around it; a BLF log packs it with NumPy into the same bytes
the per-frame path (and python-can) writes; every format reads it back; the counters count
every frame of it."""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.bus import TrafficLog, log_formats
from drivers.protocol.batch import (
    FLAG_ERROR,
    FLAG_EXTENDED,
    FLAG_REMOTE,
    FRAME_DTYPE,
    ID_MASK,
    to_messages,
)

#: frames are stamped this far ahead of now: after the log's opening (a BLF keeps times
#: relative to its start) even when the loaded machine stalls the test in between (1 s was
#: once not enough)
AHEAD_S = 30.0

# One frame: (identifier with flag bits, dlc, 8 data bytes, time after the first frame).
Row = tuple[int, int, bytes, float]
# A piece of traffic: frames, received or sent, handed over as one batch or frame by frame.
Chunk = tuple[list[Row], bool, bool]

EXAMPLES = settings(max_examples=30, derandomize=True, deadline=None)


def batch(rows: list[Row], t0: float) -> np.ndarray:
    out = np.zeros(len(rows), dtype=FRAME_DTYPE)
    for k, (ident, dlc, data, dt) in enumerate(rows):
        out[k] = (t0 + dt, ident, dlc, np.frombuffer(data, np.uint8))
    return out


def hand_over(log: TrafficLog, frames: np.ndarray, is_rx: bool, as_batch: bool) -> None:
    if as_batch:
        log.log_batch(frames, is_rx=is_rx)
        return
    for msg in to_messages(frames, is_rx=is_rx):
        (log.on_message_received if is_rx else log.log_sent)(msg)


@contextmanager
def drained_here(path: Path) -> Iterator[TrafficLog]:
    """A log whose writer thread has ended: the test drains it (as cycle_costs does);
    stopped (written and closed) on leaving."""
    log = TrafficLog(path)
    log._stopping = True
    log._wake.set()
    log._thread.join(5.0)
    assert not log._thread.is_alive()
    log._stopping = False  # stop() still writes what is queued and closes the file
    try:
        yield log
    finally:
        log.stop()


@st.composite
def rows(draw: st.DrawFn, max_size: int, error: bool, remote: bool, dlc_max: int) -> list[Row]:
    """Frames: standard and extended ids, remote (and error) frames, DLCs up to ``dlc_max``
    with garbage beyond them, times after the first frame, in order."""
    n = draw(st.integers(0, max_size))
    kinds = [0, FLAG_EXTENDED] + ([FLAG_REMOTE, FLAG_EXTENDED | FLAG_REMOTE] if remote else [])
    kinds += [FLAG_ERROR] if error else []
    out = []
    dts = sorted(draw(st.lists(st.integers(0, 10**8), min_size=n, max_size=n)))
    for dt in dts:
        kind = draw(st.sampled_from(kinds))
        ident = draw(st.integers(0, ID_MASK if kind & FLAG_EXTENDED else 0x7FF))
        dlc = draw(st.integers(0, dlc_max))
        data = draw(st.binary(min_size=8, max_size=8))
        out.append((ident | kind, dlc, data, dt * 1e-6 + draw(st.sampled_from([0.0, 3e-7]))))
    return out


def chunks(
    error: bool, remote: bool, dlc_max: int, size: int = 12
) -> st.SearchStrategy[list[Chunk]]:
    return st.lists(
        st.tuples(rows(size, error, remote, dlc_max), st.booleans(), st.booleans()),
        min_size=1,
        max_size=5,
    )


# ------------------------------------------------------------------- BLF, byte for byte


@EXAMPLES
@given(
    traffic=chunks(error=True, remote=True, dlc_max=15),
    before_start=st.floats(0.0, 2.0),
)
def test_a_batch_packs_the_same_blf_objects_as_its_frames_one_by_one(
    traffic: list[Chunk], before_start: float
) -> None:
    """The same frames handed over as ``can.Message`` objects and as batches (error frames,
    remote and extended ids, DLCs past 8, garbage past the DLC, times before the log's start)
    give the same BLF objects and, closed, the same file."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        with drained_here(d / "frames.blf") as one, drained_here(d / "batches.blf") as many:
            start = one._blf.start_s
            many._blf.start_s = many._blf.stop_s = start
            t0 = start - before_start
            for rs, is_rx, _ in traffic:
                frames = batch(rs, t0)
                hand_over(one, frames, is_rx, as_batch=False)
                hand_over(many, frames, is_rx, as_batch=True)
            one._drain()
            many._drain()
            w1, w2 = one._blf, many._blf
            assert w2.pending() == w1.pending()
            assert (w2.pending_bytes, w2.object_count) == (w1.pending_bytes, w1.object_count)
            assert w2.stop_s == w1.stop_s
            assert many._unflushed == one._unflushed == sum(len(rs) for rs, _, _ in traffic)
            assert many._last_ts == one._last_ts
        n = sum(len(rs) for rs, _, _ in traffic)
        assert one.n_frames == many.n_frames == n and many.write_errors == 0
        assert (d / "batches.blf").read_bytes() == (d / "frames.blf").read_bytes()
        assert len(list(can.LogReader(d / "batches.blf"))) == n


def test_a_batch_with_a_time_blf_cannot_hold_goes_frame_by_frame(tmp_path: Path) -> None:
    """A NaN or far-off timestamp: the batch is written frame by frame, as the same frames
    one by one are (the BLF formatter refuses the frame, the rest is logged)."""
    t = time.time()
    frames = batch([(0x181, 1, bytes(8), 0.0), (0x182, 1, bytes(8), 0.0)] * 2, t)
    frames["timestamp"][1] = np.nan
    frames["timestamp"][2] = t + 1e12
    with drained_here(tmp_path / "a.blf") as one, drained_here(tmp_path / "b.blf") as many:
        many._blf.start_s = one._blf.start_s
        hand_over(one, frames, True, as_batch=False)
        hand_over(many, frames, True, as_batch=True)
        one._drain()
        many._drain()
        assert many._blf.pending() == one._blf.pending()
    assert (many.n_frames, many.write_errors) == (one.n_frames, one.write_errors) == (2, 2)


def test_a_batch_past_the_container_size_is_cut_as_frame_by_frame(tmp_path: Path) -> None:
    """Containers of a few frames each (objects cut across them, as readers expect) after
    a batch: the same containers, the same file, as frame by frame; every frame reads
    back."""
    frames = batch([(0x181 + k, 8, bytes(range(k, k + 8)), k * 1e-3) for k in range(40)], 0.0)
    with drained_here(tmp_path / "a.blf") as one, drained_here(tmp_path / "b.blf") as many:
        for log in (one, many):
            log._blf.start_s = 0.0
            log._blf.container_bytes = 5 * 48 + 7  # 5 frames and a bit
        hand_over(one, frames, False, as_batch=False)
        hand_over(many, frames, False, as_batch=True)
        one._drain()
        many._drain()
        assert many._blf.pending() == one._blf.pending()
        one._flush()
        many._flush()
        assert many._blf.uncompressed_size == one._blf.uncompressed_size > 7 * 5 * 48
    assert (tmp_path / "a.blf").read_bytes() == (tmp_path / "b.blf").read_bytes()
    back = list(can.LogReader(tmp_path / "b.blf"))
    assert [(m.arbitration_id, bytes(m.data)) for m in back] == [
        (0x181 + k, bytes(range(k, k + 8))) for k in range(40)
    ]


# ------------------------------------------------------------------ every format reads back


def expected(fmt: str, frames: np.ndarray, is_rx: bool) -> list[tuple]:
    """What ``can.LogReader`` gives back of the frames: a remote frame has no data, a
    candump log keeps no DLC of a remote frame, python-can's TRC writer leaves remote frames
    out (LOG_FORMAT_DURABILITY)."""
    out = []
    for ts, ident, dlc, data in frames.tolist():
        remote = bool(ident & FLAG_REMOTE)
        if remote and fmt == "trc":
            continue
        out.append(
            (
                ident & ID_MASK,
                bool(ident & FLAG_EXTENDED),
                remote,
                0 if remote and fmt == "log" else dlc,
                b"" if remote else bytes(data[:dlc]),
                is_rx,
                ts,
            )
        )
    return out


def read_back(path: Path) -> list[tuple]:
    return [
        (
            m.arbitration_id,
            m.is_extended_id,
            m.is_remote_frame,
            m.dlc,
            bytes(m.data),
            m.is_rx,
            m.timestamp,
        )
        for m in can.LogReader(path)
    ]


@pytest.mark.parametrize("fmt", log_formats())
@EXAMPLES
@given(traffic=chunks(error=False, remote=True, dlc_max=8, size=30))
def test_every_format_reads_back_batches_in_order_with_single_frames(
    fmt: str, traffic: list[Chunk]
) -> None:
    """Batches mixed with frames handed over one by one read back in order: ids, extended
    and remote flags, DLC, data, direction and times (to the format's microsecond)."""
    t0 = time.time() + AHEAD_S  # after the log opens (BLF keeps times relative to its start)
    want: list[tuple] = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"bus.{fmt}"
        log = TrafficLog(path)
        offset = 0.0
        for rs, is_rx, as_batch in traffic:
            frames = batch(rs, t0 + offset)
            offset += 101.0  # after every frame of this chunk
            hand_over(log, frames, is_rx, as_batch)
            want += expected(fmt, frames, is_rx)
        log.stop()
        assert log.write_errors == 0 and log.n_lost == 0
        assert log.n_frames == sum(len(rs) for rs, _, _ in traffic)
        back = read_back(path)
    assert [b[:6] for b in back] == [w[:6] for w in want]
    if back:
        rel_back = [b[6] - back[0][6] for b in back]
        rel_want = [w[6] - want[0][6] for w in want]
        assert rel_back == pytest.approx(rel_want, abs=2e-6)


@pytest.mark.parametrize("fmt", log_formats())
def test_n_frames_counts_every_frame_of_a_batch_with_an_error_and_an_extended_frame(
    tmp_path: Path, fmt: str
) -> None:
    """A batch with an error frame (written frame by frame), an extended id and a remote
    frame, between single frames and after an empty batch: every frame handed over is
    counted; the data frames read back in order, the error frame where the format keeps
    it (not in TRC)."""
    t0 = time.time() + AHEAD_S
    mixed = batch(
        [
            (0x181, 2, b"\x01\x02" + bytes(6), 0.000),
            (0x18FF0001 | FLAG_EXTENDED, 8, bytes(range(8)), 0.001),
            (0x001 | FLAG_ERROR, 2, b"\x05\x06" + bytes(6), 0.002),
            (0x701 | FLAG_REMOTE, 1, bytes(8), 0.003),
            (0x182, 0, bytes(8), 0.004),
        ],
        t0,
    )
    single = batch([(0x601, 8, b"\x40\x41\x60\x00" + bytes(4), 0.0)], t0 - 0.01)
    after = batch([(0x1ABCDEF | FLAG_EXTENDED, 3, b"abc" + bytes(5), 0.0)], t0 + 0.01)
    path = tmp_path / f"bus.{fmt}"
    log = TrafficLog(path)
    hand_over(log, single, False, as_batch=False)
    log.log_batch(np.zeros(0, FRAME_DTYPE), is_rx=True)
    hand_over(log, mixed, True, as_batch=True)
    hand_over(log, after, True, as_batch=False)
    log.stop()
    assert (log.n_frames, log.n_lost, log.write_errors) == (7, 0, 0)
    back = list(can.LogReader(path))
    data = [
        (m.arbitration_id, m.is_extended_id, bytes(m.data), m.is_rx)
        for m in back
        if not m.is_error_frame and not m.is_remote_frame
    ]
    assert data == [
        (0x601, False, b"\x40\x41\x60\x00" + bytes(4), False),
        (0x181, False, b"\x01\x02", True),
        (0x18FF0001, True, bytes(range(8)), True),
        (0x182, False, b"", True),
        (0x1ABCDEF, True, b"abc", True),
    ]
    errors = [k for k, m in enumerate(back) if m.is_error_frame]
    assert errors == ([] if fmt == "trc" else [3])
    if fmt == "blf":  # BLF keeps an error frame's id and data
        assert (back[3].arbitration_id, bytes(back[3].data)) == (0x001, b"\x05\x06")


# ---------------------------------------------------------------------- counters, copies


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_log_the_disk_refuses_counts_every_frame_of_its_batches_as_lost(
    tmp_path: Path,
) -> None:
    """Disk full (the file's writes go to /dev/full): the frames of the batches not yet in
    the file and of those handed over later are all counted lost."""
    t0 = time.time()
    frames = batch([(0x181 + k, 8, bytes(8), k * 1e-4) for k in range(40)], t0)
    with drained_here(tmp_path / "bus.blf") as log:
        log.log_batch(frames, is_rx=True)
        hand_over(log, frames[:3], False, as_batch=False)
        log._drain()
        log._flush()
        assert (log.n_frames, log.n_lost) == (43, 0)
        log.log_batch(frames, is_rx=False)
        log._drain()
        full = os.open("/dev/full", os.O_WRONLY)
        fd, log._fd = log._fd, full
        try:
            log._flush()
        finally:
            log._fd = fd
            os.close(full)
        assert log._broken and (log.n_frames, log.n_lost) == (43, 40)
        log.log_batch(frames[:7], is_rx=True)
        hand_over(log, frames[:2], True, as_batch=False)
    assert (log.n_frames, log.n_lost) == (43, 49)
    assert "cannot write" in (log.first_error or "")
    assert len(list(can.LogReader(tmp_path / "bus.blf"))) == 43


@pytest.mark.parametrize("fmt", ["blf", "asc"])
def test_the_caller_may_reuse_its_array_at_once(tmp_path: Path, fmt: str) -> None:
    """``log_batch`` copies: what the caller writes into its array afterwards (the next
    cycle's frames) is not what is logged."""
    t0 = time.time() + AHEAD_S
    frames = batch([(0x201 + k, 6, bytes([k] * 8), 0.0) for k in range(36)], t0)
    log = TrafficLog(tmp_path / f"bus.{fmt}")
    log.log_batch(frames, is_rx=False)
    frames["id"] = 0x7FF
    frames["data"] = 0xEE
    log.stop()
    back = list(can.LogReader(tmp_path / f"bus.{fmt}"))
    assert [(m.arbitration_id, bytes(m.data)) for m in back] == [
        (0x201 + k, bytes([k] * 6)) for k in range(36)
    ]


@pytest.mark.parametrize("as_batch", [True, False])
@pytest.mark.parametrize("bad_ts", [1e12, float("inf"), float("nan"), -1.0])
def test_a_frame_a_blf_log_cannot_date_is_counted_and_the_log_goes_on(
    tmp_path: Path, as_batch: bool, bad_ts: float
) -> None:
    """An error frame stamped in the year 33658 (a red-team peer's) must not reach the BLF
    file: its header could not date the file's end, and every later frame would be lost.
    Such a frame is a write error; the frames around it are logged."""
    t0 = time.time()
    path = tmp_path / "bus.blf"
    log = TrafficLog(path)
    log.on_message_received(can.Message(timestamp=t0, arbitration_id=0x181, data=[1]))
    bad = can.Message(timestamp=bad_ts, arbitration_id=0x20000080, is_error_frame=True)
    if as_batch:
        log.log_batch(batch([(0x182, 1, bytes(8), bad_ts - t0)], t0), is_rx=True)
    log.on_message_received(bad)
    log.on_message_received(can.Message(timestamp=t0 + 0.01, arbitration_id=0x183, data=[3]))
    log.stop()  # does not raise
    assert log.write_errors == (2 if as_batch else 1)
    assert "outside 0..2**32 s" in (log.first_error or "")
    back = list(can.LogReader(path))
    assert [m.arbitration_id for m in back] == [0x181, 0x183]
    assert log.n_frames == 2
