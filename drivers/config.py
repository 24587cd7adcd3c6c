"""Bus configuration of the manipulator box (TOML): buses, node ids, control timing.

The file has a ``[control]`` table (rate and safety timing) and one
``[buses.NAME]`` table per CAN bus: a python-can ``interface``, ``channel`` and
``bitrate``, optional ``[buses.NAME.options]`` (extra ``can.Bus`` keyword
arguments) and ``[buses.NAME.nodes]`` mapping each rope motor id to its CANopen
node id.  The interface is configuration, never code: any name python-can knows
(built-in or registered under the ``can.interface`` entry point) is accepted.

This module is the one reader of the file and :class:`BoxConfig` the one typed
configuration: the host's drivers and the simulated box (``sim_bus``, ``hrm sim``)
both take it.  It describes the wire, not the host's logic; simulator settings are
arguments of ``sim_bus.box.SimBox`` and of ``hrm sim``, never keys of the file.

>>> cfg = load_box_config(None)
>>> [b.name for b in cfg.buses], cfg.n_motors, cfg.control.rate_hz
(['can0', 'can1'], 36, 100.0)
>>> cfg.location("j07r0")
(1, 1)
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import can

from drivers import default_box_path
from drivers.protocol.cia301 import (
    HOST_HEARTBEAT_NODE_ID,
    NODE_ID_MAX,
    NODE_ID_MIN,
    FrameError,
)
from drivers.protocol.cia402 import interpolation_time_period
from drivers.realtime import NORMAL_PRIORITY, REALTIME_PRIORITY_MAX
from hrm_ctrl.errors import DriverError
from hrm_ctrl.files import read_toml


class BusConfigError(DriverError):
    """The bus configuration file is missing, malformed or inconsistent."""


BUS_NAME_PATTERN = re.compile(r"[A-Za-z0-9_-]+")
"""Bus names become part of log file names: letters, digits, ``_`` and ``-`` only."""

UDP_MULTICAST_HOP_LIMIT = 0
"""``hop_limit`` a udp_multicast bus gets unless its ``options`` set one (python-can's own
default is 1): 0 keeps the traffic on this host, for the host and the simulator alike."""


def rate_problem(rate_hz: float) -> str | None:
    """Why a control rate cannot be used (a phrase after ``control.rate_hz``), or ``None``.

    The control period is written to the drives as 0x60C2 interpolation time period
    (value 1..255 times 10^index s), so the period must be exactly representable.

    >>> rate_problem(100.0) is None, rate_problem(250.0) is None
    (True, True)
    >>> rate_problem(30.0)
    'must give a period 0x60C2 can encode (value 1..255 x 10^index s; nearest: 25 or 40 Hz)'
    >>> rate_problem(0.0)
    'must be in (0, 10000]'
    """
    if not (math.isfinite(rate_hz) and 0 < rate_hz <= 10_000):
        return "must be in (0, 10000]"
    if _encodable(rate_hz):
        return None
    below = next((r for r in range(math.floor(rate_hz), 0, -1) if _encodable(r)), None)
    above = next((r for r in range(math.ceil(rate_hz), 10_001) if _encodable(r)), None)
    near = " or ".join(str(r) for r in (below, above) if r is not None)
    return f"must give a period 0x60C2 can encode (value 1..255 x 10^index s; nearest: {near} Hz)"


def _encodable(rate_hz: float) -> bool:
    try:
        interpolation_time_period(1.0 / rate_hz)
    except FrameError:
        return False
    return True


@dataclass(frozen=True)
class BusConfig:
    """One CAN bus: how to open it and which rope motors (node ids) sit on it."""

    name: str
    interface: str
    channel: str | int
    bitrate: int
    options: Mapping[str, Any]
    nodes: Mapping[str, int]  # rope motor id -> node id, in file order

    @property
    def motor_ids(self) -> tuple[str, ...]:
        return tuple(self.nodes)

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(self.nodes.values())

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus``.

        udp_multicast gets ``hop_limit = UDP_MULTICAST_HOP_LIMIT`` (0) unless the options
        say otherwise, so by default its frames never leave the host.

        >>> BusConfig("b", "virtual", "x", 500_000, {"rx_queue_size": 9}, {}).bus_kwargs()
        {'interface': 'virtual', 'channel': 'x', 'bitrate': 500000, 'rx_queue_size': 9}
        >>> udp = BusConfig("b", "udp_multicast", "239.0.0.1", 500_000, {}, {})
        >>> udp.bus_kwargs()["hop_limit"]
        0
        """
        kw = {
            "interface": self.interface,
            "channel": self.channel,
            "bitrate": self.bitrate,
            **dict(self.options),
        }
        if self.interface == "udp_multicast":
            kw.setdefault("hop_limit", UDP_MULTICAST_HOP_LIMIT)
        return kw

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "interface": self.interface,
            "channel": self.channel,
            "bitrate": self.bitrate,
            "options": dict(self.options),
            "nodes": dict(self.nodes),
        }


