"""CANopen CiA 306 device files (EDS and DCF): the one reader, typed and bounded.

The host's canopen nodes and the simulated drives take their object dictionaries from it
(:func:`canopen_dictionary`), the box check (:mod:`drivers.device_check`) its typed entries.

A device file is an INI text: ``[SECTION]`` lines, ``KEY=VALUE`` lines, ``;`` comments.
Section names and keys are case-insensitive.  An object is a section ``[IIII]`` (index,
4 hex digits) and, for an ARRAY or RECORD, one ``[IIIIsubS]`` section per sub-index (hex).
What this reader takes as the standard allows, and what real files do:

- integers in decimal, hexadecimal (``0x``) or octal (a leading ``0``), with a sign;
- ``$NODEID`` arithmetic (``$NODEID+0x200``, ``0x200+$NODEID``): the value is relative
  to the node id, resolved by :meth:`DeviceFile.value` for a given node;
- a signed type written as its unsigned bit pattern in hex or octal (INTEGER8 ``0xFD`` is
  -3, as the EPOS2's 0x60C2sub2 writes it; python-canopen reads 253 there);
- a DCF's ``ParameterValue`` over the ``DefaultValue`` (:attr:`ODEntry.value`);
- manufacturer objects (0x2000..0x5FFF), ``SupportedObjects`` in hex, tool sections
  (``[ToolInfos]``) and any other section that is not an object: kept or ignored.

What it refuses, with one line naming the file, the section and the key
(:class:`DeviceFileError`): a file past :data:`MAX_FILE_BYTES`, not UTF-8 or with a NUL
byte, a line that is neither a section nor ``KEY=VALUE``, a duplicate section or key,
more than :data:`MAX_OBJECTS` objects, an unknown data type, object type or access type, a
value outside its type or outside the entry's ``LowLimit``..``HighLimit``, a
``SubNumber`` that does not count the sub-index sections (in the manufacturer area it is
noted instead, :attr:`DeviceFile.quirks`: the PRBT's DCF has one), a sub-index section
without its object, an object list naming an object the file does not describe, and
``CompactSubObj`` (not read: no file hrm has met uses it).

>>> text = '''
... [1400]
... ParameterName=RPDO1 communication
... ObjectType=0x9
... SubNumber=2
... [1400sub0]
... ParameterName=Highest sub-index
... DataType=0x0005
... AccessType=const
... DefaultValue=1
... [1400sub1]
... ParameterName=COB-ID
... DataType=0x0007
... AccessType=rw
... DefaultValue=$NODEID+0x200
... [60C2]
... ParameterName=Interpolation time index
... ObjectType=0x7
... DataType=0x0002
... AccessType=rw
... DefaultValue=0xFD
... '''
>>> f = parse_device_file(text, "x.eds")
>>> hex(f.value(0x1400, 1, node_id=5)), f.value(0x60C2), f.entry(0x60C2).access.writable
('0x205', -3, True)
>>> bad = "[6502]\\nDataType=0x7\\nAccessType=ro\\nDefaultValue=0x1FFFFFFFF"
>>> parse_device_file(bad, "y")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
drivers.protocol.cia306.DeviceFileError: y: [6502] DefaultValue: 0x1FFFFFFFF outside UNSIGNED32 ...
"""

from __future__ import annotations

import enum
import hashlib
import math
import re
import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.errors import DriverError
from hrm_ctrl.files import read_text_file

if TYPE_CHECKING:
    import canopen

MAX_FILE_BYTES = 4 * 2**20
"""Largest device file read (the largest real one hrm has met, a Nanotec C5-E, is 174 kB)."""
MAX_LINE_CHARS = 4096
"""Longest line (a string default included)."""
MAX_SECTIONS = 32768
"""Most sections in one file (objects and sub-indices together; a C5-E has 1306)."""
MAX_OBJECTS = 4096
"""Most objects (indices) in one file."""
MAX_NUMBER_CHARS = 64
"""Longest numeric literal (a 64-bit value in octal has 23 digits)."""

MANUFACTURER_INDICES = (0x2000, 0x5FFF)
"""The manufacturer-specific area: hrm uses none of it, so a miscounted ``SubNumber`` there
is taken as described and noted (:attr:`DeviceFile.quirks`), not refused."""

Value = int | float | str


class DeviceFileError(DriverError):
    """A device file that cannot be read: one line naming the file, section and key."""


