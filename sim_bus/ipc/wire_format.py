"""The ``hrm_ipc`` datagram: a header and a batch of 21-byte frame records.

Header ``<2sBBHIQ``: magic ``b"HC"``, version 1, kind 1 (frames), frame count,
per-connection sequence number, sender id.  Per frame a record ``<dIB8s``: timestamp (the
sender's ``time.time()``), id with the SocketCAN flag bits 31 extended / 30 remote / 29
error, dlc, data padded to 8 bytes: the record of
:data:`drivers.protocol.batch.FRAME_DTYPE`, so a datagram's body is a batch without a
copy.  A datagram carries 1 to :data:`MAX_FRAMES_PER_DATAGRAM` frames; a malformed one (a
header alone, a record with dlc > 8, an 11-bit id over 0x7FF, a timestamp outside
[0, :data:`MAX_TIMESTAMP_S`)) is refused whole (:func:`datagram_header`).

>>> body = encode_frame(can.Message(arbitration_id=0x181, data=b"\\x07", is_extended_id=False), 2.0)
>>> data = pack_header(1, seq=5, sender=9) + body
>>> datagram_header(data), decode_frame(data[HEADER.size :])
((1, 5, 9), (2.0, 385, False, False, False, 1, b'\\x07'))
"""

from __future__ import annotations

import enum
import struct

import can
import numpy as np

from drivers.protocol.batch import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE, FRAME_DTYPE, ID_MASK

#: Datagram header: magic, version, kind, frame count, sequence number, sender id.
HEADER = struct.Struct("<2sBBHIQ")
#: One frame: timestamp (s, sender's time.time()), id | flags, dlc, data padded to 8 (the
#: record of drivers.protocol.batch.FRAME_DTYPE).
RECORD = struct.Struct("<dIB8s")
MAGIC = b"HC"
VERSION = 1


class DatagramKind(enum.IntEnum):
    """What a datagram carries (the header's kind byte; only frames so far)."""

    FRAMES = 1


KIND_FRAMES = DatagramKind.FRAMES
#: Datagrams of up to this many frames are checked frame by frame, longer ones with NumPy.
SMALL_DATAGRAM_FRAMES = 4
#: Frames in one datagram (a longer send_many is split into datagrams of this many).
MAX_FRAMES_PER_DATAGRAM = 256
MAX_DATAGRAM_BYTES = HEADER.size + MAX_FRAMES_PER_DATAGRAM * RECORD.size
#: A frame's timestamp (the sender's ``time.time()``) must lie in [0, this): a NaN, an
#: infinity or a date past 2106 is a malformed datagram (a BLF log cannot hold it).
MAX_TIMESTAMP_S = 2.0**32

Frame = tuple[float, int, bool, bool, bool, int, bytes]
"""A decoded record: timestamp, id, extended, remote, error, dlc, data."""


def encode_frame(msg: can.Message, timestamp: float) -> bytes:
    """The 21-byte record of ``msg`` (raises ``can.CanOperationError`` for a frame classical
    CAN cannot carry).

    >>> msg = can.Message(arbitration_id=0x7FF, data=b"\\x01", is_extended_id=False)
    >>> r = encode_frame(msg, 1.5)
    >>> len(r), decode_frame(r)
    (21, (1.5, 2047, False, False, False, 1, b'\\x01'))
    """
    if msg.is_fd:
        raise can.CanOperationError("hrm_ipc: CAN FD frames are not supported")
    ident = int(msg.arbitration_id)
    data = bytes(msg.data) if msg.data is not None else b""
    dlc = int(msg.dlc)
    if len(data) > 8 or not 0 <= dlc <= 8:
        raise can.CanOperationError(
            f"hrm_ipc: frame 0x{ident:X} has {len(data)} data bytes, dlc {dlc} (at most 8)"
        )
    raw = ident
    if msg.is_extended_id:
        if not 0 <= ident <= ID_MASK:
            raise can.CanOperationError(f"hrm_ipc: extended id 0x{ident:X} out of range")
        raw |= FLAG_EXTENDED
    elif not 0 <= ident <= 0x7FF:
        raise can.CanOperationError(f"hrm_ipc: standard id 0x{ident:X} out of range")
    if msg.is_remote_frame:
        raw |= FLAG_REMOTE
    if msg.is_error_frame:
        raw |= FLAG_ERROR
    return RECORD.pack(timestamp, raw, dlc, data)


