"""CANopen CiA 301 / CiA 402 protocol definitions and pure frame builders/parsers.

Constants are named as in the standards (CiA 301 v4.2 communication profile,
CiA 402 drive profile).  Builders (``make_*``) return :class:`can.Message`
objects (or bytes) and never touch a bus; parsers (``parse_*``) take frames or
bytes and raise :class:`FrameError` (a :class:`DriverError`) on malformed
input.  Both the host drivers and the simulated drives use this module.

>>> make_nmt(NMT_RESET_NODE, 0).data.hex()
'8100'
>>> decode_state(0x0237).name
'OPERATION_ENABLED'
>>> make_rpdo_target(5, CW_ENABLE_OPERATION, -2).data.hex()
'0f00feffffff'
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import can
import numpy as np

from hrm_ctrl.errors import DriverError


class FrameError(DriverError):
    """A CAN frame does not have the layout its COB-ID promises."""


# ---------------------------------------------------------------- CiA 301: COB-IDs
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

# ---------------------------------------------------------------- CiA 301: NMT
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

# ---------------------------------------------------------------- CiA 301: SDO
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

# SDO abort codes (CiA 301 table 22).
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
SDO_ABORT_MESSAGES = {
    SDO_ABORT_TOGGLE_BIT: "toggle bit not alternated",
    SDO_ABORT_TIMEOUT: "SDO protocol timed out",
    SDO_ABORT_COMMAND_SPECIFIER: "command specifier not valid or unknown",
    SDO_ABORT_INVALID_BLOCK_SIZE: "invalid block size",
    SDO_ABORT_INVALID_SEQUENCE: "invalid sequence number",
    SDO_ABORT_CRC: "CRC error",
    SDO_ABORT_OUT_OF_MEMORY: "out of memory",
    SDO_ABORT_UNSUPPORTED_ACCESS: "unsupported access to an object",
    SDO_ABORT_WRITE_ONLY: "attempt to read a write only object",
    SDO_ABORT_READ_ONLY: "attempt to write a read only object",
    SDO_ABORT_NO_OBJECT: "object does not exist in the object dictionary",
    SDO_ABORT_NOT_MAPPABLE: "object cannot be mapped to the PDO",
    SDO_ABORT_PDO_LENGTH: "mapped objects would exceed PDO length",
    SDO_ABORT_PARAMETER_INCOMPATIBLE: "general parameter incompatibility",
    SDO_ABORT_INTERNAL_INCOMPATIBLE: "general internal incompatibility in the device",
    SDO_ABORT_HARDWARE: "access failed due to a hardware error",
    SDO_ABORT_TYPE_MISMATCH: "data type does not match, length of service parameter",
    SDO_ABORT_LENGTH_TOO_HIGH: "data type does not match, length too high",
    SDO_ABORT_LENGTH_TOO_LOW: "data type does not match, length too low",
    SDO_ABORT_NO_SUBINDEX: "sub-index does not exist",
    SDO_ABORT_INVALID_VALUE: "invalid value for parameter",
    SDO_ABORT_VALUE_TOO_HIGH: "value of parameter written too high",
    SDO_ABORT_VALUE_TOO_LOW: "value of parameter written too low",
    SDO_ABORT_MAX_LESS_THAN_MIN: "maximum value is less than minimum value",
    SDO_ABORT_RESOURCE_NOT_AVAILABLE: "resource not available: SDO connection",
    SDO_ABORT_GENERAL: "general error",
    SDO_ABORT_DATA_TRANSFER: "data cannot be transferred or stored to the application",
    SDO_ABORT_LOCAL_CONTROL: "data cannot be transferred because of local control",
    SDO_ABORT_DEVICE_STATE: "data cannot be transferred because of the present device state",
    SDO_ABORT_NO_OD: "object dictionary not present",
    SDO_ABORT_NO_DATA: "no data available",
}

# ---------------------------------------------------------------- CiA 301: objects
OD_DEVICE_TYPE = 0x1000
OD_ERROR_REGISTER = 0x1001
OD_COB_ID_SYNC = 0x1005
OD_MANUFACTURER_DEVICE_NAME = 0x1008
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

# ---------------------------------------------------------------- CiA 402: objects
OD_ERROR_CODE = 0x603F
OD_CONTROLWORD = 0x6040
OD_STATUSWORD = 0x6041
OD_QUICK_STOP_OPTION_CODE = 0x605A
OD_MODES_OF_OPERATION = 0x6060
OD_MODES_OF_OPERATION_DISPLAY = 0x6061
OD_POSITION_ACTUAL_VALUE = 0x6064
OD_FOLLOWING_ERROR_WINDOW = 0x6065
OD_TARGET_POSITION = 0x607A
OD_SOFTWARE_POSITION_LIMIT = 0x607D
OD_INTERPOLATION_TIME_PERIOD = 0x60C2
OD_SUPPORTED_DRIVE_MODES = 0x6502

# Modes of operation (0x6060).
MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3
MODE_HOMING = 6
MODE_INTERPOLATED_POSITION = 7
MODE_CSP = 8
MODE_CSV = 9
MODE_CST = 10

# Quick stop option codes (0x605A): 2 = slow down on quick stop ramp, then switch on disabled.
QUICK_STOP_OPTION_QUICK_STOP_RAMP_DISABLE = 2
QUICK_STOP_OPTION_QUICK_STOP_RAMP_STAY = 6

# Controlword (0x6040) bits and device-control commands (CiA 402 table 31).
CW_BIT_SWITCH_ON = 0x0001
CW_BIT_ENABLE_VOLTAGE = 0x0002
CW_BIT_QUICK_STOP = 0x0004  # active low: 0 requests a quick stop
CW_BIT_ENABLE_OPERATION = 0x0008
CW_BIT_FAULT_RESET = 0x0080
CW_BIT_HALT = 0x0100
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_DISABLE_OPERATION = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080
# Short aliases named as the CiA 402 commands.
SHUTDOWN = CW_SHUTDOWN
SWITCH_ON = CW_SWITCH_ON
ENABLE_OPERATION = CW_ENABLE_OPERATION
DISABLE_VOLTAGE = CW_DISABLE_VOLTAGE
QUICK_STOP = CW_QUICK_STOP
DISABLE_OPERATION = CW_DISABLE_OPERATION
FAULT_RESET = CW_FAULT_RESET

# Statusword (0x6041) bits.
SW_READY_TO_SWITCH_ON = 0x0001
SW_SWITCHED_ON = 0x0002
SW_OPERATION_ENABLED = 0x0004
SW_FAULT = 0x0008
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP = 0x0020  # active low: 0 means a quick stop is active
SW_SWITCH_ON_DISABLED = 0x0040
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT_ACTIVE = 0x0800
SW_CSP_DRIVE_FOLLOWS_COMMAND = 0x1000  # CSP: bit 12 = drive follows the command value
SW_CSP_FOLLOWING_ERROR = 0x2000  # CSP: bit 13 = following error


class State402(IntEnum):
    """CiA 402 power drive system states, decoded from the statusword."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7
    UNKNOWN = 8


