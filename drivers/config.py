"""Bus configuration of the manipulator box (TOML): buses, node ids, control timing.

The file has a ``[control]`` table (rate and safety timing) and one
``[buses.NAME]`` table per CAN bus: a python-can ``interface``, ``channel`` and
``bitrate``, optional ``[buses.NAME.options]`` (extra ``can.Bus`` keyword
arguments) and ``[buses.NAME.nodes]`` mapping each rope motor id to its CANopen
node id; an optional ``[tension]`` table names the tension-sensor board's serial port
and its stop thresholds (:class:`TensionConfig`; no table: the box has no board); an
optional ``[tracker]`` table names the laser tracker's serial port and the wait for each of
its replies (:class:`TrackerConfig`; no table: no tracker); an optional ``[drives]`` table
names each drive's CiA 306 device file, EDS or DCF, an SDO overlay and the identity it must
answer (:class:`DrivesConfig`: ``device_file``, ``sdo``, ``identity`` for every drive,
``[drives.MOTOR]`` the same for one; no table: hrm's own ``drivers/data/hrm_drive.eds``),
which ``hrm box check`` and every bring-up check first (:mod:`drivers.device_check`).
The interface is configuration, never code: any name python-can knows (built-in or
registered under the ``can.interface`` entry point) is accepted.  A bus table without an
``interface`` takes python-can's own configuration (:func:`can.util.load_config` with the
bus's name as context: ``CAN_INTERFACE_NAME`` / ``CAN_CHANNEL_NAME`` / ``CAN_BITRATE_NAME``,
then ``CAN_INTERFACE`` / ``CAN_CHANNEL`` / ``CAN_BITRATE``, then the ``[NAME]`` and
``[default]`` sections of ``~/can.conf``, ``/etc/can.conf``, ``~/.can``, ``~/.canrc``);
a ``channel`` or ``bitrate`` the table does give wins over python-can's.  One bus can be
replaced from the command line (``--bus NAME=INTERFACE:CHANNEL[@BITRATE]``,
:func:`parse_bus_override`, :meth:`BoxConfig.with_bus_overrides`).

This module is the one reader of the file and :class:`BoxConfig` the one typed
configuration: the host's drivers and the simulated box (``sim_bus``, ``hrm sim``)
both take it.  It describes the wire, not the host's logic; simulator settings are
arguments of ``sim_bus.box.SimBox`` and of ``hrm sim``, never keys of the file.

Every value is checked against its safe range when the file loads, by the one validator
of the descriptions (:mod:`hrm_ctrl.validate`): the ranges are the metadata of the
dataclasses' fields (:data:`CONTROL_RANGES`: one per ``[control]`` key with the reason
for its bounds; :data:`CONTROL_RELATIONS` between keys), so ``hrm busload``, ``hrm run`` and the
simulated box refuse the same files, before anything is sent: a watchdog cannot be
configured away (``missing_tpdo_cycles = 1e8``) and no value a drive would abort
(0x605A, 0x6065, 0x60C2) reaches a drive after its NMT reset.  The message is one
line naming the file, the key, the value and the range:
``box.toml: control.missing_tpdo_cycles = 100000000 outside 1..25 cycles; the arm ...``.

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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import can

from drivers import default_box_path, eds_path
from drivers.protocol.cia301 import (
    HOST_HEARTBEAT_NODE_ID,
    NODE_ID_MAX,
    NODE_ID_MIN,
    FrameError,
)
from drivers.protocol.cia402 import (
    QUICK_STOP_OPTIONS_STAY,
    QUICK_STOP_OPTIONS_THEN_DISABLED,
    interpolation_time_period,
)
from drivers.realtime import (
    CPU_LATENCY_NO_REQUEST_US,
    NORMAL_PRIORITY,
    REALTIME_PRIORITY_SAFE_MAX,
)
from hrm_ctrl.errors import DriverError
from hrm_ctrl.files import read_toml
from hrm_ctrl.validate import (
    Spec,
    number_kinds,
    ranged,
    read_numbers,
    refuse_unknown,
    spec,
    specs,
    unknown_key,
)


class BusConfigError(DriverError):
    """The bus configuration file is missing, malformed or inconsistent."""


BUS_NAME_PATTERN = re.compile(r"[A-Za-z0-9_-]+")
"""Bus names become part of log file names: letters, digits, ``_`` and ``-`` only."""

UDP_MULTICAST_HOP_LIMIT = 0
"""``hop_limit`` a udp_multicast bus gets unless its ``options`` set one (python-can's own
default is 1): 0 keeps the traffic on this host, for the host and the simulator alike."""


RATE_MIN_HZ = 10.0
RATE_MAX_HZ = 1000.0
"""Control rates the stack runs at (see ``rate_hz`` in :data:`CONTROL_RANGES`)."""


def rate_problem(rate_hz: float) -> str | None:
    """Why a control rate cannot be used (a phrase after ``control.rate_hz``), or ``None``.

    The rate must lie in ``RATE_MIN_HZ..RATE_MAX_HZ`` (reasons in :data:`CONTROL_RANGES`),
    and the control period is written to the drives as 0x60C2 interpolation time period
    (value 1..255 times 10^index s), so the period must be exactly representable.

    >>> rate_problem(100.0) is None, rate_problem(250.0) is None
    (True, True)
    >>> rate_problem(30.0)
    'must give a period 0x60C2 can encode (value 1..255 x 10^index s; nearest: 25 or 40 Hz)'
    >>> rate_problem(0.0)
    'must be in 10..1000 Hz'
    """
    if not (math.isfinite(rate_hz) and RATE_MIN_HZ <= rate_hz <= RATE_MAX_HZ):
        return f"must be in {RATE_MIN_HZ:g}..{RATE_MAX_HZ:g} Hz"
    if _encodable(rate_hz):
        return None
    lo, hi = int(RATE_MIN_HZ), int(RATE_MAX_HZ)
    below = next((r for r in range(math.floor(rate_hz), lo - 1, -1) if _encodable(r)), None)
    above = next((r for r in range(math.ceil(rate_hz), hi + 1) if _encodable(r)), None)
    near = " or ".join(str(r) for r in (below, above) if r is not None)
    return f"must give a period 0x60C2 can encode (value 1..255 x 10^index s; nearest: {near} Hz)"


def _encodable(rate_hz: float) -> bool:
    try:
        interpolation_time_period(1.0 / rate_hz)
    except FrameError:
        return False
    return True


BITRATE_MAX = 1_000_000
"""Classical CAN's top bitrate (bit/s): every bus's ``bitrate`` lies in 1..1000000."""

NODE_IDS = Spec(lo=NODE_ID_MIN, hi=NODE_ID_MAX, why="a CANopen node id")
"""The range of a drive's node id (``[buses.NAME.nodes]``)."""


