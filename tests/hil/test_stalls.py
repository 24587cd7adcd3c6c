"""The machine-stall probe (``hrm_ctrl.hil.stalls``): which late cycles fall on a stall of
the machine, the probe processes and their refusals."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import time

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hrm_ctrl.hil.stalls import (
    JOIN_GAP_S,
    MARGIN_S,
    STALL_THRESHOLD_S,
    Stall,
    StallProbe,
    covering,
    explained,
    merged,
    shared,
)

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


def shared_by_definition(stalls: list[Stall], over_s: float) -> list[Stall]:
    """``shared``'s definition, every pair compared."""
    return [
        a
        for a in stalls
        if a.late_s > over_s
        and any(
            min(a.at_s + a.late_s, b.at_s + b.late_s) - max(a.at_s, b.at_s) > a.late_s / 2
            for b in stalls
            if b.cpu != a.cpu
        )
    ]


cpu_stall = st.builds(Stall, st.integers(0, 2), times, st.floats(0.0005, 0.05, allow_nan=False))


@given(st.lists(cpu_stall, max_size=40))
@example([Stall(0, 1.0, 0.006), Stall(1, 0.99, 0.0131)])  # the other began long before
@example([Stall(0, 1.0, 0.006), Stall(0, 1.001, 0.006)])  # the same CPU: not shared
@example([Stall(0, 1.0, 0.006), Stall(1, 1.003, 0.01)])  # exactly half: not shared
def test_shared_stalls_are_those_another_cpu_stalled_through_for_over_half(
    stalls: list[Stall],
) -> None:
    assert shared(stalls) == shared_by_definition(stalls, 0.002)


@given(st.lists(cpu_stall, max_size=40))
@example([Stall(0, 1.0, 0.010), Stall(0, 1.011, 0.010), Stall(1, 1.005, 0.002)])  # joined
def test_merged_stalls_cover_each_cpus_stalls_and_are_further_apart_than_the_probe_sees(
    stalls: list[Stall],
) -> None:
    out = merged(stalls)
    assert out == sorted(out, key=lambda s: (s.at_s, s.cpu))
    for cpu in {s.cpu for s in stalls}:
        runs = [r for r in out if r.cpu == cpu]
        assert all(b.at_s - (a.at_s + a.late_s) > JOIN_GAP_S for a, b in itertools.pairwise(runs))
        for s in (s for s in stalls if s.cpu == cpu):  # each inside exactly one run
            inside = [
                r
                for r in runs
                if r.at_s <= s.at_s and s.at_s + s.late_s <= r.at_s + r.late_s + 1e-9
            ]
            assert len(inside) == 1, (s, runs)
    # a run is made of stalls: it starts at one, and no longer than they reach
    assert all(any(s.cpu == r.cpu and s.at_s == r.at_s for s in stalls) for r in out)


def test_only_a_stall_as_long_as_the_window_within_the_span_covers_it() -> None:
    s = [Stall(0, 5.0, 0.020), Stall(0, 5.021, 0.015), Stall(1, 6.0, 0.025), Stall(1, 7.0, 0.05)]
    assert [(x.cpu, x.at_s) for x in covering(s, 0.030, 0.0, 10.0)] == [(0, 5.0), (1, 7.0)]
    assert [x.at_s for x in covering(s, 0.030, 6.9, 10.0)] == [7.0]
    assert covering(s, 0.030, 7.06, 10.0) == []  # ended before the span
    assert covering(s, 0.060, 0.0, 10.0) == []  # none as long as the window


def test_the_cycle_a_stall_late_cycle_held_back_is_the_stalls_too() -> None:
    """Seen in a soak's kernel trace (clock mono): CPU 0 ran nothing for 9.1 ms,
    its probe woke 8.1 ms late; the cycle due in it sent SYNC and RPDOs 8.7 ms late, and the
    next one, awake in time, held its SYNC for the supervisor's sync_delay_s (4.7 ms) after
    those RPDOs: 3.7 ms late.  The one after that was on time."""
    stalls = [Stall(0, 31620.8875, 0.0081)]
    events = [(31620.887234, 0.0087, 0), (31620.897234, 0.00367, 0)]
    assert explained(events, stalls, T) == events[:1]  # no sync_delay_s: no chain
    assert explained(events, stalls, T, sync_delay_s=0.0047) == events
    # later than the held SYNC accounts for: the stack's own
    later = [events[0], (31620.897234, 0.0047, 0)]
    assert explained(later, stalls, T, sync_delay_s=0.0047) == later[:1]
    # the chain needs the previous period's cycle: one two periods on is not held by it
    gap = [events[0], (31620.907234, 0.00367, 0)]
    assert explained(gap, stalls, T, sync_delay_s=0.0047) == gap[:1]


@given(
    st.lists(event, max_size=30, unique_by=lambda e: e[0]),  # a stream's deadlines differ
    st.lists(stall, max_size=30),
    st.floats(0.0, 0.02),
)
@example([(1.0, 0.0087, 0), (1.01, 0.0036, 0)], [Stall(0, 1.0, 0.009)], 0.0047)  # a chain
def test_a_held_cycle_is_explained_only_through_the_cycle_before_it(
    events: list[tuple[float, float, int]], stalls: list[Stall], sync_delay_s: float
) -> None:
    direct = explained(events, stalls, T)
    chained = explained(events, stalls, T, sync_delay_s)
    assert set(direct) <= set(chained)
    assert [e for e in events if e in set(chained)] == chained  # the input's order
    by_deadline = sorted(range(len(events)), key=lambda j: events[j][0])
    for pos, i in enumerate(by_deadline):
        ev = events[i]
        if ev in set(chained) and ev not in set(direct):
            prev = events[by_deadline[pos - 1]]
            assert pos > 0 and prev in set(chained)
            assert abs(ev[0] - prev[0] - T) < T / 2
            assert ev[1] <= prev[1] + sync_delay_s - T + MARGIN_S


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
    by_cpu, shared_by_cpu = summary["over_2ms_by_cpu"], summary["over_2ms_shared_by_cpu"]
    assert all(0 <= shared_by_cpu[str(c)] <= by_cpu[str(c)] for c in cpus), summary
