"""hrm_ctrl.formats.runlog: a run record and its CAN logs as arrays (a synthetic BLF
written with python-can, so every value is known), and its bad input."""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hrm_ctrl.formats.runlog import (
    RunLogError,
    check_blf_bounds,
    check_can_log,
    check_text_log_lines,
    iter_can_log,
    read_record,
    read_run,
    tension_csv,
    tension_path,
    write_tension_csv,
)

PDO = struct.Struct("<Hi")


def _write_run(tmp: Path, targets: np.ndarray, actual: np.ndarray, t0: float = 1.7e9) -> Path:
    """Two buses, one motor each (node 1 on a, node 2 on b); per cycle k: the RPDOs, the
    SYNC at t0 + k*T (+ a 5 s gap after cycle 2: a second stream), then the TPDOs."""
    T = 0.01
    logs = []
    for b, (bus, nid) in enumerate((("a", 1), ("b", 2))):
        path = tmp / f"run-x_{bus}.blf"
        with can.BLFWriter(str(path)) as w:

            def put(t: float, cid: int, data: bytes, w: can.BLFWriter = w) -> None:
                w.on_message_received(
                    can.Message(timestamp=t, arbitration_id=cid, is_extended_id=False, data=data)
                )

            for k in range(targets.shape[0]):
                t = t0 + k * T + (5.0 if k >= 3 else 0.0)
                put(t - 0.004, 0x200 + nid, PDO.pack(15, int(targets[k, b])))
                put(t, 0x80, b"")
                if np.isfinite(actual[k, b]):
                    put(t + 0.002, 0x180 + nid, PDO.pack(0x1237, int(actual[k, b])))
        logs.append(str(path))
    rec = {
        "format": "hrm-run/1", "run": "run-x", "motor_ids": ["m0", "m1"],
        "config": {"control": {"rate_hz": 100.0},
                   "buses": {"a": {"nodes": {"m0": 1}}, "b": {"nodes": {"m1": 2}}}},
        "can_logs": logs,
    }  # fmt: skip
    p = tmp / "run-x.json"
    p.write_text(json.dumps(rec))
    return p


def test_arrays_are_the_logged_values(tmp_path: Path) -> None:
    targets = np.array([[0, 0], [10, -5], [30, -15], [40, -20], [45, -22]])
    actual = np.array([[0, 0], [0, 0], [10, np.nan], [30, -15], [40, -20]], dtype=float)
    log = read_run(_write_run(tmp_path, targets, actual))
    assert log.motor_ids == ("m0", "m1") and log.period_s == 0.01
    assert np.array_equal(log.target, targets.astype(float))
    assert np.array_equal(log.actual, actual, equal_nan=True)
    assert log.streams == [(0, 3), (3, 5)]  # the 5 s gap
    assert np.allclose(log.t_s[:3], [0.0, 0.01, 0.02])
    assert log.t0_unix == pytest.approx(1.7e9, abs=1e-3)
    assert log.frames == [5 * 3, 5 * 2 + 4]  # RPDO, SYNC, TPDO per cycle; one TPDO missing
    assert np.allclose(log.sync_lateness_s(), 0.0, atol=1e-6)  # every SYNC on its period


def test_tension_file_round_trip_and_bounds(tmp_path: Path) -> None:
    rec = tmp_path / "run-y.json"
    p = write_tension_csv(tension_path(rec), [1.0, 1.1], np.array([[30.0, np.nan], [31.5, 29.0]]),
                          ["m0", "m1"])  # fmt: skip
    assert p.name == "run-y_tension.csv"
    t, n = tension_csv(p, ["m0", "m1"])
    assert np.allclose(t, [1.0, 1.1]) and np.array_equal(n, [[30.0, np.nan], [31.5, 29.0]],
                                                         equal_nan=True)  # fmt: skip
    with pytest.raises(RunLogError, match="not this run's tension file"):
        tension_csv(p, ["m0", "other"])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{", r"not JSON \(line 1"),
        ("[" * 100_000 + "]" * 100_000, r"not a run record \(JSON nested too deeply\)"),
        ("1" * 400, "too large for a number"),
        ('{"format": "hrm-plan/1"}', r"format 'hrm-plan/1', expected hrm-run/1"),
        ('{"format": "hrm-run/1", "motor_ids": [], "config": {}}', "without 'can_logs'"),
    ],
)
def test_bad_records_one_line(tmp_path: Path, text: str, message: str) -> None:
    p = tmp_path / "r.json"
    p.write_text(text)
    with pytest.raises(RunLogError, match=message) as exc:
        read_record(p)
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize(
    "name", ["a" * 5000 + ".blf", "a\0b.blf", "d/" + "b" * 300 + ".blf", "", 7]
)
def test_a_log_name_no_file_system_takes_is_one_line(tmp_path: Path, name: object) -> None:
    """A ``can_logs`` entry the file system would raise on (too long, a NUL, not a
    string) is refused naming it, before any path is looked at (it was a traceback)."""
    p = _write_run(tmp_path, np.zeros((2, 2), int), np.zeros((2, 2)))
    rec = json.loads(p.read_text())
    rec["can_logs"][1] = name
    p.write_text(json.dumps(rec))
    with pytest.raises(RunLogError, match=r"r.*\.json: can_logs\[1\] is not a file name$"):
        read_run(p)


