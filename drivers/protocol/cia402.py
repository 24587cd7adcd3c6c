"""CANopen CiA 402 drive profile: objects, controlword commands, statusword, the state machine.

The power drive system state machine (CiA 402 figure 13) is one table,
:data:`TRANSITIONS`: (state, controlword command) → next state, each entry with
its transition number.  Bring-up (:mod:`drivers.bringup`) walks a drive along
:func:`route`; the simulated drive (:mod:`sim_bus.drive.state_machine`) applies
the same table.  A pair that is not in the table raises
:class:`TransitionError` from :func:`next_state`; a simulator that models a
drive ignoring such a command asks :func:`has_transition` first.

The payload layouts of our PDO mapping (RPDO1: controlword + target position,
TPDO1: statusword + position actual value) and their builders/parsers live
here too; the communication profile (COB-IDs, NMT, SDO, EMCY) is
:mod:`drivers.protocol.cia301`.

>>> decode_state(0x0237).name
'OPERATION_ENABLED'
>>> decode_command(0x000F).name, next_state(State402.SWITCHED_ON, Command402.ENABLE_OPERATION).name
('ENABLE_OPERATION', 'OPERATION_ENABLED')
>>> [hex(t.command.controlword) for t in route(State402.FAULT, State402.OPERATION_ENABLED)]
['0x80', '0x6', '0x7', '0xf']
>>> make_rpdo_target(5, CW_ENABLE_OPERATION, -2).data.hex()
'0f00feffffff'
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from types import MappingProxyType

import can
import numpy as np

from drivers.protocol.cia301 import (
    COB_RPDO1,
    COB_TPDO1,
    FrameError,
    check_node_id,
    data_frame,
)
from drivers.protocol.pdo import PdoEntry, PdoLayout
from hrm_ctrl.errors import DriverError

# ---------------------------------------------------------------- objects (0x6000..0x6FFF)
OD_ERROR_CODE = 0x603F
OD_CONTROLWORD = 0x6040
OD_STATUSWORD = 0x6041
OD_QUICK_STOP_OPTION_CODE = 0x605A
OD_MODES_OF_OPERATION = 0x6060
OD_MODES_OF_OPERATION_DISPLAY = 0x6061
OD_POSITION_ACTUAL_VALUE = 0x6064
OD_FOLLOWING_ERROR_WINDOW = 0x6065
OD_TARGET_POSITION = 0x607A
OD_QUICK_STOP_DECELERATION = 0x6085
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

# Quick stop option codes (0x605A): 0 disables the drive function at once; 1..4 slow down
# (1 ramp, 2 quick stop ramp, 3 current limit, 4 voltage limit) then switch on disabled;
# 5..8 slow down the same ways and stay in quick stop active.
QUICK_STOP_OPTION_DISABLE_DRIVE = 0
QUICK_STOP_OPTION_QUICK_STOP_RAMP_DISABLE = 2
QUICK_STOP_OPTION_QUICK_STOP_RAMP_STAY = 6
QUICK_STOP_OPTIONS_THEN_DISABLED = frozenset({1, 2, 3, 4})
QUICK_STOP_OPTIONS_STAY = frozenset({5, 6, 7, 8})

# EMCY error code of the CSP following error (CiA 402: 0x8611 following error).
EMCY_FOLLOWING_ERROR = 0x8611

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1

# ---------------------------------------------------------------- controlword (0x6040)
CW_BIT_SWITCH_ON = 0x0001
CW_BIT_ENABLE_VOLTAGE = 0x0002
CW_BIT_QUICK_STOP = 0x0004  # active low: 0 requests a quick stop
CW_BIT_ENABLE_OPERATION = 0x0008
CW_BIT_FAULT_RESET = 0x0080
CW_BIT_HALT = 0x0100


class Command402(Enum):
    """Device-control commands (CiA 402 table 31) as (mask, value) of the controlword bits
    7, 3, 2, 1, 0.  The masks partition every controlword: :func:`decode_command` finds
    exactly one.  *Disable operation* has the bits of *switch on* (an alias: transition 5
    is (OPERATION_ENABLED, SWITCH_ON)); the fault reset is the 0→1 edge of bit 7, which
    only a receiver that remembers the previous controlword can see."""

    SHUTDOWN = (0x0087, 0x0006)
    SWITCH_ON = (0x008F, 0x0007)
    DISABLE_OPERATION = (0x008F, 0x0007)  # alias of SWITCH_ON
    ENABLE_OPERATION = (0x008F, 0x000F)
    DISABLE_VOLTAGE = (0x0082, 0x0000)
    QUICK_STOP = (0x0086, 0x0002)
    FAULT_RESET = (0x0080, 0x0080)

    @property
    def mask(self) -> int:
        """Controlword bits the command is defined by."""
        return self.value[0]

    @property
    def controlword(self) -> int:
        """The controlword a host writes for this command (the other bits 0).

        >>> [hex(c.controlword) for c in Command402]
        ['0x6', '0x7', '0xf', '0x0', '0x2', '0x80']
        """
        return self.value[1]

    def matches(self, controlword: int) -> bool:
        """True when ``controlword`` carries this command (bits outside the mask ignored).

        >>> Command402.QUICK_STOP.matches(0x000B), Command402.QUICK_STOP.matches(0x0006)
        (True, False)
        """
        return controlword & self.mask == self.controlword


CW_SHUTDOWN = Command402.SHUTDOWN.controlword
CW_SWITCH_ON = Command402.SWITCH_ON.controlword
CW_DISABLE_VOLTAGE = Command402.DISABLE_VOLTAGE.controlword
CW_QUICK_STOP = Command402.QUICK_STOP.controlword
CW_DISABLE_OPERATION = Command402.DISABLE_OPERATION.controlword
CW_ENABLE_OPERATION = Command402.ENABLE_OPERATION.controlword
CW_FAULT_RESET = Command402.FAULT_RESET.controlword


def decode_command(controlword: int) -> Command402:
    """The device-control command a controlword carries (bit 7 set: FAULT_RESET).

    >>> [decode_command(w).name for w in (0x0000, 0x0002, 0x0006, 0x0007, 0x000F, 0x0080)]
    ['DISABLE_VOLTAGE', 'QUICK_STOP', 'SHUTDOWN', 'SWITCH_ON', 'ENABLE_OPERATION', 'FAULT_RESET']
    >>> decode_command(0x010E).name  # halt (bit 8) and bit 3 are outside SHUTDOWN's mask
    'SHUTDOWN'
    """
    return _COMMAND_OF_BITS[(controlword & 0x0F) | ((controlword >> 3) & 0x10)]


def _command_of_bits(bits: int) -> Command402:
    """The one command matching the controlword bits 7, 3, 2, 1, 0 packed as 4..0."""
    controlword = (bits & 0x0F) | ((bits & 0x10) << 3)
    found = [command for command in Command402 if command.matches(controlword)]
    if len(found) != 1:
        raise FrameError(f"controlword 0x{controlword:04X} matches commands {found}")
    return found[0]


# decode_command's lookup: the masks only look at bits 7, 3, 2, 1, 0 (checked at import).
_COMMAND_OF_BITS: tuple[Command402, ...] = tuple(_command_of_bits(b) for b in range(32))


# ---------------------------------------------------------------- statusword (0x6041)
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
STATUSWORD_OF_STATE: Mapping[State402, int] = MappingProxyType(
    {
        State402.NOT_READY_TO_SWITCH_ON: 0x0000,
        State402.SWITCH_ON_DISABLED: 0x0040,
        State402.READY_TO_SWITCH_ON: 0x0021,
        State402.SWITCHED_ON: 0x0023,
        State402.OPERATION_ENABLED: 0x0027,
        State402.QUICK_STOP_ACTIVE: 0x0007,
        State402.FAULT_REACTION_ACTIVE: 0x000F,
        State402.FAULT: 0x0008,
    }
)


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


# ---------------------------------------------------------------- the state machine
class TransitionError(DriverError):
    """A controlword command has no CiA 402 transition from a state, or a state cannot be
    reached by controlword commands."""


@dataclass(frozen=True)
class Transition:
    """One commanded transition of CiA 402 figure 13 (``numbers``: (3, 4) for the
    *switch on + enable operation* shortcut)."""

    numbers: tuple[int, ...]
    source: State402
    command: Command402
    target: State402

    @property
    def label(self) -> str:
        """The transition number(s) as CiA 402 writes them.

        >>> TRANSITIONS[3].label
        '3+4'
        """
        return "+".join(str(n) for n in self.numbers)


_S = State402
_C = Command402
TRANSITIONS: tuple[Transition, ...] = (
    Transition((2,), _S.SWITCH_ON_DISABLED, _C.SHUTDOWN, _S.READY_TO_SWITCH_ON),
    Transition((3,), _S.READY_TO_SWITCH_ON, _C.SWITCH_ON, _S.SWITCHED_ON),
    Transition((4,), _S.SWITCHED_ON, _C.ENABLE_OPERATION, _S.OPERATION_ENABLED),
    Transition((3, 4), _S.READY_TO_SWITCH_ON, _C.ENABLE_OPERATION, _S.OPERATION_ENABLED),
    Transition((5,), _S.OPERATION_ENABLED, _C.DISABLE_OPERATION, _S.SWITCHED_ON),
    Transition((6,), _S.SWITCHED_ON, _C.SHUTDOWN, _S.READY_TO_SWITCH_ON),
    Transition((7,), _S.READY_TO_SWITCH_ON, _C.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition((7,), _S.READY_TO_SWITCH_ON, _C.QUICK_STOP, _S.SWITCH_ON_DISABLED),
    Transition((8,), _S.OPERATION_ENABLED, _C.SHUTDOWN, _S.READY_TO_SWITCH_ON),
    Transition((9,), _S.OPERATION_ENABLED, _C.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition((10,), _S.SWITCHED_ON, _C.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition((10,), _S.SWITCHED_ON, _C.QUICK_STOP, _S.SWITCH_ON_DISABLED),
    Transition((11,), _S.OPERATION_ENABLED, _C.QUICK_STOP, _S.QUICK_STOP_ACTIVE),
    Transition((12,), _S.QUICK_STOP_ACTIVE, _C.DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    Transition((15,), _S.FAULT, _C.FAULT_RESET, _S.SWITCH_ON_DISABLED),
    # 16 only with a quick stop option code 5..8 once the motor stands still (the drive checks).
    Transition((16,), _S.QUICK_STOP_ACTIVE, _C.ENABLE_OPERATION, _S.OPERATION_ENABLED),
)
"""Every transition a controlword command triggers.  The others are automatic: 0 and 1
(power-on → SWITCH_ON_DISABLED), 12 after a quick stop with option 1..4, 13 (a fault →
FAULT_REACTION_ACTIVE) and 14 (fault reaction done → FAULT)."""

TRANSITION_TABLE: Mapping[tuple[State402, Command402], Transition] = MappingProxyType(
    {(t.source, t.command): t for t in TRANSITIONS}
)

AUTOMATIC_SUCCESSOR: Mapping[State402, State402] = MappingProxyType(
    {
        State402.NOT_READY_TO_SWITCH_ON: State402.SWITCH_ON_DISABLED,  # 1
        State402.FAULT_REACTION_ACTIVE: State402.FAULT,  # 14
    }
)
"""States a drive leaves by itself, to the state it reaches (no command accepted there)."""

LADDER: tuple[State402, ...] = (
    State402.SWITCH_ON_DISABLED,
    State402.READY_TO_SWITCH_ON,
    State402.SWITCHED_ON,
    State402.OPERATION_ENABLED,
)
"""The states a host steers a drive between, from power stage off to operation enabled."""

ROUTE_UP: Mapping[State402, Command402] = MappingProxyType(
    {
        State402.FAULT: Command402.FAULT_RESET,  # 15
        State402.QUICK_STOP_ACTIVE: Command402.DISABLE_VOLTAGE,  # 12 (never 16: stale target)
        State402.SWITCH_ON_DISABLED: Command402.SHUTDOWN,  # 2
        State402.READY_TO_SWITCH_ON: Command402.SWITCH_ON,  # 3
        State402.SWITCHED_ON: Command402.ENABLE_OPERATION,  # 4
    }
)
"""The command of each step towards OPERATION_ENABLED (canopen's ``NEXTSTATE2ANY``)."""

ROUTE_DOWN: Mapping[State402, Command402] = MappingProxyType(
    {
        State402.FAULT: Command402.FAULT_RESET,  # 15
        State402.QUICK_STOP_ACTIVE: Command402.DISABLE_VOLTAGE,  # 12
        State402.OPERATION_ENABLED: Command402.DISABLE_OPERATION,  # 5
        State402.SWITCHED_ON: Command402.SHUTDOWN,  # 6
        State402.READY_TO_SWITCH_ON: Command402.DISABLE_VOLTAGE,  # 7
    }
)
"""The command of each step of a controlled disable, one rung of :data:`LADDER` at a time."""


def has_transition(state: State402, command: Command402) -> bool:
    """True when ``command`` triggers a transition from ``state``.

    >>> has_transition(State402.OPERATION_ENABLED, Command402.ENABLE_OPERATION)
    False
    """
    return (state, command) in TRANSITION_TABLE


def transition(state: State402, command: Command402) -> Transition:
    """The transition ``command`` triggers from ``state``; :class:`TransitionError` if none.

    >>> transition(State402.OPERATION_ENABLED, Command402.QUICK_STOP).numbers
    (11,)
    >>> transition(State402.SWITCH_ON_DISABLED, Command402.ENABLE_OPERATION)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    drivers.protocol.cia402.TransitionError: no CiA 402 transition from SWITCH_ON_DISABLED on ...
    """
    found = TRANSITION_TABLE.get((state, command))
    if found is None:
        raise TransitionError(
            f"no CiA 402 transition from {state.name} on {command.name} "
            f"(controlword 0x{command.controlword:04X})"
        )
    return found


def next_state(state: State402, command: Command402) -> State402:
    """The state ``command`` leads to from ``state``; :class:`TransitionError` if none."""
    return transition(state, command).target


def route(state: State402, goal: State402) -> tuple[Transition, ...]:
    """The commanded transitions that bring a drive from ``state`` to ``goal`` (one of
    :data:`LADDER`): up by :data:`ROUTE_UP`, down by :data:`ROUTE_DOWN`; out of FAULT or
    QUICK_STOP_ACTIVE through SWITCH_ON_DISABLED.  Empty when ``state`` is ``goal``.

    >>> [t.label for t in route(State402.OPERATION_ENABLED, State402.READY_TO_SWITCH_ON)]
    ['5', '6']
    >>> route(State402.FAULT_REACTION_ACTIVE, State402.SWITCHED_ON)
    Traceback (most recent call last):
    ...
    drivers.protocol.cia402.TransitionError: no controlword command leaves FAULT_REACTION_ACTIVE
    """
    if goal not in LADDER:
        raise TransitionError(f"{goal.name} is not reached by controlword commands")
    steps: list[Transition] = []
    for _ in range(len(State402)):
        if state is goal:
            return tuple(steps)
        down = state in LADDER and LADDER.index(state) > LADDER.index(goal)
        command = (ROUTE_DOWN if down else ROUTE_UP).get(state)
        if command is None:
            raise TransitionError(f"no controlword command leaves {state.name}")
        step = transition(state, command)
        steps.append(step)
        state = step.target
    raise TransitionError(f"no route to {goal.name}: {[t.label for t in steps]}")


# ---------------------------------------------------------------- interpolation period
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


# ---------------------------------------------------------------- our PDO mapping
#: The setpoint RPDO1: controlword (UNSIGNED16), target position (INTEGER32).
RPDO_TARGET = PdoLayout(
    (
        PdoEntry("controlword", OD_CONTROLWORD, 0, "H"),
        PdoEntry("target", OD_TARGET_POSITION, 0, "i", "target position"),
    )
)
#: The feedback TPDO1: statusword (UNSIGNED16), position actual value (INTEGER32).
TPDO_FEEDBACK = PdoLayout(
    (
        PdoEntry("statusword", OD_STATUSWORD, 0, "H"),
        PdoEntry("position", OD_POSITION_ACTUAL_VALUE, 0, "i", "position actual value"),
    )
)
# what each layout gives, under the names the drivers use
RPDO_TARGET_LAYOUT = RPDO_TARGET.struct
TPDO_FEEDBACK_LAYOUT = TPDO_FEEDBACK.struct
RPDO_TARGET_DTYPE = RPDO_TARGET.dtype
TPDO_FEEDBACK_DTYPE = TPDO_FEEDBACK.dtype
RPDO_TARGET_MAPPING = RPDO_TARGET.mapping
TPDO_FEEDBACK_MAPPING = TPDO_FEEDBACK.mapping
RPDO_TARGET_SIZE = RPDO_TARGET.size
TPDO_FEEDBACK_SIZE = TPDO_FEEDBACK.size


def make_rpdo_target_payloads(controlwords: np.ndarray, targets: np.ndarray) -> bytes:
    """RPDO1 payloads for many nodes at once: 6 bytes per node, concatenated.

    >>> make_rpdo_target_payloads(np.array([15, 2]), np.array([1, -1])).hex()
    '0f00010000000200ffffffff'
    """
    return RPDO_TARGET.pack_many(controlword=controlwords, target=targets)


def make_rpdo_target(node_id: int, controlword: int, target_counts: int) -> can.Message:
    """RPDO1 (COB-ID 0x200 + node id): controlword then target position, little-endian.

    >>> m = make_rpdo_target(3, CW_QUICK_STOP, 0x01020304)
    >>> hex(m.arbitration_id), m.data.hex()
    ('0x203', '020004030201')
    """
    check_node_id(node_id)
    return data_frame(COB_RPDO1 + node_id, RPDO_TARGET.pack(controlword, target_counts))


def make_tpdo_feedback(node_id: int, statusword: int, position_counts: int) -> can.Message:
    """TPDO1 (COB-ID 0x180 + node id): statusword then position actual value.

    >>> make_tpdo_feedback(4, 0x0237, -5).data.hex()
    '3702fbffffff'
    """
    check_node_id(node_id)
    return data_frame(COB_TPDO1 + node_id, TPDO_FEEDBACK.pack(statusword, position_counts))


def parse_rpdo_target(data: bytes | bytearray) -> tuple[int, int]:
    """(controlword, target position) from an RPDO1 payload.

    >>> parse_rpdo_target(bytes.fromhex('0f00feffffff'))
    (15, -2)
    """
    if len(data) != RPDO_TARGET_SIZE:
        raise FrameError(f"RPDO1 must carry {RPDO_TARGET_SIZE} bytes, got {len(data)}")
    cw, target = RPDO_TARGET.unpack(data)
    return int(cw), int(target)  # type: ignore[call-overload]


def parse_tpdo(data: bytes | bytearray) -> tuple[int, int]:
    """(statusword, position actual value) from a TPDO1 payload.

    >>> parse_tpdo(bytes.fromhex('3702fbffffff'))
    (567, -5)
    """
    if len(data) != TPDO_FEEDBACK_SIZE:
        raise FrameError(f"TPDO1 must carry {TPDO_FEEDBACK_SIZE} bytes, got {len(data)}")
    sw, pos = TPDO_FEEDBACK.unpack(data)
    return int(sw), int(pos)  # type: ignore[call-overload]
