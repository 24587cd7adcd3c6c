"""Benchmark of the CAN drivers: 36 drives on 2 buses at 100 Hz against the simulated box.

The default box configuration (36 rope motors, 2 buses) against the simulated box
(36 CiA 402 drive simulators), either in this interpreter on python-can ``virtual`` buses
(the default) or, with ``--box-process``, in a process of its own (``hrm sim``) over
``--wire ipc`` (``hrm_ipc``: Unix-domain datagrams, one per peer per batch), ``--wire
udp_multicast`` (hop_limit 0) or ``--wire socketcan`` (``--bus`` is the same option:
SocketCAN on ``vcan0`` and ``vcan1``; on a kernel without vcan in the vcan guest,
``tools/vcan-guest``).  ``--drives N`` runs the first N drives of the box (in turn from
each bus), the sine on their motors only: a machine that carries fewer frames than the
36 drives send (the vcan guest) is measured at the production rate with as many as it
carries.  Measured:

* bring-up of all drives (NMT reset → boot-ups → SDO configuration → CiA 402 to
  operation enabled), ``--bringups`` times;
* a ``--duration`` s stream of a sine on every motor: SYNC lateness against its
  deadline, period jitter (|SYNC-to-SYNC - T|) p50/p99/max, late cycles (SYNC > 2 ms
  after its deadline), skipped slots, missing-feedback node-cycles, host CPU per cycle
  by thread (supervisor, receive threads, CAN log writers) and of the whole process,
  the box's CPU (its process, as a fraction of a core), RSS at start and end;
* with ``--box-process``, in the same run against the same box: the same cycle written
  the way canopen's documentation shows (``bench_canopen_ref.py``), and the ratio of its
  process CPU per cycle to ours (``--no-reference`` to skip).

``--soak`` is a long stream (default 600 s) sampling RSS every 10 s, with the box in its
own process; ``tests/drivers/test_soak.py`` (marked slow) runs the same :func:`run`.

The watchdogs are the production settings of ``drivers/data/box.toml`` (3 cycles without
a TPDO, heartbeat timeout 350 ms): any spurious stop ends the run and is reported.
``--missing-tpdo-cycles`` / ``--heartbeat-timeout-ms`` relax them to measure a machine
that cannot keep up (missing TPDOs are counted either way).  CAN logs (.blf) are written
as in every run (``--no-log`` to skip); their frame counts are checked against what was
sent and received.

Run: ``python benchmarks/bench_drivers.py [--box-process [--wire ipc]] [--duration 60]``;
prints JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine

from drivers.config import BoxConfig, load_box_config
from drivers.cycle import LATE_THRESHOLD_S
from drivers.realtime import (
    CPU_LATENCY_NO_REQUEST_US,
    REALTIME_PRIORITY_SAFE_MAX,
    available_cpus,
    cpu_list,
    parse_cpus,
    process_settings,
    split_cpus,
)
from drivers.sources import TableSource
from hrm_ctrl.hil.stalls import StallProbe, explained, overlapping
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.runtime.box import NO_WATCHES, SessionOptions, open_box

WIRES = ("ipc", "udp_multicast", "socketcan")
VCAN_CHANNELS = ("vcan0", "vcan1")  # --wire socketcan: one per bus
RSS_SAMPLE_S = 10.0
BOX_READY_TIMEOUT_S = 30.0


def sine_table(
    actuation: Any,
    actual_counts: np.ndarray,
    period_s: float,
    duration_s: float,
    amplitude_deg: float = 5.0,
    freq_hz: float = 0.5,
    columns: np.ndarray | None = None,
) -> np.ndarray:
    """The arm from where it stands along a joint-space wave: joint j's angles
    ``A cos(phase_j) (1 - cos wt)`` and ``A sin(phase_j) (1 - cos wt)`` (from rest, at most
    2A), through the rope layer to every motor's counts, so the ropes stay consistent with
    one arm configuration as in a real plan (a wave per motor would strain the simulated
    arm's ropes against each other and make its rope inverse take the slow path).
    ``columns``: the rope layer's indices of the motors driven (``--drives``; None: all).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> tab = sine_table(act, np.zeros(36, dtype=np.int64), 0.01, 0.03)
    >>> tab.shape, bool((tab[0] != 0).any()), bool((np.abs(tab) < 2000).all())
    ((3, 36), True, True)
    """
    n = round(duration_s / period_s)
    t = np.arange(1, n + 1)[:, None] * period_s
    phase = np.linspace(0.0, np.pi, 12)[None, :]
    ramp = 1.0 - np.cos(2 * np.pi * freq_hz * t)
    A = np.radians(amplitude_deg)
    alpha, theta = A * np.cos(phase) * ramp, A * np.sin(phase) * ramp
    zero = actuation.counts_from_angles(np.zeros(12), np.zeros(12), check=False)
    counts = actuation.counts_from_angles(alpha, theta, check=False) - zero[None, :]
    if columns is not None:
        counts = counts[:, columns]
    return (actual_counts[None, :] + counts).astype(np.int64)


class SineSource(TableSource):
    """The :func:`sine_table` as a setpoint source."""

    name = "sine"

    def __init__(
        self, actuation: Any, duration_s: float, columns: np.ndarray | None = None
    ) -> None:
        super().__init__()
        self.actuation = actuation
        self.duration_s = duration_s
        self.columns = columns
        self.rss_after_table_mb: float | None = None

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.table = sine_table(
            self.actuation, actual_counts, period_s, self.duration_s, columns=self.columns
        )
        # the run's own data (60 000 x 36 counts for a soak, and what building them took)
        # is in the process from here on: "memory flat" is measured from this point
        self.rss_after_table_mb = rss_mb()


# ---------------------------------------------------------------- /proc readers
def thread_cpu() -> dict[str, float]:
    """CPU seconds of every thread of this process, by name (``name#tid`` when two
    threads share a name)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for t in threading.enumerate():
        try:
            with open(f"/proc/self/task/{t.native_id}/stat", encoding="ascii") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except (OSError, IndexError, ValueError):
            continue
        name = t.name if t.name not in out else f"{t.name}#{t.native_id}"
        out[name] = (int(fields[11]) + int(fields[12])) / tick
    return out


def proc_cpu_s(pid: int) -> float:
    """utime + stime of a process (all its threads), seconds."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int | str = "self") -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def role(thread: str) -> str:
    if thread.startswith("hrm-supervisor"):
        return "supervisor"
    if thread.startswith(("hrm-rx-", "Notifier")):
        return "receive"
    if thread.startswith("canlog-"):
        return "log_writers"
    if thread.startswith("simbox"):
        return "simulated_box"
    return "other"


# ---------------------------------------------------------------- the box
def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sk:
        sk.bind(("127.0.0.1", 0))
        return int(sk.getsockname()[1])


def wire_config(path: Path, cfg: BoxConfig, wire: str) -> list[dict[str, Any]]:
    """The box configuration on ``wire`` written to ``path`` (for ``hrm sim``); returns
    the host's ``can.Bus`` kwargs of every bus."""
    tag = f"{os.getpid()}-{uuid.uuid4().hex[:6]}"
    kwargs: list[dict[str, Any]] = []
    lines = ["[control]", f"rate_hz = {cfg.control.rate_hz}", ""]
    for k, b in enumerate(cfg.buses):
        if wire == "udp_multicast":
            group, port = f"239.74.{os.getpid() % 250}.{200 + k}", _free_port()
            kwargs.append(
                {"interface": "udp_multicast", "channel": group, "port": port, "hop_limit": 0}
            )
            lines += [f"[buses.{b.name}]", 'interface = "udp_multicast"', f'channel = "{group}"']
            lines += [f"bitrate = {b.bitrate}", f"[buses.{b.name}.options]", f"port = {port}"]
            lines += ["hop_limit = 0"]
        elif wire == "socketcan":
            channel = VCAN_CHANNELS[k]
            kwargs.append({"interface": "socketcan", "channel": channel})
            lines += [f"[buses.{b.name}]", 'interface = "socketcan"', f'channel = "{channel}"']
            lines += [f"bitrate = {b.bitrate}"]
        elif wire == "ipc":
            channel = f"bench-{tag}-{b.name}"
            kwargs.append({"interface": "hrm_ipc", "channel": channel})
            lines += [f"[buses.{b.name}]", 'interface = "hrm_ipc"', f'channel = "{channel}"']
            lines += [f"bitrate = {b.bitrate}"]
        else:
            raise SystemExit(f"--wire: unknown wire {wire!r} (one of {', '.join(WIRES)})")
        lines += [f"[buses.{b.name}.nodes]"]
        lines += [f"{m} = {n}" for m, n in b.nodes.items()] + [""]
    path.write_text("\n".join(lines))
    return kwargs


class BoxProcess:
    """``hrm sim --control`` in its own process (context manager): started, waited for
    its ``ready`` line, told ``quit`` at the end (killed if it does not go)."""

    def __init__(
        self,
        config_path: Path,
        rt_priority: int = 0,
        cpus: frozenset[int] | None = None,
        physics: str | None = None,
    ) -> None:
        # the whole box under SCHED_FIFO (every thread of it: what holds its interpreter
        # lock too) with ``chrt``, as a drive's firmware runs in real time; 0: normal
        chrt = ["chrt", "-f", str(rt_priority)] if rt_priority > 0 else []
        on = [] if cpus is None else ["--cpus", cpu_list(cpus)]
        on += [] if physics is None else ["--physics", physics]  # the arm's (sim_bus.physics)
        self.proc = subprocess.Popen(
            [*chrt, sys.executable, "-m", "hrm_ctrl.cli", "sim", "--config", str(config_path),
             "--control", *on],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        if self.proc.stdout is None:
            raise SystemExit("hrm sim: no stdout pipe")
        ready: list[dict[str, Any]] = []

        def read_ready() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                with contextlib.suppress(ValueError):
                    msg = json.loads(line)
                    if msg.get("event") == "ready":
                        ready.append(msg)
                        return

        reader = threading.Thread(target=read_ready, daemon=True)
        reader.start()
        reader.join(BOX_READY_TIMEOUT_S)
        if not ready:
            self.proc.kill()
            raise SystemExit(f"hrm sim did not report ready within {BOX_READY_TIMEOUT_S:g} s")
        self.ready = ready[0]

    @property
    def pid(self) -> int:
        return self.proc.pid

    def __enter__(self) -> BoxProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(OSError, ValueError):
            if self.proc.stdin is not None:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)


def first_drives(cfg: BoxConfig, n: int) -> BoxConfig:
    """``cfg`` with its first ``n`` drives only, taken in turn from each bus (each bus's in
    its own order); a one-line SystemExit when ``n`` is out of 1..all.

    >>> cfg = first_drives(load_box_config(None), 5)
    >>> [len(b.nodes) for b in cfg.buses]
    [3, 2]
    """
    total = sum(len(b.nodes) for b in cfg.buses)
    if not 1 <= n <= total:
        raise SystemExit(f"bench_drivers: --drives must be in 1..{total}, got {n}")
    per_bus = [list(b.nodes.items()) for b in cfg.buses]
    keep: list[list[tuple[str, int]]] = [[] for _ in per_bus]
    k = 0
    while sum(len(x) for x in keep) < n:
        bus = k % len(per_bus)
        if len(keep[bus]) < len(per_bus[bus]):
            keep[bus].append(per_bus[bus][len(keep[bus])])
        k += 1
    buses = tuple(
        dataclasses.replace(b, nodes=dict(nodes))
        for b, nodes in zip(cfg.buses, keep, strict=True)
        if nodes
    )
    return dataclasses.replace(cfg, buses=buses)


def ms(v: Any) -> Any:
    return None if v is None else round(float(v) * 1000.0, 3)


# ---------------------------------------------------------------- the run
def run(
    duration_s: float,
    box_process: bool = False,
    wire: str = "ipc",
    bringups: int = 1,
    log: bool = True,
    reference: bool = False,
    missing_tpdo_cycles: int | None = None,
    heartbeat_timeout_ms: int | None = None,
    rt_priority: int = 0,
    box_rt_priority: int = 0,
    rss_sample_s: float | None = None,
    work: Path | None = None,
    cpus: tuple[frozenset[int], frozenset[int]] | str | None = "auto",
    stall_probe: bool = False,
    cpu_latency_us: int | None = None,
    box_physics: str | None = None,
    drives: int | None = None,
    rate_hz: float | None = None,
) -> dict[str, Any]:
    """One benchmark run (what ``main`` prints; the soak test asserts on it).  ``cpus``:
    (host, box) CPU sets for a box process (the host's session threads and the box kept
    apart, as separate hardware is), ``"auto"`` :func:`drivers.realtime.split_cpus`, None
    anywhere."""
    split = (split_cpus() if cpus == "auto" else cpus) if box_process else None
    host_cpus, box_cpus = (None, None) if not isinstance(split, tuple) else split
    act = load_actuation(default_robot())
    cfg = load_box_config(None)
    rope: Any = act
    columns = None
    if drives is not None:
        from drivers.safety.subset import ActuationSubset

        cfg = first_drives(cfg, drives)
        motors = [m for b in cfg.buses for m in b.nodes]
        rope = ActuationSubset(act, motors)
        columns = np.array([act.motor_ids.index(m) for m in motors], dtype=np.int64)
    if rate_hz is not None:  # a machine too slow for the production rate (the vcan guest)
        cfg = cfg.with_control(rate_hz=rate_hz)
    work = Path(tempfile.mkdtemp(prefix="bench_drivers_")) if work is None else work
    if box_process:
        kwargs = wire_config(work / f"box_{wire}.toml", cfg, wire)
        box_ctx: Any = BoxProcess(
            work / f"box_{wire}.toml", box_rt_priority, box_cpus, physics=box_physics
        )
    else:
        from sim_bus.box import SimBox

        tag = uuid.uuid4().hex[:8]
        kwargs = [{"interface": "virtual", "channel": f"bench-{tag}-{b.name}"} for b in cfg.buses]
        box_ctx = None
    relaxed: dict[str, Any] = {}  # None: the production value of box.toml
    if missing_tpdo_cycles is not None:
        relaxed["missing_tpdo_cycles"] = missing_tpdo_cycles
    if heartbeat_timeout_ms is not None:
        relaxed["heartbeat_timeout_ms"] = heartbeat_timeout_ms
    if cpu_latency_us is not None:  # not a watchdog: still the production settings
        relaxed["cpu_wakeup_latency_us"] = cpu_latency_us

    cfg = cfg.with_bus_kwargs(kwargs).with_control(realtime_priority=rt_priority, **relaxed)
    if box_ctx is None:
        box_ctx = SimBox(cfg, actuation=act)
    log_dir = work if log else None
    bringup_s: list[float] = []
    rss: list[tuple[float, float, float | None]] = []  # (t_s, host MB, box MB)
    out: dict[str, Any] = {}
    with box_ctx as box:
        box_pid = box.pid if box_process else None
        for k in range(max(1, bringups)):
            options = SessionOptions(log_dir=log_dir, run_name=f"bench{k}", allow_uncalibrated=True)
            with contextlib.ExitStack() as opened:
                with process_settings(switch_interval_s=None, cpus=host_cpus):  # its threads
                    session = opened.enter_context(
                        open_box(cfg, rope, options, watches=NO_WATCHES, bring_up=False)
                    ).session
                cpu_latency_held = session.cpu_latency.max_us if session.cpu_latency.held else None
                t = time.perf_counter()
                session.bring_up()
                bringup_s.append(time.perf_counter() - t)
                if k < bringups - 1:
                    continue
                stop_sampling = threading.Event()
                t_start = time.monotonic()

                def sample(t_start: float = t_start, stop: Any = stop_sampling) -> None:
                    while True:
                        rss.append(
                            (
                                round(time.monotonic() - t_start, 1),
                                rss_mb(),
                                None if box_pid is None else rss_mb(box_pid),
                            )
                        )
                        if stop.wait(rss_sample_s or 1e9):
                            return

                sampler = threading.Thread(target=sample, name="bench-rss", daemon=True)
                sampler.start()
                cpu0 = thread_cpu()
                proc0 = time.process_time()
                box_cpu0 = proc_cpu_s(box_pid) if box_pid is not None else box.cpu_s
                wall0 = time.monotonic()
                probe = StallProbe(sorted(available_cpus()) if stall_probe else [])
                source = SineSource(act, duration_s, columns)
                with probe:
                    result = session.stream(source, raise_on_stop=False)
                wall = time.monotonic() - wall0
                box_cpu = (proc_cpu_s(box_pid) if box_pid is not None else box.cpu_s) - box_cpu0
                proc_cpu = time.process_time() - proc0
                cpu1 = thread_cpu()
                stop_sampling.set()
                sampler.join(5.0)
                rss.append((round(time.monotonic() - t_start, 1), rss_mb(),
                            None if box_pid is None else rss_mb(box_pid)))  # fmt: skip
            record = json.loads(session.record_path.read_text()) if session.record_path else None
            sync_delay_s = session.supervisor.sync_delay_s
            sent = [p.n_sent for p in session._ports]  # after close: every frame of the session
            readers = [net.notifier for net in session._networks]
            echoes = [r.traffic.echoes_dropped for r in session._receivers]
        if reference:
            from bench_canopen_ref import run_reference

            ref_box0 = proc_cpu_s(box_pid) if box_pid is not None else 0.0
            ref = run_reference(
                cfg,
                rope,
                duration_s,
                lambda a, p: sine_table(act, a, p, duration_s, columns=columns),
            )
            if box_pid is not None and ref["wall_s"] > 0:
                ref["box_core_fraction"] = round(
                    (proc_cpu_s(box_pid) - ref_box0) / ref["wall_s"], 3
                )
            out["canopen_reference"] = ref
    s = result.stats
    n = max(1, result.cycles)
    per_thread = {
        name: round((cpu1[name] - cpu0.get(name, 0.0)) / n * 1000.0, 4)
        for name in cpu1
        if name in cpu0
    }
    by_role: dict[str, float] = {}
    for name, v in per_thread.items():
        by_role[role(name)] = round(by_role.get(role(name), 0.0) + v, 4)
    host_ms = proc_cpu / n * 1000.0
    if not box_process:  # the box's threads are in this process: take them out
        host_ms -= box_cpu / n * 1000.0
    frames_logged = None
    if record is not None:
        frames_logged = {
            "in_logs": record["can_log_frames"],
            "lost": record["can_log_lost"],
            "sent": sent,
            "received_by_readers": [getattr(r, "n_frames", None) for r in readers],
            "echoes_dropped": echoes,
        }
    out = {
        "benchmark": "bench_drivers",
        "machine": machine(),
        "loadavg": Path("/proc/loadavg").read_text().split()[:3],
        "setup": {
            "box_physics": box_physics,
            "drives": sum(len(b.nodes) for b in cfg.buses),
            "buses": len(cfg.buses),
            "box": f"own process (hrm sim), wire {wire}"
            if box_process
            else "same interpreter, python-can virtual",
            "rate_hz": cfg.control.rate_hz,
            "duration_s": duration_s,
            "can_logs": log,
            "missing_tpdo_cycles": cfg.control.missing_tpdo_cycles,
            "heartbeat_timeout_ms": cfg.control.heartbeat_timeout_ms,
            "realtime_scheduling": s.get("realtime_scheduling"),
            "box_sched_fifo_priority": box_rt_priority if box_process else None,
            "host_cpus": None if host_cpus is None else cpu_list(host_cpus),
            "box_cpus": None if box_cpus is None else cpu_list(box_cpus),
            "cpu_wakeup_latency_us": cpu_latency_held,
        },
        "bringup_s": [round(b, 3) for b in bringup_s],
        "stream": {
            "completed": result.completed,
            "cycles": result.cycles,
            "stop_causes": [x.text for x in result.causes][:5],
            "sync_lateness_ms": {
                "p50": ms(s.get("lateness_p50_s")),
                "p99": ms(s.get("lateness_p99_s")),
                "max": ms(s.get("lateness_max_s")),
            },
            "wake_lateness_ms": {  # the thread awake after its deadline (scheduling)
                "p99": ms(s.get("wake_lateness_p99_s")),
                "max": ms(s.get("wake_lateness_max_s")),
            },
            "jitter_ms": {
                "p50": ms(s.get("jitter_p50_s")),
                "p99": ms(s.get("jitter_p99_s")),
                "max": ms(s.get("jitter_max_s")),
            },
            "late_cycles_over_2ms": s.get("late_cycles"),
            "skipped_slots": s.get("skipped_slots"),
            "missing_feedback_node_cycles": s.get("missing_feedback_node_cycles"),
        },
        "cpu_per_cycle_ms": {
            "host_process": round(host_ms, 4),
            "by_role": by_role,
            "supervisor_thread_time_mean": ms(s.get("cpu_per_cycle_mean_s")),
            "supervisor_thread_time_p99": ms(s.get("cpu_per_cycle_p99_s")),
            "per_thread": per_thread,
        },
        "box_core_fraction": round(box_cpu / wall, 3) if wall > 0 else None,
        "rss_mb": {
            "host_start": round(rss[0][1], 1),
            "host_after_table": (
                None if source.rss_after_table_mb is None else round(source.rss_after_table_mb, 1)
            ),
            "host_end": round(rss[-1][1], 1),
            "box_start": None if rss[0][2] is None else round(rss[0][2], 1),
            "box_end": None if rss[-1][2] is None else round(rss[-1][2], 1),
            "samples": [(t, round(h, 1), None if b is None else round(b, 1)) for t, h, b in rss],
        },
        "can_log_frames": frames_logged,
        "machine_stalls": (
            machine_stalls(probe, s, cfg.control, result.causes, sync_delay_s)
            if stall_probe
            else None
        ),
        **out,
    }
    ref = out.get("canopen_reference")
    if ref is not None and host_ms > 0:
        ref["ratio_to_ours"] = round(ref["process_cpu_per_cycle_ms"] / host_ms, 2)
    out["targets"] = {
        "host_cpu_le_1ms": host_ms <= 1.0,
        "jitter_p99_le_0_5ms": (s.get("jitter_p99_s") or 1.0) <= 0.0005,
        "box_le_0_3_core": out["box_core_fraction"] is not None and out["box_core_fraction"] <= 0.3,
    }
    return out


def machine_stalls(
    probe: StallProbe,
    stats: dict[str, Any],
    control: Any,
    causes: Sequence[Any] = (),
    sync_delay_s: float = 0.0,
) -> dict[str, Any]:
    """What the stall probes saw during the stream, and which late or missing-feedback
    cycles fell on a stall of the machine itself (``hrm_ctrl.hil.stalls``; with the
    supervisor's ``sync_delay_s``, also the cycles a stall-late cycle's RPDOs held back)
    and which did not;
    for a stream that stopped, the stalls in the watchdog's window before the stop (the
    ``missing_tpdo_cycles`` + 1 periods a TPDO watchdog counts) by CPU."""
    out: dict[str, Any] = probe.summary()
    if not probe.available:
        return out
    period_s = 1.0 / control.rate_hz
    if causes:
        t_stop = min(c.time_s for c in causes)
        window = (control.missing_tpdo_cycles + 1) * period_s
        out["stalls_before_stop"] = [  # (cpu, s before the stop, ms)
            (st.cpu, round(t_stop - st.at_s, 4), round(st.late_s * 1000, 2))
            for st in overlapping(probe.stalls, t_stop - window, t_stop)
        ]
    notable = [tuple(e) for e in stats.get("notable_cycles", [])]
    on_stall = set(explained(notable, probe.stalls, period_s, sync_delay_s))
    late = [e for e in notable if e[1] > LATE_THRESHOLD_S]
    missing = [e for e in notable if e[2]]
    other = [e for e in notable if e not in on_stall]
    t0 = notable[0][0] if notable else 0.0
    out.update(
        {
            "late_cycles_on_machine_stalls": sum(1 for e in late if e in on_stall),
            "late_cycles_otherwise": sum(1 for e in late if e not in on_stall),
            "missing_node_cycles_on_machine_stalls": sum(e[2] for e in missing if e in on_stall),
            "missing_node_cycles_otherwise": sum(e[2] for e in missing if e not in on_stall),
            # of the late cycles no probe-seen stall explains: those whose supervisor woke
            # more than the threshold late (it waited to be run: a stall the probe missed,
            # or a thread at its priority or above on its CPU) and those that woke in time
            # and were late by what ran after waking (the stack's own work)
            "late_cycles_otherwise_woke_late": sum(
                1 for e in late if e not in on_stall and e[3] > LATE_THRESHOLD_S
            ),
            "notable_cycles_kept": len(notable),
            "sync_delay_ms": _ms(sync_delay_s),  # a SYNC's wait after the RPDOs before it
            "first_notable_monotonic_s": t0,  # to lay beside a kernel trace (clock mono)
            # (s after the first notable cycle, lateness ms, missing, woke ms, cpu ms)
            "otherwise_first": [
                (round(d - t0, 3), _ms(lt), m, _ms(woke), _ms(cpu))
                for d, lt, m, woke, cpu in other[:20]
            ],
        }
    )
    return out


def _ms(seconds: float) -> float:
    return round(seconds * 1000, 2)


def cycle_costs(reps: int = 2000) -> dict[str, Any]:
    """Host CPU (``thread_time``) of each piece of one control cycle, measured alone in
    this thread (the best of several rounds) over ``reps`` cycles with the real classes
    on ``hrm_ipc`` buses (the box's ends drained by another thread, not counted): where
    each microsecond goes.
    Runs on whichever ``drivers`` is on ``sys.path`` (the code before and after a change)."""
    import can

    from drivers.bus import BusPort, TrafficLog
    from drivers.cycle import BusLayout
    from drivers.protocol import cia301, cia402
    from drivers.receive import BusReceiver
    from drivers.safety.monitor import NodeMonitor
    from drivers.safety.supervisor import Supervisor

    cfg = load_box_config(None)
    act = load_actuation(default_robot())
    work = Path(tempfile.mkdtemp(prefix="bench_costs_"))
    order = {m: i for i, m in enumerate(act.motor_ids)}
    labels = [f"{m}" for m in act.motor_ids]
    mon = NodeMonitor(labels, 25, 2.0)
    mon.hb_time[:] = time.monotonic()
    tag = uuid.uuid4().hex[:8]
    host, box, logs, ports, layouts, receivers = [], [], [], [], [], []
    for k, b in enumerate(cfg.buses):
        ch = f"costs-{tag}-{b.name}"
        host.append(can.Bus(interface="hrm_ipc", channel=ch))
        box.append(can.Bus(interface="hrm_ipc", channel=ch))
        logs.append(TrafficLog(work / f"costs_{b.name}.blf", channel=k + 1))
        ports.append(BusPort(b.name, host[-1], logs[-1]))
        idx = np.array([order[m] for m in b.nodes], dtype=np.int64)
        layouts.append(BusLayout(ports[-1], idx, np.array(list(b.nodes.values()))))

        class Net:  # canopen's part: never reached by TPDOs and heartbeats here
            def notify(self, *args: Any) -> None: ...

        rx = BusReceiver(ports[-1], Net(), logs[-1], {n: labels[order[m]] for m, n in
                         b.nodes.items()}, mon.report, lambda: True)  # type: ignore[arg-type]  # fmt: skip
        for m, nid in b.nodes.items():
            if hasattr(rx, "tpdo"):
                rx.tpdo[cia301.COB_TPDO1 + nid] = (mon, order[m])
                rx.heartbeat[cia301.COB_NMT_ERROR_CONTROL + nid] = (mon, order[m])
            else:  # the code before: TPDOs by a handler, heartbeats through canopen
                import functools

                rx.fast[cia301.COB_TPDO1 + nid] = functools.partial(mon.on_tpdo, order[m])
        receivers.append(rx)
    merged = "_send_sync_and_rpdos" in Supervisor.__dict__
    stop = threading.Event()

    def drain() -> None:  # the box's ends: read what the host sends (not counted)
        while not stop.is_set():
            for bb in box:
                while bb.recv(0.0) is not None:
                    pass
            time.sleep(0.001)

    drainer = threading.Thread(target=drain, daemon=True)
    drainer.start()
    tg = ((act.counts_min + act.counts_max) // 2).astype(np.int64)
    mon.seq = 0
    for i in range(len(labels)):
        mon.on_tpdo(i, cia402.make_tpdo_feedback(1, 0x0237, 0).data, seq=0)
    out: dict[str, float] = {}

    rounds = 10  # the best of 10 rounds: a loaded machine only ever adds time

    def timed(name: str, fn: Any, per: int = 1) -> None:
        fn()
        best = math.inf
        for _ in range(rounds):
            t = time.thread_time()
            for _ in range(reps // rounds):
                fn()
            best = min(best, (time.thread_time() - t) / (reps // rounds))
        out[name] = round(best / per * 1e6, 2)

    timed("watchdogs (NodeMonitor.check, 36 nodes)", lambda: mon.check(1.0, 0, 0.0))
    timed("setpoint limits (check_counts)", lambda: act.check_counts(tg, previous=tg, dt_s=0.01))
    timed(
        "RPDO frames, 36 (rpdo_frames, 2 buses)",
        lambda: [lay.rpdo_frames(15, tg) for lay in layouts],
    )

    def send() -> None:
        for lay in layouts:
            frames = lay.rpdo_frames(cia402.CW_ENABLE_OPERATION, tg)
            if merged:
                lay.port.send_many([cia301.make_sync(), *frames])
            else:
                lay.port.send(cia301.make_sync())
                lay.port.send_many(frames)

    timed("SYNC + 36 RPDOs built, sent, logged (2 buses)", send)
    rpdo_cost = out["RPDO frames, 36 (rpdo_frames, 2 buses)"]
    out["SYNC + 36 RPDOs sent and logged, without building"] = round(
        out.pop("SYNC + 36 RPDOs built, sent, logged (2 buses)") - rpdo_cost, 2
    )
    tpdos = [
        [cia402.make_tpdo_feedback(int(n), 0x0237, 1000) for n in lay.node_ids] for lay in layouts
    ]
    hbs = [
        [cia301.make_heartbeat(int(n), cia301.NMT_STATE_OPERATIONAL) for n in lay.node_ids]
        for lay in layouts
    ]

    def receive_cost(batches: list[list[can.Message]]) -> float:
        total = 0.0
        readers = []
        for k in range(len(receivers)):
            try:
                from drivers.receive import BusReader

                reader = BusReader.__new__(BusReader)
                reader.bus = host[k]
                recv = reader._recv()
            except ImportError:  # before: can.Notifier's loop (bus.recv, lock, listeners)
                recv = host[k].recv
            readers.append(recv)
        lock = threading.Lock()
        best = math.inf
        for _ in range(reps // 10):
            total = 0.0
            for k, rx in enumerate(receivers):
                box[k].send_many(batches[k])
                recv, n = readers[k], len(batches[k])
                t = time.thread_time()
                if hasattr(rx, "tpdo"):
                    handle = rx.on_message_received
                    for _ in range(n):
                        handle(recv(1.0))
                else:
                    listeners = [rx]
                    for _ in range(n):
                        msg = recv(1.0)
                        with lock:
                            for cb in listeners:
                                cb(msg)
                total += time.thread_time() - t
            best = min(best, total)
        return best / sum(len(b) for b in batches) * 1e6

    out["receive one TPDO (bus recv + receive path + log hand-off)"] = round(receive_cost(tpdos), 2)
    out["receive one heartbeat"] = round(receive_cost(hbs), 2)
    for log in logs:  # the writer's work per frame (its thread drains the same queue)
        log._queue.clear()
    msgs = [m for batch in tpdos for m in batch]
    wlog = TrafficLog(work / "costs_writer.blf", channel=1)
    wlog._stopping = True  # its own writer thread ends: this thread drains the queue
    wlog._wake.set()
    wlog._thread.join(5.0)
    q = wlog._queue
    best = math.inf
    for _ in range(reps // 10):
        for m in msgs:
            m.timestamp = time.time()
            m.channel = 0
        q.extend(msgs * 10)  # a flush every 10 cycles, as FLUSH_S = 0.1 s does
        t = time.thread_time()
        wlog._drain()
        wlog._flush()
        best = min(best, time.thread_time() - t)
    out["log writer per frame (BLF: format, compress, write)"] = round(
        best / (10 * len(msgs)) * 1e6, 2
    )
    wlog._stopping = False
    wlog.stop()
    stop.set()
    drainer.join(2.0)
    for log in logs:
        log.stop()
    for bb in host + box:
        bb.shutdown()
    n_hb = 36 * cfg.control.period_s / (cfg.control.node_heartbeat_ms / 1000.0)
    per_cycle = (
        out["watchdogs (NodeMonitor.check, 36 nodes)"]
        + out["setpoint limits (check_counts)"]
        + rpdo_cost
        + out["SYNC + 36 RPDOs sent and logged, without building"]
        + 36 * out["receive one TPDO (bus recv + receive path + log hand-off)"]
        + n_hb * out["receive one heartbeat"]
        + (74 + n_hb) * out["log writer per frame (BLF: format, compress, write)"]
    )
    return {
        "items_us": out,
        "per_cycle_us": round(per_cycle, 1),
        "per_cycle_counts": {"tpdos": 36, "heartbeats": n_hb, "frames_logged": 74 + n_hb},
        "merged_sync_batch": merged,
        "loadavg": Path("/proc/loadavg").read_text().split()[:3],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=None, help="stream length (s; 60, soak 600)")
    ap.add_argument("--bringups", type=int, default=3, help="bring-ups to time")
    ap.add_argument(
        "--missing-tpdo-cycles", type=int, default=None,
        help="relax the TPDO watchdog (default: box.toml's production value, 3)",
    )  # fmt: skip
    ap.add_argument(
        "--heartbeat-timeout-ms", type=int, default=None,
        help="relax the heartbeat timeout (default: box.toml's production value, 350)",
    )  # fmt: skip
    ap.add_argument("--no-log", action="store_true", help="do not write CAN logs")
    ap.add_argument(
        "--rt-priority", type=int, default=0, metavar="PRIORITY",
        help="box.toml's realtime_priority: every thread of the drive session (readers, "
        "log writers, supervisor) under SCHED_FIFO at PRIORITY (0: off)",
    )  # fmt: skip
    ap.add_argument(
        "--host-rt-priority", type=int, default=0, metavar="PRIORITY",
        help="this whole process (every thread of the host: supervisor, receive, log writers) "
        "under SCHED_FIFO at PRIORITY, entered at the process start (0: off)",
    )  # fmt: skip
    ap.add_argument(
        "--box-rt-priority", type=int, default=0, metavar="PRIORITY",
        help="with --box-process: the box process under SCHED_FIFO at PRIORITY (chrt -f; 0: off)",
    )  # fmt: skip
    ap.add_argument(
        "--box-process", action="store_true", help="the simulated box in its own process"
    )
    ap.add_argument(
        "--wire", "--bus", dest="wire", choices=WIRES, default="ipc",
        help="with --box-process (ipc); socketcan: vcan0 and vcan1 (implies --box-process)",
    )  # fmt: skip
    ap.add_argument(
        "--rate-hz", type=float, default=None, metavar="HZ",
        help="the control rate (default: box.toml's production value, 100)",
    )  # fmt: skip
    ap.add_argument(
        "--drives", type=int, default=None, metavar="N",
        help="the first N drives of the box only, in turn from each bus (default: all 36)",
    )  # fmt: skip
    ap.add_argument(
        "--box-physics",
        default=None,
        metavar="EFFECTS",
        help="with --box-process: the simulated arm's physics (hrm sim --physics; default none)",
    )
    ap.add_argument(
        "--sim-process", action="store_true", help="= --box-process --wire udp_multicast"
    )
    ap.add_argument("--no-reference", action="store_true", help="skip the canopen reference cycle")
    ap.add_argument(
        "--cpus", default="auto", metavar="HOST/BOX",
        help="with --box-process: CPU lists of the host's session threads and of the box, "
        "e.g. 0/1; 'auto' (default): the box on the highest CPU, the host on the others; "
        "'any': no affinity",
    )  # fmt: skip
    ap.add_argument("--soak", action="store_true", help="a long run, RSS sampled every 10 s")
    ap.add_argument(
        "--stall-probe", action="store_true",
        help="a SCHED_FIFO prober on every CPU during the stream (hrm_ctrl.hil.stalls): which "
        "late or missing-feedback cycles fell on a stall of the machine itself (on with --soak)",
    )  # fmt: skip
    ap.add_argument(
        "--cpu-latency-us", type=int, default=None, metavar="US",
        help="box.toml's cpu_wakeup_latency_us: a PM QoS CPU wake-up latency the session "
        "holds (0: idle CPUs poll instead of halting; default: none)",
    )  # fmt: skip
    ap.add_argument(
        "--costs", action="store_true", help="only the CPU of each piece of one cycle (us)"
    )
    args = ap.parse_args()
    if args.costs:
        with process_settings():
            print(json.dumps(cycle_costs(), indent=1))
        return
    if args.sim_process:
        args.box_process, args.wire = True, "udp_multicast"
    if args.soak or args.wire == "socketcan":
        args.box_process = True
    duration = args.duration if args.duration is not None else (600.0 if args.soak else 60.0)
    for flag, prio in (
        ("--rt-priority", args.rt_priority),
        ("--host-rt-priority", args.host_rt_priority),
        ("--box-rt-priority", args.box_rt_priority),
    ):
        if not 0 <= prio <= REALTIME_PRIORITY_SAFE_MAX:  # box.toml's safe range
            print(
                f"bench_drivers: {flag} must be in 0..{REALTIME_PRIORITY_SAFE_MAX}, got {prio}",
                file=sys.stderr,
            )
            raise SystemExit(2)
    if args.cpu_latency_us is not None and not (
        0 <= args.cpu_latency_us <= CPU_LATENCY_NO_REQUEST_US
    ):
        print(
            f"bench_drivers: --cpu-latency-us must be in 0..{CPU_LATENCY_NO_REQUEST_US}, "
            f"got {args.cpu_latency_us}",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if not (duration > 0 and np.isfinite(duration)):
        print(f"bench_drivers: --duration must be > 0 s, got {duration}", file=sys.stderr)
        raise SystemExit(2)
    with process_settings(realtime_priority=args.host_rt_priority) as applied:
        if args.host_rt_priority and not applied.realtime_granted:
            print(f"bench_drivers: --host-rt-priority: {applied.realtime_refusal}", file=sys.stderr)
            raise SystemExit(2)
        out = _run_from(args, duration)
        out["setup"]["host_sched_fifo_priority"] = args.host_rt_priority
    if not args.soak:
        out["rss_mb"].pop("samples")
    print(json.dumps(out, indent=1))


def _run_from(args: argparse.Namespace, duration: float) -> dict[str, Any]:
    return run(
        duration,
        box_process=args.box_process,
        wire=args.wire,
        bringups=1 if args.soak else args.bringups,
        log=not args.no_log,
        reference=args.box_process and not args.no_reference,
        missing_tpdo_cycles=args.missing_tpdo_cycles,
        heartbeat_timeout_ms=args.heartbeat_timeout_ms,
        rt_priority=args.rt_priority,
        box_rt_priority=args.box_rt_priority,
        rss_sample_s=RSS_SAMPLE_S if args.soak else None,
        cpus=_cpus_arg(args.cpus),
        stall_probe=args.stall_probe or args.soak,
        cpu_latency_us=args.cpu_latency_us,
        box_physics=args.box_physics,
        drives=args.drives,
        rate_hz=args.rate_hz,
    )


def _cpus_arg(text: str) -> tuple[frozenset[int], frozenset[int]] | str | None:
    if text in ("auto", "any"):
        return "auto" if text == "auto" else None
    host, sep, box = text.partition("/")
    if not sep:
        raise SystemExit("bench_drivers: --cpus takes HOST/BOX CPU lists, 'auto' or 'any'")
    return parse_cpus(host, "--cpus HOST"), parse_cpus(box, "--cpus BOX")


if __name__ == "__main__":
    main()  # the process entry: process_settings (GIL switch interval as `hrm` sets it) inside
