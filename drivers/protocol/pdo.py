"""A PDO's layout (CiA 301 7.4.2: the objects a PDO maps, in order, little-endian) and
the one encoder and parser of its bytes.

A :class:`PdoLayout` is built from its entries (object index, sub-index and the
``struct`` code of its data type; a ``"<n>x"`` code is a dummy entry of n bytes) or from
a mapping as a drive holds it (:meth:`PdoLayout.of_mapping`: 0x1600/0x1A00 values).  It
gives what every user of that PDO needs, derived from the same entries: the mapping
values written to the drive, the payload's size, one payload packed or parsed
(:meth:`~PdoLayout.pack`, :meth:`~PdoLayout.unpack`), many packed at once
(:meth:`~PdoLayout.pack_many`) and a NumPy view of the payload inside a frame record
(:meth:`~PdoLayout.view_in`).  The host's setpoint RPDO and feedback TPDO
(:data:`drivers.protocol.cia402.RPDO_TARGET`, :data:`~drivers.protocol.cia402.TPDO_FEEDBACK`)
and the simulated drive's PDOs (compiled from its object dictionary's mapping) are all
:class:`PdoLayout`, so both ends of the wire encode and parse with the same code.

Values: an unsigned entry is taken modulo its width (a controlword is 16 bits whatever
the caller's integer holds), a signed one must fit (:class:`FrameError` naming it).

>>> rpdo = PdoLayout((PdoEntry("controlword", 0x6040, 0, "H"),
...                   PdoEntry("target", 0x607A, 0, "i", "target position")))
>>> [hex(m) for m in rpdo.mapping], rpdo.size
(['0x60400010', '0x607a0020'], 6)
>>> rpdo.pack(0x000F, -2).hex()
'0f00feffffff'
>>> rpdo.unpack(bytes.fromhex('0f00feffffff'))
(15, -2)
>>> rpdo.pack(0, 2**31)
Traceback (most recent call last):
...
drivers.protocol.cia301.FrameError: target position 2147483648 outside INTEGER32
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from drivers.protocol.cia301 import FrameError, parse_pdo_mapping_entry, pdo_mapping_entry

#: CiA 301 data type names of the ``struct`` codes a PDO entry may have (messages)
TYPE_NAMES = {
    "b": "INTEGER8", "B": "UNSIGNED8", "h": "INTEGER16", "H": "UNSIGNED16",
    "i": "INTEGER32", "I": "UNSIGNED32", "q": "INTEGER64", "Q": "UNSIGNED64",
    "f": "REAL32", "d": "REAL64", "?": "BOOLEAN",
}  # fmt: skip


_CANONICAL = str.maketrans({"l": "i", "L": "I"})


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: ``name`` (how a NumPy view calls it), index, sub-index and the
    ``struct`` code of its data type (``"<n>x"``: a dummy entry of n bytes; ``"<n>s"``:
    n raw bytes of a type without a fixed code).  ``label`` names it in messages.
    Layouts compare by what is on the wire (index, sub-index, code), not by names."""

    name: str = field(compare=False)
    index: int
    subindex: int
    code: str
    label: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        # one code per type: "<l" and "<i" are both INTEGER32 (canopen uses the former)
        object.__setattr__(self, "code", self.code.translate(_CANONICAL))

    @property
    def size(self) -> int:
        return struct.calcsize("<" + self.code)

    @property
    def dummy(self) -> bool:
        return self.code.endswith("x")

    @property
    def raw(self) -> bool:
        return self.code.endswith("s")

    @property
    def type_name(self) -> str:
        return TYPE_NAMES.get(self.code, f"{self.size * 8}-bit value")


