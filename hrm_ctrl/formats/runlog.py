"""A run as it went over the wire: the run record (``hrm-run/1``, written by the drive
session beside its CAN logs) and the logs themselves (``.blf`` / ``.asc``, read with
python-can's :class:`can.LogReader`) as typed arrays.

Per SYNC (one control cycle) of the first bus: its wire time, the target every motor
was commanded (the last RPDO1 before that SYNC: controlword + target position, applied at
the SYNC) and the position it reported (its TPDO1 after that SYNC: statusword + position
actual value), each in the record's motor order.  Streams are told apart by gaps in the
SYNCs (:data:`STREAM_GAP_S`).  The CANopen layouts are the ones ``drivers.protocol``
defines (RPDO1 0x200 + node, TPDO1 0x180 + node, SYNC 0x080); they are restated here
because this layer does not import the drivers.

:func:`joint_angles` maps counts to joint angles with the rope layer's inverse
(:meth:`hrm_ctrl.ropes.actuation.Actuation.angles_from_counts`); :func:`tension_csv`
reads the run's tension side file (``<run>_tension.csv``, written by ``hrm run`` when a
tension board is read) and :func:`write_tension_csv` writes it.

Every reader is bounded whatever its input (a damaged or hostile record or log gives one
line naming the file, :class:`RunLogError`): a BLF log's objects are checked against
their bounds before python-can reads it (:func:`check_blf_bounds`), a text log's lines
(:func:`check_text_log_lines`) and a SQLite log's frames (:func:`check_db_log`) too,
the record is read
as the shared readers read JSON (:func:`hrm_ctrl.files.read_text_file`,
:func:`hrm_ctrl.files.parse_json`: size and nesting bounded), its numbers are checked
before anything divides by them or sizes an array with them (a control rate in
:data:`MIN_RATE_HZ`..:data:`MAX_RATE_HZ`, at most :data:`MAX_MOTORS` motors, node ids
1..127), and a log is read up to
:data:`MAX_LOG_FRAMES` frames and :data:`MAX_LOG_VALUES` values.

>>> split_streams(np.array([0.0, 0.01, 0.02, 5.0, 5.01]), 0.5)
[(0, 3), (3, 5)]
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sqlite3
import stat
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.errors import HrmError
from hrm_ctrl.files import parse_json, read_text_file, write_atomic

RUN_RECORD_FORMAT = "hrm-run/1"
MAX_RECORD_BYTES = 64 * 1024 * 1024  # a run record larger than this is refused
MAX_LOG_FRAMES = 60_000_000  # frames read from one CAN log at most (a 1 h run: ~27 M)
MAX_CYCLES = 400_000  # SYNCs kept at most (1 h at 100 Hz: 360 000)
MAX_MOTORS = 1024  # motors of a run record at most (the arm has 36; CANopen: 127 a bus)
MAX_LOG_VALUES = 64 * MAX_CYCLES  # counts kept per array (cycles x motors) at most
MIN_RATE_HZ, MAX_RATE_HZ = 1.0, 10_000.0  # a control rate outside is not a run's
MAX_TENSION_ROWS = 100_000
MAX_TEXT_LOG_LINE_BYTES = 64 * 1024  # one line of a text CAN log at most (a frame: < 400 B)
TEXT_LOG_SUFFIXES = frozenset({".asc", ".log", ".trc", ".csv"})
STREAM_GAP_S = 0.5  # SYNCs further apart than this belong to different streams
COB_SYNC = 0x080
COB_TPDO1 = 0x180
COB_RPDO1 = 0x200
_PDO = struct.Struct("<Hi")  # controlword/statusword (UNSIGNED16), position (INTEGER32)


class RunLogError(HrmError):
    """A run record or CAN log that cannot be read (one line naming file and problem)."""


@dataclass(frozen=True)
class RunLog:
    """A run's wire traffic as arrays: ``t_s`` (cycles,) SYNC wire times from the first
    SYNC, ``t0_unix`` that SYNC's timestamp; ``target`` / ``actual`` (cycles, motors)
    counts (``actual`` NaN where a TPDO is missing, ``target`` NaN before the first RPDO);
    ``streams`` (start, end) index ranges of the streams; ``frames`` per log."""

    record_path: Path
    record: dict[str, Any]
    motor_ids: tuple[str, ...]
    period_s: float
    t0_unix: float
    t_s: np.ndarray
    target: np.ndarray
    actual: np.ndarray
    streams: list[tuple[int, int]]
    frames: list[int]

    @property
    def n_cycles(self) -> int:
        return int(self.t_s.shape[0])

    def stream(self, index: int) -> slice:
        """The cycles of stream ``index`` (negative: from the end)."""
        if not self.streams:
            raise RunLogError(f"{self.record_path}: no stream in the CAN log")
        try:
            a, b = self.streams[index]
        except IndexError:
            raise RunLogError(
                f"{self.record_path}: stream {index}: the log has {len(self.streams)}"
            ) from None
        return slice(a, b)

    def sync_lateness_s(self) -> np.ndarray:
        """Each SYNC's interval from the one before less the control period (s); 0 first."""
        if self.n_cycles == 0:
            return np.zeros(0)
        d = np.diff(self.t_s, prepend=self.t_s[0]) - self.period_s
        d[0] = 0.0
        for a, _b in self.streams:  # the first SYNC of each stream has no predecessor
            d[a] = 0.0
        return d