@dataclass(frozen=True)
class ControlConfig:
    """Control-loop timing and safety settings (the ``[control]`` table)."""

    rate_hz: float = 100.0
    host_node_id: int = HOST_HEARTBEAT_NODE_ID
    host_heartbeat_ms: int = 100
    node_heartbeat_ms: int = 100
    heartbeat_timeout_ms: int = 350
    missing_tpdo_cycles: int = 3
    bus_load_limit: float = 0.70
    bootup_timeout_s: float = 3.0
    sdo_timeout_s: float = 0.5
    state_timeout_s: float = 0.5
    following_error_window_counts: int = 2000
    quick_stop_option_code: int = 2
    realtime_priority: int = NORMAL_PRIORITY  # SCHED_FIFO priority of the scheduler (0: off)

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class BoxConfig:
    """Every bus of the box plus the control settings; immutable."""

    buses: tuple[BusConfig, ...]
    control: ControlConfig
    source: str
    _where: Mapping[str, tuple[int, int]] = field(default_factory=dict, repr=False)

    @property
    def motor_ids(self) -> tuple[str, ...]:
        """All rope motor ids, bus by bus in file order."""
        return tuple(m for b in self.buses for m in b.nodes)

    @property
    def n_motors(self) -> int:
        return sum(len(b.nodes) for b in self.buses)

    def location(self, motor_id: str) -> tuple[int, int]:
        """(bus index, node id) of a rope motor."""
        try:
            return self._where[motor_id]
        except KeyError:
            raise BusConfigError(f"{self.source}: no node for rope motor '{motor_id}'") from None

    def check_motors(self, motor_ids: Sequence[str]) -> None:
        """Every rope motor of the rope layer has a node, and no node is unknown to it."""
        missing = [m for m in motor_ids if m not in self._where]
        extra = [m for m in self._where if m not in set(motor_ids)]
        if missing:
            raise BusConfigError(f"{self.source}: no node id for rope motor(s) {missing}")
        if extra:
            raise BusConfigError(f"{self.source}: node(s) for unknown rope motor(s) {extra}")

    def with_control(self, **changes: Any) -> BoxConfig:
        """A copy with some control settings changed (validated again)."""
        return box_config_from_dict(
            {**self.to_dict(), "control": {**self.to_dict()["control"], **changes}},
            self.source,
        )

    def with_bus_kwargs(self, kwargs: Sequence[Mapping[str, Any]]) -> BoxConfig:
        """A copy whose buses are opened with other ``can.Bus`` kwargs (same nodes).

        Used to run the same box over virtual or simulated buses.
        """
        if len(kwargs) != len(self.buses):
            raise BusConfigError(f"{self.source}: {len(self.buses)} buses, got {len(kwargs)}")
        buses = []
        for b, kw in zip(self.buses, kwargs, strict=True):
            kw = dict(kw)
            interface = str(kw.pop("interface"))
            channel = kw.pop("channel", b.channel)
            bitrate = int(kw.pop("bitrate", b.bitrate))
            _check_interface(interface, f"{self.source}: buses.{b.name}.interface")
            buses.append(
                replace(b, interface=interface, channel=channel, bitrate=bitrate, options=kw)
            )
        _check_distinct_channels(buses, self.source)
        return replace(self, buses=tuple(buses))

    def to_dict(self) -> dict[str, Any]:
        c = self.control
        return {
            "control": {k: getattr(c, k) for k in ControlConfig.__dataclass_fields__},
            "buses": {
                b.name: {
                    "interface": b.interface,
                    "channel": b.channel,
                    "bitrate": b.bitrate,
                    "options": dict(b.options),
                    "nodes": dict(b.nodes),
                }
                for b in self.buses
            },
        }