@dataclass(frozen=True)
class PdoLayout:
    """The objects one PDO maps, in order (see the module docstring)."""

    entries: tuple[PdoEntry, ...]

    @classmethod
    def of_mapping(
        cls,
        mapping: Sequence[int],
        code_of: Callable[[int, int, int], str | None],
        name_of: Callable[[int, int], str] | None = None,
    ) -> PdoLayout:
        """The layout of mapping values (0x1600/0x1A00 sub-indices 1..n) as a drive holds
        them: ``code_of(index, subindex, bits)`` gives the ``struct`` code of a mapped
        object, or None for one without a fixed code (raw bytes) or unknown (a dummy).

        >>> codes = {0x6041: "H", 0x0005: "1x"}
        >>> PdoLayout.of_mapping([0x60410010, 0x00050008, 0x20000008],
        ...                      lambda i, s, b: codes.get(i)).codes
        '<H1x1s'
        """
        entries = []
        for value in mapping:
            index, sub, bits = parse_pdo_mapping_entry(value)
            code = code_of(index, sub, bits) or f"{bits // 8}s"
            name = name_of(index, sub) if name_of is not None else f"x{index:04X}_{sub}"
            entries.append(PdoEntry(name, index, sub, code))
        return cls(tuple(entries))

    @cached_property
    def codes(self) -> str:
        """The ``struct`` format of the whole payload."""
        return "<" + "".join(e.code for e in self.entries)

    @cached_property
    def struct(self) -> struct.Struct:
        return struct.Struct(self.codes)

    @property
    def size(self) -> int:
        """Bytes of the payload."""
        return self.struct.size

    @cached_property
    def mapping(self) -> tuple[int, ...]:
        """The mapping values (0x1600/0x1A00 sub-indices 1..n) of this layout."""
        return tuple(pdo_mapping_entry(e.index, e.subindex, e.size * 8) for e in self.entries)

    @cached_property
    def values(self) -> tuple[PdoEntry, ...]:
        """The entries that carry a value (not dummies), in order: what
        :meth:`pack` takes and :meth:`unpack` returns."""
        return tuple(e for e in self.entries if not e.dummy)

    @cached_property
    def offsets(self) -> tuple[int, ...]:
        """Byte offset of each of :attr:`values` in the payload."""
        out, at = [], 0
        for e in self.entries:
            if not e.dummy:
                out.append(at)
            at += e.size
        return tuple(out)

    @cached_property
    def dtype(self) -> np.dtype:
        """One payload as a NumPy record (packed, little-endian)."""
        return np.dtype(
            {
                "names": [e.name for e in self.values],
                "formats": [f"V{e.size}" if e.raw else "<" + e.code for e in self.values],
                "offsets": list(self.offsets),
                "itemsize": self.size,
            }
        )

    @cached_property
    def _checks(self) -> tuple[tuple[int | None, tuple[int, int] | None], ...]:
        """Per value: the mask of an unsigned integer, the range of a signed one."""
        return tuple((_mask(e), _limits(e)) for e in self.values)

    def pack(self, *values: int | float | bytes) -> bytes:
        """One payload of ``values`` (one per entry of :attr:`values`, in order)."""
        if len(values) != len(self.values):
            raise FrameError(f"PDO of {len(self.values)} values, got {len(values)}")
        out: list[int | float | bytes] = []
        for (mask, limits), e, v in zip(self._checks, self.values, values, strict=True):
            if mask is not None:
                v = int(v) & mask  # type: ignore[arg-type]
            elif limits is not None:
                v = int(v)  # type: ignore[arg-type]
                if not limits[0] <= v <= limits[1]:
                    raise FrameError(f"{e.label or e.name} {v} outside {e.type_name}")
            out.append(v)
        return self.struct.pack(*out)

    def unpack(self, data: bytes | bytearray | memoryview) -> tuple[int | float | bytes, ...]:
        """The values of one payload (exactly :attr:`size` bytes)."""
        if len(data) != self.size:
            raise FrameError(f"PDO must carry {self.size} bytes, got {len(data)}")
        return self.struct.unpack(bytes(data))

    def unpack_from(self, data: bytes | bytearray) -> tuple[int | float | bytes, ...]:
        """The values of the first :attr:`size` bytes of ``data`` (a drive takes an RPDO
        longer than its mapping; a shorter one is the caller's error to report)."""
        return self.struct.unpack_from(data)

    @cached_property
    def _by_name(self) -> dict[str, tuple[PdoEntry, int | None, tuple[int, int] | None]]:
        """Per value's name: the entry, its mask (unsigned), its range (signed)."""
        return {e.name: (e, _mask(e), _limits(e)) for e in self.values}

    @cached_property
    def has_raw(self) -> bool:
        """Whether a value is raw bytes (decoded by the object's own description)."""
        return any(e.raw for e in self.values)

    def check_many(self, name: str, values: np.ndarray | int) -> None:
        """:class:`FrameError` if any of ``values`` does not fit entry ``name``."""
        e, _, limits = self._by_name[name]
        if limits is None:
            return
        v = values if isinstance(values, np.ndarray) else np.asarray(values)
        if v.size and (v.min() < limits[0] or v.max() > limits[1]):
            raise FrameError(f"{e.label or e.name} outside {e.type_name}")

    def fill(self, view: np.ndarray, **columns: int | np.ndarray) -> None:
        """Write ``columns`` (by entry name) into ``view`` (records of :attr:`dtype` or of
        :meth:`view_in`), unsigned ones modulo their width, signed ones checked (a
        control cycle's path: no copy of an array that needs none)."""
        by_name = self._by_name
        for name, value in columns.items():
            _, mask, _ = by_name[name]
            if mask is None:
                self.check_many(name, value)
                view[name] = value
            elif isinstance(value, int):
                view[name] = value & mask
            else:
                view[name] = np.asarray(value, dtype=np.int64) & mask

    def pack_many(self, **columns: int | np.ndarray) -> bytes:
        """Payloads for many nodes at once (columns broadcast), concatenated.

        >>> from drivers.protocol.cia402 import RPDO_TARGET
        >>> RPDO_TARGET.pack_many(controlword=np.array([15, 2]), target=np.array([1, -1])).hex()
        '0f00010000000200ffffffff'
        """
        shape = np.broadcast_shapes(*(np.shape(v) for v in columns.values()))
        rec = np.zeros(shape, dtype=self.dtype)
        self.fill(rec, **columns)
        return rec.tobytes()

    def view_in(self, record: np.dtype, at: str = "data") -> np.dtype:
        """A view of ``record`` (e.g. a frame record) whose field ``at`` holds this
        payload: ``record``'s other fields, then this layout's values by name.

        >>> rec = np.dtype([("id", "<u4"), ("data", "u1", (8,))])
        >>> from drivers.protocol.cia402 import TPDO_FEEDBACK
        >>> TPDO_FEEDBACK.view_in(rec).fields["position"][1]
        6
        """
        fields = [(n, *record.fields[n][:2]) for n in record.names if n != at]
        base = record.fields[at][1]
        fields += [
            (e.name, self.dtype.fields[e.name][0], base + off)
            for e, off in zip(self.values, self.offsets, strict=True)
        ]
        names, formats, offsets = (list(x) for x in zip(*fields, strict=True))
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": record.itemsize}
        )


def _limits(e: PdoEntry) -> tuple[int, int] | None:
    """The range of a signed integer entry (None: unsigned, real or raw)."""
    if e.code in ("b", "h", "i", "q"):
        bits = e.size * 8
        return -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    return None


def _mask(e: PdoEntry) -> int | None:
    """The mask of an unsigned integer entry (None: signed, real or raw)."""
    return (1 << (e.size * 8)) - 1 if e.code in ("B", "H", "I", "Q") else None
