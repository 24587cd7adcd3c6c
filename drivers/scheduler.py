"""The cyclic scheduler: one thread, phase-locked to a monotonic clock.

Deadlines sit on a fixed grid ``t0 + g T`` (no drift).  At every deadline the
scheduler

1. evaluates every watchdog (:meth:`NodeMonitor.check`): TPDOs of the last SYNC,
   statuswords, heartbeats, EMCYs, malformed frames, receive threads;
2. sends the SYNC on every bus, which applies the RPDOs sent during the previous
   period;
3. takes the next setpoint from the source, checks it against the rope layer's
   limits (position and speed; refused setpoints are never sent) and sends every
   node's RPDO (controlword + target position) on every bus;
4. records timing (lateness of the SYNC against its deadline, period jitter,
   CPU time spent).

So every period carries each node's RPDO and then the SYNC that applies it, and
the RPDOs have the rest of the period to reach the wire: a SYNC (0x080) sent right
behind a burst of RPDOs (0x2xx) could overtake them on a controller that sends
pending frames in identifier order.

Any stop cause makes it send a quick stop (controlword 0x0002 by RPDO, then, once
those RPDOs are on the wire, SYNC) to every node of every bus, repeat it each
period until the statuswords confirm it, and return the causes; watchdog events
that arrive between deadlines wake the scheduler immediately, so the quick stop
goes out within one control period of the event.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from drivers.bus import BusPort, BusSendError
from drivers.protocol import cia402 as c
from drivers.safety.limits import LimitChecker
from drivers.safety.monitor import NodeMonitor, StopCause
from drivers.sources import SetpointSource
from hrm_ctrl.errors import HrmError

LATE_THRESHOLD_S = 0.002
STOP_CONFIRM_CYCLES = 10
SYNC_MARGIN_S = 0.0005
SWITCH_INTERVAL_S = 0.0002  # GIL hand-over while streaming (default 5 ms)


@dataclass
class BusLayout:
    """The nodes of one bus in the box's global motor order."""

    port: BusPort
    index: np.ndarray  # global motor indices on this bus
    node_ids: np.ndarray
    notifier: can.Notifier | None = None
    burst_s: float = 0.0  # wire time of one cycle's worst-case traffic on this bus

    def __post_init__(self) -> None:
        self.rpdo_ids = [c.COB_RPDO1 + int(n) for n in self.node_ids]

    def rpdo_frames(self, controlword: int | np.ndarray, targets: np.ndarray) -> list[can.Message]:
        """RPDO frames of this bus for global target vector ``targets``."""
        payload = c.make_rpdo_target_payloads(
            np.broadcast_to(np.asarray(controlword), (len(self.index),)), targets[self.index]
        )
        n = c.RPDO_TARGET_SIZE
        return [
            can.Message(
                arbitration_id=cid,
                data=payload[n * i : n * i + n],
                is_extended_id=False,
                check=False,
            )
            for i, cid in enumerate(self.rpdo_ids)
        ]


@dataclass
class EventLog:
    """Timestamped events of a run (thread-safe append)."""

    t0: float = field(default_factory=time.monotonic)
    events: list[dict[str, Any]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, kind: str, text: str, **extra: Any) -> None:
        with self._lock:
            self.events.append(
                {"t_s": round(time.monotonic() - self.t0, 6), "kind": kind, "text": text, **extra}
            )

    def to_list(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.events)