def missing_frames(log: RunLog) -> list[str] | None:
    """What the run's CAN logs miss, one line per log, against the counts the session kept
    in the run record: ``can_log_frames`` (the frames it wrote to each log: a log that
    reads fewer is cut or damaged, more is not the log the run wrote) and ``can_log_lost``
    (frames that never reached the log).  Empty: every frame the run sent or received is
    there; None: the record has no counts (written before they were kept), the logs
    cannot be checked.

    >>> log = RunLog(Path("run.json"), {"can_logs": ["a.blf"], "can_log_frames": [9056],
    ...              "can_log_lost": [0]}, (), 0.01, 0.0, np.zeros(0), np.zeros((0, 0)),
    ...              np.zeros((0, 0)), [], [4239])
    >>> missing_frames(log)
    ['a.blf: 4,239 of the 9,056 frames the run record counts (the log is cut or damaged)']
    """
    rec, where = log.record, log.record_path
    written, lost = rec.get("can_log_frames"), rec.get("can_log_lost", [0] * len(log.frames))
    if written is None:
        return None
    for key, counts in (("can_log_frames", written), ("can_log_lost", lost)):
        ok = isinstance(counts, list) and len(counts) == len(log.frames)
        if not ok or not all(type(c) is int and c >= 0 for c in counts):
            raise RunLogError(f"{where}: {key} is not a frame count per CAN log")
    out = []
    for name, read, wrote, gone in zip(rec["can_logs"], log.frames, written, lost, strict=True):
        shown = _log_path(where, str(name))
        if read < wrote:
            out.append(
                f"{shown}: {read:,} of the {wrote:,} frames the run record counts "
                "(the log is cut or damaged)"
            )
        elif read > wrote:
            out.append(
                f"{shown}: {read:,} frames, the run record counts {wrote:,} "
                "(not the log the run wrote)"
            )
        if gone:
            out.append(f"{shown}: {gone:,} frame(s) never reached the log (lost as it was written)")
    return out


def split_streams(t_s: np.ndarray, gap_s: float = STREAM_GAP_S) -> list[tuple[int, int]]:
    """(start, end) index ranges of runs of SYNC times without a gap over ``gap_s``."""
    n = len(t_s)
    if n == 0:
        return []
    cuts = [0, *(int(i) + 1 for i in np.flatnonzero(np.diff(t_s) > gap_s)), n]
    return [(cuts[i], cuts[i + 1]) for i in range(len(cuts) - 1)]


