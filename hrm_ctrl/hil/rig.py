"""The HIL rig without pytest: box configurations, the simulated box (in this process or as
its own process, ``hrm sim --control``), and the host side (a :class:`drivers.session.DriveSession`
with the tension watch, as ``hrm run`` wires it).

Every box configuration written here runs the production watchdogs: the ``[control]`` table
is the drivers' default ``box.toml``'s, key for key (``missing_tpdo_cycles`` 3,
``heartbeat_timeout_ms`` 350), unless the caller passes overrides, and the tension watch
runs at the ``[tension]`` defaults (stale after 0.1 s); the plugin overrides them only for
a box in the test process (:data:`INPROCESS_CONTROL`).

>>> sorted(production_control())[:3]
['bootup_timeout_s', 'bus_load_limit', 'cpu_wakeup_latency_us']
>>> production_control()["missing_tpdo_cycles"], production_control()["heartbeat_timeout_ms"]
(3, 350)
>>> [k.value for k in BusKind]
['virtual', 'ipc', 'udp_multicast', 'socketcan']
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import socket
import threading
import time
import tomllib
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any, Protocol

from hrm_ctrl.errors import SimError

# the box in its own process: the runtime layer's (re-exported for the HIL and its tests)
from hrm_ctrl.runtime.process_box import REPLY_TIMEOUT_S, BoxProcess
from sim_bus.faults import has_control_character
from sim_bus.in_process import IN_PROCESS_MISSING_TPDO_CYCLES, IN_PROCESS_TENSION_STALE_S


class BusKind(StrEnum):
    """The buses a HIL run can use (``--hrm-bus``)."""

    VIRTUAL = "virtual"  # python-can virtual: box and host in one process
    IPC = "ipc"  # the cross-process bus (python-can interface ``hrm_ipc``)
    UDP_MULTICAST = "udp_multicast"  # IPv4 multicast, hop_limit 0, a port per bus
    SOCKETCAN = "socketcan"  # the kernel's vcan0/vcan1


class BoxMode(StrEnum):
    """Where the simulated box runs (``--hrm-box``)."""

    PROCESS = "process"  # ``hrm sim --control``, its own process
    INPROCESS = "inprocess"  # a ``sim_bus.box.SimBox`` in the test process


IPC_INTERFACE = "hrm_ipc"
MAX_BUSES = 8  # node maps (buses) of one HIL box at most
HIL_CHANNEL_PREFIX = "hrm-hil-"  # the channels of HIL boxes: hrm-hil-<tag>-<bus>
#: the host's listen for another master before its first reset: the box takes over on
#: purpose (``take_over=True``), so what it hears only names an event
HOST_LISTEN_S = 0.2
#: how long the host's tension watch waits for the board's first frame after it starts
HOST_TENSION_GRACE_S = 0.5
#: how long after a stream the drives get to leave OPERATION_ENABLED (quick-stop ramps;
#: a drive cut off from the host stops on its heartbeat consumer, 350 ms)
SETTLE_TIMEOUT_S = 2.5


#: With the box in the test process (``--hrm-box inprocess``) its 36 simulated drives and
#: its tension board share the host's interpreter: the plugin then runs the tolerances
#: ``hrm run --sim`` runs with (``sim_bus/in_process.py``: TPDO tolerance 25 cycles,
#: tension staleness 500 ms), says so in a warning, and the run record keeps them.  A box
#: in its own process runs the production settings.
INPROCESS_CONTROL: dict[str, Any] = {"missing_tpdo_cycles": IN_PROCESS_MISSING_TPDO_CYCLES}
INPROCESS_TENSION_STALE_S = IN_PROCESS_TENSION_STALE_S


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def production_control() -> dict[str, Any]:
    """The ``[control]`` table of the drivers' default ``box.toml`` (production settings)."""
    from drivers import default_box_path

    return dict(tomllib.loads(default_box_path().read_text())["control"])


def default_nodes() -> tuple[dict[str, int], ...]:
    """The node map of every bus of the drivers' default ``box.toml`` (36 motors, 2 buses)."""
    from drivers import default_box_path

    doc = tomllib.loads(default_box_path().read_text())
    return tuple(dict(b["nodes"]) for b in doc["buses"].values())


def vcan_pair_available(n: int = 2) -> bool:
    """Whether the kernel has vcan0 .. vcan{n-1}."""
    return all(Path(f"/sys/class/net/vcan{k}").exists() for k in range(n))


