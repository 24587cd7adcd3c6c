"""``hrm run`` at a terminal (a pty, pexpect): the progress bar and live line, pause and
resume from the keyboard, and Ctrl-C saying where it stopped the arm."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from tests.hrm_ctrl.cli.cli_helpers import small_plan

pexpect = pytest.importorskip("pexpect")

WAIT_S = 120  # generous: bring-up on a loaded machine (the run itself is timed by cycles)


def _relaxed_box(tmp_path: Path) -> Path:
    import drivers

    box = (Path(drivers.__file__).parent / "data" / "box.toml").read_text()
    box = box.replace("heartbeat_timeout_ms = 350", "heartbeat_timeout_ms = 2000")
    box = box.replace("missing_tpdo_cycles = 3 ", "missing_tpdo_cycles = 25 ")
    assert "heartbeat_timeout_ms = 2000" in box
    p = tmp_path / "box.toml"
    p.write_text(box)
    return p


def _spawn(tmp_path: Path, *extra: str) -> object:
    plan = tmp_path / "small.json"
    plan.write_text(json.dumps(small_plan()))
    env = dict(os.environ, HRM_CALIBRATIONS=str(tmp_path / "cal"), COLUMNS="160")
    env.pop("HRM_PROGRESS", None)
    args = ["-m", "hrm_ctrl.cli", "run", str(plan), "--sim", "--config",
            str(_relaxed_box(tmp_path)), "--log-dir", str(tmp_path / "runs"), *extra]  # fmt: skip
    return pexpect.spawn(sys.executable, args, env=env, encoding="utf-8", timeout=WAIT_S,
                         dimensions=(40, 160))  # fmt: skip


@pytest.mark.slow
def test_ctrl_c_says_where_it_stopped(tmp_path: Path) -> None:
    child = _spawn(tmp_path, "--speed", "3")
    child.expect(r"step \d+ [\d.]+ mm")  # the live line: the run is under way
    child.sendcontrol("c")
    child.expect(r"interrupted at (plan step \d+, travel [\d.]+ mm|the lead-in)[^\n]*every "
                 r"axis stopped")  # fmt: skip
    child.expect(pexpect.EOF)
    child.close()
    assert child.exitstatus == 130


@pytest.mark.slow
def test_keys_pause_and_resume(tmp_path: Path) -> None:
    child = _spawn(tmp_path, "--speed", "3")
    child.expect(r"step \d+ [\d.]+ mm")
    child.send("p")
    child.expect(r"PAUS(ING|ED)")
    child.send("p")
    child.expect(r"run record: (\S+\.json)")
    record = Path(child.match.group(1).strip())
    child.expect(pexpect.EOF)
    child.close()
    assert child.exitstatus == 0
    doc = json.loads(record.read_text())
    assert [a["action"] for a in doc["run_control"]] == ["pause", "resume"]
    assert doc["setpoints"]["play_state"] == "done"
