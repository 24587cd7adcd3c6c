"""SocketCAN tests on a kernel without vcan: they run in a User-Mode-Linux guest.

A test needs vcan when one of its parameters is ``"socketcan"`` (the ``can_backend``
fixture, ``test_canlog_durability``'s ``wire_kind``, the HIL plugin's ``hrm_bus_kind``).
Where the kernel has ``vcan0`` and ``vcan1`` they run here like every other test.  Where
it has not, with ``HRM_VCAN_GUEST=on`` and ``tools/vcan-guest/run-in-vcan-vm.sh`` able to
boot its guest (Debian's ``user-mode-linux`` installed: ``/usr/bin/linux.uml``), the
session moves them to its end and runs them all in one guest, one pytest process inside it
with the same node ids, and each test's reports (setup, call, teardown, stall reruns) come
back to this session as its own: the terminal, the summary and the exit status count them
as if they had run here.  A test the guest gave no report for (the guest did not boot,
timed out, pytest in it ended early) fails, naming why, with the tail of the guest's
output.  Without ``HRM_VCAN_GUEST=on`` they skip, naming the reason: the guest's run does
not yet fit the suite's time or pass on a loaded 2-core machine (``docs/hil.md``).

The guest runs at ``SCHED_FIFO`` priority :data:`GUEST_RT_PRIORITY` unless
``VCANVM_RT`` is set (root only: elsewhere the runner says it runs at normal priority),
and is stopped after :data:`GUEST_TIMEOUT_S` unless ``VCANVM_TIMEOUT`` is set.

>>> guest_args(["tests/a.py::t[socketcan]"], "not soak")[-3:]
['-m', 'not soak', 'tests/a.py::t[socketcan]']
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
from pathlib import Path
from typing import IO, Any

import pytest

REPO = Path(__file__).resolve().parents[1]
RUNNER = REPO / "tools" / "vcan-guest" / "run-in-vcan-vm.sh"
UML_KERNEL = Path(os.environ.get("VCANVM_UML", "/usr/bin/linux.uml"))
#: the interfaces the SocketCAN tests use (a rig's bus k is vcan{k})
VCAN_INTERFACES = ("vcan0", "vcan1")
#: SCHED_FIFO priority of the guest (the runner's ``VCANVM_RT``): under host load a guest
#: at normal priority misses 100 Hz cycles by tens of ms (tools/vcan-guest/README.md)
GUEST_RT_PRIORITY = 10
#: the whole guest run at most (the runner's ``VCANVM_TIMEOUT``); CI's own limit is 20 min
GUEST_TIMEOUT_S = 900
#: the environment variable pytest in the guest writes its reports to (one JSON a line)
REPORT_ENV = "HRM_VCAN_GUEST_REPORT"
#: ``on``: run the SocketCAN tests in the guest where the kernel has no vcan (else they skip)
SWITCH_ENV = "HRM_VCAN_GUEST"
POLL_S = 0.2
SHUTDOWN_TIMEOUT_S = 30.0
LOG_TAIL_LINES = 40
GUEST = pytest.StashKey["GuestRun"]()
IN_GUEST = pytest.StashKey[bool]()


def vcan_interfaces_present(names: Sequence[str] = VCAN_INTERFACES) -> bool:
    """Whether the kernel has every interface of ``names`` (up or not)."""
    return all(Path(f"/sys/class/net/{n}").exists() for n in names)


def in_vcan_guest() -> bool:
    """Whether this process runs in the vcan guest (``guest-init.sh`` sets ``VCANVM_GUEST``):
    one CPU, 30-40 us per system call, python-can carrying 1,500-2,200 frames/s."""
    return os.environ.get("VCANVM_GUEST") == "1"


def needs_vcan(item: pytest.Item) -> bool:
    """Whether the test runs on SocketCAN vcan: one of its parameters is ``"socketcan"``."""
    callspec = getattr(item, "callspec", None)
    if callspec is None:
        return False
    return any(isinstance(v, str) and v == "socketcan" for v in callspec.params.values())


def guest_unavailable() -> str | None:
    """Why the SocketCAN tests cannot run in the guest here (None: they can)."""
    if os.environ.get(SWITCH_ENV, "").lower() != "on":
        return f"{SWITCH_ENV}=on runs them in a User-Mode-Linux guest (tools/vcan-guest/)"
    if not sys.platform.startswith("linux"):
        return "the vcan guest is a Linux (User-Mode-Linux) guest"
    if not UML_KERNEL.is_file():
        return (
            f"no {UML_KERNEL} (apt-get install --no-install-recommends user-mode-linux kmod:"
            " the SocketCAN tests then run in a vcan guest, tools/vcan-guest/)"
        )
    return None


def guest_args(nodeids: Sequence[str], markexpr: str) -> list[str]:
    """The pytest command run in the guest: these node ids, this session's marker
    expression (the ini file's ``addopts`` apply there as here)."""
    args = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-rN"]
    if markexpr:
        args += ["-m", markexpr]
    return args + list(nodeids)


@dataclass
class GuestRun:
    """One guest running the SocketCAN tests of this session, started at the first of them."""

    nodeids: list[str]
    markexpr: str
    workdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="hrm-vcan-")))
    proc: subprocess.Popen[bytes] | None = None
    log: IO[bytes] | None = None
    started_s: float = 0.0
    ended_s: float | None = None
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
        env.setdefault("VCANVM_TIMEOUT", str(GUEST_TIMEOUT_S))
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
            return True
        self.ended_s = time.monotonic()
        if self.log is not None:
            self.log.close()
        return False

    def wait_for(self, nodeid: str) -> list[dict[str, Any]] | None:
        """The guest's reports of ``nodeid`` once it has finished it (every attempt's setup,
        call and teardown; None: the guest ended without finishing it)."""
        while True:
            alive = self.running()
            self._read()
            if nodeid in self.finished:
                return self.reports[nodeid]
            if not alive:
                return None
            time.sleep(POLL_S)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()  # the runner stops the guest and removes its run dir
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.running()
        shutil.rmtree(self.workdir, ignore_errors=True)

    def why_no_report(self) -> str:
        rc = None if self.proc is None else self.proc.returncode
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            lines = []
        tail = "\n".join(lines[-LOG_TAIL_LINES:])
        return f"no report from the vcan guest (runner exit status {rc}); its output ends:\n{tail}"

    def summary(self) -> str:
        if self.proc is not None:  # its last test reported: the guest is shutting down
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(SHUTDOWN_TIMEOUT_S)
            self.running()
        rc = None if self.proc is None else self.proc.returncode
        wall_s = (self.ended_s or time.monotonic()) - self.started_s
        return (
            f"vcan guest: {len(self.finished)} of {len(self.nodeids)} SocketCAN tests "
            f"reported, {wall_s:.0f} s wall (boot included), runner exit status {rc}"
        )


