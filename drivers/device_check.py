"""What each drive's device file allows against what hrm needs, checked before any bus opens.

hrm drives every rope motor in cyclic synchronous position mode with one RPDO
(controlword, target position) and one TPDO (statusword, position actual value), both on
SYNC, and its bring-up (:func:`drivers.bringup.configure_drive`) writes the heartbeats,
the PDO mappings, the software limits, the interpolation period, the following-error
window and the quick-stop option code.  A drive whose device file (CiA 306, read by
:mod:`drivers.protocol.cia306`; named per drive in ``box.toml``'s ``[drives]`` table) does
not offer one of these is refused with one line naming the rope motor, the file and the
object, e.g. ``j03r1: 605.3150.68-B-EK-2-60.eds: no cyclic synchronous position mode
(0x6502 = 0x25: PP, PV, HM)``.  What it needs (:data:`NEEDS` lists it for the docs):

- CSP: bit 7 of 0x6502 (supported drive modes); 0x6060 writable, 0x6061 readable;
- 0x60C2 (interpolation time period) settable to the SYNC period within its limits;
- a heartbeat consumer 0x1016 (sub-index 1 writable) and producer 0x1017: the drive
  watches the host's heartbeat, the host the drive's; or, on a drive without 0x1016, node
  guarding (0x100C/0x100D writable): the host guards the drive, the drive its life time;
- RPDO1 and TPDO1 (0x1400/0x1600, 0x1800/0x1A00) with writable COB-ID, transmission type
  and two mapping entries, the four objects PDO-mappable;
- writable software position limits 0x607D, following-error window 0x6065, quick-stop
  option code 0x605A, quick-stop deceleration 0x6085 and max profile velocity 0x607F;
- positions in encoder increments: 0x60A8 (SI unit position), where the file has it,
  must say increments (hrm sends counts).

>>> from drivers.config import load_box_config
>>> report = check_box(load_box_config(None))
>>> report.refused, len(report.nodes)
(False, 36)
>>> print(report.lines()[0].replace("; ", ";\\n"))
j01r0: hrm_drive.eds: ok: RPDO1 = 0x6040, 0x607A;
TPDO1 = 0x6041, 0x6064 on SYNC (type 1);
0x60C2 = 10 x 10^-3 s;
heartbeat consumer 0x1016;
0x6085 from the motors' acceleration limit in counts/s^2
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.bringup import DriveSetup
from drivers.config import ExpectedIdentity, SdoWrite
from drivers.protocol import cia301, cia402
from drivers.protocol.cia306 import DeviceFile, ODEntry, read_device_file
from drivers.protocol.pdo import PdoLayout
from hrm_ctrl.errors import DriverError

if TYPE_CHECKING:
    from drivers.config import BoxConfig, ControlConfig


class DeviceCheckError(DriverError):
    """Some drive's device file does not offer what hrm needs (the first refusal, and how
    many there are: ``hrm box check`` lists them all)."""


#: 0x6502 bit -> mode (CiA 402: bit n is mode n+1; bit 4 is reserved)
MODE_BITS: Mapping[int, str] = {
    0: "PP", 1: "VL", 2: "PV", 3: "TQ", 5: "HM", 6: "IP", 7: "CSP", 8: "CSV", 9: "CST",
}  # fmt: skip
CSP_BIT = cia402.MODE_CSP - 1

#: 0x60A8 SI unit codes (byte 2) the check names; 0xB5: increments, what hrm sends
SI_UNITS: Mapping[int, str] = {
    0x00: "none", 0x01: "m", 0x10: "rad", 0x41: "degree", 0xB4: "revolution",
    0xB5: "increments",
}  # fmt: skip
SI_INCREMENTS = 0xB5
OD_SI_UNIT_POSITION = 0x60A8
OD_QUICK_STOP_DECELERATION = cia402.OD_QUICK_STOP_DECELERATION
OD_MAX_PROFILE_VELOCITY = 0x607F
OD_GUARD_TIME = cia301.OD_GUARD_TIME
OD_LIFE_TIME_FACTOR = cia301.OD_LIFE_TIME_FACTOR
#: how a drive without a heartbeat consumer watches the host: the host guards it
GUARDING = "node guarding 0x100C/0x100D"
OD_SI_UNIT_VELOCITY = 0x60A9
OD_SI_UNIT_ACCELERATION = 0x60AA
OD_POSITION_ENCODER_RESOLUTION = 0x608F
OD_GEAR_RATIO = 0x6091
OD_ACCELERATION_FACTOR = 0x6097
#: 0x60A9 time codes (byte 1): the denominator of the velocity unit, in seconds
TIME_UNITS_S: Mapping[int, float] = {0x03: 1.0, 0x47: 60.0}
SI_REVOLUTION = 0xB4

#: What hrm needs from a drive, for the docs' table: (object, what for)
NEEDS: tuple[tuple[str, str], ...] = (
    ("0x6502 bit 7", "cyclic synchronous position mode (CSP)"),
    ("0x6060 / 0x6061", "mode of operation written, its display read"),
    ("0x60C2", "interpolation time period set to the SYNC period"),
    ("0x1016 sub 1, 0x1017", "heartbeat consumer (the host's) and producer"),
    ("0x1400/0x1600, 0x1800/0x1A00", "RPDO1 and TPDO1, 2 entries each, on SYNC"),
    ("0x6040, 0x607A / 0x6041, 0x6064", "PDO-mappable (RPDO / TPDO)"),
    ("0x607D", "software position limits, writable"),
    ("0x6065", "following-error window, writable"),
    ("0x605A", "quick-stop option code, writable"),
    ("0x6085", "quick-stop deceleration, writable"),
    ("0x607F", "max profile velocity, writable"),
    ("0x60A8", "position unit: increments (where the file has it)"),
)

_NAMES = {
    cia402.OD_MODES_OF_OPERATION: "modes of operation",
    cia402.OD_MODES_OF_OPERATION_DISPLAY: "modes of operation display",
    cia402.OD_SOFTWARE_POSITION_LIMIT: "software position limit",
    cia402.OD_FOLLOWING_ERROR_WINDOW: "following error window",
    cia402.OD_QUICK_STOP_OPTION_CODE: "quick stop option code",
    OD_QUICK_STOP_DECELERATION: "quick stop deceleration",
    OD_MAX_PROFILE_VELOCITY: "max profile velocity",
    cia301.OD_PRODUCER_HEARTBEAT_TIME: "producer heartbeat time",
    OD_GUARD_TIME: "guard time",
    OD_LIFE_TIME_FACTOR: "life time factor",
    cia402.OD_CONTROLWORD: "controlword",
    cia402.OD_TARGET_POSITION: "target position",
    cia402.OD_STATUSWORD: "statusword",
    cia402.OD_POSITION_ACTUAL_VALUE: "position actual value",
}


def modes_text(modes: int) -> str:
    """The modes a 0x6502 value declares.

    >>> modes_text(0x25), modes_text(0x3A5)
    ('PP, PV, HM', 'PP, PV, HM, CSP, CSV, CST')
    """
    names = [name for bit, name in MODE_BITS.items() if modes >> bit & 1]
    return ", ".join(names) if names else "none"


def unit_text(value: int) -> str:
    """A 0x60A8 value as prefix and unit.

    >>> unit_text(0xFF410000), unit_text(0x00B50000)
    ('10^-1 degree', 'increments')
    """
    prefix = (value >> 24) & 0xFF
    exponent = prefix - 256 if prefix > 127 else prefix
    unit = SI_UNITS.get((value >> 16) & 0xFF, f"unit 0x{(value >> 16) & 0xFF:02X}")
    return unit if exponent == 0 else f"10^{exponent} {unit}"


@dataclass(frozen=True)
class PdoUse:
    """A PDO hrm uses on a drive: its name, communication and mapping objects, the
    objects it maps and its transmission type."""

    name: str
    communication: int
    mapping: int
    layout: PdoLayout
    transmission_type: int = cia301.PDO_TRANSMISSION_SYNCHRONOUS

    def text(self) -> str:
        """``RPDO1 = 0x6040, 0x607A``: the PDO and the objects it maps."""
        return f"{self.name} = {', '.join(f'0x{e.index:04X}' for e in self.layout.entries)}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "communication": f"0x{self.communication:04X}",
            "mapping": f"0x{self.mapping:04X}",
            "entries": [f"0x{v:08X}" for v in self.layout.mapping],
            "transmission_type": self.transmission_type,
        }


#: The cyclic layout hrm uses on every drive (drivers.bringup.configure_drive)
RPDO_USE = PdoUse(
    "RPDO1", cia301.OD_RPDO1_COMMUNICATION, cia301.OD_RPDO1_MAPPING, cia402.RPDO_TARGET
)
TPDO_USE = PdoUse(
    "TPDO1", cia301.OD_TPDO1_COMMUNICATION, cia301.OD_TPDO1_MAPPING, cia402.TPDO_FEEDBACK
)


@dataclass(frozen=True)
class DeviceVerdict:
    """What one device file allows against what hrm needs, at one SYNC period
    (independent of the node): the refusals (each a phrase naming the object), the PDO
    layout hrm will use, the 0x60C2 value it will write, and what else the file says."""

    refusals: tuple[str, ...]
    pdos: tuple[PdoUse, ...]
    interpolation: tuple[int, int] | None
    heartbeat: str
    facts: Mapping[str, Any] = field(default_factory=dict)
    quick_stop: QuickStopScale | str = "0x6085 not written"

    def ok_text(self) -> str:
        pdos = "; ".join(p.text() for p in self.pdos)
        period = (
            ""
            if self.interpolation is None
            else (f"; 0x60C2 = {self.interpolation[0]} x 10^{self.interpolation[1]} s")
        )
        qs = self.quick_stop if isinstance(self.quick_stop, str) else self.quick_stop.text()
        return f"{pdos} on SYNC (type 1){period}; {self.heartbeat}; {qs}"


def _hex(value: Any) -> str:
    return f"0x{value:X}" if isinstance(value, int) and value >= 0 else str(value)


def _writable_problem(f: DeviceFile, index: int, sub: int = 0) -> str | None:
    """Why hrm cannot write (index, sub) on this drive, or None."""
    name = _NAMES.get(index, "")
    label = f"0x{index:04X}" + (f"sub{sub}" if sub else "") + (f" ({name})" if name else "")
    e = f.entry(index, sub)
    if e is None:
        return f"no {label}"
    if not e.access.writable:
        return f"{label} is not writable (AccessType={e.access.value})"
    return None


def _mode_problems(f: DeviceFile) -> list[str]:
    out = []
    modes = f.value(cia402.OD_SUPPORTED_DRIVE_MODES)
    if f.entry(cia402.OD_SUPPORTED_DRIVE_MODES) is None:
        out.append(
            "no 0x6502 (supported drive modes): cyclic synchronous position mode not declared"
        )
    elif not isinstance(modes, int):
        out.append(
            "0x6502 (supported drive modes) has no value in the file: cyclic synchronous "
            "position mode not declared"
        )
    elif not modes >> CSP_BIT & 1:
        out.append(
            f"no cyclic synchronous position mode (0x6502 = 0x{modes:X}: {modes_text(modes)})"
        )
    for problem in (
        _writable_problem(f, cia402.OD_MODES_OF_OPERATION),
        None
        if f.entry(cia402.OD_MODES_OF_OPERATION_DISPLAY) is not None
        else "no 0x6061 (modes of operation display)",
    ):
        if problem:
            out.append(problem)
    return out


def _limits(e: ODEntry) -> tuple[int, int]:
    lo, hi = e.data_type.int_range() if e.data_type.is_integer else (0, 0)
    if isinstance(e.low, int):
        lo = max(lo, e.low)
    if isinstance(e.high, int):
        hi = min(hi, e.high)
    return lo, hi


def interpolation_setting(f: DeviceFile, period_s: float) -> tuple[int, int] | str:
    """(value, index) the drive's 0x60C2 takes for ``period_s`` within its limits (hrm's
    own encoding first, :func:`cia402.interpolation_time_period`), or why none fits."""
    e1, e2 = f.entry(cia402.OD_INTERPOLATION_TIME_PERIOD, 1), f.entry(0x60C2, 2)
    if e1 is None or e2 is None:
        return "no 0x60C2 (interpolation time period): the SYNC period cannot be set"
    ms = period_s * 1e3
    if not e1.access.writable:
        return (
            "0x60C2sub1 (interpolation time period value) is not writable "
            f"(AccessType={e1.access.value})"
        )
    lo1, hi1 = _limits(e1)
    if e2.access.writable:
        lo2, hi2 = _limits(e2)
        indices = [i for i in (-3, -4, -5, -6, -2, -1, 0) if lo2 <= i <= hi2]
    else:
        fixed = e2.value
        indices = [fixed] if isinstance(fixed, int) else []
    for index in indices:
        value = period_s / 10.0**index
        rounded = round(value)
        if lo1 <= rounded <= hi1 and abs(value - rounded) <= 1e-9 * max(1.0, value):
            return int(rounded), index
    allowed = ", ".join(f"10^{i}" for i in indices) or "none"
    return (
        f"0x60C2 (interpolation time period) cannot be set to the SYNC period {ms:g} ms "
        f"(value {lo1}..{hi1}, index {allowed})"
    )


def _heartbeat(f: DeviceFile) -> tuple[str, list[str]]:
    """(how the drive watches the host, problems)."""
    problems = []
    consumer = f.entry(cia301.OD_CONSUMER_HEARTBEAT_TIME, 1)
    guarding = f.entry(OD_GUARD_TIME) is not None and f.entry(OD_LIFE_TIME_FACTOR) is not None
    if consumer is not None and consumer.access.writable:
        how = "heartbeat consumer 0x1016"
    elif consumer is not None:
        how = "none"
        problems.append(
            "0x1016sub1 (consumer heartbeat time) is not writable "
            f"(AccessType={consumer.access.value})"
        )
    elif guarding:
        how = GUARDING
        for index in (OD_GUARD_TIME, OD_LIFE_TIME_FACTOR):
            problem = _writable_problem(f, index)
            if problem:
                problems.append(problem)
    else:
        how = "none"
        problems.append("no heartbeat consumer 0x1016 nor node guarding 0x100C/0x100D")
    # a guarded drive produces no heartbeat (0x1017 written 0 where it has one)
    if how != GUARDING or f.entry(cia301.OD_PRODUCER_HEARTBEAT_TIME) is not None:
        producer = _writable_problem(f, cia301.OD_PRODUCER_HEARTBEAT_TIME)
        if producer:
            problems.append(producer)
    return how, problems


def _pdo_problems(f: DeviceFile, use: PdoUse, count: int) -> list[str]:
    out = []
    kind = use.name[:4]
    n_available = sum(1 for i in f.objects if use.communication <= i < use.communication + 0x200)
    if f.entry(use.communication, 1) is None or use.mapping not in f.objects:
        return [
            f"no {use.name} (0x{use.communication:04X}/0x{use.mapping:04X}): "
            f"{kind}s in the file: {n_available}"
        ]
    for sub, what in ((1, "COB-ID"), (2, "transmission type")):
        e = f.entry(use.communication, sub)
        if e is None or not e.access.writable:
            shown = "absent" if e is None else f"AccessType={e.access.value}"
            out.append(
                f"0x{use.communication:04X}sub{sub} ({use.name} {what}) is not writable ({shown})"
            )
    sub0 = f.entry(use.mapping, 0)
    if sub0 is None or not sub0.access.writable:
        out.append(
            f"0x{use.mapping:04X}sub0 ({use.name} number of mapped objects) is not "
            "writable: the mapping is fixed"
        )
    slots = [s for s, e in f.objects[use.mapping].entries.items() if s >= 1 and e.access.writable]
    if sub0 is not None and isinstance(sub0.high, int):
        slots = [s for s in slots if s <= sub0.high]
    if len(slots) < count:
        out.append(
            f"0x{use.mapping:04X} ({use.name} mapping) has {len(slots)} writable entries, "
            f"hrm maps {count}"
        )
    for entry in use.layout.entries:
        e = f.entry(entry.index, entry.subindex)
        name = _NAMES.get(entry.index, entry.label)
        if e is None:
            out.append(f"no 0x{entry.index:04X} ({name})")
        elif not e.pdo_mappable:
            out.append(f"0x{entry.index:04X} ({name}) is not PDO-mappable (PDOMapping=0)")
        elif e.data_type.bits != entry.size * 8:
            out.append(
                f"0x{entry.index:04X} ({name}) is {e.data_type.name}, hrm maps "
                f"{entry.size * 8} bits"
            )
    return out


def _unit_problem(f: DeviceFile, overlay: Sequence[SdoWrite]) -> str | None:
    """Why the drive's position unit (0x60A8, the file's or the overlay's value) is not
    increments, or None."""
    e = f.entry(OD_SI_UNIT_POSITION)
    written = [w.value for w in overlay if (w.index, w.sub) == (OD_SI_UNIT_POSITION, 0)]
    value = written[-1] if written else f.value(OD_SI_UNIT_POSITION)
    if e is None or not isinstance(value, int) or value == 0:
        return None
    if (value >> 16) & 0xFF == SI_INCREMENTS and (value >> 24) & 0xFF == 0:
        return None
    if written:
        return (
            f"position unit 0x60A8 = 0x{value:08X} ({unit_text(value)}) in the SDO overlay, "
            "not increments: hrm sends encoder counts"
        )
    settable = (
        'writable: an SDO overlay sets it, sdo = { "0x60A8" = 0x00B50000 }'
        if e.access.writable
        else "not writable"
    )
    return (
        f"position unit 0x60A8 = 0x{value:08X} ({unit_text(value)}), not increments: hrm sends "
        f"encoder counts ({settable})"
    )


@dataclass(frozen=True)
class QuickStopScale:
    """How the bring-up writes the quick-stop deceleration 0x6085 on a drive: the drive's
    acceleration ``unit``, how many of it one count/s^2 is (``per_count_s2``), and the
    values the object takes (its type within the file's ``LowLimit``..``HighLimit``, at
    least 1: a zero deceleration would not stop).

    >>> QuickStopScale("counts/s^2", 1.0, 1, 2**32 - 1).value(2.048e6)
    2048000
    >>> QuickStopScale("rpm/s", 60 / 2000, 1, 32000).value(2.048e6) is None
    True
    """

    unit: str
    per_count_s2: float
    low: int
    high: int

    def value(self, accel_counts_per_s2: float) -> int | None:
        """0x6085 for an acceleration limit of ``accel_counts_per_s2``, or None when it
        is outside :attr:`low`..:attr:`high`."""
        v = round(float(accel_counts_per_s2) * self.per_count_s2)
        return v if self.low <= v <= self.high else None

    def text(self) -> str:
        return f"0x6085 from the motors' acceleration limit in {self.unit}"


def _written_or_file(f: DeviceFile, overlay: Sequence[SdoWrite], index: int, sub: int = 0) -> Any:
    """The value ``(index, sub)`` has after the overlay: its last write, else the file's."""
    written = [w.value for w in overlay if (w.index, w.sub) == (index, sub)]
    return written[-1] if written else f.value(index, sub)