def ipc_available() -> bool:
    """Whether python-can has the cross-process bus (``hrm_ipc``): registered and its
    module importable."""
    from importlib.metadata import entry_points

    for e in entry_points(group="can.interface"):
        if e.name == IPC_INTERFACE:
            try:
                e.load()
            except (ImportError, AttributeError):
                return False
            return True
    return False


def unavailable(kind: BusKind, mode: BoxMode, n_buses: int = 2) -> str | None:
    """Why ``kind`` cannot carry a HIL run with the box ``mode`` here (None: it can)."""
    if kind is BusKind.VIRTUAL and mode is BoxMode.PROCESS:
        return (
            "--hrm-bus virtual: python-can's virtual bus is private to one process "
            "(use --hrm-box inprocess)"
        )
    if kind is BusKind.SOCKETCAN and not vcan_pair_available(n_buses):
        return (
            "SocketCAN: no vcan0/vcan1 on this kernel "
            "(modprobe vcan; ip link add dev vcan0 type vcan; ...)"
        )
    if kind is BusKind.IPC and not ipc_available():
        return f"the cross-process bus: python-can has no interface '{IPC_INTERFACE}' here"
    return None


_TOML_KEY = re.compile(r"[A-Za-z0-9_-]{1,64}")


def check_nodes(nodes: object) -> tuple[dict[str, int], ...]:
    """``hrm_box_nodes``: a sequence of node maps (rope motor -> node id), one per bus;
    anything else a one-line :class:`SimError` naming the entry.

    >>> check_nodes([{"j01r0": 1}])
    ({'j01r0': 1},)
    >>> check_nodes(("j01r0",))
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.SimError: hrm_box_nodes[0]: a node map (motor -> node id), got 'j01r0'
    """
    if isinstance(nodes, str | bytes | Mapping) or not isinstance(nodes, Sequence):
        raise SimError(f"hrm_box_nodes: a sequence of node maps, one per bus, got {nodes!r:.80}")
    if not 1 <= len(nodes) <= MAX_BUSES:
        raise SimError(f"hrm_box_nodes: 1..{MAX_BUSES} buses, got {len(nodes)}")
    out = []
    for k, bus_nodes in enumerate(nodes):
        if not isinstance(bus_nodes, Mapping):
            raise SimError(
                f"hrm_box_nodes[{k}]: a node map (motor -> node id), got {bus_nodes!r:.80}"
            )
        for motor, node in bus_nodes.items():
            if not isinstance(motor, str) or not _TOML_KEY.fullmatch(motor):
                raise SimError(f"hrm_box_nodes[{k}]: motor name {motor!r:.80} is not a name")
            if isinstance(node, bool) or not isinstance(node, int):
                raise SimError(f"hrm_box_nodes[{k}][{motor!r}]: node id must be an integer")
        out.append(dict(bus_nodes))
    return tuple(out)


def check_control(control: object) -> dict[str, Any]:
    """``hrm_control``: ``[control]`` keys to numbers, booleans or strings (checked
    against their ranges when the configuration loads); anything else a one-line
    :class:`SimError` naming the key.

    >>> check_control({"missing_tpdo_cycles": 5})
    {'missing_tpdo_cycles': 5}
    >>> check_control({"heartbeat_timeout_ms": float("nan")})
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.SimError: hrm_control['heartbeat_timeout_ms']: nan is not a finite number
    """
    if not isinstance(control, Mapping):
        raise SimError(f"hrm_control: a mapping of [control] keys, got {control!r:.80}")
    for key, value in control.items():
        if not isinstance(key, str) or not _TOML_KEY.fullmatch(key):
            raise SimError(f"hrm_control: key {key!r:.80} is not a [control] key name")
        if isinstance(value, float) and not math.isfinite(value):
            raise SimError(f"hrm_control[{key!r}]: {value!r} is not a finite number")
        if isinstance(value, str) and has_control_character(value):
            raise SimError(f"hrm_control[{key!r}]: control character in {value!r:.80}")
        if not isinstance(value, bool | int | float | str):
            raise SimError(f"hrm_control[{key!r}]: a number, boolean or string, got {value!r:.80}")
    return dict(control)


