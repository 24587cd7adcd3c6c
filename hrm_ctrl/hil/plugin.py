"""pytest plugin ``hrm_hil``: fixtures for hardware-in-the-loop tests on the simulated box
(``docs/hil.md``).  Installed with the package (entry point ``pytest11``), so any pytest run
where ``hrm`` is installed has it; nothing is imported or started until a test asks for a
fixture.

Options (command line, or ``addopts`` in the ini file):

``--hrm-bus KIND[,KIND...]`` (``auto``, ``virtual``, ``ipc``, ``udp_multicast``, ``socketcan``)
    the CAN buses between host and box; several: every HIL test runs on each (default: a
    module's ``@pytest.mark.hrm_buses(...)``, else ``auto``: the cross-process bus ``ipc``
    where python-can has it, else ``udp_multicast``); ``virtual`` needs the box in process,
    ``socketcan`` vcan0/vcan1 (tests skip, naming the reason, where a bus is unavailable).
``--hrm-box {process,inprocess}``
    the box as its own process (``hrm sim --control``, default) or in the test process.
``--hrm-rt-priority PRIORITY`` (0..49, default 0)
    the host's drive-session threads (``[control] realtime_priority``) and a box process's
    threads (``hrm sim --rt-priority``) under ``SCHED_FIFO`` at PRIORITY, as on a rig;
    0 keeps normal scheduling.  Where the process may not, the session runs at normal
    scheduling (its run record says so) and a box process refuses to start.
``--hrm-cpu-latency-us US`` (0..2000000000, default none)
    ``[control] cpu_wakeup_latency_us``: each drive session holds a PM QoS CPU wake-up
    latency request (0: idle CPUs poll instead of halting; ``drivers.realtime``).

Fixtures (``hrm_box*`` module-scoped: one box serves a test module; the rest per test):

* ``hrm_bus_kind``, ``hrm_box_mode``, ``hrm_rt_priority``, ``hrm_cpu_latency_us``: the options
  (:class:`~hrm_ctrl.hil.rig.BusKind`, :class:`~hrm_ctrl.hil.rig.BoxMode`, an ``int``);
* ``hrm_box_nodes``: the box's node map per bus (default the 36 motors of the drivers'
  ``box.toml``; override it in a test module for a smaller box);
* ``hrm_control``: ``[control]`` keys overriding the production settings (default none;
  a run with overrides is not a run at production settings; with ``--hrm-box inprocess``
  the TPDO tolerance is ``hrm run --sim``'s 25 cycles and the tension staleness 500 ms);
* ``hrm_box_config``: the box configuration file (``Path``) host and box share;
* ``hrm_box``: the started box (:class:`~hrm_ctrl.hil.rig.HilBox`: ``command``, ``ready``);
* ``hrm_host``: a :class:`~hrm_ctrl.hil.rig.HilHost` brought up on the box (the box's
  faults reset first), closed after the test; ``hrm_session``: its ``DriveSession``;
* ``hrm_fault``: fault injection (``sim_bus.faults`` grammar): ``hrm_fault(SPEC)`` now,
  ``hrm_fault.after(S, SPEC)`` in ``S`` seconds; every fault is undone after the test;
* ``hrm_arm_state``: ``hrm_arm_state()`` is the true arm now
  (:class:`~hrm_ctrl.hil.rig.ArmSnapshot`).
"""

from __future__ import annotations

import contextlib
import numbers
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from hrm_ctrl.hil.rig import ArmSnapshot, BoxMode, BusKind, HilBox, HilHost

BUS_CHOICES = ("auto", "virtual", "ipc", "udp_multicast", "socketcan")
BOX_CHOICES = ("process", "inprocess")