def split_for_guest(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``pytest_collection_modifyitems``: the SocketCAN tests to the end, run in the guest
    (nothing changes where the kernel has vcan, in the guest itself, or without a guest)."""
    vcan = [item for item in items if needs_vcan(item)]
    if not vcan or vcan_interfaces_present() or guest_unavailable() is not None:
        return
    here = [item for item in items if not needs_vcan(item)]
    items[:] = here + vcan
    markexpr = str(config.getoption("markexpr") or "")
    config.stash[GUEST] = GuestRun([item.nodeid for item in vcan], markexpr)
    for item in vcan:
        item.stash[IN_GUEST] = True
        # the outer item waits for its own report only; the guest has its own limits
        item.add_marker(pytest.mark.timeout(GUEST_TIMEOUT_S + 60))


def run_in_guest(item: pytest.Item) -> bool | None:
    """``pytest_runtest_protocol``: a SocketCAN test's reports from the guest."""
    if not item.stash.get(IN_GUEST, False):
        return None
    run = item.config.stash[GUEST]
    if run.proc is None:
        # the fixtures the host's tests left set up (a box process of a module's other
        # bus kind) would take the guest's CPU: the guest's items use none of them
        item.session._setupstate.teardown_exact(None)
        run.start()
    ihook = item.ihook
    ihook.pytest_runtest_logstart(nodeid=item.nodeid, location=item.location)
    data = run.wait_for(item.nodeid)
    if data is None:
        for when in ("setup", "call", "teardown"):
            outcome = "failed" if when == "call" else "passed"
            longrepr = run.why_no_report() if when == "call" else None
            rep = pytest.TestReport(
                item.nodeid, item.location, {}, outcome, longrepr, when, duration=0.0
            )
            ihook.pytest_runtest_logreport(report=rep)
    else:
        for d in data:
            rep = item.config.hook.pytest_report_from_serializable(config=item.config, data=d)
            if rep.skipped and isinstance(rep.longrepr, list):  # JSON made the tuple a list
                rep.longrepr = tuple(rep.longrepr)
            _relay_stall_rerun(item.config, rep)
            ihook.pytest_runtest_logreport(report=rep)
    ihook.pytest_runtest_logfinish(nodeid=item.nodeid, location=item.location)
    return True


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


def summary_line(config: pytest.Config) -> str | None:
    """``pytest_terminal_summary``: what the guest ran, how long it took."""
    run = config.stash.get(GUEST, None)
    return None if run is None or run.proc is None else run.summary()


def stop_guest(config: pytest.Config) -> None:
    """``pytest_unconfigure``: stop a guest still running (an interrupted session)."""
    run = config.stash.get(GUEST, None)
    if run is not None:
        run.stop()
