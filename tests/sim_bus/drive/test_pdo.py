"""sim_bus/drive/pdo.py: the simulated drive compiles its PDO mappings into the host's
layouts, so the host's RPDO bytes are what the drive applies and the drive's TPDO bytes
are what the host parses, byte for byte."""

from __future__ import annotations

import struct

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.protocol import batch, cia301, cia402
from tests.sim_bus.drive.test_drive import NODE, Rig, abort_code

I32 = st.integers(-(10**6), 10**6)


def test_the_drive_compiles_its_default_mappings_into_the_host_layouts() -> None:
    r = Rig()
    assert r.d.pdo.layout(cia301.OD_RPDO1_MAPPING) == cia402.RPDO_TARGET
    assert r.d.pdo.layout(cia301.OD_TPDO1_MAPPING) == cia402.TPDO_FEEDBACK


@settings(max_examples=40, deadline=None)
@given(I32)
def test_host_rpdo_bytes_are_what_the_drive_applies_and_its_tpdo_what_the_host_reads(
    target: int,
) -> None:
    r = Rig(vmax=1e9, amax=1e12)
    r.operational()
    r.enable()
    host = cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, target)
    r.rx(host)
    r.sync()
    assert r.d.od.int_value(cia402.OD_TARGET_POSITION) == target
    assert r.d.od.int_value(cia402.OD_CONTROLWORD) == cia402.CW_ENABLE_OPERATION
    out = [m for m in r.sync() if m.arbitration_id == 0x180 + NODE]
    sw, pos = r.d.statusword, r.d.live_value((cia402.OD_POSITION_ACTUAL_VALUE, 0))
    # the drive's TPDO: the host's own encoding of what the drive reports
    assert bytes(out[0].data) == cia402.TPDO_FEEDBACK.pack(sw, pos)
    v = batch.from_messages(out).view(batch.TPDO_VIEW)[0]
    assert (int(v["statusword"]), int(v["position"])) == cia402.parse_tpdo(out[0].data)
    assert int(v["position"]) == pos


def test_a_remapped_rpdo_is_compiled_from_the_drive_objects() -> None:
    r = Rig(vmax=1e7, amax=1e10)
    assert r.write(0x1400, 1, struct.pack("<I", 0x80000205))[0] == 0x60
    assert r.write(0x1600, 0, b"\x00")[0] == 0x60
    assert r.write(0x1600, 1, struct.pack("<I", 0x607A0020))[0] == 0x60
    assert r.write(0x1600, 0, b"\x01")[0] == 0x60
    layout = r.d.pdo.layout(cia301.OD_RPDO1_MAPPING)
    assert layout.mapping == (0x607A0020,) and layout.codes == "<i"
    assert layout.pack(-5) == can.Message(data=struct.pack("<i", -5)).data


def _disabled(r: Rig, comm: int) -> None:
    """PDO ``comm`` invalid and its mapping emptied: entries may be written."""
    cob = r.d.od.int_value(comm, 1)
    assert r.write(comm, 1, struct.pack("<I", cob | cia301.PDO_COB_ID_INVALID))[0] == 0x60
    assert r.write(comm + 0x200, 0, b"\x00")[0] == 0x60


@pytest.mark.parametrize(
    ("mapping", "entry", "code"),
    [
        (0x1600, 0x60770010, cia301.SDO_ABORT_NO_OBJECT),  # torque actual: not in the EDS
        (0x1A00, 0x60770010, cia301.SDO_ABORT_NO_OBJECT),
        (0x1600, 0x60C20108, cia301.SDO_ABORT_NOT_MAPPABLE),  # interpolation period value
        (0x1600, 0x60640020, cia301.SDO_ABORT_NOT_MAPPABLE),  # read-only, in an RPDO
        (0x1600, 0x607A0010, cia301.SDO_ABORT_NOT_MAPPABLE),  # 16 of the object's 32 bits
        (0x1600, 0x10170010, cia301.SDO_ABORT_NOT_MAPPABLE),  # heartbeat time: not mappable
        (0x1600, 0x60400910, cia301.SDO_ABORT_NO_SUBINDEX),  # controlword has no sub 9
        (0x1A00, 0x00050020, cia301.SDO_ABORT_NO_OBJECT),  # a dummy: the drive has none
    ],
)
def test_an_unmappable_entry_is_refused_as_it_is_written(
    mapping: int, entry: int, code: int
) -> None:
    r = Rig()
    _disabled(r, mapping - 0x200)
    assert abort_code(r.write(mapping, 1, struct.pack("<I", entry))) == code
    # nothing was stored: the entry keeps its value and the empty mapping can be set up
    assert r.d.od.int_value(mapping, 1) != entry
    assert (
        r.write(mapping, 1, struct.pack("<I", 0x60640020 if mapping == 0x1A00 else 0x607A0020))[0]
        == 0x60
    )
    assert r.write(mapping, 0, b"\x01")[0] == 0x60


def test_mappable_entries_and_an_empty_entry_are_accepted() -> None:
    r = Rig()
    _disabled(r, 0x1800)
    for k, entry in enumerate((0x60410010, 0x60640020, 0x10010008, 0), start=1):
        assert r.write(0x1A00, k, struct.pack("<I", entry))[0] == 0x60
    assert r.write(0x1A00, 0, b"\x03")[0] == 0x60
    assert r.d.pdo.layout(cia301.OD_TPDO1_MAPPING).mapping == (0x60410010, 0x60640020, 0x10010008)
