"""``hrm plan``: outputs, and every bad input of the planner issue."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hrm_ctrl.formats.planfile import read_plan
from tests.hrm_ctrl.cli.cli_helpers import run_cli as run


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_plan_scenario_writes_plan_and_figures(tmp_path: Path, capsys) -> None:
    out = tmp_path / "plan.json"
    rc, stdout, err = run(
        [
            "plan",
            "--scenario",
            "cabins",
            "--return",
            "--out",
            str(out),
            "--plot",
            str(tmp_path / "fig"),
            "--allow-collision",  # the paper plan grazes the partition's rim (-0.3 mm)
        ],
        capsys,
    )
    assert rc == 0, err
    assert "joint-limit margin" in stdout and "clearance" in stdout
    plan = read_plan(out)
    assert plan.phase[-1] == "return"
    assert sorted(p.name for p in (tmp_path / "fig").iterdir()) == [
        "angles.png",
        "arm.png",
        "backbone.png",
        "clearance.png",
    ]


def test_plan_from_a_path_file_with_duplicates_warns(tmp_path: Path, capsys) -> None:
    path = write(tmp_path, "p.csv", "x,y,z\n1200,0,0\n1200,0,0\n1300,0,0\n1400,20,0\n")
    rc, stdout, err = run(["plan", "--path", str(path), "--json"], capsys)
    assert rc == 0
    assert "warning: " in err and "dropped 1" in err
    assert json.loads(stdout)["tip_error_mm"] < 0.01


BAD_PATHS = {
    "empty": ("", "empty"),
    "header-only": ("x,y,z\n", "no points"),
    "non-numeric": ("x,y,z\n1200,0,0\n1300,a,0\n", "line 3" if False else ":3: y is not a number"),
    "nan": ("x,y,z\n1200,0,0\n1300,nan,0\n", "not finite"),
    "inf": ("x,y,z\n1200,0,0\n1300,0,inf\n", "not finite"),
    "one-point": ("x,y,z\n1200,0,0\n1200,0,0\n", "at least 2 distinct points"),
    "two-columns": ("x,y,z\n1200,0\n1300,0\n", "expected 3 columns"),
    "out-of-reach": ("x,y,z\n2500,0,0\n2600,0,0\n", "only"),
    "cannot-follow": ("x,y,z\n1200,0,0\n2400,0,0\n", "step"),
}


@pytest.mark.parametrize("case", sorted(BAD_PATHS))
def test_bad_paths_fail_cleanly(case: str, tmp_path: Path, capsys) -> None:
    text, message = BAD_PATHS[case]
    path = write(tmp_path, "p.csv", text)
    out = tmp_path / "plan.json"
    rc, _stdout, err = run(
        ["plan", "--path", str(path), "--out", str(out), "--plot", str(tmp_path / "fig")], capsys
    )
    assert rc == 2
    assert message in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "fig").exists()


def test_missing_path_file(tmp_path: Path, capsys) -> None:
    rc, _, err = run(["plan", "--path", str(tmp_path / "none.csv")], capsys)
    assert rc == 2 and "not found" in err and err.count("\n") == 1


BAD_ROBOTS = {
    "not-toml": ("links_mm = [1, 2", "not valid TOML"),
    "missing": (
        "outer_diameter_mm = 30\n[joint_limits]\nalpha_deg = 60\ntheta_deg = 60\n"
        "[base]\nposition_mm = [0, 0, 0]\n",
        "missing key 'links_mm'",
    ),
    "negative": (
        "links_mm = [179, 179, 179, 179, 179, 179, 179, 179, 179, 130, 130, -136]\n"
        "outer_diameter_mm = 30\n[joint_limits]\nalpha_deg = 60\ntheta_deg = 60\n"
        "[base]\nposition_mm = [0, 0, 0]\n",
        "links_mm[11]: must be > 0",
    ),
    "non-numeric": (
        'links_mm = [179, 179, 179, 179, 179, 179, 179, 179, 179, 130, 130, "x"]\n'
        "outer_diameter_mm = 30\n[joint_limits]\nalpha_deg = 60\ntheta_deg = 60\n"
        "[base]\nposition_mm = [0, 0, 0]\n",
        "links_mm[11]: expected a number",
    ),
    "no-limits": (
        "links_mm = [179, 179, 179, 179, 179, 179, 179, 179, 179, 130, 130, 136]\n"
        "outer_diameter_mm = 30\n[base]\nposition_mm = [0, 0, 0]\n",
        "missing table [joint_limits]",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_ROBOTS))
def test_bad_robot_files_fail_cleanly(case: str, tmp_path: Path, capsys) -> None:
    text, message = BAD_ROBOTS[case]
    robot = write(tmp_path, "robot.toml", text)
    out = tmp_path / "plan.json"
    rc, _, err = run(
        ["plan", "--scenario", "bent-pipe", "--robot", str(robot), "--out", str(out)], capsys
    )
    assert rc == 2
    assert message in err and "robot.toml" in err
    assert err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize("step", ["0", "-5", "nan"])
def test_step_must_be_positive(step: str, tmp_path: Path, capsys) -> None:
    out = tmp_path / "plan.json"
    rc, _, err = run(
        ["plan", "--scenario", "bent-pipe", f"--step={step}", "--out", str(out)], capsys
    )
    assert rc == 2 and "--step must be a finite number > 0" in err and err.count("\n") == 1
    assert not out.exists()


def test_usage_errors_are_one_line(capsys) -> None:
    rc, _, err = run(["plan", "--scenario", "nowhere"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "invalid choice" in err
    rc, _, err = run(["plan"], capsys)
    assert rc == 2 and err.count("\n") == 1


# A corner the arm cannot take within +-60 deg: 90 deg, then far enough on for
# several links to lie on both legs.
SHARP = "x,y,z\n1100,0,0\n1400,0,0\n1400,300,0\n"


def test_joint_limit_violation_names_step_joint_angle_and_writes_nothing(
    tmp_path: Path, capsys
) -> None:
    path = write(tmp_path, "sharp.csv", SHARP)
    out = tmp_path / "plan.json"
    # the paper's fit: the default (refined, beyond the paper's family) follows this corner
    rc, stdout, err = run(
        ["plan", "--path", str(path), "--fit", "paper", "--out", str(out)], capsys
    )
    assert rc == 2
    assert "joint limit broken at step" in err and "joint" in err and "deg" in err
    assert "BROKEN" in stdout
    assert not out.exists()
    rc, _, err = run(
        ["plan", "--path", str(path), "--fit", "paper", "--out", str(out), "--allow-violations"],
        capsys,
    )
    assert rc == 0
    assert read_plan(out).report["first_violation"]["step"] > 0


def test_real_process_prints_no_traceback(tmp_path: Path) -> None:
    path = write(tmp_path, "p.csv", "x,y,z\n1200,0,0\n1300,oops,0\n")
    proc = subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.cli", "plan", "--path", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert proc.stdout == ""


def test_unwritable_out_is_one_line_and_leaves_no_figures(tmp_path: Path, capsys) -> None:
    (tmp_path / "adir").mkdir()
    rc, _, err = run(
        [
            "plan",
            "--scenario",
            "cabins",
            "--out",
            str(tmp_path / "adir"),  # a folder, not a file
            "--plot",
            str(tmp_path / "fig"),
            "--allow-collision",
        ],
        capsys,
    )
    err = "".join(x for x in err.splitlines(True) if "warning: " not in x)  # the collision's
    assert rc == 2 and "exists and is not a regular file" in err and err.count("\n") == 1
    assert not list((tmp_path / "fig").glob("*.png"))


def test_unwritable_plot_dir_leaves_no_plan(tmp_path: Path, capsys) -> None:
    (tmp_path / "afile").write_text("")
    out = tmp_path / "plan.json"
    rc, _, err = run(
        [
            "plan",
            "--scenario",
            "cabins",
            "--out",
            str(out),
            "--plot",
            str(tmp_path / "afile"),
            "--allow-collision",
        ],
        capsys,
    )
    err = "".join(x for x in err.splitlines(True) if "warning: " not in x)  # the collision's
    assert rc == 2 and err.count("\n") == 1 and "afile" in err
    assert not out.exists()


def test_a_collision_is_refused_and_writes_nothing(tmp_path: Path, capsys) -> None:
    """The bent-pipe paper plan (--fit paper) cuts the last bend with link 9 (NOTES.md)."""
    out, fig = tmp_path / "plan.json", tmp_path / "fig"
    argv = ["plan", "--scenario", "bent-pipe", "--fit", "paper", "--out", str(out)]
    argv += ["--plot", str(fig)]
    rc, stdout, err = run(argv, capsys)
    assert rc == 2
    assert "COLLISION" in stdout
    assert err.count("\n") == 1 and "link 9 meets an obstacle at step 135" in err
    assert "--allow-collision" in err
    assert not out.exists() and not fig.exists()
    rc, stdout, err = run([*argv, "--allow-collision"], capsys)
    assert rc == 0, err
    assert "warning: link 9 meets an obstacle at step 135" in err
    doc = read_plan(out)
    assert doc.clearance["min"] < 0.0 and (doc.clearance["step"], doc.clearance["link"]) == (
        135,
        9,
    )
    assert (fig / "clearance.png").exists()


def test_plot_steps_choose_the_steps_drawn(tmp_path: Path, capsys) -> None:
    out = tmp_path / "plan.json"
    rc, _, err = run(
        [
            "plan",
            "--scenario",
            "bent-pipe",
            "--out",
            str(out),
            "--plot",
            str(tmp_path / "fig"),
            "--plot-steps",
            "0,60,135",
            "--allow-collision",
        ],
        capsys,
    )
    assert rc == 0, err
    doc = read_plan(out)
    assert sorted(doc.backbones_mm) == [0, 60, 135]
    assert doc.travel_mm[60] == pytest.approx(300.0)  # Fig. 11b of the paper
    rc, _, err = run(["plan", "--scenario", "bent-pipe", "--plot-steps", "0,999"], capsys)
    assert rc == 2 and "past the plan's last step 135" in err and err.count("\n") == 1


def test_a_plan_that_cannot_be_written_leaves_no_figure_folder(tmp_path: Path, capsys) -> None:
    """The figures are written first; when the plan then fails (a part of --out's folder is a
    file) they go again, and so does the folder --plot made."""
    (tmp_path / "afile").write_text("")
    fig = tmp_path / "new" / "fig"
    fig.parent.mkdir()
    argv = ["plan", "--scenario", "cabins", "--allow-collision", "--plot", str(fig)]
    rc, _, err = run([*argv, "--out", str(tmp_path / "afile" / "sub" / "plan.json")], capsys)
    err = "".join(x for x in err.splitlines(True) if "warning: " not in x)  # the collision's
    assert rc == 2 and err.count("\n") == 1
    assert f"{tmp_path / 'afile'} is not a folder" in err
    assert not fig.exists() and fig.parent.exists()