def known_interfaces() -> set[str]:
    """python-can interface names: built-in backends plus ``can.interface`` entry points.

    >>> {"virtual", "socketcan", "udp_multicast"} <= known_interfaces()
    True
    """
    names = set(can.interfaces.BACKENDS)
    try:
        from importlib.metadata import entry_points

        names |= {e.name for e in entry_points(group="can.interface")}
    except Exception:  # pragma: no cover - metadata unavailable
        pass
    return names


def _check_interface(name: Any, where: str) -> str:
    if not isinstance(name, str) or name not in known_interfaces():
        raise BusConfigError(
            f"{where}: unknown python-can interface {name!r} "
            f"(known: {', '.join(sorted(known_interfaces()))})"
        )
    return name


_CONTROL_TYPES: dict[str, type] = {
    "rate_hz": float,
    "host_node_id": int,
    "host_heartbeat_ms": int,
    "node_heartbeat_ms": int,
    "heartbeat_timeout_ms": int,
    "missing_tpdo_cycles": int,
    "bus_load_limit": float,
    "bootup_timeout_s": float,
    "sdo_timeout_s": float,
    "state_timeout_s": float,
    "following_error_window_counts": int,
    "quick_stop_option_code": int,
    "realtime_priority": int,
}


def _control_from(doc: Mapping[str, Any], where: str) -> ControlConfig:
    if not isinstance(doc, Mapping):
        raise BusConfigError(f"{where}: [control] must be a table")
    values: dict[str, Any] = {}
    for key, value in doc.items():
        w = f"{where}: control.{key}"
        if key not in _CONTROL_TYPES:
            raise BusConfigError(f"{w}: unknown key")
        kind = _CONTROL_TYPES[key]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise BusConfigError(f"{w}: expected a number, got {value!r}")
        if kind is int and (not isinstance(value, int) and not float(value).is_integer()):
            raise BusConfigError(f"{w}: expected an integer, got {value!r}")
        if not math.isfinite(float(value)):
            raise BusConfigError(f"{w}: expected a finite number, got {value!r}")
        values[key] = kind(value)
    c = ControlConfig(**values)
    checks = [
        ("rate_hz", rate_problem(c.rate_hz) is None, str(rate_problem(c.rate_hz))),
        (
            "host_node_id",
            NODE_ID_MIN <= c.host_node_id <= NODE_ID_MAX,
            f"must be in {NODE_ID_MIN}..{NODE_ID_MAX}",
        ),
        ("host_heartbeat_ms", 1 <= c.host_heartbeat_ms <= 0xFFFF, "must be in 1..65535"),
        ("node_heartbeat_ms", 1 <= c.node_heartbeat_ms <= 0xFFFF, "must be in 1..65535"),
        (
            "heartbeat_timeout_ms",
            max(c.host_heartbeat_ms, c.node_heartbeat_ms) < c.heartbeat_timeout_ms <= 0xFFFF,
            "must exceed both heartbeat periods (and be <= 65535)",
        ),
        ("missing_tpdo_cycles", c.missing_tpdo_cycles >= 1, "must be >= 1"),
        ("bus_load_limit", 0 < c.bus_load_limit <= 1, "must be in (0, 1]"),
        ("bootup_timeout_s", c.bootup_timeout_s > 0, "must be > 0"),
        ("sdo_timeout_s", c.sdo_timeout_s > 0, "must be > 0"),
        ("state_timeout_s", c.state_timeout_s > 0, "must be > 0"),
        (
            "following_error_window_counts",
            0 <= c.following_error_window_counts <= 0xFFFFFFFF,
            "must be in 0..4294967295",
        ),
        ("quick_stop_option_code", -32768 <= c.quick_stop_option_code <= 32767, "INTEGER16"),
        (
            "realtime_priority",
            NORMAL_PRIORITY <= c.realtime_priority <= REALTIME_PRIORITY_MAX,
            f"must be in {NORMAL_PRIORITY}..{REALTIME_PRIORITY_MAX}",
        ),
    ]
    for key, ok, why in checks:
        if not ok:
            raise BusConfigError(f"{where}: control.{key} {why}, got {getattr(c, key)!r}")
    return c


