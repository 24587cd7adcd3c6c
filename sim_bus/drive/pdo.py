"""PDOs and SYNC of a simulated drive (CiA 301 7.2.2, 7.2.5).

The RPDO (0x1400/0x1600, remappable) is buffered on reception and applied on
the next SYNC (synchronous types 0..240; 254/255 at once); the TPDO
(0x1800/0x1A00) is sent after every n-th SYNC (type n = 1..240, type 0 at
every SYNC).  An RPDO shorter than its mapping raises EMCY 0x8210 and is not
applied.  Each SYNC first moves the motor one interpolation period
(:mod:`sim_bus.drive.motion`).  Mapping parameters can only change while the
PDO is invalid (bit 31 of its COB-ID), sub-index 0 last; each entry is checked as it
is written (an absent object: 0x06020000 or 0x06090011; one that cannot be mapped there:
0x06040041), and the whole mapping again when sub-index 0 is set.  A mapping is compiled into a
:class:`~drivers.protocol.pdo.PdoLayout`, the layout the host encodes and parses its PDOs
with: both ends of the wire use the same encoder.
"""

from __future__ import annotations

import struct
from typing import TYPE_CHECKING, NamedTuple

import can
from canopen.objectdictionary import ODVariable

from drivers.protocol import cia301, cia402
from drivers.protocol.pdo import PdoLayout
from sim_bus.drive.objects import WRITABLE, Key, SdoAbort

if TYPE_CHECKING:
    from sim_bus.drive import DriveSim

#: A compiled mapping: its layout and, per value the layout carries, the mapped object
#: and its description.
Compiled = tuple[PdoLayout, list[tuple[Key, ODVariable]]]


class _Comm(NamedTuple):
    """PDO communication parameters as the SYNC path uses them."""

    sync_cob: int
    rpdo_cob: int | None  # None: RPDO1 invalid
    rpdo_type: int
    tpdo_cob: int  # the raw 0x1800.1 (bit 31: invalid)
    tpdo_type: int


MAX_PDO_BITS = 64
MAX_MAPPED_OBJECTS = 8
COB_ID_29_BIT = 0x20000000  # bit 29 of a PDO COB-ID: 29-bit identifier (not supported)


