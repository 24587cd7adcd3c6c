"""drivers.protocol.cia402 byte for byte: PDO payloads, statusword, the transition table."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.protocol import cia402 as c
from hrm_ctrl.errors import DriverError


def test_rpdo_tpdo_frames() -> None:
    m = c.make_rpdo_target(0x10, c.CW_ENABLE_OPERATION, 100_000)
    assert m.arbitration_id == 0x210
    assert bytes(m.data) == bytes([0x0F, 0x00, 0xA0, 0x86, 0x01, 0x00])
    t = c.make_tpdo_feedback(0x10, 0x1237, -100_000)
    assert t.arbitration_id == 0x190
    assert bytes(t.data) == bytes([0x37, 0x12, 0x60, 0x79, 0xFE, 0xFF])
    assert c.parse_tpdo(t.data) == (0x1237, -100_000)
    payloads = c.make_rpdo_target_payloads(np.array([15, 15]), np.array([100_000, -1]))
    assert payloads == bytes(m.data) + bytes([0x0F, 0x00, 0xFF, 0xFF, 0xFF, 0xFF])


@given(
    node=st.integers(1, 127),
    cw=st.integers(0, 0xFFFF),
    target=st.integers(c.INT32_MIN, c.INT32_MAX),
)
def test_rpdo_round_trip(node: int, cw: int, target: int) -> None:
    m = c.make_rpdo_target(node, cw, target)
    assert m.arbitration_id == 0x200 + node and len(m.data) == 6
    assert c.parse_rpdo_target(m.data) == (cw, target)
    assert c.make_rpdo_target_payloads(np.array([cw]), np.array([target])) == bytes(m.data)


def test_mapping_and_interpolation_values() -> None:
    assert c.RPDO_TARGET_MAPPING == (0x60400010, 0x607A0020)
    assert c.TPDO_FEEDBACK_MAPPING == (0x60410010, 0x60640020)
    assert c.interpolation_time_period(0.01) == (10, -3)
    assert c.interpolation_time_period(0.001) == (1, -3)
    assert c.interpolation_time_period(0.0005) == (5, -4)


@pytest.mark.parametrize(
    ("statusword", "state"),
    [
        (0x0000, c.State402.NOT_READY_TO_SWITCH_ON),
        (0x0040, c.State402.SWITCH_ON_DISABLED),
        (0x0250, c.State402.SWITCH_ON_DISABLED),
        (0x0021, c.State402.READY_TO_SWITCH_ON),
        (0x0031, c.State402.READY_TO_SWITCH_ON),
        (0x0023, c.State402.SWITCHED_ON),
        (0x0027, c.State402.OPERATION_ENABLED),
        (0x1637, c.State402.OPERATION_ENABLED),
        (0x0007, c.State402.QUICK_STOP_ACTIVE),
        (0x0017, c.State402.QUICK_STOP_ACTIVE),
        (0x000F, c.State402.FAULT_REACTION_ACTIVE),
        (0x0008, c.State402.FAULT),
        (0x0218, c.State402.FAULT),
    ],
)
def test_decode_state(statusword: int, state: c.State402) -> None:
    assert c.decode_state(statusword) is state
    assert c.decode_states(np.array([statusword]))[0] == int(state)
    assert c.decode_state(c.STATUSWORD_OF_STATE.get(state, statusword)) is state


@given(st.integers(0, 0xFFFF))
def test_decode_states_matches_scalar(sw: int) -> None:
    assert c.decode_states(np.array([sw]))[0] == int(c.decode_state(sw))


def test_controlword_commands_per_cia402() -> None:
    assert (c.CW_SHUTDOWN, c.CW_SWITCH_ON, c.CW_ENABLE_OPERATION) == (0x06, 0x07, 0x0F)
    assert (c.CW_DISABLE_VOLTAGE, c.CW_QUICK_STOP, c.CW_FAULT_RESET) == (0x00, 0x02, 0x80)
    assert c.MODE_CSP == 8


@pytest.mark.parametrize(
    "bad",
    [
        lambda: c.make_rpdo_target(0, 0, 0),
        lambda: c.make_rpdo_target(1, 0, 2**31),
        lambda: c.parse_tpdo(b"\x00" * 5),
        lambda: c.parse_rpdo_target(b"\x00" * 7),
        lambda: c.make_rpdo_target_payloads(np.array([0]), np.array([2**31])),
        lambda: c.make_tpdo_feedback(128, 0, 0),
        lambda: c.interpolation_time_period(0.0),
    ],
)
def test_bad_frames_raise_driver_error(bad) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(DriverError):
        bad()


# ---------------------------------------------------------------- the transition table
S = c.State402
C = c.Command402

# (mask, controlword) of each device-control command, CiA 402 table 31 (bits 7, 3, 2, 1, 0).
COMMAND_BITS = {
    C.SHUTDOWN: (0x87, 0x06),
    C.SWITCH_ON: (0x8F, 0x07),
    C.ENABLE_OPERATION: (0x8F, 0x0F),
    C.DISABLE_VOLTAGE: (0x82, 0x00),
    C.QUICK_STOP: (0x86, 0x02),
    C.FAULT_RESET: (0x80, 0x80),
}

# Every commanded transition of CiA 402 figure 13: (number, state, controlword) -> next state.
LEGAL = [
    ("2", S.SWITCH_ON_DISABLED, 0x0006, S.READY_TO_SWITCH_ON),
    ("3", S.READY_TO_SWITCH_ON, 0x0007, S.SWITCHED_ON),
    ("4", S.SWITCHED_ON, 0x000F, S.OPERATION_ENABLED),
    ("3+4", S.READY_TO_SWITCH_ON, 0x000F, S.OPERATION_ENABLED),
    ("5", S.OPERATION_ENABLED, 0x0007, S.SWITCHED_ON),
    ("6", S.SWITCHED_ON, 0x0006, S.READY_TO_SWITCH_ON),
    ("7", S.READY_TO_SWITCH_ON, 0x0000, S.SWITCH_ON_DISABLED),
    ("7", S.READY_TO_SWITCH_ON, 0x0002, S.SWITCH_ON_DISABLED),
    ("8", S.OPERATION_ENABLED, 0x0006, S.READY_TO_SWITCH_ON),
    ("9", S.OPERATION_ENABLED, 0x0000, S.SWITCH_ON_DISABLED),
    ("10", S.SWITCHED_ON, 0x0000, S.SWITCH_ON_DISABLED),
    ("10", S.SWITCHED_ON, 0x0002, S.SWITCH_ON_DISABLED),
    ("11", S.OPERATION_ENABLED, 0x0002, S.QUICK_STOP_ACTIVE),
    ("12", S.QUICK_STOP_ACTIVE, 0x0000, S.SWITCH_ON_DISABLED),
    ("15", S.FAULT, 0x0080, S.SWITCH_ON_DISABLED),
    ("16", S.QUICK_STOP_ACTIVE, 0x000F, S.OPERATION_ENABLED),
]


def test_command_masks_and_controlwords() -> None:
    assert {cmd: (cmd.mask, cmd.controlword) for cmd in C} == COMMAND_BITS
    assert C.DISABLE_OPERATION is C.SWITCH_ON  # same bits: transition 5 is (enabled, switch on)
    assert c.CW_DISABLE_OPERATION == c.CW_SWITCH_ON == 0x07


def test_every_controlword_carries_exactly_one_command() -> None:
    for cw in range(0x10000):
        matching = [cmd for cmd in C if cmd.matches(cw)]
        assert matching == [c.decode_command(cw)], hex(cw)
    assert c.decode_command(0x008F) is C.FAULT_RESET  # bit 7 wins whatever the low bits
    assert c.decode_command(0x010B) is C.QUICK_STOP  # halt, bits 3 and 0 are outside its mask


@pytest.mark.parametrize(("number", "state", "controlword", "target"), LEGAL)
def test_every_legal_transition(number: str, state: S, controlword: int, target: S) -> None:
    command = c.decode_command(controlword)
    assert command.controlword == controlword
    t = c.transition(state, command)
    assert (t.label, t.source, t.command, t.target) == (number, state, command, target)
    assert c.next_state(state, command) is target
    assert c.has_transition(state, command)


def test_the_table_is_exactly_the_legal_transitions() -> None:
    assert len(c.TRANSITIONS) == len(LEGAL) == len(c.TRANSITION_TABLE)
    assert {(s, c.decode_command(w)): t for _n, s, w, t in LEGAL} == {
        key: t.target for key, t in c.TRANSITION_TABLE.items()
    }


def test_refused_transitions_raise() -> None:
    with pytest.raises(c.TransitionError, match="SWITCH_ON_DISABLED on ENABLE_OPERATION"):
        c.next_state(S.SWITCH_ON_DISABLED, C.ENABLE_OPERATION)
    refused = 0
    for state in S:
        for command in C:
            if (state, command) in c.TRANSITION_TABLE:
                continue
            refused += 1
            assert not c.has_transition(state, command)
            with pytest.raises(c.TransitionError, match=f"from {state.name} on {command.name}"):
                c.transition(state, command)
    assert refused == len(S) * len(C) - len(LEGAL)
    assert isinstance(c.TransitionError("x"), DriverError)


def test_table_agrees_with_canopens_p402() -> None:
    from canopen.profiles.p402 import State402 as CanopenState402

    automatic = {
        ("START", "NOT READY TO SWITCH ON"),
        ("NOT READY TO SWITCH ON", "SWITCH ON DISABLED"),
    }
    automatic.add(("FAULT REACTION ACTIVE", "FAULT"))
    checked = 0
    for (src, dst), cw in CanopenState402.TRANSITIONTABLE.items():
        if (src, dst) in automatic:
            continue
        state, target = S[src.replace(" ", "_")], S[dst.replace(" ", "_")]
        assert c.next_state(state, c.decode_command(cw)) is target, (src, dst)
        checked += 1
    assert checked == 13  # canopen lacks the second ways of 7 and 10 and the 3+4 shortcut


@pytest.mark.parametrize(
    ("start", "goal", "controlwords", "labels"),
    [
        (S.SWITCH_ON_DISABLED, S.OPERATION_ENABLED, [0x06, 0x07, 0x0F], ["2", "3", "4"]),
        (S.FAULT, S.OPERATION_ENABLED, [0x80, 0x06, 0x07, 0x0F], ["15", "2", "3", "4"]),
        (S.QUICK_STOP_ACTIVE, S.SWITCHED_ON, [0x00, 0x06, 0x07], ["12", "2", "3"]),
        (S.OPERATION_ENABLED, S.SWITCHED_ON, [0x07], ["5"]),
        (S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON, [0x07, 0x06], ["5", "6"]),
        (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED, [0x07, 0x06, 0x00], ["5", "6", "7"]),
        (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, [0x07], ["3"]),
        (S.SWITCHED_ON, S.SWITCHED_ON, [], []),
    ],
)
def test_route(start: S, goal: S, controlwords: list[int], labels: list[str]) -> None:
    steps = c.route(start, goal)
    assert [t.command.controlword for t in steps] == controlwords
    assert [t.label for t in steps] == labels
    if steps:
        assert steps[0].source is start and steps[-1].target is goal


def test_route_refuses_what_no_command_reaches() -> None:
    for state in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE, S.UNKNOWN):
        with pytest.raises(c.TransitionError, match=f"no controlword command leaves {state.name}"):
            c.route(state, S.OPERATION_ENABLED)
    for goal in (S.FAULT, S.QUICK_STOP_ACTIVE, S.NOT_READY_TO_SWITCH_ON):
        with pytest.raises(c.TransitionError, match="not reached by controlword commands"):
            c.route(S.SWITCHED_ON, goal)
    assert dict(c.AUTOMATIC_SUCCESSOR) == {
        S.NOT_READY_TO_SWITCH_ON: S.SWITCH_ON_DISABLED,
        S.FAULT_REACTION_ACTIVE: S.FAULT,
    }
