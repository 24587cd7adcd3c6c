"""The box's buses as the session uses them: where each motor is, and per bus its port,
CAN log, receiver, canopen network and layout, opened together and closed together.

:class:`MotorSlots` maps the rope layer's motors to their place on the box (the slot:
an index in the rope layer's order; the bus; the node id), computed once from the
configuration.  :class:`BoxWiring` opens every configured bus (or takes buses already
opened), and per bus: a python-can log of its traffic (:class:`~drivers.bus.TrafficLog`),
the one send path (:class:`~drivers.bus.BusPort`), the receive dispatch
(:class:`~drivers.receive.BusReceiver`: feedback TPDOs, heartbeats, EMCYs to the node
monitor; SDO responses to canopen), a canopen network with one ``RemoteNode`` per drive
(:class:`~drivers.bringup.DriveLink`) and the :class:`~drivers.cycle.BusLayout` the
supervisor cycles over.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import can
import canopen
import numpy as np

from drivers.bringup import DriveLink
from drivers.bus import ECHOING_INTERFACES, BusPort
from drivers.busload import BusLoad
from drivers.canlog import TrafficLog
from drivers.config import BoxConfig, BusConfig
from drivers.cycle import BusLayout
from drivers.protocol import cia301
from drivers.protocol.cia306 import canopen_dictionary, read_device_file
from drivers.receive import BusPoller, BusReader, BusReceiver, pollable
from drivers.safety.monitor import NodeMonitor
from hrm_ctrl.errors import DriverError


@dataclass(frozen=True)
class MotorSlots:
    """Where each motor of the rope layer is: slot ``i`` is ``motor_ids[i]``, on bus
    ``bus[i]`` as node ``node_id[i]``.

    >>> from types import SimpleNamespace as NS
    >>> cfg = NS(buses=[NS(name="a", nodes={"m1": 5}), NS(name="b", nodes={"m0": 2})])
    >>> s = MotorSlots.of(cfg, ["m0", "m1"])
    >>> s.slot["m1"], s.bus, s.node_id
    (1, ('b', 'a'), (2, 5))
    >>> s.labels[0]
    'm0 (bus b node 2)'
    >>> s.on_bus(cfg.buses[0]).tolist()
    [1]
    """

    motor_ids: tuple[str, ...]
    slot: Mapping[str, int]
    bus: tuple[str, ...]
    node_id: tuple[int, ...]

    @classmethod
    def of(cls, config: BoxConfig, motor_ids: Sequence[str]) -> MotorSlots:
        """The slots of ``motor_ids`` on ``config``'s buses (every motor has a node:
        :meth:`BoxConfig.check_motors`)."""
        slot = {m: i for i, m in enumerate(motor_ids)}
        bus = [""] * len(slot)
        node = [0] * len(slot)
        for b in config.buses:
            for motor, nid in b.nodes.items():
                bus[slot[motor]], node[slot[motor]] = b.name, int(nid)
        return cls(tuple(motor_ids), MappingProxyType(slot), tuple(bus), tuple(node))

    @property
    def n(self) -> int:
        return len(self.motor_ids)

    @property
    def labels(self) -> tuple[str, ...]:
        """How messages name each slot's drive: motor, bus and node."""
        return tuple(
            f"{m} (bus {b} node {n})"
            for m, b, n in zip(self.motor_ids, self.bus, self.node_id, strict=True)
        )

    def on_bus(self, bus: BusConfig) -> np.ndarray:
        """The slots of one configured bus's nodes, in the bus's node order."""
        return np.array([self.slot[m] for m in bus.nodes], dtype=np.int64)


class PortNetwork(canopen.Network):
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