class CycleStats:
    """Per-cycle timing of a stream.

    >>> st = CycleStats(0.01)
    >>> for k, late in enumerate([0.0002, 0.0004, 0.003]):
    ...     st.add(k * 0.01, k * 0.01, k * 0.01 + late, 0.001)
    >>> s = st.summary()
    >>> s["cycles"], s["late_cycles"], round(s["jitter_max_s"] * 1000, 1)
    (3, 1, 2.6)
    """

    def __init__(self, period_s: float, late_threshold_s: float = LATE_THRESHOLD_S) -> None:
        self.period_s = period_s
        self.late_threshold_s = late_threshold_s
        self.deadline: list[float] = []
        self.woke: list[float] = []
        self.sync_sent: list[float] = []
        self.cpu_s: list[float] = []
        self.skipped_slots = 0
        self.realtime = False
        self.missing_feedback = 0
        self.process_cpu_s = 0.0

    def add(self, deadline: float, woke: float, sync_sent: float, cpu_s: float) -> None:
        self.deadline.append(deadline)
        self.woke.append(woke)
        self.sync_sent.append(sync_sent)
        self.cpu_s.append(cpu_s)

    @property
    def n_cycles(self) -> int:
        return len(self.deadline)

    def summary(self) -> dict[str, Any]:
        """Lateness = SYNC sent minus its deadline (wake lateness: scheduler awake minus
        deadline); jitter = |period - T| between consecutive SYNCs; CPU = scheduler thread
        time per cycle; process CPU includes receive threads and log writers."""
        n = self.n_cycles
        out: dict[str, Any] = {
            "cycles": n,
            "period_s": self.period_s,
            "late_threshold_s": self.late_threshold_s,
            "skipped_slots": self.skipped_slots,
            "realtime_scheduling": self.realtime,
            "missing_feedback_node_cycles": self.missing_feedback,
        }
        if n == 0:
            return out
        late = np.asarray(self.sync_sent) - np.asarray(self.deadline)
        wake = np.asarray(self.woke) - np.asarray(self.deadline)
        cpu = np.asarray(self.cpu_s)
        out.update(
            {
                "wake_lateness_p99_s": float(np.percentile(wake, 99)),
                "wake_lateness_max_s": float(wake.max()),
                "lateness_p50_s": float(np.percentile(late, 50)),
                "lateness_p99_s": float(np.percentile(late, 99)),
                "lateness_max_s": float(late.max()),
                "late_cycles": int(np.count_nonzero(late > self.late_threshold_s)),
                "cpu_per_cycle_mean_s": float(cpu.mean()),
                "cpu_per_cycle_p99_s": float(np.percentile(cpu, 99)),
                "process_cpu_per_cycle_s": self.process_cpu_s / n,
            }
        )
        if n >= 2:
            jitter = np.abs(np.diff(np.asarray(self.sync_sent)) - self.period_s)
            out.update(
                {
                    "jitter_p50_s": float(np.percentile(jitter, 50)),
                    "jitter_p99_s": float(np.percentile(jitter, 99)),
                    "jitter_max_s": float(jitter.max()),
                    "drift_s": float(
                        (self.sync_sent[-1] - self.sync_sent[0])
                        - (self.deadline[-1] - self.deadline[0])
                    ),
                }
            )
        return out


