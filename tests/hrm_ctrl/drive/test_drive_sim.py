"""``hrm drive --sim``: a scripted drive into the bent pipe streamed to the simulated box
(in its own process, opened by ``open_box``).  The CAN log's RPDO targets (one row a
SYNC: a control cycle) are the drive's setpoints: every motor within its speed,
acceleration and jerk limits in every cycle, and after the advance key is released the
motion stops within the time the deceleration allows; the shape feedback sees the arm on
the trail at rest."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivers.config import load_box_config
from hrm_ctrl.cli import main
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from tests.hrm_ctrl.cli.test_run_limits import targets_per_sync

T = 0.01  # the shipped box's control period
SPEED_MM_S = 20.0
ACCEL_MM_S2 = 40.0  # hrm drive's default advance ramp
RELEASE_S = 5.0


def test_drive_into_the_bent_pipe_on_the_simulated_box(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    keys = tmp_path / "keys.txt"
    keys.write_text(f"0 advance down\n{RELEASE_S} advance up\n{RELEASE_S + 1.0} end\n")
    logs = tmp_path / "runs"
    argv = ["drive", "--scenario", "bent-pipe", "--keys", str(keys), "--sim"]
    rc = main([*argv, "--log-dir", str(logs), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    s = json.loads(out.out)
    assert s["outcome"] == "completed" and s["completed"] is True, s["causes"]
    assert s["refusals"] == [] and s["stop_reason"] is None and s["can_log_errors"] == []
    # 0.5 s ramp to 20 mm/s, 4.5 s at it, 0.5 s ramp down: 100 mm into the pipe
    assert s["travel_mm"] == pytest.approx(100.0, abs=0.01)
    assert s["worst_clearance_mm"] > 0.0
    # shape feedback: the rope estimator on the drives' feedback and the tension board
    sh = s["shape"]
    assert sh["samples"] >= 10 and sh["tensions"] is True and sh["error"] is None
    assert sh["tip_from_trail_mm"]["last"] < 0.5  # at rest: on the trail
    # moving, the shaping's lag puts the arm off the trail by a few mm (docs/planner.md)
    assert sh["tip_from_trail_mm"]["max"] < 5.0
    record = json.loads(Path(s["run_record"]).read_text())
    lead = record["setpoints"]["lead_in_cycles"]
    last = np.array(record["setpoints"]["last_setpoint"])
    assert lead >= 5

    act = load_actuation(default_robot())
    config = load_box_config(None)
    assert config.control.period_s == T
    checked = 0
    for bus in config.buses:
        (log,) = logs.glob(f"*_{bus.name}.blf")
        targets, stops = targets_per_sync(log, bus.nodes)
        assert not stops.any()  # no quick stop
        cols = [act.motor_ids.index(m) for m in bus.nodes]
        # the drive's last setpoint is what the drives were told last
        assert np.array_equal(targets[-1], last[cols])
        seq = targets.astype(np.float64)
        speed = np.abs(np.diff(seq, axis=0))
        accel = np.abs(np.diff(seq, n=2, axis=0))
        jerk = np.abs(np.diff(seq, n=3, axis=0))
        assert np.all(speed <= act.max_rate_counts_per_s[cols] * T), speed.max()
        assert np.all(accel <= act.max_accel_counts_per_s2[cols] * T**2)
        assert np.all(jerk <= act.max_jerk_counts_per_s3[cols] * T**3)
        # one row a slot of the stream: the lead-in, the drive, the stop and the hold
        assert targets.shape[0] == s["box_cycles"]
        moving = np.flatnonzero(np.abs(np.diff(targets, axis=0)).max(axis=1) > 0)
        end = int(moving[-1]) + 1  # the last change
        # the release: drive slot RELEASE_S / T after the lead-in; the tip then slows at
        # ACCEL_MM_S2 (SPEED / ACCEL s) and the shaping follows it within its lag
        release = lead + round(RELEASE_S / T)
        assert np.abs(targets[release] - targets[release - 1]).max() > 0  # still moving
        stop_s = (end - release) * T
        print(f"bus {bus.name}: motion stops {stop_s:.2f} s after the release")
        assert SPEED_MM_S / ACCEL_MM_S2 - 0.05 <= stop_s <= SPEED_MM_S / ACCEL_MM_S2 + 0.1
        checked += len(cols)
    assert checked == act.n_motors
