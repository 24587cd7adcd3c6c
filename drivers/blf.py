"""Vector's Binary Logging Format (BLF), written by our own small formatter.

The CAN log (:class:`drivers.canlog.TrafficLog`) needs more of a BLF writer than
python-can's ``BLFWriter`` offers in public: a file whose header is rewritten in place
after every flush (a killed process leaves a readable file that carries its start time),
containers cut and padded so that a ``write(2)`` cut between pages still leaves whole
container headers, a batch of frames packed with NumPy, and no frame that could make the
header unwritable.  It once got all that by driving python-can's writer's private state
(``_buffer``, ``_flush``, ``_write_header``), which any python-can release may change.
The format itself is small and stable, so this module writes it: a file header, then
``LOG_CONTAINER`` objects whose zlib streams hold ``CAN_MESSAGE``, ``CAN_FD_MESSAGE_64``
and ``CAN_ERROR_EXT`` objects, each object with a version-1 header (time in ns after the
file's start).  The layouts are those python-can's ``BLFReader`` reads (and Vector's
tools write: the reader is the reference, ``can.LogReader`` reads every file this module
writes, as the tests check frame for frame).  A classic frame is a ``CAN_MESSAGE``, the
same 48 bytes python-can writes (``CAN_MESSAGE2`` would add a frame length and bit count
the host does not know); an FD frame is a ``CAN_FD_MESSAGE_64`` (what current Vector
tools write, its data as long as the frame's); an error frame a ``CAN_ERROR_EXT``.

:class:`BlfFormatter` only formats (no file I/O): the caller writes the bytes it hands out.

>>> import can, io, pathlib, tempfile
>>> f = BlfFormatter(start_s=1_700_000_000.0)
>>> f.add(can.Message(timestamp=1_700_000_000.5, arbitration_id=0x181, data=b"\\x01\\x02"))
>>> body = f.take_containers(at=FILE_HEADER_BYTES)
>>> path = pathlib.Path(tempfile.mkdtemp()) / "doc.blf"
>>> _ = path.write_bytes(f.header(FILE_HEADER_BYTES + len(body)) + body)
>>> [(hex(m.arbitration_id), m.data.hex(), m.timestamp) for m in can.BLFReader(path)]
[('0x181', '0102', 1700000000.5)]
"""

from __future__ import annotations

import datetime as dt
import re
import struct
import zlib

import can
import numpy as np

from drivers.protocol.batch import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE, FRAME_DTYPE, ID_MASK

# ---------------------------------------------------------------- the format's records
#: signature "LOGG", header size, application id, its version (major, minor, build), the
#: format's version (major, minor, build, patch), file size, uncompressed size, objects,
#: objects read, start and stop time (Windows SYSTEMTIME)
FILE_HEADER = struct.Struct("<4sLBBBBBBBBQQLL8H8H")
FILE_HEADER_BYTES = 144  # the header padded to this size
#: signature "LOBJ", header size, header version, object size, object type
OBJECT_BASE = struct.Struct("<4sHHLL")
#: time flags, client index, object version, time since the file's start
OBJECT_HEADER_V1 = struct.Struct("<LHHQ")
#: compression method, uncompressed size
CONTAINER = struct.Struct("<H6xL4x")
#: channel, flags, dlc, identifier, data
CAN_MESSAGE_BODY = struct.Struct("<HBBL8s")
#: channel, dlc, data bytes, tx count, identifier, frame length, flags, arbitration and
#: data bit rate, BRS and CRC delimiter offsets, bit count, direction, extended data
#: offset, CRC; then the data
CAN_FD_MESSAGE_64_BODY = struct.Struct("<BBBBLLLLLLLHBBL")
#: channel, length, flags, ECC, position, dlc, frame length, identifier, extended flags,
#: data
CAN_ERROR_EXT_BODY = struct.Struct("<HHLBBBxLLH2x8s")

