"""A bus port: sends frames under a lock and taps every frame into a python-can log.

Each bus of the box is wrapped in a :class:`BusPort`.  Frames the host sends go
through :meth:`BusPort.send` (a failed send raises :class:`BusSendError`, a
:class:`DriverError` naming the bus); frames it receives reach the
:class:`TrafficLog` as a ``can.Listener``.  The log is written by a background
thread so the control cycle never waits for the disk, in one of the formats python-can
writes (:func:`log_formats`: ``blf``, ``asc``, candump ``log``, ``trc``, and ``mf4`` where
asammdf is installed), read back by ``can.LogReader``.  Channels follow python-can's
numbering: the first bus (``can0``) is channel 0 for python-can, ``1`` in an ASC, BLF or
TRC file (python-can's writers add one, its readers take it off) and ``can0`` in a candump
``.log``.

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
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from drivers.protocol.batch import (
    FLAG_ERROR,
    FLAG_EXTENDED,
    FLAG_REMOTE,
    FRAME_DTYPE,
    ID_MASK,
    to_messages,
)
from drivers.protocol.cia301 import (
    COB_NMT,
    COB_NMT_ERROR_CONTROL,
    COB_RPDO1,
    COB_RPDO2,
    COB_RPDO3,
    COB_RPDO4,
    COB_SDO_RX,
    COB_SYNC,
    HOST_HEARTBEAT_NODE_ID,
)
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
    "mf4": "written when the log closes: a killed process leaves no readable file",
}
"""What a process killed mid-run keeps of a log in each format (docs/drivers.md)."""


def log_formats() -> tuple[str, ...]:
    """The log formats this installation writes: :data:`LOG_FORMATS_ALWAYS`, plus ``mf4``
    when asammdf (python-can's MF4 writer needs it) is installed.

    >>> log_formats()[:4]
    ('blf', 'asc', 'log', 'trc')
    """
    import importlib.util

    extra = ("mf4",) if importlib.util.find_spec("asammdf") is not None else ()
    return LOG_FORMATS_ALWAYS + extra


LOG_SUFFIXES = tuple(f".{f}" for f in (*LOG_FORMATS_ALWAYS, "mf4"))
WRITER_IDLE_S = 0.05
MAX_JOINED_FRAMES = 4096  # batches the log writer packs at once (frames, at most)
#: A frame whose timestamp lies outside [0, this) s is not written to a BLF log (counted as
#: a write error): python-can's writer takes it and then cannot write the file's header
#: (a date past the year 9999), and every frame after it would be lost.
MAX_LOG_TIMESTAMP_S = 2.0**32
BLF_COMPRESSION_LEVEL = 1  # zlib level of the BLF containers this class writes

# COB-ID ranges the host transmits (CiA 301 predefined connection set): NMT, SYNC,
# RPDO1..4 (0x200/0x300/0x400/0x500 + node), SDO client -> server (0x600 + node).
_HOST_RANGES = (
    (COB_NMT, COB_NMT),
    (COB_SYNC, COB_SYNC),
    (COB_RPDO1, COB_RPDO1 + 0x7F),
    (COB_RPDO2, COB_RPDO2 + 0x7F),
    (COB_RPDO3, COB_RPDO3 + 0x7F),
    (COB_RPDO4, COB_RPDO4 + 0x7F),
    (COB_SDO_RX, COB_SDO_RX + 0x7F),
)


def is_host_frame(cob_id: int, host_node_id: int = HOST_HEARTBEAT_NODE_ID) -> bool:
    """Whether an 11-bit COB-ID is one the host sends (not a drive).

    >>> [is_host_frame(x) for x in (0x000, 0x080, 0x201, 0x57F, 0x601, 0x77F)]
    [True, True, True, True, True, True]
    >>> [is_host_frame(x) for x in (0x081, 0x181, 0x281, 0x581, 0x701, 0x77E)]
    [False, False, False, False, False, False]
    """
    if cob_id == COB_NMT_ERROR_CONTROL + host_node_id:
        return True
    return any(lo <= cob_id <= hi for lo, hi in _HOST_RANGES)


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


class BusSendError(DriverError):
    """A frame could not be sent on a bus."""


LogEntry = can.Message | tuple[np.ndarray, bool]
"""What :class:`TrafficLog` queues: a frame, or a batch of frames and whether received."""


class TrafficLog(can.Listener):
    """Thread-safe python-can log of one bus: received frames (listener) and sent
    frames (:meth:`log_sent`), written by a background thread in arrival order.

    Every frame on the wire is logged once: what the host sends when it sends it, and
    everything received (drives, other masters, error and remote frames) as the bus's
    receiver (:class:`drivers.receive.BusReceiver`) hands it over, our own echoes
    excepted."""

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
        if self.path.suffix.lower().lstrip(".") not in formats:
            raise DriverError(
                f"{self.path}: CAN log must end in "
                f"{', '.join('.' + f for f in formats)} (python-can's formats here)"
            )
        ensure_log_dir(self.path.parent)
        self.n_frames = 0  # frames in the file (handed to the writer, for another writer)
        self.n_lost = 0  # frames that never reached the file (it could not take more)
        self._unflushed = 0  # frames handed to the writer since the last flush
        self._last_ts: float | None = None  # timestamp of the last frame handed over
        self._logged_until: float | None = None  # ... and of the last one in the file
        self._broken = False
        self._durable: str | None = None  # "blf", "asc" or "text": this class writes the file
        self._reserve = self._hold_reserve()
        try:
            self._writer: Any = can.Logger(str(self.path))
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
        write = self._blf_fast() if self._durable == "blf" else self._writer.on_message_received
        write_batch = self._blf_batch if self._durable == "blf" else None
        durable = self._durable is not None
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
                try:
                    done = write_batch is not None and write_batch(frames, is_rx)
                except Exception as exc:
                    self._failed(f"{self.path.name}: cannot log {len(frames)} frames ({exc})")
                    continue
                if done:
                    self._unflushed += len(frames)
                    self._last_ts = float(frames["timestamp"][-1])
                else:  # frame by frame, before everything queued after the batches
                    for f, rx in reversed(entries):
                        q.extendleft(reversed(to_messages(f, self._msg_channel, rx)))
                continue
            try:
                write(msg)
            except Exception as exc:  # one bad frame must not end the log
                self._failed(f"{self.path.name}: cannot log {msg} ({exc})")
                continue
            if durable:
                self._unflushed += 1
                self._last_ts = msg.timestamp
            else:
                self.n_frames += 1

    def _blf_fast(self) -> Any:
        """python-can's ``BLFWriter.on_message_received`` for a classic CAN frame in one
        ``struct`` pack (object header, its time header and the CAN_MESSAGE body: the
        same 48 bytes python-can appends, ~10x cheaper); error and FD frames go to
        python-can's writer."""
        w = self._writer
        pack = _BLF_CAN_OBJECT.pack
        slow = w.on_message_received
        buf = w._buffer
        start = w.start_timestamp

        def write(msg: can.Message) -> None:
            nonlocal buf
            ts = msg.timestamp
            if not 0.0 <= ts < MAX_LOG_TIMESTAMP_S:  # NaN too
                raise ValueError(f"timestamp {ts!r} outside 0..2**32 s")
            if msg.is_error_frame or msg.is_fd or start is None:
                slow(msg)
                buf = w._buffer  # python-can may have swapped it (a flush)
                return
            ch = msg.channel
            if type(ch) is not int:
                ch = can.util.channel2int(ch)
            ch = w.channel if ch is None else ch + 1  # python-can's numbering
            arb = msg.arbitration_id | (_BLF_CAN_MSG_EXT if msg.is_extended_id else 0)
            flags = (_BLF_REMOTE_FLAG if msg.is_remote_frame else 0) | (
                0 if msg.is_rx else _BLF_DIR
            )
            t_ns = int((ts - start) * 1e9)
            if w._buffer is not buf:
                buf = w._buffer
            buf.append(
                pack(
                    b"LOBJ", _BLF_HEADER_SIZE, 1, _BLF_OBJ_SIZE, _BLF_CAN_MESSAGE,
                    _BLF_TIME_ONE_NANS, 0, 0, t_ns if t_ns > 0 else 0,
                    ch, flags, msg.dlc, arb, bytes(msg.data),
                )
            )  # fmt: skip
            w.stop_timestamp = ts
            w._buffer_size += _BLF_OBJ_SIZE
            w.object_count += 1
            if w._buffer_size >= w.max_container_size:
                w._flush()

        return write

    def _blf_batch(self, frames: np.ndarray, is_rx: bool | np.ndarray) -> bool:
        """:meth:`_blf_fast` for a whole batch: its BLF CAN_MESSAGE objects packed at once
        with NumPy (the same bytes); ``False``, nothing written, when it must go frame by
        frame (an error frame in it, a timestamp a BLF object cannot hold).  ``is_rx``: one
        direction for all, or one per frame (batches joined)."""
        w = self._writer
        start = w.start_timestamp
        ident = frames["id"]
        flags = int(np.bitwise_or.reduce(ident))  # the flag bits any frame has
        if start is None or flags & FLAG_ERROR:
            return False
        ts = frames["timestamp"]
        if not (float(ts.min()) >= 0.0 and float(ts.max()) < MAX_LOG_TIMESTAMP_S):  # NaN
            return False  # frame by frame: the bad ones counted, the others written
        t_ns = (ts - start) * 1e9
        out = np.frombuffer(bytearray(_BLF_OBJECT_TEMPLATE * len(frames)), _BLF_OBJECT)
        out["timestamp"] = np.maximum(t_ns, 0.0, out=t_ns)  # then truncated, as int() does
        out["channel"] = self.channel
        out["dlc"] = frames["dlc"]
        out["id"] = ident & _ID_AND_EXT  # the extended bit is BLF's CAN_MSG_EXT
        words = frames.view(_FRAME_WORDS)
        data = words["data"] & _DLC_DATA_MASK.take(words["dlc"])
        if isinstance(is_rx, np.ndarray):
            direction: Any = np.where(is_rx, 0, _BLF_DIR).astype(np.uint16)
        else:
            direction = 0 if is_rx else _BLF_DIR
        if flags & FLAG_REMOTE:
            remote = (ident & FLAG_REMOTE) != 0
            out["flags"] = np.where(remote, _BLF_REMOTE_FLAG | direction, direction)
            data[remote] = 0  # a can.Message remote frame has no data
        else:
            out["flags"] = direction
        out["data"] = data
        w._buffer.append(out.tobytes())
        w.stop_timestamp = float(ts[-1])
        w._buffer_size += out.nbytes
        w.object_count += len(out)
        while w._buffer_size >= w.max_container_size:  # python-can writes one per _flush
            size = w._buffer_size
            w._flush()
            if w._buffer_size >= size:  # its file is closed
                break
        return True

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
        if self._durable is not None:
            self._close_durable()
        else:
            try:
                self._writer.stop()
            except Exception as exc:  # flush/close failed (disk full, I/O error)
                self._failed(f"{self.path.name}: cannot close ({exc})")
        self._release_reserve()

    # -------------------------------------------------------------- durability
    # Crash safety (kill -9): the file on disk is at most FLUSH_S behind, always readable
    # by can.LogReader and carries its absolute start time.  For python-can's BLF writer
    # and its text writers (ASC, candump .log, TRC) this class does the file writes itself:
    # the writer only formats (BLF objects into its buffer, text lines into a StringIO);
    # every FLUSH_S the formatted frames go out in one write(2) (BLF: zlib containers;
    # text: whole lines), then the BLF header is rewritten in place.  MF4 (asammdf) is
    # written when the log closes (LOG_FORMAT_DURABILITY).  A SIGKILL can cut a write(2)
    # only between pages (the kernel checks for it page by page), so no line and no
    # container header is let straddle a page boundary: a cut file still ends with whole
    # lines, or with a container whose headers are whole (its cut zlib stream yields
    # every whole frame in it).
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

    def _take_over_writes(self) -> str | None:
        """Make python-can's BLF, ASC, candump or TRC writer format only; this class
        writes the file (see above).  Another writer (MF4) is left alone: it writes the
        file when it stops."""
        import datetime as dt
        import io

        w = self._writer
        if isinstance(w, can.BLFWriter):
            w.file.flush()  # python-can's provisional header
            # zlib level 1: a sixth of the default level's CPU for 5 % more bytes (measured
            # on a cycle's frames: 0.09 against 0.63 ms per 37 kB)
            w.compression_level = BLF_COMPRESSION_LEVEL
            # The file's absolute start is now (in ms, as BLF keeps it), so the header has
            # it from the first flush on; frame times are kept relative to it.
            w.start_timestamp = w.stop_timestamp = int(time.time() * 1000) / 1000
            self._container_bytes = w.max_container_size
            w.max_container_size = 1 << 62  # python-can never writes a container itself
            self._fd = w.file.fileno()
            self._end = os.lseek(self._fd, 0, os.SEEK_END)  # bytes of the file that are whole
            self._write_blf_header()
            return "blf"
        if isinstance(w, can.ASCWriter):
            # python-can (4.6) writes a date's milliseconds without leading zeros (".18"
            # for 18 ms, which readers take for 180 ms): 3 digits, and the `date` of the
            # start written again with them.
            w.FORMAT_DATE = can.ASCWriter.FORMAT_DATE.replace("{}", "{:03d}")
            w.file.flush()
            lines = self.path.read_text(encoding=w.file.encoding).splitlines(keepends=True)
            if lines and lines[0].startswith("date "):
                lines[0] = f"date {w._format_header_datetime(dt.datetime.now())}\n"
            w.file.seek(0)
            w.file.truncate()
            w.file.write("".join(lines))
            w.file.flush()  # the header lines, the `date` of the start among them
            self._file = w.file
            self._encoding = w.file.encoding
            self._fd = w.file.fileno()
            self._end = os.lseek(self._fd, 0, os.SEEK_END)
            w.file = io.StringIO()
            return "asc"
        if isinstance(w, can.CanutilsLogWriter | can.TRCWriter):
            # candump: no header; TRC: its header goes out with the first frame (with the
            # frame's time as the file's start), "\r\n" line ends as python-can's writer.
            w.file.flush()
            self._file = w.file
            self._encoding = w.file.encoding
            self._fd = w.file.fileno()
            self._end = os.lseek(self._fd, 0, os.SEEK_END)
            w.file = io.StringIO(newline="\r\n" if isinstance(w, can.TRCWriter) else None)
            return "text"
        return None

    def _flush(self) -> None:
        """Put every frame handed to the writer into the file (one write(2)); on an
        ``OSError`` the log ends at its last whole write (:meth:`_break`)."""
        if self._durable is None or self._broken:
            return
        try:
            data = self._blf_containers() if self._durable == "blf" else self._asc_lines()
            if data:
                view = memoryview(data)
                while view:
                    view = view[os.write(self._fd, view) :]
                self._end += len(data)
                if self._durable == "blf":
                    self._write_blf_header()
        except OSError as exc:
            self._break(exc)
            return
        except (ValueError, OverflowError) as exc:  # a header python-can cannot write
            self._failed(f"{self.path.name}: cannot write the BLF header ({exc})")
        self.n_frames += self._unflushed
        self._unflushed = 0
        self._logged_until = self._last_ts

    def _blf_containers(self) -> bytes:
        """The writer's buffered objects as zlib log containers; a container is padded
        after its zlib stream (readers stop at the stream's end) so that the next one's
        32 header bytes start within one page."""
        import zlib

        from can.io import blf

        w = self._writer
        raw = b"".join(w._buffer)
        w._buffer, w._buffer_size = [], 0
        head = blf.OBJ_HEADER_BASE_STRUCT.size + blf.LOG_CONTAINER_STRUCT.size
        page = self.PAGE_BYTES
        out = bytearray()
        for i in range(0, len(raw), self._container_bytes):
            chunk = raw[i : i + self._container_bytes]
            body = zlib.compress(chunk, w.compression_level)
            pad = 0
            while True:  # python-can pads an object of size s by s % 4 bytes
                size = head + len(body) + pad
                if (self._end + len(out) + size + size % 4) % page <= page - head:
                    break
                pad += 1
            out += blf.OBJ_HEADER_BASE_STRUCT.pack(
                b"LOBJ", blf.OBJ_HEADER_BASE_STRUCT.size, 1, size, blf.LOG_CONTAINER
            )
            out += blf.LOG_CONTAINER_STRUCT.pack(blf.ZLIB_DEFLATE, len(chunk))
            out += body + bytes(pad + size % 4)
            w.uncompressed_size += head + len(chunk)
        return bytes(out)

    def _write_blf_header(self) -> None:
        """python-can's BLF header (start and stop time, sizes, object count) for the
        file as it is, written in place (one page: never cut)."""
        import io

        w = self._writer
        file, w.file = w.file, io.BytesIO()
        try:
            w._write_header(self._end)
            header = w.file.getvalue()
        finally:
            w.file = file
        os.pwrite(self._fd, header, 0)

    def _asc_lines(self) -> bytes:
        """The whole lines the writer formatted (ASC, candump, TRC), each kept within one
        page (a line that would straddle a page boundary is put after a blank line that
        fills the page: the readers of all three skip blank lines)."""
        text_io = self._writer.file
        text = text_io.getvalue()
        cut = text.rfind("\n") + 1
        text_io.seek(0)
        text_io.truncate()
        text_io.write(text[cut:])
        page = self.PAGE_BYTES
        pos = self._end
        out = bytearray()
        for line in text[:cut].encode(self._encoding).splitlines(keepends=True):
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
        import datetime as dt

        self._broken = True
        self.n_lost += self._unflushed
        self._unflushed = 0
        try:
            os.ftruncate(self._fd, self._end)
            os.lseek(self._fd, self._end, os.SEEK_SET)
        except OSError:
            pass
        if self._durable == "blf":
            self._writer._buffer, self._writer._buffer_size = [], 0
        ts = self._logged_until
        until = (
            "no frame is in the log"
            if ts is None
            else "it ends with the frame of "
            + dt.datetime.fromtimestamp(ts, dt.UTC).isoformat(timespec="milliseconds")
        )
        self._failed(f"{self.path.name}: cannot write ({exc.strerror or exc}); {until}")

    def _close_durable(self) -> None:
        w = self._writer
        self._flush()
        if self._broken:  # python-can's stop() would write on: close the file as it is
            file = w.file if self._durable == "blf" else self._file
            try:
                file.close()
            except OSError:
                pass
            return
        if self._durable in ("asc", "text"):
            w.file = self._file  # the writer ends the file itself (ASC: "End TriggerBlock")
        else:
            w.max_container_size = self._container_bytes
        try:
            w.stop()  # BLF: the final header (the same as the last one written)
        except Exception as exc:  # flush/close failed (disk full, I/O error)
            self._failed(f"{self.path.name}: cannot close ({exc})")


def _blf_struct() -> Any:
    import struct

    from can.io import blf

    return struct.Struct(
        "<"
        + blf.OBJ_HEADER_BASE_STRUCT.format.lstrip("<")
        + blf.OBJ_HEADER_V1_STRUCT.format.lstrip("<")
        + blf.CAN_MSG_STRUCT.format.lstrip("<")
    )


# One BLF CAN_MESSAGE object as python-can writes it (TrafficLog._blf_fast).
_BLF_CAN_OBJECT = _blf_struct()
_BLF_HEADER_SIZE = can.io.blf.OBJ_HEADER_BASE_STRUCT.size + can.io.blf.OBJ_HEADER_V1_STRUCT.size
_BLF_OBJ_SIZE = _BLF_HEADER_SIZE + can.io.blf.CAN_MSG_STRUCT.size  # 48: no padding
_BLF_CAN_MESSAGE = can.io.blf.CAN_MESSAGE
_BLF_TIME_ONE_NANS = can.io.blf.TIME_ONE_NANS
_BLF_CAN_MSG_EXT = can.io.blf.CAN_MSG_EXT
_BLF_REMOTE_FLAG = can.io.blf.REMOTE_FLAG
_BLF_DIR = can.io.blf.DIR
# The same object as a NumPy record, to pack a batch at once (TrafficLog._blf_batch); its
# 8 data bytes as one little-endian word.
_BLF_OBJECT = np.dtype(
    [
        ("signature", "S4"),
        ("header_size", "<u2"),
        ("header_version", "<u2"),
        ("object_size", "<u4"),
        ("object_type", "<u4"),
        ("time_flags", "<u4"),
        ("client_index", "<u2"),
        ("object_version", "<u2"),
        ("timestamp", "<u8"),
        ("channel", "<u2"),
        ("flags", "u1"),
        ("dlc", "u1"),
        ("id", "<u4"),
        ("data", "<u8"),
    ]
)
assert _BLF_OBJECT.itemsize == _BLF_OBJ_SIZE == _BLF_CAN_OBJECT.size
# What every object of a batch shares: the headers; time, channel and frame are set per batch.
_BLF_OBJECT_TEMPLATE = _BLF_CAN_OBJECT.pack(
    b"LOBJ", _BLF_HEADER_SIZE, 1, _BLF_OBJ_SIZE, _BLF_CAN_MESSAGE,
    _BLF_TIME_ONE_NANS, 0, 0, 0, 0, 0, 0, 0, b"",
)  # fmt: skip
# drivers.protocol.batch.FRAME_DTYPE with its 8 data bytes as one little-endian word
_FRAME_WORDS = np.dtype(
    {
        "names": ["dlc", "data"],
        "formats": ["u1", "<u8"],
        "offsets": [FRAME_DTYPE.fields["dlc"][1], FRAME_DTYPE.fields["data"][1]],
        "itemsize": FRAME_DTYPE.itemsize,
    }
)
# A frame's identifier with BLF's extended bit: SocketCAN's flag bit 31 is CAN_MSG_EXT
assert FLAG_EXTENDED == _BLF_CAN_MSG_EXT
_ID_AND_EXT = np.uint32(ID_MASK | FLAG_EXTENDED)
# Data bytes a frame carries by its DLC (min(dlc, 8), as to_messages cuts them)
_DLC_DATA_MASK = np.array([(1 << 8 * min(d, 8)) - 1 for d in range(256)], dtype=np.uint64)

EchoKey = tuple[int, bool, bool, bytes]
ECHO_WINDOW_S = 2.0  # an echo of our own frame comes back within this, or never
MAX_PENDING_ECHOES = 16384  # 36 frames x 100 Hz x 2 s = 7,200 in flight at most
ECHOING_INTERFACES = frozenset({"udp_multicast"})  # deliver a sender's frames back to it


def echo_key(msg: can.Message) -> EchoKey:
    """What identifies a frame on the wire: identifier, its format, RTR, the data."""
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, bytes(msg.data))


