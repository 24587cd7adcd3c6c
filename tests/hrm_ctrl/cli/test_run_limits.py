"""End to end: ``hrm run --sim`` plays a plan whose first step is away from where the
drives are (and pauses it); the CAN log's RPDO targets (what every drive was told, per
SYNC) keep every motor within its speed, acceleration and jerk limit in every control
cycle, lead-in and pause included."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from drivers.config import load_box_config
from drivers.protocol import cia402
from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import write_plan
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from tests.hrm_ctrl.cli.cli_helpers import small_plan

T = 0.01


def bent_start_plan() -> dict[str, Any]:
    """The small plan, bent by 2 deg more at every step: the straight arm (where the
    simulated drives start) is not its first step, so it plays with a lead-in."""
    plan = small_plan()
    for st in plan["steps"]:
        st["alpha_rad"] = [a + float(np.deg2rad(2.0)) for a in st["alpha_rad"]]
    return plan


def targets_per_sync(log: Path, nodes: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """(SYNCs, motors) the target each node's last RPDO before each SYNC carried (the one
    that SYNC applies), and whether it was a quick stop, from one bus's CAN log."""
    by_node = {n: i for i, n in enumerate(nodes.values())}
    rows: list[list[int]] = []
    stops: list[bool] = []
    cur: list[int | None] = [None] * len(by_node)
    quick = False
    with can.LogReader(str(log)) as reader:
        frames = sorted(reader, key=lambda m: m.timestamp)
    for m in frames:
        cid = m.arbitration_id
        if m.is_extended_id or m.is_error_frame:
            continue
        if cid == 0x080:
            if all(c is not None for c in cur):
                rows.append([int(c) for c in cur])  # type: ignore[arg-type]
                stops.append(quick)
        elif 0x200 < cid <= 0x27F and (cid - 0x200) in by_node and len(m.data) == 6:
            data = bytes(m.data)
            cur[by_node[cid - 0x200]] = int.from_bytes(data[2:6], "little", signed=True)
            quick = int.from_bytes(data[:2], "little") == cia402.CW_QUICK_STOP
    return np.array(rows, dtype=np.int64), np.array(stops)


@pytest.mark.parametrize(
    "controls",
    [[], ["--pause-at", "40%", "--resume-after", "0.3s"]],
    ids=["plain", "paused"],
)
def test_playback_within_speed_acceleration_and_jerk_in_every_cycle(
    tmp_path: Path, capsys: pytest.CaptureFixture, controls: list[str]
) -> None:
    """Lead-in, body, stop (and a pause: the ramp to rest, 0.3 s at rest, the ramp back,
    issue 39) within every motor's speed, acceleration and jerk, from the CAN log."""
    plan = tmp_path / "plan.json"
    write_plan(plan, bent_start_plan())
    logs = tmp_path / "runs"
    args = ["run", str(plan), "--sim", "--log-dir", str(logs), "--speed", "50", "--json"]
    rc = main(args + controls)
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True
    record = json.loads(Path(summary["run_record"]).read_text())
    if controls:  # it paused, stood and went on to the end
        assert [a["action"] for a in record["run_control"]] == ["pause", "resume"]
        assert record["setpoints"]["play_state"] == "done"
        assert record["setpoints"]["paused_s"] >= 0.25
    assert record["setpoints"]["lead_in_cycles"] >= 5
    # what the jerk bound cost the plan's body, in the record: one jerk window (a few
    # hundredths of a second) on this short plan's one leg
    cost = record["setpoints"]["jerk_bound_cost_s"]
    assert 0.0 < cost < 0.2 and record["setpoints"]["duration_without_jerk_bound_s"] > 0.0
    first_moved = _wire_within_limits(logs, summary["cycles"])
    assert first_moved < record["setpoints"]["lead_in_cycles"]  # the lead-in moved them


