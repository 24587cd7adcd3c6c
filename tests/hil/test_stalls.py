"""The machine-stall probe (``hrm_ctrl.hil.stalls``): which late cycles fall on a stall of
the machine, the probe processes and their refusals."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hrm_ctrl.hil.stalls import MARGIN_S, STALL_THRESHOLD_S, Stall, StallProbe, explained

T = 0.01


def overlaps(ev: tuple[float, float, int], stalls: list[Stall]) -> bool:
    """The definition, one stall at a time."""
    deadline, late, missing = ev
    lo = deadline - T if missing else deadline
    hi = deadline + max(late, 0.0)
    return any(s.at_s - MARGIN_S <= hi and s.at_s + s.late_s >= lo for s in stalls)


times = st.floats(0.0, 2.0, allow_nan=False)
stall = st.builds(Stall, st.just(0), times, st.floats(0.001, 0.2, allow_nan=False))
event = st.tuples(times, st.floats(-0.001, 0.02, allow_nan=False), st.integers(0, 36))


@given(st.lists(event, max_size=30), st.lists(stall, max_size=30))
@example([(1.0, 0.003, 0)], [Stall(0, 0.5, 0.6)])  # a long stall that started well before
@example([(1.0, 0.0, 18)], [Stall(0, 0.991, 0.0015)])  # feedback due in the period before
@example([(1.0, 0.003, 0)], [Stall(0, 1.0035, 0.002)])  # just after the late interval: no
def test_explained_is_the_overlap_of_each_event_with_some_stall(
    events: list[tuple[float, float, int]], stalls: list[Stall]
) -> None:
    assert explained(events, stalls, T) == [e for e in events if overlaps(e, stalls)]


def test_a_bad_cpu_argument_is_a_one_line_usage_error() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.hil.stalls", "zero"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2 and res.stderr.startswith("usage:"), res.stderr
    assert "Traceback" not in res.stderr


def test_a_probe_on_a_cpu_the_machine_lacks_reports_itself_unavailable() -> None:
    missing = max(os.sched_getaffinity(0)) + 64
    with StallProbe([missing]) as probe:
        pass
    assert not probe.available
    assert probe.refusal is not None and f"CPU {missing}" in probe.refusal
    assert probe.stalls == []


def fifo_allowed() -> bool:
    return subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not fifo_allowed(), reason="SCHED_FIFO refused to this user (chrt -f 1)")
def test_probes_on_every_cpu_report_only_stalls_inside_their_run() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    t0 = time.monotonic()
    with StallProbe(cpus) as probe:
        time.sleep(0.5)
    t1 = time.monotonic()
    assert probe.available, probe.refusal
    assert 0.45 <= probe.duration_s <= t1 - t0
    # (times come rounded to the microsecond: a stall just over the threshold may read as it)
    assert all(
        s.cpu in cpus and t0 <= s.at_s <= t1 and s.late_s >= STALL_THRESHOLD_S for s in probe.stalls
    ), [s for s in probe.stalls if not (t0 <= s.at_s <= t1 and s.late_s >= STALL_THRESHOLD_S)]
    summary = probe.summary()
    assert summary["cpus"] == cpus and summary["stalls"] == len(probe.stalls)