def bus_list(text: str) -> tuple[str, ...]:
    """``--hrm-bus`` value: one bus kind or several, comma-separated.

    >>> bus_list("ipc,udp_multicast")
    ('ipc', 'udp_multicast')
    >>> bus_list("auto,ipc")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: 'auto' is 'ipc' or 'udp_multicast': not both 'auto' and 'ipc'
    """
    import argparse

    kinds = tuple(k.strip() for k in text.split(","))
    bad = [k for k in kinds if k not in BUS_CHOICES]
    if bad or not kinds:
        raise argparse.ArgumentTypeError(
            f"unknown bus kind(s) {', '.join(bad) or repr(text)} "
            f"(choose from {', '.join(BUS_CHOICES)})"
        )
    # each kind once: the same bus twice would run every test twice on it
    twice = sorted({k for k in kinds if kinds.count(k) > 1})
    if twice:
        raise argparse.ArgumentTypeError(f"bus kind(s) given twice: {', '.join(twice)}")
    if "auto" in kinds:
        for k in ("ipc", "udp_multicast"):
            if k in kinds:
                raise argparse.ArgumentTypeError(
                    f"'auto' is 'ipc' or 'udp_multicast': not both 'auto' and {k!r}"
                )
    return kinds


def _int_in(text: str, hi: int, unit: str = "") -> int:
    """An option's integer in 0..hi, else argparse's usage error naming the range."""
    import argparse

    # ASCII digits only (int() would also take ' 3', '1_0', '+3' and other scripts' digits)
    value = int(text) if text.isascii() and text.isdigit() and len(text) <= 12 else -1
    if not 0 <= value <= hi:
        raise argparse.ArgumentTypeError(f"must be an integer in 0..{hi}{unit}, got {text!r}")
    return value


def rt_priority(text: str) -> int:
    """``--hrm-rt-priority``: an integer in 0..49 (box.toml's safe range)."""
    from drivers.realtime import REALTIME_PRIORITY_SAFE_MAX

    return _int_in(text, REALTIME_PRIORITY_SAFE_MAX)


def cpu_latency_us(text: str) -> int:
    """``--hrm-cpu-latency-us``: an integer in box.toml's range of ``cpu_wakeup_latency_us``."""
    from drivers.realtime import CPU_LATENCY_NO_REQUEST_US

    return _int_in(text, CPU_LATENCY_NO_REQUEST_US, " (us)")


@contextlib.contextmanager
def _one_line(fixture: str) -> Iterator[None]:
    """The stack's errors in a fixture's set-up or teardown (a bad ``hrm_box_nodes``, a box
    that would not start or has gone) as one line naming the fixture, not a traceback
    through the plugin's code."""
    from hrm_ctrl.errors import HrmError

    try:
        yield
    except HrmError as exc:
        pytest.fail(f"{fixture}: {exc}", pytrace=False)


@pytest.fixture(scope="session")
def hrm_cpu_latency_us(request: pytest.FixtureRequest) -> int | None:
    """``--hrm-cpu-latency-us``: the PM QoS CPU wake-up latency a session holds (None: none)."""
    value = request.config.getoption("--hrm-cpu-latency-us")
    return None if value is None else int(value)


@pytest.fixture(scope="session")
def hrm_rt_priority(request: pytest.FixtureRequest) -> int:
    """``--hrm-rt-priority``: SCHED_FIFO priority of session and box threads (0: off)."""
    return int(request.config.getoption("--hrm-rt-priority"))


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("hrm_hil", "hrm hardware-in-the-loop (simulated box)")
    group.addoption(
        "--hrm-bus",
        type=bus_list,
        default=None,
        metavar="KIND[,KIND...]",
        help=f"CAN buses between host and simulated box, one of {', '.join(BUS_CHOICES)} "
        "or several comma-separated (each HIL test runs on each); default: a module's "
        "hrm_buses marker, else auto (ipc if available, else udp_multicast)",
    )
    group.addoption(
        "--hrm-box",
        choices=BOX_CHOICES,
        default="process",
        help="the simulated box as its own process (default) or in the test process",
    )
    group.addoption(
        "--hrm-rt-priority",
        type=rt_priority,
        default=0,
        metavar="PRIORITY",
        help="SCHED_FIFO priority (1..49) of the host's session threads and of a box "
        "process (0: normal scheduling, the default)",
    )
    group.addoption(
        "--hrm-cpu-latency-us",
        type=cpu_latency_us,
        default=None,
        metavar="US",
        help="a PM QoS CPU wake-up latency each drive session holds (box.toml's "
        "cpu_wakeup_latency_us; 0: idle CPUs poll; default: none)",
    )


