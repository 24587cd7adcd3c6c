"""Bit lengths of classical CAN frames (ISO 11898-1): worst-case and exact bit stuffing.

The one definition used by the bus-load budget (:mod:`drivers.busload`) and by
the simulated wire (:mod:`sim_bus.wire`).  A frame is counted from start of
frame to the end of the interframe space: the stuffable part (SOF, arbitration
and control fields, data, CRC) plus :data:`TRAILER_BITS` that are never
stuffed.  With ``n`` stuffable bits (34 + 8 bytes with an 11-bit id, 54 + 8
bytes with a 29-bit id) a transmitter inserts at most ``floor((n - 1) / 4)``
stuff bits (Davis et al. 2007): 135 bits for 8 data bytes, 55 for a SYNC.

>>> worst_case_frame_bits(8), worst_case_frame_bits(0), worst_case_frame_bits(8, extended_id=True)
(135, 55, 160)
>>> m = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
>>> frame_bits(m), frame_bits(m, Stuffing.EXACT) <= 135
(135, True)
"""

from __future__ import annotations

from enum import StrEnum

import can

from drivers.protocol.cia301 import FrameError

#: Bits after the CRC that are never stuffed: CRC delimiter, ACK slot + delimiter, EOF, IFS.
TRAILER_BITS = 1 + 2 + 7 + 3
#: CAN's CRC-15 generator polynomial x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1.
CRC15_POLY = 0x4599
MAX_DATA_BYTES = 8


class Stuffing(StrEnum):
    """How stuff bits are counted: the worst case a frame of that length can need, or the
    stuff bits of the frame's real bit pattern (CRC included)."""

    WORST = "worst"
    EXACT = "exact"


def stuffable_bit_count(n_data_bytes: int, extended_id: bool = False) -> int:
    """Bits SOF .. CRC (the part subject to stuffing) of a data frame.

    >>> stuffable_bit_count(0), stuffable_bit_count(8), stuffable_bit_count(8, extended_id=True)
    (34, 98, 118)
    """
    if isinstance(n_data_bytes, bool) or not 0 <= n_data_bytes <= MAX_DATA_BYTES:
        raise FrameError(f"classical CAN carries 0..8 data bytes, got {n_data_bytes}")
    return (54 if extended_id else 34) + 8 * n_data_bytes


def worst_case_frame_bits(n_data_bytes: int, extended_id: bool = False) -> int:
    """Longest wire time (bits) of a classical CAN data frame, worst-case stuffing,
    interframe space included.

    >>> [worst_case_frame_bits(n) for n in (1, 6)]
    [65, 115]
    """
    n = stuffable_bit_count(n_data_bytes, extended_id)
    return n + (n - 1) // 4 + TRAILER_BITS


def stuffable_bits(msg: can.Message) -> list[int]:
    """The bit pattern SOF .. CRC of a data or remote frame (dominant = 0).

    >>> bits = stuffable_bits(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
    >>> len(bits), bits[:12]  # SOF, then the 11-bit id 0x080
    (34, [0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0])
    """
    bits: list[int] = [0]  # SOF
    dlc = msg.dlc if msg.is_remote_frame else len(msg.data)
    if dlc > MAX_DATA_BYTES:
        raise FrameError(f"classical CAN carries 0..8 data bytes, got {dlc}")

    def put(value: int, n: int) -> None:
        bits.extend((value >> (n - 1 - i)) & 1 for i in range(n))

    rtr = 1 if msg.is_remote_frame else 0
    if msg.is_extended_id:
        put(msg.arbitration_id >> 18, 11)
        put(1, 1)  # SRR
        put(1, 1)  # IDE
        put(msg.arbitration_id & 0x3FFFF, 18)
        put(rtr, 1)
        put(0, 2)  # r1, r0
    else:
        put(msg.arbitration_id, 11)
        put(rtr, 1)
        put(0, 1)  # IDE
        put(0, 1)  # r0
    put(dlc, 4)
    if not msg.is_remote_frame:
        for byte in bytes(msg.data):
            put(byte, 8)
    put(crc15(bits), 15)
    return bits


def crc15(bits: list[int]) -> int:
    """CAN's CRC-15 of a bit sequence (CRC-15/CAN: no reflection, init and xor-out 0).

    >>> hex(crc15([(byte >> (7 - i)) & 1 for byte in b"123456789" for i in range(8)]))
    '0x59e'
    """
    crc = 0
    for b in bits:
        nxt = b ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= CRC15_POLY
    return crc


def stuff_bit_count(bits: list[int]) -> int:
    """Number of stuff bits a CAN transmitter inserts into ``bits`` (after 5 equal bits).

    >>> stuff_bit_count([0] * 5), stuff_bit_count([0] * 10), stuff_bit_count([0, 1] * 8)
    (1, 2, 0)
    """
    count = 0
    run = 0
    last = -1
    for b in bits:
        if b == last:
            run += 1
        else:
            last, run = b, 1
        if run == 5:
            count += 1
            last, run = 1 - b, 1  # the stuff bit itself starts a new run
    return count


def frame_bits(msg: can.Message, stuffing: Stuffing | str = Stuffing.WORST) -> int:
    """Bits a classical CAN data/remote frame occupies on the wire, interframe space included.

    ``worst``: :func:`worst_case_frame_bits` of its length (a remote frame carries no data).
    ``exact``: the stuff bits of the real pattern (:func:`stuffable_bits`).

    >>> m = can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False)
    >>> frame_bits(m), frame_bits(m, "exact") <= 135
    (135, True)
    """
    if stuffing == Stuffing.WORST:
        n_data = 0 if msg.is_remote_frame else len(msg.data)
        return worst_case_frame_bits(n_data, msg.is_extended_id)
    if stuffing != Stuffing.EXACT:
        raise FrameError(f"stuffing must be 'worst' or 'exact', got {stuffing!r}")
    bits = stuffable_bits(msg)
    return len(bits) + stuff_bit_count(bits) + TRAILER_BITS