def read_record(path: str | Path) -> dict[str, Any]:
    """The run record at ``path`` (``hrm-run/1``), checked for what this module uses."""
    p = Path(path)
    text = read_text_file(p, RunLogError, "run record", max_bytes=MAX_RECORD_BYTES)
    doc = parse_json(text, RunLogError, str(p), "run record")
    if not isinstance(doc, dict) or doc.get("format") != RUN_RECORD_FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        shown = f"a {type(got).__name__}"
        if got is None or isinstance(got, str | int | float):  # not a whole nested value
            shown = repr(got[:40] if isinstance(got, str) else got)
        raise RunLogError(f"{p}: not a run record (format {shown}, expected {RUN_RECORD_FORMAT})")
    for key, kind in (("motor_ids", list), ("config", dict), ("can_logs", list)):
        if not isinstance(doc.get(key), kind):
            raise RunLogError(f"{p}: run record without {key!r}")
    motors = doc["motor_ids"]
    if not 0 < len(motors) <= MAX_MOTORS:
        raise RunLogError(f"{p}: run record with {len(motors)} motors (1..{MAX_MOTORS})")
    if not all(isinstance(m, str) for m in motors) or len(set(motors)) != len(motors):
        raise RunLogError(f"{p}: run record whose motor_ids are not distinct names")
    for i, name in enumerate(doc["can_logs"]):
        if not _plausible_path(name):
            raise RunLogError(f"{p}: can_logs[{i}] is not a file name")
    return doc


def _plausible_path(name: object) -> bool:
    """A string the file system could take as a path: no NUL, at most 4096 bytes, each
    part at most 255 (else ``Path.exists`` raises instead of answering)."""
    if not isinstance(name, str) or not name or "\0" in name:
        return False
    try:
        raw = os.fsencode(name)
    except UnicodeError:  # a lone surrogate
        return False
    return len(raw) <= 4096 and all(len(part) <= 255 for part in raw.split(b"/"))


def control_period_s(doc: dict[str, Any], where: Path) -> float:
    """The control period (s) of a run record: 1 / ``config.control.rate_hz``, a number
    in :data:`MIN_RATE_HZ`..:data:`MAX_RATE_HZ` (not NaN, infinite, zero or negative)."""
    control = doc["config"].get("control")
    rate = control.get("rate_hz") if isinstance(control, dict) else None
    if (
        isinstance(rate, bool)
        or not isinstance(rate, int | float)
        or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ  # False for NaN
    ):
        got = repr(rate) if isinstance(rate, int | float) else f"a {type(rate).__name__}"
        raise RunLogError(
            f"{where}: run record without a control rate (rate_hz {got}; expected "
            f"{MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} Hz)"
        )
    return 1.0 / float(rate)


def _node_maps(doc: dict[str, Any], where: Path) -> list[dict[int, int]]:
    """Per bus (record order): node id -> motor index."""
    order = {m: i for i, m in enumerate(doc["motor_ids"])}
    buses = doc["config"].get("buses")
    if not isinstance(buses, dict) or not buses:
        raise RunLogError(f"{where}: run record without buses in its config")
    maps = []
    for name, bus in buses.items():
        nodes = bus.get("nodes") if isinstance(bus, dict) else None
        if not isinstance(nodes, dict):
            raise RunLogError(f"{where}: bus {name}: no nodes in the record's config")
        if not all(m in order for m in nodes):
            raise RunLogError(f"{where}: bus {name}: nodes that are not the record's motors")
        bad = [n for n in nodes.values() if isinstance(n, bool) or n not in range(1, 128)]
        if bad:
            raise RunLogError(f"{where}: bus {name}: node id {bad[0]!r} (expected 1..127)")
        maps.append({int(nid): order[m] for m, nid in nodes.items()})
    return maps


def _log_path(record_path: Path, logged: str) -> Path:
    """A CAN log named in the record: as written, or beside the record (moved runs)."""
    p = Path(logged)
    if p.exists():
        return p
    return record_path.parent / p.name


def log_paths(record_path: str | Path, doc: dict[str, Any]) -> list[Path]:
    """The CAN logs a run record (``doc``, as :func:`read_record` returns it) names, where
    :func:`read_run` reads them (looks at the paths only)."""
    return [_log_path(Path(record_path), str(x)) for x in doc["can_logs"]]


# What python-can's readers raise on a damaged log: an empty or cut BLF (struct.error), a
# BLF of other bytes (BLFParseError), a damaged compressed container (zlib.error), bad
# text (ValueError), a .db that is not a database (sqlite3.Error), an .mf4 without
# asammdf (NotImplementedError); a CanError from any.
_LOG_ERRORS: tuple[type[Exception], ...] = (
    OSError,
    EOFError,
    ValueError,
    struct.error,
    zlib.error,
    sqlite3.Error,
    NotImplementedError,
)
_READER_LOGGER = "can.io"  # python-can's log readers' loggers (can.io.blf, ...)