def test_missing_log_named(tmp_path: Path) -> None:
    p = _write_run(tmp_path, np.zeros((2, 2), int), np.zeros((2, 2)))
    (tmp_path / "run-x_b.blf").unlink()
    with pytest.raises(RunLogError, match=r"run-x_b\.blf: cannot open CAN log"):
        read_run(p)


def _set_rate(p: Path, value: str) -> None:
    text = p.read_text().replace('"rate_hz": 100.0', f'"rate_hz": {value}')
    assert value in text
    p.write_text(text)


@pytest.mark.parametrize("rate", ["NaN", "Infinity", "-Infinity", "-100", "0", "1e300", '"100"'])
def test_control_rate_out_of_range_refused(tmp_path: Path, rate: str) -> None:
    p = _write_run(tmp_path, np.zeros((2, 2), int), np.zeros((2, 2)))
    _set_rate(p, rate)
    with pytest.raises(RunLogError, match="run record without a control rate") as exc:
        read_run(p)
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda r: r.update(motor_ids=[f"m{i}" for i in range(2000)]), "2000 motors"),
        (lambda r: r.update(motor_ids=["m0", "m0"]), "not distinct names"),
        (lambda r: r["config"]["buses"]["a"]["nodes"].update(m0=1e300), "node id 1e"),
        (lambda r: r["config"]["buses"]["b"]["nodes"].update(m1=0), "node id 0"),
    ],
)
def test_motors_and_nodes_checked(tmp_path: Path, change: Any, message: str) -> None:
    p = _write_run(tmp_path, np.zeros((2, 2), int), np.zeros((2, 2)))
    rec = json.loads(p.read_text())
    change(rec)
    p.write_text(json.dumps(rec))
    with pytest.raises(RunLogError, match=message) as exc:
        read_run(p)
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)


def _flip(raw: bytes) -> bytes:
    b = bytearray(raw)
    for i in range(len(b) // 2, len(b), 97):  # in the compressed container's data
        b[i] ^= 0x5A
    return bytes(b)


@pytest.mark.parametrize(
    ("name", "damage"),
    [
        ("run-x_a.blf", lambda raw: b""),
        ("run-x_a.blf", lambda raw: raw[:40]),
        ("run-x_b.blf", lambda raw: bytes(range(256)) * 16),
        ("run-x_a.blf", _flip),
        ("run-x_a.db", lambda raw: b"not a database" * 100),
    ],
    ids=["empty", "cut-header", "random", "damaged-container", "db-not-a-database"],
)
def test_damaged_log_one_line_nothing_logged(
    tmp_path: Path, name: str, damage: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """A damaged CAN log (whatever python-can's reader raises or logs): one line naming
    it, and none of the reader's warnings on stderr."""
    p = _write_run(tmp_path, np.zeros((40, 2), int), np.zeros((40, 2)))
    bus = "a" if "_a." in name else "b"
    raw = (tmp_path / f"run-x_{bus}.blf").read_bytes()
    (tmp_path / name).write_bytes(damage(raw))
    rec = json.loads(p.read_text())
    rec["can_logs"][0 if bus == "a" else 1] = str(tmp_path / name)
    p.write_text(json.dumps(rec))
    with pytest.raises(RunLogError, match="CAN log") as exc:
        read_run(p)
    assert str(tmp_path / name) in str(exc.value) and "\n" not in str(exc.value)
    assert not [r for r in caplog.records if r.name.startswith("can")]


def test_log_not_a_regular_file_refused(tmp_path: Path) -> None:
    p = _write_run(tmp_path, np.zeros((2, 2), int), np.zeros((2, 2)))
    (tmp_path / "run-x_b.blf").unlink()
    os.mkfifo(tmp_path / "run-x_b.blf")  # would block a reader
    with pytest.raises(RunLogError, match=r"run-x_b\.blf: CAN log is not a regular file"):
        read_run(p)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("nan,1.0,2.0", "4: no time"),
        ("1e999,1.0,2.0", "4: a number that is not finite"),
        ("1.0,inf,2.0", "4: a number that is not finite"),
        ("1.0,x,2.0", "4: not a number"),
        ("1.0,2.0", "4: 2 fields, expected 3"),
    ],
)
def test_tension_file_bad_rows(tmp_path: Path, row: str, message: str) -> None:
    p = tmp_path / "run-y_tension.csv"
    p.write_text(f"t_unix_s,m0_N,m1_N\n1.0,30.0,\n1.1,31.0,29.0\n{row}\n")
    with pytest.raises(RunLogError, match=message) as exc:
        tension_csv(p, ["m0", "m1"])
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)
    fifo = tmp_path / "fifo_tension.csv"
    os.mkfifo(fifo)
    with pytest.raises(RunLogError, match="not a regular file"):
        tension_csv(fifo, ["m0", "m1"])


