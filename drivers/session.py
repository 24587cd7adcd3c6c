"""The drive session: every bus and every CiA 402 drive of the box, from connect to
close, with one supervisor.

A :class:`DriveSession` opens the buses of a :class:`~drivers.config.BoxConfig`
(or takes buses already opened), logs each bus's traffic to a python-can log, and
starts the :class:`~drivers.safety.supervisor.Supervisor`, the one thread that owns
the control loop, every watchdog and the host heartbeat.  Its states
(:class:`SessionState`) and the calls that move between them:

.. code-block:: text

    CLOSED --open--> CONNECTED --configure--> READY --enable--> ENABLED
                        ^                        ^                | ^
                        |                        |          stream| |completed
                        |                        +--disable--+    v |
                        +-------finish---------- STOPPED <-- STREAMING
                                                 FAULT   (a stop that failed)

1. :meth:`configure`: refuse a bus over its load budget; host heartbeat on; NMT
   reset and every node's boot-up (the error lists the missing ones); SDO
   configuration of every drive in parallel (PDO mappings, heartbeat times,
   software limits 0x607D from the rope layer, interpolation period, CSP); NMT
   start.  :meth:`enable`: the CiA 402 state machine to OPERATION_ENABLED with a
   statusword check at every transition, the actual positions inside the limits;
   the supervisor is armed.  :meth:`bring_up` does both.
2. :meth:`stream`: play one setpoint source; any number of sources one after
   another (jog, hold, plan, hold) without a new NMT reset.  Any stop cause, idle
   or streaming, stops every axis (quick stop) within one control period; the
   session goes STOPPED (FAULT when the quick stop itself could not be sent).
3. :meth:`disable`: back to READY (disable operation, shutdown, by SDO).
   :meth:`finish`: disable operation, shutdown, NMT pre-operational, then the host
   heartbeat off.
4. :meth:`close`: stop the supervisor and the receive threads, close the logs,
   write the run record (JSON, atomically) beside them.

A call from a state that does not allow it raises :class:`SessionStateError`.

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

import concurrent.futures
import contextlib
import datetime as dt
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np

from drivers import eds_path
from drivers.bringup import (
    BootupError,
    DriveLink,
    DriveSettings,
    configure_drive,
    disable,
    enable_operation,
    read_state,
    sdo_write,
)
from drivers.bus import ECHOING_INTERFACES, BusPort, TrafficLog
from drivers.busload import BusLoad, check_bus_load
from drivers.config import BoxConfig
from drivers.cycle import BusLayout, EventLog, StreamResult
from drivers.interrupts import deferred_interrupts
from drivers.protocol import cia301, cia402
from drivers.realtime import (
    NORMAL_PRIORITY,
    AppliedSettings,
    CpuLatencyRequest,
    GcHold,
    process_settings,
)
from drivers.receive import BusPoller, BusReader, BusReceiver, pollable, wait_quiet_listen
from drivers.safety.causes import StopCause, StopKind
from drivers.safety.limits import MAX_SOURCE_DURATION_S, LimitChecker
from drivers.safety.monitor import NodeMonitor
from drivers.safety.supervisor import Mode, StopRecord, Supervisor, SupervisorModeError
from drivers.sources import SetpointSource
from hrm_ctrl.errors import DriverError, HrmError, interrupting_signal
from hrm_ctrl.files import write_atomic

RUN_RECORD_FORMAT = "hrm-run/1"
# Upper bounds of the parallel SDO work, in SDO transfers / CiA 402 transitions per drive
# (each transfer may take (1 + retries) SDO timeouts; each transition the state timeout).
CONFIG_SDO_TRANSFERS = 48
ENABLE_TRANSITIONS = 7
ENABLE_SDO_TRANSFERS = 12
PARALLEL_MARGIN_S = 1.0
# Before the first NMT reset: listen this long for another master (heartbeats of nodes in
# NMT operational, a SYNC producer, RPDOs, PDOs, node guarding); covers a heartbeat period
# of up to 1 s, the longest usual one (CiA 301 leaves it free).
LISTEN_BEFORE_RESET_S = 1.1
STREAM_TIMEOUT_MARGIN_S = 30.0  # a stream's wait: its own length plus this
HEARTBEAT_START_WAIT_S = 0.5  # the first host heartbeat precedes the NMT reset
STOP_RECORD_WAIT_S = 2.0  # longest wait for a stop being confirmed (10 periods at most)
EMCY_WAIT_S = 0.25  # a drive seen in FAULT: its EMCY is on the wire, the stop follows
log = logging.getLogger("drivers.session")


class SessionState(Enum):
    """Where a :class:`DriveSession` is (see the module docstring)."""

    CLOSED = "closed"
    CONNECTED = "connected"  # buses open; drives pre-operational or unknown
    READY = "ready"  # every drive configured and operational, power stage off
    ENABLED = "enabled"  # every drive OPERATION_ENABLED, supervised, holding
    STREAMING = "streaming"
    STOPPED = "stopped"  # quick-stopped by a stop cause
    FAULT = "fault"  # a stop, bring-up or disable that could not be carried out


class SessionStateError(DriverError):
    """A session call refused in the session's current state."""


UNCALIBRATED = "uncalibrated (override)"  # what the run record says without a calibration


@dataclass(frozen=True)
class CalibrationRef:
    """Which calibration the session's rope layer was built with: its version in the
    store, the file's SHA-256 checksum and where it came from (a path)."""

    version: int
    sha256: str
    source: str

    def to_dict(self) -> dict[str, Any]:
        return {"version": self.version, "sha256": self.sha256, "source": self.source}


class OtherMasterError(DriverError):
    """Another master is active on the box's buses: its drives are not reset."""


class SafetyStopError(DriverError):
    """Streaming was stopped by a watchdog, a limit or a bus failure; every axis got a
    quick stop.  ``causes`` lists why."""

    def __init__(self, message: str, causes: list[StopCause], result: StreamResult) -> None:
        super().__init__(message)
        self.causes = causes
        self.result = result


class _PortNetwork(canopen.Network):
    """A canopen network whose frames go out through a :class:`BusPort` (logged)."""

    def __init__(self, port: BusPort) -> None:
        super().__init__(port.bus)
        self.port = port

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.port.send(
            can.Message(
                arbitration_id=can_id,
                data=bytes(data),
                is_extended_id=can_id > 0x7FF,
                is_remote_frame=remote,
            )
        )
        self.check()


