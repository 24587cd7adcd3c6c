"""One simulated CiA 402 rope-motor drive: the far end of the host's CANopen traffic.

A :class:`DriveSim` owns the object dictionary of the shipped EDS
(``drivers/data/hrm_drive.eds``, :mod:`~sim_bus.drive.objects`) and answers CAN
frames the way a CiA 301 / CiA 402 drive does, one module per service:

* :mod:`~sim_bus.drive.nmt` — **NMT slave**: boot-up frame on power-on and
  after reset node / reset communication; states pre-operational, operational,
  stopped; heartbeat producer (0x1017) and **host heartbeat consumer**
  (0x1016): after the first heartbeat of a monitored node, silence longer than
  its time raises EMCY 0x8130 and a quick stop.
* :mod:`~sim_bus.drive.sdo_server` — **SDO server** for every EDS object:
  expedited and segmented upload and download with the CiA 301 abort codes.
* :mod:`~sim_bus.drive.pdo` — **PDOs**: the RPDO (remappable) applied on the
  next SYNC, the TPDO sent after every n-th SYNC; EMCY 0x8210 for a short RPDO.
* :mod:`~sim_bus.drive.state_machine` — **CiA 402 device control** through the
  one transition table of :mod:`drivers.protocol.cia402`, quick stop per
  0x605A, fault reaction then FAULT, fault reset on the 0→1 edge of bit 7.
* :mod:`~sim_bus.drive.motion` — **CSP following** on each SYNC within the
  velocity/acceleration limits and the software position limits; a following
  error beyond 0x6065 faults the drive with EMCY 0x8611.

:class:`DriveSim` composes them: it routes received frames to the service, keeps
the device-wide error state (error register 0x1001, error code 0x603F,
statusword warning) and the EMCY producer, and hands each written object to the
service that owns it.  The drive never touches a bus: it is given a ``send``
callable and fed frames and clock ticks by the box (:mod:`sim_bus.box`), one
thread per bus.

>>> sent = []
>>> d = DriveSim(5, sent.append, DriveParams(), now=0.0)
>>> hex(sent[0].arbitration_id), sent[0].data.hex()       # boot-up
('0x705', '00')
>>> d.handle(cia301.make_sdo_upload_request(5, cia402.OD_STATUSWORD, 0), now=0.001)
>>> sent[-1].data.hex()                                    # 0x6041 = 0x0250: switch on disabled
'4b41600050020000'
>>> d.handle(cia301.make_sdo_upload_request(5, 0x2000, 0), now=0.002)
>>> sent[-1].data.hex()                                    # no such object
'8000200000000206'
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from drivers.protocol import cia301, cia402
from hrm_ctrl.errors import SimError
from sim_bus.drive.motion import CspMotion
from sim_bus.drive.nmt import NmtSlave
from sim_bus.drive.objects import Key, ObjectDictionary, Value, object_table
from sim_bus.drive.pdo import PdoService
from sim_bus.drive.sdo_server import SdoServer
from sim_bus.drive.state_machine import StateMachine402

__all__ = ["DriveParams", "DriveSim", "DriveSimError", "object_table"]

State = cia402.State402
EVENTS_KEPT = 200
SIMULATOR_VENDOR_ID = 0  # 0x1018:1 of every simulated drive (drivers.identity's)


class DriveSimError(SimError):
    """A drive simulator was configured with impossible parameters."""


@dataclass(frozen=True)
class DriveParams:
    """Physical limits and start-up values of one simulated drive (counts, s).

    ``max_velocity_counts_per_s`` and ``max_accel_counts_per_s2`` limit CSP
    following; ``quick_stop_decel_counts_per_s2`` is the quick-stop and fault
    reaction ramp.  ``initial_position_counts`` is where the motor is at power-on.
    ``serial_number`` is what the identity object answers (0x1018:4); its vendor-ID is
    always :data:`SIMULATOR_VENDOR_ID` (0x1018:1, 0: no vendor's), its product code and
    revision the device file's.
    """

    max_velocity_counts_per_s: float = 2.0e6
    max_accel_counts_per_s2: float = 2.0e8
    quick_stop_decel_counts_per_s2: float = 4.0e8
    initial_position_counts: int = 0
    serial_number: int = 0

    def __post_init__(self) -> None:
        for name in (
            "max_velocity_counts_per_s",
            "max_accel_counts_per_s2",
            "quick_stop_decel_counts_per_s2",
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise DriveSimError(f"DriveParams.{name} must be a finite number > 0, got {v!r}")
        sn = self.serial_number
        if not isinstance(sn, int) or isinstance(sn, bool) or not 0 <= sn <= 0xFFFFFFFF:
            raise DriveSimError(f"DriveParams.serial_number must be an UNSIGNED32, got {sn!r}")


class DriveSim:
    """A simulated CiA 402 drive at ``node_id`` (see the module docstring).

    ``send`` is called with every frame the drive transmits; ``handle(msg, now)``
    feeds it a received frame, ``tick(now)`` advances its timers (heartbeat
    producer and consumer, motion while no SYNC arrives).  ``now`` is a
    monotonic time in seconds.  Not thread-safe: one caller at a time.
    """

    def __init__(
        self,
        node_id: int,
        send: Callable[[can.Message], None],
        params: DriveParams | None = None,
        *,
        now: float = 0.0,
        eds: str | Path | None = None,
    ) -> None:
        if not cia301.NODE_ID_MIN <= node_id <= cia301.NODE_ID_MAX:
            raise DriveSimError(f"drive node id {node_id} outside 1..127")
        self.node_id = node_id
        self._send_fn = send
        self.params = params or DriveParams()
        self.frames_sent = 0
        self.frames_failed = 0
        self.events: list[str] = []
        # device-wide error state: error register (0x1001), error code (0x603F), warning bit
        self.error_register = 0
        self.error_code = 0
        self.warning = False
        self.od = ObjectDictionary(node_id, eds)
        self.motion = CspMotion(self, self.params)
        self.state_machine = StateMachine402(self)
        self.nmt = NmtSlave(self)
        self.sdo = SdoServer(self)
        self.pdo = PdoService(self)
        self.power_on(now)

    # ================================================================ life cycle
    def power_on(self, now: float) -> None:
        """Power-on / reset node: every object to its EDS default, boot-up."""
        self.od.reset()
        self.state_machine.reset()
        self.error_register = 0
        self.error_code = 0
        self.motion.reset()
        self.warning = False
        self.reset_communication(now)

    def reset_node(self, now: float) -> None:
        """NMT reset node: power-on of the electronics; the motor stays where it is."""
        pos, vel = self.motion.position, self.motion.velocity
        self.power_on(now)
        self.motion.position, self.motion.velocity = pos, vel

    def reset_communication(self, now: float) -> None:
        """NMT reset communication: communication objects to defaults, boot-up."""
        self.od.reset_communication()
        self.pdo.reset()
        self.sdo.reset()
        self.motion.last_motion = now
        self.nmt.reset_communication(now)

    # ================================================================ shared by the services
    def transmit(self, msg: can.Message) -> None:
        """Send one frame; a failed send is counted (bus off: a real drive cannot either)."""
        try:
            self._send_fn(msg)
            self.frames_sent += 1
        except can.CanError:
            self.frames_failed += 1

    def log(self, text: str) -> None:
        self.events.append(text)
        if len(self.events) > EVENTS_KEPT:
            del self.events[: EVENTS_KEPT // 2]

    def emcy(self, code: int, extra: bytes = b"") -> None:
        """EMCY producer (0x1014; bit 31 set: no EMCY) with the present error register."""
        default = cia301.COB_EMCY + self.node_id
        cob = int(self.od.values.get((cia301.OD_COB_ID_EMCY, 0), default))  # type: ignore[arg-type]
        if cob & 0x80000000:
            return
        msg = cia301.make_emcy(self.node_id, code, self.error_register, extra[:5])
        msg.arbitration_id = cob & 0x7FF
        self.transmit(msg)

    def live_value(self, key: Key) -> Value:
        """An object's present value: the ones the drive computes, else the stored value."""
        if key == (cia402.OD_STATUSWORD, 0):
            return self.statusword
        if key == (cia402.OD_POSITION_ACTUAL_VALUE, 0):
            return self.motion.position_counts
        if key == (cia402.OD_MODES_OF_OPERATION_DISPLAY, 0):
            return self.motion.mode
        if key == (cia402.OD_ERROR_CODE, 0):
            return self.error_code
        if key == (cia301.OD_ERROR_REGISTER, 0):
            return self.error_register
        if key == (cia301.OD_IDENTITY, 1):  # a simulated drive, whatever its device file
            return SIMULATOR_VENDOR_ID
        if key == (cia301.OD_IDENTITY, 4):
            return self.params.serial_number
        return self.od.values[key]

    def check_write(self, index: int, sub: int, value: int) -> None:
        """Device rules of an integer download, asked of the service owning the object
        (raises :class:`~sim_bus.drive.objects.SdoAbort`)."""
        self.state_machine.check_write(index, sub, value)
        self.motion.check_write(index, sub, value)
        self.pdo.check_write(index, sub, value)
        self.nmt.check_write(index, sub, value)

    def after_write(self, index: int, sub: int, value: object, now: float) -> None:
        """An object was written (by SDO): the owning service reacts."""
        self.pdo.after_write(index)
        if index == cia402.OD_CONTROLWORD:
            self._on_controlword(int(value), now)  # type: ignore[call-overload]
        self.nmt.after_write(index, now)

    def _on_controlword(self, cw: int, now: float) -> None:
        """The one entry of every controlword, by SDO or RPDO (a test replaces it to model
        a drive whose state machine is stuck)."""
        self.state_machine.on_controlword(cw, now)

    # ================================================================ routing
    @property
    def sync_cob_id(self) -> int:
        return self.pdo.sync_cob_id

    @property
    def rpdo_cob_id(self) -> int | None:
        return self.pdo.rpdo_cob_id

    def monitored_heartbeats(self) -> dict[int, float]:
        """{node id: timeout s} of the 0x1016 consumer entries that are on."""
        return dict(self.nmt.monitored())

    def cob_ids(self) -> set[int]:
        """COB-IDs this drive listens to (the box routes frames by them)."""
        ids = {cia301.COB_NMT, self.pdo.sync_cob_id, cia301.COB_SDO_RX + self.node_id}
        rpdo = self.pdo.rpdo_cob_id
        if rpdo is not None:
            ids.add(rpdo)
        ids.update(cia301.COB_NMT_ERROR_CONTROL + n for n in self.nmt.monitored())
        if self.nmt.guardable:  # node-guarding requests
            ids.add(cia301.COB_NMT_ERROR_CONTROL + self.node_id)
        return ids

    def handle(self, msg: can.Message, now: float) -> None:
        """Process one received frame (never raises on bad frames)."""
        if msg.is_error_frame or msg.is_extended_id:
            return
        if msg.is_remote_frame:
            if msg.arbitration_id == cia301.COB_NMT_ERROR_CONTROL + self.node_id:
                self.nmt.on_guarding_request(now)
            return
        cob = msg.arbitration_id
        data = bytes(msg.data)
        nmt = self.nmt
        if cob == cia301.COB_NMT:
            nmt.on_nmt(data, now)
            return
        heartbeat_of = cob - cia301.COB_NMT_ERROR_CONTROL
        if nmt.stopped:
            if heartbeat_of in nmt.monitored():
                nmt.on_heartbeat(heartbeat_of, data, now)
            return
        if cob == cia301.COB_SDO_RX + self.node_id:
            self.sdo.on_request(data, now)
        elif cob == self.pdo.sync_cob_id:
            if nmt.operational:
                self.pdo.on_sync(now)
        elif cob == self.pdo.rpdo_cob_id:
            if nmt.operational:
                self.pdo.on_rpdo(data, now)
        elif heartbeat_of in nmt.monitored():
            nmt.on_heartbeat(heartbeat_of, data, now)

    # ================================================================ timers
    def tick(self, now: float, heartbeat_early_s: float = 0.0) -> None:
        """Heartbeat production and consumption (a heartbeat due within
        ``heartbeat_early_s`` goes out now); motion when no SYNC comes."""
        self.nmt.tick(now, heartbeat_early_s)
        motion = self.motion
        if (
            self.state_machine.decelerating
            and now - motion.last_motion > 1.5 * motion.interpolation_period_s
        ):
            motion.advance(now - motion.last_motion, now)

    def next_deadline(self) -> float:
        """Earliest time :meth:`tick` has something to do."""
        t = self.nmt.deadline()
        if self.state_machine.decelerating:
            motion = self.motion
            t = min(t, motion.last_motion + 1.5 * motion.interpolation_period_s + 1e-4)
        return t

    # ================================================================ state, for the box and tests
    @property
    def state(self) -> State:
        return self.state_machine.state

    @state.setter
    def state(self, state: State) -> None:
        self.state_machine.state = state

    @property
    def statusword(self) -> int:
        return self.state_machine.statusword

    @property
    def nmt_state(self) -> int:
        return self.nmt.state

    @property
    def heartbeat_enabled(self) -> bool:
        return self.nmt.heartbeat_enabled

    @heartbeat_enabled.setter
    def heartbeat_enabled(self, enabled: bool) -> None:
        self.nmt.heartbeat_enabled = enabled

    @property
    def position_counts(self) -> int:
        return self.motion.position_counts

    @property
    def velocity(self) -> float:
        return self.motion.velocity

    @property
    def jammed(self) -> bool:
        return self.motion.jammed

    @jammed.setter
    def jammed(self, jammed: bool) -> None:
        self.motion.jammed = jammed

    @property
    def following_error(self) -> bool:
        return self.motion.following_error

    @following_error.setter
    def following_error(self, on: bool) -> None:
        self.motion.following_error = on

    @property
    def interpolation_period_s(self) -> float:
        return self.motion.interpolation_period_s

    def read_object(self, index: int, sub: int = 0) -> bytes:
        """The encoded value of an object, as an SDO upload would return it."""
        return self.sdo.read_object(index, sub)

    def write_object(self, index: int, sub: int, raw: bytes, now: float) -> None:
        """Validate and store a download, as an SDO download would."""
        self.sdo.write_object(index, sub, raw, now)

    def inject_fault(self, code: int = cia301.EMCY_GENERIC_DEVICE, now: float = 0.0) -> None:
        """Fault injection: the drive faults with ``code`` (EMCY sent)."""
        self.state_machine.fault(code, now, "injected fault")