def _ratio_problem(f: DeviceFile, overlay: Sequence[SdoWrite], index: int, name: str) -> str | None:
    """Why the factor ``index`` (sub 1 / sub 2, where the file has it) is not 1:1, or None."""
    if f.entry(index, 1) is None:
        return None
    num, den = (_written_or_file(f, overlay, index, s) for s in (1, 2))
    if not (isinstance(num, int) and isinstance(den, int)):
        return f"{name} 0x{index:04X} has no value in the file"
    if num == den and num != 0:
        return None
    return f"{name} 0x{index:04X} = {num}:{den}, not 1:1"


def quick_stop_scale(f: DeviceFile, overlay: Sequence[SdoWrite] = ()) -> QuickStopScale | str:
    """How 0x6085 is written on the drive of file ``f`` (after the ``overlay``), or why hrm
    does not write it (the drive keeps its own value).

    The acceleration unit is the drive's 0x60AA (SI unit acceleration) where it has one
    (not converted by hrm), else the velocity unit 0x60A9 per second, else the position
    unit per second squared (0x60A8, which the check requires to be increments: hrm's
    counts).  A velocity unit in increments per second or minute converts directly; one in
    revolutions needs the drive's counts per revolution, 0x608F (position encoder
    resolution: increments / motor revolutions).  A gear ratio 0x6091 or acceleration
    factor 0x6097 other than 1:1 is not converted.  An SDO overlay that writes 0x6085
    itself wins.

    >>> from drivers import eds_path
    >>> from drivers.protocol.cia306 import read_device_file
    >>> quick_stop_scale(read_device_file(eds_path()))
    QuickStopScale(unit='counts/s^2', per_count_s2=1.0, low=1, high=4294967295)
    """
    e = f.entry(OD_QUICK_STOP_DECELERATION)
    if e is None or not e.access.writable or not e.data_type.is_integer:
        return "0x6085 not writable"
    if any((w.index, w.sub) == (OD_QUICK_STOP_DECELERATION, 0) for w in overlay):
        return "0x6085 by the SDO overlay"
    lo, hi = _limits(e)
    lo = max(lo, 1)
    for index, name in (
        (OD_GEAR_RATIO, "gear ratio"),
        (OD_ACCELERATION_FACTOR, "acceleration factor"),
    ):
        problem = _ratio_problem(f, overlay, index, name)
        if problem:
            return f"0x6085 the drive's own ({problem})"
    accel = _written_or_file(f, overlay, OD_SI_UNIT_ACCELERATION)
    if f.entry(OD_SI_UNIT_ACCELERATION) is not None and isinstance(accel, int) and accel:
        return f"0x6085 the drive's own (acceleration unit 0x60AA = 0x{accel:08X}: not converted)"
    velocity = _written_or_file(f, overlay, OD_SI_UNIT_VELOCITY)
    if f.entry(OD_SI_UNIT_VELOCITY) is None or not isinstance(velocity, int) or not velocity:
        return QuickStopScale("counts/s^2", 1.0, lo, hi)
    prefix = (velocity >> 24) & 0xFF
    exponent = prefix - 256 if prefix > 127 else prefix
    unit, time_code = (velocity >> 16) & 0xFF, (velocity >> 8) & 0xFF
    per_s = TIME_UNITS_S.get(time_code)
    if per_s is None or unit not in (SI_INCREMENTS, SI_REVOLUTION):
        return f"0x6085 the drive's own (velocity unit 0x60A9 = 0x{velocity:08X}: not converted)"
    scale = per_s / 10.0**exponent  # drive units per (increment or revolution)/s^2
    shown = f"{'' if exponent == 0 else f'10^{exponent} '}"
    if unit == SI_INCREMENTS:
        name = "increments/s" if per_s == 1.0 else "increments/min"
        return QuickStopScale(f"{shown}{name} per s", scale, lo, hi)
    counts, revs = (_written_or_file(f, overlay, OD_POSITION_ENCODER_RESOLUTION, s) for s in (1, 2))
    if not (isinstance(counts, int) and isinstance(revs, int) and counts > 0 and revs > 0):
        return (
            "0x6085 the drive's own (velocity unit 0x60A9 in revolutions, counts per "
            "revolution 0x608F not in the file)"
        )
    name = "rpm/s" if per_s == 60.0 else "revolutions/s^2"
    return QuickStopScale(
        f"{shown}{name} ({counts / revs:g} counts a revolution, 0x608F)",
        scale * revs / counts,
        lo,
        hi,
    )


