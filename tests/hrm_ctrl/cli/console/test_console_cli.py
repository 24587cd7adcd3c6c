"""``hrm console`` and ``hrm status`` as a user runs them: a script on stdin (a
subprocess), the interactive shell on a pseudo-terminal (pexpect), the one-shot status."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.hrm_ctrl.cli.cli_helpers import run_cli

pexpect = pytest.importorskip("pexpect")

PYTHON = sys.executable
WAIT_S = 60.0  # generous: two cores shared by the whole test run


def env_for(home: Path, tmp: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(HOME=str(home), HRM_CALIBRATIONS=str(tmp / "calibrations"), TERM="xterm",
               PROMPT_TOOLKIT_NO_CPR="1")  # fmt: skip
    return env


def records(runs: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(runs.glob("run-*.json"))]


def disabled_at_the_end(record: dict) -> bool:
    """The run record shows the finish: the drives' last power change a disable (or the
    disable of a fault reset), not an enable, then NMT pre-operational, then closed."""
    kinds = [e.get("kind") for e in record["events"]]
    power = [i for i, k in enumerate(kinds) if k in ("enabled", "disable", "fault_reset")]
    if not power or kinds[power[-1]] == "enabled":
        return False
    texts = [e.get("text", "") for e in record["events"][power[-1] :]]
    return record["session_state"] == "closed" and any("pre-operational" in t for t in texts)


def run_script(tmp_path: Path, isolated_home: Path, text: str) -> subprocess.CompletedProcess:
    script = tmp_path / "procedure.txt"
    script.write_text(text)
    (tmp_path / "runs").mkdir(exist_ok=True)  # the log folder exists (it was refused once)
    with script.open() as stdin:
        return subprocess.run(
            [PYTHON, "-m", "hrm_ctrl.cli", "console", "--sim", "--log-dir", "runs"],
            stdin=stdin, capture_output=True, text=True, timeout=WAIT_S * 2, cwd=tmp_path,
            env=env_for(isolated_home, tmp_path),
        )  # fmt: skip


def test_script_runs_line_by_line_and_end_of_input_disables(tmp_path, isolated_home) -> None:
    p = run_script(tmp_path, isolated_home, "# bring up, move a little\n\nconnect\nenable\n"
                   "jog 2 alpha -1.5   # a comment\nstatus\n")  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    echoed = [line for line in p.stdout.splitlines() if line.startswith("> ")]
    assert echoed == ["> connect", "> enable", "> jog 2 alpha -1.5", "> status"]
    assert "jog 2 alpha -1.5 deg: done" in p.stdout
    (record,) = records(tmp_path / "runs")
    assert len(record["streams"]) == 1 and record["streams"][0]["completed"]
    assert disabled_at_the_end(record)


def test_script_stops_at_the_first_error_with_its_line(tmp_path, isolated_home) -> None:
    p = run_script(tmp_path, isolated_home, "connect\nenable\n\n# too far\njog 5 theta +20\n"
                   "jog 5 theta +2\n")  # fmt: skip
    assert p.returncode == 2
    err = p.stderr.strip().splitlines()
    assert err[-1] == ("hrm console: error: procedure.txt:5: jog: jog 5 theta +20 deg: larger "
                       "than a jog's 10 deg (use a plan)")  # fmt: skip
    assert "Traceback" not in p.stderr
    assert "> jog 5 theta +2" not in p.stdout.splitlines()  # the next line did not run
    (record,) = records(tmp_path / "runs")
    assert record["streams"] == []  # nothing moved
    assert disabled_at_the_end(record)


def test_unknown_command_names_the_line(tmp_path, isolated_home) -> None:
    p = run_script(tmp_path, isolated_home, "help\nfrobnicate 3\n")
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1] == (
        "hrm console: error: procedure.txt:2: frobnicate: unknown command (try 'help')"
    )
    assert not (tmp_path / "runs").exists() or records(tmp_path / "runs") == []  # no connect


@pytest.mark.slow  # ~12 s on the loaded 2-core machine (a pty, two moves, a home)
def test_interactive_shell_on_a_terminal(tmp_path, isolated_home) -> None:
    child = pexpect.spawn(
        PYTHON, ["-m", "hrm_ctrl.cli", "console", "--sim", "--log-dir", "runs"],
        cwd=str(tmp_path), env=env_for(isolated_home, tmp_path), encoding="utf-8",
        timeout=WAIT_S, dimensions=(60, 200),
    )  # fmt: skip
    child.logfile_read = (tmp_path / "terminal.log").open("w")  # what the user saw
    try:
        child.expect(r"hrm>")
        child.send("reset-\t")  # completion of a command name
        child.expect("reset-fault")
        child.sendcontrol("c")  # Ctrl-C at the prompt clears the line
        child.expect(r"hrm>")
        child.sendline("connect")
        child.expect(r"connected: 36 drives")
        child.expect(r"hrm:ready>")
        child.sendline("jog 5 theta +2")
        child.expect(r"error: jog: the drives are not enabled \(session READY; enable first\)")
        child.sendline("enable")
        child.expect(r"hrm:enabled>")
        child.send("jog 5 t\t")  # completion of an axis
        child.expect("theta")
        child.sendcontrol("c")
        child.expect(r"hrm:enabled>")
        child.sendline("jog 3 alpha +2")
        child.expect(r"jog 3 alpha \+2 deg: done")
        child.expect(r"hrm:enabled>")
        child.sendline("home 2")  # a slow home: still moving when Ctrl-C comes
        child.expect(r"home: moving, \d+ cycles")
        child.sendcontrol("c")  # Ctrl-C while moving: every axis stops
        child.expect(r"error: home: stopped.*: home: stopped by Ctrl-C")
        child.expect(r"hrm:stopped>")
        child.sendline("reset-fault")
        child.expect(r"reset: no drive was in FAULT")
        child.expect(r"hrm:ready>")
        child.sendline("quit")
        child.expect(pexpect.EOF)
    finally:
        child.close(force=True)
    assert child.exitstatus == 0
    history = (isolated_home / ".local/state/hrm/console_history").read_text()
    assert "+connect" in history and "+home 2" in history
    (record,) = records(tmp_path / "runs")
    assert [s["completed"] for s in record["streams"]] == [True, False]
    assert record["streams"][1]["causes"][0]["kind"] == "operator"
    assert disabled_at_the_end(record)


def test_status_one_shot(tmp_path, isolated_home, capsys) -> None:
    (tmp_path / "runs").mkdir()  # a log folder that exists (as ./runs does after one run)
    rc, out, err = run_cli(["status", "--sim", "--log-dir", str(tmp_path / "runs")], capsys)
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("connected: 36 drives")
    assert lines[1].startswith("session READY")
    assert sum(line.startswith("j") and "OPERATIONAL" in line for line in lines) == 36
    assert sum(line.startswith("bus ") for line in lines) == 2
    (record,) = records(tmp_path / "runs")
    assert record["streams"] == [] and record["session_state"] == "closed"


def test_status_json(tmp_path, isolated_home, capsys) -> None:
    rc, out, err = run_cli(["status", "--sim", "--json", "--log-dir", str(tmp_path / "r")], capsys)
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["state"] == "READY" and len(doc["nodes"]) == 36 and len(doc["buses"]) == 2
    node = doc["nodes"][0]
    assert node["motor"] == "j01r0" and node["state402"] == "SWITCH_ON_DISABLED"
    from hrm_ctrl.model import default_robot
    from hrm_ctrl.ropes.actuation import load_actuation

    pretension = float(np.ravel(load_actuation(default_robot()).routing.pretension_N)[0])
    assert node["tension_N"] == pytest.approx(pretension, rel=0.1)  # the straight arm


@pytest.mark.parametrize("command", ["console", "status"])
def test_bad_config_is_one_line_and_opens_no_bus(tmp_path, isolated_home, capsys, no_bus,
                                                 command) -> None:  # fmt: skip
    bad = tmp_path / "box.toml"
    bad.write_text("[control\n")
    rc, _out, err = run_cli([command, "--config", str(bad), "--log-dir", str(tmp_path / "r")],
                           capsys)  # fmt: skip
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and str(bad) in err
    assert no_bus == [] and not (tmp_path / "r").exists()


def test_missing_script_is_one_line_and_opens_no_bus(tmp_path, isolated_home, capsys, no_bus):
    missing = tmp_path / "nowhere.txt"
    rc, out, err = run_cli(["console", str(missing), "--log-dir", str(tmp_path / "r")], capsys)
    assert rc == 2 and out == ""
    assert err.strip() == f"hrm console: error: {missing}: cannot read (No such file or directory)"
    assert no_bus == [] and not (tmp_path / "r").exists()


def test_a_script_is_never_written_over_by_its_own_commands(tmp_path, isolated_home) -> None:
    """``plan --out SCRIPT`` from the script itself (named, or on stdin from the file):
    refused with the script's line, the script unchanged (it was replaced by the plan)."""
    text = "plan --scenario bent-pipe --out procedure.txt\n"
    p = run_script(tmp_path, isolated_home, text)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1] == (
        "hrm console: error: procedure.txt:1: plan: --out procedure.txt would overwrite the "
        f"console script being read ({tmp_path / 'procedure.txt'})"
    )
    assert (tmp_path / "procedure.txt").read_text() == text
    named = subprocess.run(
        [PYTHON, "-m", "hrm_ctrl.cli", "console", "--sim", "--log-dir", "runs", "procedure.txt"],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=WAIT_S * 2,
        cwd=tmp_path, env=env_for(isolated_home, tmp_path),
    )  # fmt: skip
    assert named.returncode == 2 and "would overwrite the console script" in named.stderr
    assert (tmp_path / "procedure.txt").read_text() == text
