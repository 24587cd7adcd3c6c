"""CANopen CiA 301 communication profile: COB-IDs, NMT, heartbeat, SYNC, EMCY, SDO, PDO entries.

Constants are named as in CiA 301 v4.2.  Builders (``make_*``) return
:class:`can.Message` objects and never touch a bus; parsers (``parse_*``) take
bytes and raise :class:`FrameError` (a :class:`DriverError`) on malformed input.
The host drivers and the simulated drives both use this module; the drive
profile (controlword, statusword, the state machine, our PDO layouts) is in
:mod:`drivers.protocol.cia402`, frame bit lengths in :mod:`drivers.protocol.frames`.

>>> make_nmt(NMT_RESET_NODE, 0).data.hex()
'8100'
>>> make_heartbeat(0x7F, NMT_STATE_OPERATIONAL).arbitration_id == 0x77F
True
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import can
import numpy as np
from canopen.sdo.exceptions import SdoAbortedError

from hrm_ctrl.errors import DriverError


class FrameError(DriverError):
    """A CAN frame does not have the layout its COB-ID promises."""


# ---------------------------------------------------------------- COB-IDs
# Function codes of the predefined connection set (11-bit COB-ID = function code + node id).
COB_NMT = 0x000
COB_SYNC = 0x080
COB_EMCY = 0x080
COB_TIME = 0x100
COB_TPDO1 = 0x180
COB_RPDO1 = 0x200
COB_TPDO2 = 0x280
COB_RPDO2 = 0x300
COB_TPDO3 = 0x380
COB_RPDO3 = 0x400
COB_TPDO4 = 0x480
COB_RPDO4 = 0x500
COB_SDO_TX = 0x580  # server -> client (the drive answers)
COB_SDO_RX = 0x600  # client -> server (the host asks)
COB_NMT_ERROR_CONTROL = 0x700  # heartbeat / boot-up
FUNCTION_CODE_MASK = 0x780
NODE_ID_MASK = 0x07F

NODE_ID_MIN = 1
NODE_ID_MAX = 127
HOST_HEARTBEAT_NODE_ID = 0x7F
"""Node id under which the host produces its heartbeat (COB-ID 0x77F).

