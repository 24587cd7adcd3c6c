"""Bring-up of CiA 402 drives: SDO configuration and the device-control state machine.

canopen's ``BaseNode402`` setters swallow timeouts, so the state machine is
driven here, along the CiA 402 transition table (:func:`drivers.protocol.cia402.route`):
every controlword write is followed by statusword reads until the table's next
state shows, or a :class:`StateTimeoutError` naming the node, the state reached
and the state expected.  SDO aborts and timeouts become
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

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import canopen

from drivers.config import ExpectedIdentity, SdoWrite
from drivers.protocol import cia301, cia402
from hrm_ctrl.errors import DriverError, HrmError


class SdoError(DriverError):
    """An SDO transfer was aborted by the drive or got no answer in time (the error of
    canopen or of the bus is chained as its cause)."""


class StateTimeoutError(DriverError):
    """A drive did not reach the expected CiA 402 state in time."""


class BootupError(DriverError):
    """Some nodes did not send their boot-up frame in time, or more than one device
    answers as the same node."""


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


class IdentityMismatchError(DriverError):
    """A drive answered another identity (0x1018) than the box configuration expects."""


@dataclass(frozen=True)
class DriveSetup:
    """What the bring-up writes and checks on one drive beyond :class:`DriveSettings`, from
    its device file and the box configuration (:meth:`drivers.device_check.NodeCheck.setup`):
    0x60C2 (value, index) in the drive's own encoding (None: hrm's,
    :func:`cia402.interpolation_time_period`), the SDO overlay (written first, in order),
    the identity the drive must answer (checked before anything is written) and the
    quick-stop deceleration 0x6085 in the drive's unit (None: not written;
    :meth:`drivers.device_check.BoxCheck.setups`), and for a drive without a heartbeat
    consumer the node guarding the host does (guard time 0x100C in ms, life time factor
    0x100D; None: heartbeats)."""

    interpolation: tuple[int, int] | None = None
    sdo: tuple[SdoWrite, ...] = ()
    identity: ExpectedIdentity = field(default_factory=ExpectedIdentity)
    quick_stop_deceleration: int | None = None
    guarding: tuple[int, int] | None = None


#: 0x1018 sub-index -> name, as the identity check names them
IDENTITY_NAMES = {1: "vendor-ID", 2: "product code", 3: "revision", 4: "serial number"}


def identity_mismatches(
    expected: ExpectedIdentity, found: tuple[int, int, int, int], simulated: bool
) -> list[str]:
    """``0x1018:02 (product code) expected 0x00000011, found 0x65510000`` for each value
    the drive answered differently from ``expected``; on a simulated box (``simulated``)
    the vendor-ID and serial number are not compared (a simulated drive answers vendor 0
    and its simulated arm's serial), the product code and revision are (its device file's).

    >>> identity_mismatches(ExpectedIdentity(product_code=0x11), (0x26C, 0x12, 1, 2), False)
    ['0x1018:02 (product code) expected 0x00000011, found 0x00000012']
    >>> identity_mismatches(ExpectedIdentity(vendor_id=0x26C), (0, 0x11, 1, 2), True)
    []
    """
    out = []
    for sub, (want, got) in enumerate(zip(expected.values(), found, strict=True), start=1):
        if want is None or (simulated and sub in (1, 4)):
            continue
        if want != got:
            out.append(
                f"0x1018:{sub:02X} ({IDENTITY_NAMES[sub]}) expected 0x{want:08X}, found 0x{got:08X}"
            )
    return out


def check_identity(
    link: DriveLink, expected: ExpectedIdentity, found: tuple[int, int, int, int], simulated: bool
) -> None:
    """:class:`IdentityMismatchError` naming the drive and the first mismatch (and how many
    more) when the drive is not the one expected (:func:`identity_mismatches`)."""
    problems = identity_mismatches(expected, found, simulated)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise IdentityMismatchError(
            f"{link.label}: identity {problems[0]}{more}: not the drive the box configuration "
            "names; nothing written"
        )


@dataclass(frozen=True)
class DriveSettings:
    """Values written to every drive during configuration (``setup``: this drive's own)."""

    period_s: float
    host_node_id: int
    host_heartbeat_timeout_ms: int
    node_heartbeat_ms: int
    counts_min: int
    counts_max: int
    following_error_window_counts: int
    quick_stop_option_code: int
    setup: DriveSetup = DriveSetup()


def sdo_write(link: DriveLink, index: int, subindex: int, value: Any) -> None:
    """Write one object through the node's SDO client (encoded per the EDS)."""
    try:
        var = link.node.sdo[index][subindex] if subindex else _var(link, index)
        var.raw = value
    except canopen.SdoAbortedError as exc:
        raise SdoError(
            f"{link.label}: SDO write 0x{index:04X}:{subindex:02X} = {value!r} aborted: "
            f"{cia301.describe_sdo_abort(exc.code)}"
        ) from exc
    except canopen.SdoCommunicationError as exc:
        raise SdoError(
            f"{link.label}: SDO write 0x{index:04X}:{subindex:02X}: {exc} "
            f"(timeout {link.node.sdo.RESPONSE_TIMEOUT:g} s)"
        ) from exc
    except (KeyError, ValueError, TypeError) as exc:
        raise SdoError(
            f"{link.label}: cannot write 0x{index:04X}:{subindex:02X} = {value!r} ({exc})"
        ) from exc
    except DriverError as exc:  # the request could not be sent (bus failure)
        raise SdoError(
            f"{link.label}: SDO write 0x{index:04X}:{subindex:02X} = {value!r}: {exc}"
        ) from exc


def sdo_read(link: DriveLink, index: int, subindex: int = 0) -> Any:
    """Read one object through the node's SDO client (decoded per the EDS)."""
    try:
        var = link.node.sdo[index][subindex] if subindex else _var(link, index)
        return var.raw
    except canopen.SdoAbortedError as exc:
        raise SdoError(
            f"{link.label}: SDO read 0x{index:04X}:{subindex:02X} aborted: "
            f"{cia301.describe_sdo_abort(exc.code)}"
        ) from exc
    except canopen.SdoCommunicationError as exc:
        raise SdoError(
            f"{link.label}: SDO read 0x{index:04X}:{subindex:02X}: {exc} "
            f"(timeout {link.node.sdo.RESPONSE_TIMEOUT:g} s)"
        ) from exc
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise SdoError(f"{link.label}: cannot read 0x{index:04X}:{subindex:02X} ({exc})") from exc
    except DriverError as exc:  # the request could not be sent (bus failure)
        raise SdoError(f"{link.label}: SDO read 0x{index:04X}:{subindex:02X}: {exc}") from exc


def sdo_answers(link: DriveLink, wait_s: float, index: int = cia301.OD_DEVICE_TYPE) -> int:
    """How many answers one SDO upload request of ``index``:00 gets within ``wait_s``
    (counted until then, or until a second one): 1 from a drive, 0 from none, 2 when more
    than one device answers as the node (a second box or a node-id clash: canopen's client
    takes the first answer and drops the others unseen).  Sent and counted as raw frames,
    so no other SDO transfer with the node may be under way; an upload response or abort
    naming ``index``:00 counts.  A request that cannot be sent: :class:`SdoError`."""
    request = bytes(cia301.make_sdo_upload_request(link.node_id, index, 0).data)
    answer_id = cia301.COB_SDO_TX + link.node_id
    kinds = (cia301.SDO_SCS_INITIATE_UPLOAD, cia301.SDO_CS_ABORT)
    heard = threading.Condition()
    count = 0

    def on_answer(_cid: int, data: bytes | bytearray, _ts: float) -> None:
        nonlocal count
        if len(data) == 8 and data[0] >> 5 in kinds and bytes(data[1:4]) == request[1:4]:
            with heard:
                count += 1
                heard.notify_all()

    network = link.node.network
    network.subscribe(answer_id, on_answer)
    try:
        link.node.sdo.send_request(request)
        with heard:
            heard.wait_for(lambda: count >= 2, timeout=wait_s)
            return count
    except (canopen.SdoCommunicationError, DriverError) as exc:
        raise SdoError(f"{link.label}: SDO read 0x{index:04X}:00 (answer count): {exc}") from exc
    finally:
        network.unsubscribe(answer_id, on_answer)


def _var(link: DriveLink, index: int) -> Any:
    entry = link.node.sdo[index]
    # A VAR object is itself the variable; records/arrays need a sub-index.
    return entry if isinstance(entry, canopen.sdo.SdoVariable) else entry[0]


def _map_pdo(
    link: DriveLink, comm_index: int, cob_id: int, objects: tuple[int, ...], name: str
) -> None:
    """Map ``objects`` (sub-index 0 each, lengths from the EDS) into the PDO whose
    communication parameter is ``comm_index`` (its mapping: ``comm_index + 0x200``), in
    the order CiA 301 requires: PDO invalid, transmission type, mapping emptied, the
    entries, their count, PDO valid.  An abort names the entry, hence the object, the
    drive refused (a CiA 301 drive checks each entry as it is written)."""
    map_index = comm_index + 0x200
    steps: list[tuple[int, int, int, str]] = [
        (comm_index, 1, cob_id | cia301.PDO_COB_ID_INVALID, "COB-ID (PDO invalid)"),
        (comm_index, 2, cia301.PDO_TRANSMISSION_SYNCHRONOUS, "transmission type"),
        (map_index, 0, 0, "number of entries (0)"),
    ]
    for k, index in enumerate(objects, start=1):
        bits = len(link.node.object_dictionary[index])
        steps.append(
            (map_index, k, cia301.pdo_mapping_entry(index, 0, bits),
             f"entry {k}: object 0x{index:04X}:00 ({bits} bits)")
        )  # fmt: skip
    steps += [
        (map_index, 0, len(objects), f"number of entries ({len(objects)})"),
        (comm_index, 1, cob_id, "COB-ID (PDO valid)"),
    ]
    for index, sub, value, what in steps:
        where = f"0x{index:04X}:{sub:02X} {what}"
        try:
            link.node.sdo[index][sub].raw = value
        except canopen.SdoAbortedError as exc:
            raise SdoError(
                f"{link.label}: mapping {name}: {where} aborted: "
                f"{cia301.describe_sdo_abort(exc.code)}"
            ) from exc
        except canopen.SdoCommunicationError as exc:
            raise SdoError(f"{link.label}: mapping {name}: {where}: {exc}") from exc
        except DriverError as exc:  # the request could not be sent (bus failure)
            raise SdoError(f"{link.label}: mapping {name}: {where}: {exc}") from exc


def configure_drive(link: DriveLink, s: DriveSettings) -> None:
    """SDO configuration (node pre-operational): the box configuration's SDO overlay for
    this drive (in order), then heartbeats (or the node guarding), PDO mappings, limits,
    interpolation period (in the drive's encoding), quick stop option, quick-stop
    deceleration (where the setup gives one), mode CSP (checked on 0x6061)."""
    nid = link.node_id
    for w in s.setup.sdo:
        sdo_write(link, w.index, w.sub, w.value)
    if s.setup.guarding is not None:
        # the host guards the drive (no heartbeat consumer): no heartbeat from it (CiA 301:
        # a producer time other than 0 would switch guarding off), its life time set
        if cia301.OD_PRODUCER_HEARTBEAT_TIME in link.node.object_dictionary:
            sdo_write(link, cia301.OD_PRODUCER_HEARTBEAT_TIME, 0, 0)
        guard_ms, factor = s.setup.guarding
        sdo_write(link, cia301.OD_GUARD_TIME, 0, guard_ms)
        sdo_write(link, cia301.OD_LIFE_TIME_FACTOR, 0, factor)
    else:
        sdo_write(link, cia301.OD_PRODUCER_HEARTBEAT_TIME, 0, s.node_heartbeat_ms)
        sdo_write(
            link,
            cia301.OD_CONSUMER_HEARTBEAT_TIME,
            1,
            cia301.consumer_heartbeat_entry(s.host_node_id, s.host_heartbeat_timeout_ms),
        )
    _map_pdo(
        link,
        cia301.OD_RPDO1_COMMUNICATION,
        cia301.COB_RPDO1 + nid,
        (cia402.OD_CONTROLWORD, cia402.OD_TARGET_POSITION),
        "RPDO1 (controlword, target position)",
    )
    _map_pdo(
        link,
        cia301.OD_TPDO1_COMMUNICATION,
        cia301.COB_TPDO1 + nid,
        (cia402.OD_STATUSWORD, cia402.OD_POSITION_ACTUAL_VALUE),
        "TPDO1 (statusword, position actual value)",
    )
    sdo_write(link, cia402.OD_SOFTWARE_POSITION_LIMIT, 1, int(s.counts_min))
    sdo_write(link, cia402.OD_SOFTWARE_POSITION_LIMIT, 2, int(s.counts_max))
    value, index = s.setup.interpolation or cia402.interpolation_time_period(s.period_s)
    sdo_write(link, cia402.OD_INTERPOLATION_TIME_PERIOD, 1, value)
    sdo_write(link, cia402.OD_INTERPOLATION_TIME_PERIOD, 2, index)
    sdo_write(link, cia402.OD_FOLLOWING_ERROR_WINDOW, 0, int(s.following_error_window_counts))
    sdo_write(link, cia402.OD_QUICK_STOP_OPTION_CODE, 0, int(s.quick_stop_option_code))
    if s.setup.quick_stop_deceleration is not None:
        sdo_write(link, cia402.OD_QUICK_STOP_DECELERATION, 0, int(s.setup.quick_stop_deceleration))
    sdo_write(link, cia402.OD_MODES_OF_OPERATION, 0, cia402.MODE_CSP)
    shown = sdo_read(link, cia402.OD_MODES_OF_OPERATION_DISPLAY)
    if shown != cia402.MODE_CSP:
        raise DriverError(
            f"{link.label}: modes of operation display is {shown}, expected {cia402.MODE_CSP} (CSP)"
        )


State402 = cia402.State402

# What a drive is waiting for in a state it leaves by itself (cia402.AUTOMATIC_SUCCESSOR).
_AUTOMATIC_AFTER = {
    State402.NOT_READY_TO_SWITCH_ON: "power-on",
    State402.FAULT_REACTION_ACTIVE: "fault reaction",
}


def read_state(link: DriveLink) -> tuple[State402, int]:
    """(state, statusword) read by SDO."""
    sw = int(sdo_read(link, cia402.OD_STATUSWORD))
    return cia402.decode_state(sw), sw


def wait_state(link: DriveLink, expected: State402, timeout_s: float, after: str) -> int:
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


def command(link: DriveLink, controlword: int, expected: State402, timeout_s: float) -> int:
    """Write a controlword and wait for the expected state."""
    sdo_write(link, cia402.OD_CONTROLWORD, 0, controlword)
    return wait_state(link, expected, timeout_s, f"controlword 0x{controlword:04X}")


def step(link: DriveLink, transition: cia402.Transition, timeout_s: float) -> int:
    """Take one transition of the CiA 402 table: write its command, wait for its target.

    The fault reset is the 0→1 edge of bit 7, so bit 7 is cleared first (disable voltage:
    no transition from FAULT).  Returns the statusword that showed the target state.
    """
    if transition.command is cia402.Command402.FAULT_RESET:
        sdo_write(link, cia402.OD_CONTROLWORD, 0, cia402.CW_DISABLE_VOLTAGE)
    return command(link, transition.command.controlword, transition.target, timeout_s)


def drive_to(link: DriveLink, goal: State402, timeout_s: float) -> int:
    """Walk a drive's state machine to ``goal`` (one of :data:`cia402.LADDER`) along
    :func:`cia402.route`, the statusword confirming every step; a drive in a state it
    leaves by itself (power-on, fault reaction) is waited for first.  Returns the last
    statusword; :class:`StateTimeoutError` when a step does not show or no route exists.
    """
    state, sw = read_state(link)
    successor = cia402.AUTOMATIC_SUCCESSOR.get(state)
    if successor is not None:
        sw = wait_state(link, successor, timeout_s, _AUTOMATIC_AFTER[state])
        state = successor
    try:
        steps = cia402.route(state, goal)
    except cia402.TransitionError as exc:
        raise StateTimeoutError(
            f"{link.label}: statusword 0x{sw:04X} ({state.name}) cannot be brought to "
            f"{goal.name}: {exc}"
        ) from exc
    for transition in steps:
        sw = step(link, transition, timeout_s)
    return sw


def enable_operation(
    link: DriveLink,
    timeout_s: float,
    counts_min: int | None = None,
    counts_max: int | None = None,
) -> int:
    """CiA 402 state machine to OPERATION_ENABLED, checking the statusword at each step.

    The drive is first walked to SWITCHED_ON (:func:`drive_to`: a drive in FAULT gets
    one fault reset, one already enabled is disabled first so it starts from a known
    state).  The actual position is checked against ``counts_min``/``counts_max`` (the
    rope layer's limits; outside: :class:`DriverError`, the drive stays SWITCHED_ON, not
    enabled); then the target position is set to it before operation is enabled, so
    nothing moves.  Returns the actual position (counts).
    """
    drive_to(link, State402.SWITCHED_ON, timeout_s)
    actual = int(sdo_read(link, cia402.OD_POSITION_ACTUAL_VALUE))
    lo = cia402.INT32_MIN if counts_min is None else int(counts_min)
    hi = cia402.INT32_MAX if counts_max is None else int(counts_max)
    if not lo <= actual <= hi:
        raise DriverError(
            f"{link.label}: actual position {actual} counts is outside the limits "
            f"[{lo}, {hi}]: not enabled"
        )
    sdo_write(link, cia402.OD_TARGET_POSITION, 0, actual)
    enable = cia402.transition(State402.SWITCHED_ON, cia402.Command402.ENABLE_OPERATION)
    step(link, enable, timeout_s)
    return actual


def disable(link: DriveLink, timeout_s: float) -> int:
    """Controlled disable to READY_TO_SWITCH_ON (power stage off) along the table's route:
    from OPERATION_ENABLED *disable operation* (5, confirmed SWITCHED_ON) then *shutdown*
    (6).  No target position is sent.  Returns the last statusword."""
    return drive_to(link, State402.READY_TO_SWITCH_ON, timeout_s)


#: the states a drive leaves only by a fault reset (or is on its way into)
FAULTY = frozenset({State402.FAULT, State402.FAULT_REACTION_ACTIVE})


def disable_unless_faulty(link: DriveLink, timeout_s: float) -> int:
    """:func:`disable`, except a drive in FAULT: left there, :class:`DriverError` naming
    it (a fault is reset only on purpose: :func:`reset_to_ready`)."""
    state, sw = read_state(link)
    if state in FAULTY:
        raise DriverError(
            f"{link.label}: statusword 0x{sw:04X} ({state.name}): not disabled "
            "(reset the fault first)"
        )
    return disable(link, timeout_s)


def reset_to_ready(link: DriveLink, timeout_s: float) -> bool:
    """The fault reset if the drive is in FAULT (CiA 402 transition 15, confirmed), then
    READY_TO_SWITCH_ON (power stage off) along the table; nothing moves.  Returns whether
    the drive was in FAULT."""
    state, _sw = read_state(link)
    drive_to(link, State402.READY_TO_SWITCH_ON, timeout_s)
    return state in FAULTY


def quick_stop(link: DriveLink) -> None:
    """The quick-stop controlword by SDO (no target position is written)."""
    sdo_write(link, cia402.OD_CONTROLWORD, 0, cia402.CW_QUICK_STOP)


def read_status(link: DriveLink) -> tuple[int, int] | None:
    """(statusword, actual position) by SDO; None when the drive does not answer."""
    try:
        sw = int(sdo_read(link, cia402.OD_STATUSWORD))
        return sw, int(sdo_read(link, cia402.OD_POSITION_ACTUAL_VALUE))
    except HrmError:
        return None
