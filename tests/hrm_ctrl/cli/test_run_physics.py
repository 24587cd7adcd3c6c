"""``hrm run --sim --physics EFFECTS``: the simulated box with the arm's physics, as a user
runs it (``hrm`` in a process of its own, the box in another); ``--compensate`` with the
rope-consistency watch checking the compensated setpoints; bad values one line, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import write_plan
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT, small_plan

HAVE = "(have all, none, gravity, capstan, creep, backlash, sensor)"


@pytest.fixture(scope="module")
def bent_pipe_plan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from hrm_ctrl.formats.planfile import PlanDoc
    from hrm_ctrl.model import default_robot
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.scenarios import scenario

    sc = scenario("bent-pipe")
    plan = plan_path(default_robot(), sc.path, PlanOptions(step=5.0), sc)
    path = tmp_path_factory.mktemp("plan") / "bent_pipe.json"
    write_plan(path, PlanDoc.from_dict(plan.to_dict(), sc.name))
    return path


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["run", "--hold", "1", "--sim", "--physics", "bogus"],
         f"hrm run: error: physics 'bogus': unknown effect 'bogus' {HAVE}"),
        (["run", "--hold", "1", "--sim", "--physics", "gravity,frictoin"],
         f"hrm run: error: physics 'gravity,frictoin': unknown effect 'frictoin' {HAVE}"),
        (["run", "--hold", "1", "--sim", "--physics", ""],
         "hrm run: error: physics '': name effects (all, none, gravity, ...)"),
        (["run", "--hold", "1", "--physics", "all"],
         "hrm run: error: --physics goes with --sim"),
        (["console", "--sim", "--physics", "bogus"],
         f"hrm console: error: physics 'bogus': unknown effect 'bogus' {HAVE}"),
        (["sim", "--physics", "bogus"],
         f"hrm sim: error: physics 'bogus': unknown effect 'bogus' {HAVE}"),
    ],
)  # fmt: skip
def test_a_bad_physics_is_one_line_before_anything_opens(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    no_bus: list[dict[str, Any]],
    argv: list[str],
    message: str,
) -> None:
    """The same spelling and the same line as ``hrm sim --physics``; nothing opened or
    written."""
    logs = tmp_path / "runs"
    extra = [] if argv[0] == "sim" else ["--log-dir", str(logs)]
    rc = main([*argv, *extra])
    out = capsys.readouterr()
    assert rc == 2 and out.out == ""
    assert out.err == message + "\n"
    assert no_bus == [] and not logs.exists()


def hrm(argv: list[str], timeout_s: float = 280.0) -> tuple[int, str, dict[str, Any], dict]:
    """``hrm ARGV --json`` in a process of its own: its status, stderr, the summary and the
    run record."""
    proc = subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.cli", *argv, "--json"],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        stdin=subprocess.DEVNULL,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    summary = json.loads(proc.stdout)
    record = json.loads(Path(summary["run_record"]).read_text())
    return proc.returncode, proc.stderr, summary, record


@STALL_TOLERANT
def test_a_compensated_run_on_the_physical_arm_completes_watched(tmp_path: Path) -> None:
    """Every effect on, the plan compensated: from the straight arm (its power-on pose)
    the compensation comes in over 1 s, the plan plays, nothing stops it; the
    rope-consistency watch checked the compensated setpoints (none gated; before: every
    one skipped), and the tensions show the arm's weight (30 N without physics)."""
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    logs = tmp_path / "runs"
    rc, err, summary, record = hrm(
        ["run", str(plan), "--sim", "--physics", "all", "--compensate", "--log-dir", str(logs)]
    )
    assert rc == 0, err
    assert summary["outcome"] == "completed" and summary["causes"] == []
    assert record["setpoints"]["compensated"] is True
    rope = record["watches"]["rope_consistency"]
    check = rope["check"]
    assert rope["fault"] is None and check["evaluations"] > 10, rope
    assert check["gated"] == 0, check  # measured: 0 of 28
    assert check["compensated"]["samples"] == check["evaluations"]
    assert check["max_figure"] < check["flag_sigma"] / 2
    tension = record["watches"]["tension"]
    assert tension["fault"] is None
    # measured 13.7-54.5 N: the level arm's weight on its ropes
    assert tension["lowest_N"] < 20.0 and tension["highest_N"] > 45.0, tension


