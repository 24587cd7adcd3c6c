"""``hrm drive`` driven by a key script: the status lines, the summary, the saved trail
(planned again by ``hrm plan --path``), and bad input as one line with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.planning.known_path import load_path_csv
from tests.hrm_ctrl.cli.cli_helpers import run_cli


def keys(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "keys.txt"
    f.write_text(text)
    return f


def test_drive_the_bent_pipe_entry_and_save_the_trail(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    k = keys(
        tmp_path, "0 advance down\n1 pitch_down down\n2 pitch_down up\n2.5 advance up\n3 end\n"
    )
    out = tmp_path / "trail.csv"
    argv = ["drive", "--scenario", "bent-pipe", "--keys", str(k), "--save-trail", str(out)]
    rc, stdout, err = run_cli([*argv, "--period", "0.05", "--json"], capsys)
    assert rc == 0, err
    summary = json.loads(stdout)
    assert summary["cycles"] == 61 and summary["refusals"] == []
    assert 40.0 < summary["travel_mm"] == pytest.approx(summary["trail_length_mm"])
    assert summary["worst_clearance_mm"] > 0.0
    lines = err.splitlines()
    assert lines and all(line.startswith("hrm drive: t ") for line in lines)
    trail = load_path_csv(out)
    assert np.allclose(trail.points[0], [1200.0, 100.0, 300.0])
    assert trail.points[-1][2] < 300.0  # pitched down
    rc, _, err = run_cli(["plan", "--path", str(out), "--fit", "paper"], capsys)
    assert rc == 0, err


def test_a_refusal_is_one_status_line_when_it_begins(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    k = keys(tmp_path, "0 retract down\n1 end\n")  # nothing behind the entry to retract
    rc, stdout, err = run_cli(
        ["drive", "--scenario", "bent-pipe", "--keys", str(k), "--period", "0.05", "--json"],
        capsys,
    )
    assert rc == 0, err
    summary = json.loads(stdout)
    assert len(summary["refusals"]) == 1 and "trail's start" in summary["refusals"][0]["text"]
    holds = [line for line in err.splitlines() if "HOLD:" in line]
    assert 1 <= len(holds) <= 3  # when it begins, and once a second


@pytest.mark.parametrize(
    ("script", "extra", "message"),
    [
        ("0 jump down\n", [], "keys.txt:1: unknown key 'jump'"),
        ("1 advance down\n0 advance up\n", [], "keys.txt:2: time 0 s goes back"),
        ("0 advance down\n", ["--advance-speed", "-1"], "advance_mm_s: expected a number > 0"),
        ("0 advance down\n", ["--save-trail", "KEYS"], "--save-trail"),
        ("0 advance down\n", ["--physics", "gravity"], "--physics goes with --sim"),
        ("0 advance down\n", ["--sim", "--physics", "gravty"], "unknown effect 'gravty'"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    script: str,
    extra: list[str],
    message: str,
) -> None:
    k = keys(tmp_path, script)
    extra = [str(k) if a == "KEYS" else a for a in extra]
    before = k.read_text()
    rc, stdout, err = run_cli(
        ["drive", "--scenario", "bent-pipe", "--keys", str(k), *extra], capsys
    )
    assert rc == 2 and stdout == ""
    assert message in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keys.txt"]
    assert k.read_text() == before
