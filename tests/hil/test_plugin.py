"""The ``hrm_hil`` pytest plugin itself: loaded through its entry point, cheap to load,
its options, and the example of ``docs/hil.md`` (the same text as
``docs/examples/test_hil_example.py``) run as a user runs it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT, STALL_TOLERANT_PRODUCTION

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "docs" / "examples" / "test_hil_example.py"
DOC = REPO / "docs" / "hil.md"
RUN_TIMEOUT_S = 240.0


def run_pytest(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """pytest in a folder of its own (no project conftest, no project ini): as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rs", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
    )


def test_the_docs_show_the_example_verbatim() -> None:
    doc = DOC.read_text()
    m = re.search(
        r"<!-- example: docs/examples/test_hil_example.py -->\n```python\n(.*?)```", doc, re.S
    )
    assert m is not None, "docs/hil.md: no example block after its marker"
    assert m.group(1) == EXAMPLE.read_text(), "docs/hil.md and docs/examples differ"


def test_loading_the_plugin_imports_nothing_of_the_stack() -> None:
    code = (
        "import sys, hrm_ctrl.hil.plugin as p; "
        "print(sorted({m.split('.')[0] for m in sys.modules} "
        "& {'drivers', 'sim_bus', 'can', 'canopen', 'numpy', 'calibration'}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout


def test_the_plugin_comes_through_its_entry_point(tmp_path: Path) -> None:
    (tmp_path / "test_x.py").write_text(
        "def test_kind(hrm_bus_kind, hrm_box_mode):\n"
        "    assert hrm_box_mode.value == 'inprocess' and hrm_bus_kind.value == 'virtual'\n"
    )
    res = run_pytest(tmp_path, "--hrm-bus", "virtual", "--hrm-box", "inprocess")
    assert res.returncode == 0 and "1 passed" in res.stdout, res.stdout + res.stderr
    res = run_pytest(tmp_path, "--help")
    assert "--hrm-bus" in res.stdout and "--hrm-box" in res.stdout


def test_a_virtual_bus_with_a_box_process_skips_naming_why(tmp_path: Path) -> None:
    (tmp_path / "test_x.py").write_text("def test_box(hrm_box):\n    pass\n")
    res = run_pytest(tmp_path, "--hrm-bus", "virtual", "--hrm-box", "process")
    assert res.returncode == 0 and "1 skipped" in res.stdout, res.stdout + res.stderr
    assert "private to one process" in res.stdout


def test_an_unknown_bus_is_a_usage_error(tmp_path: Path) -> None:
    (tmp_path / "test_x.py").write_text("def test_nothing():\n    pass\n")
    res = run_pytest(tmp_path, "--hrm-bus", "can9")
    assert res.returncode == 4, res.stdout + res.stderr
    assert "--hrm-bus" in res.stderr and "can9" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("value", ["ipc,ipc", "auto,ipc", "udp_multicast,auto"])
def test_a_bus_given_twice_is_a_usage_error(tmp_path: Path, value: str) -> None:
    """``auto`` is ``ipc`` or ``udp_multicast``: either beside it is the same bus twice
    (every test would run twice on it)."""
    (tmp_path / "test_x.py").write_text("def test_nothing():\n    pass\n")
    res = run_pytest(tmp_path, "--hrm-bus", value)
    assert res.returncode == 4, res.stdout + res.stderr
    assert "--hrm-bus" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("value", ["50", "-1", "high", " 3", "1_0", "+3", "\u0663"])
def test_a_realtime_priority_outside_the_safe_range_is_a_usage_error(
    tmp_path: Path, value: str
) -> None:
    (tmp_path / "test_x.py").write_text("def test_nothing():\n    pass\n")
    res = run_pytest(tmp_path, "--hrm-rt-priority", value)
    assert res.returncode == 4, res.stdout + res.stderr
    assert "--hrm-rt-priority" in res.stderr and "0..49" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("value", ["-1", "2000000001", "soon"])
def test_a_cpu_latency_outside_its_range_is_a_usage_error(tmp_path: Path, value: str) -> None:
    (tmp_path / "test_x.py").write_text("def test_nothing():\n    pass\n")
    res = run_pytest(tmp_path, "--hrm-cpu-latency-us", value)
    assert res.returncode == 4, res.stdout + res.stderr
    assert "--hrm-cpu-latency-us" in res.stderr and "0..2000000000" in res.stderr
    assert "Traceback" not in res.stderr


def test_cpu_latency_reaches_the_session_and_the_box_configuration(tmp_path: Path) -> None:
    """The option is ``[control] cpu_wakeup_latency_us`` of the configuration host and box
    share; the session holds it (or, without access to the device, says why)."""
    (tmp_path / "test_x.py").write_text(
        "def test_lat(hrm_session, hrm_cpu_latency_us, hrm_box_config):\n"
        "    assert hrm_cpu_latency_us == 0\n"
        "    assert 'cpu_wakeup_latency_us = 0' in hrm_box_config.read_text()\n"
        "    assert hrm_session.control.cpu_wakeup_latency_us == 0\n"
        "    lat = hrm_session.cpu_latency\n"
        "    assert lat.held or lat.refusal\n"
    )
    res = run_pytest(tmp_path, "--hrm-cpu-latency-us", "0")
    assert res.returncode == 0 and "1 passed" in res.stdout, res.stdout + res.stderr


def fifo_allowed() -> bool:
    return subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not fifo_allowed(), reason="SCHED_FIFO refused to this user (chrt -f 1)")
