"""The manipulator box as the host drives it: every bus, every CiA 402 drive.

:class:`DriveBox` opens the buses of a :class:`~drivers.config.BoxConfig`
(or takes buses already opened), logs each bus's traffic to a python-can log,
and offers the run sequence:

1. :meth:`DriveBox.bring_up`: refuse when a bus is over its load budget; start
   the host heartbeat; NMT reset and wait for every node's boot-up (the error
   lists the missing ones); SDO configuration of every drive in parallel (PDO
   mappings, heartbeat times, software limits 0x607D from the rope layer,
   interpolation period = control period, CSP); NMT start; the CiA 402 state
   machine to OPERATION_ENABLED with a statusword check at every transition.
2. :meth:`DriveBox.stream`: the cyclic scheduler plays a setpoint source;
   any watchdog stops every axis (quick stop) within one cycle.
3. :meth:`DriveBox.finish`: disable operation, NMT pre-operational, stop the
   host heartbeat.
4. :meth:`DriveBox.close`: stop receive threads, close the logs, write the run
   record (JSON, atomically) beside them.

The drivers never know what is at the other end of the wire (drives or a
simulator): everything goes through python-can buses.
"""

from __future__ import annotations

import concurrent.futures
import datetime as dt
import functools
import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
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
    command,
    configure_drive,
    enable_operation,
    read_state,
    sdo_write,
)
from drivers.bus import BusPort, BusSendError, TrafficLog, is_host_frame
from drivers.busload import BusLoad, check_bus_load
from drivers.config import BoxConfig
from drivers.protocol import cia402 as c
from drivers.safety.limits import LimitChecker
from drivers.safety.monitor import NodeMonitor, StopCause
from drivers.scheduler import BusLayout, CyclicScheduler, EventLog, StreamResult
from drivers.sources import SetpointSource
from hrm_ctrl.errors import DriverError, HrmError
from hrm_ctrl.files import write_atomic

RUN_RECORD_FORMAT = "hrm-run/1"
# Upper bounds of the parallel SDO work, in SDO transfers / CiA 402 transitions per drive
# (each transfer may take (1 + retries) SDO timeouts; each transition the state timeout).
CONFIG_SDO_TRANSFERS = 48
ENABLE_TRANSITIONS = 7
ENABLE_SDO_TRANSFERS = 12
PARALLEL_MARGIN_S = 1.0
log = logging.getLogger("drivers.session")


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


class _RxRouter(can.Listener):
    """Receive path of one bus: TPDOs go straight to the monitor (every cycle, every
    node: the hot path), everything else to canopen (SDO, heartbeat, EMCY)."""

    def __init__(
        self,
        network: canopen.Network,
        on_error: Callable[[str, str], None],
        host_node_id: int = c.HOST_HEARTBEAT_NODE_ID,
    ) -> None:
        self.network = network
        self.on_error = on_error
        self.host_node_id = host_node_id
        self.fast: dict[int, Callable[[bytes], None]] = {}

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        handler = self.fast.get(msg.arbitration_id)
        if handler is not None:
            handler(msg.data)
            return
        if is_host_frame(msg.arbitration_id, self.host_node_id):
            return  # our own frame echoed back (udp_multicast): nothing for canopen
        try:
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)
        except Exception as exc:  # must not stop the receive thread: report it instead
            log.exception("canopen callback failed on 0x%03X", msg.arbitration_id)
            self.on_error("receive", f"frame 0x{msg.arbitration_id:03X} not handled ({exc!r})")


