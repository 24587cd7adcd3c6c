"""SocketCAN error frames (``linux/can/error.h``): what a CAN controller reports, and
which of it stops the box.

A SocketCAN adapter (and the kernel's CAN drivers behind it) reports bus trouble as an
*error frame*: ``can.Message.is_error_frame``, its identifier the ``CAN_ERR_*`` classes
(bit mask), its 8 data bytes the details of each class.  :func:`error_frame_verdict`
decodes one into a one-line description and whether it is a stop cause:

* **stop**: ``CAN_ERR_BUSOFF`` (the controller left the bus: nothing this host sends
  reaches the drives) and ``CAN_ERR_CRTL`` with the error-passive bits of ``data[1]``
  (``CAN_ERR_CRTL_RX_PASSIVE``/``TX_PASSIVE``: error counters past 127, the bus is
  failing; an error-passive node's frames can be held back behind error frames);
* **log only**: everything else: the error-warning level (counters past 96), buffer
  overflows (a lost frame shows as a missing TPDO: the watchdogs judge it), protocol
  violations and bus errors (single errors the controller retransmits; they may flood),
  lost arbitration, missing ACK, transceiver status, a TX timeout (a send that fails is
  a stop cause of its own), the controller's restart after a bus-off and back to
  error-active, the error counters.

The classes and the detail bits are linux/can/error.h's values; other interfaces that
pass error frames through python-can (``is_error_frame``) are read the same way.

>>> v = error_frame_verdict(0x040, bytes(8))
>>> v.stops, v.text
(True, 'bus-off (CAN_ERR_BUSOFF)')
>>> v = error_frame_verdict(0x004, bytes([0, 0x20, 0, 0, 0, 0, 0, 0]))
>>> v.stops, v.text
(True, 'controller: tx error-passive (CAN_ERR_CRTL data[1]=0x20)')
>>> v = error_frame_verdict(0x004, bytes([0, 0x08, 0, 0, 0, 0, 0, 0]))
>>> v.stops, v.text
(False, 'controller: tx error-warning (CAN_ERR_CRTL data[1]=0x08)')
"""

from __future__ import annotations

from dataclasses import dataclass

# error classes (the error frame's identifier)
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CNT = 0x200
CAN_ERR_DLC = 8

# controller problems (data[1] of CAN_ERR_CRTL)
CAN_ERR_CRTL_RX_OVERFLOW = 0x01
CAN_ERR_CRTL_TX_OVERFLOW = 0x02
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40
CAN_ERR_CRTL_PASSIVE = CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE

#: every class, in bit order, with its name and what it means in a line
ERROR_CLASSES: tuple[tuple[int, str, str], ...] = (
    (CAN_ERR_TX_TIMEOUT, "CAN_ERR_TX_TIMEOUT", "tx timeout"),
    (CAN_ERR_LOSTARB, "CAN_ERR_LOSTARB", "lost arbitration"),
    (CAN_ERR_CRTL, "CAN_ERR_CRTL", "controller"),
    (CAN_ERR_PROT, "CAN_ERR_PROT", "protocol violation"),
    (CAN_ERR_TRX, "CAN_ERR_TRX", "transceiver"),
    (CAN_ERR_ACK, "CAN_ERR_ACK", "no ACK"),
    (CAN_ERR_BUSOFF, "CAN_ERR_BUSOFF", "bus-off"),
    (CAN_ERR_BUSERROR, "CAN_ERR_BUSERROR", "bus error"),
    (CAN_ERR_RESTARTED, "CAN_ERR_RESTARTED", "controller restarted"),
    (CAN_ERR_CNT, "CAN_ERR_CNT", "error counters"),
)
_CRTL_BITS: tuple[tuple[int, str], ...] = (
    (CAN_ERR_CRTL_RX_OVERFLOW, "rx overflow"),
    (CAN_ERR_CRTL_TX_OVERFLOW, "tx overflow"),
    (CAN_ERR_CRTL_RX_WARNING, "rx error-warning"),
    (CAN_ERR_CRTL_TX_WARNING, "tx error-warning"),
    (CAN_ERR_CRTL_RX_PASSIVE, "rx error-passive"),
    (CAN_ERR_CRTL_TX_PASSIVE, "tx error-passive"),
    (CAN_ERR_CRTL_ACTIVE, "back to error-active"),
)
_KNOWN = sum(bit for bit, _name, _what in ERROR_CLASSES)  # (distinct bits: their OR)


@dataclass(frozen=True)
class ErrorFrameVerdict:
    """What one error frame reports: ``text`` (one line, the classes by name), whether it
    is a stop cause (``stops``: bus-off, error-passive), and its class bits (``classes``:
    the identifier)."""

    classes: int
    stops: bool
    text: str


def error_frame_verdict(can_id: int, data: bytes | bytearray) -> ErrorFrameVerdict:
    """Decode an error frame's identifier (its ``CAN_ERR_*`` classes; the error flag, if
    still set, is ignored) and data (missing bytes read as 0).

    >>> error_frame_verdict(0x20000048, bytes(8)).text
    'protocol violation (CAN_ERR_PROT), bus-off (CAN_ERR_BUSOFF)'
    >>> error_frame_verdict(0x000, b"").text
    'unspecified (class 0x000)'
    >>> error_frame_verdict(0x004, bytes([0, 0x30])).text
    'controller: rx error-passive, tx error-passive (CAN_ERR_CRTL data[1]=0x30)'
    >>> error_frame_verdict(0x240, bytes([0, 0, 0, 0, 0, 0, 255, 3])).text
    'bus-off (CAN_ERR_BUSOFF), error counters tx 255 rx 3 (CAN_ERR_CNT)'
    """
    classes = int(can_id) & 0x1FFFFFFF
    detail = bytes(data[:CAN_ERR_DLC]).ljust(CAN_ERR_DLC, b"\x00")
    parts: list[str] = []
    stops = False
    for bit, name, what in ERROR_CLASSES:
        if not classes & bit:
            continue
        if bit == CAN_ERR_CRTL:
            d1 = detail[1]
            bits = [text for flag, text in _CRTL_BITS if d1 & flag]
            shown = ", ".join(bits) if bits else "unspecified"
            parts.append(f"{what}: {shown} ({name} data[1]=0x{d1:02X})")
            stops = stops or bool(d1 & CAN_ERR_CRTL_PASSIVE)
        elif bit == CAN_ERR_CNT:
            parts.append(f"{what} tx {detail[6]} rx {detail[7]} ({name})")
        else:
            parts.append(f"{what} ({name})")
            stops = stops or bit == CAN_ERR_BUSOFF
    unknown = classes & ~_KNOWN
    if unknown or not parts:
        parts.append(f"unspecified (class 0x{unknown:03X})")
    return ErrorFrameVerdict(classes, stops, ", ".join(parts))
