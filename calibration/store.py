"""The calibration store: one JSON file per version, written atomically, checked on load.

A :class:`CalibrationStore` is a folder::

    calibrations/
        v0001.json      one calibration per version, never changed once written
        v0002.json
        active          the version in use: one line, its file name ("v0002.json")

:meth:`CalibrationStore.save` writes the next version and makes it active;
:meth:`~CalibrationStore.use` points ``active`` at an older one; the previous versions
are kept.  Every file is written atomically: a temporary file in the same folder
(``.v0003.json.<random>.tmp``), written, flushed and fsynced, then put in place and
the folder fsynced, so a crash (SIGKILL, power loss) at any moment leaves either the
old state or the new one.  A version file is put in place with ``os.link`` (a rename
that never replaces an existing file, so two writers cannot take the same number),
``active`` with ``os.replace``.  A ``.tmp`` file left by a killed writer is never
taken for a version; :meth:`~CalibrationStore.save` removes those older than an hour.
(``hrm_ctrl.files.write_atomic`` fsyncs the file but not the folder, and replaces an
existing file, hence the writer of its own here.)

The file format ``hrm-calibration/3`` (JSON, UTF-8, at most :data:`MAX_FILE_BYTES`)::

    {
      "format": "hrm-calibration/3",
      "version": 3,                                 # the number in the file's name
      "created_utc": "2026-12-01T21:24:33.123456+00:00",
      "routine": "kinematic",       # zero | kinematic | stiffness | manual | physics
      "robot_sha256": "<64 hex digits>",            # the robot description it belongs to
      "links_mm": [12 numbers > 0],                 # link lengths, joint 1..12
      "alpha_offset_rad": [12 numbers],             # joint zero offsets: true angle =
      "theta_offset_rad": [12 numbers],             #   commanded angle + offset
      "motor_zero_counts": {"j01r1": -1234, ...},   # per motor id: an integer (32-bit)
      "rope_EA_N": {"j01r1": 30000.0, ...},         # per rope id: axial rigidity > 0 (N)
      "residuals": {"rms_after_mm": 0.05, ...},     # the routine's figures (numbers)
      "box": {"simulated": false,                   # the box it was made on, or null:
              "drives": {"j01r1": {"vendor_id": 154, "product_code": 1026,
                                   "revision": 65536, "serial": 305419896}, ...}},
      "physics": {"link_mass_kg": [12 numbers > 0],     # or null: the description's
                  "payload_kg": 0.02,                   #   [physics] values
                  "mu_kinetic": [12 numbers >= 0]},
      "sha256": "<64 hex digits>"
    }

``box`` names the box the calibration was made on: each drive's identity object (CiA 301
0x1018, read at the bring-up; :mod:`drivers.identity`) per motor id, and whether the box
was simulated; ``null`` when it is not known.  ``physics`` holds what the physics
calibration measured (``calibration.physics``: link masses, the payload it was given, the
joints' kinetic friction), ``null`` when none was made: the robot description's
``[physics]`` values apply.  A file of the previous format ``hrm-calibration/2`` (the
same members but ``physics``) is read with no physics calibration, one of
``hrm-calibration/1`` (neither ``physics`` nor ``box``) with its box unknown too; every
file is written in the present format.

``sha256`` is the SHA-256 (lower-case hex) of the UTF-8 bytes of the canonical form of
every other member: ``json.dumps(doc, sort_keys=True, separators=(",", ":"),
ensure_ascii=True)``, numbers as Python writes them (the shortest text that reads back
to the same float, so every float round-trips bit for bit).  A reader parses the file,
recomputes it and refuses a mismatch: a hand-edited or damaged file is detected, and a
truncated one is not JSON.  Ids are 1 to 32 of ``A-Z a-z 0-9 _ . -``; there are at most
:data:`MAX_MOTORS` motors, :data:`MAX_ROPES` ropes and :data:`MAX_RESIDUALS` residuals.
No value may be NaN or infinite.

Every refusal is one :class:`~hrm_ctrl.errors.CalibrationFileError` line naming the file
and the reason.

**A store others can write is not ours.**  As ssh refuses keys others can write, the store
refuses to read or write a folder that is writable by everyone or owned by another user,
naming its owner and mode (:meth:`CalibrationStore.check_owned`).  **Check before you
move.**  :meth:`CalibrationStore.check_can_save` is what a routine that drives the arm
calls before its first move: the folder ours and writable (a file made and removed in it)
and a version number left, so its result cannot be lost for want of a place to keep it.

>>> import tempfile
>>> store = CalibrationStore(tempfile.mkdtemp())
>>> cal = Calibration.nominal(
...     links_mm=[60.0] * 12, motor_ids=["m1", "m2"], rope_EA_N={"m1": 3e4, "m2": 3e4},
...     robot_sha256="0" * 64)
>>> store.save(cal), store.save(cal), store.active()
(1, 2, 2)
>>> store.use(1); store.active()
1
>>> store.load_for("0" * 64) == cal
True
>>> store.load_for("1" * 64)  # doctest: +ELLIPSIS
Traceback (most recent call last):
hrm_ctrl.errors.CalibrationFileError: .../v0001.json: belongs to robot description 0000...
"""

