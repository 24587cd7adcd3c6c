"""Hardware-in-the-loop rig (fixtures re-exported by conftest.py): the simulated box
in its own process (``hrm sim --control``), the host stack (``drivers.session.DriveSession`` +
tension watch) in the test process, over udp_multicast with ``hop_limit = 0`` (nothing
leaves the host).  SocketCAN vcan0/vcan1 are used the same way where the kernel has
them (skipped here with the reason)."""

from __future__ import annotations

import json
import os
import queue
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hrm_ctrl.formats.planfile import PlanDoc, read_plan

REPO = Path(__file__).resolve().parents[2]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: Host watchdog timing for the HIL runs.  Over udp_multicast every frame costs ~15-30 us
#: of Python per process (send / receive, and each process gets its own frames back), so on
#: this shared 2-core machine host and box each answer a SYNC in 2-10 ms, with stalls of
#: 50-100 ms when other jobs load both cores.  The production defaults (3 cycles, 350 ms)
#: would stop spuriously; every fault below is still detected, later.
HIL_CONTROL = {"missing_tpdo_cycles": 25, "heartbeat_timeout_ms": 1000, "bootup_timeout_s": 5.0}

#: The small box of the fault tests: few drives, light load, the motors the faults name.
FAULT_BUSES: tuple[dict[str, int], ...] = (
    {"j01r0": 1, "j05r1": 2, "j03r1": 3},
    {"j08r0": 4, "j08r2": 5},
)


def default_buses() -> tuple[dict[str, int], ...]:
    """The 36-motor node map of the drivers' default box.toml."""
    import tomllib

    from drivers import default_box_path

    doc = tomllib.loads(default_box_path().read_text())
    return tuple(dict(b["nodes"]) for b in doc["buses"].values())


def write_box_toml(path: Path, kind: str, buses: tuple[dict[str, int], ...]) -> Path:
    """A bus configuration (drivers' format) for ``kind`` = udp_multicast or socketcan."""
    lines = ["[control]", "rate_hz = 100"]
    lines += [f"{k} = {v}" for k, v in HIL_CONTROL.items()]
    pid = os.getpid() % 200 + 20
    for k, nodes in enumerate(buses):
        name = f"can{k}"
        if kind == "udp_multicast":
            lines += [
                f"[buses.{name}]",
                'interface = "udp_multicast"',
                f'channel = "239.75.{pid}.{k + 1}"',  # a group per bus; a port per bus too
                "bitrate = 1000000",
                f"[buses.{name}.options]",
                "hop_limit = 0",
                f"port = {_free_udp_port()}",
            ]
        else:
            lines += [
                f"[buses.{name}]",
                'interface = "socketcan"',
                f'channel = "vcan{k}"',
                "bitrate = 1000000",
            ]
        lines.append(f"[buses.{name}.nodes]")
        lines += [f"{m} = {n}" for m, n in nodes.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


class BoxProcess:
    """``hrm sim --control`` as a child process; JSON lines in, JSON lines out."""

    def __init__(self, config: Path, *extra: str) -> None:
        # stderr to a file, not a pipe nobody drains: a chatty box must not block
        self._stderr = tempfile.TemporaryFile("w+")
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "hrm_ctrl.cli",
                "sim",
                "--config",
                f"{config}",
                "--control",
                *extra,
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
            cwd=REPO,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        self.faults: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        self.ready = self.wait("ready", timeout_s=20.0)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                self.lines.put(json.loads(line))
            except json.JSONDecodeError:
                self.lines.put({"event": "garbage", "line": line})

    def wait(self, event: str, timeout_s: float = 5.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                obj = self.lines.get(timeout=left)
            except queue.Empty:
                break
            if obj.get("event") == event:
                return obj
            if obj.get("event") == "error":
                raise AssertionError(f"box process error: {obj['error']}")
        err = ""
        if self.proc.poll() is not None:  # the box died: say what it printed
            self._stderr.seek(0)
            err = self._stderr.read()
        raise AssertionError(f"box process: no '{event}' within {timeout_s} s {err}")

    def command(self, text: str, reply: str, timeout_s: float = 5.0) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()
        return self.wait(reply, timeout_s)

    def fault(self, spec: str) -> dict[str, Any]:
        return self.command(f"fault {spec}", "fault")

    def close(self) -> None:
        try:
            if self.proc.poll() is None and self.proc.stdin is not None:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=5.0)
        except (subprocess.TimeoutExpired, BrokenPipeError, OSError):
            self.proc.kill()
            self.proc.wait(timeout=5.0)
        finally:
            self._stderr.close()


def vcan_pair_available() -> bool:
    return all(Path(f"/sys/class/net/vcan{k}").exists() for k in (0, 1))


@pytest.fixture(scope="module", params=["udp_multicast", "socketcan"])
def bus_kind(request: pytest.FixtureRequest) -> str:
    """udp_multicast everywhere; SocketCAN vcan0/vcan1 where the kernel has them."""
    if request.param == "socketcan" and not vcan_pair_available():
        pytest.skip("SocketCAN: no vcan0/vcan1 on this kernel (modprobe vcan; ip link add ...)")
    return str(request.param)


@pytest.fixture(scope="module")
def full_config(bus_kind: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default 36-motor box on two buses of ``bus_kind``."""
    return write_box_toml(tmp_path_factory.mktemp("hil") / "box.toml", bus_kind, default_buses())


@pytest.fixture(scope="module")
def full_box(full_config: Path) -> Iterator[BoxProcess]:
    p = BoxProcess(full_config)
    try:
        yield p
    finally:
        p.close()


@pytest.fixture(scope="module")
def fault_config(bus_kind: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_box_toml(tmp_path_factory.mktemp("hil") / "box.toml", bus_kind, FAULT_BUSES)


@pytest.fixture(scope="module")
def fault_box(fault_config: Path) -> Iterator[BoxProcess]:
    p = BoxProcess(fault_config)
    try:
        yield p
    finally:
        p.close()


@pytest.fixture(scope="module")
def bent_pipe_plan(tmp_path_factory: pytest.TempPathFactory) -> PlanDoc:
    out = tmp_path_factory.mktemp("plan") / "bp.json"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "hrm_ctrl.cli",
            "plan",
            "--scenario",
            "bent-pipe",
            "--out",
            f"{out}",
        ],
        check=True,
        capture_output=True,
        timeout=60,
        cwd=REPO,
    )
    return read_plan(out)
