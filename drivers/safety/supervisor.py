"""The supervisor: the one thread that owns the control loop, every watchdog and the
host heartbeat, from the moment a drive session connects until it closes.

It runs on a fixed grid of a monotonic clock, one deadline per control period, and
at each deadline does what its :class:`Mode` asks:

========== ==================================================================
mode       at every deadline
========== ==================================================================
OFF        nothing (no host heartbeat: the session is connected but idle)
HEARTBEAT  the host heartbeat when due (bring-up; after a stop)
ARMED      + every idle watchdog: heartbeats (timeout and NMT state), EMCYs,
           boot-ups, malformed frames, receive threads, failed sends, an
           operator's stop request (drives enabled, no stream)
STREAMING  + SYNC on every bus, the next setpoint checked against the rope and
           joint limits, every node's RPDO; feedback TPDOs and statuswords
STOPPING   quick stop (RPDO controlword 0x0002 + SYNC) to every node of every
           bus, repeated each period until every node's feedback confirms it
========== ==================================================================

The quick stop's targets are a deceleration ramp, not a jump to standstill: from the
speed of the last two applied targets each motor slows down by its acceleration limit
every period (``floor(a T**2)`` counts per period, at least one), beginning with the
very first quick-stop RPDO, and holds once at rest (clipped to the position limits).
That is a fault stop's ramp; a controlled stop (the operator's or a signal's: nothing
wrong with a drive, a bus or a limit) keeps the motors' jerk too, from the speed and
acceleration of the last three applied targets (:mod:`drivers.safety.ramps`: at most
``A/J``, 0.05 s with the default motors, longer).
The drives decelerate on their own in quick stop (0x605A, 0x6085); the targets they get
meanwhile stay within every motor's speed and acceleration limit per SYNC, as the CAN log
shows.  A stop found between deadlines goes out at once, so its first SYNC may follow the
stream's last by less than a period; its next SYNC waits until at least
``STOP_SYNC_MIN_SPACING`` periods after it (a deadline sooner than that is skipped), so
the ramp's steps also come a period apart on the wire.
A rope layer without acceleration limits (a test double) gets the last targets held.

Any stop cause, found at a deadline or reported between deadlines by a receive
callback (which wakes the thread at once), makes it send the quick stop to every
node of every bus right away, so every axis stops within one control period of
detection; then it keeps commanding the stop for up to ``STOP_CONFIRM_CYCLES``
periods until the statuswords confirm it, and records why (:class:`StopRecord`).

The per-period work is :meth:`Supervisor.step` (at a deadline) and
:meth:`Supervisor.wake` (between deadlines); the thread only calls them on the
grid.  Both take the time as an argument and the clock and sleep are injected, so
a test drives the supervisor deterministically with a fake bus port and a fake
clock, without the thread.
"""

from __future__ import annotations

import collections
import math
import select
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from drivers.bus import BusSendError
from drivers.cycle import (
    LATE_THRESHOLD_S,
    STOP_CONFIRM_CYCLES,
    SYNC_MARGIN_S,
    BusLayout,
    CycleStats,
    EventLog,
    StreamResult,
)
from drivers.interrupts import deferred_interrupts
from drivers.protocol import cia301, cia402
from drivers.protocol.batch import from_messages
from drivers.realtime import NORMAL_PRIORITY, process_settings
from drivers.receive import BusPoller
from drivers.rope_model import MotorLimits
from drivers.safety.causes import StopCause, StopKind, unique_causes
from drivers.safety.limits import CycleLimits, SetpointError, accel_limits, jerk_limits
from drivers.safety.monitor import NodeMonitor
from drivers.safety.ramps import braked, eased, is_controlled_stop
from drivers.sources import SetpointSource
from hrm_ctrl.errors import DriverError, HrmError, interrupting_signal

RECENT_SYNCS = 4  # SYNC times kept to count those after a stop cause's detection
PLAY_POLL_S = 0.25  # how often a caller waiting for a stream looks at the thread
THREAD_JOIN_TIMEOUT_S = 5.0
#: a deadline reached this late: the buses are read (without waiting) before the cycle
DRAIN_LATE_S = 0.0005
LOG_KICK_S = 0.08  # how often a stream cues the CAN logs' writers (< TrafficLog.FLUSH_S)
#: a quick stop's SYNCs come at least this many periods apart (its ramp steps a period each)
STOP_SYNC_MIN_SPACING = 0.95
#: how long a quick stop's burst may wait for room in one bus's transmit queue: a bus
#: whose queue stays full cannot hold back the other buses' stop for more than this
STOP_SEND_TIMEOUT_S = 0.002
_STOP_SEND: dict[str, Any] = {"timeout_s": STOP_SEND_TIMEOUT_S, "keep_going": True}
_CYCLE_SEND: dict[str, Any] = {}  # BusPort's own timeout, the first failure ends the batch
#: causes that quick-stop every node with no drive supervised (drives configured)
_GUARDED_WHILE_IDLE = frozenset({StopKind.FOREIGN})


class SupervisorModeError(DriverError):
    """A supervisor call refused in its current mode (e.g. a stream while stopping)."""


class Mode(Enum):
    """What the supervisor does at each deadline (see the module docstring)."""

    OFF = "off"
    HEARTBEAT = "heartbeat"
    ARMED = "armed"
    STREAMING = "streaming"
    STOPPING = "stopping"


