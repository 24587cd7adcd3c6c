"""One simulated CiA 402 rope-motor drive: the far end of the host's CANopen traffic.

A :class:`DriveSim` owns the object dictionary of the shipped EDS
(``drivers/data/hrm_drive.eds``) and answers CAN frames the way a CiA 301 /
CiA 402 drive does:

* **NMT slave**: boot-up frame on power-on and after reset node / reset
  communication; heartbeat producer (0x1017); states pre-operational,
  operational, stopped.
* **SDO server** for every EDS object: expedited and segmented upload and
  download; abort codes for a missing object (0x06020000) or sub-index
  (0x06090011), read-only (0x06010002) / write-only (0x06010001) access,
  wrong sizes (0x06070010/12/13), values out of range (0x06090030/31/32),
  unmappable objects or too long PDO mappings (0x06040041/42), a toggle
  error (0x05030000), an unknown command (0x05040001) and mapping changes while
  the PDO is valid (0x06010000).  Frames that are not 8 bytes long are ignored
  (as CANopenNode does).
* **PDOs**: the RPDO (0x1400/0x1600, remappable) is buffered on reception and
  applied on the next SYNC (synchronous types 0..240; 254/255 at once); the
  TPDO (0x1800/0x1A00) is sent after every n-th SYNC (type n = 1..240).  An
  RPDO shorter than its mapping raises EMCY 0x8210 and is not applied.
* **CiA 402** device control: every transition of the state machine
  (controlword commands shutdown, switch on, enable operation, disable
  voltage, quick stop, disable operation, fault reset on the 0→1 edge of
  bit 7), quick stop handled per 0x605A (0: coast; 1,2,3,4: ramp then switch
  on disabled; 5,6,7,8: ramp and stay in quick stop active), fault reaction
  then FAULT.  Mode 8 (CSP) is the only motion mode (0x6502).
* **CSP following**: on each SYNC the applied target (clamped to the software
  position limits 0x607D, statusword bit 11 while clamped) is followed for one
  interpolation period (0x60C2) with the drive's velocity and acceleration
  limits; on entering operation enabled the target is set to the actual
  position.  A following error beyond 0x6065 faults the drive with EMCY
  0x8611.
* **Host heartbeat consumer** (0x1016): after the first heartbeat of a
  monitored node, silence longer than its time raises EMCY 0x8130 and a quick
  stop.

The drive never touches a bus: it is given a ``send`` callable and fed frames
and clock ticks by the box (:mod:`sim_bus.box`), one thread per bus.

>>> sent = []
>>> d = DriveSim(5, sent.append, DriveParams(), now=0.0)
>>> hex(sent[0].arbitration_id), sent[0].data.hex()       # boot-up
('0x705', '00')
>>> d.handle(cia.make_sdo_upload_request(5, cia.OD_STATUSWORD, 0), now=0.001)
>>> sent[-1].data.hex()                                    # 0x6041 = 0x0250: switch on disabled
'4b41600050020000'
>>> d.handle(cia.make_sdo_upload_request(5, 0x2000, 0), now=0.002)
>>> sent[-1].data.hex()                                    # no such object
'8000200000000206'
"""

from __future__ import annotations

import functools
import math
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

import drivers.protocol.cia402 as cia
from drivers import eds_path
from hrm_ctrl.errors import SimError

State = cia.State402

# Error codes (CiA 301 / CiA 402 EMCY).
EMCY_NO_ERROR = 0x0000
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat error
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_PDO_LENGTH_EXCEEDED = 0x8220
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_GENERIC_DEVICE = 0x1000
# Error register (0x1001) bits.
ERR_REG_GENERIC = 0x01
ERR_REG_COMMUNICATION = 0x10
ERR_REG_MANUFACTURER = 0x80

_READABLE = {"ro", "rw", "rwr", "rww", "const"}
_WRITABLE = {"rw", "wo", "rwr", "rww"}
SUPPORTED_MODES = (0, cia.MODE_CSP)


class DriveSimError(SimError):
    """A drive simulator was configured with impossible parameters."""