class DataType(enum.IntEnum):
    """CiA 301 basic data types (the ``DataType`` codes a device file uses)."""

    BOOLEAN = 0x01
    INTEGER8 = 0x02
    INTEGER16 = 0x03
    INTEGER32 = 0x04
    UNSIGNED8 = 0x05
    UNSIGNED16 = 0x06
    UNSIGNED32 = 0x07
    REAL32 = 0x08
    VISIBLE_STRING = 0x09
    OCTET_STRING = 0x0A
    UNICODE_STRING = 0x0B
    TIME_OF_DAY = 0x0C
    TIME_DIFFERENCE = 0x0D
    DOMAIN = 0x0F
    INTEGER24 = 0x10
    REAL64 = 0x11
    INTEGER40 = 0x12
    INTEGER48 = 0x13
    INTEGER56 = 0x14
    INTEGER64 = 0x15
    UNSIGNED24 = 0x16
    UNSIGNED40 = 0x18
    UNSIGNED48 = 0x19
    UNSIGNED56 = 0x1A
    UNSIGNED64 = 0x1B

    @property
    def bits(self) -> int:
        """Width of an integer type (0 for the others).

        >>> DataType.INTEGER8.bits, DataType.UNSIGNED24.bits, DataType.REAL32.bits
        (8, 24, 0)
        """
        return _INT_BITS.get(self, 0)

    @property
    def signed(self) -> bool:
        return self.name.startswith("INTEGER")

    @property
    def is_integer(self) -> bool:
        return self.bits > 0

    def int_range(self) -> tuple[int, int]:
        """(lowest, highest) value of an integer type.

        >>> DataType.INTEGER8.int_range(), DataType.UNSIGNED16.int_range()
        ((-128, 127), (0, 65535))
        """
        n = self.bits
        return (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if self.signed else (0, 2**n - 1)


_INT_BITS = {
    DataType.BOOLEAN: 1, DataType.INTEGER8: 8, DataType.INTEGER16: 16, DataType.INTEGER24: 24,
    DataType.INTEGER32: 32, DataType.INTEGER40: 40, DataType.INTEGER48: 48,
    DataType.INTEGER56: 56, DataType.INTEGER64: 64, DataType.UNSIGNED8: 8,
    DataType.UNSIGNED16: 16, DataType.UNSIGNED24: 24, DataType.UNSIGNED32: 32,
    DataType.UNSIGNED40: 40, DataType.UNSIGNED48: 48, DataType.UNSIGNED56: 56,
    DataType.UNSIGNED64: 64, DataType.TIME_OF_DAY: 48, DataType.TIME_DIFFERENCE: 48,
}  # fmt: skip
_REALS = frozenset({DataType.REAL32, DataType.REAL64})


class ObjectType(enum.IntEnum):
    """CiA 301 object codes (``ObjectType``; absent: VAR)."""

    NULL = 0x0
    DOMAIN = 0x2
    DEFTYPE = 0x5
    DEFSTRUCT = 0x6
    VAR = 0x7
    ARRAY = 0x8
    RECORD = 0x9


class Access(enum.StrEnum):
    """CiA 306 access types (``AccessType``, case-insensitive)."""

    RO = "ro"
    WO = "wo"
    RW = "rw"
    RWR = "rwr"  # read-write, TPDO-mappable
    RWW = "rww"  # read-write, RPDO-mappable
    CONST = "const"

    @property
    def writable(self) -> bool:
        return self in (Access.WO, Access.RW, Access.RWR, Access.RWW)

    @property
    def readable(self) -> bool:
        return self is not Access.WO


@dataclass(frozen=True)
class ODEntry:
    """One (index, sub-index) of a device file: its type, access, PDO mapping, limits and
    values (``default``: ``DefaultValue``; ``parameter``: a DCF's ``ParameterValue``;
    ``node_relative``: the value adds the node id, ``$NODEID``)."""

    index: int
    sub: int
    name: str
    data_type: DataType
    access: Access
    pdo_mappable: bool
    default: Value | None
    parameter: Value | None = None
    node_relative: bool = False
    low: int | float | None = None
    high: int | float | None = None

    @property
    def value(self) -> Value | None:
        """The DCF's ``ParameterValue`` if it gives one, else the ``DefaultValue``
        (without the node id of a ``$NODEID`` value)."""
        return self.parameter if self.parameter is not None else self.default

    @property
    def section(self) -> str:
        """The section that describes it: ``1400sub1``, or ``6502`` for a VAR."""
        return f"{self.index:04X}" if self.sub == 0 and self.name == "" else self.label

    @property
    def label(self) -> str:
        return f"{self.index:04X}sub{self.sub}"


@dataclass(frozen=True)
class ODObject:
    """One object (index): its name, object type and entries by sub-index (a VAR: sub 0)."""

    index: int
    name: str
    object_type: ObjectType
    entries: Mapping[int, ODEntry]

    @property
    def section(self) -> str:
        return f"{self.index:04X}"


@dataclass(frozen=True)
class DeviceInfo:
    """What ``[DeviceInfo]`` says of the device (identity numbers, PDO counts)."""

    vendor_name: str = ""
    vendor_number: int | None = None
    product_name: str = ""
    product_number: int | None = None
    revision_number: int | None = None
    nr_of_rxpdo: int | None = None
    nr_of_txpdo: int | None = None
    granularity: int | None = None


@dataclass(frozen=True)
class DeviceFile:
    """A device file read: its ``source`` (the name in messages), whether it is a DCF,
    the node id a DCF is configured for, ``[DeviceInfo]``, every object by index."""

    source: str
    is_dcf: bool
    node_id: int | None
    device: DeviceInfo
    objects: Mapping[int, ODObject]
    quirks: tuple[str, ...] = ()  # what the reader took as written though CiA 306 says else

    @property
    def name(self) -> str:
        """The file's name without its folders (as refusals name it)."""
        return Path(self.source).name

    def entry(self, index: int, sub: int = 0) -> ODEntry | None:
        """The entry at (index, sub-index), or None when the file has none."""
        obj = self.objects.get(index)
        return None if obj is None else obj.entries.get(sub)

    def value(self, index: int, sub: int = 0, node_id: int | None = None) -> Value | None:
        """The entry's value (:attr:`ODEntry.value`) with a ``$NODEID`` resolved for
        ``node_id`` (default: the DCF's node id, else 0); None when absent or unset."""
        e = self.entry(index, sub)
        if e is None or e.value is None:
            return None
        if e.node_relative and isinstance(e.value, int):
            nid = node_id if node_id is not None else (self.node_id or 0)
            return e.value + nid
        return e.value


# ---------------------------------------------------------------- the INI text
_OBJECT_SECTION = re.compile(r"([0-9A-F]{4})(?:SUB([0-9A-F]{1,2}))?")
_NAME_SECTION = re.compile(r"[0-9A-F]{4}(?:NAME|VALUE|DENOTATION)")
_LIST_SECTIONS = ("MANDATORYOBJECTS", "OPTIONALOBJECTS", "MANUFACTUREROBJECTS")

Sections = dict[str, tuple[str, dict[str, tuple[str, str]]]]
"""Upper-case section name -> (name as written, upper-case key -> (key as written, value))."""


def _shown(text: str) -> str:
    return text if len(text) <= 40 else f"{text[:37]}..."


def _sections(text: str, source: str) -> Sections:
    """The file's sections and keys, each checked for shape and bounds."""
    if "\0" in text:
        line = text.count("\n", 0, text.index("\0")) + 1
        raise DeviceFileError(f"{source}: line {line}: NUL byte (binary content, not a text file)")
    out: Sections = {}
    current: dict[str, tuple[str, str]] | None = None
    section = ""
    for n, raw in enumerate(text.split("\n"), start=1):
        if len(raw) > MAX_LINE_CHARS:
            raise DeviceFileError(f"{source}: line {n}: longer than {MAX_LINE_CHARS} characters")
        line = raw.strip()
        if not line or line.startswith(";"):
            continue
        if line.startswith("["):
            if not line.endswith("]") or len(line) < 3:
                raise DeviceFileError(
                    f"{source}: line {n}: expected [SECTION], got {_shown(line)!r}"
                )
            section = line[1:-1].strip()
            key = section.upper()
            if key in out:
                raise DeviceFileError(f"{source}: [{section}]: section given twice (line {n})")
            if len(out) >= MAX_SECTIONS:
                raise DeviceFileError(f"{source}: line {n}: more than {MAX_SECTIONS} sections")
            current = {}
            out[key] = (section, current)
            continue
        name, eq, value = line.partition("=")
        name = name.strip()
        if not eq or not name:
            raise DeviceFileError(f"{source}: line {n}: expected KEY=VALUE, got {_shown(line)!r}")
        if current is None:
            raise DeviceFileError(f"{source}: line {n}: {name} before any [SECTION]")
        if name.upper() in current:
            raise DeviceFileError(f"{source}: [{section}] {name}: key given twice (line {n})")
        current[name.upper()] = (name, value.strip())
    return out


# ---------------------------------------------------------------- values
_NODEID = re.compile(r"\$NODEID", re.IGNORECASE)


def parse_int(text: str, where: str) -> int:
    """An integer as CiA 306 writes it: decimal, ``0x`` hexadecimal or ``0`` octal, signed.

    >>> parse_int("0x1F", "w"), parse_int("017", "w"), parse_int("-12", "w"), parse_int("0", "w")
    (31, 15, -12, 0)
    >>> parse_int("12a", "f: [1000] DefaultValue")
    Traceback (most recent call last):
    ...
    drivers.protocol.cia306.DeviceFileError: f: [1000] DefaultValue: '12a' is not an integer
    """
    s = text.strip()
    if len(s) > MAX_NUMBER_CHARS:
        raise DeviceFileError(f"{where}: {_shown(s)!r} is longer than a number may be")
    sign = -1 if s.startswith("-") else 1
    body = s[1:] if s[:1] in "+-" else s
    try:
        if body[:2].lower() == "0x":
            digits, base = body[2:], 16
        elif len(body) > 1 and body.startswith("0"):
            digits, base = body[1:], 8
        else:
            digits, base = body, 10
        if not digits or not digits.isascii() or not digits.isalnum():
            raise ValueError(body)
        return sign * int(digits, base)
    except ValueError:
        raise DeviceFileError(f"{where}: {_shown(s)!r} is not an integer") from None


def _is_pattern(text: str) -> bool:
    """Whether an integer literal is written as a bit pattern (hex or octal)."""
    body = text.strip().lstrip("+")
    return body[:2].lower() == "0x" or (len(body) > 1 and body.startswith("0"))


def _typed_int(text: str, dt: DataType, where: str) -> int:
    """An integer literal of type ``dt``: a signed type's hex/octal bit pattern is its two's
    complement value; anything outside the type's range is refused."""
    v = parse_int(text, where)
    lo, hi = dt.int_range()
    if dt.signed and _is_pattern(text) and hi < v < 2**dt.bits:
        v -= 2**dt.bits
    if not lo <= v <= hi:
        raise DeviceFileError(f"{where}: {_shown(text.strip())} outside {dt.name} ({lo}..{hi})")
    return v


def parse_value(text: str, dt: DataType, where: str) -> tuple[Value | None, bool]:
    """(value, relative to the node id) of a value of type ``dt``; an empty one is None.

    >>> parse_value("$NODEID+0x180", DataType.UNSIGNED32, "w")
    (384, True)
    >>> parse_value("0xFD", DataType.INTEGER8, "w"), parse_value("1.5", DataType.REAL32, "w")
    ((-3, False), (1.5, False))
    """
    s = text.strip()
    if not s:
        return None, False
    if dt in _REALS:
        try:
            v = float(s) if len(s) <= MAX_NUMBER_CHARS else math.nan
        except ValueError:
            v = math.nan
        if not math.isfinite(v):
            raise DeviceFileError(f"{where}: {_shown(s)!r} is not a finite {dt.name}")
        return v, False
    if not dt.is_integer:
        return s, False  # strings and domains: the text as written
    if _NODEID.search(s):
        rest = _NODEID.sub("", s.replace(" ", ""), count=1)
        rest = rest.strip("+") if rest.count("+") <= 1 else "?"
        offset = parse_int(rest, where) if rest else 0
        lo, hi = dt.int_range()
        if not lo <= offset <= hi:
            raise DeviceFileError(f"{where}: {_shown(s)} outside {dt.name} ({lo}..{hi})")
        return offset, True
    return _typed_int(s, dt, where), False


# ---------------------------------------------------------------- objects
def _enum_code(cls: type[enum.IntEnum], text: str, where: str, what: str) -> int:
    code = parse_int(text, where)
    try:
        return int(cls(code))
    except ValueError:
        raise DeviceFileError(f"{where}: unknown {what} {_shown(text)}") from None


def _entry(
    source: str,
    section: str,
    keys: Mapping[str, tuple[str, str]],
    index: int,
    sub: int,
    defaults: Mapping[str, tuple[str, str]] | None = None,
) -> ODEntry:
    """One entry from its section's keys."""
    w = f"{source}: [{section}]"

    def get(key: str) -> str | None:
        if key in keys:
            return keys[key][1]
        return None if defaults is None or key not in defaults else defaults[key][1]

    dt_text, acc_text = get("DATATYPE"), get("ACCESSTYPE")
    if dt_text is None:
        raise DeviceFileError(f"{w} DataType: missing")
    if acc_text is None:
        raise DeviceFileError(f"{w} AccessType: missing")
    dt = DataType(_enum_code(DataType, dt_text, f"{w} DataType", "data type"))
    try:
        access = Access(acc_text.strip().lower())
    except ValueError:
        raise DeviceFileError(
            f"{w} AccessType: unknown access type {_shown(acc_text)!r} "
            f"(known: {', '.join(a.value for a in Access)})"
        ) from None
    mapping = get("PDOMAPPING")
    pdo = False
    if mapping is not None and mapping.strip():
        flag = parse_int(mapping, f"{w} PDOMapping")
        if flag not in (0, 1):
            raise DeviceFileError(f"{w} PDOMapping: expected 0 or 1, got {_shown(mapping)}")
        pdo = flag == 1
    limits: list[int | float | None] = []
    for key, written in (("LOWLIMIT", "LowLimit"), ("HIGHLIMIT", "HighLimit")):
        text = get(key)
        limit, rel = (None, False) if text is None else parse_value(text, dt, f"{w} {written}")
        if isinstance(limit, str) or rel:
            limit = None  # no limits on strings and domains; none relative to the node id
        limits.append(limit)
    low, high = limits
    values: list[tuple[Value | None, bool]] = []
    for key, written in (("DEFAULTVALUE", "DefaultValue"), ("PARAMETERVALUE", "ParameterValue")):
        text = keys[key][1] if key in keys else None
        value, rel = (None, False) if text is None else parse_value(text, dt, f"{w} {written}")
        if value is not None and not rel and not isinstance(value, str):
            outside = (low is not None and value < low) or (high is not None and value > high)
            if outside:
                raise DeviceFileError(
                    f"{w} {written}: {_shown(str(text).strip())} outside LowLimit..HighLimit "
                    f"({low}..{high})"
                )
        values.append((value, rel))
    (default, rel_d), (parameter, rel_p) = values
    relative = rel_p if parameter is not None else rel_d
    name_text = get("PARAMETERNAME")
    return ODEntry(
        index=index,
        sub=sub,
        name="" if name_text is None else name_text,
        data_type=dt,
        access=access,
        pdo_mappable=pdo,
        default=default,
        parameter=parameter,
        node_relative=relative,
        low=low,
        high=high,
    )


def _objects(sections: Sections, source: str, quirks: list[str]) -> dict[int, ODObject]:
    tops: dict[int, tuple[str, dict[str, tuple[str, str]]]] = {}
    subs: dict[int, dict[int, tuple[str, dict[str, tuple[str, str]]]]] = {}
    for key, (written, keys) in sections.items():
        m = _OBJECT_SECTION.fullmatch(key)
        if m is None:
            continue  # FileInfo, DeviceInfo, ToolInfos, IIIIName, ...: not objects
        index = int(m.group(1), 16)
        if m.group(2) is None:
            if len(tops) >= MAX_OBJECTS:
                raise DeviceFileError(f"{source}: [{written}]: more than {MAX_OBJECTS} objects")
            tops[index] = (written, keys)
        else:
            subs.setdefault(index, {})[int(m.group(2), 16)] = (written, keys)
    for index, found in subs.items():
        if index not in tops:
            written = found[min(found)][0]
            raise DeviceFileError(f"{source}: [{written}]: no [{index:04X}] section for it")
    out: dict[int, ODObject] = {}
    for index, (written, keys) in tops.items():
        w = f"{source}: [{written}]"
        if "COMPACTSUBOBJ" in keys:
            raise DeviceFileError(f"{w} CompactSubObj: not supported (write each sub-index out)")
        ot_text = keys.get("OBJECTTYPE", ("", "0x7"))[1]
        ot = ObjectType(_enum_code(ObjectType, ot_text, f"{w} ObjectType", "object type"))
        name = keys.get("PARAMETERNAME", ("", ""))[1]
        own_subs = subs.get(index, {})
        if ot in (ObjectType.ARRAY, ObjectType.RECORD):
            if "SUBNUMBER" not in keys:
                raise DeviceFileError(f"{w} SubNumber: missing ({ot.name})")
            count = parse_int(keys["SUBNUMBER"][1], f"{w} SubNumber")
            if count != len(own_subs):
                miscount = (
                    f"[{written}] SubNumber: {count}, but the file has {len(own_subs)} "
                    "sub-index sections"
                )
                if not MANUFACTURER_INDICES[0] <= index <= MANUFACTURER_INDICES[1]:
                    raise DeviceFileError(f"{source}: {miscount}")
                quirks.append(f"{miscount} (a manufacturer object: taken as described)")
            entries = {
                sub: _entry(source, sw, sk, index, sub)
                for sub, (sw, sk) in sorted(own_subs.items())
            }
        else:
            if own_subs:
                written_sub = own_subs[min(own_subs)][0]
                raise DeviceFileError(
                    f"{source}: [{written_sub}]: sub-index of {ot.name} object {index:04X}"
                )
            if ot is not ObjectType.VAR and "DATATYPE" not in keys:
                entries = {}  # a DOMAIN/DEFTYPE/DEFSTRUCT description without a value
            else:
                entries = {0: _entry(source, written, keys, index, 0)}
        out[index] = ODObject(index, name, ot, entries)
    return out


def _check_lists(sections: Sections, objects: Mapping[int, ODObject], source: str) -> None:
    """Every object the lists name is described, and each list counts its entries."""
    for list_name in _LIST_SECTIONS:
        if list_name not in sections:
            continue
        written, keys = sections[list_name]
        w = f"{source}: [{written}]"
        if "SUPPORTEDOBJECTS" not in keys:
            raise DeviceFileError(f"{w} SupportedObjects: missing")
        count = parse_int(keys["SUPPORTEDOBJECTS"][1], f"{w} SupportedObjects")
        if not 0 <= count <= MAX_OBJECTS:
            raise DeviceFileError(f"{w} SupportedObjects: {count} outside 0..{MAX_OBJECTS}")
        for i in range(1, count + 1):
            if str(i) not in keys:
                raise DeviceFileError(f"{w} {i}: missing (SupportedObjects={count})")
            key_written, text = keys[str(i)]
            index = parse_int(text, f"{w} {key_written}")
            if index not in objects:
                raise DeviceFileError(
                    f"{w} {key_written}: object {index:04X} is listed but has no section"
                )


def _device_info(sections: Sections, source: str) -> DeviceInfo:
    written, keys = sections.get("DEVICEINFO", ("DeviceInfo", {}))
    w = f"{source}: [{written}]"

    def number(key: str) -> int | None:
        if key not in keys or not keys[key][1].strip():
            return None
        name, text = keys[key]
        v = parse_int(text, f"{w} {name}")
        if not 0 <= v < 2**32:
            raise DeviceFileError(f"{w} {name}: {_shown(text)} outside 0..0xFFFFFFFF")
        return v

    def text(key: str) -> str:
        return keys[key][1] if key in keys else ""

    return DeviceInfo(
        vendor_name=text("VENDORNAME"),
        vendor_number=number("VENDORNUMBER"),
        product_name=text("PRODUCTNAME"),
        product_number=number("PRODUCTNUMBER"),
        revision_number=number("REVISIONNUMBER"),
        nr_of_rxpdo=number("NROFRXPDO"),
        nr_of_txpdo=number("NROFTXPDO"),
        granularity=number("GRANULARITY"),
    )


def _dcf_node_id(sections: Sections, source: str) -> int | None:
    if "DEVICECOMISSIONING" not in sections:
        return None
    written, keys = sections["DEVICECOMISSIONING"]
    if "NODEID" not in keys or not keys["NODEID"][1].strip():
        return None
    name, text = keys["NODEID"]
    nid = parse_int(text, f"{source}: [{written}] {name}")
    if not 1 <= nid <= 127:
        raise DeviceFileError(f"{source}: [{written}] {name}: node id {nid} outside 1..127")
    return nid


def parse_device_file(text: str, source: str) -> DeviceFile:
    """Read a device file's text (``source`` names it in messages); see the module."""
    sections = _sections(text, source)
    quirks: list[str] = []
    objects = _objects(sections, source, quirks)
    _check_lists(sections, objects, source)
    is_dcf = "DEVICECOMISSIONING" in sections or any(
        e.parameter is not None for o in objects.values() for e in o.entries.values()
    )
    return DeviceFile(
        source=source,
        is_dcf=is_dcf,
        node_id=_dcf_node_id(sections, source),
        device=_device_info(sections, source),
        objects=objects,
        quirks=tuple(quirks),
    )


def read_device_file(path: str | Path, source: str | None = None) -> DeviceFile:
    """Read the EDS or DCF at ``path`` (at most :data:`MAX_FILE_BYTES`, UTF-8);
    :class:`DeviceFileError` with one line naming the file (``source``, default the path),
    the section and the key on anything it cannot take.

    >>> from drivers import eds_path
    >>> f = read_device_file(eds_path())
    >>> f.name, f.device.product_name, hex(f.value(0x1800, 1, node_id=3))
    ('hrm_drive.eds', 'HRM rope drive', '0x183')
    """
    name = str(path) if source is None else source
    text = read_text_file(path, DeviceFileError, "device file", name, max_bytes=MAX_FILE_BYTES)
    return _PARSED.get(text, name)


class _ParsedFiles:
    """The device files this process has parsed, by the SHA-256 of their text and their
    ``source``: a command that reads the same file again (the box check, the session, the
    wiring, the simulated box) reads its bytes again but parses them once; a changed file
    is a new text, hence parsed anew.  Errors are not kept (the file is parsed again and
    raises again).  At most :attr:`SIZE` files, the least recently used forgotten first;
    a :class:`DeviceFile` is immutable, so one is shared safely.

    >>> cache = _ParsedFiles()
    >>> text = "[DeviceInfo]\\nProductName=x\\n"
    >>> cache.get(text, "a.eds") is cache.get(text, "a.eds")
    True
    >>> cache.get(text, "a.eds") is cache.get(text + "\\n", "a.eds")
    False
    """

    SIZE = 16

    def __init__(self) -> None:
        self._files: OrderedDict[tuple[bytes, str], DeviceFile] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, text: str, source: str) -> DeviceFile:
        """The :func:`parse_device_file` of ``text``, parsed once."""
        key = (hashlib.sha256(text.encode("utf-8", "surrogatepass")).digest(), source)
        with self._lock:
            found = self._files.get(key)
            if found is not None:
                self._files.move_to_end(key)
                return found
        parsed = parse_device_file(text, source)
        with self._lock:
            self._files[key] = parsed
            while len(self._files) > self.SIZE:
                self._files.popitem(last=False)
        return parsed