class HeartbeatProducer:
    """The host's heartbeat (NMT state operational) on every bus, from its own thread,
    phase-locked to a monotonic clock.  Send failures are reported to the monitor."""

    def __init__(
        self,
        ports: Sequence[BusPort],
        node_id: int,
        period_s: float,
        on_error: Callable[[str], None],
    ) -> None:
        self.ports = list(ports)
        self.msg_args = (node_id, c.NMT_STATE_OPERATIONAL)
        self.period_s = period_s
        self.on_error = on_error
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="host-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t_next = time.monotonic()
        while not self._stop.is_set():
            for port in self.ports:
                try:
                    port.send(c.make_heartbeat(*self.msg_args))
                except BusSendError as exc:
                    self.on_error(str(exc))
            t_next += self.period_s
            self._stop.wait(max(0.0, t_next - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None


class IdleGuard:
    """Supervision while the drives are enabled but no stream runs (after bring-up,
    between streams): heartbeats (timeout and NMT state), EMCYs and boot-ups are checked
    every control period; any cause → quick stop of every drive and ``on_stop(causes)``."""

    def __init__(
        self,
        monitor: NodeMonitor,
        period_s: float,
        quick_stop: Callable[[list[StopCause]], None],
    ) -> None:
        self.monitor = monitor
        self.period_s = period_s
        self.quick_stop = quick_stop
        self.error: HrmError | None = None  # the idle quick stop itself failed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fired = False

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._fired = False
        self.error = None
        self.monitor.supervising = True
        if self.monitor.hb_armed_at is None:
            self.monitor.hb_armed_at = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="idle-guard", daemon=True)
        self._thread.start()

    def _check(self) -> bool:
        """One evaluation of the idle watchdogs; on any cause quick stop (True)."""
        mon = self.monitor
        causes = mon.check(time.monotonic(), -1, mon.hb_armed_at)
        if not causes:
            return False
        self._fired = True
        mon.supervising = False
        try:
            self.quick_stop(causes)
        except HrmError as exc:  # reported to the next stream / finish
            log.error("idle quick stop failed: %s", exc)
            self.error = exc
        return True

    def _run(self) -> None:
        mon = self.monitor
        while not self._stop.is_set():
            mon.wake.wait(self.period_s)
            if self._stop.is_set():
                return
            mon.wake.clear()
            if self._check():
                return

    def stop(self) -> None:
        """Stop supervising (before a stream takes over, or at the end), with a last
        check of everything queued so far: a cause found now still quick-stops."""
        self._stop.set()
        self.monitor.wake.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout=5.0)
            self._thread = None
            if not self._fired:
                self._check()
        self.monitor.wake.clear()
        self.monitor.supervising = False