from __future__ import annotations

import contextlib
import enum
import hashlib
import json
import math
import os
import pwd
import re
import stat
import tempfile
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from drivers.identity import BoxIdentity
from hrm_ctrl.errors import CalibrationFileError
from hrm_ctrl.files import parse_json, read_text_file
from hrm_ctrl.ropes.motor_map import POSITION_COUNTS_MAX

FORMAT = "hrm-calibration/3"
FORMAT_2 = "hrm-calibration/2"  # read: no ``physics`` member (the description's values)
FORMAT_1 = "hrm-calibration/1"  # read: no ``box`` member either (box unknown)
N_JOINTS = 12
MAX_FILE_BYTES = 256 * 1024  # 128 motors and ropes take about 12 kB
MAX_MOTORS = 128  # the robot has 2..8 ropes per joint: 96 at most
MAX_ROPES = 128
MAX_RESIDUALS = 32
MAX_VERSION = 999_999
ACTIVE = "active"
STALE_TMP_S = 3600.0  # a temporary file this old is a leftover of a killed writer

_ID = re.compile(r"[A-Za-z0-9_.-]{1,32}")
_HEX64 = re.compile(r"[0-9a-f]{64}")
_VERSION_FILE = re.compile(r"v(\d{4,6})\.json")
_TMP_FILE = re.compile(r"\.(v\d{4,6}\.json|active)\.[^/]+\.tmp")  # what _write_durable makes
_KEYS = (
    "format",
    "version",
    "created_utc",
    "routine",
    "robot_sha256",
    "links_mm",
    "alpha_offset_rad",
    "theta_offset_rad",
    "motor_zero_counts",
    "rope_EA_N",
    "residuals",
    "box",
    "physics",
)
_KEYS_OF = {FORMAT: _KEYS, FORMAT_2: _KEYS[:-1], FORMAT_1: _KEYS[:-2]}


def _user(uid: int) -> str:
    """``name (uid N)``, or ``uid N`` when the name is unknown."""
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


class Routine(enum.Enum):
    """The routine that produced a calibration."""

    ZERO = "zero"
    KINEMATIC = "kinematic"
    STIFFNESS = "stiffness"
    MANUAL = "manual"
    PHYSICS = "physics"


def _fail(name: str, why: str) -> CalibrationFileError:
    return CalibrationFileError(f"{name}: {why}")


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _float_array(value: Any, what: str, name: str, *, positive: bool = False) -> np.ndarray:
    if isinstance(value, np.ndarray):
        items = value.tolist() if value.ndim == 1 else None
    elif isinstance(value, list | tuple):
        items = list(value)
    else:
        items = None
    if items is None:
        raise _fail(name, f"{what} must be a list of {N_JOINTS} numbers")
    if len(items) != N_JOINTS:
        raise _fail(name, f"{what} has {len(items)} values, not {N_JOINTS}")
    for i, v in enumerate(items):
        if not _is_number(v):
            raise _fail(name, f"{what}[{i}] is not a number ({v!r})")
        if not math.isfinite(v):
            raise _fail(name, f"{what}[{i}] is {v} (NaN and infinity are refused)")
        if positive and not v > 0:
            raise _fail(name, f"{what}[{i}] is {v}, not > 0")
    out = np.array([float(v) for v in items], dtype=np.float64)
    out.flags.writeable = False
    return out


