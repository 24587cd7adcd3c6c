"""Benchmark of the simulated box: CPU of 36 drives at 100 Hz, and the wire's timing.

A synthetic host thread brings every drive to operation enabled (SDO + NMT +
controlwords in the RPDO) and then, every 10 ms on a monotonic schedule,
sends a SYNC and then each node's RPDO for the next SYNC (a sine setpoint) on
both buses and drains the TPDOs.  Two runs:

* ``virtual``: the box on python-can virtual buses; ``box_cpu_fraction`` is the
  CPU time of the box's bus threads (``time.thread_time``) over wall time.
* ``drives``: the 36 drive simulators alone, fed their frames directly (no bus, no
  thread, one interpreter thread): CPU (``time.thread_time``) per 100 Hz cycle of 36
  RPDOs, a SYNC, every drive's timers, and a host heartbeat every 10th cycle; the least of
  :data:`DRIVE_REPEATS` runs of :data:`DRIVE_CYCLES` cycles (the box's cyclic work without
  the bus threads' wake-ups; ``--drives-only`` runs just this).
* ``hrm_sim``: the same on the simulated wire at 1 Mbit/s (the wire has no
  thread of its own: the box's and the host's threads run it as they send and
  receive, so its CPU is inside theirs); every delivered frame's lateness
  (delivery time minus the ideal end of its wire time) is recorded: p50 / p99 /
  max and how many were later than 0.5 ms.

Run: ``python benchmarks/bench_sim.py [--seconds 10] [--drives-only]``; prints JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import struct
import time
import uuid
from typing import Any

import can
import numpy as np

import drivers.protocol.cia301 as cia301
import drivers.protocol.cia402 as cia
from drivers.config import load_box_config
from drivers.realtime import process_settings
from sim_bus.box import SimBox
from sim_bus.drive import DriveSim

RATE_HZ = 100.0
DRIVE_CYCLES = 1000
DRIVE_REPEATS = 5
HOST_NODE = 127  # the heartbeat the drives watch (350 ms, as box.toml has it)


def _sdo(bus: can.BusABC, node: int, msg: can.Message, timeout_s: float = 1.0) -> bytes:
    bus.send(msg)
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        m = bus.recv(left)
        if m is not None and m.arbitration_id == 0x580 + node:
            return bytes(m.data)
    raise TimeoutError(f"node {node}: no SDO answer")


def _host(buses: list[can.BusABC], nodes: list[list[int]], seconds: float) -> dict[str, Any]:
    for bus, ids in zip(buses, nodes, strict=True):
        for n in ids:
            _sdo(
                bus, n, cia301.make_sdo_download_expedited(n, cia.OD_MODES_OF_OPERATION, 0, b"\x08")
            )
            _sdo(bus, n, cia301.make_sdo_download_expedited(n, 0x6065, 0, struct.pack("<I", 10**7)))
        bus.send(cia301.make_nmt(cia301.NMT_START_REMOTE_NODE, 0))
    cpu0 = time.thread_time()
    t0 = time.monotonic()
    k = 0
    tpdos = 0
    late = 0
    cws = [cia.CW_SHUTDOWN, cia.CW_SWITCH_ON, cia.CW_ENABLE_OPERATION]
    while True:
        k += 1
        deadline = t0 + k / RATE_HZ
        if deadline - t0 > seconds:
            break
        while (left := deadline - time.monotonic()) > 0:
            time.sleep(min(left, 0.002))
        if time.monotonic() - deadline > 0.002:
            late += 1
        # SYNC first, then the RPDOs it will apply at the next SYNC: on a priority-
        # arbitrated wire a SYNC (0x080) queued behind RPDOs (0x2xx) would overtake them.
        cw = cws[min(k - 1, 2)]
        target = int(20000 * math.sin(2 * math.pi * 0.5 * k / RATE_HZ)) if k > 3 else 0
        for bus, ids in zip(buses, nodes, strict=True):
            if k > 1:
                bus.send(cia301.make_sync())
            for n in ids:
                bus.send(cia.make_rpdo_target(n, cw, target))
        for bus in buses:
            while (m := bus.recv(0)) is not None:
                if 0x181 <= m.arbitration_id <= 0x1FF:
                    tpdos += 1
    return {
        "cycles": k - 1,
        "tpdos": tpdos,
        "late_cycles": late,
        "host_cpu_s": time.thread_time() - cpu0,
    }


def run(kind: str, seconds: float) -> dict[str, Any]:
    tag = uuid.uuid4().hex[:8]
    kwargs = [{"interface": kind, "channel": f"bench-{tag}-{i}"} for i in range(2)]
    cfg = load_box_config(None).with_bus_kwargs(kwargs)
    hosts = [can.Bus(**kw) for kw in kwargs]
    if kind == "hrm_sim":
        for h in hosts:
            h.wire.record_lateness(True)  # type: ignore[attr-defined]
    box = SimBox(cfg, tension_noise_N=0.0)
    box.start()
    try:
        nodes = [list(b.nodes.values()) for b in cfg.buses]
        proc0, wall0, box0 = time.process_time(), time.monotonic(), box.cpu_s
        host = _host(hosts, nodes, seconds)
        wall = time.monotonic() - wall0
        proc = time.process_time() - proc0
        box_cpu = box.cpu_s - box0
        states = {cia.decode_state(sw).name for sw in box.statuswords().values()}
        out: dict[str, Any] = {
            "interface": kind,
            "drives": len(box.drives),
            "rate_hz": RATE_HZ,
            "seconds": round(wall, 3),
            "box_cpu_fraction": round(box_cpu / wall, 4),
            "process_cpu_fraction": round(proc / wall, 4),
            "host_cpu_fraction": round(host["host_cpu_s"] / wall, 4),
            "cycles": host["cycles"],
            "tpdos_received": host["tpdos"],
            "tpdos_expected": (host["cycles"] - 1) * len(box.drives),  # SYNC from cycle 2
            "host_late_cycles": host["late_cycles"],
            "drive_states": sorted(states),
        }
        if kind == "hrm_sim":
            lat = np.concatenate([np.array(h.wire.lateness_log()) for h in hosts])  # type: ignore[attr-defined]
            out["wire_frames"] = int(lat.size)
            out["wire_late_p50_ms"] = round(float(np.percentile(lat, 50)) * 1e3, 4)
            out["wire_late_p99_ms"] = round(float(np.percentile(lat, 99)) * 1e3, 4)
            out["wire_late_max_ms"] = round(float(lat.max()) * 1e3, 4)
            out["wire_frames_late_over_0_5ms"] = int((lat > 0.5e-3).sum())
            out["wire_bus_load"] = [round(h.wire.bus_load(1.0), 4) for h in hosts]  # type: ignore[attr-defined]
            out["wire_frames_within_0_5ms_fraction"] = round(float((lat <= 0.5e-3).mean()), 4)
        return out
    finally:
        box.stop()
        for h in hosts:
            h.shutdown()


def _enabled_drives(n: int, sent: list[can.Message]) -> list[DriveSim]:
    """``n`` drives (node ids 1..18 per bus, as the box has them), configured by SDO as a
    session configures them and in operation enabled."""
    drives = []
    for k in range(n):
        node = k % 18 + 1
        d = DriveSim(node, sent.append, now=0.0)

        def sdo(index: int, sub: int, raw: bytes, d: DriveSim = d, node: int = node) -> None:
            d.handle(cia301.make_sdo_download_expedited(node, index, sub, raw), 0.0)

        d.handle(cia301.make_nmt(cia301.NMT_START_REMOTE_NODE, node), 0.0)
        sdo(cia.OD_MODES_OF_OPERATION, 0, b"\x08")
        sdo(cia301.OD_CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", (HOST_NODE << 16) | 350))
        sdo(cia301.OD_PRODUCER_HEARTBEAT_TIME, 0, struct.pack("<H", 100))
        for cw in (cia.CW_SHUTDOWN, cia.CW_SWITCH_ON, cia.CW_ENABLE_OPERATION):
            sdo(cia.OD_CONTROLWORD, 0, struct.pack("<H", cw))
        if d.state != cia.State402.OPERATION_ENABLED:
            raise RuntimeError(f"drive {node} did not reach operation enabled ({d.state.name})")
        drives.append(d)
    return drives


def drive_cycle_us(n: int = 36, cycles: int = DRIVE_CYCLES) -> float:
    """CPU (us) of one 100 Hz cycle of ``n`` drive simulators fed their frames directly."""
    sent: list[can.Message] = []
    drives = _enabled_drives(n, sent)
    sync = cia301.make_sync()
    heartbeat = cia301.make_heartbeat(HOST_NODE, cia301.NMT_STATE_OPERATIONAL)
    rpdos = [
        can.Message(arbitration_id=0x200 + d.node_id, data=bytes(6), is_extended_id=False)
        for d in drives
    ]
    t = 0.0
    cpu0 = time.thread_time()
    for k in range(cycles):
        t += 1.0 / RATE_HZ
        target = int(20000 * math.sin(2 * math.pi * 0.5 * t))
        data = struct.pack("<Hi", cia.CW_ENABLE_OPERATION, target)
        for d, rpdo in zip(drives, rpdos, strict=True):
            rpdo.data = bytearray(data)
            d.handle(rpdo, t)
        for d in drives:
            d.handle(sync, t)
        if k % 10 == 0:
            for d in drives:
                d.handle(heartbeat, t)
        for d in drives:
            d.tick(t, 1.0 / RATE_HZ)
            d.next_deadline()
        sent.clear()
    us = (time.thread_time() - cpu0) / cycles * 1e6
    stuck = [d.node_id for d in drives if d.state != cia.State402.OPERATION_ENABLED]
    if stuck:
        raise RuntimeError(f"drives {stuck} left operation enabled during the run")
    return us


def drives_run() -> dict[str, Any]:
    runs = [drive_cycle_us() for _ in range(DRIVE_REPEATS)]
    return {
        "drives_us_per_cycle_36": round(min(runs), 1),
        "drives_us_per_cycle_runs": [round(r, 1) for r in runs],
        "drive_cycles_per_run": DRIVE_CYCLES,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--drives-only", action="store_true", help="only the drives' CPU per cycle")
    args = ap.parse_args()
    drives = drives_run()
    if args.drives_only:
        load = round(os.getloadavg()[0], 2)
        print(json.dumps({"benchmark": "bench_sim", **drives, "load_average_1min": load}, indent=2))
        return
    results = [run("virtual", args.seconds), run("hrm_sim", args.seconds)]
    v, w = results
    summary = {
        "benchmark": "bench_sim",
        "box_cpu_fraction_36_drives_100hz": v["box_cpu_fraction"],
        "box_cpu_target": 0.30,
        "box_cpu_ok": v["box_cpu_fraction"] <= 0.30,
        "box_cpu_fraction_on_hrm_sim_wire": w["box_cpu_fraction"],
        **drives,
        "wire_late_p50_ms": w["wire_late_p50_ms"],
        "wire_late_p99_ms": w["wire_late_p99_ms"],
        "wire_late_max_ms": w["wire_late_max_ms"],
        "load_average_1min": round(os.getloadavg()[0], 2),
        "wire_late_target_ms": 0.5,
        "wire_timing_ok": w["wire_late_max_ms"] <= 0.5,
        "runs": results,
    }
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    with process_settings():  # the process entry: GIL switch interval as `hrm` sets it
        main()