def overlay_problems(f: DeviceFile, overlay: Sequence[SdoWrite]) -> list[str]:
    """Why the drive cannot take an SDO overlay's writes, by its file: an object it does
    not have, not writable, not an integer, a value outside its type or its limits.

    >>> from drivers import eds_path
    >>> from drivers.config import SdoWrite
    >>> from drivers.protocol.cia306 import read_device_file
    >>> f = read_device_file(eds_path())
    >>> for line in overlay_problems(f, (SdoWrite(0x6085, 0, -1), SdoWrite(0x1018, 1, 5))):
    ...     print(line)
    SDO overlay 0x6085:00 = -1: outside UNSIGNED32 (0..4294967295)
    SDO overlay 0x1018:01 = 5: not writable (AccessType=ro)
    """
    out = []
    for w in overlay:
        what = f"SDO overlay {w.label} = {w.value}"
        e = f.entry(w.index, w.sub)
        if e is None:
            out.append(f"{what}: no such object in the file")
        elif not e.access.writable:
            out.append(f"{what}: not writable (AccessType={e.access.value})")
        elif not e.data_type.is_integer:
            out.append(f"{what}: {e.data_type.name}, not an integer")
        else:
            lo, hi = e.data_type.int_range()
            if not lo <= w.value <= hi:
                out.append(f"{what}: outside {e.data_type.name} ({lo}..{hi})")
            elif (e.low is not None and w.value < e.low) or (
                e.high is not None and w.value > e.high
            ):
                out.append(f"{what}: outside the file's LowLimit..HighLimit ({e.low}..{e.high})")
    return out


