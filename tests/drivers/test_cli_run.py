"""``hrm run``: a plan on the simulated box; bad input is one line, no files, no frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.model import default_robot
from hrm_ctrl.planfile import write_plan


def write_small_plan(path: Path) -> None:
    steps = []
    for k in range(4):
        a = float(np.deg2rad(3.0) * k / 3)
        steps.append(
            {
                "travel_mm": 5.0 * k,
                "alpha_rad": [a] * 12,
                "theta_rad": [0.0] * 12,
                "joints_mm": [[0.0, 0.0, 0.0]] * 13,
            }
        )
    plan = {
        "format": "hrm-plan/1",
        "robot": {"links_mm": [float(v) for v in default_robot().links]},
        "path_mm": [[0.0, 0.0, 0.0], [15.0, 0.0, 0.0]],
        "steps": steps,
        "report": {},
    }
    write_plan(path, plan)


def test_run_plan_on_the_simulated_box(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    plan = tmp_path / "plan.json"
    write_small_plan(plan)
    logs = tmp_path / "runs"
    rc = main(["run", str(plan), "--sim", "--log-dir", str(logs), "--speed", "60", "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True
    assert summary["cycles"] >= 26  # 15 mm at 60 mm/s = 0.25 s, + hold
    record = json.loads(Path(summary["run_record"]).read_text())
    assert record["plan_file"] == str(plan) and record["simulated_box"] is True
    assert record["setpoints"]["source"] == "plan"
    assert len(list(logs.glob("*.blf"))) == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.json"], "plan file not found"),
        (["--hold", "1", "--jog", "j01r0:1:1"], "give exactly one of"),
        (["--jog", "j01r0:9999999:1"], "jog j01r0: 9999999 counts/s exceeds"),
        (["--jog", "j01r0:fast"], "expected MOTOR:COUNTS_PER_S:SECONDS"),
        (["--hold", "1", "--config", "nope.toml"], "bus configuration not found"),
        (["--hold", "-1"], "--hold must be > 0 s"),
    ],
)
def test_bad_input_is_one_line_without_files(
    tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str], message: str
) -> None:
    logs = tmp_path / "runs"
    rc = main(["run", *args, "--sim", "--log-dir", str(logs)])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and err.count("\n") == 1, err
    assert not logs.exists()


def test_busload_command(capsys: pytest.CaptureFixture) -> None:
    assert main(["busload"]) == 0
    out = capsys.readouterr().out
    assert out.count("worst-case load 43.2%") == 2 and "163 Hz" in out
    assert main(["busload", "--rate", "200", "--json"]) == 1
    loads = json.loads(capsys.readouterr().out)
    assert [bl["fits"] for bl in loads] == [False, False]
