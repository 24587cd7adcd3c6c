"""Our own BLF writer (:mod:`drivers.blf`, written by :class:`drivers.canlog.TrafficLog`):
python-can's reader reads back every frame it writes, field for field (Hypothesis over
frames); a classic frame's object is the bytes python-can's own writer produces; a log
whose writing process is killed mid-run reads back every frame up to its last flush."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import zlib
from pathlib import Path

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.blf import (
    CONTAINER,
    FILE_HEADER_BYTES,
    OBJECT_BASE,
    BlfFormatter,
)
from drivers.canlog import TrafficLog, file_times
from drivers.protocol.batch import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE, FRAME_DTYPE
from tests.hil.hil_rig import REPO

EXAMPLES = settings(max_examples=40, derandomize=True, deadline=None)
T0 = 1_700_000_000.0  # the logs' start in these tests (a Unix time: BLF dates it)


def objects_of(path: Path) -> bytes:
    """The objects of a BLF file, its containers unpacked and joined (what any reader
    parses), read with this test's own loop."""
    data = path.read_bytes()
    pos, out = FILE_HEADER_BYTES, bytearray()
    while pos + OBJECT_BASE.size <= len(data):
        sig, _hs, _hv, size, kind = OBJECT_BASE.unpack_from(data, pos)
        assert sig == b"LOBJ" and kind == 10, (pos, sig, kind)
        method, n = CONTAINER.unpack_from(data, pos + OBJECT_BASE.size)
        body = data[pos + OBJECT_BASE.size + CONTAINER.size : pos + size]
        raw = zlib.decompress(body) if method == 2 else body
        assert len(raw) == n
        out += raw
        pos += size + size % 4
    return bytes(out)


def test_a_classic_frame_is_the_object_python_can_writes(tmp_path: Path) -> None:
    """Data, remote, extended, error frames, a frame before the start, channels given as
    numbers, names and not at all: the objects python-can's ``BLFWriter`` writes (its
    public API: a file, then its containers unpacked), byte for byte."""
    t0 = T0 + 0.25
    msgs = [
        can.Message(timestamp=t0, arbitration_id=0x181, data=b"\x37\x02\x10\x27\x00\x00",
                    is_extended_id=False, channel=0),
        can.Message(timestamp=t0 + 0.001, arbitration_id=0x201, data=b"\x0f\x00\x01\x02\x03\x04",
                    is_extended_id=False, is_rx=False, channel=0),
        can.Message(timestamp=t0 + 0.002, arbitration_id=0x080, data=b"", is_extended_id=False,
                    is_rx=False, channel=1),
        can.Message(timestamp=t0 + 0.003, arbitration_id=0x701, is_remote_frame=True, dlc=1,
                    is_extended_id=False, channel="can1"),
        can.Message(timestamp=t0 + 0.004, arbitration_id=0x1ABCDE, data=bytes(range(8)),
                    is_extended_id=True, channel=None),
        can.Message(timestamp=t0 + 0.005, is_error_frame=True, channel=0),
        can.Message(timestamp=t0 - 0.5, arbitration_id=0x7FF, data=b"\x05", is_extended_id=False,
                    channel="virtual"),  # before the start: time 0, as python-can writes it
    ]  # fmt: skip
    theirs = can.BLFWriter(tmp_path / "theirs.blf")
    ours = BlfFormatter(start_s=t0)
    for m in msgs:
        theirs.on_message_received(m)
        ours.add(m)
    theirs.stop()
    assert ours.pending() == objects_of(tmp_path / "theirs.blf")
    assert ours.object_count == len(msgs)


# ------------------------------------------------------------------ read back, field by field


@st.composite
def messages(draw: st.DrawFn) -> can.Message:
    """Any frame a log may be handed: 11- or 29-bit ids, DLC 0-8, remote and error frames,
    FD frames, either direction, channels, times from before the log's start to 2**32 s."""
    kind = draw(st.sampled_from(["data", "remote", "error", "fd"]))
    ext = draw(st.booleans())
    ident = draw(st.integers(0, 0x1FFFFFFF if ext else 0x7FF))
    ts = draw(
        st.one_of(
            st.floats(T0 - 2.0, T0 + 1e5, allow_nan=False),
            st.floats(0.0, 2.0**32 - 1e-3, allow_nan=False),
        )
    )
    channel = draw(st.sampled_from([None, 0, 1, 7, "can3", "virtual"]))
    is_rx = draw(st.booleans())
    if kind == "fd":
        n = draw(st.sampled_from([0, 1, 5, 8, 12, 16, 20, 24, 32, 48, 64]))
        return can.Message(timestamp=ts, arbitration_id=ident, is_extended_id=ext, is_fd=True,
                           bitrate_switch=draw(st.booleans()),
                           error_state_indicator=draw(st.booleans()),
                           data=draw(st.binary(min_size=n, max_size=n)), channel=channel,
                           is_rx=is_rx)  # fmt: skip
    dlc = draw(st.integers(0, 8))
    if kind == "remote":
        return can.Message(timestamp=ts, arbitration_id=ident, is_extended_id=ext,
                           is_remote_frame=True, dlc=dlc, channel=channel, is_rx=is_rx)  # fmt: skip
    data = draw(st.binary(min_size=dlc, max_size=dlc))
    return can.Message(timestamp=ts, arbitration_id=ident, is_extended_id=ext, data=data,
                       is_error_frame=kind == "error", channel=channel, is_rx=is_rx)  # fmt: skip