# (mask, value) pairs of CiA 402 table 30, in decoding order.
STATE_PATTERNS: tuple[tuple[int, int, State402], ...] = (
    (0x004F, 0x0000, State402.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State402.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State402.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State402.SWITCHED_ON),
    (0x006F, 0x0027, State402.OPERATION_ENABLED),
    (0x006F, 0x0007, State402.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State402.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State402.FAULT),
)

# Statusword bits a drive shows in each state (the low 7 bits, for simulators).
STATUSWORD_OF_STATE: dict[State402, int] = {
    State402.NOT_READY_TO_SWITCH_ON: 0x0000,
    State402.SWITCH_ON_DISABLED: 0x0040,
    State402.READY_TO_SWITCH_ON: 0x0021,
    State402.SWITCHED_ON: 0x0023,
    State402.OPERATION_ENABLED: 0x0027,
    State402.QUICK_STOP_ACTIVE: 0x0007,
    State402.FAULT_REACTION_ACTIVE: 0x000F,
    State402.FAULT: 0x0008,
}

# Controlword that moves a drive one step from a state towards OPERATION_ENABLED.
CONTROLWORD_TOWARDS_ENABLED: dict[State402, int] = {
    State402.SWITCH_ON_DISABLED: CW_SHUTDOWN,
    State402.READY_TO_SWITCH_ON: CW_SWITCH_ON,
    State402.SWITCHED_ON: CW_ENABLE_OPERATION,
    State402.FAULT: CW_FAULT_RESET,
}
# The state each of those controlwords should lead to.
NEXT_STATE_TOWARDS_ENABLED: dict[State402, State402] = {
    State402.SWITCH_ON_DISABLED: State402.READY_TO_SWITCH_ON,
    State402.READY_TO_SWITCH_ON: State402.SWITCHED_ON,
    State402.SWITCHED_ON: State402.OPERATION_ENABLED,
    State402.FAULT: State402.SWITCH_ON_DISABLED,
}