def _id_table(
    value: Any, what: str, name: str, limit: int, check: Any
) -> MappingProxyType[str, Any]:
    if not isinstance(value, Mapping):
        raise _fail(name, f"{what} must be a table of id -> value")
    if not value:
        raise _fail(name, f"{what} is empty")
    if len(value) > limit:
        raise _fail(name, f"{what} has {len(value)} entries, more than the {limit} allowed")
    out: dict[str, Any] = {}
    for key, v in value.items():
        if not isinstance(key, str) or not _ID.fullmatch(key):
            raise _fail(name, f"{what}: id {key!r} is not 1-32 of A-Z a-z 0-9 _ . -")
        out[key] = check(v, f"{what}.{key}", name)
    return MappingProxyType(out)


def _count(v: Any, what: str, name: str) -> int:
    if isinstance(v, np.integer):
        v = int(v)
    if not isinstance(v, int) or isinstance(v, bool):
        raise _fail(name, f"{what} is not an integer count ({v!r})")
    if not -POSITION_COUNTS_MAX - 1 <= v <= POSITION_COUNTS_MAX:
        raise _fail(name, f"{what} = {v} does not fit a drive's 32-bit position")
    return v


def _finite(v: Any, what: str, name: str, *, positive: bool = False) -> float:
    if isinstance(v, np.floating | np.integer):
        v = v.item()
    if not _is_number(v):
        raise _fail(name, f"{what} is not a number ({v!r})")
    if not math.isfinite(v):
        raise _fail(name, f"{what} is {v} (NaN and infinity are refused)")
    if positive and not v > 0:
        raise _fail(name, f"{what} is {v}, not > 0")
    return float(v)


def _positive(v: Any, what: str, name: str) -> float:
    return _finite(v, what, name, positive=True)


@dataclass(frozen=True, eq=False)
class PhysicsConstants:
    """The arm's physical constants a physics calibration measured
    (``calibration.physics``): each link's mass (12,) kg, > 0, the tip payload kg, >= 0
    (the one the routine was given: statics cannot tell it from the links' masses), and
    each joint's kinetic friction coefficient (12,), >= 0.  Arrays read-only float64."""

    link_mass_kg: np.ndarray
    payload_kg: float
    mu_kinetic: np.ndarray

    def __post_init__(self) -> None:
        self._check("physics")

    def _check(self, name: str) -> None:
        put = object.__setattr__
        what = "physics.link_mass_kg"
        put(self, "link_mass_kg", _float_array(self.link_mass_kg, what, name, positive=True))
        mu = _float_array(self.mu_kinetic, "physics.mu_kinetic", name)
        low = np.flatnonzero(mu < 0.0)
        if low.size:
            j = int(low[0])
            raise _fail(name, f"physics.mu_kinetic[{j}] is {mu[j]}, not >= 0")
        put(self, "mu_kinetic", mu)
        payload = _finite(self.payload_kg, "physics.payload_kg", name)
        if payload < 0.0:
            raise _fail(name, f"physics.payload_kg is {payload}, not >= 0")
        put(self, "payload_kg", payload)

    @classmethod
    def from_dict(cls, doc: Any, name: str) -> PhysicsConstants:
        """The ``physics`` member of a file (``name`` in messages)."""
        keys = ("link_mass_kg", "payload_kg", "mu_kinetic")
        if not isinstance(doc, Mapping):
            raise _fail(name, "physics must be a table (link_mass_kg, payload_kg, mu_kinetic)")
        missing = [k for k in keys if k not in doc]
        extra = sorted(set(doc) - set(keys))
        if missing or extra:
            raise _fail(name, f"physics: members missing {missing}, unknown {extra}")
        out = object.__new__(cls)
        for k in keys:
            object.__setattr__(out, k, doc[k])
        out._check(name)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "link_mass_kg": self.link_mass_kg.tolist(),
            "payload_kg": self.payload_kg,
            "mu_kinetic": self.mu_kinetic.tolist(),
        }


