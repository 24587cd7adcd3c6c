"""Machine stalls: how late the machine itself wakes a thread that nothing else can delay.

A control cycle can be late for two reasons: the host stack (its threads, the interpreter
lock, a kernel thread at the same priority) or the machine (a virtual machine's vCPUs
descheduled by the hypervisor, an SMI, a frequency change).  Only the first is ours to fix.
A :class:`StallProbe` tells them apart: one small process per CPU, pinned to it, under
``SCHED_FIFO`` at :data:`PROBE_PRIORITY` (above every priority a drive session may take,
``realtime_priority`` 0..49), sleeps to a grid of its period (:data:`PROBE_PERIOD_S`, or a
coarser one where waking every millisecond costs too much: the vcan guest's one CPU) and
records every wake-up more than :data:`STALL_THRESHOLD_S` late (:func:`next_wakeup`).  Only
interrupts and the kernel's own higher-priority threads preempt it in the guest, so what
it records is the machine's.  After a late wake-up it looks again :data:`FOLLOW_UP_S`
later whatever its period, so a pause the machine breaks into pieces reads as one
(:func:`merged`); a pause of ``D`` is recorded at least ``D - period`` long (it may begin
just after a wake-up), never longer than it was.
:func:`explained` then says which of a stream's late or missing-feedback cycles overlap a
machine stall.

Seen on the 2-core VM of ``BENCHMARKS.md``: a bare loop at normal priority was more than
2 ms late 16 times in 10 minutes (up to 15 ms); the probes see stalls of one vCPU at a time
in calm phases and of both, every millisecond or so, in noisy ones.

The probe needs ``CAP_SYS_NICE`` for ``SCHED_FIFO``; without it :class:`StallProbe` reports
itself unavailable (``available`` False, the reason in ``refusal``) rather than measure
something a normal thread's scheduling would blur.

>>> stalls = [Stall(cpu=0, at_s=10.000, late_s=0.006)]
>>> events = [(9.998, 0.0075, 0), (20.0, 0.003, 0), (30.0, 0.0, 18)]
>>> [e[0] for e in explained(events, stalls, period_s=0.01)]
[9.998]
"""

from __future__ import annotations

import bisect
import json
import os
import select
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

#: the default period (the host's).  A stall of a period + STALL_THRESHOLD_S (here 1.5 ms)
#: or more always covers a due
#: wake-up by more than the threshold: caught, wherever it falls on the probe's grid (with
#: 2 ms and 1 ms, stalls up to 3 ms could pass unseen between two wake-ups, and a cycle
#: they made 2 ms late was blamed on the stack)
PROBE_PERIOD_S = 0.001
STALL_THRESHOLD_S = 0.0005  # a wake-up later than this is a stall
#: after a late wake-up the probe looks again this soon, whatever its period: the next
#: piece of a pause the machine broke up is seen within JOIN_GAP_S and joined to it
FOLLOW_UP_S = 0.001
#: the coarsest period a probe takes: a probe sleeping longer sees too little
MAX_PERIOD_S = 1.0
PROBE_PRIORITY = 60  # above a session's realtime_priority (0..49)
MAX_STALLS = 100_000  # per probe: a 3-hour run stalling every 0.1 s
MAX_PROBE_S = 3 * 3600.0  # a probe whose parent never says stop ends by itself
STOP_TIMEOUT_S = 5.0
MARGIN_S = 0.001  # a stall this close before a late interval still explains it


E = TypeVar("E", bound=Sequence[float])  # a cycle event: (deadline_s, lateness_s, missing, ...)


@dataclass(frozen=True)
class Stall:
    """One late wake-up of a probe: due at ``at_s`` (``time.monotonic``), ``late_s`` late."""

    cpu: int
    at_s: float
    late_s: float


