"""Feedback watches: threads beside the supervisor that watch the arm's own state while
the drives are enabled, and report a stop cause through :meth:`NodeMonitor.report`.

A report queues the cause and wakes the supervisor, which quick-stops every axis within
one control period (``drivers.safety.supervisor``); a watch never runs on the
supervisor's thread, so its work does not cost the control cycle its deadline beyond
the interpreter lock (held at most one switch interval, 0.2 ms, at a time).

* **Tension** (:class:`drivers.tension_sensor.TensionWatch`, every 10 ms): a rope below
  its slack threshold or above its limit, a stale sensor, or bad data past a rate
  (``[tension]`` in the bus configuration) -> :attr:`StopKind.TENSION`, naming the rope
  or the port.
* **Rope consistency** (:class:`RopeWatch`, every ``every`` control periods): the
  feedback of one SYNC (every node's TPDO of the same SYNC) and the targets that SYNC
  applied, as the receive path recorded them at the last clean cycle
  (:meth:`NodeMonitor.feedback_snapshot`, :func:`take_snapshot`), go to a
  :class:`RopeCheck` (the rope layer's estimator, injected by the console: the drivers
  know no rope geometry) -> :attr:`StopKind.ROPE`, naming the joint and its ropes.

Each watch reports once and ends; :class:`FeedbackWatches` starts and stops a set of
them and summarises them for the run record.

>>> import numpy as np
>>> from drivers.safety.monitor import NodeMonitor
>>> mon = NodeMonitor(["m0", "m1"], 3, 0.3)
>>> take_snapshot(mon) is None          # no feedback yet
True
>>> mon.sync_sent(3, np.array([1000, 1000]))
>>> for i in range(2):          # every node answers SYNC 3 once: a clean cycle
...     mon.on_tpdo(i, bytes.fromhex("3702e8030000"))
>>> mon.sync_sent(4, np.array([1000, 1001]))
>>> for i in range(2):          # ... and SYNC 4: its feedback is recorded
...     mon.on_tpdo(i, bytes.fromhex("3702e8030000"))
>>> snap = take_snapshot(mon)
>>> snap.seq, snap.counts.tolist(), snap.reference.tolist()
(4, [1000, 1000], [1000, 1001])
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Any, Protocol

import numpy as np

from drivers.interrupts import deferred_interrupts
from drivers.safety.causes import StopKind
from drivers.safety.monitor import FeedbackSnapshot, NodeMonitor
from hrm_ctrl.errors import DriverError

ROPE_EVERY_CYCLES = 5  # rope-consistency evaluations: every 5th control period (20 Hz)
JOIN_TIMEOUT_S = 2.0


class RopeCheck(Protocol):
    """The rope layer's consistency check, as the drivers see it (injected).

    Called with the actual counts of one SYNC (n,) and the counts the drives were
    commanded to hold at it (n,) or None; returns a one-line fault naming the joint and
    rope(s), or None.  Its summary goes into the rope watch's (the run record).
    ``hrm_ctrl.ropes.estimator.RopeConsistencyCheck`` is one.
    """

    def __call__(self, counts: np.ndarray, reference: np.ndarray | None) -> str | None: ...

    def summary(self) -> dict[str, Any]: ...


class Watch(Protocol):
    """A watch thread: started once the drives are enabled, stopped before they are
    disabled; its summary goes into the run record."""

    fault: str | None

    def start(self) -> Any: ...

    def stop(self) -> None: ...

    def summary(self) -> dict[str, Any]: ...


def take_snapshot(monitor: NodeMonitor, max_age: int | None = None) -> FeedbackSnapshot | None:
    """The feedback of one SYNC: the last clean cycle's, as the receive path recorded it
    at its last TPDO (:meth:`NodeMonitor.feedback_snapshot`), or None when there was
    none (or it is more than ``max_age`` SYNCs older than the last one sent).  A
    snapshot mixing two SYNCs would show a moving arm's ropes one period apart (up to
    0.05 mm at the demo's speed: five sigma of the check).

    A TPDO is labelled with the SYNC last sent when it arrives, so a late answer to the
    SYNC before carries this one's label: the feedback counts as this SYNC's only when
    every node answered the one before exactly once before it went out, and every node
    has answered exactly once since (:meth:`NodeMonitor.sync_sent`).  (A node that
    answers every SYNC exactly one period late, for good, is not told apart.)  Seen
    without it: a loaded in-process box answered a SYNC late, then began the next burst
    and stalled in it, and a snapshot of half the one and half the other stopped a run
    on a rope consistency figure of 7.6.  Recorded by the receive path itself, a
    snapshot is there whenever a clean cycle was: taken by a watch thread that raced
    the receive thread for it, half its wakes under load had found none."""
    snap = monitor.feedback_snapshot()
    if snap is None or (max_age is not None and snap.seq < monitor.seq - max_age):
        return None
    return snap


class RopeWatch:
    """Rope-consistency watch thread (see the module docstring): every ``period_s`` the
    feedback of the last clean cycle and the targets it applied go to ``check``; a
    fault (or a check that raises) is reported once as :attr:`StopKind.ROPE` and the
    watch ends.  A SYNC already checked is not checked again: a wake with no SYNC sent
    since the one before (drives holding, no stream) counts in ``repeated``, one with
    SYNCs sent but none of them a clean cycle (the box behind) in ``missed``."""

    def __init__(self, monitor: NodeMonitor, check: RopeCheck, period_s: float) -> None:
        if not period_s > 0:
            raise DriverError(f"rope watch period must be > 0 s, got {period_s!r}")
        self.monitor = monitor
        self.check = check
        self.period_s = float(period_s)
        self.fault: str | None = None
        self.evaluations = 0
        self.missed = 0  # SYNCs sent since the last wake, no new clean cycle among them
        self.repeated = 0  # no new SYNC since the last wake
        self.cpu_s: list[float] = []  # thread CPU time of each evaluation
        self._clean0 = monitor.clean_cycles
        self._last_seq = -1  # the SYNC last checked
        self._seen_seq = monitor.seq  # the SYNC last sent at the last wake (or when made)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> RopeWatch:
        self._thread = threading.Thread(target=self._run, name="rope-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread.ident is not None:  # it did start
            self._thread.join(timeout=JOIN_TIMEOUT_S)

    def step(self) -> str | None:
        """One evaluation (the thread's work): a one-line fault, or None."""
        sent = self.monitor.seq
        snap = take_snapshot(self.monitor)
        if snap is None or snap.seq <= self._last_seq:
            if sent == self._seen_seq:
                self.repeated += 1
            else:
                self.missed += 1
            self._seen_seq = sent
            return None
        self._seen_seq = sent
        self._last_seq = snap.seq
        t0 = time.thread_time()
        try:
            text = self.check(snap.counts, snap.reference)
        except Exception as exc:  # a check that fails is a stop, never a silent watch
            text = f"rope consistency check failed at SYNC {snap.seq}: {exc!r}"
        self.cpu_s.append(time.thread_time() - t0)
        self.evaluations += 1
        return text

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                text = self.step()
            except Exception as exc:  # a watch that cannot look any more stops every axis
                text = f"rope watch failed: {exc!r}"
            if text is not None:
                self.fault = text
                self.monitor.report(StopKind.ROPE, text)
                return

    def summary(self) -> dict[str, Any]:
        cpu = np.asarray(self.cpu_s) * 1000.0
        out: dict[str, Any] = {
            "period_s": self.period_s,
            "evaluations": self.evaluations,
            "missed_snapshots": self.missed,
            "repeated_syncs": self.repeated,
            # the cycles the receive path recorded as clean meanwhile (all it could check)
            "clean_cycles": self.monitor.clean_cycles - self._clean0,
            "cpu_per_evaluation_ms": None
            if cpu.size == 0
            else {
                "mean": round(float(cpu.mean()), 3),
                "p99": round(float(np.percentile(cpu, 99)), 3),
                "max": round(float(cpu.max()), 3),
            },
            "fault": self.fault,
            "check": self.check.summary(),
        }
        return out


class FeedbackWatches:
    """A set of named watches started and stopped together; a context manager."""

    def __init__(
        self, scheduling: Callable[[], AbstractContextManager[object]] = nullcontext
    ) -> None:
        """``scheduling``: the context the watches' threads start in (a session's
        :meth:`~drivers.session.DriveSession.thread_scheduling`: its SCHED_FIFO)."""
        self.watches: dict[str, Watch] = {}
        self._closers: list[Callable[[], None]] = []
        self._scheduling = scheduling

    def add(self, name: str, watch: Watch, close: Callable[[], None] | None = None) -> None:
        """Add a watch (``close``: what to release after it stopped, e.g. its port)."""
        self.watches[name] = watch
        if close is not None:
            self._closers.append(close)

    def start(self) -> FeedbackWatches:
        # all watches start, or an interrupt waits for them
        with deferred_interrupts(), self._scheduling():
            for w in self.watches.values():
                w.start()
        return self

    def stop(self) -> None:
        """Stop every watch (also those never started) and close what they opened; an
        interrupt waits until all are stopped."""
        with deferred_interrupts():
            self._stop_all()

    def _stop_all(self) -> None:

        for w in self.watches.values():
            w.stop()
        for close in self._closers:
            close()
        self._closers = []

    @property
    def faults(self) -> list[str]:
        return [w.fault for w in self.watches.values() if w.fault is not None]

    def summary(self) -> dict[str, Any]:
        return {name: w.summary() for name, w in self.watches.items()}

    def __enter__(self) -> FeedbackWatches:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