def box_toml(
    kind: BusKind,
    nodes: Sequence[Mapping[str, int]],
    control: Mapping[str, Any] | None = None,
) -> str:
    """A bus configuration (drivers' format) on ``kind``: production ``[control]`` (with
    ``control`` overriding keys), one bus per node map, channels of their own.

    >>> text = box_toml(BusKind.VIRTUAL, [{"j01r0": 1}])
    >>> "missing_tpdo_cycles = 3" in text, 'interface = "virtual"' in text
    (True, True)
    """
    nodes = check_nodes(nodes)
    table = {**production_control(), **check_control(control or {})}
    lines = ["[control]"] + [f"{k} = {json.dumps(v)}" for k, v in table.items()]
    tag = uuid.uuid4().hex[:8]
    group = os.getpid() % 200 + 20
    for k, bus_nodes in enumerate(nodes):
        name = f"can{k}"
        lines += [f"[buses.{name}]"]
        if kind is BusKind.UDP_MULTICAST:
            lines += [
                'interface = "udp_multicast"',
                f'channel = "239.75.{group}.{k + 1}"',  # a group per bus; a port per bus too
                "bitrate = 1000000",
                f"[buses.{name}.options]",
                "hop_limit = 0",  # nothing leaves the host
                f"port = {_free_udp_port()}",
            ]
        elif kind is BusKind.SOCKETCAN:
            lines += ['interface = "socketcan"', f'channel = "vcan{k}"', "bitrate = 1000000"]
        elif kind is BusKind.IPC:
            lines += [
                f'interface = "{IPC_INTERFACE}"',
                f'channel = "{HIL_CHANNEL_PREFIX}{tag}-{name}"',
                "bitrate = 1000000",
            ]
        else:
            lines += ['interface = "virtual"', f'channel = "{HIL_CHANNEL_PREFIX}{tag}-{name}"']
            lines += ["bitrate = 1000000"]
        lines.append(f"[buses.{name}.nodes]")
        lines += [f"{m} = {n}" for m, n in bus_nodes.items()]
    return "\n".join(lines) + "\n"


def write_box_toml(
    path: Path,
    kind: BusKind,
    nodes: Sequence[Mapping[str, int]],
    control: Mapping[str, Any] | None = None,
) -> Path:
    """Write :func:`box_toml` to ``path`` and check it loads (``BusConfigError`` if not)."""
    from drivers.config import load_box_config

    text = box_toml(kind, nodes, control)
    if kind is BusKind.IPC:  # the channel folders of earlier runs killed before their end
        from sim_bus.ipc import remove_stale_channels

        remove_stale_channels(HIL_CHANNEL_PREFIX)
    path.write_text(text)
    load_box_config(path)
    return path


@dataclass(frozen=True)
class ArmSnapshot:
    """The true arm at one moment (the box's ``state``): motor counts (rope layer's order),
    joint angles (rad), joint centres O1..O13 (mm), rope tensions (N), each drive's statusword."""

    t_s: float
    counts: tuple[int, ...]
    alpha: tuple[float, ...]
    theta: tuple[float, ...]
    centres_mm: tuple[tuple[float, float, float], ...]
    tension_N: tuple[float, ...]
    statuswords: dict[str, int] = field(default_factory=dict)
    snapped: tuple[str, ...] = ()
    fixture: bool = False

    @classmethod
    def from_json(cls, obj: Mapping[str, Any]) -> ArmSnapshot:
        return cls(
            t_s=float(obj["t_s"]),
            counts=tuple(int(c) for c in obj["counts"]),
            alpha=tuple(float(a) for a in obj["alpha"]),
            theta=tuple(float(a) for a in obj["theta"]),
            centres_mm=tuple((float(x), float(y), float(z)) for x, y, z in obj["centres"]),
            tension_N=tuple(float(t) for t in obj["tension_N"]),
            statuswords={str(k): int(v) for k, v in obj["statuswords"].items()},
            snapped=tuple(obj.get("snapped", ())),
            fixture=bool(obj.get("fixture", False)),
        )

    def enabled(self) -> list[str]:
        """The motors whose drive is OPERATION_ENABLED."""
        import drivers.protocol.cia402 as cia

        return [
            m
            for m, sw in self.statuswords.items()
            if cia.decode_state(sw) is cia.State402.OPERATION_ENABLED
        ]


class HilBox(Protocol):
    """What the fixtures need of a simulated box, in this process or its own."""

    config_path: Path
    ready: dict[str, Any]

    def command(
        self, text: str, reply: str, timeout_s: float = REPLY_TIMEOUT_S
    ) -> dict[str, Any]: ...

    def close(self) -> None: ...