class EchoLedger:
    """The frames this process sent on one bus and that the bus will deliver back to it
    (udp_multicast does; virtual, SocketCAN without ``receive_own_messages`` and
    ``hrm_sim`` do not): an echo is recognised by identifier and data and taken off
    once; anything else received, even with a host-direction COB-ID, is someone else's.

    >>> led = EchoLedger()
    >>> m = can.Message(arbitration_id=0x201, data=bytes([15, 0]), is_extended_id=False)
    >>> led.add(m, now=0.0)
    >>> led.take(m, now=0.01), led.take(m, now=0.02)    # our echo once, then a stranger's
    (True, False)
    >>> sync = can.Message(arbitration_id=0x080, is_extended_id=False)
    >>> got = []
    >>> for k in range(1000):                           # 10 s of SYNCs, echoed 5 ms later
    ...     led.add(sync, now=k * 0.01)
    ...     got.append(led.take(sync, now=k * 0.01 + 0.005))
    >>> all(got), led.take(sync, now=10.0)
    (True, False)
    """

    def __init__(self) -> None:
        self._pending: dict[EchoKey, collections.deque[float]] = {}
        self._order: collections.deque[tuple[float, EchoKey]] = collections.deque()
        self._lock = threading.Lock()
        self.n_echoes = 0

    def add(self, msg: can.Message, now: float) -> None:
        key = echo_key(msg)
        with self._lock:
            self._expire(now)
            if len(self._order) >= MAX_PENDING_ECHOES:
                self._pop_oldest()
            self._pending.setdefault(key, collections.deque()).append(now)
            self._order.append((now, key))

    def discard(self, msg: can.Message) -> None:
        """A frame that was not sent after all (the send failed)."""
        key = echo_key(msg)
        with self._lock:
            times = self._pending.get(key)
            if times:
                times.pop()
                if not times:
                    del self._pending[key]

    def take(self, msg: can.Message, now: float) -> bool:
        """Whether ``msg`` is the echo of a frame we sent (then it is taken off)."""
        key = echo_key(msg)
        with self._lock:
            self._expire(now)
            times = self._pending.get(key)
            if not times:
                return False
            times.popleft()
            if not times:
                del self._pending[key]
            self.n_echoes += 1
            return True

    def _pop_oldest(self) -> None:
        """Forget the oldest frame sent, unless its echo already came back (then the
        key's oldest pending time is later than this entry's)."""
        t, key = self._order.popleft()
        times = self._pending.get(key)
        if times and times[0] <= t:
            times.popleft()
            if not times:
                del self._pending[key]

    def _expire(self, now: float) -> None:
        while self._order and now - self._order[0][0] > ECHO_WINDOW_S:
            self._pop_oldest()


