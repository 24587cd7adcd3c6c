"""A Lely ``bus.yml`` read as a box configuration (``hrm box check --lely-bus``): the
export read back gives the same verdicts; bad input is one line naming file and key."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.config import (
    BusConfigError,
    DrivesConfig,
    DriveSpec,
    ExpectedIdentity,
    SdoWrite,
    load_box_config,
)
from drivers.device_check import BoxCheck, check_box
from drivers.lely_bus import load_lely_buses, parse_bus_yml
from drivers.lely_export import export_lely
from tests.drivers.test_lely_export import _tool
from tests.drivers.test_vendor_boxes import guarded_eds
from tests.hrm_ctrl.cli.cli_helpers import run_cli

VENDOR = Path(__file__).parent / "vendor_eds"
C5E = VENDOR / "C5-E-2-09.eds"


def _verdicts(report: BoxCheck) -> list[tuple[Any, ...]]:
    """Each drive's verdict without its file's path (the export writes the files again)."""
    return [
        (n.motor, n.bus, n.node_id, n.verdict.refusals, n.verdict.ok_text(), n.overlay,
         n.identity, n.path.stem)
        for n in report.nodes
    ]  # fmt: skip


@pytest.mark.parametrize("drive", ["hrm_drive.eds", "c5-e", "guarded"])
def test_the_export_read_back_gives_the_same_verdicts(tmp_path: Path, drive: str) -> None:
    """hrm's drive; C5-Es with an overlay and an identity; drives the host guards (no
    0x1016: guard_time, life_time_factor, no heartbeat from them)."""
    cfg = load_box_config(None).with_control(
        rate_hz=200, heartbeat_timeout_ms=400, following_error_window_counts=1234
    )
    if drive == "c5-e":
        spec = DriveSpec(
            sdo=(SdoWrite(0x60A8, 0, 0x00B50000), SdoWrite(0x608F, 1, 4096)),
            identity=ExpectedIdentity(vendor_id=0x26C, product_code=17, serial=5),
        )
        cfg = replace(cfg, drives=DrivesConfig(default_file=C5E, default=spec))
    elif drive == "guarded":
        (tmp_path / "eds").mkdir()
        cfg = replace(cfg, drives=DrivesConfig(default_file=guarded_eds(tmp_path / "eds")))
    export_lely(cfg, tmp_path)
    back = load_lely_buses([tmp_path / "can0" / "bus.yml", tmp_path / "can1" / "bus.yml"])
    assert [(b.name, b.bitrate, dict(b.nodes)) for b in back.buses] == [
        (b.name, b.bitrate, dict(b.nodes)) for b in cfg.buses
    ]
    ctl, again = cfg.control, back.control
    assert (again.rate_hz, again.host_node_id, again.host_heartbeat_ms) == (
        ctl.rate_hz, ctl.host_node_id, ctl.host_heartbeat_ms
    )  # fmt: skip
    assert again.heartbeat_timeout_ms == 400 and again.node_heartbeat_ms == 100
    guarding = [n.setup.guarding for n in check_box(back).nodes]
    assert guarding == [(100, 4) if drive == "guarded" else None] * 36
    assert again.following_error_window_counts == 1234
    assert again.quick_stop_option_code == ctl.quick_stop_option_code
    assert _verdicts(check_box(back)) == _verdicts(check_box(cfg))


def test_dcfgen_takes_a_guarded_drive(tmp_path: Path) -> None:
    """A drive the host guards is exported with guard_time and life_time_factor and no
    heartbeat: dcfgen writes 0x100C/0x100D and nothing to the 0x1016 it lacks."""
    import subprocess

    cfg = replace(load_box_config(None), drives=DrivesConfig(default_file=guarded_eds(tmp_path)))
    export_lely(cfg, tmp_path / "out")
    done = subprocess.run(
        [_tool("dcfgen"), "-v", "bus.yml"], cwd=tmp_path / "out" / "can0", capture_output=True,
        text=True,
    )  # fmt: skip
    assert done.returncode == 0 and "Warning" not in done.stderr, done.stderr
    node1 = [line for line in done.stdout.splitlines() if line.startswith("j01r0: ")]
    assert "j01r0: writing 2 bytes to 0x100C/0: 64 00" in node1  # 100 ms
    assert "j01r0: writing 1 bytes to 0x100D/0: 03" in node1
    assert not any("0x1016" in line for line in node1)


def test_the_cli_checks_a_bus_yml(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    export_lely(load_box_config(None), tmp_path)
    rc, out, err = run_cli(
        ["box", "check", "--lely-bus", str(tmp_path / "can1" / "bus.yml")], capsys
    )
    assert rc == 0 and err == ""
    lines = out.splitlines()
    assert len(lines) == 18 and lines[0].startswith("j07r0: hrm_drive.eds: ok: RPDO1 = ")
    faulhaber = VENDOR / "605.3150.68-B-EK-2-60.eds"
    bus = tmp_path / "can1" / "bus.yml"
    bus.write_text(bus.read_text().replace('dcf: "hrm_drive.eds"', f'dcf: "{faulhaber}"', 1))
    rc, out, err = run_cli(["box", "check", "--lely-bus", str(bus)], capsys)
    assert rc == 2 and err == ""
    assert out.splitlines()[0] == (
        "j07r0: 605.3150.68-B-EK-2-60.eds: no cyclic synchronous position mode "
        "(0x6502 = 0x25: PP, PV, HM)"
    )
    rc, out, err = run_cli(["box", "check", "--lely-bus", str(bus), "--config", "x"], capsys)
    assert (
        rc == 2 and out == "" and err == "hrm box: error: give --config or --lely-bus, not both\n"
    )


MASTER = "master: {node_id: 127, sync_period: 10000, heartbeat_producer: 100}\n"
SLAVE = "j01r0: {node_id: 1, dcf: hrm_drive.eds, heartbeat_producer: 100"


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("a: [1\n", "line 2: expected ',' or ']', but got '<stream end>'"),
        (MASTER + "master: {}\n", "line 2: duplicate key 'master'"),
        ("- 1\n", "must be a mapping of options, master and slaves"),
        ("j01r0: {node_id: 1, dcf: a.eds}\n", "master: missing (its node id and sync_period)"),
        ("master: {node_id: 127}\n", "master.sync_period: missing (hrm streams on SYNC)"),
        (
            "master: {sync_period: 33333}\n",
            "master.sync_period: 33333 us: must give a period 0x60C2 can encode",
        ),
        ("master: {sync_period: 10000, sync: 1}\n", "master.sync: unknown key (hrm reads: "),
        (MASTER, "no slave (a key naming a rope motor)"),
        (MASTER + SLAVE + ", boot: true}\n", "j01r0.boot: unknown key (hrm reads: dcf, "),
        (MASTER + "j01r0: {node_id: 1}\n", "j01r0.dcf: missing"),
        (MASTER + SLAVE + ", node_id: 2}\n", "line 2: duplicate key 'node_id'"),
        (MASTER + "j01r0: {node_id: x, dcf: a}\n", "j01r0.node_id: expected an integer, got 'x'"),
        (MASTER + SLAVE + ", sdo: 5}\n", "j01r0.sdo: must be a list of {index, sub_index, value}"),
        (
            MASTER + SLAVE + ", sdo: [{index: 0x1600, sub_index: 1, value: 0}]}\n",
            "j01r0.sdo[0]: hrm's bring-up writes 0x1600 itself",
        ),
        (
            MASTER + SLAVE + ", sdo: [{index: 0x6060, value: 1}]}\n",
            "j01r0.sdo[0]: 0x6060 = 1: hrm drives in cyclic synchronous position mode (8)",
        ),
        (
            MASTER + SLAVE + ", sdo: [{index: 0x60C2, sub_index: 1, value: 1}, "
            "{index: 0x60C2, sub_index: 2, value: 0xFD}]}\n",
            "j01r0.sdo: 0x60C2 = 1 x 10^-3 s is not master.sync_period (10000 us)",
        ),
        (
            MASTER + SLAVE + "}\nj01r1: {node_id: 2, dcf: hrm_drive.eds, heartbeat_producer: 50}\n",
            "j01r1.heartbeat_producer: gives node_heartbeat_ms = 50, ",
        ),
        (MASTER + SLAVE + ", vendor_id: -1}\n", "j01r0.vendor_id: -1 outside 0..4294967295"),
        ("!!python/object/apply:os.system [ls]\n", "could not determine a constructor"),
    ],
)
def test_bad_bus_yml_is_one_line(tmp_path: Path, text: str, expected: str) -> None:
    bus = tmp_path / "bus.yml"
    bus.write_text(text)
    with pytest.raises(BusConfigError) as info:
        load_lely_buses([bus])
    message = str(info.value)
    assert message.startswith(f"{bus}: ") and expected in message, message
    assert "\n" not in message


def test_a_10_mb_bus_yml_is_refused_unread(tmp_path: Path) -> None:
    bus = tmp_path / "bus.yml"
    bus.write_bytes(b"a: " + b"x" * 10_000_000)
    with pytest.raises(BusConfigError) as info:
        load_lely_buses([bus])
    assert str(info.value) == f"{bus}: Lely bus.yml is larger than the 1048576 bytes it may have"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(alphabet="{}[]:,-!&*'\"#\n abc01xX\t|>%@`?", max_size=80))
def test_any_text_gives_a_mapping_or_the_one_line_error(text: str) -> None:
    try:
        doc = parse_bus_yml(text, "b.yml")
    except BusConfigError as exc:
        assert str(exc).startswith("b.yml: ") and "\n" not in str(exc)
    else:
        assert isinstance(doc, dict)