@dataclass(frozen=True)
class BusConfig:
    """One CAN bus: how to open it and which rope motors (node ids, :data:`NODE_IDS`) sit
    on it."""

    name: str
    interface: str
    channel: str | int
    bitrate: int = field(metadata=spec(lo=1, hi=BITRATE_MAX, why="classical CAN's bitrates"))
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


# 0 (QUICK_STOP_OPTION_DISABLE_DRIVE) is left out: the power stages would switch off at
# once and every motor coast from its speed, the ropes under the arm's load
_QUICK_STOP_CODES = set(QUICK_STOP_OPTIONS_THEN_DISABLED)
_QUICK_STOP_CODES |= set(QUICK_STOP_OPTIONS_STAY)


@dataclass(frozen=True)
class ControlConfig:
    """Control-loop timing and safety settings (the ``[control]`` table); each field's
    safe range, both ends included, and the reason for it in its metadata
    (:data:`CONTROL_RANGES`)."""

    # fmt: off
    rate_hz: float = ranged(
        100.0, RATE_MIN_HZ, RATE_MAX_HZ, "Hz",
        "below 10 Hz the drives interpolate over 100 ms between targets and every watchdog "
        "counted in cycles slows with it; above 1 kHz the host's control loop (a Python "
        "thread) cannot keep its period; the period must also fit 0x60C2",
    )
    host_node_id: int = ranged(
        HOST_HEARTBEAT_NODE_ID, NODE_ID_MIN, NODE_ID_MAX, "",
        "a CANopen node id (the host heartbeat's COB-ID is 0x700 + id), not a drive's",
    )
    host_heartbeat_ms: int = ranged(
        100, 10, 500, "ms",
        "sent on the control deadline nearest its due time (so one period at least); the "
        "drives' timeout (heartbeat_timeout_ms, at most 2 s) must span 3 of them",
    )
    node_heartbeat_ms: int = ranged(
        100, 10, 500, "ms",
        "0x1017 of every drive: 10 ms puts 100 frames/s per drive on its bus; the host's "
        "timeout (heartbeat_timeout_ms, at most 2 s) must span 3 of them",
    )
    heartbeat_timeout_ms: int = ranged(
        350, 30, 2000, "ms",
        "0x1016 on the drives and the host's own watch: a dead host or drive goes "
        "unnoticed at most this long; 3 of the shortest heartbeat periods at least",
    )
    missing_tpdo_cycles: int = ranged(
        3, 1, 25, "cycles",
        "the arm moves without position feedback this many cycles before every axis stops "
        "(25: the HIL rig's 250 ms at 100 Hz, over udp_multicast on a shared machine)",
    )
    bus_load_limit: float = ranged(
        0.70, 0.05, 0.9, "",
        "the worst-case load leaves no room for error frames and retransmissions above "
        "0.9, and the heartbeats (lowest priority) need idle bus time to get through",
    )
    bootup_timeout_s: float = ranged(
        3.0, 0.1, 30.0, "s",
        "nothing moves during boot-up: a missing node is reported within 30 s; no drive "
        "boots within 0.1 s of its NMT reset",
    )
    sdo_timeout_s: float = ranged(
        0.5, 0.05, 2.0, "s",
        "each SDO transfer (canopen retries once); disabling the drives after a stop is "
        "SDO, so a longer timeout delays it; 50 ms covers a drive and a loaded host",
    )
    state_timeout_s: float = ranged(
        0.5, 0.05, 5.0, "s",
        "each CiA 402 transition, a quick stop ramp included; disabling the drives after "
        "a stop waits this long per transition",
    )
    following_error_window_counts: int = ranged(
        2000, 1, 65536, "counts",
        "0x6065 (UNSIGNED32, 0xFFFFFFFF switches the drive's check off): 65536 counts are "
        "16 encoder turns, 30 mm of rope with the shipped motor map; 0 faults at any lag",
    )
    quick_stop_option_code: int = ranged(
        2, min(_QUICK_STOP_CODES), max(_QUICK_STOP_CODES), "",
        "0x605A (INTEGER16 in hrm_drive.eds): the ramps CiA 402 defines and the drive "
        "implements (it aborts any other write, 0x06090030, after its NMT reset); not 0, "
        "'disable drive function': every motor would coast from speed, the ropes under load",
    )
    #: SCHED_FIFO priority of the scheduler (0: off)
    realtime_priority: int = ranged(
        NORMAL_PRIORITY, NORMAL_PRIORITY, REALTIME_PRIORITY_SAFE_MAX, "",
        "SCHED_FIFO priority of the control thread (0: off); at 50 and above it would "
        "preempt the kernel's interrupt threads (PREEMPT_RT), the CAN controller's too",
    )
    #: PM QoS CPU wake-up latency held while the session is open (drivers.realtime;
    #: the default is the kernel's "no constraint": nothing held)
    cpu_wakeup_latency_us: int = ranged(
        CPU_LATENCY_NO_REQUEST_US, 0, CPU_LATENCY_NO_REQUEST_US, "us",
        "a PM QoS request (/dev/cpu_dma_latency, a signed 32-bit value; 0: idle CPUs poll); "
        f"{CPU_LATENCY_NO_REQUEST_US}, the kernel's 'no constraint', holds none",
    )
    # fmt: on

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


