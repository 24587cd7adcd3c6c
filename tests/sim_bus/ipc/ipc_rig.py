"""What the hrm_ipc tests share: frames, draining an end, an end in a child process, a
raw connection to an end's socket."""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import can
import pytest

from sim_bus.ipc import (
    IpcBus,
)

ROOT = Path(__file__).resolve().parents[3]  # the repository


def frame(cob: int, n: int = 8, fill: int = 0) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes([fill] * n), is_extended_id=False)


def drain(bus: IpcBus, n: int, timeout_s: float = 5.0) -> list[can.Message]:
    out: list[can.Message] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        m = bus.recv(timeout=0.2)
        if m is not None:
            out.append(m)
    return out


CHILD = textwrap.dedent(
    """
    import sys, can
    bus = can.Bus(interface="hrm_ipc", channel="kid", directory=sys.argv[1])
    print("ready", flush=True)
    if sys.argv[2] == "echo":
        m = bus.recv(timeout=20.0)
        bus.send_many([can.Message(arbitration_id=m.arbitration_id + 1, data=m.data,
                                   is_extended_id=m.is_extended_id)] * 3)
        print("sent", flush=True)
    if sys.argv[2] == "burst":
        sys.stdin.readline()  # the parent is listening
        for k in range(50):
            bus.send_many([can.Message(arbitration_id=(36 * k + i) % 0x800, data=[k, i],
                                       is_extended_id=False) for i in range(36)])
        for k in range(200):
            bus.send(can.Message(arbitration_id=k, data=[k], is_extended_id=False))
        print("sent", flush=True)
    sys.stdin.read()          # wait until the parent closes stdin (or kills us)
    bus.shutdown()
    """
)


def child(folder: str, mode: str) -> subprocess.Popen[str]:
    p = subprocess.Popen(
        [sys.executable, "-c", CHILD, folder, mode],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    ready: list[str] = []
    t = threading.Thread(target=lambda: ready.append(p.stdout.readline()), daemon=True)
    t.start()
    t.join(60.0)
    if ready != ["ready\n"]:
        p.kill()
        p.wait(10.0)
        pytest.fail(f"child did not come up: {ready!r}")
    return p


def connect_raw(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    s.connect(str(path))
    return s