CAN_MESSAGE = 1
LOG_CONTAINER = 10
CAN_ERROR_EXT = 73
CAN_FD_MESSAGE_64 = 101
ZLIB_DEFLATE = 2
TIME_ONE_NANS = 2  # object times in ns
CAN_MSG_EXT = 0x80000000  # an identifier's 29-bit flag
REMOTE_FLAG = 0x80
DIR_TX = 0x1  # CAN_MESSAGE flags: sent by this node
FD_EDL, FD_BRS, FD_ESI = 0x1000, 0x2000, 0x4000  # CAN_FD_MESSAGE_64 flags
#: the application id and versions the header names (python-can's writer's: a reader
#: that knows python-can's files knows these)
APPLICATION = (5, 0, 0, 0, 2, 6, 8, 1)
#: A frame whose timestamp lies outside [0, this) s is refused (ValueError): BLF keeps the
#: file's stop time as a calendar date, which it must be able to write.
MAX_TIMESTAMP_S = 2.0**32
CONTAINER_BYTES = 128 * 1024  # uncompressed bytes per container, as Vector's tools cut them
#: Unix times before this are written as a zero date (not a time of day: a relative clock)
MIN_DATE_S = 631152000.0

OBJECT_HEADER_BYTES = OBJECT_BASE.size + OBJECT_HEADER_V1.size  # 32
CAN_OBJECT = struct.Struct("<" + "".join(s.format.lstrip("<") for s in (
    OBJECT_BASE, OBJECT_HEADER_V1, CAN_MESSAGE_BODY)))  # fmt: skip
CAN_OBJECT_BYTES = CAN_OBJECT.size  # 48: a multiple of 4, no padding
CONTAINER_HEADER_BYTES = OBJECT_BASE.size + CONTAINER.size  # 32

_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_DIGITS = re.compile(r"(\d+)$")


def fd_dlc(length: int) -> int:
    """The DLC code of a CAN FD frame of ``length`` data bytes (the smallest that holds it).

    >>> [fd_dlc(n) for n in (0, 8, 9, 12, 13, 64)]
    [0, 8, 9, 9, 10, 15]
    """
    for code, n in enumerate(_FD_LENGTHS):
        if length <= n:
            return code
    return 15


def channel_number(channel: object, default: int) -> int:
    """The channel an object carries: python-can's 0-based number plus one (as its writer
    and readers number them), the trailing digits of a name (``"can1"`` -> 2), else
    ``default``.

    >>> channel_number(0, 7), channel_number("can1", 7), channel_number("virtual", 7)
    (1, 2, 7)
    """
    if type(channel) is int:
        return channel + 1
    if isinstance(channel, str):
        m = _DIGITS.search(channel)
        if m:
            return int(m.group(1)) + 1
    return default


