"""A snapshot of the box as the drive session sees it (``hrm status``, the console's
``status``): typed, immutable, for the CLI to format.

Per node (one rope motor's drive): its NMT state from its last heartbeat, its CiA 402
state and actual position (by SDO while the drives do not stream, from the feedback
TPDOs while they do), the position the host holds or commands (the following error is
the difference), the rope's tension from the tension-sensor board (when one is read),
how old its last heartbeat is and its last EMCY.  Per bus: the worst-case load at the
control rate, frames sent, error frames and frames of another master heard, frames the
CAN log could not take, and a SocketCAN bus's link state (``ip -details link``:
:mod:`drivers.link_state`).  And the session's state with the causes of its last stop.

>>> n = NodeStatus("j01r0", "bus0", 1, "OPERATIONAL", "OPERATION_ENABLED", 0x0637, 10, 12,
...                 31.5, 0.05, None)
>>> n.following_error_counts
-2
>>> n.fault
False
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import can
import numpy as np

from drivers.link_state import link_status_line
from drivers.protocol.cia301 import NMT_STATE_NAMES, FrameError, parse_emcy
from drivers.protocol.cia402 import SW_FAULT, State402, decode_state

if TYPE_CHECKING:  # (what the read-outs are read from; a formatter needs none of it)
    from drivers.bus import BusPort
    from drivers.busload import BusLoad
    from drivers.canlog import TrafficLog
    from drivers.config import BusConfig
    from drivers.receive import BusReceiver
    from drivers.safety.monitor import NodeMonitor
    from drivers.wiring import MotorSlots


@dataclass(frozen=True)
class NodeStatus:
    """One drive.  ``None`` where a value is not known (no heartbeat yet, no answer, no
    tension board).  ``target_counts`` is what the host holds or commands (the
    supervisor's last setpoint; None while the drives are not enabled)."""

    motor: str
    bus: str
    node_id: int
    nmt_state: str | None
    state402: str | None
    statusword: int | None
    position_counts: int | None
    target_counts: int | None
    tension_N: float | None
    heartbeat_age_s: float | None
    last_emcy: str | None

    @property
    def following_error_counts(self) -> int | None:
        """Actual minus held/commanded position (counts), when both are known."""
        if self.position_counts is None or self.target_counts is None:
            return None
        return self.position_counts - self.target_counts

    @property
    def fault(self) -> bool:
        """The statusword has the fault bit (the drive is in FAULT or reacting to one)."""
        return self.statusword is not None and bool(self.statusword & SW_FAULT)


@dataclass(frozen=True)
class BusStatus:
    """One bus: its configured bitrate and worst-case load (a fraction of the bitrate at
    the control rate, against its limit), frames sent, error frames received, frames of
    another master heard (host-direction COB-IDs we did not send), and CAN-log losses."""

    name: str
    bitrate: int
    load: float
    load_limit: float
    frames_sent: int
    error_frames: int
    foreign_frames: int
    log_frames_lost: int
    state: str | None  # python-can's bus state (ACTIVE, PASSIVE, ERROR) where it knows it
    #: a SocketCAN bus: its interface's link state from ``ip -details link`` in a line
    #: (:func:`drivers.link_state.link_status_line`), or why it could not be read
    link: str | None = None


@dataclass(frozen=True)
class SessionStatus:
    """The whole box: the session's state, its calibration, the causes of its last stop
    (idle or streaming; empty: none), when the snapshot was taken (monotonic s) and
    whether the node values came from SDO reads (``by_sdo``) or the feedback TPDOs."""

    state: str
    calibration: str
    stop_causes: tuple[str, ...]
    nodes: tuple[NodeStatus, ...]
    buses: tuple[BusStatus, ...]
    taken_s: float
    by_sdo: bool

    @property
    def faulted(self) -> tuple[NodeStatus, ...]:
        """The drives in FAULT (fault bit set)."""
        return tuple(n for n in self.nodes if n.fault)


def nmt_name(state: int) -> str | None:
    """The NMT state's name of a heartbeat's state byte (None: no heartbeat yet).

    >>> nmt_name(0x05), nmt_name(-1)
    ('OPERATIONAL', None)
    """
    if state < 0:
        return None
    return NMT_STATE_NAMES.get(int(state), f"0x{int(state):02X}")


def state_name(statusword: int | None) -> str | None:
    """The CiA 402 state's name of a statusword (None: not known).

    >>> state_name(0x0637), state_name(None)
    ('OPERATION_ENABLED', None)
    """
    if statusword is None:
        return None
    return State402(decode_state(int(statusword))).name


def node_statuses(
    motors: Sequence[str],
    buses: Sequence[str],
    node_ids: Sequence[int],
    *,
    hb_state: np.ndarray,
    hb_time_s: np.ndarray,
    now_s: float,
    statusword: Sequence[int | None],
    position: Sequence[int | None],
    targets: np.ndarray | None,
    tension_N: np.ndarray | None,
    last_emcy: Sequence[str | None],
) -> tuple[NodeStatus, ...]:
    """One :class:`NodeStatus` per motor from the session's arrays (rope-layer order).

    >>> st = node_statuses(["m0"], ["b"], [1], hb_state=np.array([5]),
    ...     hb_time_s=np.array([9.5]), now_s=10.0, statusword=[0x0637], position=[7],
    ...     targets=np.array([5]), tension_N=None, last_emcy=[None])
    >>> st[0].heartbeat_age_s, st[0].following_error_counts, st[0].tension_N
    (0.5, 2, None)
    """
    out = []
    for i, motor in enumerate(motors):
        t_hb = float(hb_time_s[i])
        tension = None
        if tension_N is not None and math.isfinite(float(tension_N[i])):
            tension = float(tension_N[i])
        sw = statusword[i]
        pos = position[i]
        out.append(
            NodeStatus(
                motor=motor,
                bus=buses[i],
                node_id=int(node_ids[i]),
                nmt_state=nmt_name(int(hb_state[i])),
                state402=state_name(sw),
                statusword=None if sw is None else int(sw),
                position_counts=None if pos is None else int(pos),
                target_counts=None if targets is None else int(targets[i]),
                tension_N=tension,
                heartbeat_age_s=(now_s - t_hb) if math.isfinite(t_hb) else None,
                last_emcy=last_emcy[i],
            )
        )
    return tuple(out)


class LastEmergencies:
    """Each drive's last EMCY, described, by slot (None: none yet): what the read-outs
    show.  :meth:`on_emcy` is subscribed to every drive's EMCY
    (:meth:`drivers.wiring.BoxWiring.subscribe_emcy`) once ``tracking``.

    >>> last = LastEmergencies(2)
    >>> last.on_emcy(1, 3, bytes.fromhex("3081110000000000"))
    >>> last.last
    [None, 'EMCY node 3: error code 0x8130, error register 0x11']
    """

    def __init__(self, n: int) -> None:
        self.last: list[str | None] = [None] * n
        self.tracking = False

    def on_emcy(self, slot: int, node_id: int, data: bytes) -> None:
        try:
            emcy = parse_emcy(node_id, data)
        except FrameError:
            return  # the monitor reports the bad frame
        self.last[slot] = emcy.describe()


def bus_statuses(
    buses: Sequence[BusConfig],
    loads: Sequence[BusLoad],
    ports: Sequence[BusPort],
    receivers: Sequence[BusReceiver],
    logs: Sequence[TrafficLog],
) -> tuple[BusStatus, ...]:
    """One :class:`BusStatus` per configured bus (a bus without its port, receiver or
    log yet shows zeros; python-can's bus state where the interface knows it; a SocketCAN
    bus's link state, ``ip`` run once per bus)."""
    out = []
    for k, b in enumerate(buses):
        port = ports[k] if k < len(ports) else None
        state = None
        if port is not None:
            try:
                state = port.bus.state.name
            except (NotImplementedError, AttributeError, can.CanError):
                state = None
        traffic = receivers[k].traffic if k < len(receivers) else None
        log_ = logs[k] if k < len(logs) else None
        out.append(
            BusStatus(
                name=b.name,
                bitrate=b.bitrate,
                load=float(loads[k].load),
                load_limit=float(loads[k].limit),
                frames_sent=0 if port is None else int(port.n_sent),
                error_frames=0 if traffic is None else int(traffic.error_frames),
                foreign_frames=0 if traffic is None else int(sum(traffic.foreign.values())),
                log_frames_lost=0 if log_ is None else int(log_.n_lost),
                state=state,
                link=link_status_line(str(b.channel)) if b.interface == "socketcan" else None,
            )
        )
    return tuple(out)


def session_status(
    *,
    state: str,
    calibration: str,
    stop_causes: Sequence[str],
    slots: MotorSlots,
    monitor: NodeMonitor,
    sdo_values: Sequence[tuple[int, int] | None] | None,
    targets: np.ndarray | None,
    tension_N: np.ndarray | None,
    last_emcy: Sequence[str | None],
    buses: tuple[BusStatus, ...],
) -> SessionStatus:
    """The snapshot of a session: node values from ``sdo_values`` (per slot, (statusword,
    actual position) read by SDO, None where a drive did not answer) or, without them,
    from the monitor's feedback TPDOs (none before the first); heartbeats from the
    monitor; ``targets``: what the host holds or commands (None: drives not enabled)."""
    n = monitor.n
    statusword: list[int | None] = [None] * n
    position: list[int | None] = [None] * n
    if sdo_values is not None:
        for i, v in enumerate(sdo_values):
            if v is not None:
                statusword[i], position[i] = v
    else:
        for i in range(n):
            if monitor.n_tpdo[i] > 0:
                statusword[i], position[i] = int(monitor.statusword[i]), int(monitor.position[i])
    nodes = node_statuses(
        slots.motor_ids, slots.bus, slots.node_id,
        hb_state=monitor.hb_state.copy(), hb_time_s=monitor.hb_time.copy(),
        now_s=monitor.clock(), statusword=statusword, position=position,
        targets=None if targets is None else np.asarray(targets).copy(),
        tension_N=tension_N, last_emcy=list(last_emcy),
    )  # fmt: skip
    return SessionStatus(
        state=state,
        calibration=calibration,
        stop_causes=tuple(stop_causes),
        nodes=nodes,
        buses=buses,
        taken_s=monitor.clock(),
        by_sdo=sdo_values is not None,
    )