def fault(box: HilBox, spec: str) -> dict[str, Any]:
    """Apply the fault ``spec`` (``sim_bus.faults`` grammar) now; the box's reply."""
    return box.command(f"fault {spec}", "fault")


def arm_state(box: HilBox) -> ArmSnapshot:
    """The true arm state now."""
    return ArmSnapshot.from_json(box.command("state", "state"))


class InProcessBox:
    """A :class:`sim_bus.box.SimBox` with its tension board in this process, answering the
    same control commands as ``hrm sim --control`` (``sim_bus.runner``'s own handler)."""

    def __init__(self, config_path: Path) -> None:
        from drivers.config import load_box_config
        from sim_bus.box import SimBox

        self.config_path = config_path
        self._lock = threading.Lock()
        cfg = load_box_config(config_path)
        self.box = SimBox(cfg).start()
        try:
            self.board = self.box.start_tension_board()
        except BaseException:
            self.box.stop()
            raise
        self._t0 = time.monotonic()
        self.ready = {
            "event": "ready",
            "tension_port": self.board.port,
            "buses": [{"name": b.name, "interface": b.interface} for b in cfg.buses],
            "motors": len(cfg.motor_ids),
            "motor_ids": list(self.box.actuation.motor_ids),
        }

    def command(self, text: str, reply: str, timeout_s: float = REPLY_TIMEOUT_S) -> dict[str, Any]:
        """Run one control command (``timeout_s``: unused, the call is direct)."""
        from sim_bus.runner import control_command

        if has_control_character(text):  # as a box process: one line
            raise SimError(f"in-process box {self.config_path}: control character in {text!r}")
        out = io.StringIO()
        with self._lock:
            control_command(text.strip(), self.box, self.board, out, time.monotonic() - self._t0)
        for line in out.getvalue().splitlines():
            obj = json.loads(line)
            if obj.get("event") == "error":
                raise SimError(f"in-process box {self.config_path}: {obj['error']}")
            if obj.get("event") == reply:
                return obj
        raise SimError(f"in-process box {self.config_path}: '{text}' gave no '{reply}'")

    def close(self) -> None:
        self.box.stop()


def start_box(config_path: Path, mode: BoxMode, rt_priority: int = 0) -> HilBox:
    """The simulated box on ``config_path``'s buses, started and ready (``rt_priority``:
    a box process's threads under ``SCHED_FIFO``; a box in this process runs as the
    process does)."""
    if mode is BoxMode.PROCESS:
        return BoxProcess(config_path, rt_priority=rt_priority)
    return InProcessBox(config_path)


@dataclass
class HostRun:
    """What the host saw of one stream, and the box's statuswords once it settled."""

    result: Any  # drivers.cycle.StreamResult | None
    error: Any  # drivers.session.SafetyStopError | None
    statuswords_after: dict[str, int]
    tension_fault: str | None
    fault_sent_s: float | None = None  # time.monotonic() just before the fault command
    fault_applied_s: float | None = None  # ... and when its reply came back

    def stopped_before_fault(self) -> bool:
        """Whether the host stopped before the fault was sent (a stop of its own: the run
        tested nothing of the fault)."""
        if self.error is None:
            return False
        first = min((c.time_s for c in self.error.causes), default=None)
        return self.fault_sent_s is None or (first is not None and first < self.fault_sent_s)

    def describe(self) -> str:
        """One line: how the stream ended and its timing (SYNC lateness, late cycles)."""
        res = self.result if self.result is not None else getattr(self.error, "result", None)
        if res is None:
            return f"no stream result ({self.error})"
        st = res.stats
        how = "completed" if res.completed else "stopped: " + "; ".join(c.text for c in res.causes)
        ms = {k: 1000 * st[k] for k in ("lateness_p99_s", "lateness_max_s") if k in st}
        return (
            f"{how} after {res.cycles} cycles; SYNC lateness p99 "
            f"{ms.get('lateness_p99_s', float('nan')):.1f} ms, max "
            f"{ms.get('lateness_max_s', float('nan')):.1f} ms, late cycles "
            f"{st.get('late_cycles')}, skipped slots {st.get('skipped_slots')}, missing "
            f"TPDOs {st.get('missing_feedback_node_cycles')} node-cycles"
        )