@dataclass
class StopRecord:
    """One stop: why, how fast the quick stop went out, whether it was confirmed,
    the sends that failed while stopping, and whether a stream was running."""

    causes: list[StopCause]
    latency_s: float
    while_streaming: bool
    failed: list[StopCause] = field(default_factory=list)
    confirmed: bool | None = None  # None: still being confirmed
    #: setpoint SYNCs the stream sent after the first cause's detection, before the quick
    #: stop (0 or 1: within one control cycle; counted up to ``RECENT_SYNCS``).  Counted
    #: in cycles, it does not depend on how busy the machine is: a thread held off the CPU
    #: sends no SYNC either
    syncs_after_detection: int = 0
    #: the nodes whose feedback never confirmed the quick stop (their labels); each was
    #: sent NMT *enter pre-operational* when the supervisor gave up waiting
    unconfirmed: list[str] = field(default_factory=list)


@dataclass
class _Stream:
    """The run state of the stream being played."""

    source: SetpointSource
    stats: CycleStats
    applied: np.ndarray  # last targets a SYNC applied
    pending: np.ndarray | None  # targets whose RPDOs went out, applied at the next SYNC
    before: np.ndarray  # the targets applied one SYNC before ``applied`` (its speed)
    earlier: np.ndarray  # the targets applied one SYNC before ``before`` (acceleration)
    t0: float  # the stream's first SYNC deadline
    g: int = 0  # grid slot of the next SYNC
    k: int = 0  # setpoint index of the pending targets
    due_seq: int = -1  # SYNC whose TPDOs are due
    missing0: int = 0
    cpu0: float = 0.0
    completed: bool = False
    error: HrmError | None = None
    crashed: BaseException | None = None
    done: threading.Event = field(default_factory=threading.Event)
    result: StreamResult | None = None