def system_time(t_s: float) -> tuple[int, ...]:
    """A Unix time as the header's SYSTEMTIME (UTC, ms): year, month, weekday, day, hour,
    minute, second, ms; zeros for a time before 1990 (a relative clock, not a date).

    >>> system_time(1_700_000_000.25)
    (2023, 11, 2, 14, 22, 13, 20, 250)
    >>> system_time(12.0)
    (0, 0, 0, 0, 0, 0, 0, 0)
    """
    if t_s < MIN_DATE_S:
        return (0,) * 8
    t = dt.datetime.fromtimestamp(round(t_s, 3), tz=dt.UTC)
    return (t.year, t.month, t.isoweekday() % 7, t.day, t.hour, t.minute, t.second,
            t.microsecond // 1000)  # fmt: skip


class BlfFormatter:
    """The objects of one BLF file, formatted as frames come, handed out as containers.

    ``start_s``: the file's start (Unix time; kept to the ms, as the header holds it);
    object times are ns after it (a frame before it is written at 0).  ``channel``: the
    number of a frame without one.  ``container_bytes``: uncompressed bytes per container
    (an object may continue in the next one, as readers expect)."""

    def __init__(
        self,
        start_s: float,
        channel: int = 1,
        compression_level: int = 1,
        container_bytes: int = CONTAINER_BYTES,
    ) -> None:
        self.start_s = int(start_s * 1000) / 1000
        self.stop_s = self.start_s  # the last frame's time (the header's stop)
        self.channel = int(channel)
        self.compression_level = int(compression_level)
        self.container_bytes = int(container_bytes)
        self.object_count = 0
        self.uncompressed_size = FILE_HEADER_BYTES  # the header and every container, unpacked
        self.pending_bytes = 0
        self._pending: list[bytes] = []

    # ---------------------------------------------------------------- frames
    def add(self, msg: can.Message) -> None:
        """Format one frame; a ``ValueError`` (nothing added) for a time outside
        [0, 2**32) s or NaN, a ``struct.error`` for a field its object cannot hold."""
        ts = msg.timestamp
        if not 0.0 <= ts < MAX_TIMESTAMP_S:  # NaN too
            raise ValueError(f"timestamp {ts!r} outside 0..2**32 s")
        ch = channel_number(msg.channel, self.channel)
        arb = msg.arbitration_id | (CAN_MSG_EXT if msg.is_extended_id else 0)
        t_ns = int((ts - self.start_s) * 1e9)
        t_ns = t_ns if t_ns > 0 else 0
        if msg.is_error_frame:
            body = CAN_ERROR_EXT_BODY.pack(ch, 0, 0, 0, 0, fd_dlc(msg.dlc), 0, arb, 0,
                                           bytes(msg.data))  # fmt: skip
            obj = self._object(CAN_ERROR_EXT, t_ns, body)
        elif msg.is_fd:
            data = bytes(msg.data)
            flags = (
                FD_EDL
                | (FD_BRS if msg.bitrate_switch else 0)
                | (FD_ESI if msg.error_state_indicator else 0)
            )
            body = CAN_FD_MESSAGE_64_BODY.pack(
                ch, fd_dlc(len(data)), len(data), 0, arb, 0, flags,
                0, 0, 0, 0, 0, 0 if msg.is_rx else 1, 0, 0,
            )  # fmt: skip
            obj = self._object(CAN_FD_MESSAGE_64, t_ns, body + data)
        else:
            flags = (REMOTE_FLAG if msg.is_remote_frame else 0) | (0 if msg.is_rx else DIR_TX)
            obj = CAN_OBJECT.pack(
                b"LOBJ", OBJECT_HEADER_BYTES, 1, CAN_OBJECT_BYTES, CAN_MESSAGE,
                TIME_ONE_NANS, 0, 0, t_ns, ch, flags, msg.dlc, arb, bytes(msg.data),
            )  # fmt: skip
        self._pending.append(obj)
        self.pending_bytes += len(obj)
        self.object_count += 1
        self.stop_s = ts

    @staticmethod
    def _object(kind: int, t_ns: int, body: bytes) -> bytes:
        size = OBJECT_HEADER_BYTES + len(body)
        return (
            OBJECT_BASE.pack(b"LOBJ", OBJECT_HEADER_BYTES, 1, size, kind)
            + OBJECT_HEADER_V1.pack(TIME_ONE_NANS, 0, 0, t_ns)
            + body
            + bytes(size % 4)  # an object is padded by its size mod 4
        )

    def add_batch(self, frames: np.ndarray, is_rx: bool | np.ndarray) -> bool:
        """:meth:`add` for a whole batch (a :data:`drivers.protocol.batch.FRAME_DTYPE`
        array): its ``CAN_MESSAGE`` objects packed at once with NumPy, the same bytes;
        ``False``, nothing added, when it must go frame by frame (an error frame in it, a
        time outside [0, 2**32) s).  ``is_rx``: one direction for all, or one per frame."""
        ident = frames["id"]
        flags = int(np.bitwise_or.reduce(ident))  # the flag bits any frame has
        if flags & FLAG_ERROR:
            return False
        ts = frames["timestamp"]
        if not (float(ts.min()) >= 0.0 and float(ts.max()) < MAX_TIMESTAMP_S):  # NaN too
            return False
        t_ns = (ts - self.start_s) * 1e9
        out = np.frombuffer(bytearray(_OBJECT_TEMPLATE * len(frames)), _OBJECT_RECORD)
        out["timestamp"] = np.maximum(t_ns, 0.0, out=t_ns)  # then truncated, as int() does
        out["channel"] = self.channel
        out["dlc"] = frames["dlc"]
        out["id"] = ident & _ID_AND_EXT  # the extended bit is BLF's CAN_MSG_EXT
        words = frames.view(_FRAME_WORDS)
        data = words["data"] & _DLC_DATA_MASK.take(words["dlc"])
        if isinstance(is_rx, np.ndarray):
            direction: np.ndarray | int = np.where(is_rx, 0, DIR_TX).astype(np.uint16)
        else:
            direction = 0 if is_rx else DIR_TX
        if flags & FLAG_REMOTE:
            remote = (ident & FLAG_REMOTE) != 0
            out["flags"] = np.where(remote, REMOTE_FLAG | direction, direction)
            data[remote] = 0  # a can.Message remote frame has no data
        else:
            out["flags"] = direction
        out["data"] = data
        self._pending.append(out.tobytes())
        self.pending_bytes += out.nbytes
        self.object_count += len(out)
        self.stop_s = float(ts[-1])
        return True

    # ---------------------------------------------------------------- the file
    def pending(self) -> bytes:
        """The objects formatted since the last :meth:`take_containers` (uncompressed)."""
        return b"".join(self._pending)

    def discard(self) -> None:
        """Forget the pending objects (the file takes no more)."""
        self._pending, self.pending_bytes = [], 0

    def take_containers(self, at: int, page_bytes: int = 4096) -> bytes:
        """The pending objects as zlib ``LOG_CONTAINER`` objects, to be written at file
        offset ``at``.  A container is padded after its zlib stream (readers stop at the
        stream's end) so that the next one's 32 header bytes lie within one page of
        ``page_bytes``: a write cut between pages leaves whole container headers."""
        raw = self.pending()
        self.discard()
        out = bytearray()
        step = self.container_bytes
        for i in range(0, len(raw), step):
            chunk = raw[i : i + step]
            body = zlib.compress(chunk, self.compression_level)
            pad = 0
            while True:  # an object of size s is followed by s % 4 bytes
                size = CONTAINER_HEADER_BYTES + len(body) + pad
                end = at + len(out) + size + size % 4
                if end % page_bytes <= page_bytes - CONTAINER_HEADER_BYTES:
                    break
                pad += 1
            out += OBJECT_BASE.pack(b"LOBJ", OBJECT_BASE.size, 1, size, LOG_CONTAINER)
            out += CONTAINER.pack(ZLIB_DEFLATE, len(chunk))
            out += body + bytes(pad + size % 4)
            self.uncompressed_size += CONTAINER_HEADER_BYTES + len(chunk)
        return bytes(out)

    def header(self, file_size: int) -> bytes:
        """The file header (:data:`FILE_HEADER_BYTES`) for a file of ``file_size`` bytes
        holding the objects taken so far: sizes, object count, start and stop time."""
        return FILE_HEADER.pack(
            b"LOGG", FILE_HEADER_BYTES, *APPLICATION, file_size, self.uncompressed_size,
            self.object_count, 0, *system_time(self.start_s), *system_time(self.stop_s),
        ).ljust(FILE_HEADER_BYTES, b"\0")  # fmt: skip


# One CAN_MESSAGE object as a NumPy record, to pack a batch at once; its 8 data bytes as
# one little-endian word.
_OBJECT_RECORD = np.dtype(
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
assert _OBJECT_RECORD.itemsize == CAN_OBJECT_BYTES
# What every object of a batch shares: the headers; time, channel and frame are set per batch.
_OBJECT_TEMPLATE = CAN_OBJECT.pack(
    b"LOBJ", OBJECT_HEADER_BYTES, 1, CAN_OBJECT_BYTES, CAN_MESSAGE, TIME_ONE_NANS,
    0, 0, 0, 0, 0, 0, 0, b"",
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
assert FLAG_EXTENDED == CAN_MSG_EXT
_ID_AND_EXT = np.uint32(ID_MASK | FLAG_EXTENDED)
# Data bytes a frame carries by its DLC (min(dlc, 8), as to_messages cuts them)
_DLC_DATA_MASK = np.array([(1 << 8 * min(d, 8)) - 1 for d in range(256)], dtype=np.uint64)