CONTROL_RANGES: Mapping[str, Spec] = specs(ControlConfig)
"""The safe range of every ``[control]`` value (:class:`hrm_ctrl.validate.Spec`: lo, hi,
unit, why), both ends included: the metadata of :class:`ControlConfig`'s fields."""

TENSION_BAUD_RANGE = (9_600, 4_000_000)
TENSION_SLACK_RANGE_N = (0.5, 100.0)
TENSION_LIMIT_MAX_N = 650.0
TENSION_STALE_RANGE_S = (0.02, 0.5)
TENSION_GARBAGE_MAX_PER_S = 50.0


@dataclass(frozen=True)
class TensionConfig:
    """The rope tension-sensor board (the optional ``[tension]`` table): its serial port
    and the thresholds that stop every axis (``drivers.tension_sensor.TensionWatch``);
    each threshold's safe range, checked on load, in its metadata."""

    port: str
    # fmt: off
    baudrate: int = ranged(921_600, *TENSION_BAUD_RANGE)
    slack_N: float = ranged(
        5.0, *TENSION_SLACK_RANGE_N, "N", "above the board's noise, so a broken rope reads below it"
    )
    limit_N: float = ranged(
        150.0, -math.inf, TENSION_LIMIT_MAX_N, "N", "the board saturates at 655.34 N",
        above="slack_N",
    )
    stale_s: float = ranged(
        0.1, *TENSION_STALE_RANGE_S, "s",
        "two frames at 100 Hz at least, half a second blind at most",
    )
    #: CRC errors, resynchronisations and wrong-size frames per second, over the last second
    garbage_per_s: float = ranged(5.0, 0.0, TENSION_GARBAGE_MAX_PER_S, "per s", lo_open=True)
    # fmt: on


TRACKER_TIMEOUT_RANGE_S = (0.01, 10.0)
TRACKER_BAUD_RANGE = TENSION_BAUD_RANGE


@dataclass(frozen=True)
class TrackerConfig:
    """The laser tracker (the optional ``[tracker]`` table): its serial port, baud rate and
    the longest wait for each reply (``drivers.tracker.TrackerReader``); safe ranges,
    checked on load, in the metadata."""

    port: str
    # fmt: off
    timeout_s: float = ranged(
        1.0, *TRACKER_TIMEOUT_RANGE_S, "s",
        "a reading takes a few ms; past 10 s a silent tracker holds a calibration up for nothing",
    )
    baudrate: int = ranged(115_200, *TRACKER_BAUD_RANGE)
    # fmt: on


DRIVE_KEYS = frozenset({"device_file", "sdo", "identity"})
"""The keys of ``[drives]`` (for every drive) and of ``[drives.MOTOR]`` (for one)."""

MAX_SDO_OVERLAY = 64
"""Most SDO writes one overlay (``sdo = {...}``) gives."""

IDENTITY_KEYS = ("vendor_id", "product_code", "revision", "serial")
"""The keys of an ``identity`` table: 0x1018 sub-indices 1..4, in that order."""

#: Objects hrm's bring-up writes itself (drivers.bringup.configure_drive): an overlay of
#: one of them would be overwritten, so it is refused.  (index, sub or None: every sub)
BRINGUP_OBJECTS: tuple[tuple[int, int | None], ...] = (
    (0x1016, None), (0x1017, None), (0x1400, None), (0x1600, None), (0x1800, None),
    (0x1A00, None), (0x6040, None), (0x6060, None), (0x607A, None), (0x607D, None),
    (0x6065, None), (0x605A, None), (0x60C2, None),
)  # fmt: skip