def test_rt_priority_puts_a_box_process_and_the_session_under_sched_fifo(tmp_path: Path) -> None:
    (tmp_path / "test_x.py").write_text(
        "import os\n"
        "def test_rt(hrm_box, hrm_session, hrm_rt_priority):\n"
        "    assert hrm_rt_priority == 7\n"
        "    assert os.sched_getscheduler(hrm_box.proc.pid) == os.SCHED_FIFO\n"
        "    assert os.sched_getparam(hrm_box.proc.pid).sched_priority == 7\n"
        "    assert hrm_session.realtime_granted\n"
        "    assert hrm_session.control.realtime_priority == 7\n"
    )
    res = run_pytest(tmp_path, "--hrm-rt-priority", "7")
    assert res.returncode == 0 and "1 passed" in res.stdout, res.stdout + res.stderr


@pytest.mark.slow  # 10-25 s: a pytest process of its own, a box, two bring-ups
@pytest.mark.parametrize(
    "options",
    [
        pytest.param((), marks=STALL_TOLERANT_PRODUCTION, id="default"),
        pytest.param(
            ("--hrm-bus", "virtual", "--hrm-box", "inprocess"),
            marks=STALL_TOLERANT,
            id="virtual-inprocess",
        ),
    ],
)
def test_the_docs_example_passes(tmp_path: Path, options: tuple[str, ...]) -> None:
    """At production settings on the loaded 2-core machine a stall of the machine can stop
    a run on its own (docs/hil.md, "Known limits"): rerun only when the stall probe saw it."""
    (tmp_path / EXAMPLE.name).write_text(EXAMPLE.read_text())
    res = run_pytest(tmp_path, *options)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-1000:]
    assert "2 passed" in res.stdout, res.stdout


def test_the_wire_log_finds_onset_stop_and_confirmation() -> None:
    """WireLog on frames made here: a node's TPDOs end at 1.0 s, three SYNCs go unanswered,
    the quick stop goes out at 1.04 s, the other node confirms it at 1.05 s."""
    import can

    from hrm_ctrl.hil.wirelog import WireLog

    def msg(t: float, cob: int, data: bytes, sent: bool) -> can.Message:
        return can.Message(timestamp=t, arbitration_id=cob, data=data, is_rx=not sent)

    enabled, quick_stop_active = bytes([0x37, 0x02, 0, 0, 0, 0]), bytes([0x17, 0x02, 0, 0, 0, 0])
    frames = [msg(1.0, 0x181, enabled, False), msg(1.0, 0x182, enabled, False)]
    frames += [msg(1.0 + 0.01 * k, 0x080, b"", True) for k in (1, 2, 3)]
    frames += [msg(1.011 + 0.01 * k, 0x182, enabled, False) for k in (0, 1, 2)]
    frames += [msg(1.04, 0x202, bytes([0x06, 0, 0, 0, 0, 0]), True)]  # shutdown: no stop
    frames += [msg(1.041, 0x201, bytes([0x02, 0, 0, 0, 0, 0]), True)]  # quick stop
    frames += [msg(1.045, 0x080, b"", True), msg(1.05, 0x182, quick_stop_active, False)]
    log = WireLog.from_frames({"can0": frames})
    qs = log.quick_stop()
    assert qs is not None and qs.t_s == 1.041 and qs.cob_id == 0x201
    last = log.last_received("can0", 0x181, before_s=qs.t_s)
    assert last is not None and last.t_s == 1.0
    assert log.syncs_sent("can0", last.t_s, qs.t_s) == 3
    confirmed, silent = log.stop_confirmed({"can0": {"a": 1, "b": 2}}, qs.t_s)
    assert confirmed == 1.05 and silent == ["a"]


def test_the_wire_log_reads_logs_bounded(tmp_path: Path) -> None:
    """WireLog.read: the frames of each bus's log, in time order; a log past the frame
    bound, damaged, or not a regular file is one RunLogError naming it."""
    import os

    import can

    from hrm_ctrl.formats.runlog import RunLogError
    from hrm_ctrl.hil.wirelog import WireLog

    paths = [tmp_path / "run_a.blf", tmp_path / "run_b.blf"]
    for b, p in enumerate(paths):
        with can.Logger(str(p)) as log:
            for k in range(5):
                log(
                    can.Message(
                        timestamp=1.0 + 0.01 * k + 0.001 * b,
                        arbitration_id=0x80,
                        data=b"",
                        is_rx=False,
                    )
                )
    wire = WireLog.read(paths, ["a", "b"])
    assert [f.bus for f in wire.frames] == ["a", "b"] * 5
    assert wire.syncs_sent("b", 0.0, 2.0) == 5
    with pytest.raises(RunLogError, match=r"run_b\.blf: more than 8 frames in all"):
        WireLog.read(paths, ["a", "b"], max_frames=8)
    with pytest.raises(RunLogError, match=r"run_a\.blf: more than 4 frames$"):
        WireLog.read(paths, ["a", "b"], max_frames=4)
    paths[1].write_bytes(b"LOGG" + b"\xff" * 200)
    with pytest.raises(RunLogError, match=r"run_b\.blf: ") as exc:
        WireLog.read(paths, ["a", "b"])
    assert "\n" not in str(exc.value)
    paths[1].unlink()
    os.mkfifo(paths[1])  # would block a reader for ever
    with pytest.raises(RunLogError, match=r"run_b\.blf: CAN log is not a regular file"):
        WireLog.read(paths, ["a", "b"])