def check_device(f: DeviceFile, period_s: float, overlay: Sequence[SdoWrite] = ()) -> DeviceVerdict:
    """What device file ``f`` allows against what hrm needs at SYNC period ``period_s``,
    with the SDO ``overlay`` the box configuration writes to it first."""
    refusals: list[str] = overlay_problems(f, overlay)
    refusals += _mode_problems(f)
    setting = interpolation_setting(f, period_s)
    if isinstance(setting, str):
        refusals.append(setting)
    how, problems = _heartbeat(f)
    refusals += problems
    refusals += _pdo_problems(f, RPDO_USE, len(cia402.RPDO_TARGET.entries))
    refusals += _pdo_problems(f, TPDO_USE, len(cia402.TPDO_FEEDBACK.entries))
    for index, sub in (
        (cia402.OD_SOFTWARE_POSITION_LIMIT, 1),
        (cia402.OD_SOFTWARE_POSITION_LIMIT, 2),
        (cia402.OD_FOLLOWING_ERROR_WINDOW, 0),
        (cia402.OD_QUICK_STOP_OPTION_CODE, 0),
        (OD_QUICK_STOP_DECELERATION, 0),
        (OD_MAX_PROFILE_VELOCITY, 0),
    ):
        problem = _writable_problem(f, index, sub)
        if problem:
            refusals.append(problem)
    unit = _unit_problem(f, overlay)
    if unit:
        refusals.append(unit)
    modes = f.value(cia402.OD_SUPPORTED_DRIVE_MODES)
    unit_value = f.value(OD_SI_UNIT_POSITION)
    quick_stop = quick_stop_scale(f, overlay)
    facts = {
        "device": f"{f.device.vendor_name} {f.device.product_name}".strip(),
        "dcf": f.is_dcf,
        "dcf_node_id": f.node_id,  # a DCF's values are its node's (COB-IDs rewritten at bring-up)
        "modes": modes_text(modes) if isinstance(modes, int) else None,
        "rpdos": sum(1 for i in f.objects if 0x1400 <= i < 0x1600),
        "tpdos": sum(1 for i in f.objects if 0x1800 <= i < 0x1A00),
        "tpdo1_transmission_type": f.value(cia301.OD_TPDO1_COMMUNICATION, 2),
        "interpolation_default": [f.value(0x60C2, 1), f.value(0x60C2, 2)],
        "position_unit": unit_text(unit_value)
        if isinstance(unit_value, int) and unit_value
        else None,
        "watches_host_by": how,
        "quick_stop_deceleration": quick_stop
        if isinstance(quick_stop, str)
        else {"unit": quick_stop.unit, "per_count_s2": quick_stop.per_count_s2,
              "range": [quick_stop.low, quick_stop.high]},
        "quirks": list(f.quirks),
    }  # fmt: skip
    return DeviceVerdict(
        refusals=tuple(refusals),
        pdos=(RPDO_USE, TPDO_USE),
        interpolation=None if isinstance(setting, str) else setting,
        heartbeat=how,
        facts=facts,
        quick_stop=quick_stop,
    )


