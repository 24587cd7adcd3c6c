"""Which box the drives are: each drive's CiA 301 identity object (0x1018), and the check
that a calibration was made on this box.

Every CiA 301 device has the identity object 0x1018: vendor-ID (sub 1, assigned by CiA),
product code (2), revision number (3) and serial number (4).  A session reads it from
every drive at the bring-up, after the boot-ups and before any configuration
(:func:`read_identity`), and keeps it as the box's :class:`BoxIdentity`.

**Simulated drives.**  The simulated drives answer with the vendor-ID
:data:`SIMULATOR_VENDOR_ID` (0: CiA assigns no vendor the ID 0, so no real drive
reports it; whatever device file the box configuration gives them), and serial numbers
derived from the simulated arm's truth (``sim_bus.truth.drive_serials``): a perturbed arm
is another box.  A box whose every
drive has that vendor-ID is a simulated box (:attr:`BoxIdentity.simulated`).

**The check** (:func:`box_problems`), of the box a calibration was made on against the
box at hand; each problem is one line:

* a calibration whose box is unknown (made before calibrations named their box) is
  refused: ``hrm calibrate use VERSION --box`` confirms it on the box at hand;
* a calibration made on a simulated box is refused on a real one, and the other way round;
* a calibration of another box (no drive of it is one of this box) is refused;
* a replaced drive (its vendor, product code or serial not the one calibrated) is named:
  its motor zero is not this drive's.  The revision is recorded only (a firmware update
  keeps the drive's zero).

>>> sim = BoxIdentity.of({"j01r0": DriveIdentity(0, 0x402, 0x10000, 0x1234)})
>>> real = BoxIdentity.of({"j01r0": DriveIdentity(0x9A, 0x402, 0x10000, 0x1234)})
>>> sim.simulated, real.simulated
(True, False)
>>> box_problems(None, real, "v0001.json")  # doctest: +ELLIPSIS
['v0001.json: box unknown (made before calibrations named their box): ...']
>>> box_problems(sim, real, "v0001.json")  # doctest: +ELLIPSIS
['v0001.json: made on a simulated box; a real box never uses it ...']
>>> new = BoxIdentity.of({"j01r0": DriveIdentity(0x9A, 0x402, 0x10000, 0x99)})
>>> box_problems(BoxIdentity.of({**real.drives, "j01r1": real.drives["j01r0"]}),
...              BoxIdentity.of({**new.drives, "j01r1": real.drives["j01r0"]}), "v0001.json")
['j01r0: drive serial 0x00000099 is not the one calibrated (0x00001234): run calibrate zero for it']
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol

from hrm_ctrl.errors import DriverError

if TYPE_CHECKING:  # the calibration store reads identities without the CANopen stack
    from drivers.bringup import DriveLink
    from drivers.cycle import EventLog

SIMULATOR_VENDOR_ID = 0x00000000
"""The vendor-ID of the simulated drives (the shipped EDS's; no real vendor has it)."""

_FIELDS = ("vendor_id", "product_code", "revision", "serial")
_ID = re.compile(r"[A-Za-z0-9_.-]{1,32}")
U32_MAX = 0xFFFFFFFF


class BoxIdentityError(DriverError):
    """The calibration in use was not made on this box (or on one of its drives)."""


@dataclass(frozen=True)
class DriveIdentity:
    """One drive's identity object 0x1018 (four UNSIGNED32)."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int

    def __post_init__(self) -> None:
        for name in _FIELDS:
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= U32_MAX:
                raise ValueError(f"{name} must be an UNSIGNED32, not {v!r}")

    def same_drive(self, other: DriveIdentity) -> bool:
        """The same physical drive (vendor, product code and serial; not the revision).
        Two simulated drives (vendor :data:`SIMULATOR_VENDOR_ID`) are the same when their
        serials are: the serial is their simulated truth's, the product code the device
        file's the box configuration names."""
        if self.vendor_id == other.vendor_id == SIMULATOR_VENDOR_ID:
            return self.serial == other.serial
        return (self.vendor_id, self.product_code, self.serial) == (
            other.vendor_id,
            other.product_code,
            other.serial,
        )

    def text(self) -> str:
        """``vendor 0x… product 0x… revision 0x… serial 0x…``."""
        return " ".join(f"{n.split('_')[0]} 0x{getattr(self, n):08X}" for n in _FIELDS)

    def to_dict(self) -> dict[str, int]:
        return {n: getattr(self, n) for n in _FIELDS}


@dataclass(frozen=True)
class BoxIdentity:
    """The identities of a box's drives, per motor id, and whether it is simulated
    (every drive has :data:`SIMULATOR_VENDOR_ID`)."""

    simulated: bool
    drives: Mapping[str, DriveIdentity] = field(default_factory=dict)

    @classmethod
    def of(cls, drives: Mapping[str, DriveIdentity]) -> BoxIdentity:
        """The box of ``drives`` (simulated when every one has the simulator's vendor)."""
        simulated = bool(drives) and all(
            d.vendor_id == SIMULATOR_VENDOR_ID for d in drives.values()
        )
        return cls(simulated, MappingProxyType(dict(drives)))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON: ``{"simulated": bool, "drives": {motor: {vendor_id: …}}}``."""
        return {
            "simulated": self.simulated,
            "drives": {m: d.to_dict() for m, d in self.drives.items()},
        }

    @classmethod
    def from_dict(cls, doc: Any, fail: Callable[[str], Exception]) -> BoxIdentity:
        """The box of :meth:`to_dict`'s ``doc``; ``fail(why)`` makes the error raised."""
        if not isinstance(doc, Mapping) or set(doc) != {"simulated", "drives"}:
            raise fail("box must be a table of simulated and drives")
        if not isinstance(doc["simulated"], bool):
            raise fail("box.simulated must be true or false")
        drives = doc["drives"]
        if not isinstance(drives, Mapping) or not drives or len(drives) > 128:
            raise fail("box.drives must be a table of 1 to 128 motor id -> identity")
        out: dict[str, DriveIdentity] = {}
        for motor, d in drives.items():
            if not isinstance(motor, str) or not _ID.fullmatch(motor):
                raise fail(f"box.drives: id {motor!r} is not 1-32 of A-Z a-z 0-9 _ . -")
            if not isinstance(d, Mapping) or set(d) != set(_FIELDS):
                raise fail(f"box.drives.{motor} must have {', '.join(_FIELDS)}")
            try:
                out[motor] = DriveIdentity(**{n: d[n] for n in _FIELDS})
            except ValueError as exc:
                raise fail(f"box.drives.{motor}: {exc}") from None
        box = cls(doc["simulated"], MappingProxyType(out))
        if box.simulated != cls.of(out).simulated:
            raise fail("box.simulated does not match the drives' vendor-IDs")
        return box

    def describe(self) -> str:
        """One line: ``simulated box, 36 drives, serials 0x…..0x…``."""
        kind = "simulated box" if self.simulated else "real box"
        serials = sorted(d.serial for d in self.drives.values())
        if not serials:
            return f"{kind}, no drives"
        return f"{kind}, {len(serials)} drives, serials 0x{serials[0]:08X}..0x{serials[-1]:08X}"


def read_identity(link: DriveLink) -> DriveIdentity:
    """The identity object 0x1018 of one drive, read by SDO (:class:`SdoError` naming the
    drive when it does not answer)."""
    from drivers.bringup import sdo_read
    from drivers.protocol.cia301 import OD_IDENTITY

    values = [int(sdo_read(link, OD_IDENTITY, sub)) for sub in (1, 2, 3, 4)]
    return DriveIdentity(*values)


def box_problems(calibrated: BoxIdentity | None, live: BoxIdentity, where: str) -> list[str]:
    """Why a calibration made on ``calibrated`` (None: unknown) may not be used on the
    box ``live`` (``where``: the calibration file, in messages); empty when it may."""
    if calibrated is None:
        return [
            f"{where}: box unknown (made before calibrations named their box): confirm it "
            "was made on this box with hrm calibrate use VERSION --box, or run the "
            "calibration again"
        ]
    if calibrated.simulated and not live.simulated:
        return [
            f"{where}: made on a simulated box; a real box never uses it (run hrm calibrate "
            "zero and kinematic on this box)"
        ]
    if live.simulated and not calibrated.simulated:
        return [f"{where}: made on a real box, not on this simulated one"]
    common = [m for m in live.drives if m in calibrated.drives]
    same = [m for m in common if live.drives[m].same_drive(calibrated.drives[m])]
    if not same:
        what = "simulated arm" if live.simulated else "box"
        return [
            f"{where}: made on another {what} (none of its {len(calibrated.drives)} drives "
            f"is one of these {len(live.drives)}): run hrm calibrate zero and kinematic on "
            "this one"
        ]
    out = []
    for m, d in live.drives.items():
        had = calibrated.drives.get(m)
        if had is None:
            out.append(f"{m}: drive serial 0x{d.serial:08X} was not calibrated: run calibrate "
                       "zero for it")  # fmt: skip
        elif not d.same_drive(had):
            what = "serial" if d.serial != had.serial else "identity"
            now, then = (
                (f"0x{d.serial:08X}", f"0x{had.serial:08X}")
                if what == "serial"
                else (d.text(), had.text())
            )
            out.append(
                f"{m}: drive {what} {now} is not the one calibrated ({then}): run calibrate "
                "zero for it"
            )
    return out


def same_box(calibrated: BoxIdentity | None, live: BoxIdentity) -> bool:
    """Whether ``live`` is the box ``calibrated`` names, drives replaced since or not
    (known, both simulated or both real, at least one drive the same)."""
    if calibrated is None or calibrated.simulated != live.simulated:
        return False
    return any(
        m in calibrated.drives and d.same_drive(calibrated.drives[m])
        for m, d in live.drives.items()
    )


def check_box(calibrated: BoxIdentity | None, live: BoxIdentity, where: str) -> None:
    """:class:`BoxIdentityError` listing :func:`box_problems`, if any ("; "-joined, one
    line)."""
    problems = box_problems(calibrated, live, where)
    if problems:
        raise BoxIdentityError("calibration refused: " + "; ".join(problems))


class CalibratedBox(Protocol):
    """What the check needs of the calibration in use
    (:class:`drivers.run_record.CalibrationRef`)."""

    @property
    def box(self) -> BoxIdentity | None: ...

    @property
    def check_box(self) -> bool: ...

    @property
    def source(self) -> str: ...


def identify_box(
    links: Sequence[DriveLink],
    parallel: Callable[[str, Callable[[DriveLink], DriveIdentity], float], list[DriveIdentity]],
    timeout_s: float,
    calibration: CalibratedBox | None,
    events: EventLog,
) -> BoxIdentity:
    """The box of ``links`` (every drive's identity read at once: ``parallel(what, fn,
    timeout_s)``, the session's), refused (:class:`BoxIdentityError`, logged in
    ``events``) unless the ``calibration`` in use was made on it (when it asks to be
    checked)."""
    ids = parallel("identity", read_identity, timeout_s)
    box = BoxIdentity.of({k.motor: v for k, v in zip(links, ids, strict=True)})
    if calibration is not None and calibration.check_box:
        try:
            check_box(calibration.box, box, calibration.source)
        except BoxIdentityError as exc:
            events.add("error", str(exc))
            raise
    return box