def box_config_from_dict(doc: Mapping[str, Any], source: str) -> BoxConfig:
    """Validate a parsed bus configuration and build a :class:`BoxConfig`."""
    where = source
    unknown = set(doc) - {"control", "buses"}
    if unknown:
        raise BusConfigError(f"{where}: unknown table(s) {sorted(unknown)}")
    control = _control_from(doc.get("control", {}), where)
    buses_doc = doc.get("buses")
    if not isinstance(buses_doc, Mapping) or not buses_doc:
        raise BusConfigError(f"{where}: needs at least one [buses.NAME] table")
    buses: list[BusConfig] = []
    placed: dict[str, tuple[int, int]] = {}
    for bi, (name, b) in enumerate(buses_doc.items()):
        w = f"{where}: buses.{name}"
        if not isinstance(name, str) or not BUS_NAME_PATTERN.fullmatch(name):
            raise BusConfigError(
                f"{where}: buses.{name!r}: bus name may only use letters, digits, '_' and '-' "
                "(it names the bus's log file)"
            )
        if not isinstance(b, Mapping):
            raise BusConfigError(f"{w}: must be a table")
        extra = set(b) - {"interface", "channel", "bitrate", "options", "nodes"}
        if extra:
            raise BusConfigError(f"{w}: unknown key(s) {sorted(extra)}")
        for key in ("interface", "channel", "bitrate", "nodes"):
            if key not in b:
                raise BusConfigError(f"{w}: missing key '{key}'")
        interface = _check_interface(b["interface"], f"{w}.interface")
        channel = b["channel"]
        if isinstance(channel, bool) or not isinstance(channel, str | int):
            raise BusConfigError(f"{w}.channel: expected a string or integer, got {channel!r}")
        bitrate = b["bitrate"]
        if (
            isinstance(bitrate, bool)
            or not isinstance(bitrate, int)
            or not 0 < bitrate <= 1_000_000
        ):
            raise BusConfigError(f"{w}.bitrate: expected an integer in 1..1000000, got {bitrate!r}")
        options = b.get("options", {})
        if not isinstance(options, Mapping):
            raise BusConfigError(f"{w}.options: must be a table")
        for key in ("interface", "channel", "bitrate"):
            if key in options:
                raise BusConfigError(f"{w}.options.{key}: set it on the bus, not in options")
        nodes = b["nodes"]
        if not isinstance(nodes, Mapping) or not nodes:
            raise BusConfigError(f"{w}.nodes: must be a non-empty table of motor = node id")
        seen: dict[int, str] = {}
        for motor, node in nodes.items():
            wn = f"{w}.nodes.{motor}"
            if isinstance(node, bool) or not isinstance(node, int):
                raise BusConfigError(f"{wn}: node id must be an integer, got {node!r}")
            if not NODE_ID_MIN <= node <= NODE_ID_MAX:
                raise BusConfigError(f"{wn}: node id {node} outside {NODE_ID_MIN}..{NODE_ID_MAX}")
            if node == control.host_node_id:
                raise BusConfigError(
                    f"{wn}: node id {node} is the host's heartbeat id (control.host_node_id)"
                )
            if node in seen:
                raise BusConfigError(f"{wn}: duplicate node id {node} (also {seen[node]})")
            if motor in placed:
                other = list(buses_doc)[placed[motor][0]]
                raise BusConfigError(f"{wn}: motor '{motor}' is also on bus {other}")
            seen[node] = motor
            placed[motor] = (bi, node)
        buses.append(
            BusConfig(
                name=str(name),
                interface=interface,
                channel=channel,
                bitrate=bitrate,
                options=dict(options),
                nodes=dict(nodes),
            )
        )
    _check_distinct_channels(buses, source)
    return BoxConfig(buses=tuple(buses), control=control, source=source, _where=placed)


def _check_distinct_channels(buses: Sequence[BusConfig], source: str) -> None:
    """Two buses on the same (interface, channel) would be one bus counted twice."""
    seen: dict[tuple[str, str], str] = {}
    for b in buses:
        key = (b.interface, str(b.channel))
        if key in seen:
            raise BusConfigError(
                f"{source}: buses.{b.name}.channel: {b.interface} channel {b.channel!r} "
                f"is already bus {seen[key]} (each bus needs its own interface and channel)"
            )
        seen[key] = b.name


def load_box_config(path: str | Path | None = None) -> BoxConfig:
    """Load a bus configuration; ``None`` loads the default ``drivers/data/box.toml``.

    Raises :class:`BusConfigError` (one line, naming file and key) on bad input.
    """
    p = default_box_path() if path is None else Path(path)
    source = str(p) if path is not None else f"<default {p.name}>"
    doc, source = read_toml(p, BusConfigError, "bus configuration", source)
    return box_config_from_dict(doc, source)
