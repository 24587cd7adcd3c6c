"""``hrm box check`` offline, and ``hrm run`` refusing a box whose device files do not offer
what hrm needs before any bus opens."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from drivers import default_box_path
from hrm_ctrl.formats.planfile import write_plan
from tests.hrm_ctrl.cli.cli_helpers import run_cli, small_plan

VENDOR = Path(__file__).parents[2] / "drivers" / "vendor_eds"
FAULHABER = VENDOR / "605.3150.68-B-EK-2-60.eds"
EPOS4 = VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"


def _box(tmp_path: Path, drives: str) -> Path:
    """The shipped box on virtual buses with a ``[drives]`` table."""
    box = tmp_path / "box.toml"
    text = default_box_path().read_text().replace('"socketcan"', '"virtual"')
    box.write_text(text + "\n" + drives)
    return box


def test_the_shipped_box_passes(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run_cli(["box", "check"], capsys)
    assert rc == 0 and err == ""
    lines = out.splitlines()
    assert len(lines) == 36 and all(": hrm_drive.eds: ok: RPDO1 = " in line for line in lines)


def test_refusals_one_line_each_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    box = _box(
        tmp_path,
        f'[drives]\ndevice_file = "{EPOS4}"\n[drives.j03r1]\ndevice_file = "{FAULHABER}"\n',
    )
    rc, out, err = run_cli(["box", "check", "--config", str(box)], capsys)
    assert rc == 2 and err == ""
    refused = [line for line in out.splitlines() if ": ok: " not in line]
    assert refused[0] == (
        "j03r1: 605.3150.68-B-EK-2-60.eds: no cyclic synchronous position mode "
        "(0x6502 = 0x25: PP, PV, HM)"
    )
    assert {line.split(":")[0] for line in refused} == {"j03r1"} and len(refused) == 4
    rc, out, _ = run_cli(["box", "check", "--config", str(box), "--json"], capsys)
    doc = json.loads(out)
    assert rc == 2 and doc["ok"] is False
    by_motor = {n["motor"]: n for n in doc["nodes"]}
    assert by_motor["j03r2"]["ok"] and by_motor["j03r2"]["pdos"][0]["entries"] == [
        "0x60400010",
        "0x607A0020",
    ]
    assert by_motor["j03r2"]["file"]["modes"] == "PP, PV, HM, CSP, CSV, CST"


def test_a_bad_device_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "junk.eds").write_bytes(b"\x00\x01binary")
    box = _box(tmp_path, '[drives]\ndevice_file = "junk.eds"\n')
    rc, out, err = run_cli(["box", "check", "--config", str(box)], capsys)
    assert rc == 2 and out == ""
    junk = tmp_path / "junk.eds"
    assert err == f"hrm box: error: {junk}: line 1: NUL byte (binary content, not a text file)\n"


def test_run_refuses_before_any_bus_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    box = _box(tmp_path, f'[drives.j03r1]\ndevice_file = "{FAULHABER}"\n')
    logs = tmp_path / "logs"
    rc, _out, err = run_cli(
        ["run", "--hold", "0.1", "--config", str(box), "--log-dir", str(logs)], capsys
    )
    assert rc == 2, err
    assert err == (
        f"hrm run: error: {box}: j03r1: 605.3150.68-B-EK-2-60.eds: no cyclic synchronous "
        "position mode (0x6502 = 0x25: PP, PV, HM) (and 3 more: hrm box check lists them)\n"
    )
    assert not logs.exists() or not any(logs.iterdir())  # no CAN log, no run record: nothing opened


C5E = VENDOR / "C5-E-2-09.eds"

#: The CSP-capable vendor files, with what their [drives] table needs beside the file
CSP_FILES = {
    EPOS4.name: "",
    C5E.name: 'sdo = { "0x60A8" = 0x00B50000 }\n',  # 0.1 deg by default: counts instead
}


@pytest.mark.parametrize("name", list(CSP_FILES))
def test_a_box_of_vendor_drives_brings_up_and_plays_a_plan_on_the_simulator(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    """36 simulated drives with the vendor file's object dictionary (the box in its own
    process): the check passes, the bring-up maps the PDOs in CiA 301's order (the overlay
    first) and the plan plays."""
    path = VENDOR / name
    box = _box(tmp_path, f'[drives]\ndevice_file = "{path}"\n{CSP_FILES[name]}')
    plan, logs = tmp_path / "plan.json", tmp_path / "logs"
    write_plan(plan, small_plan())
    argv = ["run", str(plan), "--sim", "--uncalibrated", "--config", str(box), "--speed", "60"]
    rc, out, err = run_cli([*argv, "--log-dir", str(logs), "--json"], capsys)
    assert rc == 0, err
    assert json.loads(out)["completed"] is True
    record = json.loads(next(logs.glob("*.json")).read_text())
    assert record["config"]["drives"]["device_file"] == str(path)
    # node 1 of can0's SDO writes on the wire
    import can

    writes = [
        (m.data[1] | m.data[2] << 8, m.data[3], int.from_bytes(m.data[4:8], "little"))
        for m in can.BLFReader(str(next(logs.glob("*_can0.blf"))))
        if m.arbitration_id == 0x601 and m.data[0] & 0xE0 == 0x20  # SDO download request
    ]
    overlay = [(0x60A8, 0, 0x00B50000)] if name == C5E.name else []
    assert writes[: len(overlay)] == overlay
    pdo = [w for w in writes if w[0] in (0x1400, 0x1600, 0x1800, 0x1A00)]
    assert pdo == [
        (0x1400, 1, 0x80000201), (0x1400, 2, 1), (0x1600, 0, 0),
        (0x1600, 1, 0x60400010), (0x1600, 2, 0x607A0020), (0x1600, 0, 2), (0x1400, 1, 0x201),
        (0x1800, 1, 0x80000181), (0x1800, 2, 1), (0x1A00, 0, 0),
        (0x1A00, 1, 0x60410010), (0x1A00, 2, 0x60640020), (0x1A00, 0, 2), (0x1800, 1, 0x181),
    ]  # fmt: skip
    assert (0x60C2, 1, 10) in writes and (0x60C2, 2, 0xFD) in writes  # 10 x 10^-3 s
    assert (0x6060, 0, 8) in writes  # CSP, which the file's 0x6502 declares


#: The vendor files hrm refuses: the first refusal ``hrm run`` names, and how many more
REFUSED_FILES = {
    "epos2_347717.eds": (
        "0x6502 (supported drive modes) has no value in the file: cyclic synchronous "
        "position mode not declared",
        2,
    ),
    FAULHABER.name: ("no cyclic synchronous position mode (0x6502 = 0x25: PP, PV, HM)", 3),
    "technosoft.eds": (
        "no cyclic synchronous position mode (0x6502 = 0x1F0065: PP, PV, HM, IP)",
        1,
    ),
    "prbt_0_1.dcf": ("no cyclic synchronous position mode (0x6502 = 0x43: PP, VL, IP)", 3),
}


@pytest.mark.parametrize("name", list(REFUSED_FILES))
def test_a_box_of_drives_without_what_hrm_needs_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    box = _box(tmp_path, f'[drives]\ndevice_file = "{VENDOR / name}"\n')
    plan, logs = tmp_path / "plan.json", tmp_path / "logs"
    write_plan(plan, small_plan())
    argv = ["run", str(plan), "--sim", "--uncalibrated", "--config", str(box)]
    rc, out, err = run_cli([*argv, "--log-dir", str(logs)], capsys)
    first, more = REFUSED_FILES[name]
    n = 36 * (more + 1) - 1  # every node refused, each with the same lines
    assert rc == 2 and out == ""
    assert err.splitlines()[-1] == (
        f"hrm run: error: {box}: j01r0: {name}: {first} (and {n} more: hrm box check lists them)"
    )
    assert not logs.exists() or not any(logs.iterdir())  # no CAN log, no record: nothing opened
