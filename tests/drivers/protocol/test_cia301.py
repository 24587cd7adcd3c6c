"""Frame builders and parsers of drivers.protocol.cia301, byte for byte."""

from __future__ import annotations

import pytest
from canopen.sdo.exceptions import SdoAbortedError

from drivers.protocol import cia301 as c
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


def test_consumer_heartbeat_entry() -> None:
    assert c.consumer_heartbeat_entry(0x7F, 300) == 0x007F012C


def test_cob_id_parts_and_data_frame() -> None:
    assert (c.node_id_of(0x77F), c.function_code_of(0x77F)) == (0x7F, c.COB_NMT_ERROR_CONTROL)
    m = c.data_frame(c.COB_SDO_TX + 3, b"\x60\x40\x60\x00")
    assert (m.arbitration_id, bytes(m.data), m.is_extended_id, m.dlc) == (
        0x583,
        b"\x60\x40\x60\x00",
        False,
        4,
    )
    assert c.pdo_mapping_entry(0x6040, 0, 16) == 0x60400010
    assert c.parse_pdo_mapping_entry(0x607A0020) == (0x607A, 0, 32)


ABORT_CODES = {name: v for name, v in vars(c).items() if name.startswith("SDO_ABORT_")}
ABORT_CODES.pop("SDO_ABORT_TEXTS")


def test_every_abort_code_has_canopens_text() -> None:
    assert len(ABORT_CODES) == 31  # CiA 301 table 22
    for name, code in ABORT_CODES.items():
        assert code in SdoAbortedError.CODES, name
        assert c.describe_sdo_abort(code) == f"0x{code:08X} ({SdoAbortedError.CODES[code]})"
    assert c.describe_sdo_abort(0x06090030) == "0x06090030 (Value range of parameter exceeded)"
    assert c.describe_sdo_abort(0x01020304) == "0x01020304 (unknown abort code)"


@pytest.mark.parametrize(
    "bad",
    [
        lambda: c.make_nmt(0x33, 1),
        lambda: c.make_nmt(c.NMT_RESET_NODE, 128),
        lambda: c.make_heartbeat(0, c.NMT_STATE_OPERATIONAL),
        lambda: c.make_heartbeat(1, 0x33),
        lambda: c.parse_emcy(1, b"\x00" * 7),
        lambda: c.make_emcy(1, 0x1000, 0, b"\x00" * 6),
        lambda: c.parse_heartbeat(b""),
        lambda: c.parse_heartbeat(b"\x85"),  # bit 7: a node-guarding reply, not a heartbeat
        lambda: c.parse_heartbeat(b"\x01"),  # no NMT state
        lambda: c.make_sync(0),
        lambda: c.parse_sdo_abort(b"\x60" + b"\x00" * 7),
        lambda: c.make_sdo_download_expedited(1, 0x6040, 0, b""),
        lambda: c.consumer_heartbeat_entry(0x7F, 70_000),
        lambda: c.check_node_id(True),  # type: ignore[arg-type]
    ],
)
def test_bad_frames_raise_driver_error(bad) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(DriverError):
        bad()