def _wire_within_limits(logs: Path, cycles: int) -> int:
    """Every motor's targets on the wire (the CAN logs in ``logs``) within its speed,
    acceleration and jerk limit in every cycle, from rest at 0 counts (the straight arm,
    where the simulated drives start); returns the first cycle a target moved 1000 counts
    from there."""
    act = load_actuation(default_robot())
    config = load_box_config(None)
    checked, moved = 0, cycles
    for bus in config.buses:
        (log,) = logs.glob(f"*_{bus.name}.blf")
        targets, _stops = targets_per_sync(log, bus.nodes)
        assert targets.shape[0] >= cycles - 1
        cols = [act.motor_ids.index(m) for m in bus.nodes]
        v_max = act.max_rate_counts_per_s[cols] * T
        a_max = act.max_accel_counts_per_s2[cols] * T**2
        j_max = act.max_jerk_counts_per_s3[cols] * T**3
        # the drives held their positions at enable (the straight arm: 0 counts), at rest
        seq = np.vstack([np.zeros((3, len(cols)), dtype=np.int64), targets])
        speed = np.abs(np.diff(seq, axis=0))
        accel = np.abs(np.diff(seq, n=2, axis=0))
        jerk = np.abs(np.diff(seq, n=3, axis=0))
        assert np.all(speed <= v_max), speed.max()
        assert np.all(accel <= a_max), (accel / a_max).max()
        assert np.all(jerk <= j_max), (jerk / j_max).max()
        far = np.flatnonzero(np.abs(targets).max(axis=1) > 1000)
        moved = min(moved, int(far[0]) if far.size else cycles)
        checked += len(cols)
    assert checked == act.n_motors
    return moved


@pytest.mark.slow
def test_a_pause_of_a_fast_plan_keeps_the_jerk_on_the_wire(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """The bent pipe there and back at 500 mm/s, its table at 97 % of the jerk limit,
    paused halfway and resumed after 0.3 s (issue 39): every target on the wire within
    speed, acceleration and jerk (before, a pause there reached 1.2 times the jerk)."""
    plan = tmp_path / "pipe.json"
    rc = main(["plan", "--scenario", "bent-pipe", "--return", "--out", str(plan)])
    assert rc == 0, capsys.readouterr().err
    capsys.readouterr()
    logs = tmp_path / "runs"
    rc = main(["run", str(plan), "--sim", "--log-dir", str(logs), "--speed", "500", "--json",
               "--pause-at", "50%", "--resume-after", "0.3s", "--allow-collision"])  # fmt: skip
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True
    record = json.loads(Path(summary["run_record"]).read_text())
    assert [a["action"] for a in record["run_control"]] == ["pause", "resume"]
    assert record["setpoints"]["play_state"] == "done"
    _wire_within_limits(logs, summary["cycles"])


def test_a_lead_in_far_from_the_straight_arm_keeps_the_ropes_at_their_pretension(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A red-team plan: one step with every alpha at +44 deg and theta at -44 deg, from
    the straight arm.  Its lead-in was a straight line in counts: the simulated tension
    board read 154 N and the watch stopped it.  Now a line in joint space: the run
    completes, the board's highest reading near the 30 N pretension, and every target
    on the wire decodes (the host's own rope inverse) to a pose inside the joint limits."""
    plan = small_plan()
    a = float(np.deg2rad(44.0))
    plan["steps"] = [{**plan["steps"][0], "alpha_rad": [a] * 12, "theta_rad": [-a] * 12}]
    path = tmp_path / "p44.json"
    write_plan(path, plan)
    logs = tmp_path / "runs"
    rc = main(["run", str(path), "--sim", "--log-dir", str(logs), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True
    record = json.loads(Path(summary["run_record"]).read_text())
    assert record["setpoints"]["lead_in_cycles"] > 50
    highest = record["watches"]["tension"]["highest_N"]
    assert 29.0 < highest < 35.0, highest
    act = load_actuation(default_robot())
    config = load_box_config(None)
    full: list[np.ndarray] = []
    for bus in config.buses:
        (log,) = logs.glob(f"*_{bus.name}.blf")
        full.append(targets_per_sync(log, bus.nodes)[0])
    n = min(t.shape[0] for t in full)
    order = [m for bus in config.buses for m in bus.nodes]
    wire = np.hstack([t[:n] for t in full])[:, [order.index(m) for m in act.motor_ids]]
    alpha, theta, _res = act.angles_from_counts(wire[:: max(1, n // 200)])
    act.check_angles(alpha, theta)
    assert np.degrees(np.abs(alpha)).max() == pytest.approx(44.0, abs=0.05)
