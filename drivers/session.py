"""The drive session: every bus and every CiA 402 drive of the box, from connect to
close, with one supervisor.

A :class:`DriveSession` opens the buses of a :class:`~drivers.config.BoxConfig`
(or takes buses already opened: :class:`~drivers.wiring.BoxWiring`), logs each bus's
traffic to a python-can log, and starts the :class:`~drivers.safety.supervisor.Supervisor`,
the one thread that owns the control loop, every watchdog and the host heartbeat.  Its
states (CLOSED, CONNECTED, READY, ENABLED, STREAMING, STOPPED, FAULT) and the calls that
move between them are one table (:mod:`drivers.lifecycle`, with the diagram):

1. :meth:`configure`: refuse a bus over its load budget; host heartbeat on; NMT
   reset and every node's boot-up (the error lists the missing ones); SDO
   configuration of every drive in parallel (:mod:`drivers.drive_group`: PDO mappings,
   heartbeat times, software limits 0x607D from the rope layer, interpolation period,
   CSP); NMT start.  :meth:`enable`: the CiA 402 state machine to OPERATION_ENABLED
   with a statusword check at every transition, the actual positions inside the
   limits; the supervisor is armed.  :meth:`bring_up` does both.
2. :meth:`stream`: play one setpoint source; any number of sources one after
   another (jog, hold, plan, hold) without a new NMT reset.  Any stop cause, idle
   or streaming, stops every axis (quick stop) within one control period; the
   session goes STOPPED (FAULT when the quick stop itself could not be sent).
3. :meth:`disable`: back to READY (disable operation, shutdown, by SDO).
   :meth:`finish`: disable operation, shutdown, NMT pre-operational, then the host
   heartbeat off.
4. :meth:`close`: stop the supervisor and the receive threads, close the logs,
   write the run record (:mod:`drivers.run_record`: JSON, atomically) beside them.

A call from a state that does not allow it raises :class:`SessionStateError`.  Before
the first reset the session listens for another master (:mod:`drivers.other_master`);
the console's read-outs are :meth:`status_snapshot` (:mod:`drivers.status`) and
:meth:`actual_positions`.

**Calibration.**  The session is told which calibration the rope layer it was given was
built with (:class:`CalibrationRef`: version, the file's checksum, its path; the drivers
never read calibrations themselves).  Without one, :meth:`enable` and :meth:`bring_up`
refuse (:class:`SessionStateError`, one line, before anything is sent) unless the caller
overrides explicitly (``allow_uncalibrated``); the run record names the version, or says
``uncalibrated (override)``.
The drivers never know what is at the other end of the wire (drives or a
simulator): everything goes through python-can buses.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import can
import numpy as np

from drivers.bringup import DriveLink
from drivers.bus import BusPort
from drivers.busload import BusLoad, check_bus_load
from drivers.config import BoxConfig
from drivers.cycle import EventLog, StreamResult
from drivers.device_check import check_box
from drivers.drive_group import DriveGroup
from drivers.identity import BoxIdentity, identify_box
from drivers.interrupts import deferred_interrupts
from drivers.lifecycle import Call, SessionState, SessionStateError, after_stop, next_state
from drivers.other_master import (
    OtherMasterError,
    foreign_frames,
    listen_for_other_masters,
    unconfigured_counts,
    unconfigured_traffic,
)
from drivers.protocol import cia301
from drivers.realtime import AppliedSettings
from drivers.receive import BusReceiver
from drivers.rope_model import MotorLimits
from drivers.run_record import (
    RUN_RECORD_FORMAT,
    UNCALIBRATED,
    CalibrationRef,
    calibration_text,
    run_record,
    write_run_record,
)
from drivers.safety.causes import StopCause, StopKind
from drivers.safety.limits import MAX_SOURCE_DURATION_S, accel_limits
from drivers.safety.monitor import NodeMonitor
from drivers.safety.stops import SafetyStopError, stopped_refusal, stream_stop_error
from drivers.safety.supervisor import Mode, StopRecord, Supervisor, SupervisorModeError
from drivers.scheduling import SessionScheduling
from drivers.sources import SetpointSource
from drivers.status import LastEmergencies, SessionStatus, bus_statuses, session_status
from drivers.wiring import BoxWiring, MotorSlots, PortNetwork
from hrm_ctrl.errors import DriverError, HrmError, interrupting_signal

__all__ = [
    "RUN_RECORD_FORMAT",
    "UNCALIBRATED",
    "CalibrationRef",
    "DriveSession",
    "OtherMasterError",
    "SafetyStopError",
    "SessionState",
    "SessionStateError",
]

# Before the first NMT reset: listen this long for another master (heartbeats of nodes in
# NMT operational, a SYNC producer, RPDOs, PDOs, node guarding); covers a heartbeat period
# of up to 1 s, the longest usual one (CiA 301 leaves it free).
LISTEN_BEFORE_RESET_S = 1.1
STREAM_TIMEOUT_MARGIN_S = 30.0  # a stream's wait: its own length plus this
HEARTBEAT_START_WAIT_S = 0.5  # the first host heartbeat precedes the NMT reset
STOP_RECORD_WAIT_S = 2.0  # longest wait for a stop being confirmed (10 periods at most)
EMCY_WAIT_S = 0.25  # a drive seen in FAULT: its EMCY is on the wire, the stop follows
_STOPPING = frozenset({Mode.STOPPING})


class DriveSession:
    """Every bus and drive of the box; see the module docstring for the states."""

    def __init__(
        self,
        config: BoxConfig,
        actuation: MotorLimits,
        log_dir: str | Path | None = None,
        log_suffix: str = ".blf",
        run_name: str | None = None,
        buses: Sequence[can.BusABC] | None = None,
        clock: Callable[[], float] = time.monotonic,
        take_over: bool = False,
        listen_s: float = LISTEN_BEFORE_RESET_S,
        calibration: CalibrationRef | None = None,
        allow_uncalibrated: bool = False,
    ) -> None:
        config.check_motors(actuation.motor_ids)
        if calibration is not None and not isinstance(calibration, CalibrationRef):
            raise TypeError(f"calibration must be a CalibrationRef, not {type(calibration)}")
        self.calibration = calibration
        self.allow_uncalibrated = bool(allow_uncalibrated)
        if buses is not None and len(buses) != len(config.buses):
            raise DriverError(f"{len(config.buses)} buses configured, {len(buses)} given")
        self.config = config
        self.actuation = actuation
        self.control = config.control
        self.events = EventLog()
        self.loads: list[BusLoad] = check_bus_load(config)
        # each drive's overlay, 0x60C2 encoding and identity, from its device file (read
        # before anything opens: open_box has checked them)
        # and 0x6085 from the motors' acceleration limits (checked here, before anything opens)
        accel = accel_limits(actuation)
        setups = check_box(config).setups(
            None if accel is None else dict(zip(actuation.motor_ids, accel.tolist(), strict=True))
        )
        self.run_name = run_name or dt.datetime.now(dt.UTC).strftime("run-%Y%m%dT%H%M%S-%f")
        self.log_dir = None if log_dir is None else Path(log_dir)
        self.log_suffix = log_suffix
        self.record_path: Path | None = None
        self.results: list[StreamResult] = []
        self.record_extra: dict[str, Any] = {}
        self.actual: np.ndarray | None = None
        self.box_identity: BoxIdentity | None = None  # read at configure()
        self.bringup_s: float | None = None
        self.idle_causes: list[StopCause] = []
        self.stop_error: str | None = None  # why the last quick stop could not be sent
        self._state = SessionState.CLOSED
        self._state_lock = threading.Lock()
        self.take_over = bool(take_over)
        self.listen_s = float(listen_s)
        self._brought_up = False  # this session has reset the drives (they are ours)
        ctl = self.control
        self.scheduling = SessionScheduling(
            ctl.realtime_priority, ctl.cpu_wakeup_latency_us, self.events
        )
        self._gc_hold = self.scheduling.gc_hold  # held from configure() to finish()
        self.slots = MotorSlots.of(config, actuation.motor_ids)  # motor -> slot, once
        self.emergencies = LastEmergencies(self.slots.n)
        mon = self.monitor = NodeMonitor(
            list(self.slots.labels),
            ctl.missing_tpdo_cycles,
            ctl.heartbeat_timeout_ms / 1000.0,
            clock=clock,
        )
        # drives without a heartbeat consumer: the host guards them (node guarding)
        mon.guard([self.slots.slot[m] for m, s in setups.items() if s.guarding is not None])
        log_dir = self.log_dir
        with self.scheduling.starting_threads():  # (SCHED_FIFO if granted)
            with deferred_interrupts():  # the buses and logs open whole, or close again
                self.wiring = BoxWiring(
                    config,
                    self.slots,
                    mon,
                    self.loads,
                    # another master's frames are stop causes from the configuration on
                    lambda: mon.armed or mon.guarding,
                    None if log_dir is None else lambda bus: log_dir / self._log_name(bus),
                    buses,
                )
            self.supervisor = Supervisor(
                self.wiring.layouts,
                mon,
                actuation,
                ctl.period_s,
                ctl.host_heartbeat_ms / 1000.0,
                ctl.host_node_id,
                self.events,
                on_stop=self._on_stop,
                # refused once: the threads run under normal scheduling, not asked again
                realtime_priority=self.scheduling.granted_priority,
                clock=clock,
                guarded_nodes=[
                    [nid for m, nid in b.nodes.items() if setups[m].guarding is not None]
                    for b in config.buses
                ],
            )
            self.supervisor.start()
        self.drives = DriveGroup(
            self.wiring.links, self.slots, actuation, ctl, mon, self.events, setups
        )
        self.realtime_granted = self.scheduling.realtime_granted
        self.cpu_latency = self.scheduling.hold_cpu_latency()  # while the session is open
        self._state = SessionState.CONNECTED
        self.events.add(
            "open",
            f"{len(config.buses)} bus(es), {self.slots.n} drives, {ctl.rate_hz:g} Hz",
            bus_loads=[bl.to_dict() for bl in self.loads],
        )

    def _log_name(self, bus: str) -> str:
        """The file name of bus ``bus``'s CAN log."""
        return f"{self.run_name}_{bus}{self.log_suffix}"

    # the wiring's parts under the names callers (benchmarks, the HIL rig) read
    @property
    def links(self) -> list[DriveLink]:
        """Every drive's SDO link, in slot order."""
        return self.wiring.links

    @property
    def _ports(self) -> list[BusPort]:
        return self.wiring.ports

    @property
    def _networks(self) -> list[PortNetwork]:
        return self.wiring.networks

    @property
    def _receivers(self) -> list[BusReceiver]:
        return self.wiring.receivers

    def thread_scheduling(self) -> contextlib.AbstractContextManager[AppliedSettings]:
        """A context in which the caller starts a thread that works for this session (a
        feedback watch): it gets the session's threads' scheduling, SCHED_FIFO at
        ``realtime_priority`` when the session got it, and the caller's thread its own
        policy back on leaving."""
        return self.scheduling.thread_scheduling()

    # ------------------------------------------------------------------ states
    @property
    def state(self) -> SessionState:
        return self._state

    @property
    def enabled(self) -> bool:
        """Every drive is (meant to be) OPERATION_ENABLED: ENABLED or STREAMING."""
        return self._state in (SessionState.ENABLED, SessionState.STREAMING)

    def _require(self, call: Call) -> SessionState:
        """The transition table's verdict on ``call`` now (:func:`next_state`)."""
        return next_state(self._state, call)

    def _set_state(self, state: SessionState) -> None:
        with self._state_lock:
            if self._state is not state:
                self.events.add("state", f"{self._state.name} -> {state.name}")
            self._state = state

    def _claim(self, call: Call) -> None:
        """Check and change the state in one step (a second caller is refused)."""
        with self._state_lock:
            target = next_state(self._state, call)
            self.events.add("state", f"{self._state.name} -> {target.name}")
            self._state = target

    def _unclaim_stream(self) -> None:
        """A stream refused before its first setpoint: back to ENABLED, unless the
        supervisor stopped the box meanwhile (then the stop's state stands)."""
        with self._state_lock:
            if self._state is SessionState.STREAMING and self.supervisor.mode is Mode.ARMED:
                self.events.add("state", "STREAMING -> ENABLED")
                self._state = SessionState.ENABLED

    def _on_stop(self, stop: StopRecord) -> None:
        """From the supervisor's thread: every axis was quick-stopped."""
        if not stop.while_streaming:
            self.idle_causes = list(stop.causes) + list(stop.failed)
        state, error = after_stop(stop)
        if error is not None:
            self.stop_error = error
        self._set_state(state)

    def _wait_stop_confirmed(self) -> None:
        """A quick stop under way is confirmed first (bounded: :data:`STOP_RECORD_WAIT_S`)."""
        self.supervisor.wait_while(_STOPPING, STOP_RECORD_WAIT_S)

    @property
    def sdo_transfer_s(self) -> float:
        """Longest one SDO transfer can take (timeout x (1 + canopen's retries))."""
        return self.drives.sdo_transfer_s

    # ------------------------------------------------------------------ sequence
    def configure(self) -> None:
        """NMT reset, boot-ups, SDO configuration of every drive (:class:`DriveGroup`),
        NMT start (-> READY).

        From ENABLED the drives are first disabled by SDO (never reset while enabled)."""
        self._require(Call.CONFIGURE)
        t_start = time.monotonic()
        sup = self.supervisor
        self._gc_hold.acquire()  # released by finish() and close()
        if self._state is SessionState.ENABLED:
            sup.disarm()
            try:
                self.drives.disable("disable before reset")
            except HrmError:
                self._abort_enable()
                self._set_state(SessionState.FAULT)
                raise
            self.events.add("disable", "every drive disabled (SWITCHED_ON) before the reset")
        sup.set_guard(False)  # the reset and configuration are this host's own traffic
        self._wait_stop_confirmed()  # a quick stop under way is confirmed before the reset
        self._set_state(SessionState.CONNECTED)
        sup.clear_stop_request()  # a stop asked for from here on stands
        self.idle_causes = []
        self.stop_error = None
        if not self._brought_up:
            listen_for_other_masters(self._receivers, self.listen_s, self.take_over, self.events)
        for r in self._receivers:
            r.traffic.clear_evidence()
        sup.set_heartbeat(True, wait_s=HEARTBEAT_START_WAIT_S)
        reset_at = sup.prepare_reset()
        self.send_nmt(cia301.NMT_RESET_NODE)
        self._brought_up = True
        self.events.add("nmt", "NMT reset node sent on every bus")
        self.drives.await_bootup(reset_at, t_start)  # and no node booted twice
        sup.mark_configured()  # a boot-up from here on: that drive lost its configuration
        for before in sup.drain_causes():
            # sent before the node's boot-up, so before its reset (e.g. the EMCYs of
            # drives that lost the previous session's heartbeat): the reset cleared it
            self.events.add(
                "before_reset", before.text, cause=before.kind.value, motor=before.motor
            )
        # which box this is (0x1018 of every drive): the calibration's, or refused
        try:
            self.box_identity = identify_box(
                self.links,
                self.drives.parallel,
                self.drives.budget_s(4),
                self.calibration,
                self.events,
            )
        except DriverError:  # two answers to each SDO request: a node that booted twice
            self.drives.refuse_duplicate_nodes()
            raise
        self.record_extra["box"] = self.box_identity.to_dict()
        self.drives.check_identities(self.box_identity)  # the configuration's, before any write
        self.drives.configure()
        self.send_nmt(cia301.NMT_START_REMOTE_NODE)
        self.events.add("nmt", "NMT start remote node sent on every bus")
        self.bringup_s = time.monotonic() - t_start
        sup.set_guard(True)
        self._set_state(SessionState.READY)

    def _require_calibration(self, action: str) -> None:
        """Refuse to enable drives without a calibration, unless overridden (sends nothing)."""
        if self.calibration is None and not self.allow_uncalibrated:
            text = (
                f"{action} refused: no calibration (drives are not enabled without one; "
                "the operator may override explicitly: --uncalibrated)"
            )
            self.events.add("error", text)
            raise SessionStateError(text, self._state)

    @deferred_interrupts()
    def enable(self) -> np.ndarray:
        """Every drive to OPERATION_ENABLED in CSP (-> ENABLED); return the actual
        positions (counts).  A drive whose actual position is outside its limits, or
        that does not reach the state, fails the whole enable: every drive then gets a
        quick stop by SDO and NMT pre-operational (-> FAULT).  Refused, before anything is
        sent, without a calibration unless ``allow_uncalibrated``; refused (still READY,
        nothing but SDO reads sent) when a node that booted again since answers as two
        devices (:class:`BootupError`), a stop cause came since the drives were
        configured or a drive is in FAULT: a fault is reset only on purpose
        (:meth:`reset_fault`).  A stop cause during the enable itself (an EMCY, a
        watch's cause, :meth:`request_stop`) quick-stops every axis as soon as the
        drives are enabled (-> STOPPED) and raises :class:`SafetyStopError`."""
        self._require_calibration("enable")
        self._require(Call.ENABLE)
        sup = self.supervisor
        # a cause from here on (another master's frame, a boot-up, an EMCY, a stop
        # request) is judged once every drive is enabled: every axis quick-stopped
        try:
            if not sup.set_guard_idle(False):
                raise SessionStateError("enable refused: a quick stop is in progress", self._state)
            self._require(Call.ENABLE)  # a guard stop just before: STOPPED
            foreign = foreign_frames(self._receivers)
            if foreign is not None and not self.take_over:
                text = f"enable refused: frames of another master since the reset: {foreign}"
                self.events.add("error", text)
                raise OtherMasterError(text, foreign)
            self._refuse_enable_after_causes()
        except HrmError:
            sup.set_guard_idle(True)
            raise
        t_start = time.monotonic()
        try:
            actual = self.drives.enable()
        except HrmError:
            self._abort_enable()
            sup.set_guard_idle(True)
            self._set_state(SessionState.FAULT)
            raise
        self.actual = actual
        self.bringup_s = (self.bringup_s or 0.0) + time.monotonic() - t_start
        self.events.add(
            "enabled", f"every drive OPERATION_ENABLED in CSP ({self.bringup_s:.3f} s bring-up)"
        )
        sup.arm(actual)  # heartbeats supervised from here on, across streams
        # a boot-up during the enable (up to the arming: from there it is a cause itself)
        for i in np.flatnonzero(self.monitor.rebooted).tolist():
            sup.report(
                StopKind.BOOTUP,
                f"{self.monitor.labels[i]}: node rebooted (boot-up frame) during the enable "
                "(its configuration is lost)",
            )
        sup.set_guard_idle(True)  # (armed, the idle watchdogs cover it all)
        self._set_state(SessionState.ENABLED)
        # what was reported while the drives were being enabled is judged now, not at
        # the next deadline: any cause quick-stops every axis at once
        sup.wake(sup.clock())
        self._raise_if_stopped()
        return actual

    def _refuse_enable_after_causes(self) -> None:
        """Before :meth:`enable` sends anything: refuse (still READY) when a node that
        booted again since the configuration began answers one SDO request twice (a
        second box whose boot-ups came late: :class:`BootupError` naming the duplicate
        nodes, :meth:`DriveGroup.refuse_late_duplicates`), when a stop cause was
        reported since the drives were configured (a node that rebooted by itself, an
        EMCY, a bad frame, a watch's cause: :meth:`reset_fault` clears them) or a drive
        is in FAULT (read by SDO)."""
        self.drives.refuse_late_duplicates()
        why = self.supervisor.cause_since_configured()
        if why is not None:
            self._refuse_enable(f"enable refused: {why}")
        in_fault = self.drives.in_fault()
        if in_fault:
            self._refuse_enable(
                f"enable refused: {', '.join(in_fault)} in FAULT (a fault is reset only on "
                "purpose: reset-fault)"
            )

    def _refuse_enable(self, text: str) -> None:
        self.events.add("error", text)
        raise SessionStateError(text, self._state, Call.ENABLE)

    def bring_up(self) -> np.ndarray:
        """:meth:`configure` then :meth:`enable`; return the actual positions (counts).
        Without a calibration (and no override) refused before the configuration."""
        self._require_calibration("bring-up")
        self._require(Call.BRING_UP)
        self.configure()
        return self.enable()

    def _abort_enable(self) -> None:
        """Bring-up failed half-way: quick stop by SDO to every drive (no target is
        written), then NMT pre-operational; failures here are logged, the original
        error is what the caller gets."""
        try:
            self.drives.quick_stop("abort")
        except HrmError as exc:
            self.events.add("error", f"quick stop after failed enable: {exc}")
        try:
            self.send_nmt(cia301.NMT_ENTER_PRE_OPERATIONAL)
        except DriverError as exc:
            self.events.add("error", f"NMT pre-operational after failed enable: {exc}")
        self.events.add("quick_stop", "bring-up failed: quick stop (SDO) and NMT pre-operational")

    @deferred_interrupts()
    def disable(self) -> None:
        """Disable every drive by SDO (-> READY); from STOPPED too (after a quick stop
        the drives are brought to READY_TO_SWITCH_ON the same way)."""
        target = self._require(Call.DISABLE)
        was_enabled = self._state is SessionState.ENABLED
        self.supervisor.disarm()  # with a last check: a cause found now stops every axis
        if was_enabled:
            self._raise_if_stopped()
        self.supervisor.clear_stop_request()  # (asked for while stopped: done by disabling)
        with self._guard_suspended():
            try:
                self.drives.disable("disable")
            except HrmError:
                self._set_state(SessionState.FAULT)
                raise
            self.events.add("disable", "every drive disabled and shut down (READY_TO_SWITCH_ON)")
            self._set_state(target)

    @contextlib.contextmanager
    def _guard_suspended(self) -> Iterator[None]:
        """While this session walks the drives by SDO (disable, fault reset) and then
        sets its state, the idle guard waits: another master's frame meanwhile stays
        queued, and quick-stops every node at the next deadline after (-> STOPPED), not
        in the middle where the new state would hide it."""
        self.supervisor.set_guard_idle(False)
        try:
            yield
        finally:
            self.supervisor.set_guard_idle(self.supervisor.guarding)

    def _last_causes(self) -> list[StopCause]:
        """Why the box stopped last: the idle stop's causes, or the last stream's."""
        return self.idle_causes or (self.results[-1].causes if self.results else [])

    def _refuse_stopped(self) -> None:
        """A stream asked for after a stop (idle or not): name why the box stopped."""
        causes = self._last_causes()
        if causes:
            raise stopped_refusal(causes, bool(self.idle_causes), self.stop_error, self.monitor.n)

    def _raise_if_stopped(self, expect_stop_s: float = 0.0) -> None:
        """While a stream is being prepared the supervisor may stop the box (an EMCY,
        a lost heartbeat): wait for its stop record, then refuse naming the cause.
        ``expect_stop_s``: how long to wait for a stop to begin (a drive found in FAULT
        has sent its EMCY, which may still be on its way)."""
        if expect_stop_s > 0:
            self.supervisor.wait_while(frozenset({Mode.ARMED}), expect_stop_s)
        self._wait_stop_confirmed()
        if self._state in (SessionState.STOPPED, SessionState.FAULT):
            self._refuse_stopped()

    def _stream_timeout_s(self, source: SetpointSource) -> float:
        """How long :meth:`stream` waits for ``source`` to end: its length (at most the
        longest source allowed) times 1.5, plus a margin."""
        n = source.n_cycles
        cycles = float(n) if n >= 0 else math.inf
        length_s = min(cycles * self.control.period_s, MAX_SOURCE_DURATION_S)
        return length_s * 1.5 + STREAM_TIMEOUT_MARGIN_S

    def stream(self, source: SetpointSource, raise_on_stop: bool = True) -> StreamResult:
        """Play a setpoint source from where the drives are (ENABLED -> STREAMING ->
        ENABLED); on any stop cause every axis gets a quick stop and
        :class:`SafetyStopError` is raised (or the result returned with
        ``raise_on_stop=False``).  The source is started (its whole table checked
        against every limit) and every drive's statusword read before anything is
        sent; a refusal there sends nothing and leaves the session ENABLED."""
        if self._state in (SessionState.STOPPED, SessionState.FAULT):
            self._refuse_stopped()
        self._claim(Call.STREAM)
        try:
            targets = self.supervisor.targets
            if targets is None:
                raise SessionStateError(
                    "stream: the drives hold no known position", self._state, Call.STREAM
                )
            source.start(np.asarray(targets, dtype=np.int64).copy(), self.control.period_s)
            try:
                self.drives.check_operation_enabled()  # before the first RPDO
            except DriverError:
                self._raise_if_stopped(EMCY_WAIT_S)  # the supervisor stops the box meanwhile
                raise
            self._raise_if_stopped()
        except BaseException:
            self._unclaim_stream()  # nothing was sent
            raise
        unconfigured_before = unconfigured_counts(self._receivers)
        try:
            # (the heap is out of the collector since the bring-up: self._gc_hold)
            result = self.supervisor.play(source, self._stream_timeout_s(source))
        except SupervisorModeError:  # stopped between the checks and the hand-over
            self._unclaim_stream()
            self._raise_if_stopped()
            raise
        except BaseException:
            if self.supervisor.last_result is not None:  # interrupted: it still ended
                self.results.append(self.supervisor.last_result)
            if self._state is SessionState.STREAMING:
                self._set_state(SessionState.FAULT)
            raise
        self.results.append(result)
        if not result.causes:
            # (an idle stop right after the stream's end has set STOPPED: it stands)
            if self._state is SessionState.STREAMING:
                self._set_state(SessionState.ENABLED)
            return result
        if self._state is SessionState.STREAMING:  # the stop record is already in
            self._set_state(SessionState.STOPPED)
        busy = unconfigured_traffic(self._receivers, unconfigured_before, result.cycles)
        if busy is not None:
            self.events.add("traffic", busy)
        if raise_on_stop:
            raise stream_stop_error(result, busy)
        return result

    def request_stop(
        self, kind: StopKind = StopKind.OPERATOR, text: str = "stop requested"
    ) -> None:
        """Quick stop every axis now, streaming or idle (thread-safe)."""
        self.supervisor.request_stop(kind, text)

    def send_nmt(self, command: int) -> None:
        """Broadcast one NMT command on every bus."""
        self.wiring.send_nmt(command)

    @deferred_interrupts()
    def finish(self) -> None:
        """Orderly end (-> CONNECTED), also after a safety stop: every drive disabled by
        SDO along the CiA 402 transition table (from OPERATION_ENABLED *disable
        operation* then *shutdown*; from a quick stop to READY_TO_SWITCH_ON: power stage
        off; no target position is sent; a drive in FAULT is left there), then NMT
        pre-operational, then the host heartbeat off (the drives no longer need it).
        Whatever fails, the rest is still done; then :class:`DriverError` names what
        failed (a drive left enabled stops itself when the host heartbeat ends, and on
        NMT pre-operational)."""
        target = self._require(Call.FINISH)
        sup = self.supervisor
        sup.set_guard(False)  # the drives are disabled and left from here on
        failed: list[str] = []
        try:
            if sup.mode is Mode.STREAMING:  # e.g. from another thread
                self.request_stop(StopKind.OPERATOR, "finish requested while streaming")
            # the stream ends, the stop is confirmed
            sup.wait_while(frozenset({Mode.STREAMING, Mode.STOPPING}), STOP_RECORD_WAIT_S)
            try:
                sup.disarm()  # with a last check (at once if stopping)
            except SupervisorModeError as exc:
                failed.append(str(exc))
            self._wait_stop_confirmed()
            if self.enabled or self._state in (SessionState.STOPPED, SessionState.FAULT):
                try:
                    self.drives.disable("disable")
                    self.events.add(
                        "disable", "every drive disabled and shut down (READY_TO_SWITCH_ON)"
                    )
                except HrmError as exc:
                    failed.append(str(exc))
            try:
                self.send_nmt(cia301.NMT_ENTER_PRE_OPERATIONAL)
                self.events.add("nmt", "NMT enter pre-operational sent on every bus")
            except HrmError as exc:
                failed.append(f"NMT pre-operational: {exc}")
        finally:
            sup.set_heartbeat(False)
            self._brought_up = False  # another master may take the drives from here on
            self._set_state(target)
            self._gc_hold.release()
        if self.stop_error is not None:
            failed.append(self.stop_error)
            self.stop_error = None
        if failed:
            text = "finish: " + "; ".join(failed)
            self.events.add("error", text)
            raise DriverError(text)

    # ------------------------------------------------------------------ records
    def record(self) -> dict[str, Any]:
        """The run record (:func:`drivers.run_record.run_record`)."""
        return run_record(
            run_name=self.run_name,
            config=self.config,
            motor_ids=self.actuation.motor_ids,
            calibration=self.calibration,
            allow_uncalibrated=self.allow_uncalibrated,
            loads=self.loads,
            bringup_s=self.bringup_s,
            actual=self.actual,
            results=self.results,
            state=self._state.value,
            receivers=self._receivers,
            idle_causes=self.idle_causes,
            events=self.events,
            monitor=self.monitor,
            logs=self.wiring.logs,
            extra=self.record_extra,
        )

    @deferred_interrupts()
    def close(self) -> Path | None:
        """Stop everything (-> CLOSED); write the run record (if logging); return its path.

        The record is written after the logs close, into the space they held for it
        since the session opened (:meth:`TrafficLog._hold_reserve`): a disk the run filled
        up still takes it, and names the logs that it cut short (``can_log_errors``).  A
        record that cannot be written even so raises :class:`DriverError` (one line)."""
        self.supervisor.close()
        self.scheduling.close()  # the CPU latency request and the heap hold
        self.wiring.close()
        self.supervisor.release_wake()  # (its thread selects on the descriptor)
        self._set_state(SessionState.CLOSED)
        if self.log_dir is None:
            return None
        path = self.log_dir / f"{self.run_name}.json"
        write_run_record(path, self.record())
        self.record_path = path
        return path

    def __enter__(self) -> DriveSession:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc_value: BaseException | None = None,
        traceback: object = None,
    ) -> None:
        """Finish (also after a safety stop: NMT pre-operational, host heartbeat last),
        then close.  A finish failure is raised when nothing else is in flight and the
        session was not already stopped (a stop was reported to the caller when it
        happened); otherwise it goes into the run record."""
        try:
            if self._state not in (SessionState.CLOSED, SessionState.CONNECTED) or (
                self.supervisor.mode is not Mode.OFF
            ):
                stopped = self._state in (SessionState.STOPPED, SessionState.FAULT)
                signal_name = interrupting_signal(exc_value)
                with deferred_interrupts():  # a second signal waits for the stop and finish
                    if signal_name is not None and self.supervisor.mode is Mode.ARMED:
                        # drives enabled and holding: quick stop every axis first (the
                        # finish's last idle check sends it at once), with its cause
                        self.request_stop(StopKind.SIGNAL, f"{signal_name}: stop requested")
                    try:
                        self.finish()
                    except HrmError as err:
                        if exc_type is None and not stopped:
                            raise
                        after = exc_type.__name__ if exc_type is not None else "a stop"
                        self.events.add("error", f"finish after {after}: {err}")
        finally:
            self.close()

    # ------------------------------------------------------------------ read-outs
    def track_emergencies(self) -> None:
        """Keep each drive's last EMCY (for :meth:`status_snapshot`); idempotent.  The
        console calls it right after opening the session (before any NMT reset)."""
        if not self.emergencies.tracking:
            self.emergencies.tracking = True
            self.wiring.subscribe_emcy(self.emergencies.on_emcy)

    def status_snapshot(
        self, tension_N: np.ndarray | None = None, *, read_drives: bool = True
    ) -> SessionStatus:
        """A :class:`drivers.status.SessionStatus` of the box now.  While streaming (or
        without ``read_drives``) the node values are the feedback TPDOs' (none before the
        first); otherwise every drive's statusword and actual position are read by SDO
        in parallel (bounded by the SDO timeouts; a drive that does not answer shows
        unknown values).  ``tension_N`` (n, the rope layer's order): the tension board's
        newest sample, if the caller reads one.  Sends nothing but SDO uploads."""
        by_sdo = read_drives and self._state not in (SessionState.CLOSED, SessionState.STREAMING)
        held = self.enabled or self._state is SessionState.STOPPED
        stopped = self._state in (SessionState.STOPPED, SessionState.FAULT)
        w = self.wiring
        return session_status(
            state=self._state.name,
            calibration=calibration_text(self.calibration, self.allow_uncalibrated),
            stop_causes=[x.text for x in self._last_causes()] if stopped else [],
            slots=self.slots,
            monitor=self.monitor,
            sdo_values=self.drives.statuses() if by_sdo else None,
            targets=self.supervisor.targets if held else None,
            tension_N=tension_N,
            last_emcy=self.emergencies.last,
            buses=bus_statuses(self.config.buses, self.loads, w.ports, w.receivers, w.logs),
        )

    def actual_positions(self) -> np.ndarray:
        """Every drive's actual position (0x6064, counts, the rope layer's order) read by
        SDO in parallel, bounded by the SDO timeouts (not while streaming: the feedback
        TPDOs have it); a drive that does not answer raises :class:`DriverError`."""
        self._require(Call.ACTUAL_POSITIONS)
        return self.drives.actual_positions()

    @deferred_interrupts()
    def reset_fault(self) -> list[str]:
        """After a stop: the fault reset of every drive in FAULT (CiA 402 transition 15,
        the statusword confirming it), then every drive disabled to READY_TO_SWITCH_ON
        (power stage off) along the transition table (-> READY: :meth:`enable` may follow).
        From STOPPED, FAULT or READY; returns the labels of the drives that were in FAULT.
        A drive that stays in FAULT (its cause persists) raises :class:`DriverError`
        naming it (-> FAULT); nothing moves (no target is written)."""
        target = self._require(Call.RESET_FAULT)
        sup = self.supervisor
        self._wait_stop_confirmed()
        try:
            sup.disarm()
        except SupervisorModeError as exc:
            self.events.add("error", f"reset-fault: {exc}")
        sup.clear_stop_request()  # (asked for while stopped: nothing enabled)
        for cause in sup.drain_causes():  # causes of the stop that is being cleared
            self.events.add(
                "cause_cleared", f"{cause.text} (cleared by the fault reset)",
                cause=cause.kind.value, motor=cause.motor,
            )  # fmt: skip
        with self._guard_suspended():
            try:
                reset = self.drives.reset_faults()
            except HrmError:
                self._set_state(SessionState.FAULT)
                raise
            self.events.add(
                "fault_reset",
                f"fault reset of {len(reset)} drive(s)"
                + (f" ({', '.join(reset)})" if reset else "")
                + "; every drive disabled (READY_TO_SWITCH_ON)",
            )
            self.idle_causes = []
            self.stop_error = None
            self._set_state(target)
        return reset