_SDO_KEY = re.compile(r"0x([0-9A-Fa-f]{4})(?::([0-9A-Fa-f]{1,2}))?")


@dataclass(frozen=True)
class SdoWrite:
    """One SDO write of an overlay: object (index, sub-index) and integer value.

    >>> SdoWrite(0x60A8, 0, 0x00B50000).label
    '0x60A8:00'
    """

    index: int
    sub: int
    value: int

    @property
    def label(self) -> str:
        return f"0x{self.index:04X}:{self.sub:02X}"


@dataclass(frozen=True)
class ExpectedIdentity:
    """The identity (0x1018) a drive must answer at boot; None: not checked.

    >>> ExpectedIdentity(vendor_id=0xFB).over(ExpectedIdentity(serial=7))
    ExpectedIdentity(vendor_id=251, product_code=None, revision=None, serial=7)
    """

    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None

    def over(self, base: ExpectedIdentity) -> ExpectedIdentity:
        """These values, and ``base``'s where these give none."""
        return ExpectedIdentity(
            *(
                mine if mine is not None else theirs
                for mine, theirs in zip(self.values(), base.values(), strict=True)
            )
        )

    def values(self) -> tuple[int | None, ...]:
        """(vendor_id, product_code, revision, serial): 0x1018 sub-indices 1..4."""
        return (self.vendor_id, self.product_code, self.revision, self.serial)

    def to_dict(self) -> dict[str, int]:
        return {k: v for k, v in zip(IDENTITY_KEYS, self.values(), strict=True) if v is not None}


@dataclass(frozen=True)
class DriveSpec:
    """What the box configuration says of one drive: its device file (None: the default),
    its SDO overlay and its expected identity."""

    device_file: Path | None = None
    sdo: tuple[SdoWrite, ...] = ()
    identity: ExpectedIdentity = ExpectedIdentity()

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.device_file is not None:
            out["device_file"] = str(self.device_file)
        if self.sdo:
            out["sdo"] = {w.label: w.value for w in self.sdo}
        if ident := self.identity.to_dict():
            out["identity"] = ident
        return out


@dataclass(frozen=True)
class DrivesConfig:
    """Each drive's device file, SDO overlay and expected identity (the optional
    ``[drives]`` table): ``device_file``, ``sdo`` and ``identity`` for every drive
    (``default``), the same keys in ``[drives.MOTOR]`` for one rope motor's (``motors``);
    a relative path is taken from the box file's folder; no file given: hrm's own EDS
    (:func:`drivers.eds_path`).  A motor's table that names its own device file starts
    afresh (the ``[drives]`` overlay and identity are the default device's); one that does
    not adds its overlay and identity to the default's (its own values win).

    >>> d = DrivesConfig(motor_files={"j01r0": Path("/x/epos4.dcf")})
    >>> d.device_file("j01r0").name, d.device_file("j01r1").name
    ('epos4.dcf', 'hrm_drive.eds')
    >>> d = DrivesConfig(
    ...     default=DriveSpec(sdo=(SdoWrite(0x60A8, 0, 0xB50000),)),
    ...     motors={"j01r0": DriveSpec(sdo=(SdoWrite(0x6091, 1, 2),))},
    ... )
    >>> [w.label for w in d.sdo_overlay("j01r0")], [w.label for w in d.sdo_overlay("j01r1")]
    (['0x60A8:00', '0x6091:01'], ['0x60A8:00'])
    """

    default_file: Path | None = None
    motor_files: Mapping[str, Path] = field(default_factory=dict)
    default: DriveSpec = DriveSpec()
    motors: Mapping[str, DriveSpec] = field(default_factory=dict)

    def device_file(self, motor_id: str) -> Path:
        """The device file of rope motor ``motor_id``'s drive (``motor_files`` or the
        motor's :class:`DriveSpec`, else ``default_file`` or the default's, else hrm's)."""
        own = self.motor_files.get(motor_id) or self.motors.get(motor_id, DriveSpec()).device_file
        if own is not None:
            return own
        default = self.default_file or self.default.device_file
        return eds_path() if default is None else default

    def _inherits(self, motor_id: str) -> bool:
        own = self.motor_files.get(motor_id) or self.motors.get(motor_id, DriveSpec()).device_file
        return own is None

    def sdo_overlay(self, motor_id: str) -> tuple[SdoWrite, ...]:
        """The SDO writes of ``motor_id``'s overlay, in the file's order (the motor's
        own after the default's, one write per object)."""
        own = self.motors.get(motor_id, DriveSpec()).sdo
        base = self.default.sdo if self._inherits(motor_id) else ()
        keys = {(w.index, w.sub) for w in own}
        return tuple(w for w in base if (w.index, w.sub) not in keys) + own

    def expected_identity(self, motor_id: str) -> ExpectedIdentity:
        """The identity ``motor_id``'s drive must answer (every value None: unchecked)."""
        own = self.motors.get(motor_id, DriveSpec()).identity
        return own.over(self.default.identity) if self._inherits(motor_id) else own

    def to_dict(self) -> dict[str, Any]:
        """The ``[drives]`` table (absolute paths; empty when every drive is hrm's own)."""
        out = replace(
            self.default, device_file=self.default_file or self.default.device_file
        ).to_dict()
        for motor in {**self.motor_files, **self.motors}:
            spec = self.motors.get(motor, DriveSpec())
            own = self.motor_files.get(motor) or spec.device_file
            out[motor] = replace(spec, device_file=own).to_dict()
        return out


