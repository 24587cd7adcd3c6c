"""Fault scripts, the ``hrm sim`` command and its control channel."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import can
import pytest

import drivers.protocol.cia301 as cia301
from drivers.config import box_config_from_dict, load_box_config
from hrm_ctrl.cli import main
from sim_bus.box import SimBox
from sim_bus.faults import FaultSpecError, apply_fault, parse_fault
from sim_bus.runner import run_box_process

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("text", "kind", "args", "at"),
    [
        ("heartbeat-stop:j01r0", "heartbeat-stop", ("j01r0",), None),
        ("drive-fault:j03r1@1.5", "drive-fault", ("j03r1",), 1.5),
        ("drop:can0", "drop", ("can0",), None),
        ("delay:can1:20:0x181:3@0", "delay", ("can1", "20", "0x181", "3"), 0.0),
        ("sensor-garbage:128", "sensor-garbage", ("128",), None),
        ("reset", "reset", (), None),
        (
            "delay:can0:60000:0x181:1000000000@86400",
            "delay",
            ("can0", "60000", "0x181", "1000000000"),
            86400.0,
        ),
    ],
)
def test_parse_fault(text: str, kind: str, args: tuple[str, ...], at: float | None) -> None:
    f = parse_fault(text)
    assert (f.kind, f.args, f.at_s) == (kind, args, at)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("explode:j01r0", "unknown kind"),
        ("rope-snap", "takes 1..1"),
        ("drop:can0:0x900", "COB-ID"),
        ("drop:can0:0x181:0", "count"),
        ("delay:can0:abc", "milliseconds"),
        ("bus-off:can0@soon", "seconds"),
        ("bus-off:can0@-1", ">= 0"),
        ("heartbeat-stop:j01r1\nquit", "control character"),  # would be a second command
        ("rope-snap:j01r0\x1b[2J", "control character"),
        ("drive-fault:j01r0\n", "control character"),  # at an end too (hrm_fault.after)
        ("\treset", "control character"),
        # absurd numbers: bounded, one line each
        ("delay:can0:1e300", r"0\.\.60000 ms"),
        ("delay:can0:inf", ">= 0 ms"),
        ("delay:can0:20:0x181:99999999999999999999", r"count must be 1\.\.1000000000"),
        ("drop:can0:0x181:10000000000", r"count must be 1\.\.1000000000"),
        ("drop:can0:0x181:" + "9" * 5000, "must be an integer"),
        ("rope-snap:j01r0@1e300", r"0\.\.86400 s"),
        ("bus-off:can0@nan", ">= 0"),
        ("sensor-garbage:1e9", "must be an integer"),
        ("sensor-corrupt:10000000001", r"count must be in 0\.\.1000000000"),
    ],
)
def test_bad_fault_specs_are_one_line_errors(text: str, match: str) -> None:
    with pytest.raises(FaultSpecError, match=match):
        parse_fault(text)


def _hrm_sim_box() -> tuple[SimBox, list[can.BusABC]]:
    tag = uuid.uuid4().hex[:8]
    kw = [{"interface": "hrm_sim", "channel": f"f-{tag}-{k}"} for k in range(2)]
    cfg = load_box_config(None).with_bus_kwargs(kw)
    hosts = [can.Bus(**k) for k in kw]
    return SimBox(cfg, tension_noise_N=0.0).start(), hosts


def test_wire_faults_through_the_box_and_reset() -> None:
    box, hosts = _hrm_sim_box()
    try:
        apply_fault(parse_fault("bus-off:can1"), box)
        with pytest.raises(can.CanOperationError, match="bus off"):
            hosts[1].send(cia301.make_sync())
        apply_fault(parse_fault("rope-snap:j12r2"), box)
        apply_fault(parse_fault("jam:j02r0"), box)
        assert box.arm.snapped == (35,)
        apply_fault(parse_fault("reset"), box)
        hosts[1].send(cia301.make_sync())  # bus back on
        assert box.arm.snapped == () and not box.drives["j02r0"].jammed
        with pytest.raises(FaultSpecError, match="no tension board"):
            apply_fault(parse_fault("sensor-silent"), box)
    finally:
        box.stop()
        for h in hosts:
            h.shutdown()


def run_control(inp: io.StringIO) -> list[dict[str, Any]]:
    """A one-drive box run in a thread on the control lines of ``inp``: its JSON events."""
    doc = {"buses": {"can0": {"interface": "hrm_sim", "channel": f"r-{uuid.uuid4().hex[:8]}",
                              "bitrate": 1_000_000, "nodes": {"j01r0": 1}}}}  # fmt: skip
    out = io.StringIO()
    t = threading.Thread(
        target=run_box_process,
        args=(box_config_from_dict(doc, "test"),),
        kwargs={"control": True, "out": out, "inp": inp},
    )
    t.start()
    t.join(20.0)
    assert not t.is_alive()
    return [json.loads(line) for line in out.getvalue().splitlines()]


def test_runner_control_channel_in_process(tmp_path: Path) -> None:
    events = run_control(io.StringIO("state\nfault rope-snap:j01r0\nfault bogus\nstats\nquit\n"))
    kinds = [e["event"] for e in events]
    assert kinds[0] == "ready" and Path(events[0]["tension_port"]).name.isdigit()
    assert kinds[1:] == ["state", "fault", "error", "stats", "stopped"]
    assert len(events[1]["centres"]) == 13
    assert "unknown kind" in events[3]["error"]
    assert any("snapped" in e for e in events[4]["events"])


def test_cli_bad_inputs_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[buses.can0]\ninterface = 'virtual'\nchannel = 'x'\nbitrate = 0\nnodes = {}\n")
    for argv, match in [
        (["sim", "--config", str(bad)], "bitrate"),
        (["sim", "--config", str(tmp_path / "none.toml")], "not found"),
        (["sim", "--fault", "rope-snap:j99r9"], "no simulated drive"),
        (["sim", "--fault", "bus-off:can7"], "no bus"),
        (["sim", "--duration", "-1"], "--duration"),
        (["sim", "--fault", "delay:can0:1e300"], "delay must be 0..60000 ms"),
    ]:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and match in err, err


def test_hrm_sim_process_runs_and_stops_on_duration(tmp_path: Path) -> None:
    cfg = tmp_path / "box.toml"
    cfg.write_text(
        "[buses.can0]\ninterface = 'virtual'\nchannel = 'p'\nbitrate = 1000000\n"
        "[buses.can0.nodes]\nj01r0 = 1\n"
    )
    t0 = time.monotonic()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "hrm_ctrl.cli",
            "sim",
            "--config",
            str(cfg),
            "--duration",
            "0.5",
            "--fault",
            "sensor-silent@0.1",
        ],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    lines = [json.loads(x) for x in proc.stdout.splitlines()]
    assert [e["event"] for e in lines] == ["ready", "fault", "stopped"]
    assert lines[1]["fault"] == "sensor-silent"
    assert time.monotonic() - t0 < 20


class _SlowInput(io.StringIO):
    """Control lines, then ``quit`` only after ``wait_s`` (a scheduled fault's time)."""

    def __init__(self, text: str, wait_s: float) -> None:
        super().__init__(text)
        self.wait_s = wait_s
        self.done = False

    def readline(self, size: int | None = -1) -> str:  # type: ignore[override]
        line = super().readline(size)
        if line or self.done:
            return line
        self.done = True
        time.sleep(self.wait_s)
        return "quit\n"


def test_control_channel_bounds_its_lines_and_schedules_a_fault_at_its_time() -> None:
    """A control line over 4096 characters is one error event (a 200 MB line was read
    whole and echoed back), and ``fault SPEC@T`` waits until T (it was applied at once);
    a fault count over the bound is refused (a huge one killed the tension board)."""
    inp = _SlowInput("x" * 10_000 + "\nfault rope-snap:j01r0@0.1\nfault sensor-garbage:70000\n",
                     wait_s=1.0)  # fmt: skip
    events = run_control(inp)
    assert [e["event"] for e in events[1:]] == [
        "error", "fault_scheduled", "error", "fault", "stopped"
    ]  # fmt: skip
    assert events[1]["error"] == "control line longer than 4096 characters"
    assert "count must be in 0..65536" in events[3]["error"]
    assert events[4]["fault"].startswith("rope-snap") and events[4]["t_s"] >= 0.1