def expected_channel(channel: object, default: int) -> int:
    """python-can's 0-based channel of a frame read back: its own, a name's digits, or
    the log's (``default``, 1-based in the file)."""
    if isinstance(channel, int):
        return channel
    if isinstance(channel, str) and channel[-1].isdigit():
        return int(channel[-1])
    return default - 1


def same_frame(back: can.Message, sent: can.Message, start_s: float, channel: int) -> None:
    assert back.arbitration_id == sent.arbitration_id
    assert back.is_extended_id == sent.is_extended_id
    assert back.is_error_frame == sent.is_error_frame
    assert back.is_remote_frame == sent.is_remote_frame
    assert back.is_fd == sent.is_fd
    assert back.dlc == sent.dlc
    assert back.channel == expected_channel(sent.channel, channel)
    if not sent.is_error_frame:  # an error frame keeps no direction (CAN_ERROR_EXT)
        assert back.is_rx == sent.is_rx
    if sent.is_fd:
        assert back.bitrate_switch == sent.bitrate_switch
        assert back.error_state_indicator == sent.error_state_indicator
    if not sent.is_remote_frame:
        assert bytes(back.data) == bytes(sent.data)
    # ns after the start, truncated; a frame before the start is written at the start
    assert math.isclose(back.timestamp, max(sent.timestamp, start_s), abs_tol=2e-6)


@EXAMPLES
@given(msgs=st.lists(messages(), min_size=1, max_size=30), channel=st.sampled_from([1, 2]))
def test_python_cans_reader_reads_back_every_frame_the_formatter_writes(
    msgs: list[can.Message], channel: int
) -> None:
    f = BlfFormatter(start_s=T0, channel=channel, container_bytes=200)  # objects cut across
    for m in msgs:
        f.add(m)
    body = f.take_containers(FILE_HEADER_BYTES)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.blf"
        path.write_bytes(f.header(FILE_HEADER_BYTES + len(body)) + body)
        reader = can.BLFReader(path)
        assert reader.start_timestamp == T0
        assert reader.object_count == len(msgs)
        assert reader.file_size == path.stat().st_size
        back = list(reader)
    assert len(back) == len(msgs)
    for b, m in zip(back, msgs, strict=True):
        same_frame(b, m, T0, channel)


@st.composite
def record_batches(draw: st.DrawFn) -> tuple[np.ndarray, bool]:
    """A batch of records (drivers.protocol.batch) as the host hands them to its log."""
    n = draw(st.integers(1, 12))
    out = np.zeros(n, FRAME_DTYPE)
    for k in range(n):
        kind = draw(st.sampled_from([0, FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR]))
        ident = draw(st.integers(0, 0x1FFFFFFF if kind == FLAG_EXTENDED else 0x7FF))
        out[k]["id"] = ident | kind
        out[k]["dlc"] = draw(st.integers(0, 8))
        out[k]["data"] = np.frombuffer(draw(st.binary(min_size=8, max_size=8)), np.uint8)
        out[k]["timestamp"] = time.time() + 30.0 + k * 1e-3
    return out, draw(st.booleans())


@EXAMPLES
@given(entries=st.lists(st.one_of(messages(), record_batches()), min_size=1, max_size=8))
def test_a_traffic_log_reads_back_frame_for_frame(
    entries: list[can.Message | tuple[np.ndarray, bool]],
) -> None:
    """Frames and batches through the whole log (its writer thread, its flushes): every
    frame reads back, in order; a frame whose time BLF cannot hold is counted instead."""
    from drivers.protocol.batch import to_messages

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bus.blf"
        log = TrafficLog(path, channel=2)
        sent: list[can.Message] = []
        for e in entries:
            if isinstance(e, can.Message):
                log.on_message_received(e) if e.is_rx else log.log_sent(e)
                sent.append(e)  # its channel is now the log's
            else:
                log.log_batch(e[0], is_rx=e[1])
                sent += to_messages(e[0], channel=1, is_rx=e[1])
        log.stop()
        back = list(can.LogReader(path))
        start = log._blf.start_s if log._blf is not None else 0.0
    floors = np.array([m.timestamp for m in sent])
    file_times(floors, -math.inf)  # a file's times never go back (docs/drivers.md)
    for m, t in zip(sent, floors, strict=True):
        m.timestamp = float(t)
    assert log.write_errors == 0 and log.n_frames == len(sent) == len(back)
    for b, m in zip(back, sent, strict=True):
        same_frame(b, m, start, 2)


