"""A simulated box in its own process: ``hrm sim --control`` as a child process.

The box answers ``sim_bus.runner``'s control commands (JSON lines in, JSON lines out) and
reports ``ready`` with its tension board's pseudo-terminal once its drives have booted.
The HIL fixtures (``hrm_ctrl.hil``) start one per test session;
:func:`hrm_ctrl.runtime.box.open_box` starts one for a block (:class:`ProcessBox`).
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hrm_ctrl.errors import SimError
from sim_bus.faults import has_control_character

READY_TIMEOUT_S = 20.0  # the box process: start-up to its "ready" line (36 drives booted)
REPLY_TIMEOUT_S = 5.0  # one control command's reply


@dataclass(frozen=True)
class ProcessBox:
    """A box process to start for a block of :func:`hrm_ctrl.runtime.box.open_box`: its
    bus configuration file (the session's configuration is loaded from the same file), on
    a CPU of its own (``cpus``), its threads under ``SCHED_FIFO`` at ``rt_priority`` (0:
    normal)."""

    config_path: Path
    cpus: bool = True
    rt_priority: int = 0

    def start(self) -> BoxProcess:
        return BoxProcess(self.config_path, cpus=self.cpus, rt_priority=self.rt_priority)


class BoxProcess:
    """``hrm sim --control`` as a child process; JSON lines in, JSON lines out
    (``sim_bus.runner``).  On a machine of two or more CPUs the box runs on the highest
    one (``hrm sim --cpus``, :func:`drivers.realtime.split_cpus`) and a host session on it
    (:func:`hrm_ctrl.runtime.box.open_box`, ``hrm_ctrl.hil.rig.HilHost``) keeps its threads
    on the others: separate hardware, as the drives are
    (``cpus=False``: anywhere).  ``rt_priority`` > 0: every box thread under
    ``SCHED_FIFO`` at it (``hrm sim --rt-priority``; the box fails to start where the
    process may not)."""

    def __init__(
        self,
        config_path: Path,
        *extra: str,
        cwd: Path | None = None,
        cpus: bool = True,
        rt_priority: int = 0,
    ) -> None:
        from drivers.realtime import cpu_list, split_cpus

        self.config_path = config_path
        split = split_cpus() if cpus else None
        self.host_cpus = None if split is None else split[0]
        if split is not None:
            extra = ("--cpus", cpu_list(split[1]), *extra)
        if rt_priority:
            extra = ("--rt-priority", str(rt_priority), *extra)
        # stderr to a file, not a pipe nobody drains: a chatty box must not block
        self._stderr = tempfile.TemporaryFile("w+")
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "hrm_ctrl.cli",
                "sim",
                "--config",
                f"{config_path}",
                "--control",
                *extra,
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
            cwd=cwd,
            # its own session: a terminal's Ctrl-C (SIGINT to the foreground process
            # group) reaches the test run, which stops the box itself (``quit``)
            start_new_session=True,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=10_000)
        threading.Thread(target=self._read, name="hil-box-stdout", daemon=True).start()
        try:
            self.ready = self.wait("ready", timeout_s=READY_TIMEOUT_S)
        except BaseException:
            self.close()
            raise

    def _read(self) -> None:
        out = self.proc.stdout
        if out is None:
            return
        for line in out:
            try:
                self.lines.put(json.loads(line), timeout=REPLY_TIMEOUT_S)
            except json.JSONDecodeError:
                self.lines.put({"event": "garbage", "line": line[:200]}, timeout=REPLY_TIMEOUT_S)
            except queue.Full:
                return

    def wait(self, event: str, timeout_s: float = REPLY_TIMEOUT_S) -> dict[str, Any]:
        """The next line whose ``event`` is ``event`` (others are dropped)."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                obj = self.lines.get(timeout=min(left, 0.25))
            except queue.Empty:
                if self.proc.poll() is not None and self.lines.empty():
                    break  # the box died: no reply will come
                continue
            if obj.get("event") == event:
                return obj
            if obj.get("event") == "error":
                raise SimError(f"box process {self.config_path}: {obj['error']}")
        if self.proc.poll() is not None:  # the box died: say so, and what it printed
            raise SimError(self._gone())
        raise SimError(f"box process {self.config_path}: no '{event}' within {timeout_s} s")

    def _gone(self) -> str:
        """The box process has exited: its status and the last lines it printed."""
        try:
            self._stderr.seek(0)
            err = " | ".join(self._stderr.read().strip().splitlines()[-3:])
        except ValueError:  # closed: the box was closed
            err = ""
        return f"box process {self.config_path}: exited (status {self.proc.returncode})" + (
            f": {err}" if err else ""
        )

    def command(self, text: str, reply: str, timeout_s: float = REPLY_TIMEOUT_S) -> dict[str, Any]:
        """Send one control command; its reply (one command at a time)."""
        if has_control_character(text):  # one command is one line
            raise SimError(f"box process {self.config_path}: control character in {text!r}")
        with self._lock:
            if self.proc.stdin is None or self.proc.poll() is not None:
                raise SimError(self._gone())
            self.proc.stdin.write(text + "\n")
            self.proc.stdin.flush()
            return self.wait(reply, timeout_s)

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