@dataclass(frozen=True, eq=False)
class Calibration:
    """One calibration: what the routines estimate, for one robot description.

    Arrays are read-only float64 copies, tables read-only mappings (in the given order);
    every value is checked on construction (:class:`CalibrationFileError`).  Two
    calibrations are equal when their file contents are (floats compared bit for bit).
    """

    links_mm: np.ndarray  # (12,) link lengths, > 0
    alpha_offset_rad: np.ndarray  # (12,) joint zero offsets (true = commanded + offset)
    theta_offset_rad: np.ndarray  # (12,)
    motor_zero_counts: Mapping[str, int]  # motor id -> encoder count at pretension
    rope_EA_N: Mapping[str, float]  # rope id -> axial rigidity EA (N), > 0
    created_utc: datetime  # timezone-aware, UTC
    routine: Routine
    robot_sha256: str  # 64 lower-case hex digits: the robot description's
    residuals: Mapping[str, float] = field(default_factory=dict)
    box: BoxIdentity | None = None  # the box it was made on (None: unknown)
    physics: PhysicsConstants | None = None  # masses, friction (None: the description's)

    def __post_init__(self) -> None:
        self._check("calibration")

    def _check(self, name: str) -> None:
        put = object.__setattr__
        put(self, "links_mm", _float_array(self.links_mm, "links_mm", name, positive=True))
        for key in ("alpha_offset_rad", "theta_offset_rad"):
            put(self, key, _float_array(getattr(self, key), key, name))
        put(
            self,
            "motor_zero_counts",
            _id_table(self.motor_zero_counts, "motor_zero_counts", name, MAX_MOTORS, _count),
        )
        put(self, "rope_EA_N", _id_table(self.rope_EA_N, "rope_EA_N", name, MAX_ROPES, _positive))
        res = self.residuals
        if not isinstance(res, Mapping) or len(res) > MAX_RESIDUALS:
            raise _fail(name, f"residuals must be a table of at most {MAX_RESIDUALS} numbers")
        checked: dict[str, float] = {}
        for key, v in res.items():
            if not isinstance(key, str) or not 1 <= len(key) <= 64:
                raise _fail(name, f"residuals: name {key!r} is not a string of 1-64 characters")
            checked[key] = _finite(v, f"residuals.{key}", name)
        put(self, "residuals", MappingProxyType(checked))
        if not isinstance(self.routine, Routine):
            try:
                put(self, "routine", Routine(self.routine))
            except ValueError:
                kinds = ", ".join(r.value for r in Routine)
                raise _fail(name, f"routine {self.routine!r} is not one of {kinds}") from None
        t = self.created_utc
        if not isinstance(t, datetime) or t.utcoffset() is None or t.utcoffset().total_seconds():
            raise _fail(name, f"created_utc must be a UTC date and time, not {t!r}")
        if not isinstance(self.robot_sha256, str) or not _HEX64.fullmatch(self.robot_sha256):
            raise _fail(name, "robot_sha256 is not 64 lower-case hex digits")
        if self.box is not None and not isinstance(self.box, BoxIdentity):
            put(self, "box", BoxIdentity.from_dict(self.box, lambda why: _fail(name, why)))
        if self.physics is not None and not isinstance(self.physics, PhysicsConstants):
            put(self, "physics", PhysicsConstants.from_dict(self.physics, name))

    @classmethod
    def nominal(
        cls,
        *,
        links_mm: Iterable[float],
        motor_ids: Iterable[str],
        rope_EA_N: Mapping[str, float],
        robot_sha256: str,
        routine: Routine = Routine.MANUAL,
    ) -> Calibration:
        """The description's own values: zero offsets and zero counts, created now."""
        return cls(
            links_mm=np.asarray(list(links_mm), dtype=float),
            alpha_offset_rad=np.zeros(N_JOINTS),
            theta_offset_rad=np.zeros(N_JOINTS),
            motor_zero_counts=dict.fromkeys(motor_ids, 0),
            rope_EA_N=rope_EA_N,
            created_utc=datetime.now(UTC),
            routine=routine,
            robot_sha256=robot_sha256,
        )

    @property
    def motor_ids(self) -> tuple[str, ...]:
        return tuple(self.motor_zero_counts)

    @property
    def rope_ids(self) -> tuple[str, ...]:
        return tuple(self.rope_EA_N)

    def content(self) -> dict[str, Any]:
        """The file's members but ``version`` and ``sha256`` (plain JSON types)."""
        return {
            "format": FORMAT,
            "created_utc": self.created_utc.isoformat(),
            "routine": self.routine.value,
            "robot_sha256": self.robot_sha256,
            "links_mm": self.links_mm.tolist(),
            "alpha_offset_rad": self.alpha_offset_rad.tolist(),
            "theta_offset_rad": self.theta_offset_rad.tolist(),
            "motor_zero_counts": dict(self.motor_zero_counts),
            "rope_EA_N": dict(self.rope_EA_N),
            "residuals": dict(self.residuals),
            "box": None if self.box is None else self.box.to_dict(),
            "physics": None if self.physics is None else self.physics.to_dict(),
        }

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return canonical(self.content()) == canonical(other.content())

    __hash__ = None  # type: ignore[assignment]