@dataclass(frozen=True)
class BoxConfig:
    """Every bus of the box plus the control settings; immutable."""

    buses: tuple[BusConfig, ...]
    control: ControlConfig
    source: str
    _where: Mapping[str, tuple[int, int]] = field(default_factory=dict, repr=False)
    tension: TensionConfig | None = None  # the [tension] table: None, the box has no board
    tracker: TrackerConfig | None = None  # the [tracker] table: None, no laser tracker
    drives: DrivesConfig = DrivesConfig()  # the [drives] table: each drive's device file

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

    def with_bus_overrides(
        self, overrides: Sequence[BusOverride], where: str = "--bus"
    ) -> BoxConfig:
        """A copy with some buses opened on another interface and channel (and bitrate,
        when the override gives one), their nodes kept; a bus's ``options`` are kept only
        when its interface stays the same (they are that interface's ``can.Bus``
        arguments).  A bus named twice, or not in the file, is refused.

        >>> cfg = load_box_config(None)
        >>> new = cfg.with_bus_overrides([parse_bus_override("can1=virtual:left@500000")])
        >>> b = new.buses[1]
        >>> b.interface, b.channel, b.bitrate, len(b.nodes)
        ('virtual', 'left', 500000, 18)
        >>> cfg.with_bus_overrides([parse_bus_override("can7=virtual:x")])
        Traceback (most recent call last):
        ...
        drivers.config.BusConfigError: --bus can7=virtual:x: no bus 'can7' in ...(buses: can0, can1)
        """
        names = [b.name for b in self.buses]
        by_name: dict[str, BusOverride] = {}
        for o in overrides:
            w = f"{where} {o.text}"
            if o.name not in names:
                raise BusConfigError(
                    f"{w}: no bus {o.name!r} in {self.source} (buses: {', '.join(names)})"
                )
            if o.name in by_name:
                first = by_name[o.name].text
                raise BusConfigError(f"{w}: bus {o.name} is already given as {first}")
            _check_interface(o.interface, w)
            by_name[o.name] = o
        buses = []
        for b in self.buses:
            o = by_name.get(b.name)
            if o is not None:
                b = replace(
                    b,
                    interface=o.interface,
                    channel=o.channel,
                    bitrate=b.bitrate if o.bitrate is None else o.bitrate,
                    options=b.options if o.interface == b.interface else {},
                )
            buses.append(b)
        if by_name:
            given = " ".join(f"{where} {o.text}" for o in by_name.values())
            _check_distinct_channels(buses, f"{self.source} with {given}")
        return replace(self, buses=tuple(buses))

    def with_tension(self, **changes: Any) -> BoxConfig:
        """A copy with a ``[tension]`` table (or some of its values) changed, validated
        again (e.g. the simulated board's pseudo-terminal as the port)."""
        old = {} if self.tension is None else self.to_dict()["tension"]
        return replace(self, tension=_tension_from({**old, **changes}, self.source))

    def with_tracker(self, **changes: Any) -> BoxConfig:
        """A copy with a ``[tracker]`` table (or some of its values) changed, validated
        again (e.g. the simulated tracker's pseudo-terminal as the port)."""
        old = {} if self.tracker is None else self.to_dict()["tracker"]
        return replace(self, tracker=_tracker_from({**old, **changes}, self.source))

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
            **({} if self.tension is None else {"tension": asdict(self.tension)}),
            **({} if self.tracker is None else {"tracker": asdict(self.tracker)}),
            **({"drives": d} if (d := self.drives.to_dict()) else {}),
        }


@dataclass(frozen=True)
class BusOverride:
    """One bus replaced from the command line: ``NAME=INTERFACE:CHANNEL[@BITRATE]``."""

    name: str
    interface: str
    channel: str | int
    bitrate: int | None  # None: the bus keeps the file's (or python-can's) bitrate
    text: str  # as given, for messages


BUS_OVERRIDE_FORM = "NAME=INTERFACE:CHANNEL[@BITRATE]"


