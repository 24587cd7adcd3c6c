"""Bring-up of CiA 402 drives: SDO configuration and the device-control state machine.

canopen's ``BaseNode402`` setters swallow timeouts, so the state machine is
driven here: every controlword write is followed by statusword reads until the
expected state shows, or a :class:`StateTimeoutError` naming the node, the
state reached and the state expected.  SDO aborts and timeouts become
:class:`SdoError` (a :class:`DriverError`) naming bus, node, object and abort
code.  Nothing here sends a motion command: the target position is set to the
actual position before operation is enabled.

Every function takes a :class:`DriveLink` (a canopen ``RemoteNode`` plus the
names needed in messages) and explicit settings; none keeps state.

>>> import canopen
>>> from drivers import eds_path
>>> link = DriveLink(canopen.RemoteNode(3, canopen.import_od(str(eds_path()))), "can0", "j01r2")
>>> link.label
'j01r2 (bus can0 node 3)'
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import canopen

from drivers.protocol import cia402 as c
from hrm_ctrl.errors import DriverError


class SdoError(DriverError):
    """An SDO transfer was aborted by the drive or got no answer in time."""


class StateTimeoutError(DriverError):
    """A drive did not reach the expected CiA 402 state in time."""


class BootupError(DriverError):
    """Some nodes did not send their boot-up frame in time."""


@dataclass(frozen=True)
class DriveLink:
    """A drive as the bring-up sees it: canopen node + where it is."""

    node: canopen.RemoteNode
    bus: str
    motor: str

    @property
    def node_id(self) -> int:
        return int(self.node.id)

    @property
    def label(self) -> str:
        return f"{self.motor} (bus {self.bus} node {self.node_id})"


@dataclass(frozen=True)
class DriveSettings:
    """Values written to every drive during configuration."""

    period_s: float
    host_node_id: int
    host_heartbeat_timeout_ms: int
    node_heartbeat_ms: int
    counts_min: int
    counts_max: int
    following_error_window_counts: int
    quick_stop_option_code: int


def sdo_write(link: DriveLink, index: int, subindex: int, value: Any) -> None:
    """Write one object through the node's SDO client (encoded per the EDS)."""
    try:
        var = link.node.sdo[index][subindex] if subindex else _var(link, index)
        var.raw = value
    except canopen.SdoAbortedError as exc:
        raise SdoError(
            f"{link.label}: SDO write 0x{index:04X}:{subindex:02X} = {value!r} aborted: "
            f"{c.describe_sdo_abort(exc.code)}"
        ) from None
    except canopen.SdoCommunicationError as exc:
        raise SdoError(
            f"{link.label}: SDO write 0x{index:04X}:{subindex:02X}: {exc} "
            f"(timeout {link.node.sdo.RESPONSE_TIMEOUT:g} s)"
        ) from None
    except (KeyError, ValueError, TypeError) as exc:
        raise SdoError(
            f"{link.label}: cannot write 0x{index:04X}:{subindex:02X} = {value!r} ({exc})"
        ) from None
    except DriverError as exc:  # the request could not be sent (bus failure)
        raise SdoError(
            f"{link.label}: SDO write 0x{index:04X}:{subindex:02X} = {value!r}: {exc}"
        ) from None


def sdo_read(link: DriveLink, index: int, subindex: int = 0) -> Any:
    """Read one object through the node's SDO client (decoded per the EDS)."""
    try:
        var = link.node.sdo[index][subindex] if subindex else _var(link, index)
        return var.raw
    except canopen.SdoAbortedError as exc:
        raise SdoError(
            f"{link.label}: SDO read 0x{index:04X}:{subindex:02X} aborted: "
            f"{c.describe_sdo_abort(exc.code)}"
        ) from None
    except canopen.SdoCommunicationError as exc:
        raise SdoError(
            f"{link.label}: SDO read 0x{index:04X}:{subindex:02X}: {exc} "
            f"(timeout {link.node.sdo.RESPONSE_TIMEOUT:g} s)"
        ) from None
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise SdoError(f"{link.label}: cannot read 0x{index:04X}:{subindex:02X} ({exc})") from None
    except DriverError as exc:  # the request could not be sent (bus failure)
        raise SdoError(f"{link.label}: SDO read 0x{index:04X}:{subindex:02X}: {exc}") from None


