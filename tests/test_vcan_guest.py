"""The vcan guest's switch and command (``tests/vcan_guest.py``): on with
``HRM_VCAN_GUEST=off`` (on by default), and its pytest runs the stall probe at the guest's
period."""

from __future__ import annotations

import pytest

from hrm_ctrl.hil.stall_reruns import PERIOD_OPTION
from tests import vcan_guest


@pytest.mark.parametrize("value", ["on", "ON", " on "])
def test_on_runs_the_guest_where_its_packages_are(
    monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setenv(vcan_guest.SWITCH_ENV, value)
    why = vcan_guest.guest_unavailable()
    # on: only a missing package (or another platform) keeps it from running
    assert why is None or "needs" in why or "Linux" in why, why


@pytest.mark.parametrize("value", ["off", "OFF", " off "])
def test_off_skips_the_guest_naming_the_switch_and_why(
    monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setenv(vcan_guest.SWITCH_ENV, value)
    why = vcan_guest.guest_unavailable()
    assert why is not None and why.startswith("HRM_VCAN_GUEST=off: they run"), why
    assert "docs/hil.md" in why


def test_another_switch_value_is_a_one_line_usage_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(vcan_guest.SWITCH_ENV, "yes")
    with pytest.raises(pytest.UsageError, match=r"^HRM_VCAN_GUEST='yes': expected on or off$"):
        vcan_guest.guest_unavailable()


def test_the_guests_pytest_runs_the_stall_probe_at_the_guests_period() -> None:
    args = vcan_guest.guest_args(["tests/a.py::t[socketcan]"], "")
    assert f"{PERIOD_OPTION}={vcan_guest.GUEST_PROBE_PERIOD_S:g}" in args
    assert not any(a.startswith("no:") and "stall" in a for a in args), args
    # the guest's shortest window (the stop tests' 2 cycles at its rigs' rate) is longer than
    # two of the probe's periods: a pause a period longer than it is caught however it falls
    assert 2 / vcan_guest.GUEST_RATE_HZ > 2 * vcan_guest.GUEST_PROBE_PERIOD_S


def test_the_guests_pytest_is_never_distributed() -> None:
    args = vcan_guest.guest_args(["tests/a.py::t[socketcan]"], "")
    assert args[args.index("-n") + 1] == "0", args


def test_the_controller_keeps_each_workers_socketcan_tests_once_with_their_place(
    pytestconfig: pytest.Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    """pytest-xdist's workers each name the same SocketCAN tests (their collections are
    equal); the controller keeps each once, in order, with its location for the reports."""
    monkeypatch.delitem(pytestconfig.stash, vcan_guest.WORKER_TESTS, raising=False)
    named = [["tests/a.py::t[socketcan]", ["tests/a.py", 3, "t[socketcan]"]],
             ["tests/b.py::u[socketcan]", ["tests/b.py", None, "u[socketcan]"]]]  # fmt: skip
    for _worker in range(2):
        vcan_guest.note_worker_tests(pytestconfig, {vcan_guest.WORKER_OUTPUT_KEY: named})
    vcan_guest.note_worker_tests(pytestconfig, None)  # a worker that crashed names none
    tests = pytestconfig.stash[vcan_guest.WORKER_TESTS]
    assert tests == {
        "tests/a.py::t[socketcan]": ("tests/a.py", 3, "t[socketcan]"),
        "tests/b.py::u[socketcan]": ("tests/b.py", None, "u[socketcan]"),
    }
    del pytestconfig.stash[vcan_guest.WORKER_TESTS]