def parse_bus_override(text: str) -> BusOverride:
    """Parse ``NAME=INTERFACE:CHANNEL[@BITRATE]`` (the ``--bus`` option).

    The channel is everything after the first ``:`` (an IPv6 group keeps its colons) up to
    a last ``@`` followed by digits; a channel of digits only is an integer (as python-can's
    configuration reads it).  A channel that itself contains ``@`` (slcan's ``PORT@BAUD``)
    needs the ``@BITRATE`` after it.  Raises :class:`BusConfigError` naming what is wrong.

    >>> o = parse_bus_override("can0=socketcan:can3@500000")
    >>> o.name, o.interface, o.channel, o.bitrate
    ('can0', 'socketcan', 'can3', 500000)
    >>> parse_bus_override("a=kvaser:0").channel
    0
    >>> parse_bus_override("can0=socketcan")
    Traceback (most recent call last):
    ...
    drivers.config.BusConfigError: 'can0=socketcan': expected NAME=INTERFACE:CHANNEL[@BITRATE]
    """
    name, eq, rest = text.partition("=")
    interface, colon, channel_text = rest.partition(":")
    if not (eq and colon and name and interface and channel_text):
        raise BusConfigError(f"{text!r}: expected {BUS_OVERRIDE_FORM}")
    if not BUS_NAME_PATTERN.fullmatch(name):
        raise BusConfigError(
            f"{text!r}: bus name {name!r} may only use letters, digits, '_' and '-'"
        )
    bitrate: int | None = None
    head, at, tail = channel_text.rpartition("@")
    if at:
        if not (tail.isascii() and tail.isdigit()) or not head:
            raise BusConfigError(
                f"{text!r}: bitrate {tail!r} after '@' must be an integer in 1..{BITRATE_MAX}"
            )
        if len(tail) > 7 or not 0 < int(tail) <= BITRATE_MAX:
            raise BusConfigError(f"{text!r}: bitrate {tail} outside 1..{BITRATE_MAX}")
        bitrate, channel_text = int(tail), head
    channel: str | int = (
        int(channel_text) if channel_text.isascii() and channel_text.isdigit() else channel_text
    )
    return BusOverride(name, interface, channel, bitrate, text)


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


FEEDBACK_BLIND_MAX_S = 0.5
"""Longest the arm may move without position feedback: ``missing_tpdo_cycles`` periods."""

HEARTBEATS_PER_TIMEOUT = 3
"""A heartbeat timeout spans at least this many heartbeat periods: one lost heartbeat and
a late one do not stop the arm, a dead producer does."""

CONTROL_RELATIONS: tuple[str, ...] = (
    "host_heartbeat_ms >= 1000 / rate_hz (the host heartbeat goes out on control deadlines)",
    f"heartbeat_timeout_ms >= {HEARTBEATS_PER_TIMEOUT} x host_heartbeat_ms (drives' 0x1016)",
    f"heartbeat_timeout_ms >= {HEARTBEATS_PER_TIMEOUT} x node_heartbeat_ms (the host's watch)",
    f"missing_tpdo_cycles / rate_hz <= {FEEDBACK_BLIND_MAX_S:g} s (time without feedback)",
)
"""Relations between ``[control]`` values, checked after the ranges."""


def _shown(value: Any) -> str:
    """A value for a message: its repr, or the start of it for a number of many digits.

    >>> _shown(3), _shown(10**60)
    ('3', '1000000000000000000... (61 digits)')
    """
    text = repr(value)
    return text if len(text) <= 24 else f"{text[:19]}... ({len(text)} digits)"


def _relation_problem(c: ControlConfig) -> tuple[str, str] | None:
    """(key, why) of the first relation ``c`` breaks, or ``None``."""
    period_ms = 1000.0 / c.rate_hz
    n = HEARTBEATS_PER_TIMEOUT
    if c.host_heartbeat_ms < period_ms:
        return "host_heartbeat_ms", (
            f"must be at least one control period ({period_ms:g} ms at {c.rate_hz:g} Hz): "
            "the host heartbeat goes out on control deadlines"
        )
    for key in ("host_heartbeat_ms", "node_heartbeat_ms"):
        beat = getattr(c, key)
        if c.heartbeat_timeout_ms < n * beat:
            return "heartbeat_timeout_ms", (
                f"must be at least {n} x {key} ({n} x {beat} = {n * beat} ms) so that one "
                "lost heartbeat does not stop the arm"
            )
    blind_s = c.missing_tpdo_cycles / c.rate_hz
    if blind_s > FEEDBACK_BLIND_MAX_S + 1e-12:
        return "missing_tpdo_cycles", (
            f"must keep the arm at most {FEEDBACK_BLIND_MAX_S:g} s without feedback "
            f"({c.missing_tpdo_cycles} cycles at {c.rate_hz:g} Hz are {blind_s:g} s)"
        )
    return None


def _control_from(doc: Mapping[str, Any], where: str) -> ControlConfig:
    if not isinstance(doc, Mapping):
        raise BusConfigError(f"{where}: [control] must be a table")

    def outside(key: str, value: Any, s: Spec, _: Mapping[str, Any]) -> str:
        return f"control.{key} = {_shown(value)} outside {s.text()}; {s.why}"

    c = ControlConfig(**read_numbers(ControlConfig, doc, where, BusConfigError, "control", outside))
    problem = rate_problem(c.rate_hz)
    if problem is not None:
        raise BusConfigError(f"{where}: control.rate_hz {problem}, got {c.rate_hz!r}")
    relation = _relation_problem(c)
    if relation is not None:
        key, why = relation
        raise BusConfigError(f"{where}: control.{key} = {getattr(c, key)!r} {why}")
    return c


