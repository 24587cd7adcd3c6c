"""The console's ``drive`` on the in-process simulated box, over the session ``connect``
opened: a key script into the bent pipe (the trail saved, read back as a path file, the
drives where the drive's last step puts them), a wall ahead that holds the arm (one line)
while the drive goes on and retracts, a script without keys refused before anything moves,
and the keyboard at a terminal (pexpect): hold ``w`` to advance, ``a`` to end."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.cli._console.shell import run_script
from hrm_ctrl.cli._console.table import ConsoleError
from hrm_ctrl.planning.known_path import load_path_csv


def _relaxed_box(tmp_path: Path) -> Path:
    """The shipped box with watchdogs that bear a loaded test machine."""
    import drivers

    box = (Path(drivers.__file__).parent / "data" / "box.toml").read_text()
    box = box.replace("heartbeat_timeout_ms = 350", "heartbeat_timeout_ms = 2000")
    box = box.replace("missing_tpdo_cycles = 3 ", "missing_tpdo_cycles = 25 ")
    assert "heartbeat_timeout_ms = 2000" in box and "missing_tpdo_cycles = 25" in box
    p = tmp_path / "box.toml"
    p.write_text(box)
    return p


def run(ctx: object, *lines: str) -> None:
    run_script(ctx, list(lines), "test")


def _positions(ctx: object) -> np.ndarray:
    return np.array([ctx.sim.box.drives[m].position_counts for m in ctx.actuation.motor_ids])


def _last_drive(ctx: object) -> dict:
    return ctx.session.record_extra["console_drives"][-1]


@pytest.mark.slow
def test_drive_by_a_key_script_saves_the_trail_and_holds_the_last_step(
    make_ctx, tmp_path: Path
) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    keys = tmp_path / "keys.txt"
    keys.write_text("0 advance down\n1.5 advance up\n2.2 end\n")
    trail = tmp_path / "trail.csv"
    run(ctx, "connect", "enable", f"drive --scenario bent-pipe --keys {keys} --save-trail {trail}")
    summary = [x for x in ctx.lines if x.startswith("drive: ") and "cycles, travel" in x]
    # 0.5 s ramp to 20 mm/s, 1 s at it, 0.5 s ramp down: 30 mm into the pipe
    assert summary and "travel 30.0 mm" in summary[0] and "0 hold(s)" in summary[0]
    d = _last_drive(ctx)
    assert d["refusals"] == [] and d["stop_reason"] is None
    # the drives hold the drive's last setpoint, the counts of its last online step
    assert np.array_equal(_positions(ctx), np.array(d["last_setpoint"]))
    # shape feedback: the estimator saw the arm where the plan has it, on the trail
    sh = d["shape"]
    assert sh["samples"] >= 5 and sh["error"] is None
    assert sh["tip_from_trail_mm"]["last"] < 0.5, sh
    assert any(x.startswith("drive: shape feedback") for x in ctx.lines)
    # the trail: a path file from the entry, 30 mm along the pipe's axis
    path = load_path_csv(trail)
    assert path.points[0].tolist() == [1200.0, 100.0, 300.0]
    assert np.linalg.norm(path.points[-1] - [1230.0, 100.0, 300.0]) < 1e-6
    assert any(x == f"drive: trail written to {trail}" for x in ctx.lines)


@pytest.mark.slow
def test_a_wall_ahead_holds_the_arm_with_one_line_and_the_drive_goes_on(
    make_ctx, tmp_path: Path
) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    scene = tmp_path / "wall.toml"  # a block across the way 40 mm past the entry
    scene.write_text("[[box]]\ncentre_mm = [1245, 100, 300]\nsize_mm = [10, 200, 200]\n")
    keys = tmp_path / "keys.txt"
    keys.write_text("0 advance down\n3 advance up\n3.2 retract down\n3.9 retract up\n5 end\n")
    run(ctx, "connect", "enable",
        f"drive --scenario bent-pipe --scene {scene} --keys {keys}")  # fmt: skip
    holds = [x for x in ctx.lines if x.startswith("drive: HOLD at ")]
    assert len(holds) == 1 and "link 12 would come" in holds[0], ctx.lines
    d = _last_drive(ctx)
    held_at = d["refusals"][0]["cycle"]
    assert held_at < round(3.0 / 0.01)  # refused while the advance key was held
    # the drive went on: the retract moved the arm back along the trail
    assert d["stop_reason"] is None and d["drive_cycles"] > round(3.9 / 0.01)
    s = d["summary"]
    # the tip (radius 15 mm) stopped short of the block's face at x = 1240 (1 mm margin),
    # about 24 mm along the trail; the retract (0.7 s held: 14 mm) took it back
    trail_mm = s["trail_length_mm"]
    assert 20.0 < trail_mm <= 24.0 + 1e-6
    assert s["travel_mm"] == pytest.approx(trail_mm - 14.0, abs=0.5)
    assert np.array_equal(_positions(ctx), np.array(d["last_setpoint"]))


def test_a_script_without_keys_is_refused_before_anything_moves(make_ctx, tmp_path) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "enable")
    before = _positions(ctx)
    with pytest.raises(ConsoleError, match="in a script the keys come from a key script"):
        run(ctx, "drive --scenario bent-pipe")
    assert np.array_equal(_positions(ctx), before)
    assert "console_drives" not in ctx.session.record_extra


@pytest.mark.slow
def test_drive_from_the_keyboard_at_a_terminal(tmp_path: Path, isolated_home: Path) -> None:
    pexpect = pytest.importorskip("pexpect")
    env = dict(os.environ, HOME=str(isolated_home), HRM_CALIBRATIONS=str(tmp_path / "cal"),
               COLUMNS="200")  # fmt: skip
    env.pop("HRM_PROGRESS", None)
    child = pexpect.spawn(
        sys.executable,
        ["-m", "hrm_ctrl.cli", "console", "--sim", "--config", str(_relaxed_box(tmp_path)),
         "--log-dir", "runs"],
        cwd=str(tmp_path), env=env, encoding="utf-8", timeout=120, dimensions=(60, 200),
    )  # fmt: skip
    child.logfile_read = (tmp_path / "terminal.log").open("w")
    try:
        child.expect(r"hrm>")
        child.sendline("connect")
        child.expect(r"hrm:ready>")
        child.sendline("enable")
        child.expect(r"hrm:enabled>")
        child.sendline("drive --scenario bent-pipe")
        child.expect(r"a ends the drive")
        child.expect(r"travel +[\d.]+ mm")  # the status line: the lead-in is over
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:  # w held: the terminal's auto-repeat
            child.send("w")
            time.sleep(0.05)
        child.expect(r"speed +[1-9][\d.]* mm/s")  # moving
        child.send("a")
        child.expect(r"drive: (\d+) cycles, travel ([\d.]+) mm")
        travel = float(child.match.group(2))
        child.expect(r"hrm:enabled>")
        child.sendline("quit")
        child.expect(pexpect.EOF)
    finally:
        child.close(force=True)
    assert child.exitstatus == 0
    assert travel > 1.0  # the held key advanced the tip
