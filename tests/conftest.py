"""Shared fixtures: the CAN backends this machine has.

``can_backend`` is parametrised over python-can ``virtual`` (everywhere),
``udp_multicast`` (IPv4 group, ``hop_limit=0`` so nothing leaves the host, a
UDP port of its own per bus: Linux hands every group on a port to every socket
bound to that port) and SocketCAN (the kernel's ``vcan0``, ``vcan1``: a test's
first bus is ``vcan0``, its second ``vcan1``).

Where the kernel has no vcan (as on the development machine and in CI) the SocketCAN
tests run at the end of the session
in User-Mode-Linux guests that have it, their results reported here
(``tests/vcan_guest.py``, ``tools/vcan-guest/``), or skip, naming the reason, where the
guest's packages are missing or ``HRM_VCAN_GUEST=off`` (``docs/hil.md``).

Note: a udp_multicast socket also receives the frames it sent itself; code
under test must tolerate its own frames coming back.

``quiet_heap`` (autouse) starts every test with the heap frozen out of the garbage
collector and collects it between tests, every :data:`COLLECT_EVERY_TESTS` tests.

``process_wide_settings`` (autouse, once per session) runs every test under
:func:`drivers.realtime.process_settings`, as ``hrm`` runs every command: buses,
wires and sessions change no interpreter setting, so the tests that pace frames or
stream (``tests/sim_bus/test_wire.py``, the in-process box, the HIL host side) get
the switch interval from the process entry, here pytest.
"""

from __future__ import annotations

import fcntl
import gc
import itertools
import os
import shutil
import signal
import socket
import tempfile
import threading
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from drivers.realtime import GcHold, process_settings
from tests import vcan_guest

BACKENDS = ("virtual", "udp_multicast", "socketcan")
_group_counter = itertools.count(1)