def decode_frame(record: bytes) -> Frame | None:
    """(timestamp, id, extended, remote, error, dlc, data) of a record, None if invalid.

    >>> decode_frame(RECORD.pack(0.0, 0x800, 0, bytes(8))) is None   # 11-bit id too big
    True
    """
    ts, raw, dlc, data = RECORD.unpack(record)
    return check_record(ts, raw, dlc, data)


def check_record(ts: float, raw: int, dlc: int, data: bytes) -> Frame | None:
    """:func:`decode_frame` of a record's unpacked fields.

    >>> check_record(1.0, FLAG_REMOTE | 0x701, 1, bytes(8))
    (1.0, 1793, False, True, False, 1, b'')
    """
    ident = raw & ID_MASK
    ext = bool(raw & FLAG_EXTENDED)
    if dlc > 8 or (not ext and ident > 0x7FF) or not 0.0 <= ts < MAX_TIMESTAMP_S:  # NaN too
        return None
    rtr = bool(raw & FLAG_REMOTE)
    return ts, ident, ext, rtr, bool(raw & FLAG_ERROR), dlc, b"" if rtr else data[:dlc]


def records_valid(records: np.ndarray, stamped: bool = False) -> bool:
    """Whether every record of a FRAME_DTYPE array is a classical CAN frame (dlc <= 8, an
    11-bit id unless extended, a timestamp in [0, :data:`MAX_TIMESTAMP_S`), unless
    ``stamped`` here): :func:`check_record` for all of them (one by one for a few, with
    NumPy for more).

    >>> ok = np.zeros(5, FRAME_DTYPE); ok["id"] = [0x7FF, 0x181, FLAG_EXTENDED | ID_MASK, 0, 1]
    >>> bad = ok.copy(); bad["id"][1] = 0x800
    >>> records_valid(ok), records_valid(bad), records_valid(bad[2:])
    (True, False, True)
    """
    if len(records) <= SMALL_DATAGRAM_FRAMES:
        return all(
            dlc <= 8
            and (raw & FLAG_EXTENDED or raw & ID_MASK <= 0x7FF)
            and 0.0 <= ts < MAX_TIMESTAMP_S
            for ts, raw, dlc, _data in records.tolist()
        )
    # an 11-bit frame has none of the id bits 11..28; x = id & (extended | those bits) is
    # 0 for a good 11-bit frame and >= 2**31 for an extended one: bad iff 0 < x < 2**31
    x = records["id"] & _STD_CHECK_MASK
    x -= 1  # wraps 0 to 2**32 - 1
    if int(x.min()) < FLAG_EXTENDED - 1 or int(records["dlc"].max()) > 8:
        return False
    if stamped:
        return True
    ts = records["timestamp"]  # NaN fails both comparisons
    return bool(float(ts.min()) >= 0.0 and float(ts.max()) < MAX_TIMESTAMP_S)


_STD_CHECK_MASK = np.uint32(FLAG_EXTENDED | (ID_MASK & ~0x7FF))


def pack_header(count: int, seq: int, sender: int) -> bytes:
    """The header of a datagram of ``count`` frames."""
    return HEADER.pack(MAGIC, VERSION, KIND_FRAMES, count, seq, sender)


def datagram_header(data: bytes) -> tuple[int, int, int] | None:
    """(frame count, sequence number, sender id) of a well-formed datagram, None for a
    malformed one: too short or long, another magic, version or kind, no frames, a size
    that is not its count's, or a record classical CAN cannot carry.

    >>> datagram_header(pack_header(0, 1, 2)) is None    # a header alone
    True
    """
    size = len(data)
    if size < HEADER.size or size > MAX_DATAGRAM_BYTES:
        return None
    magic, version, kind, count, seq, sender = HEADER.unpack_from(data)
    if (
        magic != MAGIC
        or version != VERSION
        or kind != KIND_FRAMES
        or count == 0  # a header alone carries nothing (and would stick in the queue)
        or size != HEADER.size + count * RECORD.size
    ):
        return None
    if not records_valid(np.frombuffer(data, FRAME_DTYPE, count, HEADER.size)):
        return None
    return count, seq, sender