class PdoService:
    """RPDO1, TPDO1 and the SYNC consumer of one drive."""

    def __init__(self, drive: DriveSim) -> None:
        self._drive = drive
        self._od = drive.od
        self._cache: dict[int, Compiled] = {}
        self._rpdo_buffer: bytes | None = None
        self._sync_count = 0
        self._comm_at = -1  # the OD generation _comm was read at
        self._comm = _Comm(cia301.COB_SYNC, None, 0, cia301.PDO_COB_ID_INVALID, 0)

    def reset(self) -> None:
        """Reset communication: no compiled mapping, no buffered RPDO, SYNC count 0."""
        self._cache = {}
        self._rpdo_buffer = None
        self._sync_count = 0
        self._comm_at = -1

    def comm(self) -> _Comm:
        """The communication parameters (SYNC COB-ID, RPDO1 and TPDO1 COB-ID and type),
        read again only when the object dictionary changed (its ``generation``)."""
        od = self._od
        if self._comm_at != od.generation:
            values = od.values
            sync = int(values.get((cia301.OD_COB_ID_SYNC, 0), cia301.COB_SYNC)) & 0x7FF  # type: ignore[arg-type]
            rcob = od.int_value(cia301.OD_RPDO1_COMMUNICATION, 1)
            self._comm = _Comm(
                sync,
                None if rcob & cia301.PDO_COB_ID_INVALID else rcob & 0x7FF,
                od.int_value(cia301.OD_RPDO1_COMMUNICATION, 2),
                od.int_value(cia301.OD_TPDO1_COMMUNICATION, 1),
                od.int_value(cia301.OD_TPDO1_COMMUNICATION, 2),
            )
            self._comm_at = od.generation
        return self._comm

    def discard_buffered(self) -> None:
        """Forget an RPDO waiting for the next SYNC (operation was just enabled)."""
        self._rpdo_buffer = None

    @property
    def sync_cob_id(self) -> int:
        return self.comm().sync_cob

    @property
    def rpdo_cob_id(self) -> int | None:
        return self.comm().rpdo_cob

    # ---------------------------------------------------------------- mappings
    def _code_of(self, index: int, sub: int, bits: int) -> str | None:
        """The ``struct`` code of a mapped object (an unknown object: a dummy entry;
        None: raw bytes, decoded by the object's own description)."""
        var = self._od.objects.get((index, sub))
        if var is None:
            return f"{bits // 8}x"
        st = var.STRUCT_TYPES.get(var.data_type)
        if isinstance(st, struct.Struct) and st.size * 8 == bits:
            return st.format.lstrip("<")
        return None

    def _compiled(self, map_index: int) -> Compiled:
        """The compiled mapping of ``map_index``, cached until a PDO parameter is written."""
        cached = self._cache.get(map_index)
        if cached is not None:
            return cached
        n = self._od.int_value(map_index)
        mapping = [self._od.int_value(map_index, k) for k in range(1, n + 1)]
        layout = PdoLayout.of_mapping(mapping, self._code_of)
        objects = [((e.index, e.subindex), self._od.objects[(e.index, e.subindex)])
                   for e in layout.values]  # fmt: skip
        out: Compiled = (layout, objects)
        self._cache[map_index] = out
        return out

    def layout(self, map_index: int) -> PdoLayout:
        """The layout of RPDO1 (``cia301.OD_RPDO1_MAPPING``) or TPDO1 as mapped now."""
        return self._compiled(map_index)[0]

    # ---------------------------------------------------------------- frames in
    def on_rpdo(self, data: bytes, now: float) -> None:
        need = self._compiled(cia301.OD_RPDO1_MAPPING)[0].size
        if len(data) < need:
            self._drive.log(f"RPDO of {len(data)} bytes, mapping needs {need}: EMCY 0x8210")
            self._drive.emcy(cia301.EMCY_PDO_LENGTH)
            return
        if self.comm().rpdo_type <= 240:
            self._rpdo_buffer = data
        else:
            self._apply_rpdo(data, now)

    def _apply_rpdo(self, data: bytes, now: float) -> None:
        layout, objects = self._compiled(cia301.OD_RPDO1_MAPPING)
        decoded = layout.unpack_from(data)
        if layout.has_raw:
            decoded = tuple(
                var.decode_raw(v) if e.raw else v  # type: ignore[arg-type]
                for e, (_key, var), v in zip(layout.values, objects, decoded, strict=True)
            )
        for (key, _var), value in zip(objects, decoded, strict=True):
            self._od.write(key, value)  # type: ignore[arg-type]
            if key == (cia402.OD_CONTROLWORD, 0):
                self._drive._on_controlword(int(value), now)  # type: ignore[call-overload]

    def on_sync(self, now: float) -> None:
        """One SYNC: motion for one interpolation period, the TPDO if due, then the RPDO
        received since the last SYNC takes effect."""
        drive = self._drive
        dt = drive.motion.interpolation_period_s
        drive.motion.advance(dt, now)
        self._sync_count += 1
        comm = self.comm()
        ttype, tcob = comm.tpdo_type, comm.tpdo_cob
        if (
            not tcob & cia301.PDO_COB_ID_INVALID
            and 1 <= ttype <= 240
            and self._sync_count % ttype == 0
        ):
            self._send_tpdo(tcob & 0x7FF)
        elif not tcob & cia301.PDO_COB_ID_INVALID and ttype == 0:
            self._send_tpdo(tcob & 0x7FF)
        if self._rpdo_buffer is not None:
            data, self._rpdo_buffer = self._rpdo_buffer, None
            self._apply_rpdo(data, now)

    def _send_tpdo(self, cob: int) -> None:
        layout, objects = self._compiled(cia301.OD_TPDO1_MAPPING)
        live = self._drive.live_value
        if layout.has_raw:
            payload = layout.pack(
                *[
                    var.encode_raw(live(key)) if e.raw else live(key)
                    for e, (key, var) in zip(layout.values, objects, strict=True)
                ]
            )
        else:  # the drive's own values, in range: the layout's encoder, unchecked
            payload = layout.struct.pack(*[live(key) for key, _var in objects])
        self._drive.transmit(can.Message(arbitration_id=cob, data=payload, is_extended_id=False))

    # ---------------------------------------------------------------- objects
    def check_write(self, index: int, sub: int, value: int) -> None:
        """PDO communication and mapping parameters (raises :class:`SdoAbort`)."""
        od = self._od
        if index in (cia301.OD_RPDO1_COMMUNICATION, cia301.OD_TPDO1_COMMUNICATION):
            if sub == 1:
                old = od.int_value(index, 1)
                valid_now = not old & cia301.PDO_COB_ID_INVALID
                # a 29-bit id, or an id beyond 11 bits on a valid PDO
                if value & COB_ID_29_BIT or (
                    value & 0x1FFFF800 and not value & cia301.PDO_COB_ID_INVALID
                ):
                    raise SdoAbort(cia301.SDO_ABORT_INVALID_VALUE)
                if valid_now and not value & cia301.PDO_COB_ID_INVALID and value != old:
                    raise SdoAbort(cia301.SDO_ABORT_INVALID_VALUE)  # disable the PDO first
            if sub == 2 and 240 < value < 254:
                raise SdoAbort(cia301.SDO_ABORT_INVALID_VALUE)
        if index in (cia301.OD_RPDO1_MAPPING, cia301.OD_TPDO1_MAPPING):
            comm = index - 0x200
            if not od.int_value(comm, 1) & cia301.PDO_COB_ID_INVALID:
                raise SdoAbort(cia301.SDO_ABORT_UNSUPPORTED_ACCESS)
            if sub == 0:
                entries = sum(1 for i, k in od.objects if i == index and k >= 1)
                if value > min(MAX_MAPPED_OBJECTS, entries):  # the device file's entries
                    raise SdoAbort(cia301.SDO_ABORT_PDO_LENGTH)
                total = 0
                for k in range(1, value + 1):
                    m_index, m_sub, bits = cia301.parse_pdo_mapping_entry(od.int_value(index, k))
                    total += bits
                    target = od.objects.get((m_index, m_sub))
                    if target is None or not target.pdo_mappable or len(target) != bits:
                        raise SdoAbort(cia301.SDO_ABORT_NOT_MAPPABLE)
                    rx = index == cia301.OD_RPDO1_MAPPING
                    if rx and target.access_type not in WRITABLE:
                        raise SdoAbort(cia301.SDO_ABORT_NOT_MAPPABLE)
                if total > MAX_PDO_BITS:
                    raise SdoAbort(cia301.SDO_ABORT_PDO_LENGTH)
            elif od.int_value(index) != 0:
                raise SdoAbort(cia301.SDO_ABORT_UNSUPPORTED_ACCESS)  # set sub 0 to 0 first
            else:
                self._check_entry(index == cia301.OD_RPDO1_MAPPING, value)

    def _check_entry(self, rx: bool, value: int) -> None:
        """A mapping entry (sub-index 1..8) as it is written: 0 (no entry), or an object of
        the dictionary (else 0x06020000 / 0x06090011) that is PDO-mappable with its own
        length, writable for an RPDO (else 0x06040041).  The drive has no dummy objects
        (its EDS lists none in ``[DummyUsage]``)."""
        if value == 0:
            return
        m_index, m_sub, bits = cia301.parse_pdo_mapping_entry(value)
        target = self._od.lookup(m_index, m_sub)
        if (
            not target.pdo_mappable
            or len(target) != bits
            or (rx and target.access_type not in WRITABLE)
        ):
            raise SdoAbort(cia301.SDO_ABORT_NOT_MAPPABLE)

    def after_write(self, index: int) -> None:
        if 0x1400 <= index <= 0x1BFF:
            self._cache.clear()