def _device_from(cls: type[_Device], doc: Any, table: str, device: str, where: str) -> _Device:
    """The ``[tension]`` or ``[tracker]`` table: a serial ``port`` and numbers, every one
    checked against its safe range."""
    if not isinstance(doc, Mapping):
        raise BusConfigError(f"{where}: [{table}] must be a table")
    kinds = number_kinds(cls)

    def outside(key: str, value: Any, s: Spec, values: Mapping[str, Any]) -> str:
        shown = kinds[key](value) if abs(value) < 1e300 else value
        if s.above is not None:
            first = f"must exceed {s.above} ({values[s.above]:g} {s.unit})"
            return f"{table}.{key} {first} and be <= {s.hi:g} {s.unit}, got {shown!r}"
        rng = s.text() if kinds[key] is int else s.interval()
        return f"{table}.{key} must be in {rng}, got {shown!r}"

    refuse_unknown(doc, kinds.keys() | _PORT, where, BusConfigError, table)
    if "port" not in doc:
        raise BusConfigError(f"{where}: {table}.port: missing ({device} serial port)")
    port = doc["port"]
    if not isinstance(port, str) or not port.strip():
        raise BusConfigError(f"{where}: {table}.port: expected a serial port path, got {port!r}")
    values = read_numbers(cls, doc, where, BusConfigError, table, outside, skip=_PORT)
    return cls(port=port, **values)


_PORT = frozenset({"port"})
_Device = TypeVar("_Device", TensionConfig, TrackerConfig)


def _tension_from(doc: Any, where: str) -> TensionConfig:
    """The ``[tension]`` table, every value checked against its safe range."""
    return _device_from(TensionConfig, doc, "tension", "the board's", where)


def _tracker_from(doc: Any, where: str) -> TrackerConfig:
    """The ``[tracker]`` table, every value checked against its safe range."""
    return _device_from(TrackerConfig, doc, "tracker", "the tracker's", where)


def _device_file_path(value: Any, where: str, base_dir: Path | None) -> Path:
    if not isinstance(value, str) or not value.strip():
        raise BusConfigError(f"{where}: expected the path of an EDS or DCF file, got {value!r}")
    path = Path(value).expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return path.absolute()