def explained(
    events: Iterable[E], stalls: Sequence[Stall], period_s: float, sync_delay_s: float = 0.0
) -> list[E]:
    """The cycle events (``(deadline_s, lateness_s, missing_nodes, ...)``, as
    :attr:`drivers.cycle.CycleStats.notable` keeps them) that a machine stall explains.

    A late cycle covers ``[deadline, deadline + lateness]``; a cycle that found TPDOs
    missing covers the whole period before it (the feedback of the previous SYNC was due
    in it).  A stall covers ``[at, at + late]``; overlap within :data:`MARGIN_S` counts.

    A stall also explains the cycle after a late cycle it explains, when that one is no
    later than the previous cycle's wait makes it: a SYNC goes out at least
    ``sync_delay_s`` (the supervisor's :attr:`~drivers.safety.supervisor.Supervisor.sync_delay_s`)
    after the RPDOs before it, so a cycle whose SYNC and RPDOs went out ``lateness`` late
    holds the next SYNC until ``lateness + sync_delay_s - period_s`` (+ :data:`MARGIN_S`
    for the RPDOs' own build) after its deadline, however early that one woke.  With
    ``sync_delay_s`` 0 (the default) no cycle is explained that way.

    >>> stalls = [Stall(cpu=0, at_s=10.000, late_s=0.009)]
    >>> events = [(10.0, 0.0087, 0), (10.01, 0.0036, 0), (10.02, 0.0036, 0)]
    >>> [e[0] for e in explained(events, stalls, period_s=0.01, sync_delay_s=0.0047)]
    [10.0, 10.01]
    """
    events = list(events)
    spans = sorted((s.at_s - MARGIN_S, s.at_s + s.late_s) for s in stalls)
    starts = [a for a, _ in spans]
    reach = []  # the latest end among the spans up to each one
    for _, end in spans:
        reach.append(max(end, reach[-1]) if reach else end)
    on_stall = []
    for ev in events:
        deadline, late, missing = ev[0], ev[1], ev[2]
        lo = deadline - period_s if missing else deadline
        hi = deadline + max(late, 0.0)
        # spans starting before hi; any of them ending after lo overlaps
        k = bisect.bisect_right(starts, hi)
        on_stall.append(bool(k and reach[k - 1] >= lo))
    if sync_delay_s > 0.0:  # the chain of held SYNCs, in deadline order
        prev: int | None = None
        for i in sorted(range(len(events)), key=lambda j: events[j][0]):
            if not on_stall[i] and prev is not None:
                deadline, late = events[i][0], events[i][1]
                p_deadline, p_late = events[prev][0], events[prev][1]
                on_stall[i] = (
                    on_stall[prev]
                    and abs(deadline - p_deadline - period_s) < period_s / 2
                    and late <= p_late + sync_delay_s - period_s + MARGIN_S
                )
            prev = i
    return [ev for ev, yes in zip(events, on_stall, strict=True) if yes]


def overlapping(stalls: Sequence[Stall], lo_s: float, hi_s: float) -> list[Stall]:
    """The stalls that overlap ``[lo_s, hi_s]`` (within :data:`MARGIN_S`), e.g. the cycles
    a watchdog counted before it stopped a stream.

    >>> s = [Stall(0, 1.0, 0.003), Stall(1, 2.0, 0.02), Stall(1, 5.0, 0.002)]
    >>> [x.at_s for x in overlapping(s, 2.015, 2.04)]
    [2.0]
    """
    return [s for s in stalls if s.at_s - MARGIN_S <= hi_s and s.at_s + s.late_s >= lo_s]


def shared(stalls: Sequence[Stall], over_s: float = 0.002) -> list[Stall]:
    """The stalls longer than ``over_s`` that a stall of another CPU overlaps for more than
    half their length: the machine paused those CPUs together (the whole VM descheduled),
    so a thread standing by on another CPU would have been held too.

    >>> s = [Stall(0, 1.000, 0.006), Stall(1, 1.001, 0.005), Stall(0, 2.0, 0.004)]
    >>> [(x.cpu, x.at_s) for x in shared(s)]
    [(0, 1.0), (1, 1.001)]
    """
    ordered = sorted(stalls, key=lambda s: s.at_s)
    starts = [s.at_s for s in ordered]
    longest = max((s.late_s for s in ordered), default=0.0)
    out = []
    for a in stalls:
        if a.late_s <= over_s:
            continue
        end = a.at_s + a.late_s
        # the stalls that may overlap a: starting before its end, not ending before it
        lo = bisect.bisect_left(starts, a.at_s - longest)
        hi = bisect.bisect_left(starts, end)
        cover = max(
            (
                min(end, b.at_s + b.late_s) - max(a.at_s, b.at_s)
                for b in ordered[lo:hi]
                if b.cpu != a.cpu
            ),
            default=0.0,
        )
        if cover > a.late_s / 2:
            out.append(a)
    return out


#: two stalls of one CPU this close are one: the probe cannot see a gap shorter than the
#: time it sleeps after a late wake-up (:data:`FOLLOW_UP_S`, whatever its period)
JOIN_GAP_S = FOLLOW_UP_S + STALL_THRESHOLD_S