def canonical(doc: Mapping[str, Any]) -> bytes:
    """The canonical bytes the checksum covers (NaN is written so that it can be refused
    after the checksum, not confused with a damaged file)."""
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return text.encode("ascii")


def checksum(doc: Mapping[str, Any]) -> str:
    """``sha256`` of a document: over every member but ``sha256`` itself."""
    return hashlib.sha256(canonical({k: v for k, v in doc.items() if k != "sha256"})).hexdigest()


def to_json(cal: Calibration, version: int) -> str:
    """The text of version ``version``'s file."""
    content = cal.content()
    doc: dict[str, Any] = {k: version if k == "version" else content.get(k) for k in _KEYS}
    doc["sha256"] = checksum(doc)
    return json.dumps(doc, indent=2, ensure_ascii=True, allow_nan=False) + "\n"


def from_json(text: str, name: str, version: int | None = None) -> Calibration:
    """The calibration in file text ``text`` (``name`` in messages); ``version``, when
    given, must be the one the file records."""
    try:
        doc = parse_json(text, CalibrationFileError, name, "calibration file")
    except CalibrationFileError as exc:
        raise CalibrationFileError(f"{exc} - truncated or damaged") from None
    if not isinstance(doc, dict):
        raise _fail(name, "not a calibration file (not a JSON object)")
    if doc.get("format") not in _KEYS_OF:
        raise _fail(name, f"format is {doc.get('format')!r}, not {FORMAT!r}")
    recorded = doc.get("sha256")
    if not isinstance(recorded, str):
        raise _fail(name, "has no sha256 checksum")
    actual = checksum(doc)
    if actual != recorded:
        raise _fail(
            name,
            f"checksum mismatch (edited by hand or damaged): content {actual[:12]}…, "
            f"recorded {recorded[:12]}…",
        )
    keys = _KEYS_OF[doc["format"]]  # /2: no physics, /1: no box either
    missing = [k for k in keys if k not in doc]
    extra = sorted(doc.keys() - {*keys, "sha256"})
    if missing or extra:
        raise _fail(name, f"members missing {missing}, unknown {extra}")
    v = doc["version"]
    if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= MAX_VERSION:
        raise _fail(name, f"version {v!r} is not an integer 1..{MAX_VERSION}")
    if version is not None and v != version:
        raise _fail(name, f"records version {v}, not {version} (a copied or renamed file)")
    try:
        created = datetime.fromisoformat(doc["created_utc"])
    except (TypeError, ValueError):
        raise _fail(name, f"created_utc {doc['created_utc']!r} is not an ISO 8601 time") from None
    cal = object.__new__(Calibration)  # checked below, naming the file
    for key in _KEYS[3:]:
        object.__setattr__(cal, key, doc.get(key))
    object.__setattr__(cal, "created_utc", created)
    cal._check(name)
    return cal