class DriveBox:
    """Every bus and drive of the box; see the module docstring for the sequence."""

    def __init__(
        self,
        config: BoxConfig,
        actuation: LimitChecker,
        log_dir: str | Path | None = None,
        log_suffix: str = ".blf",
        run_name: str | None = None,
        buses: Sequence[can.BusABC] | None = None,
    ) -> None:
        config.check_motors(actuation.motor_ids)
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
        self.enabled = False

        n = len(actuation.motor_ids)
        self._ports: list[BusPort] = []
        self._logs: list[TrafficLog] = []
        self._owned: list[can.BusABC] = []
        self._networks: list[_PortNetwork] = []
        self._layouts: list[BusLayout] = []
        self.links: list[DriveLink | None] = [None] * n
        labels = [""] * n
        order = {m: i for i, m in enumerate(actuation.motor_ids)}
        for b in config.buses:
            for motor, nid in b.nodes.items():
                labels[order[motor]] = f"{motor} (bus {b.name} node {nid})"
        self.monitor = NodeMonitor(
            labels, self.control.missing_tpdo_cycles, self.control.heartbeat_timeout_ms / 1000.0
        )
        try:
            self._open(buses)
        except BaseException:
            self._close_io()
            raise
        self.heartbeat = HeartbeatProducer(
            self._ports,
            self.control.host_node_id,
            self.control.host_heartbeat_ms / 1000.0,
            self._heartbeat_error,
        )
        self.scheduler = CyclicScheduler(
            self._layouts, self.monitor, actuation, self.control.period_s, self.events
        )
        self.scheduler.realtime_priority = self.control.realtime_priority
        self.guard = IdleGuard(self.monitor, self.control.period_s, self._idle_stop)
        self.idle_causes: list[StopCause] = []
        self.events.add(
            "open",
            f"{len(config.buses)} bus(es), {n} drives, {self.control.rate_hz:g} Hz",
            bus_loads=[bl.to_dict() for bl in self.loads],
        )

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
                    host_node_id=self.control.host_node_id,
                )
                self._logs.append(log)
            port = BusPort(b.name, bus, log)
            self._ports.append(port)
            net = _PortNetwork(port)
            router = _RxRouter(net, self.monitor.report, self.control.host_node_id)
            listeners: list[can.Listener] = [router]
            if log is not None:
                listeners.append(log)
            idx = np.array([order[m] for m in b.nodes], dtype=np.int64)
            for motor, nid in b.nodes.items():
                i = order[motor]
                node = canopen.RemoteNode(nid, od)
                net.add_node(node)
                node.sdo.RESPONSE_TIMEOUT = self.control.sdo_timeout_s
                self.links[i] = DriveLink(node, b.name, motor)
                self._subscribe(net, i, nid)
                router.fast[c.COB_TPDO1 + nid] = functools.partial(self.monitor.on_tpdo, i)
            net.notifier = can.Notifier(bus, listeners, 0.1)
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
            c.COB_NMT_ERROR_CONTROL + nid, lambda _cid, data, _ts: mon.on_heartbeat(i, data)
        )
        net.subscribe(c.COB_EMCY + nid, lambda _cid, data, _ts: mon.on_emcy(i, nid, data))

    def _heartbeat_error(self, text: str) -> None:
        self.events.add("error", f"host heartbeat: {text}")
        self.monitor.report("send", f"host heartbeat not sent ({text})")

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

    def send_nmt(self, command: int) -> None:
        """Broadcast one NMT command on every bus."""
        for port in self._ports:
            port.send(c.make_nmt(command, 0))

    # ------------------------------------------------------------------ sequence
    def bring_up(self) -> np.ndarray:
        """Reset, configure and enable every drive; return actual positions (counts)."""
        t_start = time.monotonic()
        ctl = self.control
        self.guard.stop()  # (a last check: a cause found now quick-stops every drive)
        if self.enabled:
            # A second bring-up: the drives are enabled; never reset them like that.
            try:
                self._disable_drives("disable before reset")
            except HrmError:
                self._abort_enable()
                self.enabled = False
                raise
            self.events.add("disable", "every drive disabled (SWITCHED_ON) before the reset")
        self.idle_causes = []
        self.enabled = False
        self.monitor.hb_armed_at = None
        self.heartbeat.start()
        self.monitor.reset_boot()
        self.send_nmt(c.NMT_RESET_NODE)
        self.events.add("nmt", "NMT reset node sent on every bus")
        if not self.monitor.boot_event.wait(ctl.bootup_timeout_s):
            missing = self.monitor.missing_boot()
            raise BootupError(
                f"no boot-up within {ctl.bootup_timeout_s:g} s from {len(missing)} node(s): "
                + ", ".join(missing)
            )
        self.events.add("bootup", f"every node booted ({time.monotonic() - t_start:.3f} s)")
        act = self.actuation

        def settings(link: DriveLink) -> DriveSettings:
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

        self._parallel(
            "configuration",
            lambda link: configure_drive(link, settings(link)),
            self._budget_s(CONFIG_SDO_TRANSFERS),
        )
        self.events.add("configured", "every drive configured by SDO (CSP, PDOs, limits)")
        self.send_nmt(c.NMT_START_REMOTE_NODE)
        self.events.add("nmt", "NMT start remote node sent on every bus")
        try:
            actual_list = self._parallel(
                "enable",
                lambda link: enable_operation(
                    link,
                    ctl.state_timeout_s,
                    counts_min=settings(link).counts_min,
                    counts_max=settings(link).counts_max,
                ),
                self._budget_s(ENABLE_SDO_TRANSFERS, ENABLE_TRANSITIONS),
            )
        except HrmError:
            self._abort_enable()
            raise
        order = {link.motor: k for k, link in enumerate(self._links())}
        actual = np.array([actual_list[order[m]] for m in act.motor_ids], dtype=np.int64)
        self.actual = actual
        self.enabled = True
        self.bringup_s = time.monotonic() - t_start
        self.events.add(
            "enabled", f"every drive OPERATION_ENABLED in CSP ({self.bringup_s:.3f} s bring-up)"
        )
        for stale in self.monitor.drain():
            # Reported during bring-up (e.g. the EMCY of a fault that was reset); every
            # drive has since shown OPERATION_ENABLED.
            self.events.add("during_bringup", stale.text, cause=stale.kind, motor=stale.motor)
        self.monitor.hb_armed_at = time.monotonic()  # kept across streams and idle periods
        self.guard.start()
        return actual

    def _abort_enable(self) -> None:
        """Bring-up failed half-way: quick stop by SDO to every drive (no target is
        written), then NMT pre-operational; failures here are logged, the original
        error is what the caller gets."""
        try:
            self._parallel(
                "abort",
                lambda link: sdo_write(link, c.OD_CONTROLWORD, 0, c.CW_QUICK_STOP),
                self._budget_s(1),
            )
        except HrmError as exc:
            self.events.add("error", f"quick stop after failed enable: {exc}")
        try:
            self.send_nmt(c.NMT_ENTER_PRE_OPERATIONAL)
        except DriverError as exc:
            self.events.add("error", f"NMT pre-operational after failed enable: {exc}")
        self.events.add("quick_stop", "bring-up failed: quick stop (SDO) and NMT pre-operational")

    def _disable_drives(self, what: str) -> None:
        """Controlled disable of every drive by SDO: *disable operation* (confirmed
        SWITCHED_ON by the statusword), then *shutdown* (confirmed READY_TO_SWITCH_ON:
        power stage off).  No target position is sent.  Raises naming the drives that
        failed (the others are still disabled)."""
        timeout_s = self.control.state_timeout_s

        def disable(link: DriveLink) -> None:
            command(link, c.CW_DISABLE_OPERATION, c.State402.SWITCHED_ON, timeout_s)
            command(link, c.CW_SHUTDOWN, c.State402.READY_TO_SWITCH_ON, timeout_s)

        self._parallel(what, disable, self._budget_s(0, 2))

    def _idle_stop(self, causes: list[StopCause]) -> None:
        """Called by the idle guard: quick stop every drive, remember why; raises
        :class:`DriverError` naming what failed (after trying every bus / drive)."""
        for cause in causes:
            self.events.add("stop_cause", cause.text, cause=cause.kind, motor=cause.motor)
        hold = self.results[-1].last_targets if self.results else self.actual
        failed: list[str] = []
        try:
            if hold is not None and self.results:
                sent = self.scheduler.send_controlword(c.CW_QUICK_STOP, hold)  # checked targets
                failed = [x.text for x in sent]
            else:
                self._parallel(
                    "quick stop",
                    lambda link: sdo_write(link, c.OD_CONTROLWORD, 0, c.CW_QUICK_STOP),
                    self._budget_s(1),
                )
        except HrmError as exc:
            failed.append(str(exc))
        self.idle_causes = list(causes) + [
            StopCause("send", f"idle quick stop failed: {t}", None, time.monotonic())
            for t in failed
        ]
        self.enabled = False
        if failed:
            text = "quick stop while idle failed: " + "; ".join(failed)
            self.events.add("error", text)
            raise DriverError(text)
        self.events.add("quick_stop", "quick stop sent to every drive while idle")

    def _check_ready(self) -> None:
        """Before the first RPDO of a stream: every drive's statusword (SDO upload of
        0x6041, in parallel, with timeouts) must show OPERATION_ENABLED; else
        :class:`DriverError` naming the motors and their states (nothing is sent)."""
        states = self._parallel("statusword check", read_state, self._budget_s(1))
        bad = [
            f"{link.label} statusword 0x{sw:04X} ({state.name})"
            for link, (state, sw) in zip(self._links(), states, strict=True)
            if state is not c.State402.OPERATION_ENABLED
        ]
        if bad:
            text = f"stream refused: not OPERATION_ENABLED: {', '.join(bad)}"
            self.events.add("error", text)
            raise DriverError(text)

    def stream(self, source: SetpointSource, raise_on_stop: bool = True) -> StreamResult:
        """Play a setpoint source; on any stop cause every axis gets a quick stop and
        :class:`SafetyStopError` is raised (or the result returned with ``raise_on_stop=False``)."""
        self.guard.stop()  # with a last check: a cause queued now stops every drive
        if self.idle_causes:
            causes = self.idle_causes
            failed = f" ({self.guard.error})" if self.guard.error is not None else ""
            raise SafetyStopError(
                f"stopped while idle: {causes[0].text}{failed}",
                causes,
                StreamResult(False, 0, causes, {}, np.zeros(self.monitor.n, np.int64)),
            )
        if not self.enabled or self.actual is None:
            raise DriverError("stream: drives are not enabled (bring_up first)")
        start = self.actual
        if self.results:
            start = self.results[-1].last_targets
        try:
            result = self.scheduler.stream(source, start, ready_check=self._check_ready)
        except BaseException:
            if self.scheduler.crash_stopped:
                self.enabled = False  # the scheduler quick-stopped every drive
            else:
                self.guard.start()  # the source refused to start: nothing was sent
            raise
        self.results.append(result)
        if not result.causes:
            self.guard.start()
        if result.causes:
            self.enabled = False
            if raise_on_stop:
                first = result.causes[0].text
                more = f" (+{len(result.causes) - 1} more)" if len(result.causes) > 1 else ""
                if result.error is not None and result.causes[0].kind == "limit":
                    raise SafetyStopError(f"stopped: {result.error}", result.causes, result)
                raise SafetyStopError(f"stopped: {first}{more}", result.causes, result)
        return result

    def request_stop(self) -> None:
        """Ask a running stream to stop (quick stop) at the next cycle (thread-safe)."""
        self.scheduler.stop_request.set()
        self.monitor.wake.set()

    def finish(self) -> None:
        """Orderly end: *disable operation* then *shutdown* by SDO, each confirmed by the
        statusword (power stage off, READY_TO_SWITCH_ON; no target position is sent),
        then NMT pre-operational, then the host heartbeat off (the drives no longer
        need it).  Whatever fails, the rest is still done; then :class:`DriverError`
        names what failed (a drive left enabled stops itself when the host heartbeat
        ends, and on NMT pre-operational)."""
        self.guard.stop()  # with a last check
        failed: list[str] = []
        try:
            if self.enabled:
                try:
                    self._disable_drives("disable")
                    self.events.add(
                        "disable", "every drive disabled and shut down (READY_TO_SWITCH_ON)"
                    )
                except HrmError as exc:
                    failed.append(str(exc))
            try:
                self.send_nmt(c.NMT_ENTER_PRE_OPERATIONAL)
                self.events.add("nmt", "NMT enter pre-operational sent on every bus")
            except HrmError as exc:
                failed.append(f"NMT pre-operational: {exc}")
        finally:
            self.enabled = False
            self.heartbeat.stop()
        if self.guard.error is not None:
            failed.append(str(self.guard.error))
            self.guard.error = None
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
            "bus_loads": [bl.to_dict() for bl in self.loads],
            "bringup_s": self.bringup_s,
            "actual_counts_at_enable": None if self.actual is None else self.actual.tolist(),
            "streams": [r.to_dict() for r in self.results],
            "idle_stop_causes": [x.to_dict() for x in self.idle_causes],
            "events": self.events.to_list(),
            "emergencies": [e.describe() for e in self.monitor.emergencies],
            "can_logs": [str(log.path) for log in self._logs],
            "can_log_frames": [log.n_frames for log in self._logs],
            "can_log_errors": [log.first_error for log in self._logs if log.write_errors],
            **self.record_extra,
        }

    def _close_io(self) -> None:
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

    def close(self) -> Path | None:
        """Stop everything; write the run record (if logging); return its path."""
        self.guard.stop()
        self.heartbeat.stop()
        self._close_io()
        if self.log_dir is None:
            return None
        path = self.log_dir / f"{self.run_name}.json"
        write_atomic(path, json.dumps(_jsonable(self.record()), indent=1, allow_nan=False) + "\n")
        self.record_path = path
        return path

    def __enter__(self) -> DriveBox:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        try:
            if self.enabled:
                try:
                    self.finish()
                except HrmError as err:
                    if exc_type is None:
                        raise
                    # Keep the error in flight; this one goes into the run record.
                    self.events.add("error", f"finish after {exc_type.__name__}: {err}")
        finally:
            self.close()


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
