"""The ``stall_tolerant`` marker (``hrm_ctrl.hil.stall_reruns``): a failed test is rerun only
when the stall probe saw a machine stall covering the watchdog window during the failed
call, and its output says so; every other failure is final, whatever its message."""

from __future__ import annotations

import subprocess

import pytest

pytestmark = pytest.mark.skipif(
    subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode != 0,
    reason="SCHED_FIFO refused to this user (chrt -f 1): the stall probe is unavailable",
)

HEADER = """
import time
import pytest
from hrm_ctrl.hil.stalls import Stall

CALLS = []
TOLERANT = pytest.mark.stall_tolerant(window_s=0.03, watchdog="3 cycles without a TPDO")


def stall(probe, late_s, before_s=0.0):
    '''A stall of CPU 0 of late_s, ending before_s before now, added to the probe.'''
    time.sleep(late_s + 0.01)
    now = time.monotonic()
    probe.stalls.append(Stall(0, now - before_s - late_s, late_s))
"""


def outcomes(res: pytest.RunResult) -> dict[str, int]:
    """The counts of the inner run's closing line ("2 passed, 1 rerun")."""
    return {k: v for k, v in res.parseoutcomes().items() if k in ("passed", "failed", "rerun")}


def run(pytester: pytest.Pytester, body: str) -> pytest.RunResult:
    pytester.makepyfile(test_inner=HEADER + body)
    return pytester.runpytest("-p", "hrm_ctrl.hil.stall_reruns", "-p", "no:cacheprovider", "-rA")


def test_a_failure_without_a_stall_is_not_rerun_whatever_it_says(pytester: pytest.Pytester) -> None:
    res = run(
        pytester,
        """
@TOLERANT
def test_it():
    CALLS.append(1)
    assert False, "no TPDO for j01r0 in 3 cycles; heartbeat lost; EMCY 0x8130"

def test_calls():
    assert len(CALLS) == 1
""",
    )
    assert outcomes(res) == {"passed": 1, "failed": 1}
    res.stdout.fnmatch_lines(
        [
            "*no machine stall covered the 30 ms window of 3 cycles without a TPDO during the "
            "failed phase*not rerun*"
        ]
    )
    assert "stall reruns" not in res.stdout.str()


def test_a_failure_during_a_stall_covering_the_window_is_rerun_and_says_why(
    pytester: pytest.Pytester,
) -> None:
    res = run(
        pytester,
        """
@TOLERANT
def test_it(stall_probe):
    CALLS.append(1)
    if len(CALLS) == 1:
        stall(stall_probe, 0.045)
        assert False, "a watchdog fired"

def test_calls():
    assert len(CALLS) == 2
""",
    )
    assert outcomes(res) == {"passed": 2, "rerun": 1}
    out = res.stdout.str()
    # printed at once, and listed in the summary: which CPU, when, how long, which window
    res.stdout.fnmatch_lines(
        [
            "*test_it: attempt 1 failed; CPU ? stalled * ms from * s into the failed phase "
            "(monotonic * s), covering the 30 ms window of 3 cycles without a TPDO: rerun",
            "*stall reruns*",
            "*test_inner.py::test_it: attempt 1 failed; CPU ? stalled * ms*",
        ]
    )
    assert out.count("attempt 1 failed") == 2, out


def test_a_stall_shorter_than_the_window_or_outside_the_call_is_no_evidence(
    pytester: pytest.Pytester,
) -> None:
    res = run(
        pytester,
        """
@TOLERANT
def test_short(stall_probe):
    stall(stall_probe, 0.025)
    assert False

@pytest.fixture
def slow_setup(stall_probe):
    stall(stall_probe, 0.045)  # during the setup, before the call

@TOLERANT
def test_before_the_call(slow_setup):
    assert False
""",
    )
    assert outcomes(res) == {"failed": 2}
    assert res.stdout.str().count("no machine stall covered the 30 ms window") == 2


SETUP_STALL = """
import time
from hrm_ctrl.hil.stall_reruns import PROBE
from hrm_ctrl.hil.stalls import Stall

SETUPS = []


def pytest_runtest_setup(item):  # a stall in the first setup of test_it, before its fixtures
    if item.name == "test_it":
        SETUPS.append(1)
        if len(SETUPS) == 1:
            time.sleep(0.055)
            item.stash[PROBE].stalls.append(Stall(0, time.monotonic() - 0.05, 0.045))
"""


