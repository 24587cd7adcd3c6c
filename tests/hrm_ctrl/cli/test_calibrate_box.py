"""A calibration names its box (issue 34, item 1), as a user meets it.

The leak the issue describes, reproduced: ``hrm calibrate zero --sim --perturb 3`` into a
store, then ``hrm run --sim`` (the unperturbed simulated arm) and ``hrm run --config
box.toml`` on virtual buses with a simulated box behind them (another simulated arm, a box
of real drives, a box with one drive replaced): the calibration is used only on the box it
was made on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from calibration.store import CalibrationStore
from drivers import default_box_path
from drivers.config import load_box_config
from drivers.identity import SIMULATOR_VENDOR_ID
from drivers.protocol.cia301 import OD_IDENTITY
from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import write_plan
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.runtime.arm import simulated_box_identity
from sim_bus.box import SimBox
from sim_bus.drive import DriveSim
from sim_bus.truth import TrueArm
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT, small_plan

REAL_VENDOR_ID = 0x0000009A  # any vendor but the simulator's


def _virtual_box(tmp_path: Path) -> Path:
    """The shipped box on private virtual buses (channels of this test alone)."""
    tag = uuid.uuid4().hex[:8]
    text = default_box_path().read_text().replace('"socketcan"', '"virtual"')
    text = text.replace('channel = "can0"', f'channel = "cal34-{tag}-0"')
    text = text.replace('channel = "can1"', f'channel = "cal34-{tag}-1"')
    path = tmp_path / "box.toml"
    path.write_text(text)
    return path


@contextlib.contextmanager
def _box_behind(config_path: Path, truth: TrueArm | None) -> Iterator[SimBox]:
    """A simulated box of ``truth`` answering on the configuration's virtual buses."""
    config = load_box_config(config_path)
    with SimBox(config, actuation=load_actuation(default_robot()), truth=truth) as box:
        box.start()
        yield box


