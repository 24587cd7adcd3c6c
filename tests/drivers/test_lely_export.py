"""``hrm box export --lely DIR``: the box as Lely ``dcfgen`` configurations that ``dcfgen``
(PyPI ``dcf-tools``) accepts in strict mode, and the device files written again so that
it does (four of the six vendor files it refuses as shipped)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from drivers.config import (
    DrivesConfig,
    DriveSpec,
    ExpectedIdentity,
    SdoWrite,
    load_box_config,
)
from drivers.device_check import DeviceCheckError
from drivers.lely_export import bus_yml, export_lely
from drivers.protocol.cia306 import format_device_file, parse_device_file, read_device_file
from tests.hrm_ctrl.cli.cli_helpers import run_cli

VENDOR = Path(__file__).parent / "vendor_eds"
EPOS4 = VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"
C5E = VENDOR / "C5-E-2-09.eds"
FILES = sorted(VENDOR.glob("*.eds")) + sorted(VENDOR.glob("*.dcf"))


def _tool(name: str) -> str:
    """The dcf-tools command ``name`` (beside this interpreter, or on PATH), or a skip."""
    found = shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)
    if found is None:
        pytest.skip(f"{name} not installed (pip install dcf-tools)")
    return found


def _facts(f: object) -> dict[tuple[int, int], tuple[object, ...]]:
    return {
        (i, s): (e.data_type, e.access, e.value, e.low, e.high, e.pdo_mappable, e.node_relative)
        for i, o in f.objects.items()  # type: ignore[attr-defined]
        for s, e in o.entries.items()
    }


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_a_device_file_written_again_reads_the_same(path: Path) -> None:
    f = read_device_file(path)
    again = parse_device_file(format_device_file(f, f"{path.stem}.eds"), "again.eds")
    assert _facts(again) == _facts(f)
    assert again.device == f.device


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_dcfchk_takes_every_file_written_again(path: Path, tmp_path: Path) -> None:
    dcfchk = _tool("dcfchk")
    out = tmp_path / f"{path.stem}.eds"
    out.write_text(format_device_file(read_device_file(path), out.name))
    done = subprocess.run([dcfchk, "-n", "5", str(out)], capture_output=True, text=True)
    assert done.returncode == 0 and "Warning" not in done.stderr, done.stderr


def _config(
    device: Path | None,
    sdo: tuple[SdoWrite, ...] = (),
    identity: ExpectedIdentity | None = None,
) -> object:
    cfg = load_box_config(None)
    spec = DriveSpec(sdo=sdo, identity=identity or ExpectedIdentity())
    return replace(cfg, drives=DrivesConfig(default_file=device, default=spec))


#: the C5-E's vendor-ID and product code (its file's)
C5E_IDENTITY = ExpectedIdentity(vendor_id=0x26C, product_code=17)


@pytest.mark.parametrize(
    ("device", "sdo"),
    [(None, ()), (EPOS4, ()), (C5E, (SdoWrite(0x60A8, 0, 0x00B50000),))],
    ids=["hrm_drive.eds", "epos4", "c5-e"],
)
def test_dcfgen_accepts_the_export(
    tmp_path: Path, device: Path | None, sdo: tuple[SdoWrite, ...]
) -> None:
    cfg = _config(device, sdo, C5E_IDENTITY if device == C5E else ExpectedIdentity())
    written = export_lely(cfg, tmp_path)  # type: ignore[arg-type]
    name = "hrm_drive.eds" if device is None else f"{device.stem}.eds"
    assert sorted(p.relative_to(tmp_path).as_posix() for p in written) == sorted(
        [f"can0/{name}", "can0/bus.yml", f"can1/{name}", "can1/bus.yml"]
    )
    dcfgen = _tool("dcfgen")
    done = subprocess.run(
        [dcfgen, "-v", "bus.yml"], cwd=tmp_path / "can0", capture_output=True, text=True
    )
    assert done.returncode == 0 and "Warning" not in done.stderr, done.stderr
    assert (tmp_path / "can0" / "master.dcf").is_file()
    node1 = [line for line in done.stdout.splitlines() if line.startswith("j01r0: ")]
    assert node1[0] == "j01r0: writing 4 bytes to 0x1016/1: 5E 01 7F 00"  # host 127, 350 ms
    assert "j01r0: writing 4 bytes to 0x1600/2: 20 00 7A 60" in node1  # 0x607A, 32 bits
    assert "j01r0: writing 1 bytes to 0x60C2/2: FD" in node1  # 10^-3 s
    assert node1[-1] == "j01r0: writing 1 bytes to 0x6060/0: 08"  # CSP
    if sdo:
        assert "j01r0: writing 4 bytes to 0x60A8/0: 00 00 B5 00" in node1


def test_a_refused_box_is_not_exported(tmp_path: Path) -> None:
    cfg = _config(VENDOR / "605.3150.68-B-EK-2-60.eds")
    with pytest.raises(DeviceCheckError, match="no cyclic synchronous position mode"):
        export_lely(cfg, tmp_path / "out")  # type: ignore[arg-type]
    assert not (tmp_path / "out").exists()


def test_bus_yml_names_the_expected_identity(tmp_path: Path) -> None:
    box = tmp_path / "box.toml"
    box.write_text(
        "[drives]\nidentity = { vendor_id = 9, revision = 0x10000, serial = 7 }\n"
        "[buses.can0]\ninterface = "
        '"virtual"\nchannel = "x"\nbitrate = 500000\n[buses.can0.nodes]\nj01r0 = 1\n'
    )
    text = bus_yml(load_box_config(box), "can0")
    assert "  baudrate: 500\n" in text
    assert "  vendor_id: 9\n  revision_number: 65536\n  serial_number: 7\n" in text


def test_the_cli_writes_and_refuses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run_cli(["box", "export", "--lely", str(tmp_path / "lely")], capsys)
    assert rc == 0 and err == ""
    assert out.splitlines()[-1] == str(tmp_path / "lely" / "can1" / "bus.yml")
    box = tmp_path / "box.toml"
    box.write_text(
        f'[drives]\ndevice_file = "{VENDOR / "prbt_0_1.dcf"}"\n[buses.can0]\ninterface = '
        '"virtual"\nchannel = "x"\nbitrate = 500000\n[buses.can0.nodes]\nj01r0 = 1\n'
    )
    rc, out, err = run_cli(["box", "export", "--config", str(box), "--lely", "x"], capsys)
    assert rc == 2 and out == ""
    assert err == (
        f"hrm box: error: {box}: j01r0: prbt_0_1.dcf: no cyclic synchronous position mode "
        "(0x6502 = 0x43: PP, VL, IP) (and 3 more: hrm box check lists them)\n"
    )