def test_a_setup_failing_during_a_stall_is_rerun_with_its_fixtures_set_up_again(
    pytester: pytest.Pytester,
) -> None:
    pytester.makeconftest(SETUP_STALL)
    res = run(
        pytester,
        """
@pytest.fixture(scope="module")
def box():  # a module-scoped bring-up that fails the first time
    CALLS.append(1)
    if len(CALLS) == 1:
        raise RuntimeError("no boot-up within 2 s")
    return "up"

@TOLERANT
def test_it(box):
    assert box == "up"

def test_calls():
    assert len(CALLS) == 2
""",
    )
    assert outcomes(res) == {"passed": 2, "rerun": 1}
    res.stdout.fnmatch_lines(["*test_it: attempt 1 failed; CPU ? stalled * ms*: rerun"])


def test_reruns_end_at_the_markers_count(pytester: pytest.Pytester) -> None:
    res = run(
        pytester,
        """
@pytest.mark.stall_tolerant(window_s=0.03, watchdog="3 cycles without a TPDO", reruns=1)
def test_it(stall_probe):
    CALLS.append(1)
    stall(stall_probe, 0.045)
    assert False

def test_calls():
    assert len(CALLS) == 2
""",
    )
    assert outcomes(res) == {"passed": 1, "failed": 1, "rerun": 1}
    res.stdout.fnmatch_lines(["*reruns exhausted (1)*"])


def test_a_marker_without_its_window_is_a_one_line_usage_error(pytester: pytest.Pytester) -> None:
    res = run(
        pytester,
        """
@pytest.mark.stall_tolerant(watchdog="3 cycles without a TPDO")
def test_it():
    pass
""",
    )
    assert res.ret == pytest.ExitCode.USAGE_ERROR
    res.stderr.fnmatch_lines(
        ["ERROR: test_inner.py::test_it: stall_tolerant window_s=None is not > 0 s"]
    )
    assert "Traceback" not in res.stderr.str() + res.stdout.str()


def test_a_pause_the_coarse_probe_saw_is_evidence_and_a_shorter_one_is_not(
    pytester: pytest.Pytester,
) -> None:
    """The vcan guest's probe (every 20 ms): the test's own probe process stopped for 300 ms
    (as the host stops scheduling the guest) covers a 120 ms window; a 20 ms stop does not
    (100 ms to spare for a late SIGCONT)."""
    pytester.makepyfile(
        test_inner="""
import os, signal, time
import pytest

CALLS = []
GUEST = pytest.mark.stall_tolerant(window_s=0.12, watchdog="3 cycles of 40 ms without a TPDO")


def pause(probe, s):
    os.kill(probe.pids[0], signal.SIGSTOP)
    time.sleep(s)
    os.kill(probe.pids[0], signal.SIGCONT)
    time.sleep(0.05)


@GUEST
def test_paused(stall_probe):
    CALLS.append(1)
    assert stall_probe.period_s == 0.02
    if len(CALLS) == 1:
        pause(stall_probe, 0.3)
        assert False, "heartbeats 542 ms old"


@GUEST
def test_short(stall_probe):
    pause(stall_probe, 0.02)
    assert False, "heartbeats 542 ms old"
"""
    )
    res = pytester.runpytest(
        "-p", "hrm_ctrl.hil.stall_reruns", "-p", "no:cacheprovider", "-rA",
        "--stall-probe-period=0.02",
    )  # fmt: skip
    assert outcomes(res) == {"passed": 1, "failed": 1, "rerun": 1}
    res.stdout.fnmatch_lines(
        [
            "*test_paused: attempt 1 failed; CPU ? stalled * ms from * s into the failed phase "
            "(monotonic * s), covering the 120 ms window of 3 cycles of 40 ms without a TPDO: "
            "rerun",
            "*no machine stall covered the 120 ms window * every 20 ms: * not rerun*",
        ]
    )


@pytest.mark.parametrize(
    ("period", "message"),
    [
        ("0.05", "*(--stall-probe-period=0.05): the probe could not see it"),
        ("soon", "--stall-probe-period='soon': expected seconds in (0, 1]"),
    ],
)  # fmt: skip
def test_a_probe_period_the_window_cannot_use_is_a_one_line_usage_error(
    pytester: pytest.Pytester, period: str, message: str
) -> None:
    pytester.makepyfile(test_inner=HEADER + "\n@TOLERANT\ndef test_it():\n    pass\n")
    res = pytester.runpytest(
        "-p", "hrm_ctrl.hil.stall_reruns", "-p", "no:cacheprovider",
        f"--stall-probe-period={period}",
    )  # fmt: skip
    assert res.ret == pytest.ExitCode.USAGE_ERROR
    res.stderr.fnmatch_lines([f"ERROR: *{message}"])
    assert "Traceback" not in res.stderr.str() + res.stdout.str()
