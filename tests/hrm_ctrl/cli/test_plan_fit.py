"""Issue 10 through ``hrm plan``: the clearance fit by default where an environment is
known (``--fit paper`` keeps the paper's), planning along a scan (``--scan``) inside the
fitted pipe, and ``--round-corners`` making a sharp polyline followable."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.scan import synthetic_pipe_scan
from hrm_ctrl.planning.scenarios import scenario
from tests.hrm_ctrl.cli.cli_helpers import run_cli as run


def test_bent_pipe_is_refined_by_default_and_the_paper_fit_collides(capsys) -> None:
    rc, out, err = run(["plan", "--scenario", "bent-pipe", "--json"], capsys)
    assert rc == 0, err
    r = json.loads(out)
    assert r["fit"] == "clearance"
    assert r["clearance_mm"]["min"] >= 5.0  # link axes within 15 mm of the pipe axis
    assert r["joint_limit_margin_deg"] >= 5.0
    rc, out, err = run(["plan", "--scenario", "bent-pipe", "--fit", "paper"], capsys)
    assert rc == 2 and "meets an obstacle" in err and err.count("\n") == 1


def test_plan_along_a_scan_stays_inside_the_scanned_pipe(tmp_path: Path, capsys) -> None:
    bp = scenario("bent-pipe")
    cloud = synthetic_pipe_scan(
        bp.path, 70.0, 60_000, noise_mm=0.5, outlier_fraction=0.02, rng=np.random.default_rng(4)
    )
    scan = tmp_path / "pipe.npy"
    np.save(scan, cloud)
    out = tmp_path / "plan.json"
    rc, stdout, err = run(["plan", "--scan", str(scan), "--json", "--out", str(out)], capsys)
    assert rc == 0, err
    r = json.loads(stdout.split("\nplan written")[0])
    assert r["fit"] == "clearance" and r["clearance_mm"]["min"] > 4.0
    doc = json.loads(out.read_text())
    end = np.asarray(doc["steps"][-1]["joints_mm"][-1])
    assert float(np.linalg.norm(end - bp.path.points[-1])) < 1.0  # the scan's far end
    rc, _, err = run(["plan", "--scan", str(scan), "--out", str(scan)], capsys)
    assert rc == 2 and "point cloud" in err  # never an output over an input


def test_round_corners_makes_the_cabins_corner_followable(tmp_path: Path, capsys) -> None:
    A, B, C = (1200.0, 100.0, 300.0), (1470.0, 190.0, 300.0), (1470.0, -50.0, 200.0)
    csv = tmp_path / "abc.csv"
    csv.write_text("x,y,z\n" + "\n".join(",".join(f"{v:g}" for v in p) for p in (A, B, C)))
    rc, _, err = run(["plan", "--path", str(csv), "--fit", "paper"], capsys)
    assert "cannot" in err or "can't" in err or "corner" in err  # the conditioning warning
    rc, out, err = run(["plan", "--path", str(csv), "--round-corners", "150", "--json"], capsys)
    assert rc == 0, err
    assert "warning" not in err
    r = json.loads(out)
    assert r["first_violation"] is None
    rounded = scenario("cabins").path
    assert abs(r["path_length_mm"] - KnownPath.from_points(rounded.points).length) < 1e-6
    rc, _, err = run(["plan", "--scenario", "cabins", "--round-corners", "150"], capsys)
    assert rc == 2 and "--round-corners" in err
    rc, _, err = run(["plan", "--path", str(csv), "--round-corners", "nan"], capsys)
    assert rc == 2 and "--round-corners" in err


def helix_csv(tmp_path: Path, radius: float, pitch: float, turns: float) -> Path:
    t = np.linspace(0.0, 2.0 * np.pi * turns, 200)
    pts = np.c_[
        1200.0 + pitch * t / (2 * np.pi),
        100.0 + radius * np.sin(t),
        300.0 + radius * (1 - np.cos(t)),
    ]
    csv = tmp_path / "helix.csv"
    csv.write_text("x,y,z\n" + "\n".join(",".join(f"{v:.6f}" for v in p) for p in pts))
    return csv


def test_a_bare_path_gets_the_margin_fit_by_default(tmp_path: Path, capsys) -> None:
    """Issue 39: no environment, no flag: the joint-limit margin fit, not the paper's."""
    csv = helix_csv(tmp_path, 100.0, 300.0, 0.5)
    rc, out, err = run(["plan", "--path", str(csv), "--step", "10", "--json"], capsys)
    assert rc == 0, err
    r = json.loads(out)
    assert r["fit"] == "clearance" and r["joint_limit_margin_deg"] >= 3.0
    assert r["margin_statement"].startswith("joint-limit margin")
    rc, out, err = run(
        ["plan", "--path", str(csv), "--step", "10", "--fit", "paper", "--json"], capsys
    )
    assert rc == 0, err
    assert "fit" not in json.loads(out)  # the paper's plan, as before


def test_beyond_the_paper_is_said_in_the_report(tmp_path: Path, capsys) -> None:
    csv = helix_csv(tmp_path, 60.0, 150.0, 0.5)  # the paper's fit breaks joint 12
    rc, out, err = run(["plan", "--path", str(csv), "--step", "10"], capsys)
    assert rc == 0, err
    assert "beyond the paper's family: its fit breaks joint" in out
    rc, _, err = run(["plan", "--path", str(csv), "--step", "10", "--fit", "paper"], capsys)
    assert rc == 2 and "joint limit broken" in err