class DriveSession:
    """Every bus and drive of the box; see the module docstring for the states."""

    def __init__(
        self,
        config: BoxConfig,
        actuation: LimitChecker,
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
        self.run_name = run_name or dt.datetime.now(dt.UTC).strftime("run-%Y%m%dT%H%M%S-%f")
        self.log_dir = None if log_dir is None else Path(log_dir)
        self.log_suffix = log_suffix
        self.record_path: Path | None = None
        self.results: list[StreamResult] = []
        self.record_extra: dict[str, Any] = {}
        self.actual: np.ndarray | None = None
        self.bringup_s: float | None = None
        self.idle_causes: list[StopCause] = []
        self.stop_error: str | None = None  # why the last quick stop could not be sent
        self._state = SessionState.CLOSED
        self._state_lock = threading.Lock()
        self.take_over = bool(take_over)
        self.listen_s = float(listen_s)
        self._brought_up = False  # this session has reset the drives (they are ours)
        # the heap out of the cyclic collector from configure() to the end of finish()
        # (a full collection of a large heap pauses every thread: a heartbeat timeout)
        self._gc_hold = GcHold()

        n = len(actuation.motor_ids)
        self._ports: list[BusPort] = []
        self._logs: list[TrafficLog] = []
        self._owned: list[can.BusABC] = []
        self._networks: list[_PortNetwork] = []
        self._receivers: list[BusReceiver] = []
        self._layouts: list[BusLayout] = []
        self.links: list[DriveLink | None] = [None] * n
        labels = [""] * n
        order = {m: i for i, m in enumerate(actuation.motor_ids)}
        for b in config.buses:
            for motor, nid in b.nodes.items():
                labels[order[motor]] = f"{motor} (bus {b.name} node {nid})"
        self.monitor = NodeMonitor(
            labels,
            self.control.missing_tpdo_cycles,
            self.control.heartbeat_timeout_ms / 1000.0,
            clock=clock,
        )
        # Every thread the session starts (the buses' readers and log writers, the
        # supervisor) inherits the scheduling of the thread that starts it: they start
        # under SCHED_FIFO at realtime_priority, and the caller's thread gets its own
        # policy back.  The threads share one GIL: one of them at normal priority holding
        # it while the machine's other work preempts it keeps the FIFO ones waiting
        # (measured: the supervisor alone under FIFO, 1430 node-cycles without feedback
        # in 30 s; the whole host process, 54; BENCHMARKS.md, which also has the runs of
        # the session's threads alone).
        with process_settings(
            switch_interval_s=None, realtime_priority=self.control.realtime_priority
        ) as applied:
            self.realtime_granted = applied.realtime_granted
            with deferred_interrupts():  # the buses and logs open whole, or close again
                try:
                    self._open(buses)
                except BaseException:
                    self._close_io()
                    raise
            self.supervisor = Supervisor(
                self._layouts,
                self.monitor,
                actuation,
                self.control.period_s,
                self.control.host_heartbeat_ms / 1000.0,
                self.control.host_node_id,
                self.events,
                on_stop=self._on_stop,
                # refused once: the session's threads run under normal scheduling (one
                # warning said so), the supervisor does not ask again
                realtime_priority=self._granted_priority(),
                clock=clock,
            )
            self.supervisor.start()
        # the CPUs' wake-up latency (PM QoS), held while the session is open
        self.cpu_latency = CpuLatencyRequest(self.control.cpu_wakeup_latency_us)
        if self.cpu_latency.held or self.cpu_latency.refusal:
            self.events.add(
                "cpu-latency",
                f"CPU wake-up latency at most {self.cpu_latency.max_us} us held"
                if self.cpu_latency.held
                else f"{self.cpu_latency.refusal}; CPUs may sleep",
            )
        self._state = SessionState.CONNECTED
        if applied.realtime_priority:
            self.events.add(
                "realtime",
                f"session threads under SCHED_FIFO {applied.realtime_priority}"
                if applied.realtime_granted
                else f"{applied.realtime_refusal}; normal scheduling",
            )
        self.events.add(
            "open",
            f"{len(config.buses)} bus(es), {n} drives, {self.control.rate_hz:g} Hz",
            bus_loads=[bl.to_dict() for bl in self.loads],
        )

    def _granted_priority(self) -> int:
        return self.control.realtime_priority if self.realtime_granted else NORMAL_PRIORITY

    def thread_scheduling(self) -> contextlib.AbstractContextManager[AppliedSettings]:
        """A context in which the caller starts a thread that works for this session (a
        feedback watch): it gets the session's threads' scheduling, SCHED_FIFO at
        ``realtime_priority`` when the session got it, and the caller's thread its own
        policy back on leaving."""
        return process_settings(switch_interval_s=None, realtime_priority=self._granted_priority())

    # ------------------------------------------------------------------ states
    @property
    def state(self) -> SessionState:
        return self._state

    @property
    def enabled(self) -> bool:
        """Every drive is (meant to be) OPERATION_ENABLED: ENABLED or STREAMING."""
        return self._state in (SessionState.ENABLED, SessionState.STREAMING)

    def _require(self, action: str, *allowed: SessionState) -> None:
        if self._state not in allowed:
            names = ", ".join(s.name for s in allowed)
            raise SessionStateError(
                f"{action}: not allowed in state {self._state.name} (only from {names})"
            )

    def _set_state(self, state: SessionState) -> None:
        with self._state_lock:
            if self._state is not state:
                self.events.add("state", f"{self._state.name} -> {state.name}")
            self._state = state

    def _claim(self, action: str, source: SessionState, target: SessionState) -> None:
        """Check and change the state in one step (a second caller is refused)."""
        with self._state_lock:
            if self._state is not source:
                raise SessionStateError(
                    f"{action}: not allowed in state {self._state.name} (only from {source.name})"
                )
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
        problems = [x.text for x in stop.failed]
        if stop.unconfirmed:  # still enabled for all we know: not a stop to recover from
            problems.append(
                f"not confirmed by {', '.join(stop.unconfirmed)} (sent NMT pre-operational; "
                "bring the drives up again)"
            )
        if problems:
            self.stop_error = "quick stop{} failed: {}".format(
                "" if stop.while_streaming else " while idle", "; ".join(problems)
            )
        self._set_state(SessionState.FAULT if problems else SessionState.STOPPED)

    # ------------------------------------------------------------------ I/O setup
    def _open(self, given: Sequence[can.BusABC] | None) -> None:
        od = canopen.import_od(str(eds_path()))
        order = {m: i for i, m in enumerate(self.actuation.motor_ids)}
        opened: list[can.BusABC] = []
        for bi, b in enumerate(self.config.buses):  # every bus first: no log for a bad one
            if given is not None:
                opened.append(given[bi])
                continue
            try:
                bus = can.Bus(**b.bus_kwargs())
            except Exception as exc:  # a missing interface library can raise anything
                raise DriverError(
                    f"{self.config.source}: buses.{b.name}: cannot open {b.interface} "
                    f"channel {b.channel!r} ({type(exc).__name__}: {exc})"
                ) from None
            self._owned.append(bus)
            opened.append(bus)
        for b, bus in zip(self.config.buses, opened, strict=True):
            bi = len(self._layouts)
            log = None
            if self.log_dir is not None:
                log = TrafficLog(
                    self.log_dir / f"{self.run_name}_{b.name}{self.log_suffix}",
                    channel=bi + 1,
                )
                self._logs.append(log)
            echoes = b.interface in ECHOING_INTERFACES or bool(
                b.options.get("receive_own_messages", False)
            )
            port = BusPort(b.name, bus, log, echoes=echoes)
            self._ports.append(port)
            net = _PortNetwork(port)
            labels = {nid: self.monitor.labels[order[m]] for m, nid in b.nodes.items()}
            router = BusReceiver(
                port,
                net,
                log,
                labels,
                self.monitor.report,
                # another master's frames are stop causes from the configuration on
                lambda: self.monitor.armed or self.monitor.guarding,
                self.control.host_node_id,
            )
            self._receivers.append(router)
            idx = np.array([order[m] for m in b.nodes], dtype=np.int64)
            for motor, nid in b.nodes.items():
                i = order[motor]
                node = canopen.RemoteNode(nid, od)
                net.add_node(node)
                node.sdo.RESPONSE_TIMEOUT = self.control.sdo_timeout_s
                self.links[i] = DriveLink(node, b.name, motor)
                self._subscribe(net, i, nid)
                router.tpdo[cia301.COB_TPDO1 + nid] = (self.monitor, i)
                router.heartbeat[cia301.COB_NMT_ERROR_CONTROL + nid] = (self.monitor, i)
            # our own receive thread (no can.Notifier dispatch); canopen's Network only
            # asks it for .exception (check) and .stop (disconnect)
            # a bus with a descriptor is read by the supervisor's thread (BusPoller)
            net.notifier = (  # type: ignore[assignment]
                BusPoller(bus, router, b.name) if pollable(bus) else BusReader(bus, router, b.name)
            )
            self._networks.append(net)
            load = self.loads[bi]
            self._layouts.append(
                BusLayout(
                    port,
                    idx,
                    np.array(list(b.nodes.values())),
                    net.notifier,
                    burst_s=load.bits_per_cycle / load.bitrate,
                )
            )

    def _subscribe(self, net: canopen.Network, i: int, nid: int) -> None:
        mon = self.monitor
        net.subscribe(
            cia301.COB_NMT_ERROR_CONTROL + nid, lambda _cid, data, _ts: mon.on_heartbeat(i, data)
        )
        net.subscribe(cia301.COB_EMCY + nid, lambda _cid, data, _ts: mon.on_emcy(i, nid, data))

    def _links(self) -> list[DriveLink]:
        return [link for link in self.links if link is not None]

    @property
    def sdo_transfer_s(self) -> float:
        """Longest one SDO transfer can take (timeout x (1 + canopen's retries))."""
        return self.control.sdo_timeout_s * (1 + canopen.sdo.SdoClient.MAX_RETRIES)

    def _budget_s(self, transfers: int, transitions: int = 0) -> float:
        """Time bound of parallel work of ``transfers`` SDO transfers and ``transitions``
        CiA 402 transitions per drive."""
        per_transition = self.control.state_timeout_s + self.sdo_transfer_s
        return transfers * self.sdo_transfer_s + transitions * per_transition + PARALLEL_MARGIN_S

    def _parallel(self, what: str, fn: Callable[[DriveLink], Any], timeout_s: float) -> list[Any]:
        """Run ``fn`` for every drive at once; raise the first error (all finish first),
        or :class:`DriverError` naming the drives still busy after ``timeout_s``."""
        links = self._links()
        pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=min(36, len(links)), thread_name_prefix=f"drives-{what}"
        )
        try:
            futures = [pool.submit(fn, link) for link in links]
            _done, busy = concurrent.futures.wait(futures, timeout=timeout_s)
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
        if busy:
            names = [link.label for link, f in zip(links, futures, strict=True) if f in busy]
            text = f"{what}: no answer within {timeout_s:g} s from {len(names)} drive(s): " + (
                ", ".join(names)
            )
            self.events.add("error", text)
            raise DriverError(text)
        errors = [f.exception() for f in futures if f.exception() is not None]
        if errors:
            first = errors[0]
            more = f" (and {len(errors) - 1} more drive(s) failed)" if len(errors) > 1 else ""
            self.events.add("error", f"{what}: {first}{more}")
            if isinstance(first, HrmError):
                try:
                    same_kind = type(first)(f"{first}{more}")  # keep the error's class
                except TypeError:
                    same_kind = DriverError(f"{first}{more}")
                raise same_kind from None
            raise DriverError(f"{what}: {first}{more}") from None
        return [f.result() for f in futures]

    # ------------------------------------------------------------------ sequence
    def _settings(self, link: DriveLink) -> DriveSettings:
        ctl = self.control
        act = self.actuation
        i = act.motor_ids.index(link.motor)
        return DriveSettings(
            period_s=ctl.period_s,
            host_node_id=ctl.host_node_id,
            host_heartbeat_timeout_ms=ctl.heartbeat_timeout_ms,
            node_heartbeat_ms=ctl.node_heartbeat_ms,
            counts_min=int(act.counts_min[i]),
            counts_max=int(act.counts_max[i]),
            following_error_window_counts=ctl.following_error_window_counts,
            quick_stop_option_code=ctl.quick_stop_option_code,
        )

    def configure(self) -> None:
        """NMT reset, boot-ups, SDO configuration of every drive, NMT start (-> READY).

        From ENABLED the drives are first disabled by SDO (never reset while enabled)."""
        self._require(
            "configure",
            SessionState.CONNECTED,
            SessionState.READY,
            SessionState.ENABLED,
            SessionState.STOPPED,
            SessionState.FAULT,
        )
        t_start = time.monotonic()
        ctl = self.control
        self._gc_hold.acquire()  # released by finish() and close()
        if self._state is SessionState.ENABLED:
            self.supervisor.disarm()
            try:
                self._disable_drives("disable before reset")
            except HrmError:
                self._abort_enable()
                self._set_state(SessionState.FAULT)
                raise
            self.events.add("disable", "every drive disabled (SWITCHED_ON) before the reset")
        self._guard(False)  # the reset and configuration are this host's own traffic
        deadline = time.monotonic() + STOP_RECORD_WAIT_S
        while self.supervisor.mode is Mode.STOPPING and time.monotonic() < deadline:
            time.sleep(ctl.period_s)  # a quick stop under way is confirmed before the reset
        self._set_state(SessionState.CONNECTED)
        self.supervisor.clear_stop_request()  # a stop asked for from here on stands
        self.idle_causes = []
        self.stop_error = None
        self.monitor.hb_armed_at = None
        if not self._brought_up:
            self._listen_for_other_masters()
        for r in self._receivers:
            r.traffic.clear_evidence()
        self.supervisor.set_heartbeat(True, wait_s=HEARTBEAT_START_WAIT_S)
        self.monitor.reset_boot()
        reset_at = self.monitor.clock()
        self.send_nmt(cia301.NMT_RESET_NODE)
        self._brought_up = True
        self.events.add("nmt", "NMT reset node sent on every bus")
        if not self.monitor.boot_event.wait(ctl.bootup_timeout_s):
            missing = self.monitor.describe_missing_boot(reset_at)
            raise BootupError(
                f"no boot-up within {ctl.bootup_timeout_s:g} s from {len(missing)} node(s): "
                + "; ".join(missing)
            )
        self.events.add("bootup", f"every node booted ({time.monotonic() - t_start:.3f} s)")
        self._refuse_duplicate_nodes()
        self.monitor.configured()  # a boot-up from here on: that drive lost its configuration
        for before in self.monitor.drain():
            # sent before the node's boot-up, so before its reset (e.g. the EMCYs of
            # drives that lost the previous session's heartbeat): the reset cleared it
            self.events.add(
                "before_reset", before.text, cause=before.kind.value, motor=before.motor
            )
        try:
            self._parallel(
                "configuration",
                lambda link: configure_drive(link, self._settings(link)),
                self._budget_s(CONFIG_SDO_TRANSFERS),
            )
        except DriverError:
            # a second device's boot-up may come after every node's first: two answers
            # to each SDO request fail the configuration, and this is why
            self._refuse_duplicate_nodes()
            raise
        self.events.add("configured", "every drive configured by SDO (CSP, PDOs, limits)")
        self.send_nmt(cia301.NMT_START_REMOTE_NODE)
        self.events.add("nmt", "NMT start remote node sent on every bus")
        self.bringup_s = time.monotonic() - t_start
        self._guard(True)
        self._set_state(SessionState.READY)

    def _refuse_duplicate_nodes(self) -> None:
        """:class:`BootupError` if a node booted more than once after the one NMT reset:
        two devices answer as that node (a second box, or a simulator, on the same bus; a
        node-id clash), and each SDO request would get two answers."""
        dup = self.monitor.describe_duplicate_boot()
        if dup:
            more = f" (+{len(dup) - 4} more)" if len(dup) > 4 else ""
            text = (
                f"more than one device answers as the same node ({len(dup)} node(s) booted "
                "more than once after one NMT reset: a second box or a node-id clash on "
                "the bus): " + "; ".join(dup[:4]) + more
            )
            self.events.add("error", text)
            raise BootupError(text)

    def _guard(self, on: bool) -> None:
        """Drives configured (on) until the session ends or resets them (off): another
        master's frames are stop causes even with no drive enabled; while idle (not
        enabling, no drive supervised) the supervisor quick-stops every node on them."""
        self.monitor.guarding = on
        self.supervisor.set_guard_idle(on)

    def _listen_for_other_masters(self) -> None:
        """Before resetting drives this session has not brought up: listen for another
        master (its drives operational, its SYNC, its RPDOs); refuse to reset them
        unless the operator takes over."""
        heard = wait_quiet_listen(self._receivers, self.listen_s)
        if heard is None:
            self.events.add("listen", f"no other master heard in {self.listen_s:g} s")
            return
        if self.take_over:
            self.events.add("take_over", f"another master heard, taken over: {heard}")
            return
        text = (
            f"another master is active: {heard}; not resetting its drives "
            "(take over explicitly to reset them anyway)"
        )
        self.events.add("error", text)
        raise OtherMasterError(text)

    def _foreign_frames(self) -> str | None:
        heard = [
            f"bus {r.port.name}: "
            + ", ".join(f"0x{cid:03X} x{n}" for cid, n in sorted(r.traffic.foreign.items()))
            for r in self._receivers
            if r.traffic.foreign
        ]
        return "; ".join(heard) if heard else None

    def _require_calibration(self, action: str) -> None:
        """Refuse to enable drives without a calibration, unless overridden (sends nothing)."""
        if self.calibration is None and not self.allow_uncalibrated:
            text = (
                f"{action} refused: no calibration (drives are not enabled without one; "
                "the operator may override explicitly)"
            )
            self.events.add("error", text)
            raise SessionStateError(text)

    @deferred_interrupts()
    def enable(self) -> np.ndarray:
        """Every drive to OPERATION_ENABLED in CSP (-> ENABLED); return the actual
        positions (counts).  A drive whose actual position is outside its limits, or
        that does not reach the state, fails the whole enable: every drive then gets a
        quick stop by SDO and NMT pre-operational (-> FAULT).  Refused, before anything is
        sent, without a calibration unless ``allow_uncalibrated``; refused (still READY,
        nothing but statusword reads sent) when a stop cause came since the drives were
        configured or a drive is in FAULT: a fault is reset only on purpose
        (:meth:`reset_fault`).  A stop cause during the enable itself (an EMCY, a
        watch's cause, :meth:`request_stop`) quick-stops every axis as soon as the
        drives are enabled (-> STOPPED) and raises :class:`SafetyStopError`."""
        self._require_calibration("enable")
        self._require("enable", SessionState.READY)
        # a cause from here on (another master's frame, a boot-up, an EMCY, a stop
        # request) is judged once every drive is enabled: every axis quick-stopped
        try:
            if not self.supervisor.set_guard_idle(False):
                raise SessionStateError("enable refused: a quick stop is in progress")
            if self._state is not SessionState.READY:  # a guard stop just before: STOPPED
                raise SessionStateError(f"enable: not allowed in state {self._state.name}")
            foreign = self._foreign_frames()
            if foreign is not None and not self.take_over:
                text = f"enable refused: frames of another master since the reset: {foreign}"
                self.events.add("error", text)
                raise OtherMasterError(text)
            self._refuse_enable_after_causes()
        except HrmError:
            self.supervisor.set_guard_idle(True)
            raise
        t_start = time.monotonic()
        ctl = self.control
        try:
            actual_list = self._parallel(
                "enable",
                lambda link: enable_operation(
                    link,
                    ctl.state_timeout_s,
                    counts_min=self._settings(link).counts_min,
                    counts_max=self._settings(link).counts_max,
                ),
                self._budget_s(ENABLE_SDO_TRANSFERS, ENABLE_TRANSITIONS),
            )
        except HrmError:
            self._abort_enable()
            self.supervisor.set_guard_idle(True)
            self._set_state(SessionState.FAULT)
            raise
        order = {link.motor: k for k, link in enumerate(self._links())}
        act = self.actuation
        actual = np.array([actual_list[order[m]] for m in act.motor_ids], dtype=np.int64)
        self.actual = actual
        self.bringup_s = (self.bringup_s or 0.0) + time.monotonic() - t_start
        self.events.add(
            "enabled", f"every drive OPERATION_ENABLED in CSP ({self.bringup_s:.3f} s bring-up)"
        )
        self.supervisor.arm(actual)  # heartbeats supervised from here on, across streams
        # a boot-up during the enable (up to the arming: from there it is a cause itself)
        for i in np.flatnonzero(self.monitor.rebooted).tolist():
            self.monitor.report(
                StopKind.BOOTUP,
                f"{self.monitor.labels[i]}: node rebooted (boot-up frame) during the enable "
                "(its configuration is lost)",
            )
        self.supervisor.set_guard_idle(True)  # (armed, the idle watchdogs cover it all)
        self._set_state(SessionState.ENABLED)
        # what was reported while the drives were being enabled is judged now, not at
        # the next deadline: any cause quick-stops every axis at once
        self.supervisor.wake(self.supervisor.clock())
        self._raise_if_stopped()
        return actual

    def _refuse_enable_after_causes(self) -> None:
        """Before :meth:`enable` sends anything: refuse (still READY) when a stop cause
        was reported since the drives were configured (an EMCY, a bad frame, a watch's
        cause: :meth:`reset_fault` clears them) or a drive is in FAULT (read by SDO)."""
        rebooted = [self.monitor.labels[i] for i in np.flatnonzero(self.monitor.rebooted)]
        if rebooted:
            more = f" (+{len(rebooted) - 1} more)" if len(rebooted) > 1 else ""
            text = (
                f"enable refused: {rebooted[0]}{more} rebooted since the drives were "
                "configured (its configuration is lost): bring the drives up again"
            )
            self.events.add("error", text)
            raise SessionStateError(text)
        request = self.supervisor.take_stop_request()
        if request is not None:
            text = f"enable refused: {request[1]} before the enable"
            self.events.add("stop_cause", request[1], cause=request[0].value)
            self.events.add("error", text)
            raise SessionStateError(text)
        earlier = self.monitor.drain()
        if earlier:
            more = f" (+{len(earlier) - 1} more)" if len(earlier) > 1 else ""
            text = (
                f"enable refused: {earlier[0].text}{more}, reported since the drives were "
                "configured (reset-fault clears it)"
            )
            for cause in earlier:
                self.events.add("stop_cause", cause.text, cause=cause.kind.value, motor=cause.motor)
            self.events.add("error", text)
            raise SessionStateError(text)
        faulty = (cia402.State402.FAULT, cia402.State402.FAULT_REACTION_ACTIVE)
        states = self._parallel("state check", read_state, self._budget_s(1))
        in_fault = [
            f"{link.label} (statusword 0x{sw:04X})"
            for link, (state, sw) in zip(self._links(), states, strict=True)
            if state in faulty
        ]
        if in_fault:
            text = (
                f"enable refused: {', '.join(in_fault)} in FAULT (a fault is reset only on "
                "purpose: reset-fault)"
            )
            self.events.add("error", text)
            raise SessionStateError(text)

    def bring_up(self) -> np.ndarray:
        """:meth:`configure` then :meth:`enable`; return the actual positions (counts).
        Without a calibration (and no override) refused before the configuration."""
        self._require_calibration("bring-up")
        self.configure()
        return self.enable()

    def _abort_enable(self) -> None:
        """Bring-up failed half-way: quick stop by SDO to every drive (no target is
        written), then NMT pre-operational; failures here are logged, the original
        error is what the caller gets."""
        try:
            self._parallel(
                "abort",
                lambda link: sdo_write(link, cia402.OD_CONTROLWORD, 0, cia402.CW_QUICK_STOP),
                self._budget_s(1),
            )
        except HrmError as exc:
            self.events.add("error", f"quick stop after failed enable: {exc}")
        try:
            self.send_nmt(cia301.NMT_ENTER_PRE_OPERATIONAL)
        except DriverError as exc:
            self.events.add("error", f"NMT pre-operational after failed enable: {exc}")
        self.events.add("quick_stop", "bring-up failed: quick stop (SDO) and NMT pre-operational")

    def _disable_drives(self, what: str) -> None:
        """Controlled disable of every drive by SDO along the CiA 402 transition table
        (:func:`drivers.bringup.disable`): from OPERATION_ENABLED *disable operation*
        then *shutdown*; from QUICK_STOP_ACTIVE or SWITCH_ON_DISABLED (after a quick stop)
        to READY_TO_SWITCH_ON (power stage off), each step confirmed by the statusword.
        No target position is sent.  A drive in FAULT is left there (a fault is reset
        only on purpose).  Raises naming the drives that failed (the others are still
        disabled)."""
        timeout_s = self.control.state_timeout_s

        def disable_one(link: DriveLink) -> None:
            state, sw = read_state(link)
            if state in (cia402.State402.FAULT, cia402.State402.FAULT_REACTION_ACTIVE):
                raise DriverError(
                    f"{link.label}: statusword 0x{sw:04X} ({state.name}): not disabled "
                    "(reset the fault first)"
                )
            disable(link, timeout_s)

        self._parallel(what, disable_one, self._budget_s(1, 3))

    @deferred_interrupts()
    def disable(self) -> None:
        """Disable every drive by SDO (-> READY); from STOPPED too (after a quick stop
        the drives are brought to READY_TO_SWITCH_ON the same way)."""
        self._require("disable", SessionState.ENABLED, SessionState.STOPPED)
        was_enabled = self._state is SessionState.ENABLED
        self.supervisor.disarm()  # with a last check: a cause found now stops every axis
        if was_enabled:
            self._raise_if_stopped()
        self.supervisor.clear_stop_request()  # (asked for while stopped: done by disabling)
        with self._guard_suspended():
            try:
                self._disable_drives("disable")
            except HrmError:
                self._set_state(SessionState.FAULT)
                raise
            self.events.add("disable", "every drive disabled and shut down (READY_TO_SWITCH_ON)")
            self._set_state(SessionState.READY)

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
            self.supervisor.set_guard_idle(self.monitor.guarding)

    def _check_ready(self) -> None:
        """Before the first RPDO of a stream: every drive's statusword (SDO upload of
        0x6041, in parallel, with timeouts) must show OPERATION_ENABLED; else
        :class:`DriverError` naming the motors and their states (nothing is sent)."""
        states = self._parallel("statusword check", read_state, self._budget_s(1))
        bad = [
            f"{link.label} statusword 0x{sw:04X} ({state.name})"
            for link, (state, sw) in zip(self._links(), states, strict=True)
            if state is not cia402.State402.OPERATION_ENABLED
        ]
        if bad:
            text = f"stream refused: not OPERATION_ENABLED: {', '.join(bad)}"
            self.events.add("error", text)
            raise DriverError(text)

    def _refuse_stopped(self) -> None:
        """A stream asked for after a stop (idle or not): name why the box stopped."""
        causes = self.idle_causes or (self.results[-1].causes if self.results else [])
        if not causes:
            return
        failed = f" ({self.stop_error})" if self.stop_error is not None else ""
        where = "while idle" if self.idle_causes else "earlier"
        raise SafetyStopError(
            f"stopped {where}: {causes[0].text}{failed}",
            causes,
            StreamResult(False, 0, causes, {}, np.zeros(self.monitor.n, np.int64)),
        )

    def _raise_if_stopped(self, expect_stop_s: float = 0.0) -> None:
        """While a stream is being prepared the supervisor may stop the box (an EMCY,
        a lost heartbeat): wait for its stop record, then refuse naming the cause.
        ``expect_stop_s``: how long to wait for a stop to begin (a drive found in FAULT
        has sent its EMCY, which may still be on its way)."""
        t_now = time.monotonic()
        begin_by = t_now + expect_stop_s
        while self.supervisor.mode is Mode.ARMED and time.monotonic() < begin_by:
            time.sleep(self.control.period_s)
        deadline = time.monotonic() + STOP_RECORD_WAIT_S
        while self.supervisor.mode is Mode.STOPPING and time.monotonic() < deadline:
            time.sleep(self.control.period_s)
        if self._state in (SessionState.STOPPED, SessionState.FAULT):
            self._refuse_stopped()

    def _stream_timeout_s(self, source: SetpointSource) -> float:
        n = getattr(source, "n_cycles", None)
        cycles = float(n) if isinstance(n, int | np.integer) and n >= 0 else math.inf
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
        self._claim("stream", SessionState.ENABLED, SessionState.STREAMING)
        try:
            targets = self.supervisor.targets
            if targets is None:
                raise SessionStateError("stream: the drives hold no known position")
            source.start(np.asarray(targets, dtype=np.int64).copy(), self.control.period_s)
            try:
                self._check_ready()
            except DriverError:
                self._raise_if_stopped(EMCY_WAIT_S)  # the supervisor stops the box meanwhile
                raise
            self._raise_if_stopped()
        except BaseException:
            self._unclaim_stream()  # nothing was sent
            raise
        unconfigured_before = [r.traffic.unconfigured_counts() for r in self._receivers]
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
        busy = self._unconfigured_traffic(unconfigured_before, result.cycles)
        if busy is not None:
            self.events.add("traffic", busy)
        if raise_on_stop:
            first = result.causes[0]
            more = f" (+{len(result.causes) - 1} more)" if len(result.causes) > 1 else ""
            also = "" if busy is None else f" ({busy})"
            if result.error is not None and first.kind is StopKind.LIMIT:
                raise SafetyStopError(f"stopped: {result.error}{also}", result.causes, result)
            raise SafetyStopError(f"stopped: {first.text}{more}{also}", result.causes, result)
        return result

    def _unconfigured_traffic(self, before: list[dict[int, int]], cycles: int) -> str | None:
        """What a stopped stream's buses carried from nodes not in the configuration, when
        that was at least one frame per control cycle: a device that is not ours loading
        the bus (a babbling node wins arbitration over the drives' heartbeats) is then
        named beside the watchdog it tripped.  None: no such traffic."""
        parts = []
        for r, was in zip(self._receivers, before, strict=True):
            now = r.traffic.unconfigured_counts()
            grown = {cid: n - was.get(cid, 0) for cid, n in now.items() if n > was.get(cid, 0)}
            total = sum(grown.values())
            if total and total >= max(1, cycles):
                top = sorted(grown.items(), key=lambda kv: -kv[1])[:3]
                parts.append(
                    f"bus {r.traffic.bus} carried {total} frame(s) of nodes not in the "
                    "configuration during the stream: "
                    + ", ".join(f"0x{cid:03X} x{n}" for cid, n in top)
                )
        return "; ".join(parts) if parts else None

    def request_stop(
        self, kind: StopKind = StopKind.OPERATOR, text: str = "stop requested"
    ) -> None:
        """Quick stop every axis now, streaming or idle (thread-safe)."""
        self.supervisor.request_stop(kind, text)

    def send_nmt(self, command: int) -> None:
        """Broadcast one NMT command on every bus."""
        for port in self._ports:
            port.send(cia301.make_nmt(command, 0))

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
        if self._state is SessionState.CLOSED:
            raise SessionStateError("finish: the session is closed")
        self._guard(False)  # the drives are disabled and left from here on
        failed: list[str] = []
        try:
            busy = (Mode.STREAMING, Mode.STOPPING)
            if self.supervisor.mode is Mode.STREAMING:  # e.g. from another thread
                self.request_stop(StopKind.OPERATOR, "finish requested while streaming")
            deadline = time.monotonic() + STOP_RECORD_WAIT_S
            while self.supervisor.mode in busy and time.monotonic() < deadline:
                time.sleep(self.control.period_s)  # the stream ends, the stop is confirmed
            try:
                self.supervisor.disarm()  # with a last check (at once if stopping)
            except SupervisorModeError as exc:
                failed.append(str(exc))
            deadline = time.monotonic() + STOP_RECORD_WAIT_S
            while self.supervisor.mode is Mode.STOPPING and time.monotonic() < deadline:
                time.sleep(self.control.period_s)
            if self.enabled or self._state in (SessionState.STOPPED, SessionState.FAULT):
                try:
                    self._disable_drives("disable")
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
            self.supervisor.set_heartbeat(False)
            self._brought_up = False  # another master may take the drives from here on
            self._set_state(SessionState.CONNECTED)
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
        """The run record: configuration, sources, events, timing statistics, logs."""
        return {
            "format": RUN_RECORD_FORMAT,
            "run": self.run_name,
            "written_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "config_source": self.config.source,
            "config": self.config.to_dict(),
            "motor_ids": list(self.actuation.motor_ids),
            "calibration": (
                self.calibration.to_dict()
                if self.calibration is not None
                else UNCALIBRATED
                if self.allow_uncalibrated
                else "none (enable refused)"
            ),
            "bus_loads": [bl.to_dict() for bl in self.loads],
            "bringup_s": self.bringup_s,
            "actual_counts_at_enable": None if self.actual is None else self.actual.tolist(),
            "streams": [r.to_dict() for r in self.results],
            "session_state": self._state.value,
            "bus_traffic": [r.traffic.to_dict() for r in self._receivers],
            "idle_stop_causes": [x.to_dict() for x in self.idle_causes],
            "events": self.events.to_list(),
            "emergencies": [e.describe() for e in self.monitor.emergencies],
            "emergencies_dropped": self.monitor.emergencies_dropped,
            "can_logs": [str(log.path) for log in self._logs],
            "can_log_frames": [log.n_frames for log in self._logs],
            "can_log_lost": [log.n_lost for log in self._logs],
            "can_log_errors": [log.first_error for log in self._logs if log.write_errors],
            **self.record_extra,
        }

    def _close_io(self) -> None:
        latency = getattr(self, "cpu_latency", None)
        if latency is not None:
            latency.close()
        for net in self._networks:
            if net.notifier is not None:
                net.notifier.stop(1.0)
        for log in self._logs:
            log.stop()
        for bus in self._owned:
            try:
                bus.shutdown()
            except (can.CanError, OSError):
                pass
        self._owned = []

    @deferred_interrupts()
    def close(self) -> Path | None:
        """Stop everything (-> CLOSED); write the run record (if logging); return its path.

        The record is written after the logs close, into the space they held for it
        since the session opened (:meth:`TrafficLog._hold_reserve`): a disk the run filled
        up still takes it, and names the logs that it cut short (``can_log_errors``).  A
        record that cannot be written even so raises :class:`DriverError` (one line)."""
        self.supervisor.close()
        self._close_io()
        if not self.supervisor.alive:  # its thread selects on the descriptor
            self.monitor.wake.close()
        self._gc_hold.release()
        self._set_state(SessionState.CLOSED)
        if self.log_dir is None:
            return None
        path = self.log_dir / f"{self.run_name}.json"
        text = json.dumps(_jsonable(self.record()), indent=1, allow_nan=False) + "\n"
        try:
            write_atomic(path, text)
        except OSError as exc:
            why = exc.strerror or exc
            raise DriverError(f"run record {path}: cannot write it ({why})") from None
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

    # ------------------------------------------------------------------ console (issue 11)
    def track_emergencies(self) -> None:
        """Keep each drive's last EMCY (for :meth:`status_snapshot`); idempotent.  The
        console calls it right after opening the session (before any NMT reset)."""
        if getattr(self, "_last_emcy", None) is not None:
            return
        self._last_emcy: list[str | None] = [None] * self.monitor.n
        order = {m: i for i, m in enumerate(self.actuation.motor_ids)}
        for b, net in zip(self.config.buses, self._networks, strict=True):
            for motor, nid in b.nodes.items():
                i = order[motor]

                def keep(_cid: int, data: bytes, _ts: float, i: int = i, nid: int = nid) -> None:
                    try:
                        emcy = cia301.parse_emcy(nid, data)
                    except cia301.FrameError:
                        return  # the monitor reports the bad frame
                    self._last_emcy[i] = emcy.describe()

                net.subscribe(cia301.COB_EMCY + nid, keep)

    def status_snapshot(
        self, tension_N: np.ndarray | None = None, *, read_drives: bool = True
    ) -> Any:
        """A :class:`drivers.status.SessionStatus` of the box now.  While streaming (or
        without ``read_drives``) the node values are the feedback TPDOs' (none before the
        first); otherwise every drive's statusword and actual position are read by SDO
        in parallel (bounded by the SDO timeouts; a drive that does not answer shows
        unknown values).  ``tension_N`` (n, the rope layer's order): the tension board's
        newest sample, if the caller reads one.  Sends nothing but SDO uploads."""
        from drivers.bringup import sdo_read
        from drivers.status import BusStatus, SessionStatus, node_statuses

        mon = self.monitor
        n = mon.n
        order = {m: i for i, m in enumerate(self.actuation.motor_ids)}
        bus_of = [""] * n
        nid_of = [0] * n
        for b in self.config.buses:
            for motor, nid in b.nodes.items():
                bus_of[order[motor]], nid_of[order[motor]] = b.name, nid
        statusword: list[int | None] = [None] * n
        position: list[int | None] = [None] * n
        live = self._state not in (SessionState.CLOSED,)
        by_sdo = read_drives and live and self._state is not SessionState.STREAMING
        if by_sdo:

            def read(link: DriveLink) -> tuple[int, int] | None:
                try:
                    sw = int(sdo_read(link, cia402.OD_STATUSWORD))
                    return sw, int(sdo_read(link, cia402.OD_POSITION_ACTUAL_VALUE))
                except HrmError:
                    return None

            links = self._links()
            values = self._parallel("status", read, self._budget_s(2))
            for link, v in zip(links, values, strict=True):
                if v is not None:
                    i = order[link.motor]
                    statusword[i], position[i] = v
        else:
            for i in range(n):
                if mon.n_tpdo[i] > 0:
                    statusword[i], position[i] = int(mon.statusword[i]), int(mon.position[i])
        held = self.enabled or self._state is SessionState.STOPPED
        targets = self.supervisor.targets if held else None
        emcy = getattr(self, "_last_emcy", None) or [None] * n
        nodes = node_statuses(
            self.actuation.motor_ids, bus_of, nid_of,
            hb_state=mon.hb_state.copy(), hb_time_s=mon.hb_time.copy(), now_s=mon.clock(),
            statusword=statusword, position=position,
            targets=None if targets is None else np.asarray(targets).copy(),
            tension_N=tension_N, last_emcy=list(emcy),
        )  # fmt: skip
        buses = []
        for k, b in enumerate(self.config.buses):
            port = self._ports[k] if k < len(self._ports) else None
            state = None
            if port is not None:
                try:
                    state = port.bus.state.name
                except (NotImplementedError, AttributeError, can.CanError):
                    state = None
            traffic = self._receivers[k].traffic if k < len(self._receivers) else None
            log_ = self._logs[k] if k < len(self._logs) else None
            buses.append(
                BusStatus(
                    name=b.name,
                    bitrate=b.bitrate,
                    load=float(self.loads[k].load),
                    load_limit=float(self.loads[k].limit),
                    frames_sent=0 if port is None else int(port.n_sent),
                    error_frames=0 if traffic is None else int(traffic.error_frames),
                    foreign_frames=0 if traffic is None else int(sum(traffic.foreign.values())),
                    log_frames_lost=0 if log_ is None else int(log_.n_lost),
                    state=state,
                )
            )
        causes = self.idle_causes or (self.results[-1].causes if self.results else [])
        stopped = self._state in (SessionState.STOPPED, SessionState.FAULT)
        cal = (
            f"version {self.calibration.version}" if self.calibration is not None
            else UNCALIBRATED if self.allow_uncalibrated else "none (enable refused)"
        )  # fmt: skip
        return SessionStatus(
            state=self._state.name,
            calibration=cal,
            stop_causes=tuple(x.text for x in causes) if stopped else (),
            nodes=nodes,
            buses=tuple(buses),
            taken_s=mon.clock(),
            by_sdo=by_sdo,
        )

    def actual_positions(self) -> np.ndarray:
        """Every drive's actual position (0x6064, counts, the rope layer's order) read by
        SDO in parallel, bounded by the SDO timeouts (not while streaming: the feedback
        TPDOs have it); a drive that does not answer raises :class:`DriverError`."""
        from drivers.bringup import sdo_read

        self._require(
            "actual positions",
            SessionState.CONNECTED, SessionState.READY, SessionState.ENABLED,
            SessionState.STOPPED, SessionState.FAULT,
        )  # fmt: skip
        order = {m: i for i, m in enumerate(self.actuation.motor_ids)}
        values = self._parallel(
            "actual positions",
            lambda link: int(sdo_read(link, cia402.OD_POSITION_ACTUAL_VALUE)),
            self._budget_s(1),
        )
        out = np.zeros(self.monitor.n, dtype=np.int64)
        for link, v in zip(self._links(), values, strict=True):
            out[order[link.motor]] = v
        return out

    @deferred_interrupts()
    def reset_fault(self) -> list[str]:
        """After a stop: the fault reset of every drive in FAULT (CiA 402 transition 15,
        the statusword confirming it), then every drive disabled to READY_TO_SWITCH_ON
        (power stage off) along the transition table (-> READY: :meth:`enable` may follow).
        From STOPPED, FAULT or READY; returns the labels of the drives that were in FAULT.
        A drive that stays in FAULT (its cause persists) raises :class:`DriverError`
        naming it (-> FAULT); nothing moves (no target is written)."""
        from drivers.bringup import drive_to

        self._require("reset-fault", SessionState.STOPPED, SessionState.FAULT, SessionState.READY)
        deadline = time.monotonic() + STOP_RECORD_WAIT_S
        while self.supervisor.mode is Mode.STOPPING and time.monotonic() < deadline:
            time.sleep(self.control.period_s)  # the stop is confirmed first
        try:
            self.supervisor.disarm()
        except SupervisorModeError as exc:
            self.events.add("error", f"reset-fault: {exc}")
        self.supervisor.clear_stop_request()  # (asked for while stopped: nothing enabled)
        for cause in self.monitor.drain():  # causes of the stop that is being cleared
            self.events.add(
                "cause_cleared", f"{cause.text} (cleared by the fault reset)",
                cause=cause.kind.value, motor=cause.motor,
            )  # fmt: skip
        timeout_s = self.control.state_timeout_s
        faulty = (cia402.State402.FAULT, cia402.State402.FAULT_REACTION_ACTIVE)

        def reset_one(link: DriveLink) -> str | None:
            state, _sw = read_state(link)
            drive_to(link, cia402.State402.READY_TO_SWITCH_ON, timeout_s)
            return link.label if state in faulty else None

        with self._guard_suspended():
            try:
                labels = self._parallel("fault reset", reset_one, self._budget_s(2, 4))
            except HrmError:
                self._set_state(SessionState.FAULT)
                raise
            reset = [x for x in labels if x is not None]
            self.events.add(
                "fault_reset",
                f"fault reset of {len(reset)} drive(s)"
                + (f" ({', '.join(reset)})" if reset else "")
                + "; every drive disabled (READY_TO_SWITCH_ON)",
            )
            self.idle_causes = []
            self.stop_error = None
            self._set_state(SessionState.READY)
        return reset


def _jsonable(value: Any) -> Any:
    """Replace non-finite floats (not JSON) by None, recursively.

    >>> _jsonable({"a": [1.0, float("nan")], "b": np.int64(3)})
    {'a': [1.0, None], 'b': 3}
    """
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value
