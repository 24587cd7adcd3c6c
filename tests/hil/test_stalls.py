"""The machine-stall probe (``hrm_ctrl.hil.stalls``): which late cycles fall on a stall of
the machine, the probe processes and their refusals."""

from __future__ import annotations

import itertools
import os
import signal
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
    next_wakeup,
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


def probed(period_s: float, pauses: list[tuple[float, float]], end_s: float) -> list[Stall]:
    """What a probe of ``period_s`` records over ``[0, end_s]`` on a machine that runs it
    the moment it is due, except through ``pauses`` (``[start, end)``: it wakes at the end)."""
    stalls, due = [], period_s
    while due < end_s:
        now = due
        for a, b in sorted(pauses):  # in order: a pause may end where the next begins
            if a <= now < b:
                now = b
        stall, due = next_wakeup(due, now, period_s)
        if stall is not None:
            stalls.append(stall)
    return stalls


periods = st.sampled_from([0.0005, 0.001, 0.005, 0.02, 0.05])


@st.composite
def pause_lists(draw: st.DrawFn) -> list[tuple[float, float]]:
    """Pauses of 0.1-800 ms in [0.1, 10] s, at least 0.1 s apart."""
    out, t = [], 0.1
    for _ in range(draw(st.integers(0, 6))):
        t += draw(st.floats(0.1, 1.0))
        length = draw(st.floats(0.0001, 0.8))
        out.append((t, t + length))
        t += length
    return out


@given(periods, pause_lists())
@example(0.02, [(1.0, 1.5)])  # the guest's half-second pause, the guest's period
@example(0.02, [(1.0, 1.14)])  # 120 ms window + 20 ms period: still evidence
@example(0.001, [(1.0, 1.0015)])  # one period and the threshold: caught at 1 ms too
def test_the_probe_records_every_pause_a_period_longer_than_the_window_and_nothing_else(
    period_s: float, pauses: list[tuple[float, float]]
) -> None:
    """A pause of ``D`` is recorded at least ``D - period`` long (one stall, or pieces that
    :func:`merged` joins) and never longer than it was, nor outside it: a pause of a watchdog
    window + the period is evidence for that window (:func:`covering`), a pause shorter than
    the window never is."""
    stalls = probed(period_s, pauses, 12.0)
    # nothing recorded outside a pause, nothing longer than its pause
    assert all(
        any(a <= s.at_s and s.at_s + s.late_s <= b + 1e-9 for a, b in pauses) for s in stalls
    )
    for a, b in pauses:
        inside = [s for s in merged(stalls) if a <= s.at_s < b]
        if b - a > period_s + STALL_THRESHOLD_S:
            assert len(inside) == 1 and inside[0].late_s >= b - a - period_s - 1e-9, inside
        for window_s in (0.03, 0.12):
            found = covering(stalls, window_s, a, b)
            if b - a >= window_s + period_s:
                assert found, (a, b, window_s)
            if b - a < window_s:
                assert not found, (a, b, window_s, found)


def fifo_allowed() -> bool:
    return subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not fifo_allowed(), reason="SCHED_FIFO refused to this user (chrt -f 1)")
@pytest.mark.parametrize("period_s", [0.001, 0.02])
def test_a_probe_process_held_off_its_cpu_records_the_pause(period_s: float) -> None:
    """The probe process stopped (SIGSTOP) for 300 ms, as the vcan guest's UML process is
    when the host does not schedule it: one stall of it, at least 300 ms less a period."""
    cpu = min(os.sched_getaffinity(0))
    with StallProbe([cpu], period_s) as probe:
        assert probe.available, probe.refusal
        time.sleep(0.1)
        t0 = time.monotonic()
        os.kill(probe.pids[0], signal.SIGSTOP)
        t_stopped = time.monotonic()
        time.sleep(0.3)
        os.kill(probe.pids[0], signal.SIGCONT)
        t1 = time.monotonic()
        time.sleep(0.1)
    assert probe.summary()["period_ms"] == period_s * 1000
    found = covering(probe.stalls, 0.3 - period_s - 0.01, t0, t1)
    assert len(found) == 1, probe.stalls
    # it began at the stop, a period at most after it (or earlier, the machine busy)
    assert found[0].at_s <= t_stopped + period_s + MARGIN_S, (t0, t_stopped, found)


def test_a_bad_probe_period_is_refused() -> None:
    with pytest.raises(ValueError, match="expected"):
        StallProbe([0], 0.0)
    res = subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.hil.stalls", "0", "soon"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "PERIOD_S='soon': expected seconds in (0, 1]" in res.stderr


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
