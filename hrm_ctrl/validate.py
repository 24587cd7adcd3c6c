"""The one validator of the TOML descriptions: ``box.toml``, the robot description and the
simulated arm's truth.

A value's safe range is a :class:`Spec`: bounds (each inclusive or not), a unit, the
reason for the bounds, and optionally another value it must exceed.  A dataclass read
from a flat TOML table carries them in its field metadata (:func:`ranged`, or
``field(metadata=spec(...))``; read back by :func:`specs`); a file whose keys are not
one dataclass's fields keeps one table of them.  Whether a value is an integer comes
from the field's annotation (:func:`number_kinds`), never restated.  Every check raises
the caller's error class with one line that names the file and the key
(``box.toml: control.rate_hz: ...``); each reader words its out-of-range sentence once,
for all of its keys.

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Pump:
...     rate_hz: float = ranged(10.0, 1, 100, "Hz", "the pump's own limits")
...     count: int = ranged(1, 1, 8)
>>> specs(Pump)["rate_hz"].interval(), specs(Pump)["count"].text()
('[1, 100] Hz', '1..8')
>>> def outside(key, value, s, values):
...     return f"pump.{key} = {value!r} outside {s.text()}"
>>> read_numbers(Pump, {"count": 3.0}, "p.toml", ValueError, "pump", outside)
{'count': 3}
>>> read_numbers(Pump, {"rate_hz": 0}, "p.toml", ValueError, "pump", outside)
Traceback (most recent call last):
ValueError: p.toml: pump.rate_hz = 0 outside 1..100 Hz
>>> read_numbers(Pump, {"count": 1.5}, "p.toml", ValueError, "pump", outside)
Traceback (most recent call last):
ValueError: p.toml: pump.count: expected an integer, got 1.5
>>> read_numbers(Pump, {"colour": 1}, "p.toml", ValueError, "pump", outside)
Traceback (most recent call last):
ValueError: p.toml: pump.colour: unknown key
"""

from __future__ import annotations

import math
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

_SPEC = "hrm_ctrl.validate.spec"  # the field-metadata key


@dataclass(frozen=True)
class Spec:
    """The safe range of one value: ``lo..hi`` (``lo_open``/``hi_open``: that end
    excluded), its unit, why it ends there, and the field it must exceed (``above``,
    a relation between two values of one table).

    >>> s = Spec(lo=0, hi=50, lo_open=True, unit="per s")
    >>> s.contains(0), s.contains(50), s.interval()
    (False, True, '(0, 50] per s')
    """

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    unit: str = ""
    why: str = ""
    above: str | None = None

    def contains(self, value: Any, values: Mapping[str, Any] | None = None) -> bool:
        """Whether ``value`` (a number, or an array: every element) lies in the range and,
        with ``above``, exceeds ``values[above]``.  Compares without converting, so an
        integer of any size is judged exactly (no overflow)."""
        ok = self.inside(value)
        if self.above is not None and values is not None:
            ok = ok & (value > values[self.above])
        return bool(ok) if isinstance(ok, bool) else bool(ok.all())

    def inside(self, value: Any) -> Any:
        """Whether ``value`` lies in ``lo..hi``: a bool, or for an array one per element
        (NaN is outside)."""
        lo_ok = value > self.lo if self.lo_open else value >= self.lo
        hi_ok = value < self.hi if self.hi_open else value <= self.hi
        return lo_ok & hi_ok

    def text(self) -> str:
        """``lo..hi unit`` (integers, and the ``[control]`` table's ranges)."""
        return f"{_num(self.lo)}..{_num(self.hi)}{self._unit()}"

    def interval(self) -> str:
        """``[lo, hi] unit`` with ``(`` / ``)`` at an excluded end."""
        left, right = "(" if self.lo_open else "[", ")" if self.hi_open else "]"
        return f"{left}{_num(self.lo)}, {_num(self.hi)}{right}{self._unit()}"

    def _unit(self) -> str:
        return f" {self.unit}" if self.unit else ""


def _num(x: float) -> str:
    """A bound for a message: all its digits when it is a whole number, else ``:g``.

    >>> _num(4_000_000), _num(0.05), _num(10.0)
    ('4000000', '0.05', '10')
    """
    return str(int(x)) if math.isfinite(x) and float(x).is_integer() else f"{x:g}"


def spec(**bounds: Any) -> dict[str, Spec]:
    """Field metadata holding a :class:`Spec`: ``field(default=1.0, metadata=spec(lo=0))``."""
    return {_SPEC: Spec(**bounds)}


