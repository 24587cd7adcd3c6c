"""Frame builders and parsers of drivers.protocol.cia402, byte for byte."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.protocol import cia402 as c
from hrm_ctrl.errors import DriverError


def test_nmt_frames_byte_for_byte() -> None:
    assert c.make_nmt(c.NMT_RESET_NODE).data == b"\x81\x00"
    assert c.make_nmt(c.NMT_START_REMOTE_NODE, 5).data == b"\x01\x05"
    assert c.make_nmt(c.NMT_ENTER_PRE_OPERATIONAL, 127).data == b"\x80\x7f"
    assert c.make_nmt(c.NMT_STOP_REMOTE_NODE, 1).arbitration_id == 0
    assert c.make_nmt(c.NMT_RESET_COMMUNICATION, 0).data == b"\x82\x00"
    assert not c.make_nmt(c.NMT_RESET_NODE).is_extended_id


def test_sync_heartbeat_frames() -> None:
    assert (c.make_sync().arbitration_id, bytes(c.make_sync().data)) == (0x80, b"")
    assert bytes(c.make_sync(240).data) == b"\xf0"
    hb = c.make_heartbeat(0x7F, c.NMT_STATE_OPERATIONAL)
    assert (hb.arbitration_id, bytes(hb.data)) == (0x77F, b"\x05")
    boot = c.make_heartbeat(9, c.NMT_STATE_BOOTUP)
    assert (boot.arbitration_id, bytes(boot.data)) == (0x709, b"\x00")
    assert c.parse_heartbeat(b"\x7f") == c.NMT_STATE_PRE_OPERATIONAL


def test_rpdo_tpdo_frames() -> None:
    m = c.make_rpdo_target(0x10, c.ENABLE_OPERATION, 100_000)
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


def test_emcy_and_sdo_frames() -> None:
    e = c.make_emcy(7, 0x8130, 0x11, b"\x01\x02")
    assert (e.arbitration_id, bytes(e.data)) == (0x87, bytes.fromhex("3081110102000000"))
    emcy = c.parse_emcy(7, e.data)
    assert (emcy.error_code, emcy.error_register, emcy.manufacturer) == (
        0x8130,
        0x11,
        b"\x01\x02\x00\x00\x00",
    )
    d = c.make_sdo_download_expedited(2, 0x1017, 0, (100).to_bytes(2, "little"))
    assert (d.arbitration_id, bytes(d.data)) == (0x602, bytes.fromhex("2b17100064000000"))
    d4 = c.make_sdo_download_expedited(2, 0x607D, 1, (-5).to_bytes(4, "little", signed=True))
    assert bytes(d4.data) == bytes.fromhex("237d6001fbffffff")
    u = c.make_sdo_upload_request(2, 0x6041, 0)
    assert (u.arbitration_id, bytes(u.data)) == (0x602, bytes.fromhex("4041600000000000"))
    a = c.make_sdo_abort(2, 0x6060, 0, c.SDO_ABORT_INVALID_VALUE)
    assert (a.arbitration_id, bytes(a.data)) == (0x582, bytes.fromhex("8060600030000906"))
    assert c.parse_sdo_abort(a.data) == (0x6060, 0, 0x06090030)


def test_mapping_heartbeat_and_interpolation_values() -> None:
    assert c.RPDO_TARGET_MAPPING == (0x60400010, 0x607A0020)
    assert c.TPDO_FEEDBACK_MAPPING == (0x60410010, 0x60640020)
    assert c.consumer_heartbeat_entry(0x7F, 300) == 0x007F012C
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
    assert (c.SHUTDOWN, c.SWITCH_ON, c.ENABLE_OPERATION) == (0x06, 0x07, 0x0F)
    assert (c.DISABLE_VOLTAGE, c.QUICK_STOP, c.FAULT_RESET) == (0x00, 0x02, 0x80)
    assert c.MODE_CSP == 8


@pytest.mark.parametrize(
    "bad",
    [
        lambda: c.make_nmt(0x33, 1),
        lambda: c.make_nmt(c.NMT_RESET_NODE, 128),
        lambda: c.make_rpdo_target(0, 0, 0),
        lambda: c.make_rpdo_target(1, 0, 2**31),
        lambda: c.parse_tpdo(b"\x00" * 5),
        lambda: c.parse_emcy(1, b"\x00" * 7),
        lambda: c.parse_heartbeat(b""),
        lambda: c.make_sync(0),
        lambda: c.parse_sdo_abort(b"\x60" + b"\x00" * 7),
        lambda: c.interpolation_time_period(0.0),
    ],
)
def test_bad_frames_raise_driver_error(bad) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(DriverError):
        bad()
