"""The CiA 306 device-file reader: the six vendor files and ours read as the standard
allows; malformed or hostile input gets one line naming file, section and key."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers import eds_path
from drivers.protocol.cia306 import (
    MAX_FILE_BYTES,
    Access,
    DataType,
    DeviceFileError,
    format_device_file,
    parse_device_file,
    read_device_file,
)

VENDOR = Path(__file__).parents[1] / "vendor_eds"
EPOS4 = VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"
EPOS2 = VENDOR / "epos2_347717.eds"
C5E = VENDOR / "C5-E-2-09.eds"
FAULHABER = VENDOR / "605.3150.68-B-EK-2-60.eds"
TECHNOSOFT = VENDOR / "technosoft.eds"
PRBT = VENDOR / "prbt_0_1.dcf"
ALL = [EPOS4, EPOS2, C5E, FAULHABER, TECHNOSOFT, PRBT]


@pytest.mark.parametrize("path", ALL, ids=lambda p: p.name)
def test_every_vendor_file_reads(path: Path) -> None:
    f = read_device_file(path)
    assert f.entry(0x6041) is not None and f.entry(0x1000) is not None
    assert f.device.nr_of_rxpdo is not None and f.device.nr_of_rxpdo >= 2


def test_our_own_eds_reads_as_canopen_reads_it() -> None:
    import canopen

    ours = read_device_file(eds_path())
    od = canopen.import_od(str(eds_path()), 7)
    for obj in ours.objects.values():
        for sub, e in obj.entries.items():
            var = od[obj.index] if obj.object_type.name == "VAR" else od[obj.index][sub]
            assert ours.value(obj.index, sub, node_id=7) == var.default, (obj.index, sub)
            assert e.data_type == var.data_type


def test_epos2_integer8_0xfd_is_minus_3() -> None:
    """EPOS2's 0x60C2sub2 ``DefaultValue=0xFD`` with ``LowLimit=HighLimit=0xFD``: -3
    (python-canopen reads 253)."""
    e = read_device_file(EPOS2).entry(0x60C2, 2)
    assert e is not None
    assert (e.data_type, e.default, e.low, e.high) == (DataType.INTEGER8, -3, -3, -3)


def test_dcf_parameter_value_over_default() -> None:
    f = read_device_file(EPOS4)
    assert f.is_dcf and f.node_id == 1
    e = f.entry(0x6502)
    assert e is not None and e.default is None and e.parameter == 0x3A5
    assert f.value(0x6502) == 0x3A5
    prbt = read_device_file(PRBT)
    sub1 = prbt.entry(0x60C2, 1)
    assert sub1 is not None and (sub1.default, sub1.parameter, sub1.value) == (8, 10, 10)


def test_tool_sections_and_manufacturer_objects() -> None:
    f = read_device_file(EPOS4)  # [ToolInfos]
    assert any(0x2000 <= i <= 0x5FFF for i in f.objects)
    assert read_device_file(TECHNOSOFT).entry(0x1016) is None  # node guarding instead
    assert read_device_file(TECHNOSOFT).entry(0x100C) is not None


def test_prbt_miscounted_manufacturer_record_noted() -> None:
    f = read_device_file(PRBT)
    assert f.quirks and f.quirks[0].startswith("[20A0] SubNumber: 8, but the file has 1")


def test_access_types() -> None:
    assert Access.RWW.writable and Access.RWR.writable and not Access.CONST.writable
    assert not Access.WO.readable


def _one_line(text: str, source: str = "t.eds") -> str:
    with pytest.raises(DeviceFileError) as info:
        parse_device_file(text, source)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{source}: ")
    return msg


T = "t.eds: [6065] "


def V(dt: str, acc: str, v: str) -> str:
    return VAR.format(dt=dt, acc=acc, v=v)


VAR = "[6065]\nParameterName=x\nObjectType=0x7\nDataType={dt}\nAccessType={acc}\nDefaultValue={v}\n"


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (V("0x0099", "rw", "1"), T + "DataType: unknown data type 0x0099"),
        (V("0x0007", "rx", "1"), T + "AccessType: unknown access type 'rx'"),
        (V("0x0005", "rw", "256"), T + "DefaultValue: 256 outside UNSIGNED8 (0..255)"),
        (V("0x0002", "rw", "253"), T + "DefaultValue: 253 outside INTEGER8 (-128..127)"),
        (V("0x0007", "rw", "-1"), T + "DefaultValue: -1 outside UNSIGNED32"),
        (V("0x0007", "rw", "12z"), T + "DefaultValue: '12z' is not an integer"),
        (V("0x0008", "rw", "nan"), T + "DefaultValue: 'nan' is not a finite REAL32"),
        ("[1600]\nObjectType=0x9\nSubNumber=3\n[1600sub0]\nDataType=5\nAccessType=rw\n",
         "t.eds: [1600] SubNumber: 3, but the file has 1 sub-index sections"),
        ("[1600sub0]\nDataType=5\nAccessType=rw\n", "t.eds: [1600sub0]: no [1600] section for it"),
        ("[1000]\nDataType=7\n[1000]\n", "t.eds: [1000]: section given twice"),
        ("[1000]\nDataType=7\nDataType=7\n", "t.eds: [1000] DataType: key given twice"),
        ("[1000]\nDataType=7\n", "t.eds: [1000] AccessType: missing"),
        ("garbage\n", "t.eds: line 1: expected KEY=VALUE"),
        ("a=1\n", "t.eds: line 1: a before any [SECTION]"),
        ("[1000\n", "t.eds: line 1: expected [SECTION]"),
        ("[OptionalObjects]\nSupportedObjects=0x1\n1=0x6065\n",
         "t.eds: [OptionalObjects] 1: object 6065 is listed but has no section"),
        ("[DeviceComissioning]\nNodeID=200\n", "t.eds: [DeviceComissioning] NodeID: node id 200"),
        ("[1000]\n\0\0", "t.eds: line 2: NUL byte"),
        (V("7", "rw", "5") + "LowLimit=10\n",
         T + "DefaultValue: 5 outside LowLimit..HighLimit (10..None)"),
        (V("7", "rw", "5") + "ParameterValue=0x1000\nHighLimit=100\n",
         T + "ParameterValue: 0x1000 outside LowLimit..HighLimit (None..100)"),
        ("[1000]\nObjectType=0x8\nCompactSubObj=3\nDataType=7\nAccessType=ro\n",
         "t.eds: [1000] CompactSubObj: not supported"),
    ],
)  # fmt: skip
def test_bad_input_one_line(text: str, expected: str) -> None:
    assert _one_line(text).startswith(expected)


def test_dcf_parameter_value_out_of_type() -> None:
    text = V("0x0006", "rw", "1") + "ParameterValue=70000\n"
    assert "ParameterValue: 70000 outside UNSIGNED16" in _one_line(text)


def test_large_and_binary_files_refused(tmp_path: Path) -> None:
    big = tmp_path / "big.eds"
    big.write_bytes(b"[1000]\n" + b";" * (MAX_FILE_BYTES + 10))
    with pytest.raises(DeviceFileError, match=r"big.eds: device file is larger than"):
        read_device_file(big)
    binary = tmp_path / "bin.eds"
    binary.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(DeviceFileError, match=r"bin.eds: "):
        read_device_file(binary)
    with pytest.raises(DeviceFileError, match=r"none.eds: device file not found"):
        read_device_file(tmp_path / "none.eds")


_keys = st.sampled_from(
    ["ParameterName", "ObjectType", "DataType", "AccessType", "DefaultValue", "PDOMapping",
     "LowLimit", "HighLimit", "ParameterValue", "SubNumber", "SupportedObjects", "1", "2",
     "NodeID", "NrOfRXPDO", "CompactSubObj", "x"]
)  # fmt: skip
_values = st.one_of(
    st.sampled_from(["0x7", "0x8", "0x9", "7", "0x0002", "0xFD", "-3", "$NODEID+0x180", "rw",
                     "ro", "const", "rww", "1", "0", "", "0x1FFFFFFFFFFFFFFFFFFFF", "1e9999",
                     "0x6041", "$NODEID+$NODEID", "08", "0x"]),
    st.text(max_size=30),
)  # fmt: skip
_section_names = st.one_of(
    st.sampled_from(["1000", "1400", "1400sub0", "1400sub1", "1400sub2", "6502", "60C2sub2",
                     "DeviceInfo", "OptionalObjects", "ManufacturerObjects", "ToolInfos",
                     "DeviceComissioning", "2000", "2000sub1", "1000Name"]),
    st.text(max_size=12),
)  # fmt: skip
_sections = st.lists(
    st.tuples(_section_names, st.lists(st.tuples(_keys, _values), max_size=8)), max_size=8
)


@settings(max_examples=300)
@given(sections=_sections, garbage=st.text(max_size=20))
def test_random_files_raise_only_the_one_line_error(
    sections: list[tuple[str, list[tuple[str, str]]]], garbage: str
) -> None:
    lines = []
    for name, keys in sections:
        lines.append(f"[{name}]")
        lines.extend(f"{k}={v}" for k, v in keys)
    lines.append(garbage)
    try:
        f = parse_device_file("\n".join(lines), "h.eds")
    except DeviceFileError as exc:
        msg = str(exc)
        assert msg.startswith("h.eds: ") and "\n" not in msg
        return
    for obj in f.objects.values():
        for sub in obj.entries:
            f.value(obj.index, sub, node_id=5)


_INT_TYPES = [t for t in DataType if t.is_integer]


@st.composite
def _entry_keys(draw: st.DrawFn) -> list[str]:
    """The keys of one valid entry: a data type, an access type, a value of the type
    written as decimal, hex, octal or (signed) bit pattern, maybe limits around it, maybe
    relative to the node id, maybe a DCF's ParameterValue."""
    dt = draw(st.sampled_from([*_INT_TYPES, DataType.REAL32, DataType.VISIBLE_STRING]))
    keys = [
        f"ParameterName={draw(st.text('abc XYZ_-()', max_size=12))}",
        f"DataType=0x{int(dt):04X}",
        f"AccessType={draw(st.sampled_from([a.value for a in Access]))}",
        f"PDOMapping={draw(st.integers(0, 1))}",
    ]
    if dt is DataType.VISIBLE_STRING:
        return [*keys, f"DefaultValue={draw(st.text('abc 123.', max_size=10)).strip()}"]
    if dt is DataType.REAL32:
        v = draw(st.floats(-1e6, 1e6, allow_nan=False))
        return [*keys, f"DefaultValue={v!r}"]
    lo, hi = dt.int_range()
    v = draw(st.integers(lo, hi))
    if draw(st.booleans()):
        low, high = draw(st.integers(lo, v)), draw(st.integers(v, hi))
        keys += [f"LowLimit={low}", f"HighLimit={high}"]
    if not dt.signed and v <= 0x7FF and draw(st.booleans()):
        text = f"$NODEID+0x{v:X}"
    else:
        form = draw(st.sampled_from(["dec", "hex", "oct", "pattern"]))
        if form == "hex" and v >= 0:
            text = f"0x{v:X}"
        elif form == "oct" and v > 0:
            text = f"0{v:o}"
        elif form == "pattern" and dt.signed and v < 0:
            text = f"0x{v + 2**dt.bits:X}"
        else:
            text = str(v)
    keys.append(f"{draw(st.sampled_from(['DefaultValue', 'ParameterValue']))}={text}")
    return keys


