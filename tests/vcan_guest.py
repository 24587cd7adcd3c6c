"""SocketCAN tests on a kernel without vcan: they run in User-Mode-Linux guests.

A test needs vcan when one of its bus parameters (:data:`VCAN_PARAMS`) is ``"socketcan"``
(the ``can_backend`` fixture, ``test_canlog_durability``'s ``wire_kind``, the HIL plugin's
``hrm_bus_kind``).  Where the kernel has ``vcan0`` and ``vcan1`` they run here like every
other test.  Where it has not, ``HRM_VCAN_GUEST`` is not ``off`` (on by default,
:data:`SWITCH_DEFAULT`) and ``tools/vcan-guest/run-in-vcan-vm.sh``
can boot its guest (Debian's ``user-mode-linux``, ``kmod`` and ``iproute2`` installed),
the session moves them to its end and runs them in :func:`guest_count` guests side by side
(a guest has one CPU, and is kept on a host CPU of its own: :func:`guest_cpus`); with the
pytest-xdist workers (``-n 2``), each worker names them and leaves them out, and the controller
runs them once every worker has ended (:func:`run_guests_after_workers`),
each a pytest process with the same node ids over whole test modules (a module's fixtures
stay in one guest), and each test's reports (setup, call, teardown, stall reruns) come back
to this session as its own: the terminal, the summary and the exit status count them as if
they had run here, a failure with its traceback and captured output.  A test a guest gave
no report for (the guest did not boot, timed out, pytest in it ended early) fails, naming
why, with the tail of that guest's output.  With ``HRM_VCAN_GUEST=off``, or with a guest
that cannot be installed here, they skip, naming the reason.  A stall-tolerant test there is
rerun only on a pause of the guest its stall probe saw (every :data:`GUEST_PROBE_PERIOD_S`).

Each guest runs at ``SCHED_FIFO`` priority :data:`GUEST_RT_PRIORITY` unless ``VCANVM_RT``
is set (root only: elsewhere the runner says it runs at normal priority), and is stopped
after :data:`GUEST_TIMEOUT_S` (``VCANVM_TIMEOUT``); this session stops waiting for it
:data:`DEADLINE_MARGIN_S` later whatever the runner does.

>>> guest_args(["tests/a.py::t[socketcan]"], "not soak")[-4:]
['--stall-probe-period=0.02', '-m', 'not soak', 'tests/a.py::t[socketcan]']
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import IO, Any

import pytest

from drivers.realtime import SWITCH_INTERVAL_ENV

REPO = Path(__file__).resolve().parents[1]
RUNNER = REPO / "tools" / "vcan-guest" / "run-in-vcan-vm.sh"
UML_KERNEL = Path(os.environ.get("VCANVM_UML", "/usr/bin/linux.uml"))
#: the interfaces the SocketCAN tests use (a rig's bus k is vcan{k})
VCAN_INTERFACES = ("vcan0", "vcan1")
#: The stall probe's period in the guest (``hrm_ctrl.hil.stall_reruns``'s
#: ``--stall-probe-period``).  Waking every 1 ms (the host's) it took about 30 % of the
#: guest's one CPU from a busy loop, and 8 of the 9 fault tests' boxes missed their TPDOs
#: with it; every 20 ms it takes no measurable share (docs/hil.md), and a pause of the
#: guest (its UML process not scheduled: 500 ms stopped, 491 ms recorded) is recorded at
#: least 20 ms short of its length: evidence against the guest's shortest watchdog window,
#: 3 cycles at :data:`GUEST_RATE_HZ` (120 ms), for every pause of 140 ms or more.
GUEST_PROBE_PERIOD_S = 0.02
#: the control rate of the HIL rigs over SocketCAN in the guest (the fault tests' and the
#: bent-pipe plan's ``GUEST_CONTROL``): their 3-cycle TPDO watchdog spans 120 ms there
GUEST_RATE_HZ = 25
#: the parameters that choose a test's buses (``tests/conftest.py``'s ``can_backend``,
#: ``test_canlog_durability``'s ``wire_kind``, the HIL plugin's ``hrm_bus_kind``)
VCAN_PARAMS = ("can_backend", "wire_kind", "hrm_bus_kind")
#: SCHED_FIFO priority of the guest (the runner's ``VCANVM_RT``): under host load a guest
#: at normal priority misses 100 Hz cycles by tens of ms (tools/vcan-guest/README.md)
GUEST_RT_PRIORITY = 10
#: the GIL switch interval of every stack process in the guest (``HRM_SWITCH_INTERVAL_S``):
#: at the hosts' 0.2 ms a session's hand-overs took the CPU from the drives' box process
GUEST_SWITCH_INTERVAL_S = 1e-3
#: a guest's whole run at most, boot included (the runner's ``VCANVM_TIMEOUT``)
GUEST_TIMEOUT_S = 600
#: after a guest's timeout this session stops waiting for its runner, whatever it does
DEADLINE_MARGIN_S = 30.0
#: the environment variable pytest in the guest writes its reports to (one JSON a line)
REPORT_ENV = "HRM_VCAN_GUEST_REPORT"
#: ``on``: a guest runs the SocketCAN tests where the kernel has no vcan; ``off``: they skip
SWITCH_ENV = "HRM_VCAN_GUEST"
#: the switch unset: on wherever the guest's packages are installed (``.ci/run`` installs
#: them); two guests at ``SCHED_FIFO`` take a 2-core machine's CPUs for about two minutes
#: (docs/hil.md), which ``off`` spares
SWITCH_DEFAULT = "on"
#: how many guests run side by side (default :func:`guest_count`)
COUNT_ENV = "HRM_VCAN_GUESTS"
#: a guest's measured wall time per test of a module (the rest: :data:`DEFAULT_COST_S`),
#: to share the modules out evenly between the guests
MODULE_COST_S = {
    "tests/hil/test_plugin_plan.py": 60.0,
    "tests/hil/test_plugin_faults.py": 15.0,
    "tests/drivers/test_canlog_durability.py": 25.0,
}
DEFAULT_COST_S = 3.0
#: modules a guest runs after its others: the fault tests (``tests/hil/test_plugin_faults.py``)
#: run after the kill test in the same guest failed 8 of 8 there (the box's heartbeats and
#: tension frames 1-2 s old when the host's stream began, no pause of the guest seen) and
#: all 8 passed after the bus tests; the cause is not found (docs/hil.md)
RUN_LAST = ("tests/drivers/test_canlog_durability.py",)
POLL_S = 0.2
SHUTDOWN_TIMEOUT_S = 30.0
LOG_TAIL_LINES = 40
GUEST = pytest.StashKey["Guests"]()
#: pytest-xdist: a worker's output naming the SocketCAN tests it left to the guests
WORKER_OUTPUT_KEY = "hrm_vcan_tests"
#: pytest-xdist's controller: those tests (node id: location) for the guests
WORKER_TESTS = pytest.StashKey[dict[str, "Location"]]()
IN_GUEST = pytest.StashKey[bool]()


def vcan_interfaces_present(names: Sequence[str] = VCAN_INTERFACES) -> bool:
    """Whether the kernel has every interface of ``names`` (up or not)."""
    return all(Path(f"/sys/class/net/{n}").exists() for n in names)


def in_vcan_guest() -> bool:
    """Whether this process runs in the vcan guest (``guest-init.sh`` sets ``VCANVM_GUEST``):
    one CPU, 30-40 us per system call, python-can carrying 1,500-2,200 frames/s."""
    return os.environ.get("VCANVM_GUEST") == "1"


def needs_vcan(item: pytest.Item) -> bool:
    """Whether the test runs on SocketCAN vcan: one of its bus parameters
    (:data:`VCAN_PARAMS`) is ``"socketcan"``, and its drivers' rig is not the ``hrm_sim``
    wire (that combination skips: ``hrm_sim`` runs once, beside ``virtual``).  A
    ``"socketcan"`` that is data (a configuration string under test) needs no vcan."""
    callspec = getattr(item, "callspec", None)
    if callspec is None:
        return False
    params = callspec.params
    if params.get("bus_backend") == "hrm_sim":
        return False
    return any(params.get(name) == "socketcan" for name in VCAN_PARAMS)


def _has_tool(name: str) -> bool:
    return shutil.which(name) is not None or any(
        Path(d, name).is_file() for d in ("/usr/sbin", "/sbin")
    )


def guest_unavailable() -> str | None:
    """Why the SocketCAN tests cannot run in a guest here (None: they can)."""
    switch = os.environ.get(SWITCH_ENV, "").strip().lower() or SWITCH_DEFAULT
    if switch not in ("on", "off"):
        raise pytest.UsageError(f"{SWITCH_ENV}={os.environ[SWITCH_ENV]!r}: expected on or off")
    if switch == "off":
        return (
            f"{SWITCH_ENV}=off: they run in User-Mode-Linux guests unless it is off (docs/hil.md)"
        )
    if not sys.platform.startswith("linux"):
        return "the vcan guest is a Linux (User-Mode-Linux) guest"
    missing = [
        pkg
        for pkg, present in (
            ("user-mode-linux", UML_KERNEL.is_file()),
            ("kmod", _has_tool("modprobe")),
            ("iproute2", _has_tool("ip")),
        )
        if not present
    ]
    if missing:
        return (
            f"the vcan guest needs {', '.join(missing)} (Debian: apt-get install"
            f" --no-install-recommends {' '.join(missing)}; tools/vcan-guest/)"
        )
    return None


def guest_count(n_cpus: int | None = None) -> int:
    """How many guests run the SocketCAN tests side by side: ``HRM_VCAN_GUESTS``, else
    one per CPU up to two (a guest has one CPU; this session waits meanwhile).

    >>> guest_count(1), guest_count(2), guest_count(8)
    (1, 2, 2)
    """
    text = os.environ.get(COUNT_ENV, "")
    if text:
        try:
            n = int(text)
        except ValueError:
            raise pytest.UsageError(f"{COUNT_ENV}={text!r}: expected a whole number") from None
        if n < 1:
            raise pytest.UsageError(f"{COUNT_ENV}={text!r}: expected at least 1")
        return n
    if n_cpus is None:
        n_cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    return max(1, min(2, n_cpus))


def guest_cpus(n: int, cpus: Sequence[int] | None = None) -> list[int | None]:
    """The host CPU each of ``n`` guests is kept on: the k-th of this process's CPUs for
    guest k, None (any) where there are fewer CPUs than guests.  A guest's system call is
    a ptrace hand-over between its kernel's host process and its user process: kept on
    one CPU the hand-over is a context switch, across two a wake-up of the other CPU, and
    the kill test's guest took 76 s unpinned and 47 s pinned with a third of its CPU taken
    by a busier process (docs/hil.md).

    >>> guest_cpus(2, [0, 1]), guest_cpus(1, [3, 5]), guest_cpus(3, [0, 1])
    ([0, 1], [3], [None, None, None])
    """
    if cpus is None:
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if len(cpus) < n:
        return [None] * n
    return list(cpus[:n])


def _keep_on_cpu(cpu: int) -> None:
    """(in the guest's runner before it starts) keep it and its children on ``cpu``"""
    os.sched_setaffinity(0, {cpu})


def module_of(nodeid: str) -> str:
    """``'tests/a.py'`` of ``'tests/a.py::t[socketcan]'``."""
    return nodeid.split("::", 1)[0]


def share_out(nodeids: Sequence[str], n: int) -> list[list[str]]:
    """The node ids in at most ``n`` groups of whole modules, the modules' costs
    (:data:`MODULE_COST_S`) as even as the longest first onto the lightest group makes
    them; each group in the session's order, the modules of :data:`RUN_LAST` last.

    >>> share_out(["a.py::x", "b.py::y", "a.py::z"], 2)
    [['a.py::x', 'a.py::z'], ['b.py::y']]
    >>> share_out([f"{RUN_LAST[0]}::k", "b.py::y"], 1)
    [['b.py::y', 'tests/drivers/test_canlog_durability.py::k']]
    """
    order = {nodeid: k for k, nodeid in enumerate(nodeids)}
    modules: dict[str, list[str]] = {}
    for nodeid in nodeids:
        modules.setdefault(module_of(nodeid), []).append(nodeid)

    def cost(module: str) -> float:
        return MODULE_COST_S.get(module, DEFAULT_COST_S) * len(modules[module])

    groups: list[list[str]] = [[] for _ in range(max(1, n))]
    loads = [0.0] * len(groups)
    for module in sorted(modules, key=lambda m: (-cost(m), order[modules[m][0]])):
        k = loads.index(min(loads))
        groups[k] += modules[module]
        loads[k] += cost(module)

    def place(nodeid: str) -> tuple[bool, int]:
        return module_of(nodeid) in RUN_LAST, order[nodeid]

    return [sorted(g, key=place) for g in groups if g]


def guest_args(nodeids: Sequence[str], markexpr: str) -> list[str]:
    """The pytest command run in the guest: these node ids, this session's marker
    expression (the ini file's ``addopts`` apply there as here)."""
    # one process there (-n 0: pytest-xdist's workers, where asked for, are the host's)
    args = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-n", "0", "-rN"]
    # the stall probe wakes every GUEST_PROBE_PERIOD_S there, not every 1 ms
    args += [f"--stall-probe-period={GUEST_PROBE_PERIOD_S:g}"]
    if markexpr:
        args += ["-m", markexpr]
    return args + list(nodeids)


def guest_timeout_s() -> float:
    """A guest's whole run at most: ``VCANVM_TIMEOUT`` (the runner's), else
    :data:`GUEST_TIMEOUT_S`."""
    text = os.environ.get("VCANVM_TIMEOUT", "")
    try:
        return float(text) if text else GUEST_TIMEOUT_S
    except ValueError:
        raise pytest.UsageError(f"VCANVM_TIMEOUT={text!r}: expected seconds") from None


@dataclass
class GuestRun:
    """One guest running its share of this session's SocketCAN tests."""

    name: str
    nodeids: list[str]
    markexpr: str
    timeout_s: float = GUEST_TIMEOUT_S
    #: the host CPU the guest's processes are kept on (:func:`guest_cpus`), None: any
    cpu: int | None = None
    workdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="hrm-vcan-")))
    proc: subprocess.Popen[bytes] | None = None
    log: IO[bytes] | None = None
    started_s: float = 0.0
    ended_s: float | None = None
    timed_out: bool = False
    reports: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    finished: set[str] = field(default_factory=set)
    _rerun: set[str] = field(default_factory=set)
    _offset: int = 0

    @property
    def report_path(self) -> Path:
        return self.workdir / "reports.jsonl"

    @property
    def log_path(self) -> Path:
        return self.workdir / "guest.log"

    def start(self) -> None:
        env = dict(os.environ)
        env[REPORT_ENV] = str(self.report_path)
        env.setdefault("VCANVM_RT", str(GUEST_RT_PRIORITY))
        env["VCANVM_TIMEOUT"] = f"{self.timeout_s:g}"
        env["VCANVM_NO_INSTALL"] = "1"  # guest_unavailable() has checked the packages
        # the guest's system calls cost 30-40 us: its processes hand the interpreter lock
        # over less often (drivers.realtime.machine_switch_interval)
        env.setdefault(SWITCH_INTERVAL_ENV, f"{GUEST_SWITCH_INTERVAL_S:g}")
        env["VCANVM_RW"] = ":".join(filter(None, [env.get("VCANVM_RW"), str(self.workdir)]))
        env["VCANVM_IFACES"] = " ".join(VCAN_INTERFACES)
        self.report_path.touch()
        self.log = self.log_path.open("wb")
        self.started_s = time.monotonic()
        self.proc = subprocess.Popen(
            [str(RUNNER), "--", *guest_args(self.nodeids, self.markexpr)],
            cwd=REPO,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # a Ctrl-C of this session reaches it through stop()
            preexec_fn=None if self.cpu is None else partial(_keep_on_cpu, self.cpu),
        )

    def _read(self) -> None:
        with self.report_path.open("rb") as f:
            f.seek(self._offset)
            data = f.read()
        end = data.rfind(b"\n") + 1  # a line still being written waits for its end
        self._offset += end
        for line in data[:end].splitlines():
            rep = json.loads(line)
            nodeid = rep["nodeid"]
            self.reports.setdefault(nodeid, []).append(rep)
            # an attempt the stall-rerun plugin reran (a report "rerun") is followed by
            # its teardown and the next attempt: the test is done at a teardown after none
            if rep["outcome"] == "rerun":
                self._rerun.add(nodeid)
            elif rep["when"] == "teardown" and nodeid not in self._rerun:
                self.finished.add(nodeid)
            elif rep["when"] == "teardown":
                self._rerun.discard(nodeid)

    def running(self) -> bool:
        if self.proc is None or self.ended_s is not None:
            return False
        if self.proc.poll() is None:
            if time.monotonic() - self.started_s > self.timeout_s + DEADLINE_MARGIN_S:
                self.timed_out = True  # the runner's own timeout did not end it
                self.stop(remove=False)
                return False
            return True
        self.ended_s = time.monotonic()
        if self.log is not None:
            self.log.close()
        return False

    def wait_for(self, nodeid: str) -> list[dict[str, Any]] | None:
        """The guest's reports of ``nodeid`` once it has finished it (every attempt's setup,
        call and teardown; None: the guest ended, or passed its deadline, without it)."""
        while True:
            alive = self.running()
            self._read()
            if nodeid in self.finished:
                return self.reports[nodeid]
            if not alive:
                return None
            time.sleep(POLL_S)

    def stop(self, remove: bool = True) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()  # the runner stops the guest and removes its run dir
            try:
                self.proc.wait(SHUTDOWN_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, 9)  # the runner's group: UML and its relays
                self.proc.wait()
        if self.ended_s is None and self.proc is not None:
            self.ended_s = time.monotonic()
            if self.log is not None:
                self.log.close()
        if remove:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def why_no_report(self) -> str:
        rc = None if self.proc is None else self.proc.returncode
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            lines = []
        tail = "\n".join(lines[-LOG_TAIL_LINES:])
        if self.timed_out or rc == 124:
            why = (
                f"the vcan {self.name} passed its {self.timeout_s:g} s limit (VCANVM_TIMEOUT)"
                " and was stopped"
            )
        elif rc == 125:
            why = f"the vcan {self.name} failed before running pytest (runner exit status 125)"
        else:
            why = f"the vcan {self.name} ended without it (runner exit status {rc})"
        return f"no report from the vcan guest: {why}; its output ends:\n{tail}"

    def summary(self) -> str:
        if self.proc is not None:  # its last test reported: the guest is shutting down
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(SHUTDOWN_TIMEOUT_S)
            self.running()
        rc = None if self.proc is None else self.proc.returncode
        wall_s = (self.ended_s or time.monotonic()) - self.started_s
        return (
            f"vcan {self.name}: {len(self.finished)} of {len(self.nodeids)} SocketCAN tests "
            f"reported, {wall_s:.0f} s wall (boot included), runner exit status {rc}"
        )