def _fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_durable(path: Path, text: str, *, replace: bool) -> None:
    """Write ``text`` to ``path`` atomically and durably (see the module docstring).
    With ``replace`` false an existing ``path`` raises ``FileExistsError``."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(text.encode("utf-8"))
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        if replace:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)  # never replaces: FileExistsError
            os.unlink(tmp)
        _fsync_folder(path.parent)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@dataclass(frozen=True)
class Version:
    """One line of :meth:`CalibrationStore.history`."""

    version: int
    path: Path
    active: bool
    calibration: Calibration | None  # None when the file is refused
    problem: str | None  # the refusal, one line


class CalibrationStore:
    """The versioned calibrations in ``folder`` (created on the first save)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def path_of(self, version: int) -> Path:
        if not isinstance(version, int) or isinstance(version, bool):
            raise CalibrationFileError(f"{self.folder}: version {version!r} is not an integer")
        if not 1 <= version <= MAX_VERSION:
            raise CalibrationFileError(f"{self.folder}: version {version} is not 1..{MAX_VERSION}")
        return self.folder / f"v{version:04d}.json"

    def check_owned(self) -> None:
        """Refuse (one line naming owner and mode) a store folder writable by everyone or
        owned by another user; a folder not made yet passes (the store makes it, ours)."""
        try:
            st = os.stat(self.folder)
        except FileNotFoundError:
            return
        except OSError as exc:
            raise CalibrationFileError(f"{self.folder}: cannot read the store ({exc})") from None
        mode = f"mode {stat.filemode(st.st_mode)} ({st.st_mode & 0o7777:04o})"
        me = os.getuid()
        if st.st_uid != me:
            raise CalibrationFileError(
                f"{self.folder}: the calibration store is owned by {_user(st.st_uid)}, not "
                f"by {_user(me)} ({mode}): a store others can write is not used"
            )
        if st.st_mode & stat.S_IWOTH:
            raise CalibrationFileError(
                f"{self.folder}: the calibration store is writable by everyone (owner "
                f"{_user(st.st_uid)}, {mode}): a store others can write is not used "
                f"(chmod o-w {self.folder})"
            )

    def check_can_save(self) -> None:
        """Everything :meth:`save` needs, checked before a routine moves the arm: the
        folder (made if missing) ours, writable (a temporary file written and removed in
        it) with no folder in the active pointer's place, and a version number left."""
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CalibrationFileError(f"{self.folder}: cannot create the store ({exc})") from None
        self.check_owned()
        self._refuse_folder_pointer()
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{ACTIVE}.", suffix=".tmp", dir=self.folder)
            os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            raise CalibrationFileError(
                f"{self.folder}: the calibration store is not writable ({exc.strerror or exc}):"
                " a result could not be kept"
            ) from None
        last = max(self.versions(), default=0)
        if last >= MAX_VERSION:
            raise CalibrationFileError(
                f"{self.folder}: no version number left (v{last:04d} is the last of "
                f"{MAX_VERSION}): a result could not be kept"
            )

    def versions(self) -> list[int]:
        """The versions in the folder, oldest first (temporary files are not versions)."""
        self.check_owned()
        try:
            names = os.listdir(self.folder)
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise CalibrationFileError(f"{self.folder}: cannot list the store ({exc})") from None
        found = (_VERSION_FILE.fullmatch(n) for n in names)
        return sorted(
            v
            for m in found
            if m and 1 <= (v := int(m.group(1))) <= MAX_VERSION and m.group(0) == f"v{v:04d}.json"
        )

    def save(self, cal: Calibration, *, activate: bool = True) -> int:
        """Write ``cal`` as the next version (and make it active); return its number."""
        if not isinstance(cal, Calibration):
            raise TypeError(f"save() takes a Calibration, not {type(cal).__name__}")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CalibrationFileError(f"{self.folder}: cannot create the store ({exc})") from None
        self.check_owned()
        if activate:  # refused before the version is written: nothing left behind
            self._refuse_folder_pointer()
        self._remove_stale_tmp()
        version = max(self.versions(), default=0) + 1
        while True:
            path = self.path_of(version)
            try:
                _write_durable(path, to_json(cal, version), replace=False)
                break
            except FileExistsError:  # another writer took this number
                version += 1
            except OSError as exc:
                raise CalibrationFileError(f"{path}: cannot write ({exc})") from None
        if activate:
            self._point_at(version)
        return version

    def load(self, version: int) -> Calibration:
        """Version ``version``, checked (format, checksum, values); any robot."""
        path = self.path_of(version)
        self.check_owned()
        text = read_text_file(
            path,
            CalibrationFileError,
            "calibration file",
            max_bytes=MAX_FILE_BYTES,
            follow_symlinks=False,  # never written by the store: not a version of it
        )
        return from_json(text, str(path), version)

    def history(self) -> list[Version]:
        """Every version, oldest first, each checked; a refused file has its ``problem``.
        A damaged active pointer marks no version active (:meth:`active_problem` says
        what is wrong with it): the versions are still listed, so one can be chosen."""
        try:
            active = self._active_or_none()
        except CalibrationFileError:
            active = None
        out = []
        for v in self.versions():
            try:
                cal, problem = self.load(v), None
            except CalibrationFileError as exc:
                cal, problem = None, str(exc)
            out.append(Version(v, self.path_of(v), v == active, cal, problem))
        return out

    def use(self, version: int, robot_sha256: str | None = None) -> None:
        """Make ``version`` active; it must load (and belong to ``robot_sha256`` if given)."""
        cal = self.load(version)
        if robot_sha256 is not None:
            self._check_robot(cal, version, robot_sha256)
        self._point_at(version)

    def active_problem(self) -> str | None:
        """What is wrong with the active pointer (one line), or None when it is sound or
        absent."""
        try:
            self._active_or_none()
        except CalibrationFileError as exc:
            return str(exc)
        return None

    def active(self) -> int | None:
        """The active version, or None when no version was ever made active."""
        return self._active_or_none()

    def load_active(self) -> Calibration:
        """The active calibration, checked; any robot."""
        version = self._active_or_none()
        if version is None:
            raise CalibrationFileError(f"{self.folder / ACTIVE}: no active calibration")
        return self.load(version)

    def load_for(self, robot_sha256: str) -> Calibration:
        """The active calibration, refused unless it belongs to ``robot_sha256``."""
        version = self._active_or_none()
        if version is None:
            raise CalibrationFileError(f"{self.folder / ACTIVE}: no active calibration")
        cal = self.load(version)
        self._check_robot(cal, version, robot_sha256)
        return cal

    def _check_robot(self, cal: Calibration, version: int, robot_sha256: str) -> None:
        if cal.robot_sha256 != robot_sha256:
            raise CalibrationFileError(
                f"{self.path_of(version)}: belongs to robot description "
                f"{cal.robot_sha256[:12]}…, not to this one ({str(robot_sha256)[:12]}…)"
            )

    def _active_or_none(self) -> int | None:
        if os.path.exists(self.folder) and not os.path.isdir(self.folder):  # not "none yet"
            raise CalibrationFileError(f"{self.folder}: the calibration store is not a folder")
        self.check_owned()
        path = self.folder / ACTIVE
        try:
            text = read_text_file(
                path, CalibrationFileError, "active pointer", max_bytes=64, follow_symlinks=False
            )
        except CalibrationFileError:
            if not os.path.lexists(path):  # (False, not OSError, on a too-long name)
                return None
            raise
        m = _VERSION_FILE.fullmatch(text.strip())
        if m is None:
            raise _fail(str(path), f"does not name a version file ({text.strip()[:40]!r})")
        version = int(m.group(1))
        if not 1 <= version <= MAX_VERSION:
            raise _fail(str(path), f"names version {version}, not 1..{MAX_VERSION}")
        if not os.path.lexists(self.path_of(version)):  # a link there: load() says so
            raise _fail(str(path), f"names {m.group(0)}, which is not in the store")
        return version

    def _refuse_folder_pointer(self) -> None:
        """A folder in the active pointer's place (``os.replace`` cannot put a file over
        it) is refused with one line; it is the user's to remove, not the store's."""
        path = self.folder / ACTIVE
        if os.path.isdir(path) and not os.path.islink(path):
            raise CalibrationFileError(
                f"{path}: the active pointer is a folder; remove it, then try again"
            )

    def _point_at(self, version: int) -> None:
        path = self.folder / ACTIVE
        self._refuse_folder_pointer()
        try:
            _write_durable(path, self.path_of(version).name + "\n", replace=True)
        except OSError as exc:
            raise CalibrationFileError(f"{path}: cannot write ({exc})") from None

    def _remove_stale_tmp(self) -> None:
        now = time.time()
        with os.scandir(self.folder) as entries:
            for e in entries:
                if _TMP_FILE.fullmatch(e.name):
                    with contextlib.suppress(OSError):
                        if now - e.stat().st_mtime > STALE_TMP_S:
                            os.unlink(e.path)