class BoxWiring:
    """Every bus of the box with its log, port, receiver, network and layout.

    ``guarding``: whether another master's frames are stop causes now (the receivers ask
    it per frame).  Construction opens everything or, on any failure, closes what it
    opened and raises (a bus that cannot be opened: :class:`DriverError` naming it)."""

    def __init__(
        self,
        config: BoxConfig,
        slots: MotorSlots,
        monitor: NodeMonitor,
        loads: Sequence[BusLoad],
        guarding: Callable[[], bool],
        log_path: Callable[[str], Path] | None,
        buses: Sequence[can.BusABC] | None = None,
    ) -> None:
        self.config = config
        self.slots = slots
        self.ports: list[BusPort] = []
        self.logs: list[TrafficLog] = []
        self.owned: list[can.BusABC] = []
        self.networks: list[PortNetwork] = []
        self.receivers: list[BusReceiver] = []
        self.layouts: list[BusLayout] = []
        self.links: list[DriveLink] = []
        try:
            self._open(monitor, loads, guarding, log_path, buses)
        except BaseException:
            self.close()
            raise

    def _open(
        self,
        monitor: NodeMonitor,
        loads: Sequence[BusLoad],
        guarding: Callable[[], bool],
        log_path: Callable[[str], Path] | None,
        given: Sequence[can.BusABC] | None,
    ) -> None:
        config, slots = self.config, self.slots
        control = config.control
        # each drive's object dictionary from its device file (box.toml [drives]), one
        # read per file
        ods: dict[Path, canopen.ObjectDictionary] = {}

        def od_of(motor: str) -> canopen.ObjectDictionary:
            path = config.drives.device_file(motor)
            if path not in ods:
                ods[path] = canopen_dictionary(read_device_file(path))
            return ods[path]

        opened: list[can.BusABC] = []
        for bi, b in enumerate(config.buses):  # every bus first: no log for a bad one
            if given is not None:
                opened.append(given[bi])
                continue
            try:
                bus = can.Bus(**b.bus_kwargs())
            except Exception as exc:  # a missing interface library can raise anything
                raise DriverError(
                    f"{config.source}: buses.{b.name}: cannot open {b.interface} "
                    f"channel {b.channel!r} ({type(exc).__name__}: {exc})"
                ) from exc
            self.owned.append(bus)
            opened.append(bus)
        links: list[DriveLink | None] = [None] * slots.n
        for bi, (b, bus) in enumerate(zip(config.buses, opened, strict=True)):
            log = None
            if log_path is not None:
                log = TrafficLog(log_path(b.name), channel=bi + 1)
                self.logs.append(log)
            echoes = b.interface in ECHOING_INTERFACES or bool(
                b.options.get("receive_own_messages", False)
            )
            port = BusPort(b.name, bus, log, echoes=echoes)
            self.ports.append(port)
            net = PortNetwork(port)
            idx = slots.on_bus(b)
            labels = {nid: monitor.labels[slots.slot[m]] for m, nid in b.nodes.items()}
            router = BusReceiver(
                port, net, log, labels, monitor.report, guarding, control.host_node_id
            )
            self.receivers.append(router)
            for motor, nid in b.nodes.items():
                i = slots.slot[motor]
                node = canopen.RemoteNode(nid, od_of(motor))
                net.add_node(node)
                node.sdo.RESPONSE_TIMEOUT = control.sdo_timeout_s
                links[i] = DriveLink(node, b.name, motor)
                _subscribe(net, monitor, i, nid)
                router.tpdo[cia301.COB_TPDO1 + nid] = (monitor, i)
                router.heartbeat[cia301.COB_NMT_ERROR_CONTROL + nid] = (monitor, i)
            # our own receive thread (no can.Notifier dispatch); canopen's Network only
            # asks it for .exception (check) and .stop (disconnect); a bus with a
            # descriptor is read by the supervisor's thread (BusPoller)
            net.notifier = (  # type: ignore[assignment]
                BusPoller(bus, router, b.name) if pollable(bus) else BusReader(bus, router, b.name)
            )
            self.networks.append(net)
            load = loads[bi]
            self.layouts.append(
                BusLayout(
                    port,
                    idx,
                    np.array(list(b.nodes.values())),
                    net.notifier,
                    burst_s=load.bits_per_cycle / load.bitrate,
                )
            )
        self.links = [link for link in links if link is not None]

    def send_nmt(self, command: int) -> None:
        """Broadcast one NMT command on every bus."""
        for port in self.ports:
            port.send(cia301.make_nmt(command, 0))

    def subscribe_emcy(self, on_emcy: Callable[[int, int, bytes], None]) -> None:
        """``on_emcy(slot, node_id, data)`` for every EMCY of every drive (besides the
        monitor's own)."""
        for b, net in zip(self.config.buses, self.networks, strict=True):
            for motor, nid in b.nodes.items():
                i = self.slots.slot[motor]

                def keep(_cid: int, data: bytes, _ts: float, i: int = i, nid: int = nid) -> None:
                    on_emcy(i, nid, data)

                net.subscribe(cia301.COB_EMCY + nid, keep)

    def close(self) -> None:
        """Stop the receive threads, close the logs, shut the buses this wiring opened
        (idempotent; errors of a bus's shutdown are not raised)."""
        for net in self.networks:
            if net.notifier is not None:
                net.notifier.stop(1.0)
        for log in self.logs:
            log.stop()
        for bus in self.owned:
            try:
                bus.shutdown()
            except (can.CanError, OSError):
                pass
        self.owned = []


def _subscribe(net: canopen.Network, mon: NodeMonitor, i: int, nid: int) -> None:
    net.subscribe(
        cia301.COB_NMT_ERROR_CONTROL + nid, lambda _cid, data, _ts: mon.on_heartbeat(i, data)
    )
    net.subscribe(cia301.COB_EMCY + nid, lambda _cid, data, _ts: mon.on_emcy(i, nid, data))
