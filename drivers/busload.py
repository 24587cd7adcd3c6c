"""Worst-case CAN bus load of the cyclic traffic, and the budget check.

Per control cycle each bus carries one RPDO per node (host -> drive), one TPDO
per node (drive -> host) and one SYNC; besides, heartbeats of every node and of
the host.  Each frame counts its worst-case wire time,
:func:`drivers.protocol.frames.worst_case_frame_bits` (bit stuffing included:
135 bits for 8 data bytes, 55 for a SYNC), the figure the simulated wire uses too.

>>> from drivers.config import load_box_config
>>> [round(b.load, 3) for b in bus_loads(load_box_config(None))]
[0.432, 0.432]
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.config import BoxConfig, BusConfig, ControlConfig, rate_problem
from drivers.protocol.cia402 import RPDO_TARGET_SIZE, TPDO_FEEDBACK_SIZE
from drivers.protocol.frames import worst_case_frame_bits
from hrm_ctrl.errors import DriverError

HEARTBEAT_SIZE = 1
SYNC_SIZE = 0


class BusLoadError(DriverError):
    """A bus would be loaded above the configured limit."""


@dataclass(frozen=True)
class BusLoad:
    """Worst-case load of one bus at the configured rate."""

    bus: str
    n_nodes: int
    bitrate: int
    rate_hz: float
    bits_per_cycle: int
    heartbeat_bits_per_s: float
    load: float  # fraction of the bitrate
    limit: float
    max_rate_hz: float  # highest usable control rate (whole Hz, 0x60C2-encodable) within the limit

    @property
    def fits(self) -> bool:
        return self.load <= self.limit

    def to_dict(self) -> dict[str, float | int | str | bool]:
        return {
            "bus": self.bus,
            "n_nodes": self.n_nodes,
            "bitrate": self.bitrate,
            "rate_hz": self.rate_hz,
            "bits_per_cycle": self.bits_per_cycle,
            "heartbeat_bits_per_s": self.heartbeat_bits_per_s,
            "load": self.load,
            "limit": self.limit,
            "max_rate_hz": self.max_rate_hz,
            "fits": self.fits,
        }


def bus_load(
    bus: BusConfig,
    control: ControlConfig,
    rpdo_bytes: int = RPDO_TARGET_SIZE,
    tpdo_bytes: int = TPDO_FEEDBACK_SIZE,
) -> BusLoad:
    """Worst-case load of one bus from mapped PDO sizes, node count, heartbeats and bitrate."""
    n = len(bus.nodes)
    per_cycle = n * (worst_case_frame_bits(rpdo_bytes) + worst_case_frame_bits(tpdo_bytes))
    per_cycle += worst_case_frame_bits(SYNC_SIZE)
    hb_bits = worst_case_frame_bits(HEARTBEAT_SIZE)
    heartbeat_bps = hb_bits * (
        n * 1000.0 / control.node_heartbeat_ms + 1000.0 / control.host_heartbeat_ms
    )
    load = (per_cycle * control.rate_hz + heartbeat_bps) / bus.bitrate
    budget = control.bus_load_limit * bus.bitrate - heartbeat_bps
    max_rate = highest_usable_rate(budget / per_cycle) if budget > 0 else 0.0
    return BusLoad(
        bus=bus.name,
        n_nodes=n,
        bitrate=bus.bitrate,
        rate_hz=control.rate_hz,
        bits_per_cycle=per_cycle,
        heartbeat_bits_per_s=heartbeat_bps,
        load=load,
        limit=control.bus_load_limit,
        max_rate_hz=max_rate,
    )


def highest_usable_rate(limit_hz: float) -> float:
    """The highest whole rate (Hz) <= ``limit_hz`` whose period the drives can take in
    0x60C2 (see :func:`drivers.config.rate_problem`); 0 if none.

    >>> highest_usable_rate(163.9), highest_usable_rate(81.4), highest_usable_rate(0.5)
    (125.0, 80.0, 0.0)
    """
    r = math.floor(limit_hz)
    while r > 0 and rate_problem(float(r)) is not None:
        r -= 1
    return float(max(r, 0))


def bus_loads(config: BoxConfig) -> list[BusLoad]:
    """Worst-case load of every bus of a box."""
    return [bus_load(b, config.control) for b in config.buses]


def check_bus_load(config: BoxConfig) -> list[BusLoad]:
    """Raise :class:`BusLoadError` naming the first bus above the limit and the highest
    rate that fits; return every bus's load otherwise.

    >>> from drivers.config import load_box_config
    >>> cfg = load_box_config(None).with_control(rate_hz=200.0)
    >>> check_bus_load(cfg)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    drivers.busload.BusLoadError: bus can0: worst-case load 85.1% at 200 Hz ... fits: 125 Hz
    """
    loads = bus_loads(config)
    for bl in loads:
        if not bl.fits:
            raise BusLoadError(
                f"bus {bl.bus}: worst-case load {100 * bl.load:.1f}% at {bl.rate_hz:g} Hz "
                f"exceeds the {100 * bl.limit:g}% limit ({bl.n_nodes} nodes at "
                f"{bl.bitrate} bit/s); highest rate that fits: {bl.max_rate_hz:g} Hz"
            )
    return loads