_PARSED = _ParsedFiles()


def canopen_dictionary(f: DeviceFile, node_id: int | None = None) -> canopen.ObjectDictionary:
    """The device file as python-canopen's object dictionary, for a canopen node (host)
    or the simulated drive: this reader's values (a DCF's ``ParameterValue`` as the
    default, INTEGER8 ``0xFD`` as -3), ``$NODEID`` resolved for ``node_id`` when given
    (``relative`` and ``default_raw`` keep it, as canopen's own reader does).

    >>> from drivers import eds_path
    >>> od = canopen_dictionary(read_device_file(eds_path()), 5)
    >>> hex(od[0x1400][1].default), od[0x60C2][2].default, od[0x6041].access_type
    ('0x205', -3, 'ro')
    """
    from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

    od = ObjectDictionary()
    od.node_id = node_id

    def variable(e: ODEntry, name: str) -> ODVariable:
        var = ODVariable(name or e.name, e.index, e.sub)
        var.data_type = int(e.data_type)
        var.access_type = e.access.value
        var.pdo_mappable = e.pdo_mappable
        var.min, var.max = e.low, e.high
        value: Any = e.value
        if e.node_relative and isinstance(value, int):
            var.relative = True
            var.default_raw = f"$NODEID+0x{value:X}"
            value = value + (node_id or 0) if node_id is not None else value
        var.default = value
        var.value = value if e.parameter is not None else None
        return var

    for obj in f.objects.values():
        if obj.object_type in (ObjectType.ARRAY, ObjectType.RECORD):
            group = (ODArray if obj.object_type is ObjectType.ARRAY else ODRecord)(
                obj.name, obj.index
            )
            for e in obj.entries.values():
                group.add_member(variable(e, e.name))
            od.add_object(group)
        elif 0 in obj.entries:
            od.add_object(variable(obj.entries[0], obj.name))
    return od