BAD_FIXTURES = {
    "nodes-not-maps": ("hrm_box_nodes", "('j01r0',)", "hrm_box_nodes[0]: a node map"),
    "nodes-bad-id": ("hrm_box_nodes", "({'j01r0': 1.5},)", "node id must be an integer"),
    "control-nan": (
        "hrm_control",
        "{'heartbeat_timeout_ms': float('nan')}",
        "hrm_control['heartbeat_timeout_ms']: nan is not a finite number",
    ),
    "control-out-of-range": ("hrm_control", "{'missing_tpdo_cycles': 0}", "missing_tpdo_cycles"),
}


@pytest.mark.parametrize("case", sorted(BAD_FIXTURES))
def test_a_bad_fixture_value_is_one_line_naming_it(tmp_path: Path, case: str) -> None:
    """A user's ``hrm_box_nodes``/``hrm_control`` override that is not a box: the test
    errors with one line naming the fixture and entry, not a traceback through the plugin."""
    name, value, words = BAD_FIXTURES[case]
    (tmp_path / "test_x.py").write_text(
        "import pytest\n"
        f"@pytest.fixture(scope='module')\ndef {name}():\n    return {value}\n"
        "def test_box(hrm_box):\n    pass\n"
    )
    res = run_pytest(tmp_path, "--hrm-bus", "virtual", "--hrm-box", "inprocess")
    assert res.returncode == 1 and "1 error" in res.stdout, res.stdout + res.stderr
    assert "hrm_box_config: " in res.stdout and words in res.stdout, res.stdout
    assert "Traceback" not in res.stdout and "rig.py" not in res.stdout, res.stdout


def test_a_box_process_that_exits_at_once_is_reported_with_its_status(tmp_path: Path) -> None:
    """A motor the rope layer does not know: ``hrm sim`` refuses it and exits at once; the
    error says so (not a 20 s wait for 'ready')."""
    (tmp_path / "test_x.py").write_text(
        "import pytest\n"
        "@pytest.fixture(scope='module')\ndef hrm_box_nodes():\n    return ({'j99r9': 1},)\n"
        "def test_box(hrm_box):\n    pass\n"
    )
    res = run_pytest(tmp_path, "--hrm-bus", "auto")
    assert res.returncode == 1 and "1 error" in res.stdout, res.stdout + res.stderr
    assert re.search(r"hrm_box: box process \S+: exited \(status 2\): .*j99r9", res.stdout)
    assert "within" not in res.stdout and "Traceback" not in res.stdout, res.stdout


def test_fault_injection_refuses_what_would_hide_or_smuggle_a_fault(tmp_path: Path) -> None:
    """``hrm_fault.after`` refuses a delay that is not a number of seconds in range (a timer
    would die in its thread and the fault never come, or come at once); a spec with a
    newline (a second box command) is refused and the box keeps running; the box process
    is in a session of its own (a terminal's Ctrl-C reaches only the test run)."""
    (tmp_path / "test_x.py").write_text(
        "import math, os, pytest\n"
        "from sim_bus.faults import FaultSpecError\n"
        "@pytest.fixture(scope='module')\ndef hrm_box_nodes():\n"
        "    return ({'j01r0': 1, 'j01r1': 2},)\n"
        "@pytest.mark.parametrize('delay', [math.inf, 1e300, math.nan, -1.0, '0.1', True])\n"
        "def test_delay(hrm_fault, delay):\n"
        "    with pytest.raises(FaultSpecError, match='delay must be a number of seconds'):\n"
        "        hrm_fault.after(delay, 'heartbeat-stop:j01r1')\n"
        "def test_newline(hrm_box, hrm_fault, hrm_arm_state):\n"
        "    with pytest.raises(FaultSpecError, match='control character'):\n"
        "        hrm_fault('heartbeat-stop:j01r1\\nquit')\n"
        "    assert hrm_box.proc.poll() is None and hrm_arm_state().counts\n"
        "    assert os.getsid(hrm_box.proc.pid) != os.getsid(0)\n"
    )
    res = run_pytest(tmp_path, "--hrm-bus", "auto")
    assert res.returncode == 0 and "7 passed" in res.stdout, res.stdout + res.stderr