@dataclass(frozen=True)
class NodeCheck:
    """One drive of the box: its rope motor, bus, node id, device file and verdict."""

    motor: str
    bus: str
    node_id: int
    path: Path
    verdict: DeviceVerdict
    overlay: tuple[SdoWrite, ...] = ()
    identity: ExpectedIdentity = field(default_factory=ExpectedIdentity)

    @property
    def file(self) -> str:
        return self.path.name

    guarding: tuple[int, int] | None = None

    @property
    def setup(self) -> DriveSetup:
        """What the bring-up writes and checks on this drive beyond the common settings:
        the overlay, 0x60C2 in the drive's encoding, the identity it must answer, and the
        node guarding (guard time ms, life time factor) of a drive the host guards."""
        return DriveSetup(
            self.verdict.interpolation, self.overlay, self.identity, guarding=self.guarding
        )

    def lines(self) -> list[str]:
        """One line per refusal, or one ``ok`` line with the layout hrm will use (and the
        SDO overlay's writes)."""
        if not self.verdict.refusals:
            overlay = "".join(f"; {w.label} = {_hex(w.value)}" for w in self.overlay)
            return [f"{self.motor}: {self.file}: ok: {self.verdict.ok_text()}{overlay}"]
        return [f"{self.motor}: {self.file}: {r}" for r in self.verdict.refusals]

    def to_dict(self) -> dict[str, Any]:
        v = self.verdict
        return {
            "motor": self.motor,
            "bus": self.bus,
            "node_id": self.node_id,
            "device_file": str(self.path),
            "ok": not v.refusals,
            "refusals": list(v.refusals),
            "pdos": [p.to_dict() for p in v.pdos],
            "interpolation_time_period": None if v.interpolation is None else list(v.interpolation),
            "sdo_overlay": {w.label: w.value for w in self.overlay},
            "identity": self.identity.to_dict(),
            "file": dict(v.facts),
        }


