"""A simulated box in its own process: ``hrm sim --control`` as a child process.

The box answers ``sim_bus.runner``'s control commands (JSON lines in, JSON lines out) and
reports ``ready`` with its tension board's pseudo-terminal once its drives have booted.
The HIL fixtures (``hrm_ctrl.hil``) start one per test session;
:func:`hrm_ctrl.runtime.box.open_box` starts one for a block (:class:`ProcessBox`), and
for ``--sim`` (:func:`simulated_box_process`: the simulated box of a
:class:`~hrm_ctrl.runtime.simulated.SimulatedBox` whose ``wire`` is :data:`PROCESS_WIRE`).

Why its own process: in the host's interpreter the box's 36 drives, its tension board
and the host's control loop, receive threads and watches take turns on one GIL; beside two
CPU burners the box's TPDOs and the board's frames fell behind by more than the simulated
box's tolerances (``sim_bus.in_process``).  In a process of its own the box runs in
parallel with the host, and the scheduler sees two processes (each in a session of its
own: a group of its own where the kernel groups tasks by session).
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.errors import SimError
from hrm_ctrl.runtime.simulated import PROCESS_WIRE
from sim_bus.faults import has_control_character

if TYPE_CHECKING:
    import numpy as np

    from drivers.config import BoxConfig
    from hrm_ctrl.runtime.simulated import SimulatedBox

READY_TIMEOUT_S = 20.0  # the box process: start-up to its "ready" line (36 drives booted)
REPLY_TIMEOUT_S = 5.0  # one control command's reply
TRACE_TIMEOUT_S = 60.0  # the trace's reply: a run's positions at every SYNC, as JSON


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
        ready_timeout_s: float = READY_TIMEOUT_S,
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
            self.ready = self.wait("ready", timeout_s=ready_timeout_s)
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

    # the running simulated box's controls (``hrm_ctrl.runtime.simulated.SimControl``):
    # the control commands of ``sim_bus.runner``, answered by the box process

    def set_straight_fixture(self, on: bool) -> None:
        """Lay the arm into its zero fixture (``on``) or take it out."""
        self.command(f"fixture {'on' if on else 'off'}", "fixture")

    def record_trace(self, enabled: bool = True) -> None:
        """Start (clearing) or stop recording every drive's position at each SYNC."""
        self.command(f"trace {'on' if enabled else 'off'}", "trace")

    def trace(self) -> tuple[np.ndarray, np.ndarray]:
        """The recorded SYNC times (k,) and motor positions (k, n), as
        :meth:`sim_bus.box.SimBox.trace` gives them in the box process."""
        import numpy as np

        reply = self.command("trace", "trace", timeout_s=TRACE_TIMEOUT_S)
        times = np.asarray(reply["t_s"], dtype=float)
        n = int(self.ready["motors"])
        return times, np.asarray(reply["counts"], dtype=np.int64).reshape(len(times), n)

    def fault(self, spec: str) -> str:
        """Apply the fault ``spec`` now (``sim_bus.faults``); what was applied, in a line."""
        return str(self.command(f"fault {spec}", "fault")["fault"])

    def stop(self) -> None:
        """Stop the box (:meth:`close`)."""
        self.close()

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


#: the simulated box process: start-up (imports, 36 drives booted) to its ``ready`` line;
#: longer than the HIL's: a command waits for it on a machine that may be busy
SIM_READY_TIMEOUT_S = 60.0
SIM_CHANNEL_PREFIX = "hrm-sim-"  # the channels of --sim box processes: hrm-sim-<tag>-<bus>


