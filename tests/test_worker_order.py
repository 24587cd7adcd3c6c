"""The order each pytest-xdist worker takes its tests in (``tests/conftest.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import LONG_MODULES_S, worker_order

REPO = Path(__file__).resolve().parents[1]


def test_every_long_module_is_a_test_module_of_the_suite() -> None:
    missing = [m for m in LONG_MODULES_S if not (REPO / m).is_file()]
    assert missing == []


class Item:
    """What :func:`worker_order` reads of a pytest item."""

    def __init__(self, nodeid: str, exclusive: bool = False) -> None:
        self.nodeid = nodeid
        self.exclusive = exclusive

    def get_closest_marker(self, name: str) -> object | None:
        return pytest.mark.exclusive if name == "exclusive" and self.exclusive else None


def test_exclusive_first_then_the_long_modules_longest_first_then_the_rest_in_order() -> None:
    items = [
        Item("tests/a.py::t1"),
        Item("tests/hrm_ctrl/cli/test_view.py::t"),
        Item("tests/b.py::t"),
        Item("tests/hrm_ctrl/cli/test_demo.py::t"),
        Item("tests/hil/test_plugin_plan.py::t", exclusive=True),
        Item("tests/a.py::t2"),
    ]
    order = [i.nodeid for i in sorted(items, key=worker_order)]  # type: ignore[arg-type]
    assert order == [
        "tests/hil/test_plugin_plan.py::t",
        "tests/hrm_ctrl/cli/test_demo.py::t",
        "tests/hrm_ctrl/cli/test_view.py::t",
        "tests/a.py::t1",
        "tests/b.py::t",
        "tests/a.py::t2",
    ]