class _ReaderWarnings(logging.Handler):
    """What python-can's readers log while a log is read (a damaged BLF container, a
    line a reader skips), kept off stderr: a damaged log is one :class:`RunLogError`."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []  # the first one only: a reader may warn per object
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1
        if not self.messages:
            self.messages.append(record.getMessage())


@contextlib.contextmanager
def _reader_warnings() -> Iterator[_ReaderWarnings]:
    """Collect the readers' warnings (not propagated to the root logger) while open."""
    logger = logging.getLogger(_READER_LOGGER)
    handler, propagate = _ReaderWarnings(), logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def read_run(path: str | Path, *, max_frames: int = MAX_LOG_FRAMES) -> RunLog:
    """The run record at ``path`` and its CAN logs as a :class:`RunLog`."""
    rp = Path(path)
    doc = read_record(rp)
    maps = _node_maps(doc, rp)
    logs = log_paths(rp, doc)
    if len(logs) != len(maps):
        raise RunLogError(f"{rp}: {len(logs)} CAN logs for {len(maps)} buses")
    n = len(doc["motor_ids"])
    period_s = control_period_s(doc, rp)
    rows = _Rows(n, min(MAX_CYCLES, MAX_LOG_VALUES // n))
    frames = []
    for b, (lp, nodes) in enumerate(zip(logs, maps, strict=True)):
        with _reader_warnings() as warned:
            frames.append(_read_log(lp, b, nodes, rows, max_frames))
        if warned.messages:  # a reader that skipped what it could not parse
            raise RunLogError(f"{lp}: cannot read CAN log ({_first_line(warned.messages[0])})")
    t = np.asarray(rows.sync_t, dtype=np.float64)
    t0 = float(t[0]) if t.size else math.nan
    if t.size and not np.isfinite(t - t0).all():
        raise RunLogError(f"{logs[0]}: SYNC times out of range")
    return RunLog(
        record_path=rp,
        record=doc,
        motor_ids=tuple(str(m) for m in doc["motor_ids"]),
        period_s=period_s,
        t0_unix=t0,
        t_s=t - t0 if t.size else t,
        target=np.array(rows.target).reshape(-1, n),
        actual=np.array(rows.actual).reshape(-1, n),
        streams=split_streams(t - t0 if t.size else t),
        frames=frames,
    )


@dataclass
class _Rows:
    """What :func:`_read_log` collects per SYNC of the first bus (at most ``max_syncs``):
    its time, the targets held and the positions reported, ``n`` motors each."""

    n: int
    max_syncs: int
    sync_t: list[float] = field(default_factory=list)
    target: list[np.ndarray] = field(default_factory=list)
    actual: list[np.ndarray] = field(default_factory=list)


def _read_log(lp: Path, b: int, nodes: dict[int, int], rows: _Rows, max_frames: int) -> int:
    """Read CAN log ``lp`` of bus ``b`` (node id -> motor index ``nodes``) into ``rows``;
    its frame count.  Whatever the log holds, a problem is one :class:`RunLogError`."""
    n = rows.n
    held = np.full(n, np.nan)
    k = -1  # SYNCs of this bus so far
    count = 0
    for msg in iter_can_log(lp, max_frames):
        count += 1
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            continue
        cid = msg.arbitration_id
        if cid == COB_SYNC and len(msg.data) == 0:
            k += 1
            if k >= rows.max_syncs:
                raise RunLogError(
                    f"{lp}: more than {rows.max_syncs} SYNCs"
                    + (f" for {n} motors" if rows.max_syncs < MAX_CYCLES else "")
                )
            if b == 0:
                ts = float(msg.timestamp)
                if not math.isfinite(ts):
                    raise RunLogError(f"{lp}: frame {count}: SYNC at time {ts}")
                rows.sync_t.append(ts)
                rows.target.append(held.copy())
                rows.actual.append(np.full(n, np.nan))
            elif k < len(rows.target):
                rows.target[k] = np.where(np.isnan(held), rows.target[k], held)
            continue
        base, nid = cid & 0x780, cid & 0x07F
        if len(msg.data) != _PDO.size or nid not in nodes:
            continue
        if base == COB_RPDO1:
            held[nodes[nid]] = _PDO.unpack(bytes(msg.data))[1]
        elif base == COB_TPDO1 and 0 <= k < len(rows.actual):
            rows.actual[k][nodes[nid]] = _PDO.unpack(bytes(msg.data))[1]
    return count


def iter_can_log(path: str | Path, max_frames: int = MAX_LOG_FRAMES) -> Iterator[Any]:
    """The frames (:class:`can.Message`) of CAN log ``path``, read in bounded memory and
    time: :func:`check_can_log` first, at most ``max_frames`` frames, and whatever the
    reader raises on a damaged log as one :class:`RunLogError` naming the file.  The
    reader is closed when the iteration ends, early or not.

    >>> import tempfile, can
    >>> p = Path(tempfile.mkdtemp()) / "bus.asc"
    >>> with can.Logger(str(p)) as log:
    ...     for i in range(3):
    ...         log(can.Message(arbitration_id=0x80, timestamp=float(i), data=b""))
    >>> [m.arbitration_id for m in iter_can_log(p)]
    [128, 128, 128]
    >>> list(iter_can_log(p, max_frames=2))  # doctest: +IGNORE_EXCEPTION_DETAIL
    Traceback (most recent call last):
    RunLogError: .../bus.asc: more than 2 frames
    """
    import can

    lp = Path(path)
    errors = log_errors()
    check_can_log(lp)
    try:
        reader = can.LogReader(str(lp))
    except errors as exc:
        raise RunLogError(f"{lp}: cannot open CAN log ({_why(exc)})") from None
    count = 0
    try:
        it = iter(reader)
        while True:
            try:
                msg = next(it)
            except StopIteration:
                return
            except errors as exc:
                raise RunLogError(f"{lp}: cannot read CAN log ({_why(exc)})") from None
            count += 1
            if count > max_frames:
                raise RunLogError(f"{lp}: more than {max_frames} frames")
            yield msg
    finally:
        stop = getattr(reader, "stop", None)
        if callable(stop):
            stop()


# BLF bounds (python-can and CANoe write containers of 128 KiB; a CAN FD frame is < 200 B)
MAX_BLF_OBJECT_BYTES = 1 << 20  # one object of the file (a log container), at most
MAX_BLF_CONTAINER_BYTES = 1 << 20  # one container, uncompressed, at most
MAX_BLF_INNER_BYTES = 64 * 1024  # one object inside the containers (a frame), at most
_BLF_FILE_HEADER = struct.Struct("<4sL")  # "LOGG", header size
_BLF_OBJECT_HEADER = struct.Struct("<4sHHLL")  # "LOBJ", header size, version, size, type
_BLF_CONTAINER = struct.Struct("<H6xL4x")  # compression method, uncompressed size
_BLF_LOG_CONTAINER = 10
_BLF_STORED, _BLF_ZLIB = 0, 2


def check_can_log(lp: Path) -> None:
    """Before a reader opens it: a CAN log is a regular file (a FIFO would block, a
    device never end), not compressed (python-can would inflate a ``.gz`` unbounded; hrm
    never writes one) and a BLF log within :func:`check_blf_bounds`."""
    try:
        mode = os.stat(lp).st_mode
    except (OSError, ValueError) as exc:
        raise RunLogError(f"{lp}: cannot open CAN log ({_why(exc)})") from None
    if not stat.S_ISREG(mode):
        raise RunLogError(f"{lp}: CAN log is not a regular file")
    if lp.suffix.lower() == ".gz":
        raise RunLogError(f"{lp}: compressed CAN logs are not read (decompress it first)")
    suffix = lp.suffix.lower()
    if suffix == ".blf":
        check_blf_bounds(lp)
    elif suffix in TEXT_LOG_SUFFIXES:
        check_text_log_lines(lp)
    elif suffix == ".db":
        check_db_log(lp)


def check_text_log_lines(
    path: str | Path, max_line_bytes: int = MAX_TEXT_LOG_LINE_BYTES, chunk_bytes: int = 1 << 20
) -> None:
    """Refuse a text CAN log (``.asc``, ``.log``, ``.trc``, ``.csv``) with a line longer than
    ``max_line_bytes``: python-can's readers read a line at a time, so one line of a
    gigabyte (a file with no line breaks) would be a gigabyte in memory, twice.  Scans
    the file in ``chunk_bytes`` chunks (2.1 GB/s from the page cache on the development
    VM, some 90 times python-can's ASC reader: 23 MB/s, 254 000 frames/s).

    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "bus.asc"
    >>> _ = p.write_bytes(b"date Fri Dec 4\\n" + b"x" * 100 + b"\\n")
    >>> check_text_log_lines(p)
    >>> check_text_log_lines(p, max_line_bytes=64)  # doctest: +IGNORE_EXCEPTION_DETAIL
    Traceback (most recent call last):
    RunLogError: .../bus.asc: line 2 is longer than 64 bytes
    """
    lp = Path(path)
    run = 0  # bytes since the last line break
    line = 1  # the line ``run`` belongs to
    try:
        with open(lp, "rb") as f:
            while chunk := f.read(chunk_bytes):
                breaks = np.flatnonzero(np.frombuffer(chunk, dtype=np.uint8) == 0x0A)
                if breaks.size:
                    lengths = np.diff(breaks, prepend=-1) - 1  # the lines ending in this chunk
                    lengths[0] += run
                    over = np.flatnonzero(lengths > max_line_bytes)
                    if over.size:
                        at = line + int(over[0])
                        raise RunLogError(f"{lp}: line {at} is longer than {max_line_bytes} bytes")
                    line += breaks.size
                    run = len(chunk) - 1 - int(breaks[-1])
                else:
                    run += len(chunk)
                if run > max_line_bytes:
                    raise RunLogError(f"{lp}: line {line} is longer than {max_line_bytes} bytes")
    except OSError as exc:
        raise RunLogError(f"{lp}: cannot open CAN log ({_why(exc)})") from None


def check_db_log(path: str | Path, max_data_bytes: int = MAX_BLF_INNER_BYTES) -> None:
    """Refuse a SQLite CAN log (``.db``, python-can's :class:`can.SqliteWriter` schema)
    without a ``messages`` table or with a frame's data longer than ``max_data_bytes``
    (python-can would copy whatever the column holds into the message).  Opened read-only:
    reading a log never changes it."""
    lp = Path(path)
    try:
        with contextlib.closing(
            sqlite3.connect(f"{lp.resolve().as_uri()}?mode=ro", uri=True)
        ) as db:
            (longest,) = db.execute("SELECT max(length(data)) FROM messages").fetchone()
    except sqlite3.Error as exc:
        raise RunLogError(f"{lp}: cannot read CAN log ({_why(exc)})") from None
    if longest is not None and longest > max_data_bytes:
        raise RunLogError(f"{lp}: a frame's data is longer than {max_data_bytes} bytes")


def check_blf_bounds(path: str | Path, max_objects: int = MAX_LOG_FRAMES) -> None:
    """Refuse a BLF file that python-can's reader would not read in bounded memory and
    time: an object or container larger than :data:`MAX_BLF_OBJECT_BYTES` /
    :data:`MAX_BLF_CONTAINER_BYTES` (once uncompressed: a zlib bomb), a frame object
    inside the containers shorter than its own header or longer than
    :data:`MAX_BLF_INNER_BYTES` (an object of size 0 makes python-can 4.6 loop for ever),
    of a header version other than 1 or 2 (python-can warns once per such object and
    skips it), or more than ``max_objects`` of them (objects python-can skips silently
    count too: 1 KB of zlib stands for 1 MiB of them).  Walks the objects as python-can
    does (an object may continue in the next container; up to 8 bytes of padding between
    objects) and decompresses each container at most to its bound.  Raises :class:`RunLogError`
    naming the file and the byte offset of the object.

    >>> import can, tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     path = Path(d) / "ok.blf"
    ...     with can.BLFWriter(str(path)) as w:
    ...         w.on_message_received(can.Message(arbitration_id=0x80, data=b""))
    ...     check_blf_bounds(path)   # python-can's own log passes
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(_BLF_FILE_HEADER.size)
            if len(head) < _BLF_FILE_HEADER.size or head[:4] != b"LOGG":
                raise RunLogError(f"{p}: CAN log is not BLF (no LOGG header)")
            header_size = _BLF_FILE_HEADER.unpack(head)[1]
            if not _BLF_FILE_HEADER.size <= header_size <= MAX_BLF_INNER_BYTES:
                raise RunLogError(f"{p}: CAN log: BLF file header of {header_size} bytes")
            f.seek(header_size)
            tail, count = b"", 0
            while True:
                at = f.tell()
                raw = f.read(_BLF_OBJECT_HEADER.size)
                if not raw:
                    break
                if len(raw) < _BLF_OBJECT_HEADER.size:
                    raise RunLogError(f"{p}: CAN log: BLF object at byte {at} cut short")
                signature, _, _, obj_size, obj_type = _BLF_OBJECT_HEADER.unpack(raw)
                if signature != b"LOBJ":
                    raise RunLogError(f"{p}: CAN log: no BLF object at byte {at}")
                if not _BLF_OBJECT_HEADER.size <= obj_size <= MAX_BLF_OBJECT_BYTES:
                    raise RunLogError(f"{p}: CAN log: BLF object at byte {at} of {obj_size} bytes")
                body = f.read(obj_size - _BLF_OBJECT_HEADER.size)
                f.read(obj_size % 4)  # padding
                if obj_type != _BLF_LOG_CONTAINER:
                    continue
                if len(body) < _BLF_CONTAINER.size:
                    raise RunLogError(f"{p}: CAN log: BLF container at byte {at} cut short")
                method = _BLF_CONTAINER.unpack_from(body)[0]
                data = body[_BLF_CONTAINER.size :]
                if method == _BLF_ZLIB:
                    zobj = zlib.decompressobj()
                    data = zobj.decompress(data, MAX_BLF_CONTAINER_BYTES)
                    if zobj.unconsumed_tail:
                        raise RunLogError(
                            f"{p}: CAN log: BLF container at byte {at} holds more than "
                            f"{MAX_BLF_CONTAINER_BYTES} bytes uncompressed"
                        )
                elif method != _BLF_STORED:
                    continue  # python-can skips it (with a warning: refused by the reader)
                elif len(data) > MAX_BLF_CONTAINER_BYTES:
                    raise RunLogError(
                        f"{p}: CAN log: BLF container at byte {at} of {len(data)} bytes"
                    )
                tail, n = _walk_blf_frames(p, at, tail + data)
                count += n
                if count > max_objects:
                    raise RunLogError(f"{p}: CAN log: more than {max_objects} BLF objects")
    except zlib.error as exc:
        raise RunLogError(f"{p}: CAN log: damaged BLF container ({exc})") from None
    except OSError as exc:
        raise RunLogError(f"{p}: cannot read CAN log ({_why(exc)})") from None


def _walk_blf_frames(p: Path, at: int, data: bytes) -> tuple[bytes, int]:
    """The frame objects of one container's data (after the last one's unread rest):
    each checked against its bounds; returns what continues in the next container and
    how many objects ended in this one."""
    pos, end, count = 0, len(data), 0
    unpack = _BLF_OBJECT_HEADER.unpack_from
    while True:
        found = data.find(b"LOBJ", pos, pos + 8)
        if found < 0:
            if pos + 8 > end:
                break  # the rest (a partial object, padding) continues in the next one
            raise RunLogError(f"{p}: CAN log: BLF container at byte {at}: no object where one ends")
        pos = found
        if pos + _BLF_OBJECT_HEADER.size > end:
            break
        _, _, version, obj_size, _ = unpack(data, pos)
        if not _BLF_OBJECT_HEADER.size < obj_size <= MAX_BLF_INNER_BYTES:
            raise RunLogError(
                f"{p}: CAN log: BLF container at byte {at}: a frame of {obj_size} bytes"
            )
        if version not in (1, 2):
            raise RunLogError(
                f"{p}: CAN log: BLF container at byte {at}: a frame of header version {version}"
            )
        if pos + obj_size > end:
            break
        pos += obj_size
        count += 1
    return data[pos:], count


def log_errors() -> tuple[type[Exception], ...]:
    """What python-can's log readers raise on a damaged log (a CanError from any)."""
    import can

    return (*_LOG_ERRORS, can.CanError, _blf_parse_error())


def _blf_parse_error() -> type[Exception]:
    """python-can's error for a damaged BLF (not a :class:`can.CanError`)."""
    try:
        from can.io.blf import BLFParseError
    except ImportError:  # pragma: no cover - an older python-can
        return struct.error
    return BLFParseError


def _why(exc: BaseException) -> str:
    """One line on a reader's error: its message's first line, or its class."""
    return _first_line(getattr(exc, "strerror", None) or str(exc)) or type(exc).__name__


def _first_line(text: str, width: int = 200) -> str:
    """The first line of ``text``, at most ``width`` characters."""
    lines = text.strip().splitlines()
    line = lines[0] if lines else ""
    return line if len(line) <= width else line[: width - 3] + "..."


def joint_angles(actuation: Any, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, theta) (rows, 12) rad from counts (rows, motors); rows with a missing
    value come out NaN."""
    c = np.asarray(counts, dtype=np.float64)
    nj = int(actuation.robot.n_joints)
    alpha = np.full((c.shape[0], nj), np.nan)
    theta = np.full((c.shape[0], nj), np.nan)
    ok = np.isfinite(c).all(axis=1)
    if ok.any():
        a, t, _res = actuation.angles_from_counts(c[ok], robust=False)
        alpha[ok], theta[ok] = a, t
    return alpha, theta


def tension_path(record_path: str | Path) -> Path:
    """Where a run's tension side file goes: ``<run>_tension.csv`` beside the record."""
    p = Path(record_path)
    return p.with_name(p.stem + "_tension.csv")


def write_tension_csv(
    path: str | Path, t_unix: Sequence[float], tensions_N: np.ndarray, motor_ids: Sequence[str]
) -> Path:
    """Write tension samples (wire-clock times, N per motor) atomically, at most
    :data:`MAX_TENSION_ROWS` rows (the newest kept)."""
    tn = np.asarray(tensions_N, dtype=np.float64).reshape(len(t_unix), len(motor_ids))
    t = np.asarray(t_unix, dtype=np.float64)[-MAX_TENSION_ROWS:]
    tn = tn[-MAX_TENSION_ROWS:]
    lines = ["t_unix_s," + ",".join(f"{m}_N" for m in motor_ids)]
    for ti, row in zip(t, tn, strict=True):
        lines.append(f"{ti:.6f}," + ",".join("" if not np.isfinite(v) else f"{v:.3f}" for v in row))
    p = Path(path)
    write_atomic(p, "\n".join(lines) + "\n")
    return p


def tension_csv(path: str | Path, motor_ids: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(t_unix (rows,), tensions_N (rows, motors)) of a tension side file."""
    p = Path(path)
    lines = read_text_file(p, RunLogError, "tension file").split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    header = lines[0].strip().split(",") if lines else []
    want = ["t_unix_s", *(f"{m}_N" for m in motor_ids)]
    if header != want:
        raise RunLogError(f"{p}: not this run's tension file (header {header[:3]}...)")
    if len(lines) > MAX_TENSION_ROWS + 1:
        raise RunLogError(f"{p}: more than {MAX_TENSION_ROWS} rows")
    rows = []
    for i, line in enumerate(lines[1:], start=2):
        cells = line.split(",")
        if len(cells) != len(want):
            raise RunLogError(f"{p}:{i}: {len(cells)} fields, expected {len(want)}")
        try:
            row = [float(c) if c or j == 0 else math.nan for j, c in enumerate(cells)]
        except ValueError:
            raise RunLogError(f"{p}:{i}: not a number") from None
        if not all(math.isfinite(v) for v in row if v == v):  # NaN: an empty cell
            raise RunLogError(f"{p}:{i}: a number that is not finite")
        if not math.isfinite(row[0]):
            raise RunLogError(f"{p}:{i}: no time")
        rows.append(row)
    a = np.array(rows, dtype=np.float64).reshape(-1, len(motor_ids) + 1)
    return a[:, 0], a[:, 1:]