@dataclass(frozen=True)
class BoxCheck:
    """Every drive of a box checked (:func:`check_box`)."""

    source: str
    nodes: tuple[NodeCheck, ...]

    @property
    def refused(self) -> bool:
        return any(n.verdict.refusals for n in self.nodes)

    def lines(self) -> list[str]:
        return [line for n in self.nodes for line in n.lines()]

    def refusal_lines(self) -> list[str]:
        return [line for n in self.nodes if n.verdict.refusals for line in n.lines()]

    def to_dict(self) -> dict[str, Any]:
        return {
            "config": self.source,
            "ok": not self.refused,
            "nodes": [n.to_dict() for n in self.nodes],
        }

    def setups(
        self, accel_counts_per_s2: Mapping[str, float] | None = None
    ) -> dict[str, DriveSetup]:
        """Each motor's :class:`drivers.bringup.DriveSetup` (for the bring-up), with the
        quick-stop deceleration 0x6085 from each motor's acceleration limit
        (``accel_counts_per_s2``, counts/s^2, per motor; none: 0x6085 not written) in its
        drive's unit (:func:`quick_stop_scale`).  A value outside what the drive's 0x6085
        takes is :class:`DeviceCheckError` (one line naming motor, file, value and range),
        before anything is sent."""
        out = {}
        for n in self.nodes:
            setup = n.setup
            scale = n.verdict.quick_stop
            accel = None if accel_counts_per_s2 is None else accel_counts_per_s2.get(n.motor)
            if accel is not None and isinstance(scale, QuickStopScale):
                value = scale.value(accel)
                if value is None:
                    raise DeviceCheckError(
                        f"{self.source}: {n.motor}: {n.file}: quick-stop deceleration 0x6085: "
                        f"the motor's acceleration limit {accel:g} counts/s^2 is "
                        f"{accel * scale.per_count_s2:g} {scale.unit}, outside "
                        f"{scale.low}..{scale.high} (the object's type and limits)"
                    )
                setup = replace(setup, quick_stop_deceleration=value)
            out[n.motor] = setup
        return out

    def raise_if_refused(self) -> None:
        """:class:`DeviceCheckError` with the first refusal and the count, if any."""
        refusals = self.refusal_lines()
        if refusals:
            more = (
                f" (and {len(refusals) - 1} more: hrm box check lists them)"
                if len(refusals) > 1
                else ""
            )
            raise DeviceCheckError(f"{self.source}: {refusals[0]}{more}")


