"""``hrm run --sim`` watches the arm while it moves: a snapped rope (tension), a shifted
encoder (rope consistency) and sensor garbage stop the run, naming the rope; a clean run
of the whole bent-pipe plan at the demo's speed raises nothing."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import PlanDoc, write_plan
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario
from hrm_ctrl.runtime import simulated as _simwire
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT

DEMO_SPEED = "50"  # mm/s, hrm demo's default
PERIOD_S = 0.01


@pytest.fixture(scope="module")
def bent_pipe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    robot = default_robot()
    sc = scenario("bent-pipe")
    plan = plan_path(robot, sc.path, PlanOptions(step=5.0), sc)
    path = tmp_path_factory.mktemp("plan") / "bent_pipe.json"
    write_plan(path, PlanDoc.from_dict(plan.to_dict(), sc.name))
    return path


@pytest.fixture
def inject(monkeypatch: pytest.MonkeyPatch) -> Callable[[int, Callable[[Any], None]], list[Any]]:
    """``inject(n, fault)``: the in-process box of the next ``--sim`` gets ``fault(box)``
    once it has seen ``n`` SYNCs (i.e. ``n`` cycles into the stream)."""
    real = _simwire.start_in_process_sim
    boxes: list[Any] = []

    def arm(n_syncs: int, fault: Callable[[Any], None]) -> list[Any]:
        def start(*args: Any, **kw: Any) -> Any:
            config, sim = real(*args, **kw)
            sim.record_trace(True)
            boxes.append(sim)

            def wait_then_fault() -> None:
                while not done.wait(0.005):
                    if len(sim.trace()[0]) >= n_syncs:
                        fault(sim)
                        return

            threading.Thread(target=wait_then_fault, daemon=True).start()
            return config, sim

        monkeypatch.setattr(_simwire, "start_in_process_sim", start)
        return boxes

    done = threading.Event()
    yield arm
    done.set()


def hrm_run(
    args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture, *, in_process: bool = True
) -> tuple[int, Any]:
    # the bent-pipe paper plan grazes the pipe (issue 10: refused without the flag); these
    # tests are about the watches.  The box in this interpreter (--wire virtual) where a
    # fault is injected into it, else in its own process (the default)
    wire = ["--wire", "virtual"] if in_process else []
    argv = ["run", *args, "--sim", *wire, "--log-dir", str(tmp_path / "runs"), "--json"]
    rc = main([*argv, "--allow-collision"])
    out = capsys.readouterr()
    assert "Traceback" not in out.err, out.err
    summary = json.loads(out.out)
    record = json.loads(Path(summary["run_record"]).read_text())
    return rc, (out.err, summary, record)


def stop_line(err: str) -> str:
    lines = [x for x in err.splitlines() if x.startswith("hrm run: stopped: ")]
    assert len(lines) == 1, err
    return lines[0]


def assert_stopped(record: dict[str, Any], kind: str, text: str) -> dict[str, Any]:
    stream = record["streams"][0]
    assert stream["completed"] is False
    first = stream["causes"][0]
    assert first["kind"] == kind and text in first["text"], stream["causes"]
    # every axis within one control cycle of detection, counted in cycles: the stream sent
    # at most the SYNC already under way after the cause was known.  (The wall-time
    # figure, stop_latency_s, is the supervisor's wake-up on the loaded machine with 36
    # in-process drives; 10.8 and 11.3 ms were seen with both cores busy.  The one-period
    # wall-time bound is asserted on the drivers' rigs: tests/drivers/safety.)
    assert stream["stop_syncs_after_detection"] <= 1, stream
    assert stream["stop_latency_s"] > 0
    return first


@STALL_TOLERANT
def test_a_snapped_rope_stops_the_run_naming_the_rope(
    bent_pipe: Path, tmp_path: Path, capsys: pytest.CaptureFixture, inject: Any
) -> None:
    inject(60, lambda box: box.snap_rope("j05r2"))
    rc, (err, summary, record) = hrm_run([str(bent_pipe), "--speed", DEMO_SPEED], tmp_path, capsys)
    assert rc == 2, err
    assert stop_line(err) == (
        "hrm run: stopped: rope j05r2: tension 0.0 N below 5 N (slack or broken)"
    )
    assert_stopped(record, "tension", "rope j05r2")
    assert summary["cycles"] < 200  # of ~1400: stopped soon after the snap
    assert record["watches"]["tension"]["fault"].startswith("rope j05r2: ")
    assert record["config"]["tension"]["port"].startswith("/dev/")


@STALL_TOLERANT
def test_a_shifted_encoder_stops_the_run_naming_joint_and_rope(
    bent_pipe: Path, tmp_path: Path, capsys: pytest.CaptureFixture, inject: Any
) -> None:
    # past the lead-in (~27 cycles), j05r1's feedback 0.5 mm (1075 counts) off its motor
    inject(100, lambda box: box.shift_encoder("j05r1", 1075))
    rc, (err, summary, record) = hrm_run([str(bent_pipe), "--speed", DEMO_SPEED], tmp_path, capsys)
    assert rc == 2, err
    line = stop_line(err)
    assert line.startswith("hrm run: stopped: rope consistency: joint 5, ropes "), line
    assert "j05r1" in line and "lengths do not fit the other ropes" in line
    assert_stopped(record, "rope", "joint 5")
    assert 100 <= summary["cycles"] < 200
    assert record["watches"]["tension"]["fault"] is None  # the arm itself did not move


@STALL_TOLERANT
def test_sensor_garbage_past_the_rate_stops_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture, inject: Any
) -> None:
    inject(30, lambda box: box.tension_board.inject_garbage(64, continuous=True))
    rc, (err, _summary, record) = hrm_run(["--hold", "3"], tmp_path, capsys)
    assert rc == 2, err
    assert "bad frames or garbage runs in the last 1 s (limit 5/s" in stop_line(err)
    assert_stopped(record, "tension", "tension sensor /dev/")


@STALL_TOLERANT
def test_the_whole_bent_pipe_at_the_demo_speed_raises_nothing(
    bent_pipe: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    rc, (err, summary, record) = hrm_run(
        [str(bent_pipe), "--speed", DEMO_SPEED], tmp_path, capsys, in_process=False
    )
    assert rc == 0, err
    assert summary["completed"] is True and summary["causes"] == []
    assert summary["cycles"] > 1300
    rope = record["watches"]["rope_consistency"]
    # the watch woke at 20 Hz over the ~14 s (each wake an evaluation, or no snapshot of
    # one SYNC to judge: the box behind, its TPDOs of two SYNCs mixed), and judged often
    wakes = rope["evaluations"] + rope["missed_snapshots"] + rope["repeated_syncs"]
    assert rope["fault"] is None and wakes > 200 and rope["evaluations"] > 100, rope
    assert rope["check"]["max_figure"] < rope["check"]["flag_sigma"] / 2
    tension = record["watches"]["tension"]
    assert tension["fault"] is None and tension["frames"] > 1000
    assert 5.0 < tension["lowest_N"] and tension["highest_N"] < 150.0


def test_a_tension_threshold_outside_its_range_is_refused_before_any_bus_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[dict[str, Any]]
) -> None:
    from drivers import default_box_path

    box = tmp_path / "box.toml"
    box.write_text(default_box_path().read_text() + '\n[tension]\nport = "/dev/x"\nslack_N = 0\n')
    logs = tmp_path / "runs"
    rc = main(["run", "--hold", "0.1", "--sim", "--config", str(box), "--log-dir", str(logs)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert f"{box}: tension.slack_N must be in [0.5, 100] N, got 0.0" in err
    assert no_bus == [] and not logs.exists()


@STALL_TOLERANT
def test_a_shifted_encoder_stops_a_compensated_run_on_the_physical_arm(
    tmp_path: Path, capsys: pytest.CaptureFixture, inject: Any
) -> None:
    """With every effect of the arm's physics on and the plan compensated, the
    rope-consistency watch checks the compensated setpoints (it takes off what the
    feed-forward added) and still catches an encoder 0.5 mm off."""
    from hrm_ctrl.formats.planfile import write_plan
    from tests.hrm_ctrl.cli.cli_helpers import small_plan

    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    # 100 rows bring the compensation in (1 s at rest), then 15 mm of plan and its hold:
    # 161 cycles in all.  The shift while the compensation comes in: the watch needs a few
    # checks (its figure is averaged) and under load half its wakes find no snapshot of
    # one SYNC (a shift at 110 was caught at 128 once and not before the end once)
    inject(40, lambda box: box.shift_encoder("j05r1", 1075))
    rc, (err, summary, record) = hrm_run(
        [str(plan), "--physics", "all", "--compensate"], tmp_path, capsys
    )
    assert rc == 2, err
    line = stop_line(err)
    assert line.startswith("hrm run: stopped: rope consistency: joint 5, ropes "), line
    assert "j05r1" in line and "lengths do not fit the other ropes" in line
    assert_stopped(record, "rope", "joint 5")
    assert 40 <= summary["cycles"] < 161
    check = record["watches"]["rope_consistency"]["check"]
    assert check["gated"] == 0 and check["compensated"]["samples"] == check["evaluations"]
    assert record["watches"]["tension"]["fault"] is None