@pytest.fixture(scope="session")
def hrm_box_mode(request: pytest.FixtureRequest) -> BoxMode:
    """Where the simulated box runs (``--hrm-box``)."""
    from hrm_ctrl.hil.rig import BoxMode

    return BoxMode(request.config.getoption("--hrm-box"))


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "hrm_buses(*kinds): the bus kinds a HIL test runs on when --hrm-bus is not given",
    )


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Every test that uses the box runs once per bus kind (``--hrm-bus``, else its
    ``hrm_buses`` marker, else ``auto``); one box per module and kind."""
    if "hrm_bus_kind" not in metafunc.fixturenames:
        return
    kinds: tuple[str, ...] | None = metafunc.config.getoption("--hrm-bus")
    if kinds is None:
        marker = metafunc.definition.get_closest_marker("hrm_buses")
        kinds = ("auto",)
        if marker is not None:
            import argparse

            try:
                kinds = bus_list(",".join(marker.args))
            except argparse.ArgumentTypeError as exc:
                where = metafunc.definition.nodeid
                raise pytest.UsageError(f"{where}: hrm_buses marker: {exc}") from None
    metafunc.parametrize("hrm_bus_kind", kinds, indirect=True, scope="module")


@pytest.fixture(scope="session")
def hrm_bus_kind(request: pytest.FixtureRequest, hrm_box_mode: BoxMode) -> BusKind:
    """The buses between host and box (``--hrm-bus``); skips where they are unavailable."""
    from hrm_ctrl.hil.rig import BusKind, ipc_available, unavailable

    name = getattr(request, "param", "auto")
    if name == "auto":
        kind = BusKind.IPC if ipc_available() else BusKind.UDP_MULTICAST
    else:
        kind = BusKind(name)
    why = unavailable(kind, hrm_box_mode)
    if why is not None:
        pytest.skip(why)
    return kind


@pytest.fixture(scope="session")
def hrm_process_settings() -> Iterator[None]:
    """The interpreter settings every ``hrm`` process runs under (GIL switch interval)."""
    from drivers.realtime import process_settings

    with process_settings():
        yield


@pytest.fixture(scope="module")
def hrm_box_nodes() -> tuple[dict[str, int], ...]:
    """Rope motor -> node id, per bus (default: the drivers' 36-motor ``box.toml``)."""
    from hrm_ctrl.hil.rig import default_nodes

    return default_nodes()


@pytest.fixture(scope="module")
def hrm_control() -> dict[str, Any]:
    """``[control]`` keys overriding the production settings (default: none)."""
    return {}


@pytest.fixture(scope="module")
def hrm_box_config(
    hrm_bus_kind: BusKind,
    hrm_box_mode: BoxMode,
    hrm_box_nodes: tuple[dict[str, int], ...],
    hrm_control: dict[str, Any],
    hrm_rt_priority: int,
    hrm_cpu_latency_us: int | None,
    tmp_path_factory: pytest.TempPathFactory,
) -> Path:
    """The bus configuration host and box share (production ``[control]``; a box in the
    test process gets ``hrm run --sim``'s TPDO tolerance, with a warning)."""
    from hrm_ctrl.hil.rig import INPROCESS_CONTROL, BoxMode, write_box_toml

    control = dict(hrm_control)
    if hrm_rt_priority:  # scheduling, not a watchdog: still the production settings
        control.setdefault("realtime_priority", hrm_rt_priority)
    if hrm_cpu_latency_us is not None:  # the same
        control.setdefault("cpu_wakeup_latency_us", hrm_cpu_latency_us)
    if hrm_box_mode is BoxMode.INPROCESS:
        control = {**INPROCESS_CONTROL, **control}
        warnings.warn(
            f"--hrm-box inprocess: the box shares the host's interpreter: {INPROCESS_CONTROL}"
            " and tension staleness 500 ms, as hrm run --sim (not production settings)",
            stacklevel=1,
        )
    path = tmp_path_factory.mktemp("hrm-hil") / "box.toml"
    with _one_line("hrm_box_config"):
        write_box_toml(path, hrm_bus_kind, hrm_box_nodes, control)
    return path


@pytest.fixture(scope="module")
def hrm_box(
    hrm_box_config: Path, hrm_box_mode: BoxMode, hrm_rt_priority: int, hrm_process_settings: None
) -> Iterator[HilBox]:
    """The simulated box, started (its drives booted, its tension board running)."""
    from hrm_ctrl.hil.rig import start_box

    with _one_line("hrm_box"):
        box = start_box(hrm_box_config, hrm_box_mode, hrm_rt_priority)
    try:
        yield box
    finally:
        box.close()


#: ``hrm_fault.after``'s longest delay (an hour: longer than any test should run)
MAX_FAULT_DELAY_S = 3600.0


class FaultInjector:
    """``hrm_fault``: faults on the box now or later; undone after the test."""

    def __init__(self, box: HilBox) -> None:
        self.box = box
        self.applied: list[dict[str, Any]] = []
        self.errors: list[str] = []
        self._timers: list[threading.Timer] = []

    def __call__(self, spec: str) -> dict[str, Any]:
        """Apply ``spec`` now; the box's reply (``{"event": "fault", "fault": ...}``)."""
        from hrm_ctrl.hil.rig import fault
        from sim_bus.faults import parse_fault

        parse_fault(spec)  # a malformed spec: FaultSpecError here, whichever box it is
        reply = fault(self.box, spec)
        self.applied.append(reply)
        return reply

    def after(self, delay_s: float, spec: str) -> threading.Timer:
        """Apply ``spec`` in ``delay_s`` seconds (a started timer); a failure to apply it
        is raised after the test."""
        from sim_bus.faults import FaultSpecError, parse_fault

        parse_fault(spec)  # a bad spec fails here, not in the timer's thread
        # so does a bad delay (a timer given inf or a string dies in its thread, a fault
        # never applied; nan or a negative one applies at once)
        ok = isinstance(delay_s, numbers.Real) and not isinstance(delay_s, bool)
        if not ok or not 0.0 <= delay_s <= MAX_FAULT_DELAY_S:
            raise FaultSpecError(
                f"hrm_fault.after: delay must be a number of seconds in "
                f"0..{MAX_FAULT_DELAY_S:g}, got {delay_s!r}"
            )
        timer = threading.Timer(float(delay_s), self._later, args=(spec,))
        timer.daemon = True
        self._timers.append(timer)
        timer.start()
        return timer

    def _later(self, spec: str) -> None:
        try:
            self(spec)
        except Exception as exc:  # the timer's thread: kept for undo() to raise
            self.errors.append(f"fault {spec!r}: {exc}")

    def undo(self) -> None:
        """Cancel pending faults, undo every fault (``reset``); raise a delayed fault's
        failure."""
        from hrm_ctrl.errors import SimError
        from hrm_ctrl.hil.rig import REPLY_TIMEOUT_S, fault

        for timer in self._timers:
            timer.cancel()
            timer.join(REPLY_TIMEOUT_S)
        fault(self.box, "reset")
        if self.errors:
            raise SimError("; ".join(self.errors))


@pytest.fixture
def hrm_fault(hrm_box: HilBox) -> Iterator[FaultInjector]:
    """Fault injection on the box (``sim_bus.faults`` grammar)."""
    injector = FaultInjector(hrm_box)
    try:
        yield injector
    finally:
        with _one_line("hrm_fault"):
            injector.undo()


@pytest.fixture
def hrm_arm_state(hrm_box: HilBox) -> Any:
    """A callable: the true arm state now (:class:`~hrm_ctrl.hil.rig.ArmSnapshot`)."""
    from hrm_ctrl.hil.rig import arm_state

    def now() -> ArmSnapshot:
        return arm_state(hrm_box)

    return now


@pytest.fixture
def hrm_host(
    hrm_box: HilBox, hrm_box_mode: BoxMode, tmp_path: Path, hrm_process_settings: None
) -> Iterator[HilHost]:
    """The host stack brought up on the box (faults reset first); closed after the test.
    Its CAN logs and run record go to ``tmp_path``."""
    from hrm_ctrl.hil.rig import INPROCESS_TENSION_STALE_S, BoxMode, HilHost, fault

    with _one_line("hrm_host"):
        fault(hrm_box, "reset")
    stale = INPROCESS_TENSION_STALE_S if hrm_box_mode is BoxMode.INPROCESS else None
    host = HilHost(hrm_box, tmp_path, tension_stale_s=stale)
    try:
        yield host
    finally:
        host.close()


@pytest.fixture
def hrm_session(hrm_host: HilHost) -> Any:
    """The connected, brought-up :class:`drivers.session.DriveSession` of ``hrm_host``."""
    return hrm_host.session
