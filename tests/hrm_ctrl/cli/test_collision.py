"""Issue 10: a collision is not a warning. ``hrm plan`` refuses a plan whose arm meets an
obstacle (exit 2, one line naming step and link, nothing written) and ``hrm run`` a plan file
that states or hides one (before any bus opens), unless ``--allow-collision``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import read_plan, write_plan
from tests.hrm_ctrl.cli.cli_helpers import run_cli as run
from tests.hrm_ctrl.cli.cli_helpers import small_plan

# a straight path along +x in front of the base, and a box 40 mm wide across it
PATH_CSV = "x,y,z\n1200,0,0\n1300,0,0\n1400,0,0\n"
BOX_ON_PATH = "[[box]]\ncentre_mm = [1350, 0, 0]\nsize_mm = [20, 40, 40]\n"
BOX_BESIDE = "[[box]]\ncentre_mm = [1350, 0, 200]\nsize_mm = [20, 40, 40]\n"


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    f = {
        "path": tmp_path / "p.csv",
        "on": tmp_path / "on.toml",
        "beside": tmp_path / "beside.toml",
        "empty": tmp_path / "empty.toml",
    }
    f["path"].write_text(PATH_CSV)
    f["on"].write_text(BOX_ON_PATH)
    f["beside"].write_text(BOX_BESIDE)
    f["empty"].write_text('description = "free space"\n')
    return f


def test_plan_through_a_box_is_refused_and_writes_nothing(files, tmp_path, capsys) -> None:
    out, fig = tmp_path / "plan.json", tmp_path / "fig"
    argv = ["plan", "--path", str(files["path"]), "--scene", str(files["on"])]
    rc, stdout, err = run([*argv, "--out", str(out), "--plot", str(fig)], capsys)
    assert rc == 2
    assert err.count("\n") == 1 and "meets an obstacle at step" in err and "link 12" in err
    assert "COLLISION" in stdout
    assert not out.exists() and not fig.exists()
    rc, _, err = run([*argv, "--out", str(out), "--plot", str(fig), "--allow-collision"], capsys)
    assert rc == 0, err
    assert err.startswith("hrm plan: warning: link 12 meets an obstacle")
    doc = read_plan(out)
    assert doc.environment is not None and doc.clearance["min"] < 0.0
    assert (fig / "clearance.png").exists()


def test_plan_beside_a_box_is_written_with_its_clearance(files, tmp_path, capsys) -> None:
    out = tmp_path / "plan.json"
    argv = ["plan", "--path", str(files["path"]), "--scene", str(files["beside"])]
    rc, stdout, err = run([*argv, "--out", str(out), "--json"], capsys)
    assert rc == 0, err
    c = json.loads(stdout[: stdout.rindex("}") + 1])["clearance_mm"]
    # the end link passes 180 mm below the box (z = 180 its face), less its 15 mm radius
    assert c["min"] == pytest.approx(165.0, abs=0.5)
    assert read_plan(out).clearance["min"] == pytest.approx(c["min"])


def test_scene_replaces_the_scenarios_environment(files, tmp_path, capsys) -> None:
    rc, stdout, err = run(
        ["plan", "--scenario", "bent-pipe", "--scene", str(files["empty"])], capsys
    )
    assert rc == 0, err  # no pipe: nothing to collide with
    assert "no link meets an obstacle" in stdout


def test_a_bad_scene_file_is_one_line(files, tmp_path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[[box]]\ncentre_mm = [0, 0, 0]\nsize_mm = [1, -1, 1]\n")
    out = tmp_path / "plan.json"
    rc, _, err = run(
        ["plan", "--path", str(files["path"]), "--scene", str(bad), "--out", str(out)], capsys
    )
    assert rc == 2 and err.count("\n") == 1
    assert "bad.toml: box[0].size_mm[1]: expected a number > 0" in err
    assert not out.exists()


def test_plan_refuses_to_write_over_its_scene(files, capsys) -> None:
    argv = ["plan", "--path", str(files["path"]), "--scene", str(files["on"])]
    rc, _, err = run([*argv, "--out", str(files["on"])], capsys)
    assert rc == 2 and "scene file" in err and err.count("\n") == 1
    assert files["on"].read_text() == BOX_ON_PATH


# ---- hrm run -----------------------------------------------------------------------------


def colliding_plan(summary: dict[str, Any] | None) -> dict[str, Any]:
    """The small plan (every joint at the origin) in a box around the origin."""
    plan = small_plan()
    plan["scenario"] = {
        "name": "boxed",
        "environment": {"box": [{"centre_mm": [0, 0, 0], "size_mm": [50, 50, 50]}]},
    }
    if summary is not None:
        plan["report"]["clearance_mm"] = summary
    return plan


@pytest.mark.parametrize(
    "summary",
    [
        {"min": -40.0, "step": 0, "link": 1},  # stated
        {"min": 12.0, "step": 3, "link": 2},  # edited: the environment says otherwise
        None,  # none stated
    ],
    ids=["stated", "edited", "unstated"],
)
def test_run_refuses_a_colliding_plan_before_any_bus_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[Any], summary: Any
) -> None:
    plan, logs = tmp_path / "plan.json", tmp_path / "runs"
    write_plan(plan, colliding_plan(summary))
    rc = main(["run", str(plan), "--sim", "--log-dir", str(logs)])
    err = capsys.readouterr().err
    assert rc == 2
    errors = [x for x in err.splitlines() if x.startswith("hrm run: error: ")]
    assert len(errors) == 1 and "meets an obstacle at step" in errors[0], err
    assert "--allow-collision" in errors[0]
    assert no_bus == [] and not logs.exists()


def test_run_refuses_a_stated_collision_without_an_environment(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[Any]
) -> None:
    plan = small_plan()
    plan["report"]["clearance_mm"] = {"min": -1.5, "step": 2, "link": 9}
    write_plan(tmp_path / "plan.json", plan)
    rc = main(["run", str(tmp_path / "plan.json"), "--sim", "--log-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2 and "link 9 meets an obstacle at step 2 (clearance -1.50 mm)" in err
    assert no_bus == []


def test_run_plays_a_colliding_plan_with_allow_collision(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    plan, logs = tmp_path / "plan.json", tmp_path / "runs"
    write_plan(plan, colliding_plan({"min": -40.0, "step": 0, "link": 1}))
    assert main(["run", str(plan), "--sim", "--log-dir", str(logs)]) == 2
    capsys.readouterr()
    argv = ["run", str(plan), "--sim", "--log-dir", str(logs), "--speed", "60", "--json"]
    rc = main([*argv, "--allow-collision"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "hrm run: warning: " in out.err and "--allow-collision" in out.err
    assert json.loads(out.out)["completed"] is True


# ---- red team (issue 10): edited plan files cannot hide a collision ----------------------


@pytest.mark.parametrize("od", ["abc", [30.0, 30.0], [-1000.0] * 12, {"a": 1}, 0.0, True], ids=repr)
def test_run_refuses_an_edited_link_diameter(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[Any], od: Any
) -> None:
    """Found: a string or a short list was a traceback, a negative diameter (radius -500 mm)
    made the colliding arm clear by 475 mm and the plan was played."""
    plan = colliding_plan(None)
    plan["robot"]["outer_diameter_mm"] = od
    write_plan(tmp_path / "plan.json", plan)
    rc = main(["run", str(tmp_path / "plan.json"), "--sim", "--log-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [x for x in err.splitlines() if x.startswith("hrm run: error: ")]
    assert len(lines) == 1 and "robot.outer_diameter_mm: expected a number > 0" in lines[0]
    assert "Traceback" not in err and no_bus == []


def test_run_refuses_a_collision_hidden_by_edited_joint_centres(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[Any]
) -> None:
    """Found: the check used the stored joint centres only; moved 5 m away (the angles, which
    are what is played, unchanged) they hid the arm's collision with a box around it."""
    import numpy as np

    from hrm_ctrl.kinematics import joint_centres
    from hrm_ctrl.model import default_robot

    plan = small_plan()
    a = np.array([st["alpha_rad"] for st in plan["steps"]])
    O = joint_centres(default_robot(), a, np.zeros_like(a))
    middle = O[0, 6].tolist()
    for st, Ok in zip(plan["steps"], O, strict=True):
        st["joints_mm"] = (Ok + np.array([0.0, 0.0, 5000.0])).tolist()
    plan["scenario"] = {
        "name": "boxed",
        "environment": {"box": [{"centre_mm": middle, "size_mm": [60, 60, 60]}]},
    }
    plan["report"]["clearance_mm"] = {"min": 4000.0, "step": 0, "link": 1}
    write_plan(tmp_path / "plan.json", plan)
    rc = main(["run", str(tmp_path / "plan.json"), "--sim", "--log-dir", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [x for x in err.splitlines() if x.startswith("hrm run: error: ")]
    assert len(lines) == 1 and "meets an obstacle at step" in lines[0], err
    assert no_bus == []