def _with_container(raw: bytes, inner: bytes, *, stored_size: int | None = None) -> bytes:
    """``raw`` (a BLF python-can wrote) with one more zlib log container, holding
    ``inner``, before its own objects."""
    header_size = struct.unpack_from("<4sL", raw)[1]
    packed = zlib.compress(inner, 9)
    body = struct.pack("<H6xL4x", 2, len(inner) if stored_size is None else stored_size) + packed
    obj = struct.pack("<4sHHLL", b"LOBJ", 16, 1, 16 + len(body), 10) + body
    obj += b"\0" * (len(obj) % 4)
    return raw[:header_size] + obj + raw[header_size:]


_CAN_MESSAGE_OBJECT = struct.pack("<4sHHLL", b"LOBJ", 32, 1, 48, 1)  # header of a CAN frame


@pytest.mark.timeout(60)  # python-can 4.6 alone loops for ever on the first one
@pytest.mark.parametrize(
    ("inner", "message"),
    [
        (struct.pack("<4sHHLL", b"LOBJ", 16, 7, 0, 86) + bytes(64), "a frame of 0 bytes"),
        (struct.pack("<4sHHLL", b"LOBJ", 32, 1, 0, 1) + bytes(64), "a frame of 0 bytes"),
        (bytes(200 << 20), r"holds more than 1048576 bytes uncompressed"),  # 200 KB on disk
        (struct.pack("<4sHHLL", b"LOBJ", 32, 1, 1 << 30, 1) + bytes(64), "a frame of 1073741824"),
        (_CAN_MESSAGE_OBJECT + bytes(32) + b"garbage!" * 4, "no object where one ends"),
        (struct.pack("<4sHHLL", b"LOBJ", 16, 7, 20, 86) + bytes(4), "header version 7"),
    ],
    ids=[
        "size-0-unknown-version",
        "size-0-can-frame",
        "zlib-bomb",
        "huge-frame",
        "garbage",
        "unknown-version",  # python-can warns once per object: 2000x the file in warnings
    ],
)
def test_hostile_blf_refused_before_python_can_reads_it(
    tmp_path: Path, inner: bytes, message: str
) -> None:
    """A BLF that would make python-can's reader loop for ever, inflate a few hundred KB
    into hundreds of MB, or keep a growing unread rest: one line, in bounded time and
    memory, naming the log."""
    p = _write_run(tmp_path, np.zeros((4, 2), int), np.zeros((4, 2)))
    log = tmp_path / "run-x_a.blf"
    log.write_bytes(_with_container(log.read_bytes(), inner))
    with pytest.raises(RunLogError, match=message) as exc:
        read_run(p)
    assert str(log) in str(exc.value) and "\n" not in str(exc.value)


def test_blf_bounds_pass_a_long_log_python_can_wrote(tmp_path: Path) -> None:
    """Frames split over containers (python-can's 128 KiB) are walked across them."""
    targets = np.arange(6000).reshape(3000, 2)
    p = _write_run(tmp_path, targets, targets.astype(float))
    assert (tmp_path / "run-x_a.blf").stat().st_size > 20_000  # several containers
    log = read_run(p)
    assert np.array_equal(log.target, targets.astype(float))


