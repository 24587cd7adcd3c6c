"""``hrm run``: a plan on the simulated box; bad input is one line, no files, no frames."""

from __future__ import annotations

import errno
import hashlib
import json
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from drivers.canlog import TrafficLog
from hrm_ctrl.cli import main
from hrm_ctrl.formats.planfile import write_plan
from tests.hrm_ctrl.cli.cli_helpers import small_plan


def write_small_plan(path: Path) -> None:
    write_plan(path, small_plan())


def test_run_plan_on_the_simulated_box(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    plan = tmp_path / "plan.json"
    write_small_plan(plan)
    logs = tmp_path / "runs"
    rc = main(["run", str(plan), "--sim", "--log-dir", str(logs), "--speed", "60", "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True
    assert summary["cycles"] >= 26  # 15 mm at 60 mm/s = 0.25 s, + hold
    record = json.loads(Path(summary["run_record"]).read_text())
    assert record["plan_file"] == str(plan) and record["simulated_box"] is True
    assert record["plan_sha256"] == hashlib.sha256(plan.read_bytes()).hexdigest()
    assert record["plan_format"] == "hrm-plan/1" and record["plan_steps"] == 4
    assert record["setpoints"]["source"] == "plan"
    assert len(list(logs.glob("*.blf"))) == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.json"], "plan file not found"),
        (["--hold", "1", "--jog", "j01r0:1:1"], "give exactly one of"),
        (["--jog", "j01r0:9999999:1"], "jog j01r0: 9999999 counts/s exceeds"),
        (["--jog", "j01r0:fast"], "expected MOTOR:COUNTS_PER_S:SECONDS"),
        (["--hold", "1", "--config", "nope.toml"], "bus configuration not found"),
        (["--hold", "-1"], "--hold must be > 0 s"),
    ],
)
def test_bad_input_is_one_line_without_files(
    tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str], message: str
) -> None:
    logs = tmp_path / "runs"
    rc = main(["run", *args, "--sim", "--log-dir", str(logs)])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and err.count("\n") == 1, err
    assert not logs.exists()


def test_busload_command(capsys: pytest.CaptureFixture) -> None:
    assert main(["busload"]) == 0
    out = capsys.readouterr().out
    assert out.count("worst-case load 43.2%") == 2 and "125 Hz" in out
    assert main(["busload", "--rate", "200", "--json"]) == 1
    loads = json.loads(capsys.readouterr().out)
    assert [bl["fits"] for bl in loads] == [False, False]


@pytest.mark.parametrize("where", ["file", "under_file", "proc"])
def test_bad_log_dir_is_one_line_before_any_bus_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[dict[str, Any]], where: str
) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("not a directory")
    bad = {"file": blocker, "under_file": blocker / "runs", "proc": Path("/proc/nope")}[where]
    rc = main(["run", "--hold", "0.1", "--sim", "--log-dir", str(bad)])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith(f"hrm run: error: log directory {bad}: ") and err.count("\n") == 1, err
    assert no_bus == []
    assert blocker.read_text() == "not a directory"


def test_rate_0x60C2_cannot_encode_is_refused_before_any_bus_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture, no_bus: list[dict[str, Any]]
) -> None:
    from drivers import default_box_path

    box = tmp_path / "box.toml"
    box.write_text(default_box_path().read_text().replace("rate_hz = 100", "rate_hz = 30", 1))
    assert "rate_hz = 30" in box.read_text()
    logs = tmp_path / "runs"
    rc = main(["run", "--hold", "0.1", "--sim", "--config", str(box), "--log-dir", str(logs)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert f"{box}: control.rate_hz must give a period 0x60C2 can encode" in err
    assert no_bus == [] and not logs.exists()


def test_busload_refuses_a_rate_0x60C2_cannot_encode(capsys: pytest.CaptureFixture) -> None:
    assert main(["busload", "--rate", "30"]) == 2
    err = capsys.readouterr().err
    assert "--rate 30: must give a period 0x60C2 can encode" in err and err.count("\n") == 1


def test_incomplete_can_log_fails_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A disk that fills up after each log's first write: the next write of frames fails
    with ENOSPC, as os.write would (the log is cut back to its last whole write)."""
    real_flush = TrafficLog._flush
    wrote: set[int] = set()

    def full_disk_flush(log: TrafficLog) -> None:
        if id(log) in wrote and log._unflushed:
            log._break(OSError(errno.ENOSPC, "No space left on device"))
            return
        real_flush(log)
        wrote.add(id(log))

    monkeypatch.setattr(TrafficLog, "_flush", full_disk_flush)
    logs = tmp_path / "runs"
    rc = main(["run", "--hold", "0.1", "--sim", "--log-dir", str(logs), "--json"])
    out = capsys.readouterr()
    assert rc == 2, out.err
    lines = [x for x in out.err.splitlines() if "CAN log" in x]
    assert len(lines) == 1 and lines[0].startswith("hrm run: error: CAN log incomplete: "), out.err
    assert "No space left on device" in lines[0] and "Traceback" not in out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True and summary["can_log_errors"]
    record = json.loads(Path(summary["run_record"]).read_text())
    assert len(record["can_log_errors"]) == 2  # both buses' logs
    assert all("No space left on device" in e for e in record["can_log_errors"])


def test_complete_can_logs_exit_zero(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    logs = tmp_path / "runs"
    rc = main(["run", "--hold", "0.1", "--sim", "--log-dir", str(logs), "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["can_log_errors"] == [] and "CAN log" not in out.err
    record = json.loads(Path(summary["run_record"]).read_text())
    assert record["plan_file"] is None and record["can_log_errors"] == []


def test_a_plan_with_a_return_leg_plays_out_and_back(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """In to 15 mm and back out (phase ``return``): the plan plays on the simulated box,
    and every rope motor's RPDO targets go out and come back to where they started."""
    plan = tmp_path / "plan.json"
    write_small_plan(plan)
    doc = json.loads(plan.read_text())
    for step in doc["steps"]:
        step["phase"] = "in"
    back = [dict(s, phase="return") for s in reversed(doc["steps"][:-1])]
    doc["steps"] += back
    plan.write_text(json.dumps(doc))
    logs = tmp_path / "runs"
    rc = main(["run", str(plan), "--sim", "--log-dir", str(logs), "--speed", "60", "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    summary = json.loads(out.out)
    assert summary["completed"] is True and summary["causes"] == []
    assert summary["cycles"] >= 51  # 30 mm of travel at 60 mm/s = 0.5 s, + hold
    targets: dict[tuple[str, int], list[int]] = {}  # (bus log, COB-ID): RPDO targets
    for log in sorted(logs.glob("*.blf")):
        for m in can.LogReader(log):
            if not m.is_rx and 0x200 < m.arbitration_id <= 0x27F and m.data[:2] == b"\x0f\x00":
                pos = int.from_bytes(bytes(m.data[2:6]), "little", signed=True)
                targets.setdefault((log.name, m.arbitration_id), []).append(pos)
    assert len(targets) >= 2
    swing = {cid: max(abs(t - ts[0]) for t in ts) for cid, ts in targets.items()}
    assert max(swing.values()) > 1000  # the arm really moved out ...
    for (bus, cid), ts in targets.items():
        far = int(np.argmax([abs(t - ts[0]) for t in ts]))
        assert abs(ts[-1] - ts[0]) <= 2, f"{bus} 0x{cid:03X} did not come back"  # ... and back
        assert 0.3 < far / len(ts) < 0.7 or swing[(bus, cid)] < 50  # the far end is mid-run