def ranged(default: Any, lo: float, hi: float, unit: str = "", why: str = "", **more: Any) -> Any:
    """A dataclass field with a default and a safe range ``lo..hi`` (:class:`Spec`; ``more``:
    its other settings): ``timeout_s: float = ranged(1.0, 0.01, 10.0, "s", "why")``."""
    return field(default=default, metadata=spec(lo=lo, hi=hi, unit=unit, why=why, **more))


def specs(cls: type) -> dict[str, Spec]:
    """The :class:`Spec` of every field of dataclass ``cls`` that has one, in field order."""
    return {f.name: f.metadata[_SPEC] for f in fields(cls) if _SPEC in f.metadata}


def number_kinds(cls: type) -> dict[str, type]:
    """``int`` or ``float`` for every numeric field of dataclass ``cls``, from its
    annotations (a field of another type is left out)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls) if hints[f.name] in (int, float)}


def number(value: Any, where: str, error: type[Exception], *, integer: bool = False) -> Any:
    """``value`` checked to be a finite number (an integer when ``integer``: an integral
    float such as ``1e8`` is one), returned unconverted; else ``error`` with one line
    ``WHERE: expected a number, got ...`` (or ``a finite number``, ``an integer``).

    >>> number(2.0, "k", ValueError, integer=True), number(3, "k", ValueError)
    (2.0, 3)
    >>> number(True, "f: k", ValueError)
    Traceback (most recent call last):
    ValueError: f: k: expected a number, got True
    >>> number(float("nan"), "f: k", ValueError)
    Traceback (most recent call last):
    ValueError: f: k: expected a finite number, got nan
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise error(f"{where}: expected a number, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise error(f"{where}: expected a finite number, got {value!r}")
    if integer and isinstance(value, float) and not value.is_integer():
        raise error(f"{where}: expected an integer, got {value!r}")
    return value


OutOfRange = Callable[[str, Any, Spec, Mapping[str, Any]], str]
"""A reader's out-of-range sentence: ``(key, value, spec, all values) -> text`` after
``FILE: ``."""


def read_numbers(
    cls: type,
    doc: Mapping[str, Any],
    where: str,
    error: type[Exception],
    table: str,
    out_of_range: OutOfRange,
    *,
    skip: frozenset[str] = frozenset(),
) -> dict[str, Any]:
    """The numeric fields of dataclass ``cls`` that the TOML table ``doc`` gives, each a
    finite number of its field's kind (:func:`number_kinds`) within its :class:`Spec`
    (checked on the value as written, before any conversion, in field order, once every
    value is known: ``above`` compares with the other field's value or default, whenever
    either of the two is given).  A key
    that is no field is refused (``FILE: TABLE.KEY: unknown key``); keys in ``skip``
    (fields of other types) are left to the caller."""
    kinds = number_kinds(cls)
    refuse_unknown(doc, kinds.keys() | skip, where, error, table)
    raw = {
        key: number(value, f"{where}: {table}.{key}", error, integer=kinds[key] is int)
        for key, value in doc.items()
        if key in kinds
    }
    defaults = {f.name: f.default for f in fields(cls)}
    values = {**defaults, **raw}
    for key, s in specs(cls).items():
        given = key in raw or s.above in raw  # a relation: checked when either side is given
        if given and not s.contains(values[key], values):
            raise error(f"{where}: {out_of_range(key, values[key], s, values)}")
    return {key: kinds[key](value) for key, value in raw.items()}


def refuse_unknown(
    doc: Mapping[str, Any], known: Any, where: str, error: type[Exception], table: str
) -> None:
    """``error`` ``FILE: TABLE.KEY: unknown key`` for the first key of ``doc`` not in
    ``known``."""
    for key in doc:
        if key not in known:
            raise error(f"{where}: {table}.{key}: unknown key")


def unknown_key(key: str, known: Any, tables: Any = ()) -> str:
    """`` (did you mean ...?)`` for a near miss of ``key`` among ``known`` (a name in
    ``tables`` shown as ``[name]``), else the known names (for an unknown-key message).

    >>> unknown_key("yaw", {"yaw_deg", "pitch_deg"})
    " (did you mean 'yaw_deg'?)"
    >>> unknown_key("ropess", {"ropes", "name"}, {"ropes"}), unknown_key("zz", {"a", "b"})
    (' (did you mean [ropes]?)', ' (known: a, b)')
    """
    import difflib

    close = difflib.get_close_matches(key, sorted(known), n=1)
    if not close:
        return f" (known: {', '.join(sorted(known))})"
    match = close[0]
    return f" (did you mean {f'[{match}]' if match in tables else repr(match)}?)"
