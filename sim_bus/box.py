"""The simulated manipulator box: a drive simulator for every node of a bus configuration.

:class:`SimBox` opens (or is given) one python-can bus per configured bus,
creates a :class:`~sim_bus.drive.DriveSim` for every rope motor on it, and runs
a thread that receives frames, routes them by COB-ID to the drives listening to
them and ticks the drives' timers every ``tick_s``: one thread for every bus that has
a descriptor to wait on (``hrm_ipc``, SocketCAN, udp_multicast), else one per bus (two
threads of one interpreter answering two SYNCs at once only queue for its lock, and on a
two-core machine they take the core the host's control loop needs).  The
drives' actual positions make the arm (:class:`~sim_bus.arm.SimArm`): true
joint angles and joint centres, rope tensions, all of the arm's truth
(:class:`~sim_bus.truth.TrueArm`, ``truth=``; default the robot description itself).

Frames the box sent itself and gets back (udp_multicast echoes them) are
ignored: no drive listens to another drive's TPDO, SDO response, heartbeat or
EMCY COB-IDs.

Fault injection (thread-safe, from tests or ``hrm sim``): :meth:`stop_heartbeat`,
:meth:`fault_drive`, :meth:`jam`, :meth:`snap_rope`, :meth:`shift_encoder`,
:meth:`drop_frames`, :meth:`delay_frames`, :meth:`set_bus_off`.  The box's tension-sensor
board (:meth:`start_tension_board`, :attr:`tension_board`) serves the arm's rope tensions
on a pseudo-terminal until the box stops, and so does its laser tracker
(:meth:`start_tracker`, :attr:`tracker`: the true end point in the tracker's frame;
:meth:`tracker_lose_target`).  :meth:`set_straight_fixture` puts the arm in its straight
zero fixture (the rope geometry held straight, each rope's tension its own).  On an
``hrm_sim`` wire the frame faults act on the wire (both directions, the host sees a
bus-off as failing sends); on other interfaces the box applies them to the frames it sends and
(for drops) receives, and a bus-off box neither sends nor listens.

>>> import can
>>> from drivers.config import load_box_config
>>> cfg = load_box_config(None).with_bus_kwargs(
...     [{"interface": "hrm_sim", "channel": "doc-box-0"},
...      {"interface": "hrm_sim", "channel": "doc-box-1"}])
>>> host = can.Bus(interface="hrm_sim", channel="doc-box-0")
>>> with SimBox(cfg) as box:
...     boots = sorted({m.arbitration_id for m in iter(lambda: host.recv(0.05), None)})
>>> len(boots), hex(boots[0]), hex(boots[-1])          # 18 boot-ups on bus can0
(18, '0x701', '0x712')
>>> host.shutdown()
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import math
import platform
import select
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import can
import numpy as np

import drivers.protocol.cia301 as cia301
from drivers.config import BoxConfig
from drivers.protocol.cia402 import EMCY_FOLLOWING_ERROR, OD_POSITION_ACTUAL_VALUE
from drivers.realtime import GcHold
from hrm_ctrl.errors import SimError
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from sim_bus.arm import ArmState, SimArm
from sim_bus.drive import DriveParams, DriveSim
from sim_bus.physics import Physics
from sim_bus.tension_board import TensionBoard
from sim_bus.tracker import Tracker
from sim_bus.truth import TrueArm, drive_serials
from sim_bus.wire import FrameMatch, SimWireBus

log = logging.getLogger("sim_bus.box")

#: with the arm's physics, how often the tension board's refresh steps the arm (s): as
#: often as the arm without physics is refreshed (an equilibrium costs about what the rope
#: inverse does, a median of 1-2.6 ms of CPU on the loaded machine; every 10 ms that alone
#: would take 0.1-0.26 of a core, beyond the box's budget with its drives)
PHYSICS_PERIOD_S = 0.05

#: Receive buffer asked for on socket-based buses (udp_multicast, socketcan): a Python
#: process that stalls for 50-100 ms on a loaded machine must not lose frames in the kernel.
RECEIVE_BUFFER_BYTES = 8 * 1024 * 1024
#: Linux's SO_RCVBUFFORCE (a buffer beyond ``net.core.rmem_max``, with CAP_NET_ADMIN): the
#: socket module does not define it; 33 in the kernel's generic socket.h, which x86, arm and
#: riscv use (alpha, mips, parisc and sparc number it differently: not used there)
SO_RCVBUFFORCE: int | None = getattr(
    socket,
    "SO_RCVBUFFORCE",
    33
    if sys.platform.startswith("linux")
    and platform.machine() in ("x86_64", "i686", "aarch64", "armv7l", "riscv64")
    else None,
)


def enlarge_receive_buffer(bus: can.BusABC, size_bytes: int = RECEIVE_BUFFER_BYTES) -> int | None:
    """Raise the kernel receive buffer of a socket-based python-can bus; returns the new
    size in bytes, or None when the bus has no socket (virtual, hrm_sim) or refuses.

    udp_multicast delivers every frame as one datagram, and the default buffer (~200 kB)
    holds only a few cycles of a 36-drive bus: a stalled reader loses frames silently.
    """
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if sock is None:
        sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return None
    for opt in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
        if opt is None:
            continue
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, size_bytes)
            return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
        except OSError:
            continue
    return None


class _BoxBus:
    """One bus of the box: its python-can bus, drives, routes and box-level faults."""

    def __init__(self, name: str, bus: can.BusABC, owned: bool) -> None:
        self.name = name
        self.bus = bus
        self.owned = owned
        self.drives: list[DriveSim] = []
        self.routes: dict[int, list[DriveSim]] = {}
        self.drop_rules: list[list[Any]] = []  # [match, remaining]
        self.delay_rules: list[list[Any]] = []  # [match, remaining, delay_s]
        self.delayed: list[tuple[float, int, can.Message]] = []
        self.bus_off = False
        self.seq = 0
        self.frames_in = 0
        self.frames_out = 0
        self.trace: list[tuple[float, list[int]]] | None = None
        self.cpu_s = 0.0
        self.timers_dirty = True
        self.next_tick = -math.inf  # the drives' timers are due (box clock)

    def rebuild_routes(self) -> None:
        routes: dict[int, list[DriveSim]] = {}
        for d in self.drives:
            for cob in d.cob_ids():
                routes.setdefault(cob, []).append(d)
        self.routes = routes

    @property
    def wire(self) -> Any:
        return self.bus.wire if isinstance(self.bus, SimWireBus) else None


def _fileno(bus: can.BusABC) -> int | None:
    """The bus's descriptor to wait on (None: it has none, e.g. python-can's virtual)."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, can.CanError, OSError, ValueError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def _take(rules: list[list[Any]], msg: can.Message) -> list[Any] | None:
    for rule in rules:
        match, remaining = rule[0], rule[1]
        if remaining is not None and remaining <= 0:
            continue
        if match is None or match(msg):
            if remaining is not None:
                rule[1] = remaining - 1
            return rule
    return None