def decode_state(statusword: int) -> State402:
    """The CiA 402 state shown by a statusword.

    >>> decode_state(0x0250).name
    'SWITCH_ON_DISABLED'
    >>> decode_state(0x0231).name, decode_state(0x0233).name
    ('READY_TO_SWITCH_ON', 'SWITCHED_ON')
    >>> decode_state(0x0217).name, decode_state(0x0218).name
    ('QUICK_STOP_ACTIVE', 'FAULT')
    """
    for mask, value, state in STATE_PATTERNS:
        if statusword & mask == value:
            return state
    return State402.UNKNOWN


def decode_states(statuswords: np.ndarray) -> np.ndarray:
    """Vectorised :func:`decode_state`: int array of :class:`State402` values.

    >>> decode_states(np.array([0x0237, 0x0008, 0x0021])).tolist()
    [4, 7, 2]
    """
    sw = np.asarray(statuswords, dtype=np.int64)
    out = np.full(sw.shape, int(State402.UNKNOWN), dtype=np.int64)
    for mask, value, state in reversed(STATE_PATTERNS):
        out = np.where(sw & mask == value, int(state), out)
    return out


def statusword_has_fault(statusword: int) -> bool:
    """True when the statusword's fault bit (bit 3) is set.

    >>> statusword_has_fault(0x0218), statusword_has_fault(0x0237)
    (True, False)
    """
    return bool(statusword & SW_FAULT)


# ---------------------------------------------------------------- helpers for values
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


def _check_node_id(node_id: int, *, allow_broadcast: bool = False) -> None:
    low = 0 if allow_broadcast else NODE_ID_MIN
    if isinstance(node_id, bool) or not isinstance(node_id, int | np.integer):
        raise FrameError(f"node id must be an integer, got {node_id!r}")
    if not low <= int(node_id) <= NODE_ID_MAX:
        raise FrameError(f"node id {node_id} outside {low}..{NODE_ID_MAX}")