@dataclass
class Guests:
    """This session's guests and which runs each SocketCAN test."""

    runs: list[GuestRun]
    started_s: float = 0.0

    def run_of(self, nodeid: str) -> GuestRun:
        return next(r for r in self.runs if nodeid in r.nodeids)

    def start(self) -> None:
        self.started_s = time.monotonic()
        for run in self.runs:
            run.start()

    @property
    def started(self) -> bool:
        return any(r.proc is not None for r in self.runs)

    def summary(self) -> list[str]:
        lines = [run.summary() for run in self.runs]
        ends = [r.ended_s for r in self.runs if r.ended_s is not None]
        if ends and len(ends) == len(self.runs):
            lines.append(
                f"vcan guests: {len(self.runs)} side by side, {max(ends) - self.started_s:.0f} s"
                " wall from the first boot to the last exit"
            )
        return lines

    def stop(self) -> None:
        for run in self.runs:
            run.stop()


def make_guests(config: pytest.Config, nodeids: Sequence[str]) -> Guests:
    """The guests that run ``nodeids`` (:func:`share_out`), each on a CPU of its own."""
    markexpr = str(config.getoption("markexpr") or "")
    timeout_s = guest_timeout_s()
    groups = share_out(nodeids, guest_count())
    return Guests(
        [
            GuestRun(f"guest {k + 1}", group, markexpr, timeout_s, cpu)
            for k, (group, cpu) in enumerate(zip(groups, guest_cpus(len(groups)), strict=True))
        ]
    )