@st.composite
def _valid_files(draw: st.DrawFn) -> str:
    lines = ["[DeviceInfo]", f"ProductName={draw(st.text('abc ', max_size=8)).strip()}"]
    for index in draw(st.sets(st.integers(0x1000, 0x6FFF), max_size=6)):
        if draw(st.booleans()):
            lines += [f"[{index:04X}]", "ObjectType=0x7", *draw(_entry_keys())]
        else:
            subs = draw(st.integers(1, 4))
            lines += [f"[{index:04X}]", f"ObjectType=0x{draw(st.sampled_from([8, 9])):X}",
                      f"SubNumber={subs}", "ParameterName=group"]  # fmt: skip
            for sub in range(subs):
                lines += [f"[{index:04X}sub{sub:X}]", *draw(_entry_keys())]
    return "\n".join(lines)


@settings(max_examples=200)
@given(text=_valid_files())
def test_a_file_read_and_written_again_reads_the_same(text: str) -> None:
    """What the reader takes, :func:`format_device_file` writes so that it reads the same
    (the Lely export's device files): types, access, values, limits, node-id relative."""
    f = parse_device_file(text, "h.eds")
    again = parse_device_file(format_device_file(f, "again.eds"), "again.eds")
    facts = [
        {
            (i, s): (e.data_type, e.access, e.value, e.low, e.high, e.pdo_mappable, e.node_relative)
            for i, o in g.objects.items()
            for s, e in o.entries.items()
        }
        for g in (f, again)
    ]
    assert facts[0] == facts[1]
    assert again.device == f.device


def test_a_file_read_again_is_parsed_once_unless_its_text_changed(tmp_path: Path) -> None:
    """The same text is parsed once a process (the box check, the session and the wiring
    each read a box's files); a file rewritten in place with the same size and times is a
    new text, hence read anew (the parse is keyed by the text's digest, not by its stat)."""
    import os

    path = tmp_path / "d.eds"
    path.write_text(eds_path().read_text())
    first = read_device_file(path)
    assert read_device_file(path) is first
    stat = path.stat()
    text = path.read_text().replace("HRM rope drive", "HRM rope drivE")
    path.write_text(text)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    again = read_device_file(path)
    assert again is not first and again.device.product_name == "HRM rope drivE"
    path.write_text(text.replace("[6502]", "[6502]\nDataType=0x0099", 1))
    for _ in range(2):  # an error is not kept: raised again
        with pytest.raises(DeviceFileError, match=r"\[6502\] DataType"):
            read_device_file(path)
