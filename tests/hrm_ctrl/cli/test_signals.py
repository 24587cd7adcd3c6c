"""SIGTERM and SIGHUP do what SIGINT does: quick stop, drives disabled, run record
written, CAN logs closed and readable (``hrm run --sim`` in its own process)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

STARTUP_TIMEOUT_S = 60.0
SYNCS_BEFORE_SIGNAL = 20  # the stream is running: the log (flushed every 0.1 s) shows it


def start_hold_run(logs: Path) -> subprocess.Popen[str]:
    """``hrm run --sim --hold 30`` in its own process, logging to ``logs`` as .asc."""
    return subprocess.Popen(
        [sys.executable, "-m", "hrm_ctrl.cli", "run", "--sim", "--hold", "30",
         "--log-dir", str(logs), "--log-format", "asc"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def syncs_logged(logs: Path) -> int:
    """SYNC frames in the live CAN logs (whole lines only are ever on disk)."""
    n = 0
    for log in logs.glob("*.asc"):
        try:
            n += sum(1 for m in can.LogReader(log) if m.arbitration_id == 0x080)
        except (ValueError, IndexError):  # a log still being opened
            pass
    return n


@pytest.mark.parametrize(
    ("sig", "status"),
    [(signal.SIGTERM, 128 + 15), (signal.SIGHUP, 128 + 1), (signal.SIGINT, 130)],
)
def test_a_signal_stops_the_run_cleanly(tmp_path: Path, sig: int, status: int) -> None:
    logs = tmp_path / "runs"
    proc = start_hold_run(logs)
    try:
        t_end = time.monotonic() + STARTUP_TIMEOUT_S
        while syncs_logged(logs) < SYNCS_BEFORE_SIGNAL:
            if time.monotonic() > t_end or proc.poll() is not None:
                pytest.fail(f"the stream did not start: {proc.communicate(timeout=5)}")
            time.sleep(0.1)
        proc.send_signal(sig)
        _out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == status, err
    name = signal.Signals(sig).name
    lines = [ln for ln in err.splitlines() if not ln.startswith("hrm run: --sim:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert (name in lines[0]) if sig != signal.SIGINT else ("interrupted" in lines[0])
    records = list(logs.glob("*.json"))
    assert len(records) == 1
    record = json.loads(records[0].read_text())
    causes = [c for s in record["streams"] for c in s["causes"]]
    assert causes and causes[0]["kind"] == "signal" and name in causes[0]["text"]
    assert any(e["kind"] == "quick_stop" for e in record["events"])
    assert any(e["kind"] == "disable" for e in record["events"])  # power stages off
    assert any(e["kind"] == "nmt" and "pre-operational" in e["text"] for e in record["events"])
    assert record["session_state"] == "closed"
    for log in logs.glob("*.asc"):
        frames = list(can.LogReader(log))
        stops = [
            m for m in frames
            if not m.is_rx and 0x200 < m.arbitration_id <= 0x27F
            and bytes(m.data[:2]) == b"\x02\x00"
        ]  # fmt: skip
        assert stops, f"{log.name}: no quick stop in the log"


def test_a_signal_during_bring_up_ends_cleanly(tmp_path: Path) -> None:
    """SIGTERM while the session listens, resets and enables (before the stream): one
    stderr line, no traceback, the run record written, the drives finished."""
    logs = tmp_path / "runs"
    proc = start_hold_run(logs)
    try:
        t_end = time.monotonic() + STARTUP_TIMEOUT_S
        while len(list(logs.glob("*.asc"))) < 2:  # the session is open: bring-up begins
            if time.monotonic() > t_end or proc.poll() is not None:
                pytest.fail(f"no CAN logs appeared: {proc.communicate(timeout=5)}")
            time.sleep(0.02)
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if not ln.startswith("hrm run: --sim:")]
    assert lines == ["hrm run: stopped by SIGTERM"], err
    records = list(logs.glob("*.json"))
    assert len(records) == 1
    record = json.loads(records[0].read_text())
    assert record["session_state"] == "closed"