def _var(link: DriveLink, index: int) -> Any:
    entry = link.node.sdo[index]
    # A VAR object is itself the variable; records/arrays need a sub-index.
    return entry if hasattr(entry, "raw") else entry[0]


def _map_pdo(
    link: DriveLink, pdo_map: Any, cob_id: int, objects: tuple[int, ...], name: str
) -> None:
    try:
        pdo_map.clear()
        for index in objects:
            pdo_map.add_variable(index)
        pdo_map.cob_id = cob_id
        pdo_map.trans_type = c.PDO_TRANSMISSION_SYNCHRONOUS
        pdo_map.enabled = True
        pdo_map.save()
    except canopen.SdoAbortedError as exc:
        raise SdoError(
            f"{link.label}: mapping {name} aborted: {c.describe_sdo_abort(exc.code)}"
        ) from None
    except canopen.SdoCommunicationError as exc:
        raise SdoError(f"{link.label}: mapping {name}: {exc}") from None
    # The scheduler reads the PDOs itself; canopen need not decode every frame.
    try:
        link.node.network.unsubscribe(cob_id, pdo_map.on_message)
    except (KeyError, ValueError):
        pass


def configure_drive(link: DriveLink, s: DriveSettings) -> None:
    """SDO configuration (node pre-operational): PDO mappings, heartbeats, limits,
    interpolation period, quick stop option, mode CSP (checked on 0x6061)."""
    nid = link.node_id
    sdo_write(link, c.OD_PRODUCER_HEARTBEAT_TIME, 0, s.node_heartbeat_ms)
    sdo_write(
        link,
        c.OD_CONSUMER_HEARTBEAT_TIME,
        1,
        c.consumer_heartbeat_entry(s.host_node_id, s.host_heartbeat_timeout_ms),
    )
    _map_pdo(
        link,
        link.node.rpdo[1],
        c.COB_RPDO1 + nid,
        (c.OD_CONTROLWORD, c.OD_TARGET_POSITION),
        "RPDO1 (controlword, target position)",
    )
    _map_pdo(
        link,
        link.node.tpdo[1],
        c.COB_TPDO1 + nid,
        (c.OD_STATUSWORD, c.OD_POSITION_ACTUAL_VALUE),
        "TPDO1 (statusword, position actual value)",
    )
    sdo_write(link, c.OD_SOFTWARE_POSITION_LIMIT, 1, int(s.counts_min))
    sdo_write(link, c.OD_SOFTWARE_POSITION_LIMIT, 2, int(s.counts_max))
    value, index = c.interpolation_time_period(s.period_s)
    sdo_write(link, c.OD_INTERPOLATION_TIME_PERIOD, 1, value)
    sdo_write(link, c.OD_INTERPOLATION_TIME_PERIOD, 2, index)
    sdo_write(link, c.OD_FOLLOWING_ERROR_WINDOW, 0, int(s.following_error_window_counts))
    sdo_write(link, c.OD_QUICK_STOP_OPTION_CODE, 0, int(s.quick_stop_option_code))
    sdo_write(link, c.OD_MODES_OF_OPERATION, 0, c.MODE_CSP)
    shown = sdo_read(link, c.OD_MODES_OF_OPERATION_DISPLAY)
    if shown != c.MODE_CSP:
        raise DriverError(
            f"{link.label}: modes of operation display is {shown}, expected {c.MODE_CSP} (CSP)"
        )


def read_state(link: DriveLink) -> tuple[c.State402, int]:
    """(state, statusword) read by SDO."""
    sw = int(sdo_read(link, c.OD_STATUSWORD))
    return c.decode_state(sw), sw