@EXAMPLES
@given(msgs=st.lists(messages(), min_size=1, max_size=20))
def test_another_readers_objects_are_the_frames(msgs: list[can.Message]) -> None:
    """A reader written apart from python-can (``vblf``, after Vector's object
    definitions; skipped where it is not installed) finds each frame as the object Vector's
    tools write for it, with its fields, and the header's counts and start."""
    reader = pytest.importorskip("vblf.reader")
    vcan = pytest.importorskip("vblf.can")
    f = BlfFormatter(start_s=T0, channel=1, container_bytes=300)
    for m in msgs:
        f.add(m)
    body = f.take_containers(FILE_HEADER_BYTES)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.blf"
        path.write_bytes(f.header(FILE_HEADER_BYTES + len(body)) + body)
        with reader.BlfReader(path) as r:
            stats = r.file_statistics
            objs = list(r)
    assert (stats.object_count, stats.file_size) == (len(msgs), FILE_HEADER_BYTES + len(body))
    start = stats.measurement_start_time
    assert (start.year, start.hour, start.minute, start.second) == (2023, 22, 13, 20)
    assert len(objs) == len(msgs)
    for o, m in zip(objs, msgs, strict=True):
        ident = m.arbitration_id | (0x80000000 if m.is_extended_id else 0)
        assert o.frame_id == ident
        assert o.channel == expected_channel(m.channel, 1) + 1
        t_ns = o.header.object_time_stamp
        assert abs(T0 + t_ns * 1e-9 - max(m.timestamp, T0)) < 2e-6
        if m.is_error_frame:
            assert isinstance(o, vcan.CanErrorFrameExt)
            assert bytes(o.data[: m.dlc]) == bytes(m.data)
        elif m.is_fd:
            assert isinstance(o, vcan.CanFdMessage64)
            assert bytes(o.data) == bytes(m.data) and o.valid_data_bytes == len(m.data)
            assert bool(o.flags & 0x1000) and bool(o.flags & 0x2000) == m.bitrate_switch
            assert o.dir == (0 if m.is_rx else 1)
        else:
            assert isinstance(o, vcan.CanMessage) and o.dlc == m.dlc
            assert bool(o.flags & 0x80) == m.is_remote_frame
            assert bool(o.flags & 0x01) == (not m.is_rx)
            if not m.is_remote_frame:
                assert bytes(o.data[: m.dlc]) == bytes(m.data)


# ------------------------------------------------------------------ kill -9 mid-write

CHILD_WRITES_UNTIL_KILLED = textwrap.dedent(
    """
    import json, sys, time
    import can
    from drivers.canlog import TrafficLog
    TrafficLog.FLUSH_S = 0.005  # many flushes: the kill lands in or between them
    log = TrafficLog(sys.argv[1])
    k = 0
    while True:
        for n in range(37):
            log.on_message_received(can.Message(
                arbitration_id=0x181 + n % 18, data=[k % 256, n, k // 256 % 256],
                timestamp=time.time(), is_extended_id=False))
        k += 1
        if k % 10 == 0:  # what the file holds for sure (flushed), from the writer's counter
            print(json.dumps({"flushed": log.n_frames}), flush=True)
        time.sleep(0.001)
    """
)


def test_a_log_killed_mid_write_reads_back_every_frame_up_to_its_last_flush(
    tmp_path: Path,
) -> None:
    """SIGKILL of a process writing a BLF log at full speed: the file reads back with
    python-can without an error, its frames are exactly the first ones handed over, and
    at least as many as the writer had reported flushed before the kill."""
    for attempt in range(3):  # three kills at different moments
        path = tmp_path / f"killed{attempt}.blf"
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD_WRITES_UNTIL_KILLED, f"{path}"],
            stdout=subprocess.PIPE, text=True, cwd=REPO,
        )  # fmt: skip
        assert child.stdout is not None
        flushed = 0
        t_end = time.monotonic() + 0.3 + 0.15 * attempt
        while time.monotonic() < t_end or flushed == 0:
            line = child.stdout.readline()
            assert line, "the writer ended by itself"
            flushed = json.loads(line)["flushed"]
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
        child.stdout.close()
        back = list(can.LogReader(path))
        assert len(back) >= flushed > 0, (len(back), flushed)
        expect = [(0x181 + n % 18, bytes([k % 256, n, k // 256 % 256]))
                  for k in range(len(back) // 37 + 1) for n in range(37)]  # fmt: skip
        assert [(m.arbitration_id, bytes(m.data)) for m in back] == expect[: len(back)]
        assert can.BLFReader(path).start_timestamp > 0