def merged(stalls: Sequence[Stall]) -> list[Stall]:
    """Each CPU's stalls joined where the gap between two is shorter than the probe can see
    (:data:`JOIN_GAP_S`): the spans in which that CPU ran nothing of ours, by start time.

    >>> s = [Stall(0, 1.0, 0.010), Stall(0, 1.011, 0.010), Stall(1, 1.0, 0.003),
    ...      Stall(0, 1.1, 0.002)]
    >>> [(x.cpu, x.at_s, round(x.late_s, 4)) for x in merged(s)]
    [(0, 1.0, 0.021), (1, 1.0, 0.003), (0, 1.1, 0.002)]
    """
    out: list[Stall] = []
    for cpu in sorted({s.cpu for s in stalls}):
        run: Stall | None = None
        for s in sorted((s for s in stalls if s.cpu == cpu), key=lambda s: s.at_s):
            if run is not None and s.at_s - (run.at_s + run.late_s) <= JOIN_GAP_S:
                end = max(run.at_s + run.late_s, s.at_s + s.late_s)
                run = Stall(cpu, run.at_s, end - run.at_s)
                continue
            if run is not None:
                out.append(run)
            run = s
        if run is not None:
            out.append(run)
    return sorted(out, key=lambda s: (s.at_s, s.cpu))


def covering(stalls: Sequence[Stall], window_s: float, lo_s: float, hi_s: float) -> list[Stall]:
    """The stalls (:func:`merged` per CPU) at least ``window_s`` long that overlap
    ``[lo_s, hi_s]``: each held a CPU through a whole watchdog window of ``window_s``
    within that span, long enough to trip that watchdog with nothing else wrong.

    >>> s = [Stall(0, 5.0, 0.020), Stall(0, 5.021, 0.015), Stall(1, 6.0, 0.025)]
    >>> [(x.cpu, x.at_s, round(x.late_s, 4)) for x in covering(s, 0.030, 0.0, 10.0)]
    [(0, 5.0, 0.036)]
    >>> covering(s, 0.030, 5.5, 10.0)
    []
    """
    return [s for s in merged(stalls) if s.late_s >= window_s and s in overlapping([s], lo_s, hi_s)]


def next_wakeup(due_s: float, now_s: float, period_s: float) -> tuple[Stall | None, float]:
    """One wake-up of a probe due at ``due_s`` that woke at ``now_s``: the stall it records
    (CPU 0; None when it was no more than :data:`STALL_THRESHOLD_S` late) and when it is
    due next: a period on along its grid, or :data:`FOLLOW_UP_S` (at most a period) after a
    late wake-up.

    >>> next_wakeup(1.0, 1.0002, 0.02)
    (None, 1.02)
    >>> next_wakeup(1.0, 1.5, 0.02)
    (Stall(cpu=0, at_s=1.0, late_s=0.5), 1.501)
    """
    late_s = now_s - due_s
    if late_s > STALL_THRESHOLD_S:
        return Stall(0, due_s, late_s), now_s + min(FOLLOW_UP_S, period_s)
    due_s += period_s
    return None, (due_s if due_s >= now_s else now_s + period_s)


def probe_period_s(text: str, where: str) -> float:
    """A probe period read from ``text`` (seconds), or :class:`ValueError` naming ``where``.

    >>> probe_period_s("0.02", "--stall-probe-period")
    0.02
    >>> probe_period_s("0", "--stall-probe-period")
    Traceback (most recent call last):
    ...
    ValueError: --stall-probe-period='0': expected seconds in (0, 1]
    """
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 < value <= MAX_PERIOD_S:  # NaN fails too
        raise ValueError(f"{where}={text!r}: expected seconds in (0, {MAX_PERIOD_S:g}]")
    return value


