"""The CAN log of one bus: every frame on the wire, written by a background thread.

:class:`TrafficLog` takes frames the host sent (:meth:`TrafficLog.log_sent`,
:meth:`TrafficLog.log_batch`) and frames it received (as a ``can.Listener``) and writes
them in arrival order, so the control cycle never waits for the disk, in one of the
formats python-can reads back with ``can.LogReader`` (:func:`log_formats`: ``blf``,
``asc``, candump ``log``, ``trc``; not ``mf4``: :data:`REFUSED_LOG_FORMATS`).  BLF is
formatted by :mod:`drivers.blf` (our own writer: why, there); the text formats by
python-can's public writers, whose formatted lines this class writes to the file itself
(durability below).  Channels follow python-can's
numbering: the first bus (``can0``) is channel 0 for python-can, ``1`` in an ASC, BLF or
TRC file (the writers add one, python-can's readers take it off) and ``can0`` in a
candump ``.log``.

>>> import tempfile, pathlib
>>> path = pathlib.Path(tempfile.mkdtemp()) / "doc.asc"
>>> log = TrafficLog(path)
>>> log.on_message_received(can.Message(arbitration_id=0x181, data=b"\\x01", timestamp=1.0))
>>> log.stop()
>>> [hex(m.arbitration_id) for m in can.LogReader(path)]
['0x181']
"""

from __future__ import annotations

import collections
import datetime as dt
import io
import math
import os
import struct
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from drivers.blf import FILE_HEADER_BYTES, MAX_TIMESTAMP_S, BlfFormatter
from drivers.protocol.batch import to_messages
from drivers.realtime import step_below_starter
from hrm_ctrl.errors import DriverError

LOG_FORMATS_ALWAYS = ("blf", "asc", "log", "trc")
"""Log formats python-can writes with what it needs installed (``--log-format``)."""

LOG_FORMAT_DURABILITY = {
    "blf": "crash-safe: at most FLUSH_S behind, whole frames after a kill -9",
    "asc": "crash-safe: at most FLUSH_S behind, whole lines after a kill -9",
    "log": "crash-safe: at most FLUSH_S behind, whole lines after a kill -9",
    "trc": "crash-safe: at most FLUSH_S behind, whole lines after a kill -9; python-can's "
    "writer leaves out error and remote frames",
}
"""What a process killed mid-run keeps of a log in each format (docs/drivers.md)."""


REFUSED_LOG_FORMATS = {
    "mf4": "python-can's MF4 writer takes about 0.5 ms a frame, slower than a bus sends "
    "them (a 36-drive cycle every 10 ms): the log would be incomplete; use blf",
}
"""Formats python-can writes that a CAN log of a run refuses, and why (``--log-format``)."""


def log_formats() -> tuple[str, ...]:
    """The log formats a CAN log is written in (:data:`LOG_FORMATS_ALWAYS`; python-can's
    ``mf4`` is refused: :data:`REFUSED_LOG_FORMATS`).

    >>> log_formats()
    ('blf', 'asc', 'log', 'trc')
    """
    return LOG_FORMATS_ALWAYS


LOG_SUFFIXES = tuple(f".{f}" for f in (*LOG_FORMATS_ALWAYS, "mf4"))
WRITER_IDLE_S = 0.05
MAX_JOINED_FRAMES = 4096  # batches the log writer packs at once (frames, at most)
#: A frame whose timestamp lies outside [0, this) s is not written to a BLF log (counted as
#: a write error): the file's header could not date it.
MAX_LOG_TIMESTAMP_S = MAX_TIMESTAMP_S
BLF_COMPRESSION_LEVEL = 1  # zlib level of the BLF containers this class writes


