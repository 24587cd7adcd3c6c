"""``hrm scan``: from a scan file to a path file ``hrm plan --path`` reads; bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.planning.known_path import load_path_csv
from hrm_ctrl.planning.scan import synthetic_pipe_scan
from hrm_ctrl.planning.scenarios import scenario
from tests.hrm_ctrl.cli.cli_helpers import run_cli as run

BENT = scenario("bent-pipe").path


@pytest.fixture(scope="module")
def cloud() -> np.ndarray:
    return synthetic_pipe_scan(BENT, 70.0, 30_000, 0.5, 0.02, np.random.default_rng(21))


def test_scan_writes_a_path_file_that_plan_reads(tmp_path: Path, cloud, capsys) -> None:
    src = tmp_path / "pipe.npy"
    np.save(src, cloud)
    out = tmp_path / "axis" / "centre.csv"
    rc, stdout, err = run(["scan", str(src), "--out", str(out)], capsys)
    assert rc == 0, err
    assert "inner diameter" in stdout and "rms" in stdout and "p95" in stdout
    assert f"written to {out}" in stdout
    path = load_path_csv(out)
    assert np.linalg.norm(path.points[0] - BENT.points[0]) < 2.0  # starts nearest the base
    assert BENT.distance_to(path.points).max() < 1.0
    rc, stdout, err = run(["plan", "--path", str(out), "--step", "50"], capsys)
    assert rc == 0, err
    assert "joint-limit margin" in stdout


def test_scan_json(tmp_path: Path, cloud, capsys) -> None:
    src = tmp_path / "pipe.csv"
    np.savetxt(src, cloud, delimiter=",", header="x,y,z", comments="", fmt="%.6f")
    rc, stdout, err = run(["scan", str(src), "--json"], capsys)
    assert rc == 0, err
    doc = json.loads(stdout)
    assert abs(doc["inner_diameter_mm"] - 70.0) < 1.0
    assert doc["points"] == len(cloud) and 0 < doc["outliers"] < 0.05 * len(cloud)
    assert doc["out"] is None and doc["rms_mm"] < 0.6
    assert doc["axis_length_mm"] == pytest.approx(BENT.length, abs=3.0)


def test_bad_input_exits_2_with_one_line_and_writes_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "centre.csv"
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z\n1,2,3\n1,nan,3\n")
    blob = tmp_path / "blob.npy"
    np.save(blob, np.random.default_rng(2).normal(0, 100, (5000, 3)))
    for argv, match in [
        (["scan", str(bad), "--out", str(out)], "bad.csv:3: y is not finite"),
        (["scan", str(tmp_path / "none.ply"), "--out", str(out)], "point cloud not found"),
        (["scan", str(blob), "--out", str(out)], "a scan of a pipe's inner wall"),
        (["scan", str(bad), "--out", str(bad)], "would overwrite the point cloud"),
    ]:
        rc, _, err = run(argv, capsys)
        assert rc == 2, (argv, err)
        assert err.startswith("hrm scan: error: ") and match in err, err
        assert err.count("\n") == 1
        assert not out.exists()
    assert bad.read_text() == "x,y,z\n1,2,3\n1,nan,3\n"  # the input is untouched


def test_an_unwritable_output_is_one_line(tmp_path: Path, cloud, capsys) -> None:
    src = tmp_path / "pipe.npy"
    np.save(src, cloud)
    blocker = tmp_path / "file"
    blocker.write_text("")
    rc, _, err = run(["scan", str(src), "--out", str(blocker / "x.csv")], capsys)
    assert rc == 2 and "cannot write path file" in err and err.count("\n") == 1
