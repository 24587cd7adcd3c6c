"""``hrm ropes PLAN.json [--robot FILE] [--out SETPOINTS.csv]``."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation


def make_plan(n: int = 20, scale: float = 0.6, travel_step: float = 5.0) -> dict[str, Any]:
    robot = default_robot()
    s = np.linspace(0.0, 1.0, n)[:, None]
    ph = np.arange(12)[None, :]
    alpha = scale * s * np.sin(0.7 * ph)
    theta = scale * s * np.cos(0.5 * ph)
    O = joint_centres(robot, alpha, theta)
    steps = [
        {
            "travel_mm": travel_step * i,
            "alpha_rad": alpha[i].tolist(),
            "theta_rad": theta[i].tolist(),
            "joints_mm": O[i].tolist(),
        }
        for i in range(n)
    ]
    return {
        "format": "hrm-plan/1",
        "robot": {"links_mm": robot.links.tolist()},
        "path_mm": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
        "steps": steps,
        "report": {},
    }


def write(tmp_path: Path, plan: dict[str, Any], name: str = "plan.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(plan))
    return p


def test_setpoint_table_and_summary(
    tmp_path: Path, act: Actuation, capsys: pytest.CaptureFixture
) -> None:
    plan = make_plan()
    out = tmp_path / "sp.csv"
    assert main(["ropes", str(write(tmp_path, plan)), "--out", str(out)]) == 0
    rows = list(csv.reader(out.open()))
    assert rows[0] == ["t_s", "step", "travel_mm", *act.motor_ids]
    assert len(rows) == 21
    table = np.array([[int(v) for v in r[3:]] for r in rows[1:]])
    expected = act.counts_from_angles(
        np.array([s["alpha_rad"] for s in plan["steps"]]),
        np.array([s["theta_rad"] for s in plan["steps"]]),
    )
    np.testing.assert_array_equal(table, expected)
    t_s = np.array([float(r[0]) for r in rows[1:]])
    assert t_s[0] == 0.0 and np.all(np.diff(t_s) > 0)  # when the playback passes each step
    text = capsys.readouterr().out
    assert "20 steps, 36 rope motors" in text and "largest travel" in text
    assert "j12r2" in text
    # 95 mm with the tip at most the default 50 mm/s, at the shipped box's 100 Hz, with the
    # ramps from and to rest
    assert "played with the tip at most 50 mm/s: " in text and "control cycles of 10 ms" in text
    assert float(t_s[-1]) >= 95.0 / 50.0 and "hardest accelerating" in text


def test_every_control_cycle_table(tmp_path: Path, act: Actuation) -> None:
    """``--cycles``: the trajectory hrm run plays, with its time column, differentiable."""
    from hrm_ctrl.ropes.trajectory import finite_differences

    out = tmp_path / "cycles.csv"
    assert main(["ropes", str(write(tmp_path, make_plan())), "--cycles", "--out", str(out)]) == 0
    header, *rows = list(csv.reader(out.open()))
    assert header[:3] == ["t_s", "step", "travel_mm"]
    t_s = np.array([float(r[0]) for r in rows])
    np.testing.assert_allclose(np.diff(t_s), 0.01, atol=1e-6)
    travel = np.array([float(r[2]) for r in rows])
    assert travel[0] == 0.0 and travel[-1] == pytest.approx(95.0) and np.all(np.diff(travel) >= 0)
    assert np.diff(travel).max() / 0.01 <= 50.0 + 1e-6  # the tip-speed cap
    counts = np.array([[int(v) for v in r[3:]] for r in rows])
    v, a = finite_differences(counts, 0.01)
    assert np.all(v <= act.max_rate_counts_per_s) and np.all(a <= act.max_accel_counts_per_s2)


def test_json_summary(tmp_path: Path, act: Actuation, capsys: pytest.CaptureFixture) -> None:
    assert main(["ropes", str(write(tmp_path, make_plan())), "--json", "--speed", "10"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["steps"] == 20 and len(s["motors"]) == 36
    m = s["motors"][0]
    assert m["largest_travel_step"] == 19  # the bend grows along the plan
    assert m["largest_change_counts"] > 0
    assert 0 < m["peak_rate_counts_per_s"] < m["rate_limit_counts_per_s"]
    assert 0 < m["peak_accel_counts_per_s2"] <= m["accel_limit_counts_per_s2"]
    pb = s["playback"]
    assert pb["speed_mm_per_s"] == 10.0 and pb["period_s"] == 0.01
    assert 9.5 <= pb["duration_s"] <= 9.8  # 95 mm at up to 10 mm/s, from and to rest
    assert pb["cycles"] == round(pb["duration_s"] / 0.01) + 1


def test_a_plan_with_a_return_leg(tmp_path: Path, act: Actuation, capsys) -> None:
    """Out and back: travel goes down again on the return steps, and the plan plays."""
    plan = make_plan(n=10)
    back = [dict(st, phase="return") for st in plan["steps"][-2::-1]]
    plan["steps"] = [dict(st, phase="in") for st in plan["steps"]] + back
    out = tmp_path / "sp.csv"
    assert main(["ropes", str(write(tmp_path, plan)), "--out", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["steps"] == 19 and s["travel_mm"] == [0.0, 0.0]
    assert 1.8 <= s["playback"]["duration_s"] <= 2.2  # 45 mm in and back at up to 50 mm/s
    rows = list(csv.reader(out.open()))[1:]
    table = np.array([[int(v) for v in r[3:]] for r in rows])
    np.testing.assert_array_equal(table[10:], table[8::-1])  # back the way it came
    t_s = [float(r[0]) for r in rows]
    assert t_s[9] == pytest.approx(t_s[-1] / 2, abs=0.011)  # the far end half way


def bad_plans() -> list[tuple[str, Any, str]]:
    p1 = make_plan()
    p1["format"] = "hrm-plan/0"
    p2 = make_plan()
    p2["steps"][7]["alpha_rad"][4] = 1.3
    p3 = make_plan()
    p3["robot"]["links_mm"][0] = 100.0
    return [
        ("format", p1, "expected 'hrm-plan/1'"),
        ("limit", p2, "plan step 7 (travel 35.0 mm): joint 5: alpha"),
        ("robot", p3, "plan was made for links"),
        ("notjson", "{not json", "not JSON"),
    ]


@pytest.mark.parametrize(
    ("label", "plan", "match"),
    bad_plans(),
    ids=lambda v: v if isinstance(v, str) and len(v) < 10 else "",
)
def test_bad_plans_one_line_no_output(
    tmp_path: Path, capsys: pytest.CaptureFixture, label: str, plan: Any, match: str
) -> None:
    p = tmp_path / "plan.json"
    p.write_text(plan if isinstance(plan, str) else json.dumps(plan))
    out = tmp_path / "sp.csv"
    assert main(["ropes", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_a_cap_faster_than_the_motors_plays_at_their_limits(
    tmp_path: Path, act: Actuation, capsys: pytest.CaptureFixture
) -> None:
    """A tip-speed cap the motors cannot follow: the playback is as fast as their speed
    and acceleration allow, within both (it used to be refused)."""
    plan = make_plan(n=20, scale=0.9)
    out = tmp_path / "sp.csv"
    assert main(["ropes", str(write(tmp_path, plan)), "--out", str(out), "--speed", "5000"]) == 0
    text = capsys.readouterr().out
    assert "played with the tip at most 5000 mm/s" in text
    assert main(["ropes", str(write(tmp_path, plan)), "--speed", "5000", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    rate = max(m["peak_rate_counts_per_s"] / m["rate_limit_counts_per_s"] for m in s["motors"])
    acc = max(m["peak_accel_counts_per_s2"] / m["accel_limit_counts_per_s2"] for m in s["motors"])
    assert 0.8 < max(rate, acc) <= 1.0 and rate <= 1.0 and acc <= 1.0  # near time-optimal
    assert s["playback"]["duration_s"] > 95.0 / 5000 * 5
    assert main(["ropes", str(write(tmp_path, plan)), "--speed", "-1"]) == 2
    assert "--speed" in capsys.readouterr().err


def test_bad_robot_routing_and_missing_files(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from importlib import resources

    text = resources.files("hrm_ctrl.data").joinpath("robot.toml").read_text()
    bad = tmp_path / "robot.toml"
    bad.write_text(text.replace("hole_radius_mm = 12.0", "hole_radius_mm = 15.0"))
    plan = write(tmp_path, make_plan())
    out = tmp_path / "sp.csv"
    assert main(["ropes", str(plan), "--robot", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "robot.toml" in err and "outside the 30 mm disk" in err and err.count("\n") == 1
    bad.write_text(text.replace("direction = 1", "direction = { j99r0 = -1 }"))
    assert main(["ropes", str(plan), "--robot", str(bad)]) == 2
    assert "unknown motor id 'j99r0'" in capsys.readouterr().err
    assert main(["ropes", str(tmp_path / "none.json")]) == 2
    assert "plan file not found" in capsys.readouterr().err
    assert not out.exists()
