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
AFTER_LOGS_S = 2.0  # bring-up (listen 0.5 s, ~0.7 s) is over by then; the hold runs 30 s


@pytest.mark.parametrize(
    ("sig", "status"),
    [(signal.SIGTERM, 128 + 15), (signal.SIGHUP, 128 + 1), (signal.SIGINT, 130)],
)
def test_a_signal_stops_the_run_cleanly(tmp_path: Path, sig: int, status: int) -> None:
    logs = tmp_path / "runs"
    proc = subprocess.Popen(
        [sys.executable, "-m", "hrm_ctrl.cli", "run", "--sim", "--hold", "30",
         "--log-dir", str(logs), "--log-format", "asc"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        t_end = time.monotonic() + STARTUP_TIMEOUT_S
        while len(list(logs.glob("*.asc"))) < 2:
            if time.monotonic() > t_end or proc.poll() is not None:
                pytest.fail(f"no CAN logs appeared: {proc.communicate(timeout=5)}")
            time.sleep(0.05)
        time.sleep(AFTER_LOGS_S)
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