# ---------------------------------------------------------------- writing
def _written(e: ODEntry, value: Value | None) -> str:
    """A value as an EDS writes it: unsigned integers in hex, signed in decimal, a node-id
    relative one as ``$NODEID+0x…``, reals and strings as they are."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    if isinstance(value, float):
        return repr(value)
    if e.node_relative:
        return f"$NODEID+0x{value:X}"
    return str(value) if e.data_type.signed or value < 0 else f"0x{value:X}"


def _entry_lines(e: ODEntry, name: str) -> list[str]:
    lines = [
        f"ParameterName={name}",
        "ObjectType=0x7",
        f"DataType=0x{int(e.data_type):04X}",
        f"AccessType={e.access.value}",
    ]
    if e.low is not None:
        lines.append(f"LowLimit={_written(replace(e, node_relative=False), e.low)}")
    if e.high is not None:
        lines.append(f"HighLimit={_written(replace(e, node_relative=False), e.high)}")
    lines += [f"DefaultValue={_written(e, e.value)}", f"PDOMapping={int(e.pdo_mappable)}"]
    return lines


def format_device_file(f: DeviceFile, file_name: str) -> str:
    """``f`` written out again as a plain CiA 306 EDS named ``file_name``: what this reader
    took (a DCF's ``ParameterValue`` as the default, INTEGER8 ``0xFD`` as -3, hex
    ``SupportedObjects`` in decimal, the object lists rebuilt, tool sections and
    descriptions without a value left out), for a tool stricter than the standard (Lely's
    ``dcfgen``).  Read back, it gives the same objects.

    >>> from drivers import eds_path
    >>> f = read_device_file(eds_path())
    >>> again = parse_device_file(format_device_file(f, "hrm.eds"), "hrm.eds")
    >>> again.objects == f.objects, again.device == f.device
    (True, True)
    """
    d = f.device
    info = [
        ("VendorName", d.vendor_name), ("VendorNumber", d.vendor_number),
        ("ProductName", d.product_name), ("ProductNumber", d.product_number),
        ("RevisionNumber", d.revision_number), ("NrOfRxPDO", d.nr_of_rxpdo),
        ("NrOfTxPDO", d.nr_of_txpdo), ("Granularity", d.granularity),
    ]  # fmt: skip
    lines = [
        "[FileInfo]",
        f"FileName={file_name}",
        "FileVersion=1",
        "FileRevision=0",
        "EDSVersion=4.0",
        f"Description={d.vendor_name} {d.product_name} (from {f.name})".replace("\n", " "),
        "",
        "[DeviceInfo]",
        *(
            f"{key}={f'0x{v:X}' if isinstance(v, int) and key.endswith('Number') else v}"
            for key, v in info
            if v is not None and v != ""
        ),
        "",
    ]
    objects = [o for i, o in sorted(f.objects.items()) if o.entries]
    mandatory = [o.index for o in objects if o.index in (0x1000, 0x1001, 0x1018)]
    manufacturer = [
        o.index for o in objects if MANUFACTURER_INDICES[0] <= o.index <= MANUFACTURER_INDICES[1]
    ]
    optional = [o.index for o in objects if o.index not in {*mandatory, *manufacturer}]
    for section, indices in (
        ("MandatoryObjects", mandatory),
        ("OptionalObjects", optional),
        ("ManufacturerObjects", manufacturer),
    ):
        lines += [f"[{section}]", f"SupportedObjects={len(indices)}"]
        lines += [f"{k}=0x{index:04X}" for k, index in enumerate(indices, start=1)]
        lines.append("")
    for obj in objects:
        if obj.object_type in (ObjectType.ARRAY, ObjectType.RECORD):
            lines += [
                f"[{obj.index:04X}]",
                f"ParameterName={obj.name}",
                f"ObjectType=0x{int(obj.object_type):X}",
                f"SubNumber={len(obj.entries)}",
                "",
            ]
            for sub, e in sorted(obj.entries.items()):
                lines += [f"[{obj.index:04X}sub{sub:X}]", *_entry_lines(e, e.name), ""]
        else:
            lines += [f"[{obj.index:04X}]", *_entry_lines(obj.entries[0], obj.name), ""]
    return "\n".join(lines)