@STALL_TOLERANT
@pytest.mark.timeout(600)
def test_the_bent_pipe_on_the_physical_arm_stops_in_its_lead_in(
    bent_pipe_plan: Path, tmp_path: Path
) -> None:
    """The bent pipe from the straight arm, every effect on, compensated: the lead-in to
    the plan's first pose goes at the pretension's counts (the compensation comes in
    only at rest on the first step: a lead-in is checked against the rope model's
    command band, which a compensated target is beyond), and there the arm's weight
    slackens a rope of joint 2 (1.4 N at the first pose, quasi-static, gravity alone;
    the slack threshold 5 N): the tension watch stops the run, in one line, before the
    compensation has come in."""
    logs = tmp_path / "runs"
    rc, err, summary, record = hrm(
        ["run", str(bent_pipe_plan), "--sim", "--physics", "all", "--compensate",
         "--allow-collision", "--log-dir", str(logs)],
        timeout_s=560.0,
    )  # fmt: skip
    assert rc == 2, err
    stops = [x for x in err.splitlines() if x.startswith("hrm run: stopped: ")]
    assert len(stops) == 1, err
    assert stops[0].startswith("hrm run: stopped: rope j02r"), stops
    assert stops[0].endswith("N below 5 N (slack or broken)"), stops
    assert summary["outcome"] == "stopped"
    first = record["streams"][0]["causes"][0]
    assert first["kind"] == "tension" and first["text"].startswith("rope j02r"), first
    sp = record["setpoints"]
    assert sp["compensated"] is True
    # measured: rows 24 and 51 (the lead-in 48 rows): in the lead-in, or in the first rows
    # of the ramp-in, before 1 % of the compensation has come in (smootherstep at 10 of
    # its 100 rows: 0.86 %), depending on when the loaded machine's watch read it
    assert sp["stopped_at_row"] < sp["lead_in_cycles"] + 10, sp


def test_a_compensated_run_on_a_real_box_is_watched_with_its_compensation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--compensate`` on real buses: the rope-consistency watch gets what the
    feed-forward added to every row (it checks the compensated setpoints, so a real box
    is no longer refused the compensation), as on the simulated box."""
    import numpy as np

    from hrm_ctrl.runtime import box as runtime_box

    seen: dict[str, Any] = {}

    class OpenedError(Exception):
        pass

    def fake_open_box(*args: Any, **kw: Any) -> Any:
        seen.update(kw)
        raise OpenedError

    monkeypatch.setattr(runtime_box, "open_box", fake_open_box)
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    argv = ["run", str(plan), "--compensate", "--uncalibrated", "--log-dir", str(tmp_path / "r")]
    with pytest.raises(OpenedError):
        main(argv)
    assert seen["sim"] is None  # the configured buses
    comp = seen["watches"].compensation
    assert comp is not None and comp.n_rows > 100  # the 1 s ramp-in and the plan
    assert np.abs(comp.added).max() > 100  # it does add (the level arm's weight)
    with pytest.raises(OpenedError):
        main([*argv[:2], *argv[3:]])  # without --compensate: nothing to take off
    assert seen["watches"].compensation is None


def test_the_console_box_takes_the_physics(tmp_path: Path) -> None:
    """``hrm status --sim --physics all`` (the console's ``connect`` and ``status`` once,
    on the box the console starts): the level arm's weight on its ropes at power-on
    (measured 17.6-54.1 N on joint 1's), 30 N each without physics."""
    tensions = {}
    for physics in ("all", "none"):
        proc = subprocess.run(
            [sys.executable, "-m", "hrm_ctrl.cli", "status", "--sim", "--physics", physics,
             "--log-dir", str(tmp_path / physics), "--json"],
            capture_output=True, text=True, timeout=280.0, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        nodes = json.loads(proc.stdout)["nodes"]
        tensions[physics] = [n["tension_N"] for n in nodes]
    assert len(tensions["all"]) == 36
    assert max(tensions["all"]) > 45.0 and min(tensions["all"]) < 20.0, tensions["all"]
    assert all(abs(t - 30.0) < 1.0 for t in tensions["none"]), tensions["none"]