class HilHost:
    """The host stack on a box: a :class:`drivers.session.DriveSession` (taking the drives
    over, uncalibrated: the simulated arm is its description) with the tension reader and
    watch at the ``[tension]`` defaults, brought up.  :meth:`play` streams a source (with a
    fault injected during it); :meth:`close` ends the session and returns its run record."""

    def __init__(
        self,
        box: HilBox,
        log_dir: Path,
        *,
        actuation: Any = None,
        listen_s: float = HOST_LISTEN_S,
        bring_up: bool = True,
        tension_stale_s: float | None = None,
    ) -> None:
        from drivers.config import TensionConfig, load_box_config
        from drivers.realtime import process_settings
        from drivers.safety.subset import ActuationSubset
        from hrm_ctrl.model import default_robot
        from hrm_ctrl.ropes.actuation import load_actuation

        self.box = box
        self.config = load_box_config(box.config_path)
        self.actuation = actuation if actuation is not None else load_actuation(default_robot())
        ids = self.config.motor_ids
        self.limits = (
            self.actuation
            if set(ids) == set(self.actuation.motor_ids)
            else ActuationSubset(self.actuation, ids)
        )
        self.tension = TensionConfig(port=str(box.ready["tension_port"]))  # the defaults
        if tension_stale_s is not None:
            self.tension = replace(self.tension, stale_s=float(tension_stale_s))
        self.record: dict[str, Any] | None = None
        self._stack = contextlib.ExitStack()
        # every thread of the host (the session's, the tension reader and watch) on the
        # CPUs the box process leaves free (BoxProcess); the caller's thread gets its own back
        cpus = getattr(box, "host_cpus", None)
        with process_settings(switch_interval_s=None, cpus=cpus):
            self._open(log_dir, listen_s, bring_up)

    def _open(self, log_dir: Path, listen_s: float, bring_up: bool) -> None:
        from hrm_ctrl.runtime.box import SessionOptions, WatchOptions, open_box
        from sim_bus.box import enlarge_receive_buffer

        options = SessionOptions(
            log_dir=log_dir,
            take_over=True,  # one box serves many tests: the next host takes over
            allow_uncalibrated=True,  # the simulated arm is its description
            listen_s=listen_s,
        )
        # the tension watch alone (no rope watch), on the whole arm's board
        watches = WatchOptions(ropes=False, grace_s=HOST_TENSION_GRACE_S, actuation=self.actuation)
        config = replace(self.config, tension=self.tension)
        self.opened = self._stack.enter_context(
            open_box(config, self.limits, options, watches=watches, bring_up=False)
        )
        try:
            self.session = self.opened.session
            for port in self.session._ports:  # see sim_bus.box.enlarge_receive_buffer
                enlarge_receive_buffer(port.bus)
            self.watch = self.opened.watches.watches["tension"]
            if bring_up:
                self.opened.bring_up()
        except BaseException:
            self._stack.close()
            raise

    def play(
        self, source: Any, fault_spec: str | None = None, fault_after_s: float = 0.4
    ) -> HostRun:
        """Stream ``source``; with ``fault_spec``, inject it ``fault_after_s`` into the stream.
        Then wait (at most ``SETTLE_TIMEOUT_S``) until no drive is OPERATION_ENABLED."""
        from drivers.session import SafetyStopError

        times: dict[str, float] = {}
        failed: list[BaseException] = []

        def inject() -> None:
            times["sent"] = time.monotonic()
            try:
                fault(self.box, fault_spec or "")
            except Exception as exc:  # raised below, in the caller's thread
                failed.append(exc)
            times["applied"] = time.monotonic()

        timer = None
        if fault_spec is not None:
            timer = threading.Timer(fault_after_s, inject)
            timer.start()
        result = err = None
        try:
            result = self.session.stream(source)
        except SafetyStopError as exc:
            err = exc
        finally:
            if timer is not None:
                timer.join(REPLY_TIMEOUT_S)
        if failed:
            raise SimError(f"fault {fault_spec!r} could not be injected: {failed[0]}")
        deadline = time.monotonic() + SETTLE_TIMEOUT_S
        while True:
            state = arm_state(self.box)
            if time.monotonic() > deadline or not state.enabled():
                break
            time.sleep(0.05)
        return HostRun(
            result,
            err,
            state.statuswords,
            self.watch.fault,
            times.get("sent"),
            times.get("applied"),
        )

    def close(self) -> dict[str, Any]:
        """Stop the watch, finish and close the session (:func:`hrm_ctrl.runtime.box.open_box`
        closes them in that order); its run record."""
        if self.record is None:
            self._stack.close()
            path = self.session.record_path
            self.record = json.loads(path.read_text()) if path is not None else {}
        return self.record
