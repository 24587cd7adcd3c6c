"""``hrm demo``: the whole stack on the in-process simulated box."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import read_plan


@pytest.mark.parametrize("wire", ["virtual", "hrm_sim"])
def test_demo_plays_a_scenario_on_the_simulated_box(
    wire: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(
        ["demo", "--scenario", "cabins", "--out", str(tmp_path), "--speed", "50", "--wire", wire]
    )
    out, err = capsys.readouterr()
    assert rc == 0, err
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert summary["run"]["completed"] is True
    assert summary["run"]["causes"] == []
    tr = summary["tracking"]
    assert tr["compared_cycles"] > 0.8 * tr["body_cycles"]
    assert tr["max_error_mm"] < 1.0
    assert tr["median_lag_cycles"] == 1  # a drive reaches a setpoint at the next SYNC
    assert tr["p95_lag_cycles"] <= 2
    plan = read_plan(tmp_path / "plan.json")
    assert plan.report["tip_error_mm"] < 0.01
    assert {p.name for p in (tmp_path / "figures").iterdir()} == {
        "angles.png",
        "arm.png",
        "backbone.png",
        "clearance.png",
    }
    logs = summary["can_logs"]
    assert len(logs) == 2
    for log in logs:
        frames = list(can.LogReader(log))
        assert any(f.arbitration_id == 0x80 for f in frames)  # SYNC
        assert any(0x200 < f.arbitration_id < 0x280 for f in frames)  # RPDO1 setpoints
    assert "simulated arm vs plan" in out


def test_demo_refuses_bad_input_before_anything_is_written(tmp_path: Path, capsys) -> None:
    rc = main(["demo", "--out", str(tmp_path / "d"), "--speed", "-1"])
    _, err = capsys.readouterr()
    assert rc == 2 and "--speed must be > 0" in err and err.count("\n") == 1
    assert not (tmp_path / "d").exists()
