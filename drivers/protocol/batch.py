"""A batch of classic CAN frames as one NumPy record array: the control cycle's frames
without a Python object per frame.

One record is 21 bytes, packed, little-endian: ``timestamp`` (float64, s, ``time.time()``
of the sender), ``id`` (uint32: the identifier, with SocketCAN's flag bits 31 extended,
30 remote, 29 error), ``dlc`` (uint8) and ``data`` (8 bytes, zero-padded).  It is the
record of the ``hrm_ipc`` datagram (``sim_bus/ipc.py``), so a received datagram's body is
a batch without a copy, and a batch's bytes are a datagram's body; a bus that can send or
receive batches (``send_batch`` / ``recv_batch``) carries a cycle's frames that way, any
other bus gets ``can.Message`` objects (:func:`to_messages`, :func:`from_messages`).

Views of the same bytes name a frame's CANopen fields without copying:
:data:`TPDO_VIEW` (statusword and position actual of the feedback TPDO) and
:data:`RPDO_VIEW` (controlword and target of the setpoint RPDO).

>>> b = rpdo_batch(np.array([0x205, 0x206]), 0x000F, np.array([7, -1]), 1.5)
>>> bytes(b[0]["data"]).hex(), int(b.view(RPDO_VIEW)[1]["target"]), b.itemsize
('0f00070000000000', -1, 21)
>>> [(hex(m.arbitration_id), m.data.hex(), m.dlc) for m in to_messages(b)]
[('0x205', '0f0007000000', 6), ('0x206', '0f00ffffffff', 6)]
>>> back = from_messages(to_messages(b))
>>> bool((back == b).all())
True
"""

from __future__ import annotations

from collections.abc import Sequence

import can
import numpy as np

from drivers.protocol.cia402 import RPDO_TARGET, TPDO_FEEDBACK

#: One frame (packed, 21 bytes): the ``hrm_ipc`` record ``<dIB8s``.
FRAME_DTYPE = np.dtype([("timestamp", "<f8"), ("id", "<u4"), ("dlc", "u1"), ("data", "u1", (8,))])
FLAG_EXTENDED = 0x80000000
FLAG_REMOTE = 0x40000000
FLAG_ERROR = 0x20000000
FLAGS = FLAG_EXTENDED | FLAG_REMOTE | FLAG_ERROR
ID_MASK = 0x1FFFFFFF
STD_ID_MAX = 0x7FF

#: The feedback TPDO1's fields in a frame record (statusword UNSIGNED16, position INTEGER32).
TPDO_VIEW = TPDO_FEEDBACK.view_in(FRAME_DTYPE)
#: The setpoint RPDO1's fields in a frame record (controlword UNSIGNED16, target INTEGER32).
RPDO_VIEW = RPDO_TARGET.view_in(FRAME_DTYPE)
RPDO_DLC = RPDO_TARGET.size


def rpdo_batch(
    cob_ids: np.ndarray, controlword: int, targets: np.ndarray, timestamp: float = 0.0
) -> np.ndarray:
    """RPDO1 frames (controlword, target) for ``cob_ids`` as a batch (a target outside
    INTEGER32 raises :class:`~drivers.protocol.cia301.FrameError`)."""
    out = np.zeros(len(cob_ids), dtype=FRAME_DTYPE)
    v = out.view(RPDO_VIEW)
    v["timestamp"] = timestamp
    v["id"] = cob_ids
    v["dlc"] = RPDO_DLC
    RPDO_TARGET.fill(v, controlword=controlword, target=targets)
    return out


def to_messages(batch: np.ndarray, channel: object = None, is_rx: bool = True) -> list[can.Message]:
    """The frames of a batch as ``can.Message`` objects (for a bus without batches, the
    slow path of the receiver and the log formats written frame by frame)."""
    out = []
    for ts, ident, dlc, data in batch.tolist():
        ident = int(ident)
        out.append(
            can.Message(
                timestamp=ts,
                arbitration_id=ident & ID_MASK,
                is_extended_id=bool(ident & FLAG_EXTENDED),
                is_remote_frame=bool(ident & FLAG_REMOTE),
                is_error_frame=bool(ident & FLAG_ERROR),
                dlc=dlc,
                data=bytes(data[: min(dlc, 8)]),
                channel=channel,
                is_rx=is_rx,
                check=False,
            )
        )
    return out


def from_messages(msgs: Sequence[can.Message]) -> np.ndarray:
    """A batch of ``can.Message`` objects (classic frames; data beyond 8 bytes is cut)."""
    out = np.zeros(len(msgs), dtype=FRAME_DTYPE)
    for k, m in enumerate(msgs):
        ident = m.arbitration_id & ID_MASK
        if m.is_extended_id:
            ident |= FLAG_EXTENDED
        if m.is_remote_frame:
            ident |= FLAG_REMOTE
        if m.is_error_frame:
            ident |= FLAG_ERROR
        data = bytes(m.data)[:8]
        out[k] = (m.timestamp, ident, m.dlc, np.frombuffer(data.ljust(8, b"\0"), np.uint8))
    return out