def _u32(value: Any, where: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= 0xFFFFFFFF:
        raise BusConfigError(f"{where}: expected an integer 0..0xFFFFFFFF, got {value!r}")
    return value


def _sdo_overlay(doc: Any, where: str) -> tuple[SdoWrite, ...]:
    """An ``sdo`` table: ``"0xIIII" = value`` or ``"0xIIII:SS" = value`` (sub-index hex)."""
    if not isinstance(doc, Mapping):
        raise BusConfigError(f'{where}: must be a table ("0x60A8" = 0x00B50000, ...)')
    if len(doc) > MAX_SDO_OVERLAY:
        raise BusConfigError(f"{where}: more than {MAX_SDO_OVERLAY} writes")
    out: list[SdoWrite] = []
    seen: set[tuple[int, int]] = set()
    for key, value in doc.items():
        m = _SDO_KEY.fullmatch(str(key))
        w = f"{where}.{key}"
        if m is None:
            raise BusConfigError(
                f'{w}: expected an object "0xIIII" or "0xIIII:SS" (index and sub-index in hex)'
            )
        index, sub = int(m.group(1), 16), int(m.group(2) or "0", 16)
        if index < 0x1000:
            raise BusConfigError(f"{w}: 0x{index:04X} is not an object (data types below 0x1000)")
        if (index, sub) in seen:
            raise BusConfigError(f"{w}: object given twice")
        for bi, bs in BRINGUP_OBJECTS:
            if index == bi and bs in (None, sub):
                raise BusConfigError(
                    f"{w}: hrm's bring-up writes 0x{index:04X} itself (from [control] and "
                    "the rope layer's limits)"
                )
        if not isinstance(value, int) or isinstance(value, bool):
            raise BusConfigError(f"{w}: expected an integer value, got {value!r}")
        if not -(2**63) <= value < 2**64:
            raise BusConfigError(f"{w}: {value} outside 64 bits")
        seen.add((index, sub))
        out.append(SdoWrite(index, sub, value))
    return tuple(out)


def _identity(doc: Any, where: str) -> ExpectedIdentity:
    if not isinstance(doc, Mapping):
        raise BusConfigError(f"{where}: must be a table (vendor_id = 0x..., serial = ...)")
    for key in doc:
        if key not in IDENTITY_KEYS:
            hint = unknown_key(str(key), frozenset(IDENTITY_KEYS))
            raise BusConfigError(f"{where}.{key}: unknown key{hint}")
    return ExpectedIdentity(
        *(None if k not in doc else _u32(doc[k], f"{where}.{k}") for k in IDENTITY_KEYS)
    )


def _drive_spec(doc: Mapping[str, Any], where: str, base_dir: Path | None) -> DriveSpec:
    """The keys of ``[drives]`` or of ``[drives.MOTOR]`` (``where``: that table's name)."""
    return DriveSpec(
        device_file=None
        if "device_file" not in doc
        else _device_file_path(doc["device_file"], f"{where}.device_file", base_dir),
        sdo=() if "sdo" not in doc else _sdo_overlay(doc["sdo"], f"{where}.sdo"),
        identity=ExpectedIdentity()
        if "identity" not in doc
        else _identity(doc["identity"], f"{where}.identity"),
    )


def _drives_from(
    doc: Any, where: str, motors: Mapping[str, Any], base_dir: Path | None
) -> DrivesConfig:
    """The ``[drives]`` table: ``device_file``, ``sdo`` and ``identity`` for every drive,
    ``[drives.MOTOR]`` tables (one per rope motor of the buses) for one."""
    if not isinstance(doc, Mapping):
        raise BusConfigError(f"{where}: [drives] must be a table")
    default = _drive_spec(
        {k: v for k, v in doc.items() if k in DRIVE_KEYS}, f"{where}: drives", base_dir
    )
    own: dict[str, DriveSpec] = {}
    for key, value in doc.items():
        if key in DRIVE_KEYS:
            continue
        if key in motors:
            if not isinstance(value, Mapping):
                raise BusConfigError(f"{where}: drives.{key}: must be a table (device_file = ...)")
            for sub in value:
                if sub not in DRIVE_KEYS:
                    hint = unknown_key(str(sub), DRIVE_KEYS)
                    raise BusConfigError(f"{where}: drives.{key}.{sub}: unknown key{hint}")
            own[str(key)] = _drive_spec(value, f"{where}: drives.{key}", base_dir)
        else:
            raise BusConfigError(
                f"{where}: drives.{key}: neither a key of [drives] "
                f"({', '.join(sorted(DRIVE_KEYS))}) nor a rope motor of the buses"
            )
    return DrivesConfig(
        default_file=default.device_file,
        motor_files={m: s.device_file for m, s in own.items() if s.device_file is not None},
        default=default,
        motors=own,
    )


def box_config_from_dict(
    doc: Mapping[str, Any], source: str, base_dir: Path | None = None
) -> BoxConfig:
    """Validate a parsed bus configuration and build a :class:`BoxConfig` (``base_dir``:
    the folder relative device-file paths are taken from)."""
    where = source
    unknown = set(doc) - {"control", "buses", "tension", "tracker", "drives"}
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
        if "interface" not in b:
            b = _with_python_can_config(b, str(name), w)
        for key in ("interface", "channel", "bitrate", "nodes"):
            if key not in b:
                raise BusConfigError(f"{w}: missing key '{key}'")
        interface = _check_interface(b["interface"], f"{w}.interface")
        channel = b["channel"]
        if isinstance(channel, bool) or not isinstance(channel, str | int):
            raise BusConfigError(f"{w}.channel: expected a string or integer, got {channel!r}")
        bitrate = b["bitrate"]
        rate = _BITRATE
        if isinstance(bitrate, bool) or not isinstance(bitrate, int) or not rate.contains(bitrate):
            raise BusConfigError(
                f"{w}.bitrate: expected an integer in {rate.text()}, got {bitrate!r}"
            )
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
            if not NODE_IDS.contains(node):
                raise BusConfigError(f"{wn}: node id {node} outside {NODE_IDS.text()}")
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
    tension = _tension_from(doc["tension"], where) if "tension" in doc else None
    tracker = _tracker_from(doc["tracker"], where) if "tracker" in doc else None
    drives = _drives_from(doc["drives"], where, placed, base_dir) if "drives" in doc else None
    return BoxConfig(
        buses=tuple(buses),
        control=control,
        source=source,
        _where=placed,
        tension=tension,
        tracker=tracker,
        drives=DrivesConfig() if drives is None else drives,
    )


_BITRATE = specs(BusConfig)["bitrate"]

PYTHON_CAN_CONFIG_WHERE = (
    "CAN_{KEY}_{name} or CAN_{KEY}, or {key} in [{name}] or [default] of ~/can.conf"
)
"""Where python-can's configuration takes a value from, for messages."""

_PYTHON_CAN_KEYS = ("interface", "channel", "bitrate")


def _with_python_can_config(b: Mapping[str, Any], name: str, where: str) -> dict[str, Any]:
    """A bus table without an ``interface``, completed from python-can's configuration
    (:func:`can.util.load_config`, context: the bus's name); the table's own ``channel``,
    ``bitrate`` and ``options`` win.  Other keys python-can's configuration gives become
    ``options`` (``can.Bus`` keyword arguments)."""
    given = {k: b[k] for k in ("channel", "bitrate") if k in b}
    try:
        found = dict(can.util.load_config(config=given, context=name))
    except can.CanInterfaceNotImplementedError as exc:
        there = PYTHON_CAN_CONFIG_WHERE.format(KEY="INTERFACE", key="interface", name=name)
        raise BusConfigError(
            f"{where}: no interface in the file and none python-can can use in its "
            f"configuration ({exc}); set interface here, or {there}"
        ) from None
    except Exception as exc:  # a malformed CAN_CONFIG (JSON), port or state value
        raise BusConfigError(
            f"{where}: python-can's configuration: {type(exc).__name__}: {exc}"
        ) from None
    out = {k: v for k, v in b.items() if k not in _PYTHON_CAN_KEYS}
    for key in _PYTHON_CAN_KEYS:
        if found.get(key) is None:
            there = PYTHON_CAN_CONFIG_WHERE.format(KEY=key.upper(), key=key, name=name)
            raise BusConfigError(
                f"{where}: interface {found['interface']!r} from python-can's configuration, "
                f"but no {key}: set {key} here, or {there}"
            )
        out[key] = found[key]
    extra = {k: v for k, v in found.items() if k not in _PYTHON_CAN_KEYS}
    if extra:
        options = b.get("options", {})
        if isinstance(options, Mapping):
            out["options"] = {**extra, **options}
    return out


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
    return box_config_from_dict(doc, source, base_dir=p.parent)