def test_blf_objects_counted_and_compressed_logs_refused(tmp_path: Path) -> None:
    """More objects than the bound (1 KB of zlib stands for 1 MiB of them): refused; a
    ``.gz`` log (python-can would inflate it unbounded; hrm never writes one): refused."""
    import gzip

    p = _write_run(tmp_path, np.zeros((40, 2), int), np.zeros((40, 2)))
    log = tmp_path / "run-x_a.blf"
    check_blf_bounds(log, max_objects=40 * 3)  # 40 RPDOs, SYNCs and TPDOs on bus a
    with pytest.raises(RunLogError, match="more than 119 BLF objects"):
        check_blf_bounds(log, max_objects=119)
    packed = tmp_path / "run-x_a.blf.gz"
    packed.write_bytes(gzip.compress(log.read_bytes()))
    rec = json.loads(p.read_text())
    rec["can_logs"][0] = str(packed)
    p.write_text(json.dumps(rec))
    with pytest.raises(RunLogError, match=r"run-x_a\.blf\.gz: compressed CAN logs are not read"):
        read_run(p)


@given(
    lines=st.lists(st.integers(0, 40), min_size=0, max_size=30),
    tail=st.booleans(),
    chunk=st.integers(1, 50),
    limit=st.integers(0, 45),
)
@example(lines=[10, 25], tail=True, chunk=7, limit=24)  # the long line spans three chunks
@example(lines=[3], tail=False, chunk=1, limit=2)  # the last line has no line break
def test_text_log_line_bound_names_the_first_long_line(
    tmp_path_factory: pytest.TempPathFactory, lines: list[int], tail: bool, chunk: int, limit: int
) -> None:
    """Whatever the chunking, the scan refuses exactly the files with a line longer than
    the bound, naming the first such line (1-based), as splitting the whole file would."""
    body = b"\n".join(b"x" * n for n in lines) + (b"\n" if tail and lines else b"")
    p = tmp_path_factory.mktemp("t") / "bus.asc"
    p.write_bytes(body)
    long = [i + 1 for i, line in enumerate(body.split(b"\n")) if len(line) > limit]
    if not long:
        check_text_log_lines(p, max_line_bytes=limit, chunk_bytes=chunk)
        return
    with pytest.raises(
        RunLogError, match=rf"bus\.asc: line {long[0]} is longer than {limit} bytes$"
    ):
        check_text_log_lines(p, max_line_bytes=limit, chunk_bytes=chunk)


@pytest.mark.parametrize("suffix", [".asc", ".log", ".trc", ".csv"])
def test_text_log_without_line_breaks_refused_before_reading(tmp_path: Path, suffix: str) -> None:
    """A text log of one 2 MiB line (python-can would hold it whole, twice) is refused by
    the check every reader of a run's logs runs first."""
    p = tmp_path / f"bus{suffix}"
    p.write_bytes(b"base hex  timestamps absolute\n" + b"7" * (2 << 20))
    with pytest.raises(RunLogError, match=r"line 2 is longer than 65536 bytes"):
        check_can_log(p)
    with pytest.raises(RunLogError, match=r"line 2 is longer than 65536 bytes"):
        list(iter_can_log(p))


def test_db_log_checked_read_only(tmp_path: Path) -> None:
    """A SQLite log: python-can's own is read; one without its table, or with a frame of
    1 MiB of data, is one line; the check changes nothing in the file."""
    import sqlite3

    good = tmp_path / "bus.db"
    with can.SqliteWriter(str(good)) as w:
        for k in range(3):
            w.on_message_received(can.Message(timestamp=float(k), arbitration_id=0x80, data=b""))
    assert [m.arbitration_id for m in iter_can_log(good)] == [0x80] * 3
    bad = tmp_path / "big.db"
    with sqlite3.connect(bad) as db:
        db.execute("CREATE TABLE messages (ts REAL, id INT, ext INT, rtr INT, err INT, dlc INT, "
                   "data BLOB)")  # fmt: skip
        db.execute("INSERT INTO messages VALUES (0, 128, 0, 0, 0, 8, ?)", (b"x" * (1 << 20),))
    db_bytes = bad.read_bytes()
    with pytest.raises(RunLogError, match=r"big\.db: a frame's data is longer than 65536 bytes"):
        check_can_log(bad)
    assert bad.read_bytes() == db_bytes
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as db:
        db.execute("CREATE TABLE t (x INT)")
    with pytest.raises(RunLogError, match=r"other\.db: cannot read CAN log \(no such table"):
        check_can_log(other)