def _raise_priority(priority: int) -> Callable[[], None] | None:
    """Put the calling thread under SCHED_FIFO at ``priority`` (Linux; needs the right);
    return a function restoring the previous policy, or None when not granted."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return None
    try:
        policy = os.sched_getscheduler(0)
        param = os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError):
        return None

    def restore() -> None:
        try:
            os.sched_setscheduler(0, policy, param)
        except OSError:
            pass

    return restore


@dataclass
class StreamResult:
    """How a stream ended."""

    completed: bool
    cycles: int
    causes: list[StopCause]
    stats: dict[str, Any]
    last_targets: np.ndarray
    stop_latency_s: float | None = None
    stop_confirmed: bool | None = None
    final_statuswords: list[int] = field(default_factory=list)
    error: HrmError | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "completed": self.completed,
            "cycles": self.cycles,
            "causes": [x.to_dict() for x in self.causes],
            "stop_latency_s": self.stop_latency_s,
            "stop_confirmed": self.stop_confirmed,
            "final_statuswords": self.final_statuswords,
            "stats": self.stats,
            "error": None if self.error is None else str(self.error),
        }


class CyclicScheduler:
    """Streams setpoints to every node of every bus, one SYNC per control period."""

    def __init__(
        self,
        buses: list[BusLayout],
        monitor: NodeMonitor,
        limits: LimitChecker,
        period_s: float,
        events: EventLog,
        late_threshold_s: float = LATE_THRESHOLD_S,
    ) -> None:
        self.buses = buses
        self.monitor = monitor
        self.limits = limits
        self.period_s = float(period_s)
        self.events = events
        self.late_threshold_s = late_threshold_s
        self.seq = -1  # SYNC sequence number, continues across streams
        self.stop_request = threading.Event()
        self.switch_interval_s = SWITCH_INTERVAL_S
        self.realtime_priority = 0
        self.crash_stopped = False  # the last stream ended by an exception after a quick stop

    # ------------------------------------------------------------------ sending
    @property
    def sync_delay_s(self) -> float:
        """Wait between a burst of RPDOs and an immediate SYNC: one cycle's worst-case
        traffic on the slowest bus plus a margin, so the SYNC (higher priority) cannot
        overtake RPDOs still queued in a controller that arbitrates by identifier."""
        return max((lay.burst_s for lay in self.buses), default=0.0) + SYNC_MARGIN_S

    def _send_rpdos(self, frames: list[list[can.Message]]) -> list[StopCause]:
        failed: list[StopCause] = []
        for layout, msgs in zip(self.buses, frames, strict=True):
            try:
                layout.port.send_many(msgs)
            except BusSendError as exc:
                failed.append(StopCause("send", str(exc), None, time.monotonic()))
        return failed

    def _send_syncs(self) -> list[StopCause]:
        self.seq += 1
        self.monitor.seq = self.seq
        failed: list[StopCause] = []
        for layout in self.buses:
            try:
                layout.port.send(c.make_sync())
            except BusSendError as exc:
                failed.append(StopCause("send", str(exc), None, time.monotonic()))
        return failed

    def send_controlword(self, controlword: int, targets: np.ndarray) -> list[StopCause]:
        """One RPDO per node (same controlword for all), then after :attr:`sync_delay_s`
        one SYNC on every bus; send failures are returned (other buses still served)."""
        failed = self._send_rpdos([lay.rpdo_frames(controlword, targets) for lay in self.buses])
        time.sleep(self.sync_delay_s)
        return failed + self._send_syncs()

    # ------------------------------------------------------------------ stopping
    def _quick_stop(
        self, causes: list[StopCause], targets: np.ndarray, detected_at: float
    ) -> tuple[float, bool, list[StopCause]]:
        extra = self.send_controlword(c.CW_QUICK_STOP, targets)
        latency = time.monotonic() - detected_at
        for cause in causes:
            self.events.add("stop_cause", cause.text, cause=cause.kind, motor=cause.motor)
        self.events.add(
            "quick_stop",
            f"quick stop (RPDO + SYNC) sent to every node of every bus {latency * 1000:.2f} ms "
            "after detection",
        )
        # Keep commanding quick stop until every node's feedback confirms it.
        confirmed = False
        t_next = time.monotonic() + self.period_s
        for _ in range(STOP_CONFIRM_CYCLES):
            time.sleep(max(0.0, t_next - time.monotonic()))
            t_next += self.period_s
            mon = self.monitor
            fresh = mon.rx_seq >= self.seq
            states = c.decode_states(mon.statusword)
            if bool(np.all(fresh & (states != int(c.State402.OPERATION_ENABLED)))):
                confirmed = True
                break
            extra += self.send_controlword(c.CW_QUICK_STOP, targets)
        self.events.add(
            "quick_stop_confirmed" if confirmed else "quick_stop_unconfirmed",
            "every node left OPERATION_ENABLED"
            if confirmed
            else "some nodes did not confirm the quick stop by TPDO",
        )
        return latency, confirmed, extra

    # ------------------------------------------------------------------ streaming
    def _watchdogs(self, now: float, due_seq: int, hb_armed: float | None) -> list[StopCause]:
        causes = self.monitor.check(now, due_seq, hb_armed)
        for layout in self.buses:
            exc = layout.notifier.exception if layout.notifier is not None else None
            if exc is not None:
                causes.append(
                    StopCause(
                        "receive", f"bus {layout.port.name}: receive failed ({exc})", None, now
                    )
                )
        if self.stop_request.is_set():
            causes.append(StopCause("operator", "stop requested", None, now))
        return causes

    def _next_setpoint(
        self, source: SetpointSource, k: int, previous: np.ndarray
    ) -> np.ndarray | None:
        """Setpoint of SYNC k, checked against the rope layer (raises on a limit)."""
        target = source.setpoint(k)
        if target is not None:
            self.limits.check_counts(target, previous=previous, dt_s=self.period_s)
        return target

    def stream(
        self,
        source: SetpointSource,
        actual: np.ndarray,
        ready_check: Callable[[], None] | None = None,
    ) -> StreamResult:
        """Run ``source`` from the actual positions until it ends or something stops it.

        Cycle: at each deadline, watchdogs, then SYNC on every bus (applying the RPDOs
        sent during the previous period), then the next setpoint is checked and its
        RPDOs sent; they have the rest of the period to reach the wire before the next
        SYNC.  Deadlines sit on a fixed grid ``t0 + g T``; if the host falls more than a
        period behind, grid slots are skipped (counted) but setpoints are never skipped,
        so the motion slows down rather than jumps.

        Before the first RPDO: ``ready_check`` (e.g. every drive's statusword read by
        SDO) may refuse by raising (nothing is sent); then every cause queued by the
        receive callbacks so far (an EMCY, a boot-up, a failed send, ...) is a stop
        cause: quick stop of every node, no setpoint is sent.
        """
        T = self.period_s
        mon = self.monitor
        self.crash_stopped = False
        mon.supervising = True  # boot-ups / NMT states from here on are stop causes too
        source.start(np.asarray(actual, dtype=np.int64), T)
        # Anything reported before the first RPDO (e.g. an EMCY just before the start)
        # stops the stream before it begins; heartbeats are checked from the time
        # supervision was armed (bring-up), not from this stream's start.
        hb_armed = mon.hb_armed_at
        early = self._watchdogs(time.monotonic(), -1, hb_armed)
        if ready_check is not None and not early:
            ready_check()
        stats = CycleStats(T, self.late_threshold_s)
        applied = np.asarray(actual, dtype=np.int64).copy()  # last target a SYNC applied
        due_seq = -1
        mon.missing_run[:] = 0
        missing0 = mon.missing_total
        self.stop_request.clear()
        mon.supervising = True
        self.events.add("stream_start", f"streaming {source.describe()}")
        causes: list[StopCause] = []
        error: HrmError | None = None
        completed = False
        old_switch = sys.getswitchinterval()
        sys.setswitchinterval(self.switch_interval_s)
        restore_sched = _raise_priority(self.realtime_priority)
        stats.realtime = restore_sched is not None
        cpu0 = time.process_time()
        crashed: BaseException | None = None
        try:
            k = 0
            causes = early + self._watchdogs(time.monotonic(), -1, hb_armed)
            pending = None
            if not causes:
                try:
                    pending = self._next_setpoint(source, 0, applied)
                except HrmError as exc:
                    error, pending = exc, None
                    causes = [
                        StopCause("limit", f"setpoint refused: {exc}", None, time.monotonic())
                    ]
            if not causes and pending is None:
                completed = True
            elif not causes and pending is not None:
                causes = self._send_rpdos(
                    [lay.rpdo_frames(c.CW_ENABLE_OPERATION, pending) for lay in self.buses]
                )
            t0 = time.monotonic() + max(self.sync_delay_s, T / 5)
            if hb_armed is None:
                hb_armed = t0
            g = 0
            while pending is not None and not causes:
                deadline = t0 + g * T
                remaining = deadline - time.monotonic()
                if remaining > 0 and mon.wake.wait(remaining):
                    # A watchdog fired between deadlines: react now.
                    mon.wake.clear()
                    causes = self._watchdogs(time.monotonic(), -1, None)
                    continue
                th0 = time.thread_time()
                now = time.monotonic()
                if now - deadline > T:
                    skip = int((now - t0) // T) - g
                    stats.skipped_slots += skip
                    g += skip
                    deadline = t0 + g * T
                causes = self._watchdogs(now, due_seq, hb_armed)
                if causes:
                    break
                causes = self._send_syncs()
                t_sync = time.monotonic()
                due_seq = self.seq
                applied = pending
                if causes:
                    break
                try:
                    pending = self._next_setpoint(source, k + 1, applied)
                except HrmError as exc:
                    error = exc
                    causes = [
                        StopCause("limit", f"setpoint refused: {exc}", None, time.monotonic())
                    ]
                    pending = None
                if pending is not None:
                    frames = [lay.rpdo_frames(c.CW_ENABLE_OPERATION, pending) for lay in self.buses]
                    causes = self._send_rpdos(frames)
                elif not causes:
                    completed = True
                stats.add(deadline, now, t_sync, time.thread_time() - th0)
                k += 1
                g += 1
        except BaseException as exc:  # interrupted or a bug: stop every axis, then re-raise
            crashed = exc
            causes = [
                StopCause("internal", f"scheduler interrupted: {exc!r}", None, time.monotonic())
            ]
        finally:
            sys.setswitchinterval(old_switch)
            if restore_sched is not None:
                restore_sched()
            stats.process_cpu_s = time.process_time() - cpu0
            stats.missing_feedback = mon.missing_total - missing0
        last = applied
        result = StreamResult(
            completed=completed,
            cycles=stats.n_cycles,
            causes=causes,
            stats={},
            last_targets=last,
            error=error,
        )
        if causes:
            unique: dict[tuple[str, str | None], StopCause] = {}
            for x in causes:
                unique.setdefault((x.kind, x.motor or x.text), x)
            causes = list(unique.values())
            detected = min((x.time_s for x in causes if x.time_s > 0), default=time.monotonic())
            latency, confirmed, extra = self._quick_stop(causes, last, detected)
            result.causes = causes + extra
            result.stop_latency_s = latency
            result.stop_confirmed = confirmed
        mon.supervising = False
        result.stats = stats.summary()
        result.final_statuswords = [int(v) for v in mon.statusword]
        self.events.add(
            "stream_end",
            "plan completed" if completed else "stopped: " + "; ".join(x.text for x in causes),
            stats=result.stats,
        )
        if crashed is not None:
            self.crash_stopped = True
            raise crashed
        return result