def box_toml(config: BoxConfig) -> str:
    """The ``[control]``, ``[buses]`` and ``[drives]`` tables of ``config`` as a bus
    configuration file (what a box process needs; its own board and tracker replace
    ``[tension]`` and ``[tracker]``).

    >>> from drivers.config import box_config_from_dict, load_box_config
    >>> import tomllib
    >>> cfg = load_box_config(None)
    >>> again = box_config_from_dict(tomllib.loads(box_toml(cfg)), "again")
    >>> again.buses == cfg.buses, again.control == cfg.control
    (True, True)
    >>> from drivers import eds_path
    >>> drives = {"j01r0": {"device_file": str(eds_path())}}
    >>> own = box_config_from_dict({**cfg.to_dict(), "drives": drives}, "x")
    >>> box_config_from_dict(tomllib.loads(box_toml(own)), "again").drives == own.drives
    True
    >>> drives = {"sdo": {"0x60A8": 0xB50000}, "j01r0": {"identity": {"serial": 7}}}
    >>> own = box_config_from_dict({**cfg.to_dict(), "drives": drives}, "x")
    >>> box_config_from_dict(tomllib.loads(box_toml(own)), "again").drives == own.drives
    True
    """
    from drivers.config import DRIVE_KEYS

    doc = config.to_dict()
    lines = ["[control]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in doc["control"].items() if v is not None]
    for name, b in doc["buses"].items():
        lines += [f"[buses.{name}]"]
        lines += [f"{k} = {json.dumps(b[k])}" for k in ("interface", "channel", "bitrate")]
        if b["options"]:
            lines += [f"[buses.{name}.options]"]
            lines += [f"{k} = {json.dumps(v)}" for k, v in b["options"].items()]
        lines += [f"[buses.{name}.nodes]"]
        lines += [f"{k} = {v}" for k, v in b["nodes"].items()]
    drives = doc.get("drives", {})  # each drive's device file (absolute paths), overlay, identity
    if drives:
        lines += ["[drives]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in drives.items() if k in DRIVE_KEYS]
        for motor, table in drives.items():
            if motor not in DRIVE_KEYS:
                lines += [f"[drives.{motor}]"]
                lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    """A TOML value: a table inline (``{ "0x60A8" = 11862016 }``), else as JSON writes it."""
    if isinstance(value, dict):
        return (
            "{ " + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) + " }"
        )
    return json.dumps(value)


def start_box_process(
    config: BoxConfig, box: SimulatedBox, prog: str = "hrm"
) -> tuple[BoxConfig, BoxProcess]:
    """Start the simulated box of ``box`` in its own process (``hrm sim --control`` on
    :data:`PROCESS_WIRE` buses of fresh channels): ``config`` rewritten onto its buses,
    with its tension board (and tracker) as ports, and the process, which the caller
    stops (:meth:`BoxProcess.stop`; :func:`simulated_box_process` does for a block).

    The box simulates ``box.arm``: the robot description ``box.arm.physical`` was read from,
    its truth (passed as a truth file), its motors at ``box.arm.initial_counts``.  The
    simulated box's tolerances (:func:`~hrm_ctrl.runtime.simulated.sim_tolerances`) apply
    as in the host's interpreter, said on stderr: the box still shares this machine's CPUs.
    """
    from hrm_ctrl.runtime.simulated import sim_realtime_priority, sim_tolerances
    from sim_bus.ipc.cleanup import remove_stale_channels
    from sim_bus.truth import write_truth

    config, raised, tension = sim_tolerances(config)
    tag = uuid.uuid4().hex[:8]
    config = config.with_bus_kwargs(
        [
            {"interface": PROCESS_WIRE, "channel": f"{SIM_CHANNEL_PREFIX}{tag}-{b.name}"}
            for b in config.buses
        ]
    )
    remove_stale_channels(SIM_CHANNEL_PREFIX)  # of earlier runs killed before their end
    arm = box.arm
    # the box's files are read as it starts: gone once it is ready
    with tempfile.TemporaryDirectory(prefix="hrm-sim-") as folder:
        path = Path(folder, "box.toml")
        path.write_text(box_toml(config))
        extra: list[str] = []
        source = arm.physical.robot.source
        if not source.startswith("<"):  # a file, not the shipped description
            extra += ["--robot", source]
        if arm.truth is not None:
            write_truth(Path(folder, "truth.toml"), arm.truth)
            extra += ["--truth", str(Path(folder, "truth.toml"))]
        if arm.initial_counts is not None:
            extra += ["--initial-counts", ",".join(str(int(c)) for c in arm.initial_counts)]
        if arm.physics is not None:
            extra += ["--physics", arm.physics.describe()]
        if box.fixture:
            extra.append("--fixture")
        if box.tracker:
            extra.append("--tracker")
        process = BoxProcess(
            path,
            *extra,
            cpus=False,
            rt_priority=sim_realtime_priority(config),
            ready_timeout_s=SIM_READY_TIMEOUT_S,
        )
    try:
        motors = tuple(process.ready.get("motor_ids", ()))
        if motors != tuple(arm.physical.motor_ids):
            raise SimError(f"box process {path}: motors {motors[:3]}... are not the arm's")
        config = config.with_tension(port=str(process.ready["tension_port"]), **tension)
        if box.tracker:
            config = config.with_tracker(port=str(process.ready["tracker_port"]))
    except BaseException:
        process.close()
        raise
    if raised:
        print(
            f"{prog}: --sim: {', '.join(raised)} (the simulated box, in its own "
            "process, shares this machine's CPUs)",
            file=sys.stderr,
        )
    return config, process


@contextmanager
def simulated_box_process(
    config: BoxConfig, box: SimulatedBox, prog: str = "hrm"
) -> Iterator[tuple[BoxConfig, BoxProcess]]:
    """The simulated box of ``box`` in its own process (:func:`start_box_process`) for
    the block: closed on leaving, whatever ends the block."""
    config, process = start_box_process(config, box, prog)
    try:
        yield config, process
    finally:
        process.close()