def pdo_mapping_entry(index: int, subindex: int, bit_length: int) -> int:
    """A PDO mapping entry (0x1600/0x1A00 sub-index value): index<<16 | sub<<8 | bits.

    >>> hex(pdo_mapping_entry(OD_TARGET_POSITION, 0, 32))
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


def interpolation_time_period(period_s: float) -> tuple[int, int]:
    """0x60C2 (value, index) so that value * 10**index seconds == period_s.

    Prefers milliseconds (index -3, the usual unit), then finer, then coarser units.

    >>> interpolation_time_period(0.01)
    (10, -3)
    >>> interpolation_time_period(0.0025)
    (25, -4)
    """
    if not period_s > 0:
        raise FrameError(f"interpolation period must be > 0 s, got {period_s}")
    for index in (-3, -4, -5, -6, -2, -1, 0):
        value = period_s / 10.0**index
        rounded = round(value)
        if 1 <= rounded <= 255 and abs(value - rounded) <= 1e-9 * max(1.0, value):
            return int(rounded), index
    raise FrameError(f"period {period_s} s cannot be written as value*10^index (value 1..255)")


# ---------------------------------------------------------------- frame builders
def _message(cob_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


def make_nmt(command: int, node_id: int = 0) -> can.Message:
    """NMT node-control frame (COB-ID 0x000); ``node_id`` 0 addresses every node.

    >>> m = make_nmt(NMT_START_REMOTE_NODE, 12)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x0', '010c')
    """
    if command not in NMT_COMMANDS:
        raise FrameError(f"unknown NMT command 0x{command:02X}")
    _check_node_id(node_id, allow_broadcast=True)
    return _message(COB_NMT, bytes((command, node_id)))


def make_sync(counter: int | None = None) -> can.Message:
    """SYNC frame (COB-ID 0x080), without data or with a counter 1..240.

    >>> make_sync().data.hex(), make_sync(3).data.hex()
    ('', '03')
    """
    if counter is None:
        return _message(COB_SYNC, b"")
    if not 1 <= counter <= 240:
        raise FrameError(f"SYNC counter {counter} outside 1..240")
    return _message(COB_SYNC, bytes((counter,)))


def make_heartbeat(node_id: int, nmt_state: int) -> can.Message:
    """Heartbeat (or boot-up, state 0) frame of a node: COB-ID 0x700 + node id.

    >>> m = make_heartbeat(0x7F, NMT_STATE_OPERATIONAL)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x77f', '05')
    """
    _check_node_id(node_id)
    if nmt_state not in NMT_STATE_NAMES:
        raise FrameError(f"unknown NMT state 0x{nmt_state:02X}")
    return _message(COB_NMT_ERROR_CONTROL + node_id, bytes((nmt_state,)))


RPDO_TARGET_LAYOUT = struct.Struct("<Hi")  # controlword (UNSIGNED16), target position (INTEGER32)
TPDO_FEEDBACK_LAYOUT = struct.Struct("<Hi")  # statusword (UNSIGNED16), position actual (INTEGER32)
RPDO_TARGET_DTYPE = np.dtype([("controlword", "<u2"), ("target", "<i4")])
TPDO_FEEDBACK_DTYPE = np.dtype([("statusword", "<u2"), ("position", "<i4")])
RPDO_TARGET_MAPPING = (
    pdo_mapping_entry(OD_CONTROLWORD, 0, 16),
    pdo_mapping_entry(OD_TARGET_POSITION, 0, 32),
)
TPDO_FEEDBACK_MAPPING = (
    pdo_mapping_entry(OD_STATUSWORD, 0, 16),
    pdo_mapping_entry(OD_POSITION_ACTUAL_VALUE, 0, 32),
)
RPDO_TARGET_SIZE = RPDO_TARGET_LAYOUT.size
TPDO_FEEDBACK_SIZE = TPDO_FEEDBACK_LAYOUT.size

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1


def make_rpdo_target_payloads(controlwords: np.ndarray, targets: np.ndarray) -> bytes:
    """RPDO1 payloads for many nodes at once: 6 bytes per node, concatenated.

    >>> make_rpdo_target_payloads(np.array([15, 2]), np.array([1, -1])).hex()
    '0f00010000000200ffffffff'
    """
    cw = np.asarray(controlwords)
    tg = np.asarray(targets)
    if np.any((tg < INT32_MIN) | (tg > INT32_MAX)):
        raise FrameError("target position outside INTEGER32")
    rec = np.empty(np.broadcast_shapes(cw.shape, tg.shape), dtype=RPDO_TARGET_DTYPE)
    rec["controlword"] = cw
    rec["target"] = tg
    return rec.tobytes()


def make_rpdo_target(node_id: int, controlword: int, target_counts: int) -> can.Message:
    """RPDO1 (COB-ID 0x200 + node id): controlword then target position, little-endian.

    >>> m = make_rpdo_target(3, CW_QUICK_STOP, 0x01020304)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x203', '020004030201')
    """
    _check_node_id(node_id)
    if not INT32_MIN <= int(target_counts) <= INT32_MAX:
        raise FrameError(f"target position {target_counts} outside INTEGER32")
    return _message(
        COB_RPDO1 + node_id, RPDO_TARGET_LAYOUT.pack(controlword & 0xFFFF, int(target_counts))
    )


def make_tpdo_feedback(node_id: int, statusword: int, position_counts: int) -> can.Message:
    """TPDO1 (COB-ID 0x180 + node id): statusword then position actual value.

    >>> make_tpdo_feedback(4, 0x0237, -5).data.hex()
    '3702fbffffff'
    """
    _check_node_id(node_id)
    return _message(
        COB_TPDO1 + node_id, TPDO_FEEDBACK_LAYOUT.pack(statusword & 0xFFFF, int(position_counts))
    )


def parse_rpdo_target(data: bytes | bytearray) -> tuple[int, int]:
    """(controlword, target position) from an RPDO1 payload.

    >>> parse_rpdo_target(bytes.fromhex('0f00feffffff'))
    (15, -2)
    """
    if len(data) != RPDO_TARGET_SIZE:
        raise FrameError(f"RPDO1 must carry {RPDO_TARGET_SIZE} bytes, got {len(data)}")
    cw, target = RPDO_TARGET_LAYOUT.unpack(bytes(data))
    return int(cw), int(target)


def parse_tpdo(data: bytes | bytearray) -> tuple[int, int]:
    """(statusword, position actual value) from a TPDO1 payload.

    >>> parse_tpdo(bytes.fromhex('3702fbffffff'))
    (567, -5)
    """
    if len(data) != TPDO_FEEDBACK_SIZE:
        raise FrameError(f"TPDO1 must carry {TPDO_FEEDBACK_SIZE} bytes, got {len(data)}")
    sw, pos = TPDO_FEEDBACK_LAYOUT.unpack(bytes(data))
    return int(sw), int(pos)


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
    _check_node_id(node_id)
    if len(manufacturer) > 5:
        raise FrameError("EMCY manufacturer field is at most 5 bytes")
    payload = struct.pack("<HB", error_code, error_register) + manufacturer.ljust(5, b"\x00")
    return _message(COB_EMCY + node_id, payload)


def parse_emcy(node_id: int, data: bytes | bytearray) -> Emergency:
    """Decode an EMCY payload.

    >>> parse_emcy(2, bytes.fromhex('1186210000000000')).error_code == 0x8611
    True
    """
    if len(data) != 8:
        raise FrameError(f"EMCY from node {node_id} must carry 8 bytes, got {len(data)}")
    code, reg = struct.unpack_from("<HB", bytes(data))
    return Emergency(node_id, int(code), int(reg), bytes(data[3:8]))


def parse_heartbeat(data: bytes | bytearray) -> int:
    """NMT state carried by a heartbeat / boot-up frame (toggle bit ignored).

    >>> parse_heartbeat(b'\\x05'), parse_heartbeat(b'\\x85')
    (5, 5)
    """
    if len(data) != 1:
        raise FrameError(f"heartbeat must carry 1 byte, got {len(data)}")
    return int(data[0]) & 0x7F


# SDO expedited frames (used by tests and simulators; the host uses canopen's SDO client).
def make_sdo_download_expedited(
    node_id: int, index: int, subindex: int, value: bytes
) -> can.Message:
    """Client expedited download request (COB-ID 0x600 + node id), 1..4 data bytes.

    >>> make_sdo_download_expedited(1, OD_MODES_OF_OPERATION, 0, b'\\x08').data.hex()
    '2f60600008000000'
    """
    _check_node_id(node_id)
    n = len(value)
    if not 1 <= n <= 4:
        raise FrameError(f"expedited SDO carries 1..4 bytes, got {n}")
    cmd = (SDO_CCS_INITIATE_DOWNLOAD << 5) | ((4 - n) << 2) | 0x03
    payload = struct.pack("<BHB", cmd, index, subindex) + value.ljust(4, b"\x00")
    return _message(COB_SDO_RX + node_id, payload)


def make_sdo_upload_request(node_id: int, index: int, subindex: int) -> can.Message:
    """Client initiate upload request (COB-ID 0x600 + node id).

    >>> make_sdo_upload_request(1, OD_STATUSWORD, 0).data.hex()
    '4041600000000000'
    """
    _check_node_id(node_id)
    payload = struct.pack("<BHB", SDO_CCS_INITIATE_UPLOAD << 5, index, subindex) + bytes(4)
    return _message(COB_SDO_RX + node_id, payload)


def make_sdo_abort(node_id: int, index: int, subindex: int, abort_code: int) -> can.Message:
    """Server abort transfer (COB-ID 0x580 + node id).

    >>> make_sdo_abort(1, OD_TARGET_POSITION, 0, SDO_ABORT_VALUE_TOO_HIGH).data.hex()
    '807a600031000906'
    """
    _check_node_id(node_id)
    payload = struct.pack("<BHBI", SDO_CS_ABORT << 5, index, subindex, abort_code)
    return _message(COB_SDO_TX + node_id, payload)


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
    """Text of an SDO abort code.

    >>> describe_sdo_abort(0x06020000)
    '0x06020000 (object does not exist in the object dictionary)'
    """
    return f"0x{code:08X} ({SDO_ABORT_MESSAGES.get(code, 'unknown abort code')})"