class SimBox:
    """The simulated box (see the module docstring); a context manager.

    Args:
        config: buses and nodes: the bus configuration the host uses too
            (:func:`drivers.config.load_box_config`); its ``[control]`` settings are
            the host's and are not used here.
        buses: already open buses, one per configured bus (else opened from config).
        actuation: the rope layer (default: the default robot's).
        max_accel_counts_per_s2 / quick_stop_decel_counts_per_s2: drive ramps; the
            velocity limit is the rope layer's ``max_rate_counts_per_s``.
        tick_s: longest sleep of a bus thread between drive timer checks (the threads wake
            at each drive's next heartbeat / consumer deadline anyway).
        clock: monotonic clock (s).
        truth: how the simulated arm differs from its description (``None``: it does not;
            :class:`sim_bus.truth.TrueArm`), also the tracker's frame and noise.
        seed: the seed of the box's noise (tension sensor, tracker).
        physics: the arm's physics (:class:`sim_bus.physics.Physics`; ``None``, the
            default: none, the arm goes where its ropes' lengths put it).  With physics the
            tension board's refresh steps the arm every :data:`PHYSICS_PERIOD_S`.
    """

    def __init__(
        self,
        config: BoxConfig,
        buses: Sequence[can.BusABC] | None = None,
        *,
        actuation: Actuation | None = None,
        initial_counts: Sequence[int] | np.ndarray | None = None,
        max_accel_counts_per_s2: float = 2.0e7,
        quick_stop_decel_counts_per_s2: float = 4.0e7,
        tension_noise_N: float = 0.05,
        snap_drift_rad_per_s: float = 0.2,
        tick_s: float = 0.05,
        clock: Callable[[], float] = time.monotonic,
        truth: TrueArm | None = None,
        seed: int = 0,
        physics: Physics | None = None,
    ) -> None:
        self.config = config
        self.actuation = actuation if actuation is not None else load_actuation(default_robot())
        self.clock = clock
        self.tick_s = float(tick_s)
        ids = self.actuation.motor_ids
        unknown = [m for m in config.motor_ids if m not in ids]
        if unknown:
            raise SimError(f"{config.source}: rope motor(s) {unknown} unknown to the rope layer")
        if buses is not None and len(buses) != len(config.buses):
            raise SimError(f"{config.source}: {len(config.buses)} buses, got {len(buses)}")
        init = (
            np.zeros(len(ids), dtype=np.int64)
            if initial_counts is None
            else np.asarray(initial_counts, dtype=np.int64)
        )
        if init.shape != (len(ids),):
            raise SimError(f"initial_counts must have {len(ids)} values, got {init.shape}")
        self._initial = init
        self._accel = float(max_accel_counts_per_s2)
        self._qs_decel = float(quick_stop_decel_counts_per_s2)
        self.arm = SimArm(
            self.actuation,
            truth=truth,
            noise_N=tension_noise_N,
            snap_drift_rad_per_s=snap_drift_rad_per_s,
            seed=seed,
            physics=physics,
        )
        self.truth: TrueArm = self.arm.truth
        self._seed = int(seed)
        self._given = list(buses) if buses is not None else None
        self._buses: list[_BoxBus] = []
        self.drives: dict[str, DriveSim] = {}
        self._motor_order: list[tuple[int, DriveSim]] = []
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._gc_hold = GcHold()  # held while the threads run: see start()
        self.events: list[str] = []
        self._cpu_closed_s = 0.0
        self._tension_cache: tuple[float, np.ndarray, tuple[int, ...], bool] | None = None
        self.tension_board: TensionBoard | None = None
        self.tracker: Tracker | None = None
        self._encoder_shift: dict[str, int] = {}

    # ------------------------------------------------------------ life cycle
    def start(self) -> SimBox:
        """Open the buses, power on every drive (boot-up frames) and start the threads."""
        if self._threads:
            return self
        now = self.clock()
        ids = self.actuation.motor_ids
        vmax = self.actuation.max_rate_counts_per_s
        serials = drive_serials(self.truth)  # another truth: another box (0x1018)
        try:
            for k, bcfg in enumerate(self.config.buses):
                if self._given is not None:
                    bus, owned = self._given[k], False
                else:
                    try:
                        bus, owned = can.Bus(**bcfg.bus_kwargs()), True
                    except (can.CanError, OSError, ValueError, ImportError) as exc:
                        raise SimError(
                            f"{self.config.source}: cannot open bus {bcfg.name} ({exc})"
                        ) from None
                enlarge_receive_buffer(bus)
                self._buses.append(_BoxBus(bcfg.name, bus, owned))
            with self._lock:
                for bb, bcfg in zip(self._buses, self.config.buses, strict=True):
                    for motor, node in bcfg.nodes.items():
                        i = ids.index(motor)
                        params = DriveParams(
                            max_velocity_counts_per_s=float(vmax[i]),
                            max_accel_counts_per_s2=self._accel,
                            quick_stop_decel_counts_per_s2=self._qs_decel,
                            initial_position_counts=int(self._initial[i]),
                            serial_number=serials[motor],
                        )
                        d = DriveSim(
                            node,
                            self._sender(bb),
                            params,
                            now=now,
                            eds=self.config.drives.device_file(motor),  # box.toml [drives]
                        )
                        d.motor_id = motor  # type: ignore[attr-defined]
                        bb.drives.append(d)
                        self.drives[motor] = d
                    bb.rebuild_routes()
                self._motor_order = [(ids.index(m), d) for m, d in self.drives.items()]
        except BaseException:
            self._close_buses()
            raise
        fds = [_fileno(bb.bus) for bb in self._buses]
        if self._buses and all(fd is not None for fd in fds):
            groups = [self._buses]  # one thread waits on every bus
        else:
            groups = [[bb] for bb in self._buses]
        # a full collection of the heap the imports left pauses every thread for tens of
        # ms (measured: 40 ms in ``hrm sim``), past the host's feedback watchdog (3 cycles)
        self._gc_hold.acquire()
        for group in groups:
            name = "simbox:" + "+".join(bb.name for bb in group)
            t = threading.Thread(target=self._run_buses, args=(group,), name=name)
            t.daemon = True
            self._threads.append(t)
            t.start()
        return self

    def start_tension_board(self, rate_hz: float = 100.0) -> TensionBoard:
        """Start the box's tension-sensor board (once): :meth:`tension_N` in frames on a
        pseudo-terminal (:attr:`TensionBoard.port`), until the box stops."""
        if self.tension_board is None:
            self.tension_board = TensionBoard(self.tension_N, rate_hz).start()
        return self.tension_board

    def start_tracker(self) -> Tracker:
        """Start the box's laser tracker (once): the true end point O_13 in the tracker's
        frame (the truth's), with its noise, answering requests on a pseudo-terminal
        (:attr:`Tracker.port`, protocol ``drivers.protocol.tracker``), until the box stops."""
        if self.tracker is None:
            t = self.truth
            self.tracker = Tracker(
                self.end_point_mm,
                t.tracker_rotation,
                t.tracker_translation_mm,
                noise_mm=t.tracker_noise_mm,
                seed=self._seed + 1,
                fiducials_mm=self.actuation.robot.base_fiducials,  # the base is as drawn
            ).start()
        return self.tracker

    def end_point_mm(self) -> np.ndarray:
        """The true end point O_13 now (base frame, mm)."""
        return self.arm_state().centres[-1]

    def tracker_lose_target(self, lost: bool = True) -> None:
        """Fault injection: the tracker loses (or finds again) its target."""
        if self.tracker is None:
            raise SimError("the box's tracker is not started (start_tracker)")
        self.tracker.lose_target(lost)
        self._fault_event(f"fault: tracker target {'lost' if lost else 'found'}")

    def set_straight_fixture(self, on: bool) -> None:
        """The arm lies in (or leaves) its zero fixture: while on, every joint's rope geometry
        is held straight whatever the motors do (the links at their joint offsets) and each
        rope's tension follows from its own length (``sim_bus.arm``); the tension board
        shows it at once."""
        self.arm.set_fixture(on)
        self._tension_cache = None
        self._fault_event(f"fixture: arm {'held straight' if on else 'free'}")

    def stop(self) -> None:
        """Stop the threads and close the buses the box opened (timeout 2 s each)."""
        if self.tension_board is not None:
            self.tension_board.stop()
            self.tension_board = None
        if self.tracker is not None:
            self.tracker.stop()
            self.tracker = None
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        self._gc_hold.release()
        self._close_buses()

    @property
    def cpu_s(self) -> float:
        """CPU time (s) the box's bus threads used so far."""
        return self._cpu_closed_s + sum(bb.cpu_s for bb in self._buses)

    def _close_buses(self) -> None:
        self._cpu_closed_s += sum(bb.cpu_s for bb in self._buses)
        for bb in self._buses:
            if bb.owned:
                bb.bus.shutdown()
        self._buses.clear()

    def __enter__(self) -> SimBox:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------ engine
    def _sender(self, bb: _BoxBus) -> Callable[[can.Message], None]:
        def send(msg: can.Message) -> None:
            if bb.bus_off:
                raise can.CanOperationError(f"box bus {bb.name}: bus off")
            if bb.wire is None:
                if _take(bb.drop_rules, msg) is not None:
                    return
                rule = _take(bb.delay_rules, msg)
                if rule is not None:
                    bb.seq += 1
                    heapq.heappush(bb.delayed, (self.clock() + rule[2], bb.seq, msg))
                    return
            bb.bus.send(msg)
            bb.frames_out += 1

        return send

    def _run_buses(self, group: list[_BoxBus]) -> None:
        """The thread of ``group``: one bus waited on with ``recv`` (its timeout up to the
        next drive timer), several with one ``select`` on their descriptors."""
        fds = {_fileno(bb.bus): bb for bb in group} if len(group) > 1 else {}
        cpu0 = time.thread_time()
        while not self._stop.is_set():
            now = self.clock()
            wake = min(min(bb.next_tick, bb.delayed[0][0] if bb.delayed else math.inf)
                       for bb in group)  # fmt: skip
            timeout = min(max(0.0, wake - now), 0.05)
            if fds:
                try:
                    ready = [fds[fd] for fd in select.select(list(fds), [], [], timeout)[0]]
                except (OSError, ValueError) as exc:
                    self._event(f"box buses: wait failed ({exc})")
                    if self._stop.wait(0.05):
                        break
                    continue
                for bb in group:
                    self._serve(bb, bb in ready, 0.0)
            else:
                self._serve(group[0], True, timeout)
            t = time.thread_time()
            share = (t - cpu0) / len(group)
            for bb in group:
                bb.cpu_s += share
            cpu0 = t

    def _serve(self, bb: _BoxBus, receive: bool, timeout: float) -> None:
        """One round of a bus: what it delivers (waiting at most ``timeout``), the drives'
        timers when due, delayed frames whose time came."""
        batch: list[can.Message] = []
        if receive:
            try:
                msg = bb.bus.recv(timeout=timeout)
                while msg is not None:  # drain what is queued: one lock round per burst
                    batch.append(msg)
                    msg = bb.bus.recv(timeout=0.0) if len(batch) < 256 else None
            except (can.CanError, OSError, ValueError) as exc:
                self._event(f"bus {bb.name}: receive failed ({exc})")
                if self._stop.wait(0.05):
                    return
        now = self.clock()
        if (
            not batch
            and now < bb.next_tick
            and not bb.timers_dirty
            and not (bb.delayed and bb.delayed[0][0] <= now)
        ):
            return
        # one datagram per peer for what this burst makes the drives send, on a bus
        # that batches (hrm_ipc); a no-op on the others
        with self._lock, getattr(bb.bus, "batch", contextlib.nullcontext)():
            now = self.clock()
            synced = False
            if not bb.bus_off:
                for msg in batch:
                    self._dispatch(bb, msg, now)
                    synced = synced or msg.arbitration_id == cia301.COB_SYNC
            if now >= bb.next_tick or bb.timers_dirty or synced:
                # after a SYNC every heartbeat due before the next one goes out now, with
                # the TPDOs: one datagram per bus and cycle (each drive's heartbeat at
                # most one period early, on its own grid; CiA 301 asks no phase of it)
                early = self.config.control.period_s if synced else 0.0
                for d in bb.drives:
                    d.tick(now, early)
                # sleep until the earliest drive timer (heartbeat due, consumer timeout,
                # quick-stop motion), at most tick_s: no fixed-rate polling of 36 drives
                soonest = min((d.next_deadline() for d in bb.drives), default=math.inf)
                bb.next_tick = min(max(soonest, now + 1e-4), now + self.tick_s)
                bb.timers_dirty = False
            while bb.delayed and bb.delayed[0][0] <= now and not bb.bus_off:
                _t, _s, late = heapq.heappop(bb.delayed)
                try:
                    bb.bus.send(late)
                except can.CanError:
                    pass

    def _dispatch(self, bb: _BoxBus, msg: can.Message, now: float) -> None:
        targets = bb.routes.get(msg.arbitration_id)
        if not targets:
            return
        if bb.wire is None and bb.drop_rules and _take(bb.drop_rules, msg) is not None:
            return
        bb.frames_in += 1
        for d in targets:
            try:
                d.handle(msg, now)
            except Exception as exc:  # a drive must never take the box down
                self._event(f"drive {bb.name}/{d.node_id}: error handling {msg} ({exc!r})")
        cob = msg.arbitration_id
        if cob == cia301.COB_SYNC and bb.trace is not None:
            bb.trace.append((now, [d.position_counts for d in bb.drives]))
        if cob == cia301.COB_NMT or cia301.COB_SDO_RX < cob <= cia301.COB_SDO_RX + 0x7F:
            bb.rebuild_routes()
            bb.timers_dirty = True
        elif cob > cia301.COB_NMT_ERROR_CONTROL:  # a heartbeat may start a consumer's watch
            bb.timers_dirty = True

    def _timers_changed(self) -> None:
        for bb in self._buses:
            bb.timers_dirty = True

    def _fault_event(self, text: str) -> None:
        self._event(text, logging.INFO)

    def _event(self, text: str, level: int = logging.WARNING) -> None:
        log.log(level, text)
        with self._lock:
            self.events.append(text)
            if len(self.events) > 1000:
                del self.events[:500]

    # ------------------------------------------------------------ state
    def counts(self) -> np.ndarray:
        """Actual motor positions (n,) in the rope layer's motor order (motors without a
        simulated drive stay where they started)."""
        out = self._initial.copy()
        with self._lock:
            for i, d in self._motor_order:
                out[i] = d.position_counts
        return out

    def arm_state(self) -> ArmState:
        """The arm now: true joint angles and centres, tensions."""
        return self.arm.state(self.counts(), self.clock())

    def record_trace(self, enabled: bool = True) -> None:
        """Start (clearing) or stop recording every drive's position at each SYNC."""
        with self._lock:
            for bb in self._buses:
                bb.trace = [] if enabled else None

    def trace(self) -> tuple[np.ndarray, np.ndarray]:
        """Recorded SYNC times (k,) (bus 0's clock reading) and actual motor positions
        (k, n) after each SYNC, in the rope layer's motor order; k is the number of
        SYNCs every bus has seen."""
        ids = self.actuation.motor_ids
        with self._lock:
            traces = [(bb, list(bb.trace or [])) for bb in self._buses]
        k = min((len(tr) for _bb, tr in traces), default=0)
        counts = np.tile(self._initial, (k, 1))
        times = np.array([t for t, _p in traces[0][1][:k]]) if traces else np.zeros(0)
        for bb, tr in traces:
            cols = [ids.index(d.motor_id) for d in bb.drives]  # type: ignore[attr-defined]
            if k:
                counts[:, cols] = np.array([p for _t, p in tr[:k]], dtype=np.int64)
        return times, counts

    def tension_N(self, max_age_s: float = 0.05) -> np.ndarray:
        """Rope tensions (n,) for the tension board: the arm state is recomputed at most
        every ``max_age_s`` (the rope inverse costs ~1-2 ms; at 100 Hz that would take a
        large share of the box's CPU), and at once after a rope snaps; with the arm's
        physics at most every :data:`PHYSICS_PERIOD_S` (each state continues the last), a
        snapped rope reading 0 at once and the rest at the next refresh (the frames do not
        wait for the equilibrium's new solve)."""
        now = self.clock()
        cached = self._tension_cache
        snapped, fixture = self.arm.snapped, self.arm.fixture
        if self.arm.physics is not None:
            max_age_s = min(max_age_s, PHYSICS_PERIOD_S)
            if cached is not None and cached[2] != snapped and cached[3] == fixture:
                tension = cached[1].copy()
                tension[list(snapped)] = 0.0
                cached = (cached[0], tension, snapped, fixture)
                self._tension_cache = cached
        if (
            cached is None
            or now - cached[0] > max_age_s
            or cached[2] != snapped
            or cached[3] != fixture
        ):
            state = self.arm_state()
            cached = (now, state.tension_N, snapped, fixture)
            self._tension_cache = cached
        return cached[1]

    def statuswords(self) -> dict[str, int]:
        with self._lock:
            return {m: d.statusword for m, d in self.drives.items()}

    def bus_names(self) -> list[str]:
        return [bb.name for bb in self._buses]

    def _drive(self, motor: str) -> DriveSim:
        try:
            return self.drives[motor]
        except KeyError:
            raise SimError(f"no simulated drive for rope motor '{motor}'") from None

    def _bus(self, name: str) -> _BoxBus:
        for bb in self._buses:
            if bb.name == name:
                return bb
        raise SimError(f"no bus '{name}' in the box (have {self.bus_names()})")

    # ------------------------------------------------------------ faults
    def stop_heartbeat(self, motor: str, stopped: bool = True) -> None:
        """The drive of ``motor`` stops (or resumes) producing its heartbeat."""
        with self._lock:
            self._drive(motor).heartbeat_enabled = not stopped
            self._timers_changed()
        self._fault_event(f"fault: heartbeat of {motor} {'stopped' if stopped else 'resumed'}")

    def fault_drive(self, motor: str, code: int = EMCY_FOLLOWING_ERROR) -> None:
        """The drive faults now (following error by default) and sends its EMCY."""
        with self._lock:
            d = self._drive(motor)
            if code == EMCY_FOLLOWING_ERROR:
                d.following_error = True
            d.inject_fault(code, self.clock())
            self._timers_changed()
        self._fault_event(f"fault: drive {motor} faulted with 0x{code:04X}")

    def jam(self, motor: str, jammed: bool = True) -> None:
        """The motor stalls: it faults by following error once its target moves away."""
        with self._lock:
            self._drive(motor).jammed = jammed
        self._fault_event(f"fault: motor {motor} {'jammed' if jammed else 'free'}")

    def snap_rope(self, motor: str) -> None:
        """The rope of ``motor`` breaks: tension 0, its joint drifts."""
        self.arm.snap(motor, self.clock())
        self._fault_event(f"fault: rope {motor} snapped")

    def shift_encoder(self, motor: str, counts: int) -> None:
        """The position ``motor``'s drive reports (TPDO, 0x6064) is off by ``counts`` from
        where its motor is (an encoder slipped on its shaft): the motor, its rope and the
        arm stay where commanded, the feedback no longer fits the other ropes.  0 ends it."""
        with self._lock:
            d = self._drive(motor)
            shift = int(counts)
            if shift:
                self._encoder_shift[motor] = shift
                true_value = type(d).live_value.__get__(d)

                def live_value(key: Any, _true: Any = true_value, _motor: str = motor) -> Any:
                    value = _true(key)
                    if key == (OD_POSITION_ACTUAL_VALUE, 0):
                        return int(value) + self._encoder_shift.get(_motor, 0)
                    return value

                d.live_value = live_value  # type: ignore[method-assign]
            else:
                self._encoder_shift.pop(motor, None)
                d.__dict__.pop("live_value", None)
        self._fault_event(f"fault: encoder of {motor} shifted by {shift} counts")

    def drop_frames(self, bus: str, match: FrameMatch | None = None, count: int | None = 1) -> None:
        """Lose ``count`` frames (``None``: all) matching ``match`` on bus ``bus``."""
        bb = self._bus(bus)
        if bb.wire is not None:
            bb.wire.drop(match, count)
        else:
            with self._lock:
                bb.drop_rules.append([match, count])
        self._fault_event(f"fault: drop {count if count is not None else 'all'} frame(s) on {bus}")

    def delay_frames(
        self, bus: str, delay_s: float, match: FrameMatch | None = None, count: int | None = 1
    ) -> None:
        """Delay ``count`` frames matching ``match`` on bus ``bus`` by ``delay_s``."""
        if not delay_s >= 0:
            raise SimError(f"delay must be >= 0 s, got {delay_s!r}")
        bb = self._bus(bus)
        if bb.wire is not None:
            bb.wire.delay(delay_s, match, count)
        else:
            with self._lock:
                bb.delay_rules.append([match, count, float(delay_s)])
        self._fault_event(f"fault: delay frames on {bus} by {delay_s * 1000:.1f} ms")

    def set_bus_off(self, bus: str, off: bool = True) -> None:
        """Bus ``bus`` goes off (nothing passes) or comes back."""
        bb = self._bus(bus)
        if bb.wire is not None:
            bb.wire.set_bus_off(off)
        with self._lock:
            bb.bus_off = off
            if off:
                bb.delayed.clear()
        self._fault_event(f"fault: bus {bus} {'off' if off else 'on'}")

    def reset_faults(self) -> None:
        """Undo every injected fault: frame faults, bus-off, heartbeats, jams, snapped
        ropes, shifted encoders (the drives keep their state; a host brings them up
        again)."""
        self.clear_frame_faults()
        for bb in list(self._buses):
            if bb.bus_off:
                self.set_bus_off(bb.name, False)
        with self._lock:
            for d in self.drives.values():
                d.heartbeat_enabled = True
                d.jammed = False
                d.__dict__.pop("live_value", None)
            self._encoder_shift.clear()
            self._timers_changed()
        self.arm.repair()
        self._fault_event("fault: every fault reset")

    def clear_frame_faults(self) -> None:
        with self._lock:
            for bb in self._buses:
                bb.drop_rules.clear()
                bb.delay_rules.clear()
                bb.delayed.clear()  # frames still held back are lost, not sent late
                if bb.wire is not None:
                    bb.wire.clear_faults()