def wait_state(link: DriveLink, expected: c.State402, timeout_s: float, after: str) -> int:
    """Poll the statusword until it shows ``expected``; return the statusword.

    Raises :class:`StateTimeoutError` naming the last state seen.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        state, sw = read_state(link)
        if state is expected:
            return sw
        if time.monotonic() >= deadline:
            raise StateTimeoutError(
                f"{link.label}: statusword 0x{sw:04X} ({state.name}) {timeout_s:g} s after "
                f"{after}, expected {expected.name}"
            )
        time.sleep(0.001)


def command(link: DriveLink, controlword: int, expected: c.State402, timeout_s: float) -> int:
    """Write a controlword and wait for the expected state."""
    sdo_write(link, c.OD_CONTROLWORD, 0, controlword)
    return wait_state(link, expected, timeout_s, f"controlword 0x{controlword:04X}")


def enable_operation(
    link: DriveLink,
    timeout_s: float,
    counts_min: int | None = None,
    counts_max: int | None = None,
) -> int:
    """CiA 402 state machine to OPERATION_ENABLED, checking the statusword at each step.

    A drive in FAULT gets one fault reset (0→1 edge of bit 7).  The actual position
    is checked against ``counts_min``/``counts_max`` (the rope layer's limits; outside:
    :class:`DriverError`, the drive stays SWITCHED_ON, not enabled); then the target
    position is set to it before operation is enabled, so nothing moves.
    Returns the actual position (counts).
    """
    state, sw = read_state(link)
    if state in (c.State402.FAULT, c.State402.FAULT_REACTION_ACTIVE):
        if state is c.State402.FAULT_REACTION_ACTIVE:
            wait_state(link, c.State402.FAULT, timeout_s, "fault reaction")
        sdo_write(link, c.OD_CONTROLWORD, 0, c.CW_DISABLE_VOLTAGE)
        command(link, c.CW_FAULT_RESET, c.State402.SWITCH_ON_DISABLED, timeout_s)
        state = c.State402.SWITCH_ON_DISABLED
    if state is c.State402.NOT_READY_TO_SWITCH_ON:
        wait_state(link, c.State402.SWITCH_ON_DISABLED, timeout_s, "power-on")
        state = c.State402.SWITCH_ON_DISABLED
    if state is c.State402.QUICK_STOP_ACTIVE:
        command(link, c.CW_DISABLE_VOLTAGE, c.State402.SWITCH_ON_DISABLED, timeout_s)
        state = c.State402.SWITCH_ON_DISABLED
    if state is c.State402.OPERATION_ENABLED:
        # Start from a known state: back to switched on, then enable again below.
        command(link, c.CW_DISABLE_OPERATION, c.State402.SWITCHED_ON, timeout_s)
        state = c.State402.SWITCHED_ON
    if state is c.State402.SWITCH_ON_DISABLED:
        command(link, c.CW_SHUTDOWN, c.State402.READY_TO_SWITCH_ON, timeout_s)
        state = c.State402.READY_TO_SWITCH_ON
    if state is c.State402.READY_TO_SWITCH_ON:
        command(link, c.CW_SWITCH_ON, c.State402.SWITCHED_ON, timeout_s)
        state = c.State402.SWITCHED_ON
    if state is not c.State402.SWITCHED_ON:
        raise StateTimeoutError(
            f"{link.label}: statusword 0x{sw:04X} ({state.name}) cannot be brought to SWITCHED_ON"
        )
    actual = int(sdo_read(link, c.OD_POSITION_ACTUAL_VALUE))
    lo = -(2**31) if counts_min is None else int(counts_min)
    hi = 2**31 - 1 if counts_max is None else int(counts_max)
    if not lo <= actual <= hi:
        raise DriverError(
            f"{link.label}: actual position {actual} counts is outside the limits "
            f"[{lo}, {hi}]: not enabled"
        )
    sdo_write(link, c.OD_TARGET_POSITION, 0, actual)
    command(link, c.CW_ENABLE_OPERATION, c.State402.OPERATION_ENABLED, timeout_s)
    return actual