def _refusal(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [x for x in err.splitlines() if "error" in x]
    assert len(lines) == 1, err
    return lines[0]


@STALL_TOLERANT
def test_a_simulated_calibration_stays_with_its_simulated_arm(
    store_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    model = default_robot()
    runs = tmp_path / "runs"
    rc = main(["calibrate", "zero", "--sim", "--perturb", "3", "--log-dir", str(runs), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err[-2000:]
    store = CalibrationStore(store_dir)
    assert store.active() == 1
    cal = store.load(1)
    # the file names the box: simulated, its drives' identities those of truth 3
    assert cal.box is not None and cal.box.simulated
    assert cal.box == simulated_box_identity(model, perturb=3)
    assert json.loads(store.path_of(1).read_text())["format"] == "hrm-calibration/3"

    # history and show print the box
    assert main(["calibrate", "history"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "box: simulated box, 36 drives" in line, line
    assert main(["calibrate", "show"]) == 0
    assert "\nbox: simulated box, 36 drives, serials 0x" in capsys.readouterr().out

    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    # --sim (the unperturbed arm): another simulated arm, the calibration not used
    rc = main(["run", str(plan), "--sim", "--log-dir", str(runs / "a"), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err[-2000:]
    assert "made on another simulated arm" in out.err and "not used" in out.err, out.err
    assert "hrm run: calibration v" not in out.err
    record = json.loads(Path(json.loads(out.out)["run_record"]).read_text())
    assert record["calibration"] == "uncalibrated (override)"
    assert record["box"]["simulated"] is True

    # --sim --perturb 3 (the arm it was made on): used, and the run says which version
    rc = main(["run", str(plan), "--sim", "--perturb", "3", "--log-dir", str(runs / "b"), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err[-2000:]
    assert f"hrm run: calibration v0001 ({store.path_of(1)}; zero, made on a simulated box" in (
        out.err
    )
    record = json.loads(Path(json.loads(out.out)["run_record"]).read_text())
    assert record["calibration"]["version"] == 1

    # a box on virtual buses: the gate that keeps drives disabled refuses before the
    # configuration, whatever answers there
    box_toml = _virtual_box(tmp_path)
    hold = ["run", "--hold", "0.1", "--config", str(box_toml)]
    # the unperturbed simulated arm: another box
    with _box_behind(box_toml, None):
        text = _refusal([*hold, "--log-dir", str(runs / "c")], capsys)
    assert "calibration refused:" in text and "made on another simulated arm" in text, text
    record = json.loads(next((runs / "c").glob("*.json")).read_text())
    assert not any(e["kind"] == "configured" for e in record["events"])
    # a box of real drives (their vendor is not the simulator's): never a simulated one's
    live_value = DriveSim.live_value

    def real_vendor(self: DriveSim, key: tuple[int, int]) -> object:
        if key == (OD_IDENTITY, 1):
            return REAL_VENDOR_ID
        return live_value(self, key)

    with monkeypatch.context() as m:
        m.setattr(DriveSim, "live_value", real_vendor)
        with _box_behind(box_toml, TrueArm.perturbed(load_actuation(model), 3)):
            text = _refusal([*hold, "--log-dir", str(runs / "d")], capsys)
    assert "made on a simulated box; a real box never uses it" in text, text
    # the very arm it was made on with one drive replaced: that motor is named
    with _box_behind(box_toml, TrueArm.perturbed(load_actuation(model), 3)) as box:
        drive = box.drives["j05r1"]
        old = drive.params.serial_number
        drive.params = dataclasses.replace(drive.params, serial_number=0x00C0FFEE)
        text = _refusal([*hold, "--log-dir", str(runs / "e")], capsys)
    assert text.endswith(
        f"j05r1: drive serial 0x00C0FFEE is not the one calibrated (0x{old:08X}): run "
        "calibrate zero for it"
    ), text
    assert SIMULATOR_VENDOR_ID == 0  # the simulated drives' vendor (the EDS's)


@STALL_TOLERANT
def test_a_joint_slack_at_the_enable_names_the_calibration(
    store_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A calibration of this simulated arm whose joint-3 motor zeros are 5000 counts off:
    every rope of joint 3 goes slack as the drives take hold, and the stop says the
    calibration is the likely cause, not only "slack or broken"."""
    from calibration.apply import nominal_calibration, updated

    model = default_robot()
    base = nominal_calibration(model)
    zeros = {m: (-5000 if m.startswith("j03") else 0) for m in base.motor_ids}
    cal = updated(
        base,
        routine="zero",
        residuals={},
        motor_zero_counts=zeros,
        box=simulated_box_identity(model),
    )
    store = CalibrationStore(store_dir)
    assert store.save(cal) == 1
    rc = main(["run", "--hold", "2", "--sim", "--log-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert rc == 2, err
    (line,) = [x for x in err.splitlines() if "stopped" in x]
    assert "rope j03r" in line and "(slack or broken); every rope of joint 3 (j03r0 " in line
    assert f"likely the calibration in use (v0001, {store.path_of(1)})" in line, line


def _old_file(store_dir: Path) -> None:
    """Version 1 in an old format (``hrm-calibration/1``: no box, no physics), active."""
    from calibration.apply import nominal_calibration
    from calibration.store import checksum, to_json

    doc = json.loads(to_json(nominal_calibration(default_robot()), 1))
    del doc["box"], doc["physics"]
    doc["format"] = "hrm-calibration/1"
    doc["sha256"] = checksum(doc)
    store_dir.mkdir(parents=True)
    (store_dir / "v0001.json").write_text(json.dumps(doc))
    (store_dir / "active").write_text("v0001.json\n")


def test_an_old_file_is_box_unknown_until_confirmed_on_a_box(
    store_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _old_file(store_dir)
    store = CalibrationStore(store_dir)
    assert store.load(1).box is None  # read, its box unknown
    assert main(["calibrate", "history"]) == 0
    assert "box: unknown" in capsys.readouterr().out
    assert main(["calibrate", "show"]) == 0
    assert "\nbox: unknown (made before calibrations named their box" in capsys.readouterr().out
    # plan and ropes use it (no drives), and say which version
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    assert main(["ropes", str(plan)]) == 0
    err = capsys.readouterr().err
    assert f"hrm ropes: calibration v0001 ({store.path_of(1)}; manual, box unknown)" in err
    box_toml = _virtual_box(tmp_path)
    runs = tmp_path / "runs"
    hold = ["run", "--hold", "0.1", "--config", str(box_toml)]
    with _box_behind(box_toml, None) as box:
        text = _refusal([*hold, "--log-dir", str(runs / "a")], capsys)
        assert "box unknown (made before calibrations named their box)" in text, text
        assert "hrm calibrate use VERSION --box" in text
        # --box without a box to confirm it on, or with --sim's options: refused
        assert _refusal(["calibrate", "use", "1", "--box"], capsys).endswith(
            "use --box: give --config BOX.toml, the box to confirm it on"
        )
        rc = main(["calibrate", "use", "1", "--box", "--config", str(box_toml)])
        out = capsys.readouterr()
        assert rc == 0, out.err
        assert out.out.startswith(f"active: v0002 ({store.path_of(2)}): v0001 confirmed on this")
        serials = {m: d.params.serial_number for m, d in box.drives.items()}
    confirmed = store.load(2)
    assert store.active() == 2 and confirmed.box is not None and confirmed.box.simulated
    assert {m: d.serial for m, d in confirmed.box.drives.items()} == serials
    assert dict(confirmed.motor_zero_counts) == dict(store.load(1).motor_zero_counts)
    assert store.load(1).box is None  # the old file is never changed
    # a version that names its box is not confirmed again (a replaced drive: zero anew)
    text = _refusal(["calibrate", "use", "2", "--box", "--config", str(box_toml)], capsys)
    assert "names its box already (simulated box, 36 drives" in text, text
    # --sim uses none of them but its own arm's: the old file's box is unknown
    _refusal(["calibrate", "use", "1", "--config", str(box_toml)], capsys)  # --config: --box
    assert main(["calibrate", "use", "1"]) == 0
    capsys.readouterr()
    rc = main(["run", str(plan), "--sim", "--log-dir", str(runs / "b")])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "box unknown (made before calibrations named their box)" in err and "not used" in err