class BusPort:
    """One opened CAN bus of the box: a name, a send lock, an optional log tap, and
    (on a bus that delivers our own frames back) the ledger of frames sent."""

    def __init__(
        self, name: str, bus: can.BusABC, log: TrafficLog | None = None, echoes: bool = False
    ) -> None:
        self.name = name
        self.bus = bus
        self.log = log
        self.echoes = EchoLedger() if echoes else None
        self._lock = threading.Lock()
        self.n_sent = 0
        # the bus's batch send (duck-typed: hrm_ipc has one; drivers never import it)
        self._send_batch = getattr(bus, "send_many", None)
        if not callable(self._send_batch):
            self._send_batch = None
        # a bus that sends a record array of frames (drivers.protocol.batch) as it is
        self._send_records = getattr(bus, "send_batch", None)
        if not callable(self._send_records) or echoes:
            self._send_records = None

    def is_own_echo(self, msg: can.Message) -> bool:
        """Whether a received frame is one this process sent, coming back."""
        return self.echoes is not None and self.echoes.take(msg, time.monotonic())

    def send(self, msg: can.Message, timeout_s: float = 0.05) -> None:
        """Send one frame; raise :class:`BusSendError` naming the bus on failure."""
        msg.timestamp = time.time()
        msg.is_rx = False
        echoes = self.echoes
        try:
            with self._lock:
                if echoes is not None:  # before sending: the echo may beat the return
                    echoes.add(msg, time.monotonic())
                self.bus.send(msg, timeout=timeout_s)
        except (can.CanError, OSError, ValueError) as exc:
            if echoes is not None:
                echoes.discard(msg)
            raise BusSendError(
                f"bus {self.name}: send of 0x{msg.arbitration_id:03X} failed ({exc})"
            ) from None
        self.n_sent += 1
        if self.log is not None:
            self.log.log_sent(msg)

    def send_batch(
        self, frames: np.ndarray, timeout_s: float = 0.05, keep_going: bool = False
    ) -> None:
        """Send a batch of frames (a :data:`drivers.protocol.batch.FRAME_DTYPE` array, its
        timestamps set here) in order: as one record array on a bus that takes batches
        (``hrm_ipc``: one datagram per peer, no Python object per frame), else as
        ``can.Message`` objects through :meth:`send_many`.  Logged as sent.
        ``keep_going``: see :meth:`send_many`."""
        if self._send_records is None:
            self.send_many(to_messages(frames, is_rx=False), timeout_s, keep_going)
            return
        try:  # the bus stamps the frames with the send time (what the log gets too)
            with self._lock:
                self._send_records(frames, timeout=timeout_s)
                self.n_sent += len(frames)
                if self.log is not None:
                    self.log.log_batch(frames, is_rx=False)
        except (can.CanError, OSError, ValueError) as exc:
            raise BusSendError(f"bus {self.name}: send failed ({exc})") from None

    def send_many(
        self, msgs: list[can.Message], timeout_s: float = 0.05, keep_going: bool = False
    ) -> None:
        """Send frames in order under one lock acquisition; through the bus's own
        ``send_many`` when it has one (``hrm_ipc``: one datagram per peer), else frame
        by frame.  ``keep_going`` (a quick stop's burst): frame by frame, a frame that
        fails does not hold back the ones after it, and ``timeout_s`` bounds the whole
        batch (not each frame); the failures are raised together after the last frame."""
        now = time.time()
        echoes = self.echoes
        mono = time.monotonic()
        batch = self._send_batch
        if batch is not None:
            log_ = self.log
            try:
                with self._lock:
                    for msg in msgs:
                        msg.timestamp = now
                        msg.is_rx = False
                        if echoes is not None:
                            echoes.add(msg, mono)
                    try:
                        batch(msgs, timeout=timeout_s)
                    except BaseException:
                        if echoes is not None:
                            for msg in msgs:
                                echoes.discard(msg)
                        raise
                    self.n_sent += len(msgs)
                    if log_ is not None:
                        for msg in msgs:
                            log_.log_sent(msg)
            except (can.CanError, OSError, ValueError) as exc:
                raise BusSendError(f"bus {self.name}: send failed ({exc})") from None
            return
        self._send_each(msgs, timeout_s, keep_going)

    def _send_each(self, msgs: list[can.Message], timeout_s: float, keep_going: bool) -> None:
        """Frame by frame (see :meth:`send_many`): each frame waits up to ``timeout_s``
        and the first failure ends the batch; with ``keep_going`` every frame is tried,
        all within ``timeout_s``, and the failures are raised together at the end."""
        now = time.time()
        echoes = self.echoes
        mono = time.monotonic()
        deadline = mono + timeout_s
        failed: list[str] = []
        with self._lock:
            for msg in msgs:
                msg.timestamp = now
                msg.is_rx = False
                if echoes is not None:
                    echoes.add(msg, mono)
                wait_s = max(0.0, deadline - time.monotonic()) if keep_going else timeout_s
                try:
                    self.bus.send(msg, timeout=wait_s)
                except BaseException as exc:
                    if echoes is not None:
                        echoes.discard(msg)
                    if not isinstance(exc, can.CanError | OSError | ValueError):
                        raise
                    if not keep_going:
                        raise BusSendError(f"bus {self.name}: send failed ({exc})") from None
                    failed.append(f"0x{msg.arbitration_id:03X} ({exc})")
                    continue
                self.n_sent += 1
                if self.log is not None:
                    self.log.log_sent(msg)
        if failed:
            more = f" (+{len(failed) - 1} more)" if len(failed) > 1 else ""
            raise BusSendError(f"bus {self.name}: send of {failed[0]} failed{more}")