def ensure_log_dir(path: str | Path) -> Path:
    """Create the log directory if needed; a one-line :class:`DriverError` naming it
    when it is not a directory or cannot be created or written.

    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "file"
    >>> _ = f.write_text("")
    >>> ensure_log_dir(f)
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.DriverError: log directory ... exists and is not a directory
    """
    p = Path(path)
    if os.path.exists(p) and not os.path.isdir(p):  # (os.path: False on a too-long name)
        raise DriverError(f"log directory {p}: exists and is not a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DriverError(f"log directory {p}: cannot create it ({exc.strerror or exc})") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise DriverError(f"log directory {p}: not writable")
    return p


LogEntry = can.Message | tuple[np.ndarray, bool]
"""What :class:`TrafficLog` queues: a frame, or a batch of frames and whether received."""


class TrafficLog(can.Listener):
    """Thread-safe python-can log of one bus: received frames (listener) and sent
    frames (:meth:`log_sent`), written by a background thread in arrival order.

    Every frame on the wire is logged once: what the host sends when it sends it, and
    everything received (drives, other masters, error and remote frames) as the bus's
    receiver (:class:`drivers.receive.BusReceiver`) hands it over, our own echoes
    excepted.  Times in a file never go back: a frame is written with its own timestamp
    (a sent frame: the host's send time; a received one: its receive time on the host's
    clock as the interface gives it), or, when it reached the log after a frame stamped
    later (a received frame the host picked up late; an interface that stamps with the
    sender's time), with that later time: when the host had it at the latest."""

    def __init__(self, path: str | Path, channel: int = 1) -> None:
        self.path = Path(path)
        # ``channel``: the number an ASC, BLF or TRC file shows (1 for the first bus, as
        # CANalyzer and python-can's writers number them); frames carry python-can's
        # 0-based number (channel - 1), which its readers give back and candump writes
        # as ``can0``.
        self.channel = int(channel)
        self._msg_channel = self.channel - 1
        self.write_errors = 0
        self.first_error: str | None = None
        formats = log_formats()
        suffix = self.path.suffix.lower().lstrip(".")
        if suffix in REFUSED_LOG_FORMATS:
            raise DriverError(f"{self.path}: .{suffix} refused: {REFUSED_LOG_FORMATS[suffix]}")
        if suffix not in formats:
            raise DriverError(
                f"{self.path}: CAN log must end in "
                f"{', '.join('.' + f for f in formats)} (python-can's formats here)"
            )
        ensure_log_dir(self.path.parent)
        self.n_frames = 0  # frames in the file (handed to the writer, for another writer)
        self.n_lost = 0  # frames that never reached the file (it could not take more)
        self._unflushed = 0  # frames handed to the writer since the last flush
        self._last_ts: float | None = None  # timestamp of the last frame handed over
        self._file_ts = -math.inf  # ... as written: a file's times never go back
        self._logged_until: float | None = None  # ... and of the last one in the file
        self._broken = False
        self._durable = False  # this class writes the file (BLF, ASC, candump, TRC)
        self._blf: BlfFormatter | None = None  # BLF: our formatter (drivers.blf)
        self._writer: Any = None  # other formats: python-can's writer
        self._reserve = self._hold_reserve()
        if self.path.suffix.lower() == ".blf":
            self._open_blf()
            self._durable = True
        else:
            try:
                self._writer = can.Logger(str(self.path))
            except (OSError, ValueError, NotImplementedError) as exc:
                self._release_reserve()
                raise DriverError(f"{self.path}: cannot open CAN log ({exc})") from None
            try:
                self._durable = self._take_over_writes()
            except OSError as exc:
                self._release_reserve()
                try:
                    self._writer.file.close()
                except OSError:
                    pass
                raise DriverError(f"{self.path}: cannot open CAN log ({exc})") from None
        self._queue: collections.deque[LogEntry] = collections.deque()
        self._wake = threading.Event()
        self._kicked = False
        self._stopping = False
        self._thread = threading.Thread(
            target=self._run, name=f"canlog-{self.path.name}", daemon=True
        )
        self._thread.start()

    def on_message_received(self, msg: can.Message) -> None:
        """Record a received frame (every one: the bus's receiver has already dropped
        the echoes of our own frames, which were logged when sent)."""
        # Interfaces name channels freely (a virtual bus: any string); logs want a number.
        msg.channel = self._msg_channel
        # received: python-can's socketcan marks a frame another socket of this machine
        # sent (MSG_DONTROUTE: every frame on vcan, a local candump's) as not received
        msg.is_rx = True
        self._queue.append(msg)

    def log_sent(self, msg: can.Message) -> None:
        """Record a frame the host sent (``is_rx=False``)."""
        msg.channel = self._msg_channel
        self._queue.append(msg)

    def log_batch(self, frames: np.ndarray, is_rx: bool) -> None:
        """Record a batch of frames (a :data:`drivers.protocol.batch.FRAME_DTYPE` array,
        received or sent as ``is_rx`` says), in order with the frames queued around it.
        Queued as one entry (a copy: the caller may reuse the array); a BLF log packs it
        without a Python object per frame, other formats get ``can.Message`` objects in
        the writer thread."""
        if len(frames):
            self._queue.append((frames.copy(), bool(is_rx)))

    def _failed(self, text: str) -> None:
        self.write_errors += 1
        if self.first_error is None:
            self.first_error = text

    def _drain(self) -> None:
        q = self._queue
        if self._broken:  # the file takes no more: count what it misses
            while q:
                entry = q.popleft()
                self.n_lost += len(entry[0]) if type(entry) is tuple else 1
            return
        blf = self._blf
        write = blf.add if blf is not None else self._writer.on_message_received
        write_batch = blf.add_batch if blf is not None else None
        durable = self._durable
        while q:
            msg = q.popleft()
            if type(msg) is tuple:  # a batch (log_batch), and the batches right behind it
                entries = [msg]
                n = len(msg[0])
                while q and type(q[0]) is tuple and n < MAX_JOINED_FRAMES:
                    entries.append(q.popleft())
                    n += len(entries[-1][0])
                if len(entries) == 1:
                    frames, is_rx = msg
                else:  # packed at once: the packing's fixed cost once per drain
                    frames = np.concatenate([f for f, _rx in entries])
                    is_rx = np.repeat([rx for _f, rx in entries], [len(f) for f, _rx in entries])
                stamps = frames["timestamp"]  # our copy (log_batch): never earlier than the last
                running = file_times(stamps, self._file_ts)
                try:
                    done = write_batch is not None and write_batch(frames, is_rx)
                except Exception as exc:
                    self._failed(f"{self.path.name}: cannot log {len(frames)} frames ({exc})")
                    continue
                if done:
                    self._unflushed += len(frames)
                    self._last_ts = float(stamps[-1])
                    self._file_ts = running
                else:  # frame by frame, before everything queued after the batches
                    for f, rx in reversed(entries):
                        q.extendleft(reversed(to_messages(f, self._msg_channel, rx)))
                continue
            ts = msg.timestamp
            datable = 0.0 <= ts < MAX_LOG_TIMESTAMP_S  # else left as it is (BLF refuses it)
            if datable and ts < self._file_ts:  # reached the log after a later frame
                msg.timestamp = self._file_ts
            try:
                write(msg)
            except Exception as exc:  # one bad frame must not end the log
                self._failed(f"{self.path.name}: cannot log {msg} ({exc})")
                continue
            if datable:
                self._file_ts = msg.timestamp
            if durable:
                self._unflushed += 1
                self._last_ts = msg.timestamp
            else:
                self.n_frames += 1

    def kick(self) -> None:
        """The control loop's cue, right after a cycle's frames went out (when its next
        deadline is furthest): write and flush now.  While kicks come (at least every
        :attr:`FLUSH_S`), the writer works only then: its time holding the interpreter
        lock falls in the cycle's slack instead of delaying a SYNC (BENCHMARKS.md); when
        they stop, its own timer takes over within :attr:`FLUSH_S`."""
        self._kicked = True
        self._wake.set()

    def _run(self) -> None:
        step_below_starter()  # under FIFO, the supervisor preempts the writer
        now = time.monotonic()
        next_flush = now + self.FLUSH_S
        last_kick = -math.inf
        while not self._stopping:
            if now - last_kick < self.FLUSH_S:  # kicked: the next kick, or FLUSH_S
                timeout = max(0.0, last_kick + self.FLUSH_S - now)
            else:
                timeout = max(0.0, min(WRITER_IDLE_S, next_flush - now))
            self._wake.wait(timeout)
            self._wake.clear()
            kicked, self._kicked = self._kicked, False
            now = time.monotonic()
            if kicked:
                last_kick = now
            self._drain()
            if kicked or now >= next_flush:
                self._flush()
                now = time.monotonic()
                next_flush = now + self.FLUSH_S
        self._drain()

    def stop(self) -> None:
        """Write everything queued and close the file (idempotent); then give back the
        space held for the run record (:meth:`_hold_reserve`)."""
        if self._stopping:
            return
        self._stopping = True
        self._wake.set()
        self._thread.join(timeout=10.0)
        if self._thread.is_alive():  # the disk hangs: do not write from two threads
            self._failed(f"{self.path.name}: writer still busy after 10 s")
            self._release_reserve()
            return
        self._drain()
        if self._durable:
            self._close_durable()
        else:
            try:
                self._writer.stop()
            except Exception as exc:  # flush/close failed (disk full, I/O error)
                self._failed(f"{self.path.name}: cannot close ({exc})")
        self._release_reserve()

    # -------------------------------------------------------------- durability
    # Crash safety (kill -9): the file on disk is at most FLUSH_S behind, always readable
    # by can.LogReader and carries its absolute start time.  This class does the file
    # writes of BLF (drivers.blf formats) and of the text formats (python-can's ASC,
    # candump .log and TRC writers format into a StringIO): every FLUSH_S the formatted
    # frames go out in one write(2) (BLF: zlib containers; text: whole lines), then the
    # BLF header is rewritten in place.  A SIGKILL can cut a write(2) only between pages (the
    # kernel checks for it page by page), so no line and no container header is let
    # straddle a page boundary: a cut file still ends with whole lines, or with a
    # container whose headers are whole (its cut zlib stream yields every whole frame in
    # it).
    # Disk full: the file is cut back to its last whole write and ends there, the frames
    # that missed it are counted (``n_lost``) and the error named (``first_error``).

    FLUSH_S = 0.1  # the file is never further behind the frames handed over than this
    RECORD_RESERVE_BYTES = 64 * 1024  # held in the log's folder for the run record
    PAGE_BYTES = 4096  # the granularity at which a SIGKILL can cut a write(2)

    def _hold_reserve(self) -> Path:
        """Hold :attr:`RECORD_RESERVE_BYTES` of disk in the log's folder (a hidden file,
        removed when the log closes), so that a disk the run fills up still takes the run
        record written after the logs close; a disk already full refuses the log."""
        reserve = self.path.with_name(f".{self.path.name}.reserve")
        try:
            with open(reserve, "wb") as f:
                f.write(bytes(self.RECORD_RESERVE_BYTES))
        except OSError as exc:
            try:
                reserve.unlink()
            except OSError:
                pass
            raise DriverError(
                f"{self.path.parent}: no room for the run record "
                f"({self.RECORD_RESERVE_BYTES} bytes: {exc.strerror or exc})"
            ) from None
        return reserve

    def _release_reserve(self) -> None:
        try:
            self._reserve.unlink()
        except OSError:
            pass

    def _open_blf(self) -> None:
        """Open a BLF file (:mod:`drivers.blf` formats it, this class writes it): its
        header, with the file's absolute start, written at once."""
        # The file's absolute start is now (in ms, as BLF keeps it), so the header has it
        # from the first flush on; frame times are kept relative to it.  zlib level 1: a
        # sixth of the default level's CPU for 5 % more bytes (measured on a cycle's
        # frames: 0.09 against 0.63 ms per 37 kB).
        self._blf = BlfFormatter(
            start_s=time.time(), channel=self.channel, compression_level=BLF_COMPRESSION_LEVEL
        )
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        except OSError as exc:
            self._release_reserve()
            raise DriverError(f"{self.path}: cannot open CAN log ({exc})") from None
        try:
            header = self._blf.header(FILE_HEADER_BYTES)
            view = memoryview(header)
            while view:
                view = view[os.write(self._fd, view) :]
        except OSError as exc:
            self._release_reserve()
            os.close(self._fd)
            raise DriverError(f"{self.path}: cannot open CAN log ({exc})") from None
        self._end = FILE_HEADER_BYTES  # bytes of the file that are whole

    def _take_over_writes(self) -> bool:
        """Make python-can's ASC, candump or TRC writer format only; this class writes
        the file (see above).  Another writer is left alone: it writes the file itself."""
        w = self._writer
        if isinstance(w, can.ASCWriter):
            # python-can (4.6) writes a date's milliseconds without leading zeros (".18"
            # for 18 ms, which readers take for 180 ms): 3 digits, and the `date` of the
            # start written again with them.
            w.FORMAT_DATE = can.ASCWriter.FORMAT_DATE.replace("{}", "{:03d}")
            w.file.flush()
            lines = self.path.read_text(encoding=w.file.encoding).splitlines(keepends=True)
            if lines and lines[0].startswith("date "):
                lines[0] = f"date {asc_date(dt.datetime.now())}\n"
            w.file.seek(0)
            w.file.truncate()
            w.file.write("".join(lines))
            w.file.flush()  # the header lines, the `date` of the start among them
            self._file = w.file
            self._encoding = w.file.encoding
            self._fd = w.file.fileno()
            self._end = os.lseek(self._fd, 0, os.SEEK_END)
            w.file = io.StringIO()
            return True
        if isinstance(w, can.CanutilsLogWriter | can.TRCWriter):
            # candump: no header; TRC: its header goes out with the first frame (with the
            # frame's time as the file's start), "\r\n" line ends as python-can's writer.
            w.file.flush()
            self._file = w.file
            self._encoding = w.file.encoding
            self._fd = w.file.fileno()
            self._end = os.lseek(self._fd, 0, os.SEEK_END)
            w.file = io.StringIO(newline="\r\n" if isinstance(w, can.TRCWriter) else None)
            return True
        return False

    def _flush(self) -> None:
        """Put every frame handed to the writer into the file (one write(2)); on an
        ``OSError`` the log ends at its last whole write (:meth:`_break`)."""
        if not self._durable or self._broken:
            return
        blf = self._blf
        try:
            if blf is not None:
                data = blf.take_containers(self._end, self.PAGE_BYTES)
            else:
                data = self._asc_lines()
            if data:
                view = memoryview(data)
                while view:
                    view = view[os.write(self._fd, view) :]
                self._end += len(data)
                if blf is not None:  # the header for the file as it is (one page: never cut)
                    os.pwrite(self._fd, blf.header(self._end), 0)
        except OSError as exc:
            self._break(exc)
            return
        except (ValueError, OverflowError, struct.error) as exc:  # a header it cannot pack
            self._failed(f"{self.path.name}: cannot write the BLF header ({exc})")
        self.n_frames += self._unflushed
        self._unflushed = 0
        self._logged_until = self._last_ts

    def _asc_lines(self) -> bytes:
        """The whole lines the writer formatted (ASC, candump, TRC), each kept within one
        page.  ASC and TRC: a line that would straddle a page boundary is put after a
        blank line that fills the page (their readers skip blank lines).  candump: can-utils'
        tools (``log2long``, ``canplayer``) stop at a line that is not a frame, so the page
        is filled with spaces at the end of the line before it (every candump reader splits
        a line at whitespace), and the last line of a write is padded so when less than
        :data:`CANDUMP_LINE_BYTES` of its page are left (the next write's first line fits)."""
        text_io = self._writer.file
        text = text_io.getvalue()
        cut = text.rfind("\n") + 1
        text_io.seek(0)
        text_io.truncate()
        text_io.write(text[cut:])
        lines = text[:cut].encode(self._encoding).splitlines(keepends=True)
        if isinstance(self._writer, can.CanutilsLogWriter):
            return candump_lines(lines, self._end, self.PAGE_BYTES)
        page = self.PAGE_BYTES
        pos = self._end
        out = bytearray()
        for line in lines:
            room = page - pos % page
            if room < len(line) <= page:
                out += b" " * (room - 1) + b"\n"
                pos += room
            out += line
            pos += len(line)
        return bytes(out)

    def _break(self, exc: OSError) -> None:
        """The file takes no more (disk full, I/O error): cut it back to its last whole
        write (readable, its header intact), drop every later frame, name why."""
        self._broken = True
        self.n_lost += self._unflushed
        self._unflushed = 0
        try:
            os.ftruncate(self._fd, self._end)
            os.lseek(self._fd, self._end, os.SEEK_SET)
        except OSError:
            pass
        if self._blf is not None:
            self._blf.discard()
        ts = self._logged_until
        until = (
            "no frame is in the log"
            if ts is None
            else "it ends with the frame of "
            + dt.datetime.fromtimestamp(ts, dt.UTC).isoformat(timespec="milliseconds")
        )
        self._failed(f"{self.path.name}: cannot write ({exc.strerror or exc}); {until}")

    def _close_durable(self) -> None:
        self._flush()
        if self._blf is not None:  # the final header (the same as the last one written)
            try:
                if not self._broken:
                    os.pwrite(self._fd, self._blf.header(self._end), 0)
            except (OSError, ValueError, OverflowError, struct.error) as exc:
                self._failed(f"{self.path.name}: cannot close ({exc})")
            try:
                os.close(self._fd)
            except OSError as exc:
                self._failed(f"{self.path.name}: cannot close ({exc})")
            return
        if self._broken:  # python-can's stop() would write on: close the file as it is
            try:
                self._file.close()
            except OSError:
                pass
            return
        w = self._writer
        w.file = self._file  # the writer ends the file itself (ASC: "End TriggerBlock")
        try:
            w.stop()
        except Exception as exc:  # flush/close failed (disk full, I/O error)
            self._failed(f"{self.path.name}: cannot close ({exc})")


def file_times(stamps: np.ndarray, last_s: float) -> float:
    """Raise each time of ``stamps`` (in place) to the latest before it and ``last_s``, so
    they never go back; a time outside [0, :data:`MAX_LOG_TIMESTAMP_S`) is left as it is
    and sets no floor.  Returns the floor after the last.

    >>> t = np.array([5.0, 3.0, -1.0, 4.0, 7.0, 6.0])
    >>> file_times(t, 4.5), t.tolist()
    (7.0, [5.0, 5.0, -1.0, 5.0, 7.0, 7.0])
    """
    datable = (stamps >= 0.0) & (stamps < MAX_LOG_TIMESTAMP_S)
    floor = np.maximum.accumulate(np.maximum(np.where(datable, stamps, -math.inf), last_s))
    stamps[datable] = floor[datable]
    return float(floor[-1]) if len(floor) else last_s


#: A candump line python-can writes for a classical frame is at most 55 bytes ("(%f)" of a
#: Unix time, " can" + channel, a 29-bit id, 8 data bytes, " R", newline): a write leaves
#: at least this much of its last page, or fills it.
CANDUMP_LINE_BYTES = 64


def candump_lines(lines: list[bytes], pos: int, page: int) -> bytes:
    """candump ``lines`` to be written at file offset ``pos``, none straddling a ``page``
    boundary: the page is filled with spaces at the end of the line before (a candump
    reader splits at whitespace; no line that is not a frame, where can-utils' tools stop).

    >>> out = candump_lines([b"(1.000000) can0 181#01 R\\n"] * 3, 4096 - 60, 4096)
    >>> [len(x) for x in out.splitlines(keepends=True)], out.split(b"\\n")[0].rstrip()
    ([25, 35, 25], b'(1.000000) can0 181#01 R')
    """
    out = bytearray()
    for line in lines:
        room = page - pos % page
        if out and room < len(line) <= page:  # the line before fills the page
            out[-1:-1] = b" " * room
            pos += room
        out += line
        pos += len(line)
    room = page - pos % page
    if out and room < CANDUMP_LINE_BYTES and room != page:
        out[-1:-1] = b" " * room
    return bytes(out)


def asc_date(when: dt.datetime) -> str:
    """A date as an ASC file's ``date`` line has it, with 3 digits of milliseconds
    (python-can's format, which writes ".18" for 18 ms).

    >>> asc_date(dt.datetime(2024, 3, 5, 7, 8, 9, 18_000))
    'Tue Mar 05 07:08:09.018 2024'
    """
    fmt = can.ASCWriter.FORMAT_DATE.replace("{}", "{:03d}")
    return when.strftime(fmt.format(when.microsecond // 1000 % 1000))
