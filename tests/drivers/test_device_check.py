"""Each drive's device file against what hrm needs: the verdict on the six vendor files and
ours pinned, the ``[drives]`` table of box.toml, a refusal before anything opens."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from drivers.config import BusConfigError, DrivesConfig, SdoWrite, load_box_config
from drivers.device_check import (
    DeviceCheckError,
    QuickStopScale,
    check_box,
    interpolation_setting,
    quick_stop_scale,
)
from drivers.protocol.cia306 import DeviceFileError, read_device_file

VENDOR = Path(__file__).parent / "vendor_eds"

OK = (
    "ok: RPDO1 = 0x6040, 0x607A; TPDO1 = 0x6041, 0x6064 on SYNC (type 1); "
    "0x60C2 = 10 x 10^-3 s; heartbeat consumer 0x1016; "
)
OK_COUNTS = OK + "0x6085 from the motors' acceleration limit in counts/s^2"
OK_EPOS4 = OK + "0x6085 the drive's own (acceleration unit 0x60AA = 0x00C00300: not converted)"
OK_C5E = (
    OK + "0x6085 from the motors' acceleration limit in rpm/s (2000 counts a revolution, 0x608F)"
)

#: What ``hrm box check`` says of each file at 100 Hz (the shipped box.toml's rate)
PINNED: dict[str | None, list[str]] = {
    None: [OK_COUNTS],  # hrm's own EDS
    "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf": [OK_EPOS4],
    "C5-E-2-09.eds": [
        "position unit 0x60A8 = 0xFF410000 (10^-1 degree), not increments: hrm sends encoder "
        'counts (writable: an SDO overlay sets it, sdo = { "0x60A8" = 0x00B50000 })'
    ],
    "epos2_347717.eds": [
        "0x6502 (supported drive modes) has no value in the file: cyclic synchronous position "
        "mode not declared",
        "0x60C2 (interpolation time period) cannot be set to the SYNC period 10 ms "
        "(value 1..1, index 10^-3)",
        "no 0x605A (quick stop option code)",
    ],
    "605.3150.68-B-EK-2-60.eds": [
        "no cyclic synchronous position mode (0x6502 = 0x25: PP, PV, HM)",
        "no 0x60C2 (interpolation time period): the SYNC period cannot be set",
        "no 0x6065 (following error window)",
        "no 0x605A (quick stop option code)",
    ],
    "technosoft.eds": [
        "no cyclic synchronous position mode (0x6502 = 0x1F0065: PP, PV, HM, IP)",
        "no 0x607F (max profile velocity)",  # node guarding instead of 0x1016: taken
    ],
    "prbt_0_1.dcf": [
        "no cyclic synchronous position mode (0x6502 = 0x43: PP, VL, IP)",
        "no 0x605A (quick stop option code)",
        "no 0x6085 (quick stop deceleration)",
        "no 0x607F (max profile velocity)",
    ],
}


@pytest.mark.parametrize("name", list(PINNED), ids=lambda n: n or "hrm_drive.eds")
def test_box_check_pinned_per_device_file(name: str | None) -> None:
    cfg = load_box_config(None)
    drives = DrivesConfig(default_file=None if name is None else VENDOR / name)
    report = check_box(replace(cfg, drives=drives))
    shown = name or "hrm_drive.eds"
    assert len(report.nodes) == 36
    first = [line for line in report.lines() if line.startswith("j01r0: ")]
    assert first == [f"j01r0: {shown}: {text}" for text in PINNED[name]]
    assert report.refused == (not PINNED[name][0].startswith(OK))
    assert len(report.lines()) == 36 * len(PINNED[name])  # every node, one line each


def test_refusal_names_node_file_and_object_and_counts_the_rest() -> None:
    cfg = load_box_config(None)
    drives = DrivesConfig(motor_files={"j03r1": VENDOR / "605.3150.68-B-EK-2-60.eds"})
    report = check_box(replace(cfg, drives=drives))
    with pytest.raises(DeviceCheckError) as info:
        report.raise_if_refused()
    assert str(info.value) == (
        "<default box.toml>: j03r1: 605.3150.68-B-EK-2-60.eds: no cyclic synchronous position "
        "mode (0x6502 = 0x25: PP, PV, HM) (and 3 more: hrm box check lists them)"
    )
    assert [n.motor for n in report.nodes if n.verdict.refusals] == ["j03r1"]


def test_epos2_interpolation_period_is_1_ms_only() -> None:
    epos2 = read_device_file(VENDOR / "epos2_347717.eds")
    assert interpolation_setting(epos2, 0.001) == (1, -3)
    assert isinstance(interpolation_setting(epos2, 0.01), str)
    epos4 = read_device_file(VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf")
    assert interpolation_setting(epos4, 0.0025) == (25, -4)  # index writable
    assert interpolation_setting(epos4, 0.2) == (20, -2)  # value 0..100: not 200 x 10^-3


def _box(tmp_path: Path, drives: str) -> Path:
    box = tmp_path / "box.toml"
    box.write_text(
        drives + '[buses.can0]\ninterface = "virtual"\nchannel = "x"\nbitrate = 1000000\n'
        "[buses.can0.nodes]\nj01r0 = 1\nj01r1 = 2\n"
    )
    return box


def test_drives_table_default_and_per_motor_relative_to_the_box_file(tmp_path: Path) -> None:
    (tmp_path / "eds").mkdir()
    box = _box(
        tmp_path,
        '[drives]\ndevice_file = "eds/a.dcf"\n[drives.j01r1]\ndevice_file = "/abs/b.eds"\n',
    )
    cfg = load_box_config(box)
    assert cfg.drives.device_file("j01r0") == tmp_path / "eds" / "a.dcf"
    assert cfg.drives.device_file("j01r1") == Path("/abs/b.eds")
    again = cfg.with_control(rate_hz=200)  # through to_dict and back
    assert again.drives == cfg.drives
    assert load_box_config(None).to_dict().get("drives") is None  # the shipped box unchanged


@pytest.mark.parametrize(
    ("drives", "expected"),
    [
        ("[drives]\ndevice_file = 3\n", "drives.device_file: expected the path of an EDS or DCF"),
        ("[drives.j09r9]\ndevice_file = 'a.eds'\n", "drives.j09r9: neither a key of [drives]"),
        ("[drives.j01r0]\ndevice_fle = 'a.eds'\n", "drives.j01r0.device_fle: unknown key (did"),
        ("[drives]\nj01r0 = 'a.eds'\n", "drives.j01r0: must be a table"),
        ("drives = 1\n", "[drives] must be a table"),
    ],
)
def test_bad_drives_table_one_line(tmp_path: Path, drives: str, expected: str) -> None:
    with pytest.raises(BusConfigError) as info:
        load_box_config(_box(tmp_path, drives))
    assert expected in str(info.value) and "\n" not in str(info.value)
    assert str(info.value).startswith(str(tmp_path / "box.toml"))


def test_hostile_device_file_named_in_the_box_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "bad.eds").write_text("[6502]\nDataType=0x0099\nAccessType=ro\n")
    cfg = load_box_config(_box(tmp_path, '[drives]\ndevice_file = "bad.eds"\n'))
    with pytest.raises(DeviceFileError) as info:
        check_box(cfg)
    assert str(info.value) == f"{tmp_path / 'bad.eds'}: [6502] DataType: unknown data type 0x0099"
    with pytest.raises(DeviceFileError, match=r"none\.eds: device file not found"):
        check_box(load_box_config(_box(tmp_path, '[drives]\ndevice_file = "none.eds"\n')))


C5E = VENDOR / "C5-E-2-09.eds"
EPOS4 = VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"


def test_an_sdo_overlay_setting_increments_makes_the_c5e_ok(tmp_path: Path) -> None:
    box = _box(tmp_path, f'[drives]\ndevice_file = "{C5E}"\nsdo = {{ "0x60A8" = 0x00B50000 }}\n')
    report = check_box(load_box_config(box))
    assert not report.refused
    assert report.lines()[0] == f"j01r0: C5-E-2-09.eds: {OK_C5E}; 0x60A8:00 = 0xB50000"
    setup = report.setups()["j01r0"]
    assert [(w.index, w.sub, w.value) for w in setup.sdo] == [(0x60A8, 0, 0x00B50000)]
    assert setup.interpolation == (10, -3)
    node = report.to_dict()["nodes"][0]
    assert node["sdo_overlay"] == {"0x60A8:00": 0x00B50000} and node["identity"] == {}


@pytest.mark.parametrize(
    ("sdo", "expected"),
    [
        (
            '{ "0x60A8" = 0x00410000 }',
            "position unit 0x60A8 = 0x00410000 (degree) in the SDO overlay, not increments: "
            "hrm sends encoder counts",
        ),
        ('{ "0x2FFF:3" = 1 }', "SDO overlay 0x2FFF:03 = 1: no such object in the file"),
        ('{ "0x1018:1" = 1 }', "SDO overlay 0x1018:01 = 1: not writable (AccessType=ro)"),
        ('{ "0x6085" = -5 }', "SDO overlay 0x6085:00 = -5: outside UNSIGNED32 (0..4294967295)"),
    ],
)
def test_an_overlay_the_file_does_not_allow_is_refused(
    tmp_path: Path, sdo: str, expected: str
) -> None:
    box = _box(tmp_path, f'[drives]\ndevice_file = "{C5E}"\nsdo = {sdo}\n')
    lines = check_box(load_box_config(box)).refusal_lines()
    assert f"j01r0: C5-E-2-09.eds: {expected}" in lines, lines


def test_overlay_and_identity_per_device_and_per_node(tmp_path: Path) -> None:
    box = _box(
        tmp_path,
        f'[drives]\ndevice_file = "{C5E}"\n'
        'sdo = { "0x60A8" = 0x00B50000, "0x6091:1" = 1 }\n'
        "identity = { vendor_id = 0x26C, product_code = 17 }\n"
        '[drives.j01r1]\nsdo = { "0x6091:01" = 2 }\nidentity = { serial = 0x1234 }\n',
    )
    drives = load_box_config(box).drives
    assert [(w.label, w.value) for w in drives.sdo_overlay("j01r0")] == [
        ("0x60A8:00", 0xB50000), ("0x6091:01", 1)
    ]  # fmt: skip
    assert [(w.label, w.value) for w in drives.sdo_overlay("j01r1")] == [
        ("0x60A8:00", 0xB50000), ("0x6091:01", 2)
    ]  # fmt: skip
    assert drives.expected_identity("j01r1").values() == (0x26C, 17, None, 0x1234)
    assert drives.expected_identity("j01r0").values() == (0x26C, 17, None, None)
    cfg = load_box_config(box)
    assert cfg.with_control(rate_hz=200).drives == cfg.drives  # through to_dict and back


def test_a_node_with_its_own_device_file_does_not_take_the_default_overlay(
    tmp_path: Path,
) -> None:
    box = _box(
        tmp_path,
        f'[drives]\ndevice_file = "{C5E}"\nsdo = {{ "0x60A8" = 0x00B50000 }}\n'
        "identity = { product_code = 17 }\n"
        f'[drives.j01r1]\ndevice_file = "{EPOS4}"\n',
    )
    drives = load_box_config(box).drives
    assert drives.sdo_overlay("j01r1") == () and drives.expected_identity("j01r1").values() == (
        None, None, None, None
    )  # fmt: skip


@pytest.mark.parametrize(
    ("drives", "expected"),
    [
        ("[drives]\nsdo = 1\n", 'drives.sdo: must be a table ("0x60A8" = 0x00B50000, ...)'),
        ('[drives]\nsdo = { "60A8" = 1 }\n', 'drives.sdo.60A8: expected an object "0xIIII"'),
        ('[drives]\nsdo = { "0x0007" = 1 }\n', "drives.sdo.0x0007: 0x0007 is not an object"),
        ('[drives]\nsdo = { "0x6085" = "fast" }\n', "drives.sdo.0x6085: expected an integer"),
        ('[drives]\nsdo = { "0x6085" = 1, "0x6085:0" = 2 }\n', "0x6085:0: object given twice"),
        ('[drives]\nsdo = { "0x60C2:1" = 1 }\n', "hrm's bring-up writes 0x60C2 itself"),
        ('[drives]\nsdo = { "0x1600:1" = 1 }\n', "hrm's bring-up writes 0x1600 itself"),
        ("[drives]\nidentity = { vendor = 1 }\n", "drives.identity.vendor: unknown key"),
        ("[drives]\nidentity = { serial = -1 }\n", "drives.identity.serial: expected an integer"),
        ("[drives.j01r0]\nidentity = 3\n", "drives.j01r0.identity: must be a table"),
    ],
)
def test_bad_overlay_or_identity_one_line(tmp_path: Path, drives: str, expected: str) -> None:
    with pytest.raises(BusConfigError) as info:
        load_box_config(_box(tmp_path, drives))
    assert expected in str(info.value) and "\n" not in str(info.value)


def test_quick_stop_deceleration_in_the_drive_s_unit() -> None:
    """0x6085 from counts/s^2: hrm's EDS in counts; the C5-E in rpm/s by its 0x608F (an
    overlay's encoder resolution counts); not converted through a gear ratio other than
    1:1, an acceleration unit 0x60AA, or when the overlay writes 0x6085 itself."""
    c5e = read_device_file(C5E)
    unit = (SdoWrite(0x60A8, 0, 0x00B50000),)
    scale = quick_stop_scale(c5e, unit)
    assert isinstance(scale, QuickStopScale) and scale.per_count_s2 == pytest.approx(0.03)
    assert scale.value(2_048_000) == 61_440  # rpm/s at 2000 counts a revolution
    resolution = (*unit, SdoWrite(0x608F, 1, 4096))
    scale = quick_stop_scale(c5e, resolution)
    assert isinstance(scale, QuickStopScale) and scale.value(2_048_000) == 30_000
    assert quick_stop_scale(c5e, (*unit, SdoWrite(0x6091, 1, 2))) == (
        "0x6085 the drive's own (gear ratio 0x6091 = 2:1, not 1:1)"
    )
    assert quick_stop_scale(c5e, (*unit, SdoWrite(0x6085, 0, 9000))) == (
        "0x6085 by the SDO overlay"
    )
    assert quick_stop_scale(read_device_file(EPOS4)) == (
        "0x6085 the drive's own (acceleration unit 0x60AA = 0x00C00300: not converted)"
    )
    assert QuickStopScale("counts/s^2", 1.0, 1, 10).value(0.2) is None  # 0 stops nothing


def test_quick_stop_deceleration_outside_the_object_is_one_line(tmp_path: Path) -> None:
    """The Faulhaber's 0x6085 takes 0..32000: a motor limit beyond it is refused with one
    line when the setups are made (before any bus opens); within it, the value is set."""
    faulhaber = VENDOR / "605.3150.68-B-EK-2-60.eds"
    report = check_box(load_box_config(_box(tmp_path, f'[drives]\ndevice_file = "{faulhaber}"\n')))
    with pytest.raises(DeviceCheckError) as info:
        report.setups({"j01r0": 2.048e6, "j01r1": 1000.0})
    assert str(info.value) == (
        f"{tmp_path / 'box.toml'}: j01r0: 605.3150.68-B-EK-2-60.eds: quick-stop deceleration "
        "0x6085: the motor's acceleration limit 2.048e+06 counts/s^2 is 2.048e+06 counts/s^2, "
        "outside 1..32000 (the object's type and limits)"
    )
    setups = report.setups({"j01r0": 32000.0, "j01r1": 1000.4})
    assert [setups[m].quick_stop_deceleration for m in ("j01r0", "j01r1")] == [32000, 1000]
    assert report.setups()["j01r0"].quick_stop_deceleration is None  # no limits: not written


def test_a_drive_with_node_guarding_and_no_heartbeat_consumer_is_guarded(tmp_path: Path) -> None:
    from tests.drivers.test_vendor_boxes import guarded_eds

    path = guarded_eds(tmp_path)
    report = check_box(load_box_config(_box(tmp_path, f'[drives]\ndevice_file = "{path}"\n')))
    assert report.lines()[0] == "j01r0: guarded.eds: " + OK_COUNTS.replace(
        "heartbeat consumer 0x1016", "node guarding 0x100C/0x100D"
    )
    assert report.setups()["j01r0"].guarding == (100, 3)  # host heartbeat period, 350 // 100
    assert report.to_dict()["nodes"][0]["file"]["watches_host_by"] == "node guarding 0x100C/0x100D"
    hrm = check_box(load_box_config(None))
    assert hrm.setups()["j01r0"].guarding is None  # a heartbeat consumer: heartbeats
