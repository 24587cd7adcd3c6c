"""``hrm run --sim --perturb SEED | --truth FILE``: the in-process box with a true arm that
differs from its description; without a calibration of it, its ropes are far from their
pretension and the tension watch stops the run before anything moves far."""

from __future__ import annotations

import json
from pathlib import Path

from tests.hrm_ctrl.cli.cli_helpers import run_cli as run
from tests.hrm_ctrl.cli.cli_helpers import small_plan


def test_a_true_arm_needs_the_simulated_box(tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.setenv("HRM_CALIBRATIONS", str(tmp_path / "cal"))
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps(small_plan()))
    rc, _, err = run(["run", str(plan), "--perturb", "3", "--log-dir", str(tmp_path)], capsys)
    assert rc == 2 and "go with --sim" in err and err.count("\n") == 1
    rc, _, err = run(["run", str(plan), "--sim", "--perturb", "3", "--truth", "t.toml"], capsys)
    assert rc == 2 and "not allowed with" in err
    # a bad seed or truth file: the one error line, not the no-calibration note before it
    for bad in (["--perturb", "-1"], ["--truth", str(tmp_path / "none.toml")]):
        rc, out, err = run(["run", str(plan), "--sim", *bad, "--log-dir", str(tmp_path)], capsys)
        assert rc == 2 and err.count("\n") == 1 and "error" in err and out == "", err


def test_an_uncalibrated_perturbed_arm_is_stopped_by_its_tensions(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    monkeypatch.setenv("HRM_CALIBRATIONS", str(tmp_path / "cal"))
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps(small_plan()))
    argv = ["run", str(plan), "--sim", "--perturb", "3", "--log-dir", str(tmp_path / "runs")]
    rc, _, err = run(argv, capsys)
    assert rc == 2
    assert "tension" in err and ("slack" in err or "above" in err)
