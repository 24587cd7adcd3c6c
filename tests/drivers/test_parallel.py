"""drivers/parallel.py: SDO work on every drive at once, bounded in time; the first error
is raised as itself (class and fields kept, the others counted, the original chained)."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from drivers.parallel import run_parallel, with_message
from drivers.safety.stops import SafetyStopError
from hrm_ctrl.errors import DriverError
from tests.drivers.driver_rig import Rig


class CodedError(DriverError):
    """An error with a field its constructor requires."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def fail_on(bad: dict[int, BaseException]) -> Callable[[int], int]:
    def fn(x: int) -> int:
        if x in bad:
            raise bad[x]
        return x

    return fn


def test_results_come_in_the_items_order() -> None:
    assert run_parallel("x", lambda x: x * 10, [3, 1, 2], 5.0, label=str) == [30, 10, 20]
    assert run_parallel("x", lambda x: x, [], 5.0, label=str) == []


def test_the_first_error_keeps_its_class_fields_and_cause() -> None:
    first = CodedError("drive 1: abort 0x06090011", 0x06090011)
    events: list[str] = []
    with pytest.raises(CodedError) as info:
        run_parallel(
            "configuration",
            fail_on({1: first, 2: CodedError("drive 2: timeout", 2)}),
            [0, 1, 2],
            5.0,
            label=str,
            on_error=events.append,
        )
    err = info.value
    assert str(err) == "drive 1: abort 0x06090011 (and 1 more drive(s) failed)"
    assert err.code == 0x06090011  # the field survives (type(first)(...) dropped it)
    assert err.__cause__ is first
    assert events == ["configuration: drive 1: abort 0x06090011 (and 1 more drive(s) failed)"]


def test_an_error_whose_constructor_needs_more_than_a_message_is_kept() -> None:
    stop = SafetyStopError("stopped: EMCY", ["cause"], None)  # type: ignore[arg-type]
    with pytest.raises(SafetyStopError) as info:
        run_parallel("enable", fail_on({0: stop}), [0], 5.0, label=str)
    assert info.value.causes == ["cause"] and info.value.__cause__ is stop


def test_a_foreign_error_becomes_a_driver_error_naming_the_work() -> None:
    bug = KeyError("oops")
    with pytest.raises(DriverError, match=r"^state check: 'oops'$") as info:
        run_parallel("state check", fail_on({0: bug}), [0, 1], 5.0, label=str)
    assert info.value.__cause__ is bug


def test_with_message_copies_without_calling_the_constructor() -> None:
    e = with_message(CodedError("a", 3), "a (more)")
    assert (type(e), str(e), e.code, e.args) == (CodedError, "a (more)", 3, ("a (more)",))


def test_parallel_sdo_work_is_bounded_in_time(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    t0 = time.monotonic()
    with pytest.raises(DriverError, match=r"probe: no answer within 0.2 s from 3 drive\(s\)"):
        box.drives.parallel("probe", lambda link: time.sleep(1.5), 0.2)
    assert time.monotonic() - t0 < 1.0