def wait_while(
    mode_of: Callable[[], Mode],
    modes: frozenset[Mode],
    timeout_s: float,
    poll_s: float,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> Mode:
    """Poll ``mode_of()`` every ``poll_s`` until it is none of ``modes`` or ``timeout_s``
    has passed on ``clock``; return the last mode read (one of ``modes``: timed out).
    The one wait of the session on the supervisor (a stop being confirmed, a stream
    ending, a stop beginning).

    >>> t = [0.0]
    >>> wait_while(lambda: Mode.STOPPING, frozenset({Mode.STOPPING}), 0.05, 0.01,
    ...            clock=lambda: t[0], sleep=lambda s: t.__setitem__(0, t[0] + s)).name
    'STOPPING'
    >>> round(t[0], 3)
    0.05
    """
    deadline = clock() + timeout_s
    mode = mode_of()
    while mode in modes and clock() < deadline:
        sleep(poll_s)
        mode = mode_of()
    return mode


class Supervisor:
    """The one owner of the control loop (see the module docstring).

    ``layouts``: every bus with its nodes; ``monitor``: the receive state the bus
    callbacks fill; ``limits``: the rope layer's limit checks; ``on_stop``: called
    (from the supervisor's thread) with each finished :class:`StopRecord`.
    """

    def __init__(
        self,
        layouts: Sequence[BusLayout],
        monitor: NodeMonitor,
        limits: MotorLimits,
        period_s: float,
        heartbeat_period_s: float,
        host_node_id: int,
        events: EventLog,
        on_stop: Callable[[StopRecord], None] | None = None,
        late_threshold_s: float = LATE_THRESHOLD_S,
        realtime_priority: int = NORMAL_PRIORITY,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        guarded_nodes: Sequence[Sequence[int]] = (),
    ) -> None:
        self.layouts = list(layouts)
        # per layout, the node-guarding requests sent with each host heartbeat (the nodes
        # the host guards: drives without a heartbeat consumer)
        self._guarding_requests = [
            [cia301.make_guarding_request(nid) for nid in nodes] for nodes in guarded_nodes
        ] + [[] for _ in range(len(self.layouts) - len(guarded_nodes))]
        self.monitor = monitor
        self.limits = limits
        self.period_s = float(period_s)
        self.heartbeat_period_s = float(heartbeat_period_s)
        self.host_node_id = int(host_node_id)
        self.events = events
        self.on_stop = on_stop
        self.late_threshold_s = late_threshold_s
        self.realtime_priority = int(realtime_priority)
        self.realtime_granted = False  # SCHED_FIFO granted to the thread
        self.clock = clock
        self.sleep = sleep
        self.mode = Mode.OFF
        self.targets: np.ndarray | None = None  # what the drives hold (last applied)
        self.seq = -1  # SYNC sequence number, continues across streams
        self.last_result: StreamResult | None = None  # how the last stream ended
        self._lock = threading.RLock()
        self._stream: _Stream | None = None
        self._stop_request = threading.Event()
        # drives configured, none enabled or supervised (set by the session): another
        # master's frames quick-stop every node even so (it may be enabling them)
        self.guard_idle = False
        self._stop_reason: tuple[StopKind, str] = (StopKind.OPERATOR, "stop requested")
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._hb_next = 0.0
        self._hb_sent = threading.Event()  # set once a heartbeat went out after set_heartbeat
        self._stopping: StopRecord | None = None
        self._confirm_cycles = 0
        self._next_deadline = 0.0
        # the stop ramp: where it is, its speed and deceleration (counts per period)
        self._accel = accel_limits(limits, fallback=False)  # counts/s^2, or None
        self._cycle_limits = CycleLimits(limits, self.period_s)  # the per-setpoint check
        self._stop_decel: np.ndarray | None = (
            None
            if self._accel is None
            else np.maximum(np.floor(self._accel * self.period_s**2), 1).astype(np.int64)
        )
        # a controlled stop's ramp keeps the jerk too (drivers.safety.ramps): the motors'
        # speed, acceleration and jerk in whole counts per period (squared, cubed)
        if self._stop_decel is not None:
            T = self.period_s
            v_max = np.asarray(limits.max_rate_counts_per_s, dtype=np.float64)
            self._stop_speed = np.maximum(np.floor(v_max * T), 1).astype(np.int64)
            self._stop_jerk = np.maximum(np.floor(jerk_limits(limits) * T**3), 1).astype(np.int64)
        self._ramp_pos: np.ndarray | None = None
        self._ramp_vel: np.ndarray | None = None
        self._ramp_acc: np.ndarray | None = None  # a controlled stop's (None: a fault stop)
        self._rpdos_sent_at = -math.inf  # clock() when the last RPDO burst was handed over
        self._last_sync_at = -math.inf  # clock() when the last SYNC was handed over
        self._recent_syncs: collections.deque[float] = collections.deque(maxlen=RECENT_SYNCS)
        self._sync = from_messages([cia301.make_sync()])  # the SYNC as a one-frame batch
        # the CAN logs of the buses, kicked every LOG_KICK_S while streaming
        self._logs = [lay.port.log for lay in self.layouts if lay.port.log is not None]
        self._log_kick_cycles = max(1, round(LOG_KICK_S / self.period_s))

    # ------------------------------------------------------------------ thread
    def start(self) -> None:
        """Start the thread (idempotent)."""
        if self._thread is not None:
            return
        self._closing.clear()
        self._next_deadline = self.clock()
        self._thread = threading.Thread(target=self._run, name="hrm-supervisor", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread (the mode goes OFF: no more frames from the supervisor)."""
        with self._lock:
            self._stop_before_off()
            self.mode = Mode.OFF
            self.monitor.armed = False
        self._closing.set()
        self.monitor.wake.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout=THREAD_JOIN_TIMEOUT_S)
            if not thread.is_alive():  # one that outlived its join stays known (alive)
                self._thread = None

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        """The thread: under ``SCHED_FIFO`` at :attr:`realtime_priority` when asked for
        and granted (the switch interval is the process's, set by its entry point)."""
        with process_settings(
            switch_interval_s=None, realtime_priority=self.realtime_priority
        ) as applied:
            self.realtime_granted = applied.realtime_granted
            self._loop()

    def _loop(self) -> None:
        T = self.period_s
        mon = self.monitor
        # buses read in this thread (drivers.receive.BusPoller): waited for beside the
        # deadline and the wake event, in one select
        pollers = {
            lay.notifier.fileno(): lay.notifier
            for lay in self.layouts
            if isinstance(lay.notifier, BusPoller)
        }
        fds = [mon.wake.fileno(), *pollers]
        select_ = select.select
        while not self._closing.is_set():
            remaining = self._next_deadline - self.clock()
            if remaining > 0:
                if pollers:
                    try:
                        ready = select_(fds, (), (), remaining)[0]
                    except (OSError, ValueError):  # a bus closed under us: its poll says why
                        ready = list(pollers)
                    dead = False
                    for fd in ready:
                        poller = pollers.get(fd)
                        if poller is not None:
                            poller.poll()
                            if poller.exception is not None:  # a stop cause: not waited on
                                del pollers[fd]
                                dead = True
                    if dead:
                        fds = [mon.wake.fileno(), *pollers]
                    if not ready:
                        continue
                    woke = mon.wake.is_set()
                else:
                    woke = mon.wake.wait(remaining)
                if woke:
                    mon.wake.clear()
                    if self._closing.is_set():
                        return
                    self._guarded(self.wake, self.clock())
                continue
            now = self.clock()
            if now - self._next_deadline > DRAIN_LATE_S:
                # woken late (held off the CPU): what arrived meanwhile is read before the
                # watchdogs judge the cycle; a TPDO waiting in the socket is not missing
                for poller in pollers.values():
                    poller.poll()
            if now - self._next_deadline > T:  # fell more than a period behind: skip slots
                skip = int((now - self._next_deadline) // T)
                self._next_deadline += skip * T
                stream = self._stream
                if stream is not None:
                    stream.stats.skipped_slots += skip
            self._guarded(self.step, now, self._next_deadline)
            self._next_deadline += T

    def _guarded(self, fn: Callable[..., None], *args: float) -> None:
        """Run one step; a failure of the step itself (a bug, a source raising) stops
        every axis and is handed to the caller of :meth:`play`."""
        try:
            fn(*args)
        except BaseException as exc:
            stream = self._stream
            if stream is not None:
                stream.crashed = exc
            cause = StopCause(
                StopKind.INTERNAL, f"control loop interrupted: {exc!r}", None, self.clock()
            )
            try:
                if self.mode is not Mode.STOPPING:
                    self._begin_stop([cause], self.clock())
            except BaseException as again:
                self.events.add("error", f"quick stop after a supervisor failure: {again!r}")

    # ------------------------------------------------------------------ control
    def set_heartbeat(self, on: bool, wait_s: float = 0.0) -> bool:
        """Host heartbeat on (mode HEARTBEAT, the first one at once) or off (mode OFF).

        With ``wait_s`` > 0, wait that long at most for the first heartbeat to be sent
        (so it precedes what the caller sends next); return whether it was."""
        with self._lock:
            if on:
                self._hb_next = self.clock()
                self._hb_sent.clear()
                if self.mode is Mode.OFF:
                    self.mode = Mode.HEARTBEAT
                self.monitor.wake.set()
            else:
                self._stop_before_off()
                self.mode = Mode.OFF
                self.monitor.armed = False
        if on and wait_s > 0:
            return self._hb_sent.wait(wait_s)
        return True

    def _stop_before_off(self) -> None:
        """Going OFF (finish, close) with the drives enabled or a stream running: quick
        stop every axis first and end the stream with its result (under the lock)."""
        if self.mode in (Mode.ARMED, Mode.STREAMING):
            self._begin_stop(
                [StopCause(StopKind.OPERATOR, "session closed while enabled", None,
                           self.clock())],
                self.clock(),
            )  # fmt: skip
        if self.mode is Mode.STOPPING and self._stopping is not None:
            stop = self._stopping
            stop.confirmed = False
            self.events.add("quick_stop_unconfirmed", "supervisor going off while stopping")
            self._finish_stop(stop)

    def arm(self, targets: np.ndarray) -> None:
        """Drives enabled, holding ``targets``: every idle watchdog from now on.
        Heartbeat supervision counts from the first arming after bring-up."""
        with self._lock:
            if self.mode not in (Mode.HEARTBEAT, Mode.ARMED):
                raise SupervisorModeError(f"supervisor: cannot arm in mode {self.mode.name}")
            self.targets = np.asarray(targets, dtype=np.int64).copy()
            if self.monitor.hb_armed_at is None:
                self.monitor.hb_armed_at = self.clock()
            # a stop asked for since :meth:`clear_stop_request` (during the enable) stands
            self.monitor.armed = True
            self.mode = Mode.ARMED

    def disarm(self) -> None:
        """Drives about to be disabled on purpose: heartbeat only, no watchdogs."""
        with self._lock:
            if self.mode is Mode.STREAMING:
                raise SupervisorModeError(f"supervisor: cannot disarm in mode {self.mode.name}")
            if self.mode is Mode.ARMED:
                self.check_idle(self.clock())  # a last check: a cause now still stops
            if self.mode is Mode.ARMED:
                self.mode = Mode.HEARTBEAT
            self.monitor.armed = False

    def set_guard_idle(self, on: bool) -> bool:
        """Guard the configured drives while idle (see :attr:`guard_idle`), under the
        loop's lock; returns False when a quick stop is in progress (mode STOPPING)."""
        with self._lock:
            self.guard_idle = on
            return self.mode is not Mode.STOPPING

    def clear_stop_request(self) -> None:
        """Forget a stop asked for before the drives were configured."""
        self._stop_request.clear()

    # ------------------------------------------------------------------ the monitor's owner
    # The session moves the monitor's state only through these (the receive callbacks feed
    # it frames; the loop reads and arms it): one writer of what the watchdogs judge by.
    def set_guard(self, on: bool) -> None:
        """Drives configured (on) until the session ends or resets them (off): another
        master's frames are stop causes even with no drive enabled, and while idle the
        loop quick-stops every node on them (:meth:`set_guard_idle`)."""
        with self._lock:
            self.monitor.guarding = on
            self.guard_idle = on

    @property
    def guarding(self) -> bool:
        """Whether the configured drives are guarded (:meth:`set_guard`)."""
        return self.monitor.guarding

    def prepare_reset(self) -> float:
        """Just before an NMT reset: heartbeat supervision counts from the next arming
        again and every node's boot-up is awaited anew; returns the monitor's time of
        the reset (for :meth:`NodeMonitor.describe_missing_boot`)."""
        with self._lock:
            self.monitor.hb_armed_at = None
            self.monitor.reset_boot()
            return self.monitor.clock()

    def mark_configured(self) -> None:
        """Every node booted and is being configured: a boot-up from now on is a node
        that lost its configuration (a stop cause)."""
        self.monitor.configured()

    def drain_causes(self) -> list[StopCause]:
        """The stop causes queued so far, taken (the session logs or refuses on them)."""
        return self.monitor.drain()

    def cause_since_configured(self) -> str | None:
        """Why the drives may not be enabled now, or None: a node rebooted since the
        configuration (its configuration is lost), a stop asked for, or stop causes
        reported (an EMCY, a bad frame, a watch's cause: taken, each logged)."""
        mon = self.monitor
        rebooted = [mon.labels[i] for i in np.flatnonzero(mon.rebooted)]
        if rebooted:
            more = f" (+{len(rebooted) - 1} more)" if len(rebooted) > 1 else ""
            return (
                f"{rebooted[0]}{more} rebooted since the drives were configured (its "
                "configuration is lost): bring the drives up again"
            )
        request = self.take_stop_request()
        if request is not None:
            self.events.add("stop_cause", request[1], cause=request[0].value)
            return f"{request[1]} before the enable"
        earlier = mon.drain()
        if earlier:
            more = f" (+{len(earlier) - 1} more)" if len(earlier) > 1 else ""
            for cause in earlier:
                self.events.add("stop_cause", cause.text, cause=cause.kind.value, motor=cause.motor)
            return (
                f"{earlier[0].text}{more}, reported since the drives were configured "
                "(reset-fault clears it)"
            )
        return None

    def report(self, kind: StopKind, text: str) -> None:
        """A stop cause found outside the loop (judged at the next deadline or wake)."""
        self.monitor.report(kind, text)

    def release_wake(self) -> None:
        """After :meth:`close`: the monitor's wake-up descriptor closed, unless the
        thread outlived its join (it still selects on it)."""
        if not self.alive:
            self.monitor.wake.close()

    def wait_while(self, modes: frozenset[Mode], timeout_s: float) -> Mode:
        """Wait (polling once a period) until the mode is none of ``modes`` or
        ``timeout_s`` has passed; return the mode then (see :func:`wait_while`)."""
        return wait_while(lambda: self.mode, modes, timeout_s, self.period_s)

    def take_stop_request(self) -> tuple[StopKind, str] | None:
        """A stop asked for while no drive was enabled (kind, text), taken; or None."""
        if not self._stop_request.is_set():
            return None
        self._stop_request.clear()
        return self._stop_reason

    def request_stop(
        self, kind: StopKind = StopKind.OPERATOR, text: str = "stop requested"
    ) -> None:
        """Quick stop at once (thread-safe): an operator's stop, Ctrl-C, a signal."""
        self._stop_reason = (kind, text)
        self._stop_request.set()
        self.monitor.wake.set()

    def begin(self, source: SetpointSource) -> _Stream:
        """Hand a started source to the loop (mode ARMED -> STREAMING).

        Before the first RPDO every cause queued so far (an EMCY just before the start,
        a heartbeat overdue since bring-up, ...) is checked: any stops every axis and no
        setpoint is sent.  Else setpoint 0 is checked and its RPDOs sent; the first
        SYNC is on the next grid deadline at least one RPDO burst later.
        """
        with self._lock:
            if self.mode is not Mode.ARMED or self.targets is None:
                raise SupervisorModeError(f"supervisor: cannot stream in mode {self.mode.name}")
            now = self.clock()
            T = self.period_s
            # The first SYNC: the first grid deadline at least one RPDO burst from now.
            lead = now + max(self.sync_delay_s, T / 5) - self._next_deadline
            t0 = self._next_deadline + max(0, math.ceil(lead / T - 1e-9)) * T
            stream = _Stream(
                source=source,
                stats=CycleStats(T, self.late_threshold_s),
                applied=self.targets.copy(),
                pending=None,
                before=self.targets.copy(),
                earlier=self.targets.copy(),
                t0=t0,
                missing0=self.monitor.missing_total,
                cpu0=time.process_time(),
            )
            stream.stats.realtime = self.realtime_granted
            self.monitor.missing_run[:] = 0
            causes = self._watchdogs(now, -1, self.monitor.hb_armed_at)
            self.events.add("stream_start", f"streaming {source.describe()}")
            self._stream = stream
            self.mode = Mode.STREAMING
            try:
                self._first_setpoint(stream, causes, now)
            except BaseException as exc:  # an interrupt or a bug: no stream left running
                stream.crashed = exc
                if self.mode is Mode.STREAMING:
                    name = interrupting_signal(exc)
                    cause = StopCause(
                        StopKind.INTERNAL if name is None else StopKind.SIGNAL,
                        f"stream start interrupted: {name or repr(exc)}",
                        None,
                        now,
                    )
                    self._begin_stop([cause], now)
                raise
            return stream

    def _first_setpoint(self, stream: _Stream, causes: list[StopCause], now: float) -> None:
        """Causes queued before the stream stop it; else setpoint 0 checked and sent."""
        if causes:
            self._begin_stop(causes, now)
            return
        try:
            stream.pending = self._checked(stream.source, 0, stream.applied, stream.before)
        except HrmError as exc:
            stream.error = exc
            self._begin_stop([self._limit_cause(exc)], now)
            return
        if stream.pending is None:
            stream.completed = True
            self._end_stream()
            return
        causes = self._send_rpdos(cia402.CW_ENABLE_OPERATION, stream.pending)
        if causes:
            self._begin_stop(causes, now)

    def play(self, source: SetpointSource, timeout_s: float) -> StreamResult:
        """Play a started source to its end or its stop; return how it ended.

        Blocks the caller (polling the thread, so Ctrl-C is seen): an interrupt stops
        every axis and is re-raised once the stop went out; a failure inside the
        loop (a bug, a source raising something other than a limit) too.  Waits at
        most ``timeout_s``, then stops every axis and raises :class:`DriverError`.
        """
        self.last_result = None
        stream: _Stream | None = None
        deadline = self.clock() + timeout_s
        try:
            stream = self.begin(source)
            while not stream.done.wait(PLAY_POLL_S):
                if not self.alive:
                    raise DriverError("supervisor thread is not running")
                if self.clock() > deadline:
                    self.request_stop()
                    stream.done.wait(THREAD_JOIN_TIMEOUT_S)
                    raise DriverError(f"stream did not end within {timeout_s:g} s")
        except BaseException as exc:
            if isinstance(exc, SupervisorModeError):
                raise  # refused before anything was sent
            with deferred_interrupts():  # a second signal waits for this stop
                name = interrupting_signal(exc)
                if name is not None:
                    self.request_stop(StopKind.SIGNAL, f"{name}: stop requested")
                else:
                    self.request_stop(StopKind.INTERNAL, f"stream wait failed: {exc!r}")
                if stream is None:
                    stream = self._stream
                if stream is not None:
                    stream.done.wait(THREAD_JOIN_TIMEOUT_S)
            raise
        if stream.crashed is not None:
            raise stream.crashed
        if stream.result is None:  # done is only set with a result
            raise DriverError("stream ended without a result")
        return stream.result

    # ------------------------------------------------------------------ the work
    @property
    def sync_delay_s(self) -> float:
        """Wait between a burst of RPDOs and an immediate SYNC: one cycle's worst-case
        traffic on the slowest bus plus a margin, so the SYNC (higher priority) cannot
        overtake RPDOs still queued in a controller that arbitrates by identifier."""
        return max((lay.burst_s for lay in self.layouts), default=0.0) + SYNC_MARGIN_S

    def step(self, now: float, deadline: float | None = None) -> None:
        """Everything due at one deadline of the grid (``now`` is when it runs)."""
        deadline = now if deadline is None else deadline
        with self._lock:
            mode = self.mode
            if mode is Mode.ARMED:
                self.check_idle(now)
            elif mode is Mode.STREAMING:
                self._stream_cycle(now, deadline)
            elif mode is Mode.STOPPING:
                self._confirm_stop(now)
            elif mode is Mode.HEARTBEAT and self.guard_idle:
                self._guard_idle(now)
            self._heartbeat_if_due(now)

    def wake(self, now: float) -> None:
        """A receive callback reported something between deadlines: react now."""
        with self._lock:
            if self.mode is Mode.ARMED or self.mode is Mode.STREAMING:
                causes = self._watchdogs(now, -1, None)
                if causes:
                    self._begin_stop(causes, now)
            elif self.mode is Mode.HEARTBEAT and self.guard_idle:
                self._guard_idle(now)
            self._heartbeat_if_due(now)

    def _guard_idle(self, now: float) -> None:
        """Drives configured, none supervised (ready, or after a stop): another master's
        frame quick-stops every node of every bus at once (it may be enabling or moving
        them), logged with its cause; other causes stay queued for the next enable."""
        causes = self.monitor.take(_GUARDED_WHILE_IDLE)
        if causes:
            self._begin_stop(causes, now)

    def check_idle(self, now: float) -> None:
        """The idle watchdogs (mode ARMED): any cause stops every axis."""
        causes = self._watchdogs(now, -1, self.monitor.hb_armed_at)
        if causes:
            self._begin_stop(causes, now)

    def _heartbeat_if_due(self, now: float) -> None:
        """The host heartbeat at the deadline nearest its due time."""
        if self.mode is Mode.OFF or now < self._hb_next - self.period_s / 2:
            return
        self._hb_next += self.heartbeat_period_s
        if self._hb_next < now:  # fell behind by more than a heartbeat period
            self._hb_next = now + self.heartbeat_period_s
        msg_args = (self.host_node_id, cia301.NMT_STATE_OPERATIONAL)
        for layout, requests in zip(self.layouts, self._guarding_requests, strict=True):
            try:
                layout.port.send(cia301.make_heartbeat(*msg_args))
                for request in requests:  # node guarding, at the host heartbeat's period
                    layout.port.send(request)
            except BusSendError as exc:
                self.events.add("error", f"host heartbeat: {exc}")
                self.monitor.report(StopKind.SEND, f"host heartbeat not sent ({exc})")
        self._hb_sent.set()

    def _watchdogs(self, now: float, due_seq: int, hb_armed: float | None) -> list[StopCause]:
        causes = self.monitor.check(now, due_seq, hb_armed)
        for layout in self.layouts:
            exc = layout.notifier.exception if layout.notifier is not None else None
            if exc is not None:
                causes.append(
                    StopCause(
                        StopKind.RECEIVE,
                        f"bus {layout.port.name}: receive failed ({exc})",
                        None,
                        now,
                    )
                )
        if self._stop_request.is_set():
            kind, text = self._stop_reason
            causes.append(StopCause(kind, text, None, now))
        return causes

    def _checked(
        self, source: SetpointSource, k: int, previous: np.ndarray, before: np.ndarray
    ) -> np.ndarray | None:
        """Setpoint k of the source, checked against the rope layer (raises on a limit):
        position and speed from ``previous``, acceleration (the second difference with
        ``before``, applied one period earlier) against the motors' acceleration limits."""
        target = source.setpoint(k)
        if target is not None:
            if target.dtype.kind not in "iu":  # sent as int32: a fraction would be cut off
                raise SetpointError(
                    f"setpoint {k} of {source.describe()} is not whole counts "
                    f"(dtype {target.dtype}): not sent"
                )
            self._cycle_limits.check(target, previous, before)
        return target

    def _limit_cause(self, exc: HrmError) -> StopCause:
        return StopCause(StopKind.LIMIT, f"setpoint refused: {exc}", None, self.clock())

    def _send_rpdos(
        self, controlword: int, targets: np.ndarray, stopping: bool = False
    ) -> list[StopCause]:
        failed: list[StopCause] = []
        for layout in self.layouts:
            try:
                # a quick stop: a full queue holds no bus back long, a failed frame no node
                kw = _STOP_SEND if stopping else _CYCLE_SEND
                layout.port.send_batch(layout.rpdo_batch(controlword, targets), **kw)
            except BusSendError as exc:
                failed.append(StopCause(StopKind.SEND, str(exc), None, self.clock()))
        self._rpdos_sent_at = self.clock()
        return failed

    def _after_rpdo_burst(self) -> None:
        """A SYNC never overtakes the RPDOs before it: when a late cycle handed its RPDOs
        over less than :attr:`sync_delay_s` ago (the next deadline came early), wait out the
        rest (at most ``sync_delay_s``), so every node applies the same cycle's target."""
        wait = self._rpdos_sent_at + self.sync_delay_s - self.clock()
        if wait > 0.0:
            self.sleep(min(wait, self.sync_delay_s))

    def _send_syncs(self, targets: np.ndarray, stopping: bool = False) -> list[StopCause]:
        """One SYNC on every bus, applying ``targets`` (whose RPDOs went out before it:
        noted with the SYNC for the feedback watches, :meth:`NodeMonitor.sync_sent`)."""
        self.seq += 1
        self.monitor.sync_sent(self.seq, targets)
        failed: list[StopCause] = []
        for layout in self.layouts:
            try:
                layout.port.send_batch(self._sync, **(_STOP_SEND if stopping else _CYCLE_SEND))
            except BusSendError as exc:
                failed.append(StopCause(StopKind.SEND, str(exc), None, self.clock()))
        self._last_sync_at = self.clock()
        return failed

    def send_controlword(self, controlword: int, targets: np.ndarray) -> list[StopCause]:
        """One RPDO per node (same controlword for all), then after :attr:`sync_delay_s`
        one SYNC on every bus; send failures are returned (other buses still served).
        A quick stop's burst waits at most ``STOP_SEND_TIMEOUT_S`` for each bus's queue,
        and a frame that fails does not keep the nodes after it from theirs."""
        stopping = controlword == cia402.CW_QUICK_STOP
        failed = self._send_rpdos(controlword, targets, stopping)
        self.sleep(self.sync_delay_s)
        return failed + self._send_syncs(targets, stopping)

    def _stream_cycle(self, now: float, deadline: float) -> None:
        stream = self._stream
        if stream is None:
            return
        if now < stream.t0 - 1e-9:  # the stream's first SYNC is at t0
            return
        th0 = time.thread_time()
        causes = self._watchdogs(now, stream.due_seq, self.monitor.hb_armed_at)
        if causes:
            self._begin_stop(causes, now)
            return
        self._after_rpdo_burst()
        # the SYNC applies the pending targets; without any the drives hold the last
        causes = self._send_syncs(stream.pending if stream.pending is not None else stream.applied)
        t_sync = self.clock()
        self._recent_syncs.append(t_sync)
        stream.due_seq = self.seq
        stream.earlier = stream.before
        stream.before = stream.applied
        if stream.pending is not None:
            stream.applied = stream.pending
            self.targets = stream.pending
        if causes:
            self._begin_stop(causes, now)
            return
        try:
            stream.pending = self._checked(
                stream.source, stream.k + 1, stream.applied, stream.before
            )
        except HrmError as exc:
            stream.error = exc
            stream.pending = None
            causes = [self._limit_cause(exc)]
        if stream.pending is not None:
            causes = self._send_rpdos(cia402.CW_ENABLE_OPERATION, stream.pending)
        elif not causes:
            stream.completed = True
        if stream.g % self._log_kick_cycles == 0:
            for log_ in self._logs:  # the CAN logs write in this cycle's slack
                log_.kick()
        stream.stats.add(
            deadline, now, t_sync, time.thread_time() - th0, self.monitor.missing_total
        )
        stream.k += 1
        stream.g += 1
        if causes:
            self._begin_stop(causes, now)
        elif stream.completed:
            self._end_stream()

    def _result(self, stream: _Stream, stop: StopRecord | None) -> StreamResult:
        stream.stats.process_cpu_s = time.process_time() - stream.cpu0
        stream.stats.missing_feedback = self.monitor.missing_total - stream.missing0
        result = StreamResult(
            completed=stream.completed,
            cycles=stream.stats.n_cycles,
            causes=[] if stop is None else stop.causes + stop.failed,
            stats=stream.stats.summary(),
            last_targets=stream.applied,
            error=stream.error,
        )
        if stop is not None:
            result.stop_latency_s = stop.latency_s
            result.stop_syncs_after_detection = stop.syncs_after_detection
            result.stop_confirmed = stop.confirmed
        result.final_statuswords = [int(v) for v in self.monitor.statusword]
        self.last_result = result
        return result

    def _end_stream(self) -> None:
        """The source ended: back to ARMED, the result to the caller."""
        stream = self._stream
        if stream is None:
            return
        self._stream = None
        self.mode = Mode.ARMED
        stream.result = self._result(stream, None)
        self.events.add("stream_end", "plan completed", stats=stream.result.stats)
        stream.done.set()

    # ------------------------------------------------------------------ stopping
    def _begin_stop(self, causes: list[StopCause], now: float) -> None:
        """Quick stop every node of every bus now (RPDO + SYNC), then STOPPING."""
        causes = unique_causes(causes)
        detected = min((x.time_s for x in causes if x.time_s > 0), default=now)
        hold = self.targets if self.targets is not None else self._fed_back_positions()
        before = earlier = hold
        stream = self._stream
        if stream is not None:
            hold, before, earlier = stream.applied, stream.before, stream.earlier
        self.monitor.armed = False
        self._stop_request.clear()
        self._ramp_pos = np.asarray(hold, dtype=np.int64).copy()
        self._ramp_vel = self._ramp_pos - np.asarray(before, dtype=np.int64)
        self._ramp_acc = None
        if is_controlled_stop(causes) and self._stop_decel is not None:
            self._ramp_acc = self._ramp_vel - (
                np.asarray(before, dtype=np.int64) - np.asarray(earlier, dtype=np.int64)
            )
        failed = self.send_controlword(cia402.CW_QUICK_STOP, self._stop_targets())
        latency = self.clock() - detected
        syncs_after = sum(t > detected for t in self._recent_syncs) if stream is not None else 0
        self._recent_syncs.clear()
        for cause in causes:
            self.events.add("stop_cause", cause.text, cause=cause.kind.value, motor=cause.motor)
        where = "" if stream is not None else " while idle"
        if failed:
            self.events.add(
                "error", "quick stop failed: " + "; ".join(x.text for x in failed) + where
            )
        else:
            self.events.add(
                "quick_stop",
                f"quick stop (RPDO + SYNC) sent to every node of every bus{where} "
                f"{latency * 1000:.2f} ms after detection",
            )
        self._stopping = StopRecord(
            causes, latency, stream is not None, failed, syncs_after_detection=syncs_after
        )
        self._confirm_cycles = 0
        self.mode = Mode.STOPPING

    def _fed_back_positions(self) -> np.ndarray:
        """Where the drives last said they were (0 for a node not heard from): the
        targets of a quick stop before any drive was enabled (the idle guard's), so none
        carries a target far from the drive."""
        mon = self.monitor
        return np.where(mon.n_tpdo > 0, mon.position, 0).astype(np.int64)

    def _stop_targets(self) -> np.ndarray:
        """The next targets of the stop ramp (module docstring): a fault stop's each
        motor's speed less its deceleration, at once; a controlled stop's also keeping the
        jerk (:mod:`drivers.safety.ramps`); held where the rope layer has no acceleration
        limits.
        What the SYNC applies is what the drives hold from then on (``targets``)."""
        pos, vel = self._ramp_pos, self._ramp_vel
        if pos is None or vel is None:
            pos = self.targets if self.targets is not None else self._fed_back_positions()
            return np.asarray(pos, dtype=np.int64)
        if self._stop_decel is not None:
            acc = self._ramp_acc
            if acc is None:  # a fault stop: as fast as the acceleration allows
                nxt, vel = braked(pos, vel, self._stop_decel)
            else:  # a controlled stop: the jerk limit kept too
                nxt, vel, acc = eased(
                    pos, vel, acc, self._stop_speed, self._stop_decel, self._stop_jerk
                )
            lo = np.asarray(self.limits.counts_min, dtype=np.int64)
            hi = np.asarray(self.limits.counts_max, dtype=np.int64)
            nxt = np.clip(nxt, np.minimum(lo, pos), np.maximum(hi, pos))
            if acc is not None:
                acc = acc - (vel - (nxt - pos))  # what the position limits took
            vel = nxt - pos
            pos = nxt
            self._ramp_acc = acc
        else:
            vel = np.zeros_like(vel)
        self._ramp_pos, self._ramp_vel = pos, vel
        self.targets = pos
        if self._stream is not None:
            self._stream.earlier = self._stream.before
            self._stream.before = self._stream.applied
            self._stream.applied = pos
        return pos

    def _confirm_stop(self, now: float) -> None:
        """Once a period while STOPPING: done when every node's fresh feedback shows it
        left OPERATION_ENABLED; else the quick stop again (at most STOP_CONFIRM_CYCLES)."""
        stop = self._stopping
        if stop is None:
            self.mode = Mode.HEARTBEAT
            return
        mon = self.monitor
        fresh = mon.rx_seq >= self.seq
        states = cia402.decode_states(mon.statusword)
        confirmed = bool(np.all(fresh & (states != int(cia402.State402.OPERATION_ENABLED))))
        if not confirmed and now + self.sync_delay_s - self._last_sync_at < (
            STOP_SYNC_MIN_SPACING * self.period_s
        ):
            return  # the stop's own SYNC (between deadlines) went out under a period ago
        self._confirm_cycles += 1
        if not confirmed and self._confirm_cycles < STOP_CONFIRM_CYCLES:
            stop.failed += self.send_controlword(cia402.CW_QUICK_STOP, self._stop_targets())
            return
        stop.confirmed = confirmed
        if confirmed:
            self.events.add("quick_stop_confirmed", "every node left OPERATION_ENABLED")
        else:
            stuck = np.flatnonzero(~(fresh & (states != int(cia402.State402.OPERATION_ENABLED))))
            stop.unconfirmed = [mon.labels[i] for i in stuck.tolist()]
            self.events.add(
                "quick_stop_unconfirmed",
                f"{len(stuck)} node(s) did not confirm the quick stop by TPDO within "
                f"{STOP_CONFIRM_CYCLES} periods: {', '.join(stop.unconfirmed)}; NMT enter "
                "pre-operational sent to each (no PDO is processed there any more)",
            )
            stop.failed += self._pre_operational(set(stuck.tolist()))
        self._finish_stop(stop)

    def _pre_operational(self, slots: set[int]) -> list[StopCause]:
        """NMT *enter pre-operational* to the nodes in the global ``slots``: a drive that
        did not confirm a quick stop leaves NMT operational (CiA 402: its 0x6007 reaction
        to the lost connection); send failures are returned."""
        failed: list[StopCause] = []
        for layout in self.layouts:
            for slot, node in zip(layout.index.tolist(), layout.node_ids.tolist(), strict=True):
                if slot not in slots:
                    continue
                try:
                    layout.port.send(cia301.make_nmt(cia301.NMT_ENTER_PRE_OPERATIONAL, node))
                except BusSendError as exc:
                    failed.append(StopCause(StopKind.SEND, str(exc), None, self.clock()))
        return failed

    def _finish_stop(self, stop: StopRecord) -> None:
        """The stop is over: record it, end the stream with its result, tell the owner."""
        self._stopping = None
        self.mode = Mode.HEARTBEAT
        for cause in self.monitor.queued():  # reported while stopping (left queued)
            self.events.add(
                "cause_while_stopping", cause.text, cause=cause.kind.value, motor=cause.motor
            )
        stream = self._stream
        self._stream = None
        if stream is not None:
            stream.result = self._result(stream, stop)
            self.events.add(
                "stream_end",
                "stopped: " + "; ".join(x.text for x in stream.result.causes),
                stats=stream.result.stats,
            )
        if self.on_stop is not None:
            self.on_stop(stop)
        if stream is not None:
            stream.done.set()
