"""The one validator of the descriptions (box.toml, the robot description, the truth file):
ranges in field metadata, kinds from the annotations, one-line messages."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.config import BusConfig, ControlConfig, TensionConfig, TrackerConfig
from hrm_ctrl.validate import Spec, number_kinds, ranged, read_numbers, specs


@dataclass(frozen=True)
class Valve:
    port: str
    opening: float = ranged(0.5, 0.0, 1.0, "", "a fraction", lo_open=True)
    pulses: int = ranged(10, 1, 100, "", "per stroke")
    ceiling: float = ranged(50.0, -math.inf, 90.0, "deg", "the stop", above="floor")
    floor: float = ranged(10.0, 0.0, 80.0, "deg", "the seat")


def outside(key: str, value: Any, s: Spec, values: Any) -> str:
    return f"valve.{key} = {value!r} outside {s.interval()}"


@pytest.mark.parametrize("cls", [ControlConfig, TensionConfig, TrackerConfig])
def test_every_number_of_a_box_table_has_a_range_its_default_keeps(cls: type) -> None:
    ranges = specs(cls)
    assert set(ranges) == set(number_kinds(cls))  # no number without its range
    defaults = {f.name: f.default for f in fields(cls) if f.name in ranges}
    for key, s in ranges.items():
        assert s.contains(defaults[key], defaults), key


def test_kinds_come_from_the_annotations() -> None:
    assert number_kinds(Valve) == {
        "opening": float,
        "pulses": int,
        "ceiling": float,
        "floor": float,
    }
    assert number_kinds(BusConfig) == {"bitrate": int}
    assert specs(BusConfig)["bitrate"].text() == "1..1000000"


@given(
    key=st.sampled_from(["opening", "pulses", "ceiling", "floor"]),
    value=st.one_of(
        st.integers(-(10**30), 10**30),
        st.floats(allow_nan=True, allow_infinity=True),
        st.sampled_from([0, 0.0, 1, 1.0, 100, 101, 90.0, 10.0, 10.000001, True, "1"]),
    ),
)
def test_a_value_is_taken_exactly_when_it_is_a_number_of_its_kind_in_its_range(
    key: str, value: Any
) -> None:
    defaults = {f.name: f.default for f in fields(Valve)}
    number = not isinstance(value, bool) and isinstance(value, int | float)
    finite = number and math.isfinite(value)
    whole = finite and float(value).is_integer() if isinstance(value, float) else finite
    kind_ok = finite and (number_kinds(Valve)[key] is float or whole)
    values = {**defaults, key: value}
    good = kind_ok and all(r.contains(values[k], values) for k, r in specs(Valve).items())
    try:
        got = read_numbers(Valve, {key: value}, "v.toml", ValueError, "valve", outside)
    except ValueError as exc:
        msg = str(exc)
        assert not good, msg
        named = "ceiling" if key == "floor" and "valve.floor" not in msg else key  # relation
        assert msg.startswith(f"v.toml: valve.{named}") and "\n" not in msg, msg
        assert len(msg) < 200, msg
        return
    assert good
    assert got == {key: number_kinds(Valve)[key](value)}
    assert type(got[key]) is number_kinds(Valve)[key]


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"opening": 0}, "v.toml: valve.opening = 0 outside (0, 1]"),
        ({"pulses": 2.5}, "v.toml: valve.pulses: expected an integer, got 2.5"),
        ({"pulses": "3"}, "v.toml: valve.pulses: expected a number, got '3'"),
        ({"floor": math.inf}, "v.toml: valve.floor: expected a finite number, got inf"),
        ({"ceiling": 20.0, "floor": 30.0}, "v.toml: valve.ceiling = 20.0 outside [-inf, 90] deg"),
        ({"ceiling": 5.0}, "v.toml: valve.ceiling = 5.0 outside [-inf, 90] deg"),  # floor 10
        ({"floor": 60.0}, "v.toml: valve.ceiling = 50.0 outside [-inf, 90] deg"),  # its default
        ({"colour": 1}, "v.toml: valve.colour: unknown key"),
        ({"port": "/dev/x"}, "v.toml: valve.port: unknown key"),  # not a number: not skipped
    ],
)
def test_refusals_are_one_line_naming_file_and_key(doc: dict, message: str) -> None:
    with pytest.raises(ValueError) as info:
        read_numbers(Valve, doc, "v.toml", ValueError, "valve", outside)
    assert str(info.value) == message


def test_an_integer_of_any_size_is_judged_without_overflow() -> None:
    with pytest.raises(ValueError, match=r"valve\.pulses = 1000000000\d* outside"):
        read_numbers(Valve, {"pulses": 10**400}, "v.toml", ValueError, "valve", outside)
    assert read_numbers(Valve, {"pulses": 1e2}, "v", ValueError, "valve", outside) == {
        "pulses": 100
    }