def is_xdist_worker(config: pytest.Config) -> bool:
    """Whether this session is a pytest-xdist worker (xdist gives it ``workerinput``)."""
    return hasattr(config, "workerinput")


def split_for_guest(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``pytest_collection_modifyitems``: the SocketCAN tests to the end, run in the guests
    (nothing changes where the kernel has vcan or in a guest itself); where no guest can
    run they skip, naming why."""
    vcan = [item for item in items if needs_vcan(item)]
    if not vcan or vcan_interfaces_present():
        return
    why = guest_unavailable()
    if why is not None:
        reason = f"SocketCAN: no vcan0/vcan1 on this kernel and no vcan guest: {why}"
        for item in vcan:
            item.add_marker(pytest.mark.skip(reason=reason))
        return
    here = [item for item in items if not needs_vcan(item)]
    if is_xdist_worker(config):
        # pytest-xdist: the controller runs them once every worker has ended
        # (:func:`run_guests_after_workers`); each worker names them (all name the same)
        config.workeroutput[WORKER_OUTPUT_KEY] = [  # type: ignore[attr-defined]
            [item.nodeid, list(item.location)] for item in vcan
        ]
        items[:] = here
        return
    items[:] = here + vcan
    config.stash[GUEST] = make_guests(config, [item.nodeid for item in vcan])
    for item in vcan:
        item.stash[IN_GUEST] = True
        # the outer item waits for its own report only; its guest has its own deadline
        item.add_marker(pytest.mark.timeout(guest_timeout_s() + 2 * DEADLINE_MARGIN_S))


def run_in_guest(item: pytest.Item) -> bool | None:
    """``pytest_runtest_protocol``: a SocketCAN test's reports from its guest."""
    if not item.stash.get(IN_GUEST, False):
        return None
    guests = item.config.stash[GUEST]
    if not guests.started:
        # the fixtures the host's tests left set up (a box process of a module's other
        # bus kind) would take the guests' CPU: the guests' items use none of them
        item.session._setupstate.teardown_exact(None)
        guests.start()
    relay(item.config, guests.run_of(item.nodeid), item.nodeid, item.location)
    return True


Location = tuple[str, int | None, str]


def relay(config: pytest.Config, run: GuestRun, nodeid: str, location: Location) -> bool:
    """Wait for ``nodeid``'s reports from its guest and report them as this session's
    (a failed call naming why where there are none); whether it failed."""
    hook = config.hook
    hook.pytest_runtest_logstart(nodeid=nodeid, location=location)
    failed = False
    data = run.wait_for(nodeid)
    if data is None:
        for when in ("setup", "call", "teardown"):
            outcome = "failed" if when == "call" else "passed"
            longrepr = run.why_no_report() if when == "call" else None
            rep = pytest.TestReport(nodeid, location, {}, outcome, longrepr, when, duration=0.0)
            hook.pytest_runtest_logreport(report=rep)
        failed = True
    else:
        for d in data:
            rep = hook.pytest_report_from_serializable(config=config, data=d)
            if rep.skipped and isinstance(rep.longrepr, list):  # JSON made the tuple a list
                rep.longrepr = tuple(rep.longrepr)
            _relay_stall_rerun(config, rep)
            hook.pytest_runtest_logreport(report=rep)
            failed = failed or rep.failed
    hook.pytest_runtest_logfinish(nodeid=nodeid, location=location)
    return failed


def note_worker_tests(config: pytest.Config, workeroutput: dict[str, Any] | None) -> None:
    """``pytest_testnodedown`` (pytest-xdist's controller): the SocketCAN tests a worker
    left to the guests (:func:`split_for_guest`)."""
    named = (workeroutput or {}).get(WORKER_OUTPUT_KEY) or []
    tests = config.stash.setdefault(WORKER_TESTS, {})
    for nodeid, (path, lineno, name) in named:
        tests.setdefault(nodeid, (path, lineno, name))


def run_guests_after_workers(session: pytest.Session) -> None:
    """``pytest_sessionfinish`` (pytest-xdist's controller, every worker ended): the
    guests run the SocketCAN tests the workers named, their reports are this session's,
    and a failure among them fails the session."""
    config = session.config
    tests = config.stash.get(WORKER_TESTS, {})
    stopped = session.exitstatus == pytest.ExitCode.INTERRUPTED
    if not tests or stopped or session.shouldstop or session.shouldfail:
        return  # (an interrupted session, or one stopped at its first failures: -x)
    guests = config.stash[GUEST] = make_guests(config, list(tests))
    guests.start()
    failed = 0
    for run in guests.runs:
        for nodeid in run.nodeids:
            failed += relay(config, run, nodeid, tests[nodeid])
    session.testsfailed += failed
    if failed and session.exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def _relay_stall_rerun(config: pytest.Config, rep: pytest.TestReport) -> None:
    """A guest's stall rerun into this session's "stall reruns" summary."""
    if rep.outcome != "rerun":
        return
    from hrm_ctrl.hil.stall_reruns import RERUNS

    texts = [text for name, text in rep.sections if name == "stall probe"]
    config.stash.setdefault(RERUNS, []).extend(f"{rep.nodeid}: {t}" for t in texts)


class ReportWriter:
    """In the guest: every report of the session, one JSON line each, to the file the
    host named in :data:`REPORT_ENV`."""

    def __init__(self, config: pytest.Config, path: Path) -> None:
        self.config = config
        self.path = path

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        hook = self.config.hook
        data = hook.pytest_report_to_serializable(config=self.config, report=report)
        with self.path.open("a", encoding="utf-8") as f:
            f.write(json.dumps(data) + "\n")


def register_report_writer(config: pytest.Config) -> None:
    """``pytest_configure`` in the guest: the :class:`ReportWriter`; the variable leaves
    the environment (the processes the tests start, pytest among them, do not inherit it)."""
    path = os.environ.pop(REPORT_ENV, None)
    if path:
        config.pluginmanager.register(ReportWriter(config, Path(path)), "hrm-vcan-guest-report")


def summary_lines(config: pytest.Config) -> list[str]:
    """``pytest_terminal_summary``: what each guest ran, how long it took."""
    guests = config.stash.get(GUEST, None)
    return [] if guests is None or not guests.started else guests.summary()


def stop_guest(config: pytest.Config) -> None:
    """``pytest_unconfigure``: stop a guest still running (an interrupted session)."""
    guests = config.stash.get(GUEST, None)
    if guests is not None:
        guests.stop()