class StallProbe:
    """One probe process per CPU in ``cpus``, waking every ``period_s``, while the context
    lasts; :attr:`stalls` after.

    >>> with StallProbe([0]) as probe:   # doctest: +SKIP
    ...     run_the_stream()
    >>> probe.stalls[:1]                 # doctest: +SKIP
    [Stall(cpu=0, at_s=13485.5983, late_s=0.02066)]
    """

    def __init__(self, cpus: Iterable[int], period_s: float = PROBE_PERIOD_S) -> None:
        if not 0.0 < period_s <= MAX_PERIOD_S:
            raise ValueError(f"stall probe period {period_s!r} s: expected (0, {MAX_PERIOD_S:g}]")
        self.cpus = sorted(set(cpus))
        self.period_s = period_s
        self.stalls: list[Stall] = []
        self.available = False
        self.refusal: str | None = None
        self.duration_s = 0.0
        self._procs: list[subprocess.Popen[str]] = []
        self._t0 = 0.0

    @property
    def pids(self) -> list[int]:
        """The probe processes' ids, one per CPU (e.g. to pause one in a test)."""
        return [proc.pid for proc in self._procs]

    def __enter__(self) -> StallProbe:
        for cpu in self.cpus:
            proc = subprocess.Popen(
                [sys.executable, "-m", "hrm_ctrl.hil.stalls", str(cpu), repr(self.period_s)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            self._procs.append(proc)
        for proc in self._procs:  # each says "ready" or why not
            if proc.stdout is None:
                continue
            ready, _, _ = select.select([proc.stdout], [], [], STOP_TIMEOUT_S)
            line = proc.stdout.readline().strip() if ready else "no answer"
            if line != "ready":
                self.refusal = self.refusal or line or "probe exited"
        self.available = self.refusal is None and bool(self._procs)
        self._t0 = time.monotonic()
        return self

    def __exit__(self, *exc: object) -> None:
        self.duration_s = time.monotonic() - self._t0
        for proc in self._procs:
            try:
                out, _ = proc.communicate("stop\n", timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
                self.available = False
                self.refusal = self.refusal or "a probe did not stop"
                continue
            if not self.available:
                continue
            try:
                rows = json.loads(out)
            except ValueError:
                self.available = False
                self.refusal = "a probe's output was not JSON"
                continue
            self.stalls.extend(Stall(int(c), float(a), float(s)) for c, a, s in rows)
        self.stalls.sort(key=lambda s: s.at_s)

    def summary(self, over_s: float = 0.002) -> dict[str, object]:
        """Counts for a report: stalls in all, those longer than ``over_s``, the longest,
        and those of them another CPU stalled through too (:func:`shared`)."""
        both = shared(self.stalls, over_s)
        return {
            "available": self.available,
            "refusal": self.refusal,
            "cpus": self.cpus,
            "duration_s": round(self.duration_s, 1),
            "period_ms": self.period_s * 1000,
            "threshold_ms": STALL_THRESHOLD_S * 1000,
            "stalls": len(self.stalls),
            f"stalls_over_{over_s * 1000:g}ms": sum(1 for s in self.stalls if s.late_s > over_s),
            "max_ms": round(max((s.late_s for s in self.stalls), default=0.0) * 1000, 2),
            f"over_{over_s * 1000:g}ms_by_cpu": {
                str(c): sum(1 for s in self.stalls if s.cpu == c and s.late_s > over_s)
                for c in self.cpus
            },
            # of those, the ones another CPU stalled through too (shared)
            f"over_{over_s * 1000:g}ms_shared_by_cpu": {
                str(c): sum(1 for s in both if s.cpu == c) for c in self.cpus
            },
        }


def _probe(cpu: int, period_s: float) -> int:
    """The probe process: pinned, SCHED_FIFO, until "stop" (or EOF) on stdin."""
    try:
        os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PROBE_PRIORITY))
    except OSError as exc:
        print(f"stall probe on CPU {cpu}: {exc.strerror or exc}", flush=True)
        return 2
    print("ready", flush=True)
    stdin = sys.stdin.fileno()
    rows: list[tuple[int, float, float]] = []
    t_end = time.monotonic() + MAX_PROBE_S
    due = time.monotonic() + period_s
    while due < t_end:
        wait = due - time.monotonic()
        ready, _, _ = select.select([stdin], [], [], max(0.0, wait))
        if ready:  # "stop" or EOF
            break
        stall, due = next_wakeup(due, time.monotonic(), period_s)
        if stall is not None and len(rows) < MAX_STALLS:
            rows.append((cpu, round(stall.at_s, 6), round(stall.late_s, 6)))
    print(json.dumps(rows), flush=True)
    return 0


def _main(argv: list[str]) -> int:
    usage = "usage: python -m hrm_ctrl.hil.stalls CPU [PERIOD_S]"
    if not 1 <= len(argv) <= 2 or not argv[0].isdigit():
        print(usage, file=sys.stderr)
        return 2
    try:
        period_s = probe_period_s(argv[1], "PERIOD_S") if len(argv) == 2 else PROBE_PERIOD_S
    except ValueError as exc:
        print(f"{usage}: {exc}", file=sys.stderr)
        return 2
    return _probe(int(argv[0]), period_s)


if __name__ == "__main__":
    raise SystemExit(_main(sys.argv[1:]))