def guarding_setting(control: ControlConfig) -> tuple[int, int]:
    """(guard time 0x100C in ms, life time factor 0x100D) of a drive the host guards: a
    guarding request every host heartbeat period (the host's watch of the drive is its
    heartbeat timeout on the answers), the drive's life time the whole periods within the
    heartbeat timeout (at least 3: ``[control]``'s relations).

    >>> from drivers.config import ControlConfig
    >>> guarding_setting(ControlConfig(host_heartbeat_ms=100, heartbeat_timeout_ms=350))
    (100, 3)
    """
    factor = control.heartbeat_timeout_ms // control.host_heartbeat_ms
    return control.host_heartbeat_ms, max(1, min(255, factor))


def check_box(config: BoxConfig) -> BoxCheck:
    """Every drive of ``config`` against its device file (each file read once);
    :class:`drivers.protocol.cia306.DeviceFileError` on a file that cannot be read."""
    files: dict[Path, DeviceFile] = {}
    verdicts: dict[tuple[Path, tuple[SdoWrite, ...]], DeviceVerdict] = {}
    nodes = []
    for bus in config.buses:
        for motor, node_id in bus.nodes.items():
            path = config.drives.device_file(motor)
            overlay = config.drives.sdo_overlay(motor)
            if path not in files:
                files[path] = read_device_file(path)
            if (path, overlay) not in verdicts:
                verdicts[(path, overlay)] = check_device(
                    files[path], config.control.period_s, overlay
                )
            verdict = verdicts[(path, overlay)]
            nodes.append(
                NodeCheck(
                    motor,
                    bus.name,
                    node_id,
                    path,
                    verdict,
                    overlay,
                    config.drives.expected_identity(motor),
                    guarding_setting(config.control) if verdict.heartbeat == GUARDING else None,
                )
            )
    return BoxCheck(config.source, tuple(nodes))