@dataclass(frozen=True)
class DriveParams:
    """Physical limits and start-up values of one simulated drive (counts, s).

    ``max_velocity_counts_per_s`` and ``max_accel_counts_per_s2`` limit CSP
    following; ``quick_stop_decel_counts_per_s2`` is the quick-stop and fault
    reaction ramp.  ``initial_position_counts`` is where the motor is at power-on.
    """

    max_velocity_counts_per_s: float = 2.0e6
    max_accel_counts_per_s2: float = 2.0e8
    quick_stop_decel_counts_per_s2: float = 4.0e8
    initial_position_counts: int = 0

    def __post_init__(self) -> None:
        for name in (
            "max_velocity_counts_per_s",
            "max_accel_counts_per_s2",
            "quick_stop_decel_counts_per_s2",
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise DriveSimError(f"DriveParams.{name} must be a finite number > 0, got {v!r}")


class _SdoAbortError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


@functools.lru_cache(maxsize=8)
def _load_od(path: str) -> canopen.ObjectDictionary:
    return canopen.import_od(path)


def object_table(path: str | Path | None = None) -> dict[tuple[int, int], ODVariable]:
    """Every (index, sub-index) of the EDS with its canopen variable description.

    >>> t = object_table()
    >>> (0x6041, 0) in t, (0x607D, 2) in t, (0x1016, 1) in t
    (True, True, True)
    """
    od = _load_od(str(path if path is not None else eds_path()))
    out: dict[tuple[int, int], ODVariable] = {}
    for obj in od.values():
        if isinstance(obj, ODRecord | ODArray):
            for sub in obj.subindices.values():
                out[(obj.index, sub.subindex)] = sub
        else:
            out[(obj.index, 0)] = obj
    return out


def _default_value(var: ODVariable, node_id: int) -> int | str | bytes:
    raw = getattr(var, "default_raw", None)
    if getattr(var, "relative", False) and raw is not None:
        return int(re.sub(r"\+?\$NODEID\+?", "", raw.replace(" ", "").upper()), 0) + node_id
    if var.default is None:
        if var.data_type == datatypes.VISIBLE_STRING:
            return ""
        if var.data_type in (datatypes.DOMAIN, datatypes.OCTET_STRING):
            return b""
        return 0
    return var.default


def _type_range(var: ODVariable) -> tuple[int, int] | None:
    if var.data_type not in datatypes.INTEGER_TYPES:
        return None
    bits = len(var)
    if var.data_type in datatypes.SIGNED_TYPES:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


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
        if not cia.NODE_ID_MIN <= node_id <= cia.NODE_ID_MAX:
            raise DriveSimError(f"drive node id {node_id} outside 1..127")
        self.node_id = node_id
        self._send_fn = send
        self.params = params or DriveParams()
        self._objects = object_table(eds)
        self.position = float(self.params.initial_position_counts)
        self.velocity = 0.0
        self.jammed = False
        self.heartbeat_enabled = True
        self.frames_sent = 0
        self.frames_failed = 0
        self.events: list[str] = []
        self.power_on(now)

    # ================================================================ life cycle
    def power_on(self, now: float) -> None:
        """Power-on / reset node: every object to its EDS default, boot-up."""
        self.values: dict[tuple[int, int], int | str | bytes] = {
            key: _default_value(var, self.node_id) for key, var in self._objects.items()
        }
        self.state = State.SWITCH_ON_DISABLED
        self.error_register = 0
        self.error_code = 0
        self.limit_active = False
        self.following_error = False
        self.warning = False
        self._last_cw = 0
        self._reset_communication(now)

    def _reset_communication(self, now: float) -> None:
        for key, var in self._objects.items():
            if 0x1000 <= key[0] < 0x2000 and key[0] not in (0x1001,):
                self.values[key] = _default_value(var, self.node_id)
        self.nmt_state = cia.NMT_STATE_PRE_OPERATIONAL
        self._pdo_cache: dict[int, tuple[struct.Struct | None, list, int]] = {}
        self._sdo: dict[str, object] | None = None
        self._rpdo_buffer: bytes | None = None
        self._sync_count = 0
        self._last_motion = now
        self._hb_next = now
        self._hb_seen: dict[int, float] = {}
        self._hb_lost: set[int] = set()
        self._send(cia.make_heartbeat(self.node_id, cia.NMT_STATE_BOOTUP))
        self._schedule_heartbeat(now)

    def _schedule_heartbeat(self, now: float) -> None:
        period_ms = int(self.values[(cia.OD_PRODUCER_HEARTBEAT_TIME, 0)])
        self._hb_next = now + period_ms / 1000.0 if period_ms else math.inf

    def _send(self, msg: can.Message) -> None:
        try:
            self._send_fn(msg)
            self.frames_sent += 1
        except can.CanError:
            self.frames_failed += 1  # bus off: a real drive cannot transmit either

    def _log(self, text: str) -> None:
        self.events.append(text)
        if len(self.events) > 200:
            del self.events[:100]

    # ================================================================ routing
    @property
    def sync_cob_id(self) -> int:
        return int(self.values.get((cia.OD_COB_ID_SYNC, 0), cia.COB_SYNC)) & 0x7FF

    @property
    def rpdo_cob_id(self) -> int | None:
        v = int(self.values[(cia.OD_RPDO1_COMMUNICATION, 1)])
        return None if v & cia.PDO_COB_ID_INVALID else v & 0x7FF

    def monitored_heartbeats(self) -> dict[int, float]:
        """{node id: timeout s} of the 0x1016 consumer entries that are on."""
        out: dict[int, float] = {}
        n = int(self.values.get((cia.OD_CONSUMER_HEARTBEAT_TIME, 0), 0))
        for sub in range(1, n + 1):
            v = int(self.values.get((cia.OD_CONSUMER_HEARTBEAT_TIME, sub), 0))
            node, ms = (v >> 16) & 0xFF, v & 0xFFFF
            if 1 <= node <= 127 and ms:
                out[node] = ms / 1000.0
        return out

    def cob_ids(self) -> set[int]:
        """COB-IDs this drive listens to (the box routes frames by them)."""
        ids = {cia.COB_NMT, self.sync_cob_id, cia.COB_SDO_RX + self.node_id}
        if self.rpdo_cob_id is not None:
            ids.add(self.rpdo_cob_id)
        ids.update(cia.COB_NMT_ERROR_CONTROL + n for n in self.monitored_heartbeats())
        return ids

    # ================================================================ statusword
    @property
    def statusword(self) -> int:
        sw = cia.STATUSWORD_OF_STATE[self.state] | cia.SW_REMOTE
        if self.state != State.NOT_READY_TO_SWITCH_ON:
            sw |= cia.SW_VOLTAGE_ENABLED
        if self.warning:
            sw |= cia.SW_WARNING
        if self.limit_active:
            sw |= cia.SW_INTERNAL_LIMIT_ACTIVE
        if self.state == State.OPERATION_ENABLED and int(self._mode) == cia.MODE_CSP:
            sw |= cia.SW_CSP_DRIVE_FOLLOWS_COMMAND
        if self.following_error:
            sw |= cia.SW_CSP_FOLLOWING_ERROR
        return sw

    @property
    def _mode(self) -> int:
        return int(self.values[(cia.OD_MODES_OF_OPERATION, 0)])

    @property
    def _target(self) -> float:
        lo = int(self.values[(cia.OD_SOFTWARE_POSITION_LIMIT, 1)])
        hi = int(self.values[(cia.OD_SOFTWARE_POSITION_LIMIT, 2)])
        t = int(self.values[(cia.OD_TARGET_POSITION, 0)])
        return float(min(max(t, lo), hi)) if lo <= hi else float(t)

    def _live_value(self, key: tuple[int, int]) -> int | str | bytes:
        if key == (cia.OD_STATUSWORD, 0):
            return self.statusword
        if key == (cia.OD_POSITION_ACTUAL_VALUE, 0):
            return self.position_counts
        if key == (cia.OD_MODES_OF_OPERATION_DISPLAY, 0):
            return self._mode
        if key == (cia.OD_ERROR_CODE, 0):
            return self.error_code
        if key == (cia.OD_ERROR_REGISTER, 0):
            return self.error_register
        return self.values[key]

    @property
    def position_counts(self) -> int:
        return int(max(cia.INT32_MIN, min(cia.INT32_MAX, round(self.position))))

    # ================================================================ frames in
    def handle(self, msg: can.Message, now: float) -> None:
        """Process one received frame (never raises on bad frames)."""
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        cob = msg.arbitration_id
        data = bytes(msg.data)
        if cob == cia.COB_NMT:
            self._on_nmt(data, now)
            return
        if self.nmt_state == cia.NMT_STATE_STOPPED:
            if cob - cia.COB_NMT_ERROR_CONTROL in self.monitored_heartbeats():
                self._on_heartbeat(cob - cia.COB_NMT_ERROR_CONTROL, data, now)
            return
        if cob == cia.COB_SDO_RX + self.node_id:
            self._on_sdo(data, now)
        elif cob == self.sync_cob_id:
            if self.nmt_state == cia.NMT_STATE_OPERATIONAL:
                self._on_sync(now)
        elif cob == self.rpdo_cob_id:
            if self.nmt_state == cia.NMT_STATE_OPERATIONAL:
                self._on_rpdo(data, now)
        elif cob - cia.COB_NMT_ERROR_CONTROL in self.monitored_heartbeats():
            self._on_heartbeat(cob - cia.COB_NMT_ERROR_CONTROL, data, now)

    def _on_nmt(self, data: bytes, now: float) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return
        cmd = data[0]
        if cmd == cia.NMT_START_REMOTE_NODE:
            self.nmt_state = cia.NMT_STATE_OPERATIONAL
        elif cmd == cia.NMT_STOP_REMOTE_NODE:
            self._leave_operational(now)
            self.nmt_state = cia.NMT_STATE_STOPPED
        elif cmd == cia.NMT_ENTER_PRE_OPERATIONAL:
            self._leave_operational(now)
            self.nmt_state = cia.NMT_STATE_PRE_OPERATIONAL
        elif cmd == cia.NMT_RESET_NODE:
            self._log("NMT reset node")
            pos, vel = self.position, self.velocity
            self.power_on(now)
            self.position, self.velocity = pos, vel
        elif cmd == cia.NMT_RESET_COMMUNICATION:
            self._log("NMT reset communication")
            self._reset_communication(now)

    def _leave_operational(self, now: float) -> None:
        if self.nmt_state == cia.NMT_STATE_OPERATIONAL and self.state == State.OPERATION_ENABLED:
            self._log("left NMT operational while enabled: quick stop")
            self._quick_stop(now)

    def _on_heartbeat(self, node: int, data: bytes, now: float) -> None:
        if len(data) != 1:
            return
        self._hb_seen[node] = now
        if node in self._hb_lost:
            self._hb_lost.discard(node)
            if not self._hb_lost:
                self.warning = False
                self.error_register &= ~ERR_REG_COMMUNICATION
                if self.state != State.FAULT:
                    self._emcy(EMCY_NO_ERROR)

    # ================================================================ timers
    def tick(self, now: float) -> None:
        """Heartbeat production and consumption; motion when no SYNC comes."""
        if now >= self._hb_next and self.heartbeat_enabled:
            self._send(cia.make_heartbeat(self.node_id, self.nmt_state))
            period_s = int(self.values[(cia.OD_PRODUCER_HEARTBEAT_TIME, 0)]) / 1000.0
            self._hb_next = self._hb_next + period_s if period_s else math.inf
            if self._hb_next <= now:
                self._hb_next = now + period_s
        elif now >= self._hb_next:
            self._schedule_heartbeat(now)
        monitored = self.monitored_heartbeats()
        for node, last in list(self._hb_seen.items()):
            timeout = monitored.get(node)
            if timeout is None:
                del self._hb_seen[node]
                continue
            if node not in self._hb_lost and now - last > timeout:
                self._hb_lost.add(node)
                self.warning = True
                self.error_register |= ERR_REG_COMMUNICATION | ERR_REG_GENERIC
                self.error_code = EMCY_HEARTBEAT
                self._log(f"heartbeat of node {node} lost ({timeout * 1000:.0f} ms): quick stop")
                self._emcy(EMCY_HEARTBEAT, bytes((node,)))
                if self.state in (State.OPERATION_ENABLED,):
                    self._quick_stop(now)
        moving = self.state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
        if moving and now - self._last_motion > 1.5 * self.interpolation_period_s:
            self._advance(now - self._last_motion, now)

    def next_deadline(self) -> float:
        """Earliest time :meth:`tick` has something to do."""
        t = self._hb_next if self.heartbeat_enabled else math.inf
        monitored = self.monitored_heartbeats()
        for node, last in self._hb_seen.items():
            if node in monitored and node not in self._hb_lost:
                t = min(t, last + monitored[node] + 1e-4)
        if self.state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            t = min(t, self._last_motion + 1.5 * self.interpolation_period_s + 1e-4)
        return t

    @property
    def interpolation_period_s(self) -> float:
        value = int(self.values[(cia.OD_INTERPOLATION_TIME_PERIOD, 1)])
        index = int(self.values[(cia.OD_INTERPOLATION_TIME_PERIOD, 2)])
        period = value * 10.0**index
        return period if period > 0 else 0.01

    # ================================================================ PDO
    def _mapping(self, map_index: int) -> list[tuple[int, int, int]]:
        n = int(self.values[(map_index, 0)])
        return [
            cia.parse_pdo_mapping_entry(int(self.values[(map_index, k)])) for k in range(1, n + 1)
        ]

    def _compiled(self, map_index: int) -> tuple[struct.Struct | None, list, int]:
        """(struct of the whole PDO or None, [(key, var, nbytes)], total bytes), cached
        until a PDO parameter is written."""
        cached = self._pdo_cache.get(map_index)
        if cached is not None:
            return cached
        entries = []
        fmt = "<"
        for index, sub, bits in self._mapping(map_index):
            var = self._objects.get((index, sub))
            st = var.STRUCT_TYPES.get(var.data_type) if var is not None else None
            if isinstance(st, struct.Struct) and st.size * 8 == bits:
                fmt += st.format.lstrip("<")
            else:
                fmt = ""
            entries.append(((index, sub), var, bits // 8))
        total = sum(n for _k, _v, n in entries)
        packer = struct.Struct(fmt) if fmt and fmt != "<" else None
        out = (packer, entries, total)
        self._pdo_cache[map_index] = out
        return out

    def _on_rpdo(self, data: bytes, now: float) -> None:
        need = self._compiled(cia.OD_RPDO1_MAPPING)[2]
        if len(data) < need:
            self._log(f"RPDO of {len(data)} bytes, mapping needs {need}: EMCY 0x8210")
            self._emcy(EMCY_PDO_LENGTH)
            return
        ttype = int(self.values[(cia.OD_RPDO1_COMMUNICATION, 2)])
        if ttype <= 240:
            self._rpdo_buffer = data
        else:
            self._apply_rpdo(data, now)

    def _apply_rpdo(self, data: bytes, now: float) -> None:
        packer, entries, _total = self._compiled(cia.OD_RPDO1_MAPPING)
        if packer is not None:
            decoded = packer.unpack_from(data)
        else:
            decoded, offset = [], 0
            for _key, var, n in entries:
                chunk = data[offset : offset + n]
                offset += n
                decoded.append(var.decode_raw(chunk) if var is not None else None)
        for (key, var, _n), value in zip(entries, decoded, strict=True):
            if var is None:
                continue  # dummy entry
            self.values[key] = value
            if key == (cia.OD_CONTROLWORD, 0):
                self._on_controlword(int(value), now)

    def _on_sync(self, now: float) -> None:
        dt = self.interpolation_period_s
        self._advance(dt, now)
        self._sync_count += 1
        ttype = int(self.values[(cia.OD_TPDO1_COMMUNICATION, 2)])
        tcob = int(self.values[(cia.OD_TPDO1_COMMUNICATION, 1)])
        if (
            not tcob & cia.PDO_COB_ID_INVALID
            and 1 <= ttype <= 240
            and self._sync_count % ttype == 0
        ):
            self._send_tpdo(tcob & 0x7FF)
        elif not tcob & cia.PDO_COB_ID_INVALID and ttype == 0:
            self._send_tpdo(tcob & 0x7FF)
        if self._rpdo_buffer is not None:
            data, self._rpdo_buffer = self._rpdo_buffer, None
            self._apply_rpdo(data, now)

    def _send_tpdo(self, cob: int) -> None:
        packer, entries, _total = self._compiled(cia.OD_TPDO1_MAPPING)
        if packer is not None:
            payload = packer.pack(*[self._live_value(key) for key, _v, _n in entries])
        else:
            parts = [
                var.encode_raw(self._live_value(key)) if var is not None else bytes(n)
                for key, var, n in entries
            ]
            payload = b"".join(parts)
        self._send(can.Message(arbitration_id=cob, data=payload, is_extended_id=False))

    # ================================================================ motion
    def _advance(self, dt: float, now: float) -> None:
        """Move the motor for ``dt`` seconds according to the drive state."""
        self._last_motion = now
        p = self.params
        if self.jammed:
            self.velocity = 0.0
        elif self.state == State.OPERATION_ENABLED and self._mode == cia.MODE_CSP:
            lo = int(self.values[(cia.OD_SOFTWARE_POSITION_LIMIT, 1)])
            hi = int(self.values[(cia.OD_SOFTWARE_POSITION_LIMIT, 2)])
            raw = int(self.values[(cia.OD_TARGET_POSITION, 0)])
            self.limit_active = lo <= hi and not lo <= raw <= hi
            self._follow(self._target, dt, p.max_accel_counts_per_s2)
        elif self.state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            self._brake(dt)
            if self.velocity == 0.0:
                self._stopped(now)
        else:
            self.velocity = 0.0  # brake engaged / disabled
        if self.state == State.OPERATION_ENABLED:
            window = int(self.values[(cia.OD_FOLLOWING_ERROR_WINDOW, 0)])
            err = abs(self._target - self.position)
            if window != 0xFFFFFFFF and err > window:
                self.following_error = True
                self._fault(
                    EMCY_FOLLOWING_ERROR,
                    now,
                    f"following error {err:.0f} counts > window {window}",
                )

    def _follow(self, target: float, dt: float, accel: float) -> None:
        """Velocity- and acceleration-limited step towards ``target`` (time-optimal stop)."""
        vmax = self.params.max_velocity_counts_per_s
        e = target - self.position
        v_des = e / dt
        v_brake = math.sqrt(2.0 * accel * abs(e))
        v_des = math.copysign(min(abs(v_des), v_brake, vmax), e)
        dv = max(-accel * dt, min(accel * dt, v_des - self.velocity))
        self.velocity += dv
        self.position += self.velocity * dt
        if abs(target - self.position) < 0.5 and abs(self.velocity) <= accel * dt:
            self.position, self.velocity = target, 0.0

    def _brake(self, dt: float) -> None:
        dec = self.params.quick_stop_decel_counts_per_s2
        v = self.velocity
        if abs(v) <= dec * dt:
            self.position += v * dt / 2.0
            self.velocity = 0.0
        else:
            nv = v - math.copysign(dec * dt, v)
            self.position += (v + nv) * dt / 2.0
            self.velocity = nv

    def _stopped(self, now: float) -> None:
        if self.state == State.FAULT_REACTION_ACTIVE:
            self.state = State.FAULT  # transition 14
        elif self.state == State.QUICK_STOP_ACTIVE:
            code = int(self.values[(cia.OD_QUICK_STOP_OPTION_CODE, 0)])
            if code in (1, 2, 3, 4):
                self.state = State.SWITCH_ON_DISABLED  # transition 12

    # ================================================================ CiA 402
    def _quick_stop(self, now: float) -> None:
        """Transition 11 (operation enabled → quick stop active) and the 0x605A reaction."""
        code = int(self.values[(cia.OD_QUICK_STOP_OPTION_CODE, 0)])
        if code == 0:
            self.velocity = 0.0
            self.state = State.SWITCH_ON_DISABLED
            return
        self.state = State.QUICK_STOP_ACTIVE
        if self.velocity == 0.0:
            self._stopped(now)

    def _fault(self, code: int, now: float, why: str, extra: bytes = b"") -> None:
        """Enter fault reaction active (transition 13) and send the EMCY."""
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        self._log(f"fault 0x{code:04X}: {why}")
        self.error_code = code
        self.error_register |= ERR_REG_GENERIC | (ERR_REG_MANUFACTURER if code >= 0xFF00 else 0)
        self.state = State.FAULT_REACTION_ACTIVE
        self._emcy(code, extra)
        if self.velocity == 0.0:
            self.state = State.FAULT

    def inject_fault(self, code: int = EMCY_GENERIC_DEVICE, now: float = 0.0) -> None:
        """Fault injection: the drive faults with ``code`` (EMCY sent)."""
        self._fault(code, now, "injected fault")

    def _emcy(self, code: int, extra: bytes = b"") -> None:
        cob = int(self.values.get((cia.OD_COB_ID_EMCY, 0), cia.COB_EMCY + self.node_id))
        if cob & 0x80000000:
            return
        msg = cia.make_emcy(self.node_id, code, self.error_register, extra[:5])
        msg.arbitration_id = cob & 0x7FF
        self._send(msg)

    def _on_controlword(self, cw: int, now: float) -> None:
        """Device control (CiA 402 table 31): apply one controlword."""
        rising_reset = bool(cw & cia.CW_BIT_FAULT_RESET) and not (
            self._last_cw & cia.CW_BIT_FAULT_RESET
        )
        self._last_cw = cw
        s = self.state
        if s == State.FAULT:
            if rising_reset:  # transition 15
                self.state = State.SWITCH_ON_DISABLED
                self.error_code = 0
                self.error_register = 0
                self.following_error = False
                self.warning = bool(self._hb_lost)
                self._emcy(EMCY_NO_ERROR)
            return
        if s in (State.FAULT_REACTION_ACTIVE, State.NOT_READY_TO_SWITCH_ON):
            return
        if cw & cia.CW_BIT_FAULT_RESET:
            return  # fault reset bit set outside FAULT: no device-control command
        low = cw & 0x0F
        disable_voltage = not low & cia.CW_BIT_ENABLE_VOLTAGE
        quick_stop = (low & 0x06) == 0x02
        shutdown = (low & 0x07) == 0x06
        switch_on = (low & 0x0F) == 0x07
        enable = (low & 0x0F) == 0x0F
        if s == State.SWITCH_ON_DISABLED:
            if shutdown:
                self.state = State.READY_TO_SWITCH_ON  # 2
        elif s == State.READY_TO_SWITCH_ON:
            if disable_voltage or quick_stop:
                self.state = State.SWITCH_ON_DISABLED  # 7
            elif switch_on:
                self.state = State.SWITCHED_ON  # 3
            elif enable:
                self.state = State.SWITCHED_ON  # 3 + 4
                self._enable_operation()
        elif s == State.SWITCHED_ON:
            if disable_voltage or quick_stop:
                self.state = State.SWITCH_ON_DISABLED  # 10
            elif shutdown:
                self.state = State.READY_TO_SWITCH_ON  # 6
            elif enable:
                self._enable_operation()  # 4
        elif s == State.OPERATION_ENABLED:
            if disable_voltage:
                self.velocity = 0.0
                self.state = State.SWITCH_ON_DISABLED  # 9
            elif quick_stop:
                self._log("quick stop commanded")
                self._quick_stop(now)  # 11
            elif shutdown:
                self.velocity = 0.0
                self.state = State.READY_TO_SWITCH_ON  # 8
            elif switch_on:
                self.velocity = 0.0
                self.state = State.SWITCHED_ON  # 5
        elif s == State.QUICK_STOP_ACTIVE:
            code = int(self.values[(cia.OD_QUICK_STOP_OPTION_CODE, 0)])
            if disable_voltage:
                self.velocity = 0.0
                self.state = State.SWITCH_ON_DISABLED  # 12
            elif enable and code in (5, 6, 7, 8) and self.velocity == 0.0:
                self._enable_operation()  # 16

    def _enable_operation(self) -> None:
        self.state = State.OPERATION_ENABLED
        self.values[(cia.OD_TARGET_POSITION, 0)] = self.position_counts
        self.velocity = 0.0
        self._rpdo_buffer = None

    # ================================================================ SDO server
    def _on_sdo(self, data: bytes, now: float) -> None:
        if len(data) != 8:
            return  # CANopenNode ignores SDO frames of another length
        cs = data[0] >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        try:
            if cs == cia.SDO_CS_ABORT:
                self._sdo = None
            elif cs == cia.SDO_CCS_INITIATE_UPLOAD:
                self._sdo_initiate_upload(index, sub)
            elif cs == cia.SDO_CCS_UPLOAD_SEGMENT:
                self._sdo_upload_segment(data)
            elif cs == cia.SDO_CCS_INITIATE_DOWNLOAD:
                self._sdo_initiate_download(data, index, sub, now)
            elif cs == cia.SDO_CCS_DOWNLOAD_SEGMENT:
                self._sdo_download_segment(data, now)
            else:
                raise _SdoAbortError(cia.SDO_ABORT_COMMAND_SPECIFIER)
        except (_SdoAbortError, ValueError, TypeError, KeyError, struct.error) as exc:
            code = exc.code if isinstance(exc, _SdoAbortError) else cia.SDO_ABORT_GENERAL
            if not isinstance(exc, _SdoAbortError):
                self._log(f"SDO request {data.hex()} failed internally ({exc!r}): general abort")
            if self._sdo is not None and cs in (
                cia.SDO_CCS_UPLOAD_SEGMENT,
                cia.SDO_CCS_DOWNLOAD_SEGMENT,
            ):
                index, sub = self._sdo["index"], self._sdo["sub"]  # type: ignore[assignment]
            self._sdo = None
            self._send(cia.make_sdo_abort(self.node_id, int(index), int(sub), code))

    def _sdo_reply(self, payload: bytes) -> None:
        self._send(
            can.Message(
                arbitration_id=cia.COB_SDO_TX + self.node_id,
                data=payload.ljust(8, b"\x00"),
                is_extended_id=False,
            )
        )

    def _lookup(self, index: int, sub: int) -> ODVariable:
        var = self._objects.get((index, sub))
        if var is None:
            if not any(k[0] == index for k in self._objects):
                raise _SdoAbortError(cia.SDO_ABORT_NO_OBJECT)
            raise _SdoAbortError(cia.SDO_ABORT_NO_SUBINDEX)
        return var

    def read_object(self, index: int, sub: int = 0) -> bytes:
        """The encoded value of an object, as an SDO upload would return it."""
        var = self._lookup(index, sub)
        if var.access_type not in _READABLE:
            raise _SdoAbortError(cia.SDO_ABORT_WRITE_ONLY)
        value = self._live_value((index, sub))
        return var.encode_raw(value)

    def _sdo_initiate_upload(self, index: int, sub: int) -> None:
        self._sdo = None
        raw = self.read_object(index, sub)
        head = struct.pack("<HB", index, sub)
        if 0 < len(raw) <= 4:
            cmd = (cia.SDO_SCS_INITIATE_UPLOAD << 5) | ((4 - len(raw)) << 2) | 0x03
            self._sdo_reply(bytes((cmd,)) + head + raw)
        else:
            cmd = (cia.SDO_SCS_INITIATE_UPLOAD << 5) | 0x01
            self._sdo_reply(bytes((cmd,)) + head + struct.pack("<I", len(raw)))
            self._sdo = {"kind": "upload", "index": index, "sub": sub, "data": raw, "toggle": 0}

    def _sdo_upload_segment(self, data: bytes) -> None:
        st = self._sdo
        if st is None or st["kind"] != "upload":
            raise _SdoAbortError(cia.SDO_ABORT_COMMAND_SPECIFIER)
        toggle = (data[0] >> 4) & 1
        if toggle != st["toggle"]:
            raise _SdoAbortError(cia.SDO_ABORT_TOGGLE_BIT)
        rest: bytes = st["data"]  # type: ignore[assignment]
        chunk, rest = rest[:7], rest[7:]
        last = not rest
        cmd = (cia.SDO_SCS_UPLOAD_SEGMENT << 5) | (toggle << 4) | ((7 - len(chunk)) << 1) | last
        self._sdo_reply(bytes((cmd,)) + chunk)
        if last:
            self._sdo = None
        else:
            st["data"], st["toggle"] = rest, toggle ^ 1

    def _sdo_initiate_download(self, data: bytes, index: int, sub: int, now: float) -> None:
        self._sdo = None
        var = self._lookup(index, sub)
        if var.access_type not in _WRITABLE:
            raise _SdoAbortError(cia.SDO_ABORT_READ_ONLY)
        expedited = bool(data[0] & 0x02)
        size_given = bool(data[0] & 0x01)
        head = struct.pack("<HB", index, sub)
        if expedited:
            n = 4 - ((data[0] >> 2) & 0x03) if size_given else None
            if n is None:
                n = len(var) // 8 if var.fixed_size else 4
            self.write_object(index, sub, data[4 : 4 + n], now)
            self._sdo_reply(bytes((cia.SDO_SCS_INITIATE_DOWNLOAD << 5,)) + head)
            return
        size = struct.unpack_from("<I", data, 4)[0] if size_given else None
        if size is not None and var.fixed_size:
            self._check_size(var, size)
        self._sdo = {
            "kind": "download",
            "index": index,
            "sub": sub,
            "size": size,
            "data": b"",
            "toggle": 0,
        }
        self._sdo_reply(bytes((cia.SDO_SCS_INITIATE_DOWNLOAD << 5,)) + head)

    def _sdo_download_segment(self, data: bytes, now: float) -> None:
        st = self._sdo
        if st is None or st["kind"] != "download":
            raise _SdoAbortError(cia.SDO_ABORT_COMMAND_SPECIFIER)
        toggle = (data[0] >> 4) & 1
        if toggle != st["toggle"]:
            raise _SdoAbortError(cia.SDO_ABORT_TOGGLE_BIT)
        n = 7 - ((data[0] >> 1) & 0x07)
        st["data"] = st["data"] + data[1 : 1 + n]  # type: ignore[operator]
        if len(st["data"]) > 4096:  # type: ignore[arg-type]
            raise _SdoAbortError(cia.SDO_ABORT_OUT_OF_MEMORY)
        last = bool(data[0] & 0x01)
        if last:
            payload: bytes = st["data"]  # type: ignore[assignment]
            if st["size"] is not None and st["size"] != len(payload):
                raise _SdoAbortError(cia.SDO_ABORT_TYPE_MISMATCH)
            self.write_object(int(st["index"]), int(st["sub"]), payload, now)  # type: ignore[call-overload]
            self._sdo = None
        else:
            st["toggle"] = toggle ^ 1
        self._sdo_reply(bytes(((cia.SDO_SCS_DOWNLOAD_SEGMENT << 5) | (toggle << 4),)))

    @staticmethod
    def _check_size(var: ODVariable, size: int) -> None:
        want = len(var) // 8
        if size > want:
            raise _SdoAbortError(cia.SDO_ABORT_LENGTH_TOO_HIGH)
        if size < want:
            raise _SdoAbortError(cia.SDO_ABORT_LENGTH_TOO_LOW)

    def write_object(self, index: int, sub: int, raw: bytes, now: float) -> None:
        """Validate and store an SDO download; raises ``_SdoAbortError`` with the CiA 301 code."""
        var = self._lookup(index, sub)
        if var.access_type not in _WRITABLE:
            raise _SdoAbortError(cia.SDO_ABORT_READ_ONLY)
        if var.fixed_size:
            self._check_size(var, len(raw))
        value = var.decode_raw(raw)
        if isinstance(value, int):
            lo = var.min if var.min is not None else None
            hi = var.max if var.max is not None else None
            if lo is not None and value < lo:
                raise _SdoAbortError(cia.SDO_ABORT_VALUE_TOO_LOW)
            if hi is not None and value > hi:
                raise _SdoAbortError(cia.SDO_ABORT_VALUE_TOO_HIGH)
            self._check_device_rules(index, sub, value)
        self.values[(index, sub)] = value
        self._after_write(index, sub, value, now)

    def _check_device_rules(self, index: int, sub: int, value: int) -> None:
        if index == cia.OD_QUICK_STOP_OPTION_CODE and not 0 <= value <= 8:
            raise _SdoAbortError(cia.SDO_ABORT_INVALID_VALUE)
        if index == cia.OD_MODES_OF_OPERATION and value not in SUPPORTED_MODES:
            raise _SdoAbortError(cia.SDO_ABORT_INVALID_VALUE)
        if index in (cia.OD_RPDO1_COMMUNICATION, cia.OD_TPDO1_COMMUNICATION):
            if sub == 1:
                old = int(self.values[(index, 1)])
                valid_now = not old & cia.PDO_COB_ID_INVALID
                if value & 0x20000000 or (value & 0x1FFFF800 and not value & 0x80000000):
                    raise _SdoAbortError(
                        cia.SDO_ABORT_INVALID_VALUE
                    )  # 29-bit / out of 11-bit range
                if valid_now and not value & cia.PDO_COB_ID_INVALID and value != old:
                    raise _SdoAbortError(cia.SDO_ABORT_INVALID_VALUE)  # disable the PDO first
            if sub == 2 and 240 < value < 254:
                raise _SdoAbortError(cia.SDO_ABORT_INVALID_VALUE)
        if index in (cia.OD_RPDO1_MAPPING, cia.OD_TPDO1_MAPPING):
            comm = index - 0x200
            if not int(self.values[(comm, 1)]) & cia.PDO_COB_ID_INVALID:
                raise _SdoAbortError(cia.SDO_ABORT_UNSUPPORTED_ACCESS)
            if sub == 0:
                if value > 8:
                    raise _SdoAbortError(cia.SDO_ABORT_PDO_LENGTH)
                total = 0
                for k in range(1, value + 1):
                    m_index, m_sub, bits = cia.parse_pdo_mapping_entry(int(self.values[(index, k)]))
                    total += bits
                    target = self._objects.get((m_index, m_sub))
                    if target is None or not target.pdo_mappable or len(target) != bits:
                        raise _SdoAbortError(cia.SDO_ABORT_NOT_MAPPABLE)
                    rx = index == cia.OD_RPDO1_MAPPING
                    if rx and target.access_type not in _WRITABLE:
                        raise _SdoAbortError(cia.SDO_ABORT_NOT_MAPPABLE)
                if total > 64:
                    raise _SdoAbortError(cia.SDO_ABORT_PDO_LENGTH)
            elif int(self.values[(index, 0)]) != 0:
                raise _SdoAbortError(cia.SDO_ABORT_UNSUPPORTED_ACCESS)  # set sub 0 to 0 first
        if index == cia.OD_CONSUMER_HEARTBEAT_TIME and sub >= 1:
            node = (value >> 16) & 0xFF
            if value >> 24 or (node == self.node_id and value & 0xFFFF):
                raise _SdoAbortError(cia.SDO_ABORT_INVALID_VALUE)

    def _after_write(self, index: int, sub: int, value: object, now: float) -> None:
        if 0x1400 <= index <= 0x1BFF:
            self._pdo_cache.clear()
        if index == cia.OD_CONTROLWORD:
            self._on_controlword(int(value), now)  # type: ignore[call-overload]
        elif index == cia.OD_PRODUCER_HEARTBEAT_TIME:
            self._schedule_heartbeat(now)
        elif index == cia.OD_CONSUMER_HEARTBEAT_TIME:
            self._hb_seen.clear()
            self._hb_lost.clear()