Drives must therefore use ids 1..126 when the host heartbeat is on; the bus
configuration checks this."""

# ---------------------------------------------------------------- NMT
NMT_START_REMOTE_NODE = 0x01
NMT_STOP_REMOTE_NODE = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_COMMANDS = (
    NMT_START_REMOTE_NODE,
    NMT_STOP_REMOTE_NODE,
    NMT_ENTER_PRE_OPERATIONAL,
    NMT_RESET_NODE,
    NMT_RESET_COMMUNICATION,
)

# NMT states as carried by heartbeat / boot-up frames.
NMT_STATE_BOOTUP = 0x00
NMT_STATE_STOPPED = 0x04
NMT_STATE_OPERATIONAL = 0x05
NMT_STATE_PRE_OPERATIONAL = 0x7F
NMT_STATE_NAMES = {
    NMT_STATE_BOOTUP: "BOOTUP",
    NMT_STATE_STOPPED: "STOPPED",
    NMT_STATE_OPERATIONAL: "OPERATIONAL",
    NMT_STATE_PRE_OPERATIONAL: "PRE-OPERATIONAL",
}

# ---------------------------------------------------------------- SDO
# Client command specifiers (ccs, bits 7..5 of byte 0 of a client request).
SDO_CCS_DOWNLOAD_SEGMENT = 0
SDO_CCS_INITIATE_DOWNLOAD = 1
SDO_CCS_INITIATE_UPLOAD = 2
SDO_CCS_UPLOAD_SEGMENT = 3
SDO_CS_ABORT = 4
SDO_CCS_BLOCK_UPLOAD = 5
SDO_CCS_BLOCK_DOWNLOAD = 6
# Server command specifiers (scs, bits 7..5 of byte 0 of a server response).
SDO_SCS_UPLOAD_SEGMENT = 0
SDO_SCS_DOWNLOAD_SEGMENT = 1
SDO_SCS_INITIATE_UPLOAD = 2
SDO_SCS_INITIATE_DOWNLOAD = 3
SDO_SCS_BLOCK_DOWNLOAD = 5
SDO_SCS_BLOCK_UPLOAD = 6

# SDO abort codes (CiA 301 table 22); their texts are canopen's (describe_sdo_abort).
SDO_ABORT_TOGGLE_BIT = 0x05030000
SDO_ABORT_TIMEOUT = 0x05040000
SDO_ABORT_COMMAND_SPECIFIER = 0x05040001
SDO_ABORT_INVALID_BLOCK_SIZE = 0x05040002
SDO_ABORT_INVALID_SEQUENCE = 0x05040003
SDO_ABORT_CRC = 0x05040004
SDO_ABORT_OUT_OF_MEMORY = 0x05040005
SDO_ABORT_UNSUPPORTED_ACCESS = 0x06010000
SDO_ABORT_WRITE_ONLY = 0x06010001
SDO_ABORT_READ_ONLY = 0x06010002
SDO_ABORT_NO_OBJECT = 0x06020000
SDO_ABORT_NOT_MAPPABLE = 0x06040041
SDO_ABORT_PDO_LENGTH = 0x06040042
SDO_ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
SDO_ABORT_INTERNAL_INCOMPATIBLE = 0x06040047
SDO_ABORT_HARDWARE = 0x06060000
SDO_ABORT_TYPE_MISMATCH = 0x06070010
SDO_ABORT_LENGTH_TOO_HIGH = 0x06070012
SDO_ABORT_LENGTH_TOO_LOW = 0x06070013
SDO_ABORT_NO_SUBINDEX = 0x06090011
SDO_ABORT_INVALID_VALUE = 0x06090030
SDO_ABORT_VALUE_TOO_HIGH = 0x06090031
SDO_ABORT_VALUE_TOO_LOW = 0x06090032
SDO_ABORT_MAX_LESS_THAN_MIN = 0x06090036
SDO_ABORT_RESOURCE_NOT_AVAILABLE = 0x060A0023
SDO_ABORT_GENERAL = 0x08000000
SDO_ABORT_DATA_TRANSFER = 0x08000020
SDO_ABORT_LOCAL_CONTROL = 0x08000021
SDO_ABORT_DEVICE_STATE = 0x08000022
SDO_ABORT_NO_OD = 0x08000023
SDO_ABORT_NO_DATA = 0x08000024

SDO_ABORT_TEXTS: dict[int, str] = dict(SdoAbortedError.CODES)
"""Text of each abort code: canopen's table, which has every code of CiA 301 table 22
(so no text of our own; ``tests/drivers/protocol`` checks every ``SDO_ABORT_*`` has one)."""

# ---------------------------------------------------------------- EMCY
# Emergency error codes (CiA 301 table 21) and error register (0x1001) bits.
EMCY_NO_ERROR = 0x0000  # error reset / no error
EMCY_GENERIC_DEVICE = 0x1000  # generic error
EMCY_HEARTBEAT = 0x8130  # life guard error or heartbeat error
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_PDO_LENGTH_EXCEEDED = 0x8220  # PDO length exceeded
ERR_REG_GENERIC = 0x01
ERR_REG_COMMUNICATION = 0x10
ERR_REG_MANUFACTURER = 0x80

# ---------------------------------------------------------------- objects (0x1000..0x1FFF)
OD_DEVICE_TYPE = 0x1000
OD_ERROR_REGISTER = 0x1001
OD_COB_ID_SYNC = 0x1005
OD_MANUFACTURER_DEVICE_NAME = 0x1008
OD_GUARD_TIME = 0x100C
OD_LIFE_TIME_FACTOR = 0x100D
OD_COB_ID_EMCY = 0x1014
OD_CONSUMER_HEARTBEAT_TIME = 0x1016
OD_PRODUCER_HEARTBEAT_TIME = 0x1017
OD_IDENTITY = 0x1018
OD_RPDO1_COMMUNICATION = 0x1400
OD_RPDO1_MAPPING = 0x1600
OD_TPDO1_COMMUNICATION = 0x1800
OD_TPDO1_MAPPING = 0x1A00
PDO_COB_ID_INVALID = 0x80000000  # bit 31 of a PDO COB-ID: PDO does not exist / is not valid
PDO_TRANSMISSION_SYNCHRONOUS = 0x01  # acyclic-synchronous: act on / send at every SYNC


# ---------------------------------------------------------------- values
def node_id_of(cob_id: int) -> int:
    """Node id part of a predefined-connection-set COB-ID.

    >>> node_id_of(0x18A)
    10
    """
    return cob_id & NODE_ID_MASK


def function_code_of(cob_id: int) -> int:
    """Function code part of a COB-ID.

    >>> hex(function_code_of(0x18A))
    '0x180'
    """
    return cob_id & FUNCTION_CODE_MASK


def check_node_id(node_id: int, *, allow_broadcast: bool = False) -> None:
    """Raise :class:`FrameError` unless ``node_id`` is 1..127 (0 too with ``allow_broadcast``).

    >>> check_node_id(0)
    Traceback (most recent call last):
    ...
    drivers.protocol.cia301.FrameError: node id 0 outside 1..127
    """
    low = 0 if allow_broadcast else NODE_ID_MIN
    if isinstance(node_id, bool) or not isinstance(node_id, int | np.integer):
        raise FrameError(f"node id must be an integer, got {node_id!r}")
    if not low <= int(node_id) <= NODE_ID_MAX:
        raise FrameError(f"node id {node_id} outside {low}..{NODE_ID_MAX}")


def pdo_mapping_entry(index: int, subindex: int, bit_length: int) -> int:
    """A PDO mapping entry (0x1600/0x1A00 sub-index value): index<<16 | sub<<8 | bits.

    >>> hex(pdo_mapping_entry(0x607A, 0, 32))
    '0x607a0020'
    """
    return (index << 16) | (subindex << 8) | bit_length


def parse_pdo_mapping_entry(value: int) -> tuple[int, int, int]:
    """Inverse of :func:`pdo_mapping_entry`: (index, subindex, bit length).

    >>> [hex(v) for v in parse_pdo_mapping_entry(0x60410010)]
    ['0x6041', '0x0', '0x10']
    """
    return (value >> 16) & 0xFFFF, (value >> 8) & 0xFF, value & 0xFF


def consumer_heartbeat_entry(node_id: int, time_ms: int) -> int:
    """A 0x1016 consumer heartbeat entry: node id in bits 16..23, time (ms) in bits 0..15.

    >>> hex(consumer_heartbeat_entry(0x7F, 250))
    '0x7f00fa'
    """
    if not 0 <= time_ms <= 0xFFFF:
        raise FrameError(f"heartbeat time {time_ms} ms outside 0..65535")
    return ((node_id & 0xFF) << 16) | (time_ms & 0xFFFF)


# ---------------------------------------------------------------- frame builders / parsers
def data_frame(cob_id: int, data: bytes) -> can.Message:
    """A classical data frame with an 11-bit identifier.

    >>> m = data_frame(0x123, b"\\x01")
    >>> hex(m.arbitration_id), m.data.hex(), m.is_extended_id
    ('0x123', '01', False)
    """
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


def make_nmt(command: int, node_id: int = 0) -> can.Message:
    """NMT node-control frame (COB-ID 0x000); ``node_id`` 0 addresses every node.

    >>> m = make_nmt(NMT_START_REMOTE_NODE, 12)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x0', '010c')
    """
    if command not in NMT_COMMANDS:
        raise FrameError(f"unknown NMT command 0x{command:02X}")
    check_node_id(node_id, allow_broadcast=True)
    return data_frame(COB_NMT, bytes((command, node_id)))


def make_sync(counter: int | None = None) -> can.Message:
    """SYNC frame (COB-ID 0x080), without data or with a counter 1..240.

    >>> make_sync().data.hex(), make_sync(3).data.hex()
    ('', '03')
    """
    if counter is None:
        return data_frame(COB_SYNC, b"")
    if not 1 <= counter <= 240:
        raise FrameError(f"SYNC counter {counter} outside 1..240")
    return data_frame(COB_SYNC, bytes((counter,)))


def make_heartbeat(node_id: int, nmt_state: int) -> can.Message:
    """Heartbeat (or boot-up, state 0) frame of a node: COB-ID 0x700 + node id.

    >>> m = make_heartbeat(0x7F, NMT_STATE_OPERATIONAL)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x77f', '05')
    """
    check_node_id(node_id)
    if nmt_state not in NMT_STATE_NAMES:
        raise FrameError(f"unknown NMT state 0x{nmt_state:02X}")
    return data_frame(COB_NMT_ERROR_CONTROL + node_id, bytes((nmt_state,)))


def make_guarding_request(node_id: int) -> can.Message:
    """Node-guarding request of the NMT master (CiA 301 7.2.8.3.1): a remote frame on
    0x700 + node id, 1 byte asked for.

    >>> m = make_guarding_request(3)
    >>> hex(m.arbitration_id), m.is_remote_frame, m.dlc
    ('0x703', True, 1)
    """
    check_node_id(node_id)
    return can.Message(
        arbitration_id=COB_NMT_ERROR_CONTROL + node_id,
        is_remote_frame=True,
        dlc=1,
        is_extended_id=False,
    )


def parse_guarding_answer(data: bytes | bytearray) -> tuple[int, int]:
    """(NMT state, toggle bit) of a node-guarding answer (CiA 301 7.2.8.3.1: bit 7 the
    toggle, bits 0..6 the state: stopped, operational or pre-operational).

    >>> parse_guarding_answer(b'\\x85'), parse_guarding_answer(b'\\x7f')
    ((5, 1), (127, 0))
    >>> parse_guarding_answer(b'\\x80')
    Traceback (most recent call last):
    ...
    drivers.protocol.cia301.FrameError: node-guarding answer 0x80 names no NMT state
    """
    if len(data) != 1:
        raise FrameError(f"node-guarding answer must carry 1 byte, got {len(data)}")
    state, toggle = int(data[0]) & 0x7F, int(data[0]) >> 7
    if state not in NMT_STATE_NAMES or state == NMT_STATE_BOOTUP:
        raise FrameError(f"node-guarding answer 0x{data[0]:02X} names no NMT state")
    return state, toggle


def parse_heartbeat(data: bytes | bytearray) -> int:
    """NMT state carried by a heartbeat / boot-up frame (CiA 301 7.2.8.3.2.2).  A heartbeat
    has no toggle bit (bit 7 is reserved, 0: a set bit 7 is a node-guarding reply, which
    this stack never asks for) and names one of the four states; anything else is a
    :class:`FrameError`, not a state guessed at.

    >>> parse_heartbeat(b'\\x05'), parse_heartbeat(b'\\x7f'), parse_heartbeat(b'\\x00')
    (5, 127, 0)
    >>> parse_heartbeat(b'\\x85')
    Traceback (most recent call last):
    ...
    drivers.protocol.cia301.FrameError: heartbeat byte 0x85 names no NMT state
    """
    if len(data) != 1:
        raise FrameError(f"heartbeat must carry 1 byte, got {len(data)}")
    state = int(data[0])
    if state not in NMT_STATE_NAMES:
        raise FrameError(f"heartbeat byte 0x{state:02X} names no NMT state")
    return state


@dataclass(frozen=True)
class Emergency:
    """A decoded EMCY frame (CiA 301 7.2.7)."""

    node_id: int
    error_code: int
    error_register: int
    manufacturer: bytes

    def describe(self) -> str:
        """One-line text.

        >>> Emergency(3, 0x2310, 0x03, b'').describe()
        'EMCY node 3: error code 0x2310, error register 0x03'
        """
        text = (
            f"EMCY node {self.node_id}: error code 0x{self.error_code:04X}, "
            f"error register 0x{self.error_register:02X}"
        )
        return text + (f", data {self.manufacturer.hex()}" if any(self.manufacturer) else "")


def make_emcy(
    node_id: int, error_code: int, error_register: int, manufacturer: bytes = b"\x00" * 5
) -> can.Message:
    """EMCY frame (COB-ID 0x080 + node id): error code, error register, 5 manufacturer bytes.

    >>> m = make_emcy(2, 0x8611, 0x21)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x82', '1186210000000000')
    """
    check_node_id(node_id)
    if len(manufacturer) > 5:
        raise FrameError("EMCY manufacturer field is at most 5 bytes")
    payload = struct.pack("<HB", error_code, error_register) + manufacturer.ljust(5, b"\x00")
    return data_frame(COB_EMCY + node_id, payload)


def parse_emcy(node_id: int, data: bytes | bytearray) -> Emergency:
    """Decode an EMCY payload.

    >>> parse_emcy(2, bytes.fromhex('1186210000000000')).error_code == 0x8611
    True
    """
    if len(data) != 8:
        raise FrameError(f"EMCY from node {node_id} must carry 8 bytes, got {len(data)}")
    code, reg = struct.unpack_from("<HB", bytes(data))
    return Emergency(node_id, int(code), int(reg), bytes(data[3:8]))


# SDO expedited frames (used by tests and simulators; the host uses canopen's SDO client).
def make_sdo_download_expedited(
    node_id: int, index: int, subindex: int, value: bytes
) -> can.Message:
    """Client expedited download request (COB-ID 0x600 + node id), 1..4 data bytes.

    >>> make_sdo_download_expedited(1, 0x6060, 0, b'\\x08').data.hex()
    '2f60600008000000'
    """
    check_node_id(node_id)
    n = len(value)
    if not 1 <= n <= 4:
        raise FrameError(f"expedited SDO carries 1..4 bytes, got {n}")
    cmd = (SDO_CCS_INITIATE_DOWNLOAD << 5) | ((4 - n) << 2) | 0x03
    payload = struct.pack("<BHB", cmd, index, subindex) + value.ljust(4, b"\x00")
    return data_frame(COB_SDO_RX + node_id, payload)


def make_sdo_upload_request(node_id: int, index: int, subindex: int) -> can.Message:
    """Client initiate upload request (COB-ID 0x600 + node id).

    >>> make_sdo_upload_request(1, 0x6041, 0).data.hex()
    '4041600000000000'
    """
    check_node_id(node_id)
    payload = struct.pack("<BHB", SDO_CCS_INITIATE_UPLOAD << 5, index, subindex) + bytes(4)
    return data_frame(COB_SDO_RX + node_id, payload)


def make_sdo_abort(node_id: int, index: int, subindex: int, abort_code: int) -> can.Message:
    """Server abort transfer (COB-ID 0x580 + node id).

    >>> make_sdo_abort(1, 0x607A, 0, SDO_ABORT_VALUE_TOO_HIGH).data.hex()
    '807a600031000906'
    """
    check_node_id(node_id)
    payload = struct.pack("<BHBI", SDO_CS_ABORT << 5, index, subindex, abort_code)
    return data_frame(COB_SDO_TX + node_id, payload)


def parse_sdo_abort(data: bytes | bytearray) -> tuple[int, int, int]:
    """(index, subindex, abort code) of an SDO abort frame.

    >>> [hex(v) for v in parse_sdo_abort(bytes.fromhex('807a600031000906'))]
    ['0x607a', '0x0', '0x6090031']
    """
    if len(data) != 8 or (data[0] >> 5) != SDO_CS_ABORT:
        raise FrameError("not an SDO abort frame")
    _, index, sub, code = struct.unpack("<BHBI", bytes(data))
    return int(index), int(sub), int(code)


def describe_sdo_abort(code: int) -> str:
    """Text of an SDO abort code (canopen's wording).

    >>> describe_sdo_abort(0x06020000)
    '0x06020000 (Object does not exist)'
    >>> describe_sdo_abort(0x12345678)
    '0x12345678 (unknown abort code)'
    """
    return f"0x{code:08X} ({SDO_ABORT_TEXTS.get(code, 'unknown abort code')})"
