"""The box's view of the bus configuration TOML (the drivers' ``box.toml`` format).

``sim_bus`` does not import the host's driver code, so it reads the same file
itself: ``[buses.NAME]`` tables with ``interface``, ``channel``, ``bitrate``,
optional ``options`` and ``nodes`` (rope motor id = node id), and
``[control] rate_hz``.  Other ``[control]`` keys belong to the host and are
ignored here.  Simulator settings are arguments of :class:`sim_bus.box.SimBox`
and of ``hrm sim`` (the host's loader refuses tables it does not know).

>>> cfg = load_sim_config(None)
>>> [b.name for b in cfg.buses], len(cfg.motor_ids), cfg.rate_hz
(['can0', 'can1'], 36, 100.0)
>>> cfg.buses[1].nodes["j07r0"]
1
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

from hrm_ctrl.errors import SimError
from hrm_ctrl.files import read_toml

DEFAULT_BOX = ("drivers.data", "box.toml")


class SimConfigError(SimError):
    """The bus configuration file given to the simulator is missing or malformed."""


@dataclass(frozen=True)
class SimBusConfig:
    name: str
    interface: str
    channel: str | int
    bitrate: int
    options: Mapping[str, Any]
    nodes: Mapping[str, int]

    def bus_kwargs(self) -> dict[str, Any]:
        """``can.Bus`` keyword arguments for this bus.

        udp_multicast gets ``hop_limit = 0`` unless the file says otherwise, so the
        simulated bus's frames never leave the host by default.

        >>> SimBusConfig("b", "virtual", "x", 500_000, {}, {}).bus_kwargs()
        {'interface': 'virtual', 'channel': 'x', 'bitrate': 500000}
        >>> udp = SimBusConfig("b", "udp_multicast", "239.0.0.1", 500_000, {}, {})
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
            kw.setdefault("hop_limit", 0)
        return kw


@dataclass(frozen=True)
class SimConfig:
    buses: tuple[SimBusConfig, ...]
    rate_hz: float
    source: str

    @property
    def motor_ids(self) -> tuple[str, ...]:
        return tuple(m for b in self.buses for m in b.nodes)

    def with_bus_kwargs(self, kwargs: Sequence[Mapping[str, Any]]) -> SimConfig:
        """The same nodes on other buses (one kwargs mapping per bus, in order)."""
        if len(kwargs) != len(self.buses):
            raise SimConfigError(f"{self.source}: {len(self.buses)} buses, got {len(kwargs)}")
        out = []
        for b, kw in zip(self.buses, kwargs, strict=True):
            kw = dict(kw)
            out.append(
                replace(
                    b,
                    interface=str(kw.pop("interface")),
                    channel=kw.pop("channel", b.channel),
                    bitrate=int(kw.pop("bitrate", b.bitrate)),
                    options=kw,
                )
            )
        return replace(self, buses=tuple(out))


def sim_config_from_dict(doc: Mapping[str, Any], source: str) -> SimConfig:
    """Validate a parsed bus configuration (the parts the box needs)."""
    buses_doc = doc.get("buses")
    if not isinstance(buses_doc, Mapping) or not buses_doc:
        raise SimConfigError(f"{source}: needs at least one [buses.NAME] table")
    control = doc.get("control", {})
    if not isinstance(control, Mapping):
        raise SimConfigError(f"{source}: [control] must be a table")
    rate = control.get("rate_hz", 100.0)
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not 0 < rate <= 10_000:
        raise SimConfigError(f"{source}: control.rate_hz must be a number in (0, 10000]")
    buses: list[SimBusConfig] = []
    motors: set[str] = set()
    for name, b in buses_doc.items():
        w = f"{source}: buses.{name}"
        if not isinstance(b, Mapping):
            raise SimConfigError(f"{w}: must be a table")
        for key in ("interface", "channel", "bitrate", "nodes"):
            if key not in b:
                raise SimConfigError(f"{w}: missing key '{key}'")
        if not isinstance(b["interface"], str):
            raise SimConfigError(f"{w}.interface: expected a string")
        ch = b["channel"]
        if isinstance(ch, bool) or not isinstance(ch, str | int):
            raise SimConfigError(f"{w}.channel: expected a string or integer, got {ch!r}")
        br = b["bitrate"]
        if isinstance(br, bool) or not isinstance(br, int) or not 0 < br <= 1_000_000:
            raise SimConfigError(f"{w}.bitrate: expected an integer in 1..1000000, got {br!r}")
        options = b.get("options", {})
        if not isinstance(options, Mapping):
            raise SimConfigError(f"{w}.options: must be a table")
        nodes = b["nodes"]
        if not isinstance(nodes, Mapping) or not nodes:
            raise SimConfigError(f"{w}.nodes: must be a non-empty table of motor = node id")
        seen: set[int] = set()
        for motor, node in nodes.items():
            if isinstance(node, bool) or not isinstance(node, int) or not 1 <= node <= 127:
                raise SimConfigError(f"{w}.nodes.{motor}: node id must be in 1..127, got {node!r}")
            if node in seen:
                raise SimConfigError(f"{w}.nodes.{motor}: duplicate node id {node}")
            if motor in motors:
                raise SimConfigError(f"{w}.nodes.{motor}: motor is on two buses")
            seen.add(node)
            motors.add(motor)
        buses.append(SimBusConfig(str(name), b["interface"], ch, br, dict(options), dict(nodes)))
    return SimConfig(tuple(buses), float(rate), source)


def load_sim_config(path: str | Path | None = None) -> SimConfig:
    """Load a bus configuration; ``None``: the drivers' default ``box.toml``."""
    if path is None:
        default = resources.files(DEFAULT_BOX[0]).joinpath(DEFAULT_BOX[1])
        with resources.as_file(default) as p:
            doc, source = read_toml(
                p, SimConfigError, "bus configuration", f"<default {DEFAULT_BOX[1]}>"
            )
    else:
        doc, source = read_toml(path, SimConfigError, "bus configuration")
    return sim_config_from_dict(doc, source)
