"""How a drive session's threads run, and what the session holds of the process while it
is open: one object per session, so the session asks the kernel once and logs once.

* Every thread the session starts (the buses' readers and log writers, the supervisor)
  inherits the scheduling of the thread that starts it: they start inside
  :meth:`SessionScheduling.starting_threads`, under ``SCHED_FIFO`` at the configured
  priority when granted, and the caller's thread gets its own policy back.  The threads
  share one GIL: one of them at normal priority holding it while the machine's other work
  preempts it keeps the FIFO ones waiting (measured: the supervisor alone under FIFO, 1430
  node-cycles without feedback in 30 s; the whole host process, 54; BENCHMARKS.md).  A
  thread started later for the session (a feedback watch) gets the same
  (:meth:`~SessionScheduling.thread_scheduling`); refused once, never asked again.
* The CPUs' wake-up latency (PM QoS, :class:`~drivers.realtime.CpuLatencyRequest`), held
  while the session is open when the configuration asks for it.
* The heap out of the cyclic collector from the configuration to the end of the finish
  (:class:`~drivers.realtime.GcHold`: a full collection of a large heap pauses every
  thread, a heartbeat timeout).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from drivers.cycle import EventLog
from drivers.realtime import (
    NORMAL_PRIORITY,
    AppliedSettings,
    CpuLatencyRequest,
    GcHold,
    process_settings,
)


class SessionScheduling:
    """The scheduling of one session's threads (see the module docstring); events go to
    the session's ``events``."""

    def __init__(self, realtime_priority: int, cpu_wakeup_latency_us: int, events: EventLog):
        self.realtime_priority = int(realtime_priority)
        self.cpu_wakeup_latency_us = int(cpu_wakeup_latency_us)
        self.events = events
        self.realtime_granted = False
        self.gc_hold = GcHold()
        self.cpu_latency: CpuLatencyRequest | None = None

    @contextlib.contextmanager
    def starting_threads(self) -> Iterator[None]:
        """The context the session starts its threads in (once); logs what was granted."""
        with process_settings(
            switch_interval_s=None, realtime_priority=self.realtime_priority
        ) as applied:
            self.realtime_granted = applied.realtime_granted
            yield
        if applied.realtime_priority:
            self.events.add(
                "realtime",
                f"session threads under SCHED_FIFO {applied.realtime_priority}"
                if applied.realtime_granted
                else f"{applied.realtime_refusal}; normal scheduling",
            )

    @property
    def granted_priority(self) -> int:
        """The priority the session's threads run at (refused: normal scheduling)."""
        return self.realtime_priority if self.realtime_granted else NORMAL_PRIORITY

    def thread_scheduling(self) -> contextlib.AbstractContextManager[AppliedSettings]:
        """A context in which the caller starts a thread that works for the session: it
        gets the session's threads' scheduling, the caller's thread its own back."""
        return process_settings(switch_interval_s=None, realtime_priority=self.granted_priority)

    def hold_cpu_latency(self) -> CpuLatencyRequest:
        """Hold the CPUs' wake-up latency the configuration asks for (until :meth:`close`)."""
        if self.cpu_latency is None:
            lat = self.cpu_latency = CpuLatencyRequest(self.cpu_wakeup_latency_us)
            if lat.held or lat.refusal:
                self.events.add(
                    "cpu-latency",
                    f"CPU wake-up latency at most {lat.max_us} us held"
                    if lat.held
                    else f"{lat.refusal}; CPUs may sleep",
                )
        return self.cpu_latency

    def close(self) -> None:
        """Release the CPU latency request and the heap hold (idempotent)."""
        if self.cpu_latency is not None:
            self.cpu_latency.close()
        self.gc_hold.release()