# Hypothesis measures wall time: a 200 ms deadline per example and a "too slow" check on
# data generation.  With both cores busy examples of tests/hrm_ctrl/planning/
# test_environment.py took 261-496 ms and failed as DeadlineExceeded / FlakyFailure.  No
# requirement here is an example's wall time, so neither applies anywhere (a test's own
# @settings still sets everything else).
settings.register_profile("hrm", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("hrm")


# The test process's heap grows test by test, and a full collection walks all of it inside
# whichever test triggers it: 120-240 ms unloaded, up to 844 ms with both cores busy
# (gc.callbacks over tests/drivers), every thread held, long enough for an
# in-process box's heartbeat or board watchdog to trip.  Each test starts with the heap
# frozen (its collections walk what it allocated), and the heap is collected between tests.
COLLECT_EVERY_TESTS = 100
_tests_since_collect = itertools.count(1)


@pytest.fixture(autouse=True)
def quiet_heap() -> None:
    """Freeze the heap before the test; every :data:`COLLECT_EVERY_TESTS` tests collect it
    first (unless a drive session still holds it: :class:`drivers.realtime.GcHold`)."""
    if next(_tests_since_collect) % COLLECT_EVERY_TESTS == 0 and GcHold.holders() == 0:
        gc.unfreeze()
        gc.collect()
    gc.freeze()


class SigintHandlerLeaked(pytest.PytestWarning):
    """A test left another SIGINT handler than it found (restored after it)."""


@pytest.fixture(autouse=True)
def sigint_handler_kept(request: pytest.FixtureRequest) -> Iterator[None]:
    """Each test finds SIGINT's handler as the one before it left it: a handler left
    behind (a box runner's "stop on SIGINT", an ignored signal) makes a later test's
    ``_thread.interrupt_main`` (Ctrl-C as a terminal sends it) do nothing.  A leak is
    restored and named in the warnings summary."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGINT)
    yield
    after = signal.getsignal(signal.SIGINT)
    if after is not before:
        signal.signal(signal.SIGINT, before)
        warnings.warn(
            SigintHandlerLeaked(f"{request.node.nodeid} left SIGINT's handler {after!r}"),
            stacklevel=1,
        )


@pytest.fixture(scope="session", autouse=True)
def process_wide_settings() -> Iterator[None]:
    """The interpreter settings every ``hrm`` process runs under (GIL switch interval)."""
    with process_settings():
        yield


@pytest.fixture
def ipc_dir() -> Iterator[Path]:
    """A folder of a short path for hrm_ipc's sockets, removed after the test: a socket
    path has at most 107 bytes, and a pytest-xdist worker's ``tmp_path`` is 10 longer than
    a single session's (``popen-gw0/``)."""
    path = Path(tempfile.mkdtemp(prefix="hrm-ipc-"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


#: the longest a test waits for its turn beside another worker's tests (the suite's limit
#: per test is 300 s; a test marked ``exclusive`` waits for the one running beside it)
TURN_TIMEOUT_S = 600.0
TURN_POLL_S = 0.05


def _flock_within(fd: int, how: int, timeout_s: float, what: str) -> None:
    """``flock(fd, how)``, failing the test after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            fcntl.flock(fd, how | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                pytest.fail(f"waited {timeout_s:g} s for {what}: another worker's test held it")
            time.sleep(TURN_POLL_S)


@pytest.fixture(autouse=True)
def exclusive_among_workers(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[None]:
    """With pytest-xdist, a test marked ``exclusive`` (the load tests' CPU burners, the HIL
    plan's box on a CPU of its own) runs with no other worker's test beside it; the others
    run side by side.  A readers-writer lock of two ``flock`` files of this run: a test
    passes the turnstile, then holds the room shared; an exclusive one holds the turnstile
    (so no new test enters) and the room alone."""
    config = request.config
    if not vcan_guest.is_xdist_worker(config):
        yield
        return
    base = tmp_path_factory.getbasetemp().parent / "hrm-turn"  # the workers' common folder
    exclusive = request.node.get_closest_marker("exclusive") is not None
    fds = [os.open(f"{base}.{name}", os.O_RDWR | os.O_CREAT, 0o600) for name in ("turn", "room")]
    turn, room = fds
    try:
        _flock_within(turn, fcntl.LOCK_EX, TURN_TIMEOUT_S, "the turnstile")
        if not exclusive:
            fcntl.flock(turn, fcntl.LOCK_UN)
        _flock_within(room, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH, TURN_TIMEOUT_S,
                      "the room")  # fmt: skip
        yield
    finally:
        for fd in fds:
            os.close(fd)  # (closing releases its lock)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def vcan_available(name: str = "vcan0") -> bool:
    return Path(f"/sys/class/net/{name}").exists()


#: The modules of the longest tests, with their seconds in a whole run on two workers on
#: the idle development machine (the waits for an exclusive test left out).
#: pytest-xdist's ``loadfile`` hands the modules out in the workers' order, each to the
#: first worker free: these go first (longest first), so the run does not end with one
#: worker in a long module and the other idle.  A module not here, or a figure gone
#: stale, changes the order only.
LONG_MODULES_S = {
    "tests/hrm_ctrl/cli/test_demo.py": 96,
    "tests/hrm_ctrl/cli/test_calibrate_physics.py": 59,
    "tests/hil/test_plugin.py": 57,
    "tests/hrm_ctrl/cli/test_calibrate.py": 54,
    "tests/hrm_ctrl/cli/console/test_console_wayback.py": 51,
    "tests/hrm_ctrl/ropes/test_estimator_compensated.py": 49,
    "tests/calibration/test_physics.py": 48,
    "tests/hrm_ctrl/cli/test_run_limits.py": 46,
    "tests/hrm_ctrl/cli/console/test_console_drive_cabins.py": 45,
    "tests/hrm_ctrl/cli/test_calibrate_box.py": 44,
    "tests/hrm_ctrl/planning/test_scan.py": 38,
    "tests/hrm_ctrl/cli/console/test_console_session.py": 38,
    "tests/hrm_ctrl/ropes/test_feedforward.py": 35,
    "tests/hrm_ctrl/cli/test_view.py": 31,
    "tests/drivers/test_canlog_durability.py": 31,
    "tests/calibration/test_zero.py": 31,
    "tests/drivers/safety/test_supervisor_stops.py": 30,
    "tests/drivers/safety/test_supervisor_foreign.py": 29,
    "tests/hrm_ctrl/cli/test_run_watches.py": 24,
    "tests/drivers/test_session.py": 23,
    "tests/hrm_ctrl/cli/test_signals.py": 22,
    "tests/hrm_ctrl/cli/console/test_console_cli.py": 22,
}


def worker_order(item: pytest.Item) -> tuple[bool, int]:
    """The sort key of a worker's items: the exclusive tests first (an exclusive module sent
    beside a long test, the demo's, waited for it with its own worker idle), then the
    modules of :data:`LONG_MODULES_S`, longest first; the others keep their order."""
    exclusive = item.get_closest_marker("exclusive") is not None
    return not exclusive, -LONG_MODULES_S.get(item.nodeid.split("::")[0], 0)


@pytest.hookimpl(trylast=True)  # after -k and -m deselect: the guests run only what is left
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if vcan_guest.is_xdist_worker(config):
        items.sort(key=worker_order)  # the same order in every worker (a stable sort)
    vcan_guest.split_for_guest(config, items)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> bool | None:
    return vcan_guest.run_in_guest(item)


def pytest_configure(config: pytest.Config) -> None:
    vcan_guest.register_report_writer(config)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    for line in vcan_guest.summary_lines(terminalreporter.config):
        terminalreporter.write_line(line)


def pytest_unconfigure(config: pytest.Config) -> None:
    vcan_guest.stop_guest(config)


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's controller
def pytest_testnodedown(node: Any, error: object) -> None:
    vcan_guest.note_worker_tests(node.config, getattr(node, "workeroutput", None))


@pytest.hookimpl(tryfirst=True)  # before the terminal's summary counts the reports
def pytest_sessionfinish(session: pytest.Session) -> None:
    vcan_guest.run_guests_after_workers(session)


BusFactory = Callable[[], dict[str, Any]]


@pytest.fixture(params=BACKENDS)
def can_backend(request: pytest.FixtureRequest) -> BusFactory:
    """A factory: each call returns ``can.Bus`` keyword arguments for a new,
    isolated bus on this backend (all ends of one bus use the same kwargs)."""
    kind = request.param
    if kind == "socketcan":
        if not vcan_available():
            why = vcan_guest.guest_unavailable() or "this test is not one the guest runs"
            pytest.skip(
                "SocketCAN: no vcan0 on this kernel (modprobe vcan; ip link add vcan0 type"
                f" vcan), no vcan guest: {why}"
            )
        channels = iter(vcan_guest.VCAN_INTERFACES)

        def vcan() -> dict[str, Any]:
            channel = next(channels, None)
            if channel is None:
                names = ", ".join(vcan_guest.VCAN_INTERFACES)
                pytest.fail(f"SocketCAN: a test has at most the buses {names}")
            return {"interface": "socketcan", "channel": channel}

        return vcan
    if kind == "udp_multicast":

        def udp() -> dict[str, Any]:
            n = next(_group_counter) % 250 + 1
            return {
                "interface": "udp_multicast",
                "channel": f"239.74.{os.getpid() % 250}.{n}",
                "port": _free_udp_port(),
                "hop_limit": 0,
            }

        return udp
    return lambda: {"interface": "virtual", "channel": f"hrm-test-{uuid.uuid4().hex[:12]}"}
