"""The reference a user would otherwise reach for: the same 36-drive 100 Hz cycle written
the way canopen's documentation shows it (its PDO maps and ``network.sync``).

Per bus one ``canopen.Network`` (``network.connect(...)``, which opens the python-can bus
and its ``can.Notifier``), one ``RemoteNode`` per drive from the EDS.  Bring-up: NMT reset,
boot-ups, the drives' SDO configuration and the CiA 402 state machine (this project's
``drivers.bringup`` on the canopen nodes, the host heartbeat not supervised: canopen has no
heartbeat producer for a master); then the documented cyclic part:

* ``node.tpdo[1]`` / ``node.rpdo[1]`` as PDO maps (``subscribe()``: canopen decodes every
  TPDO it receives, through its subscription path, into the map's variables);
* ``network.sync.start(period)`` (python-can's periodic send task) on every bus;
* every period: each node's ``rpdo[1]['Target position'].raw = target`` and
  ``rpdo[1].transmit()``, then each node's ``tpdo[1]['Statusword'].raw`` and
  ``['Position actual value'].raw`` read back (the feedback a controller needs).

Measured: process CPU per cycle (everything in the process: the loop, canopen's
notifiers, the SYNC task), cycles, and node-cycles whose TPDO did not change its
timestamp since the previous period.  :func:`run_reference` is called by
``bench_drivers.py`` in the same run as our control cycle, against the same box.
"""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Callable, Sequence
from typing import Any

import canopen
import numpy as np

from drivers import eds_path
from drivers.bringup import DriveLink, DriveSettings, configure_drive, disable, enable_operation
from drivers.config import BoxConfig
from drivers.protocol import cia301

BOOT_TIMEOUT_S = 10.0


def _parallel(
    fn: Callable[[DriveLink], Any], links: Sequence[DriveLink], timeout_s: float
) -> list[Any]:
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(links)) as pool:
        futures = [pool.submit(fn, link) for link in links]
        _done, busy = concurrent.futures.wait(futures, timeout=timeout_s)
        if busy:
            raise SystemExit(f"canopen reference: {len(busy)} drive(s) did not answer in time")
        return [f.result() for f in futures]


def run_reference(
    cfg: BoxConfig,
    actuation: Any,
    duration_s: float,
    table: Callable[[np.ndarray, float], np.ndarray],
) -> dict[str, Any]:
    """Bring up every drive with canopen, play ``table(actual, period)`` (cycles x motors
    counts) the documented way, disable; return the measured figures."""
    od = canopen.import_od(str(eds_path()))
    period_s = cfg.control.period_s
    order = {m: i for i, m in enumerate(actuation.motor_ids)}
    nets: list[canopen.Network] = []
    slots: list[tuple[canopen.RemoteNode, int]] = []  # node, global motor index
    links: list[DriveLink] = []
    try:
        for b in cfg.buses:
            net = canopen.Network()
            net.connect(**b.bus_kwargs())
            nets.append(net)
            for motor, nid in b.nodes.items():
                node = canopen.RemoteNode(nid, od)
                net.add_node(node)
                node.sdo.RESPONSE_TIMEOUT = cfg.control.sdo_timeout_s
                slots.append((node, order[motor]))
                links.append(DriveLink(node, b.name, motor))
        booted: set[int] = set()
        for node, i in slots:  # boot-ups may come before a wait_for_bootup would start

            def on_state(state: int, i: int = i) -> None:
                if state == cia301.NMT_STATE_BOOTUP:
                    booted.add(i)

            node.nmt.add_heartbeat_callback(on_state)
        for net in nets:
            net.nmt.send_command(cia301.NMT_RESET_NODE)
        t_end = time.monotonic() + BOOT_TIMEOUT_S
        while len(booted) < len(slots) and time.monotonic() < t_end:
            time.sleep(0.01)
        if len(booted) < len(slots):
            raise SystemExit(f"canopen reference: {len(slots) - len(booted)} drive(s) did not boot")
        ctl = cfg.control

        def settings(link: DriveLink) -> DriveSettings:
            i = order[link.motor]
            return DriveSettings(
                period_s=period_s,
                host_node_id=ctl.host_node_id,
                host_heartbeat_timeout_ms=0,  # not supervised: canopen sends no heartbeat
                node_heartbeat_ms=ctl.node_heartbeat_ms,
                counts_min=int(actuation.counts_min[i]),
                counts_max=int(actuation.counts_max[i]),
                following_error_window_counts=ctl.following_error_window_counts,
                quick_stop_option_code=ctl.quick_stop_option_code,
            )

        _parallel(lambda link: configure_drive(link, settings(link)), links, 60.0)
        for node, _i in slots:
            node.tpdo[1].subscribe()  # canopen decodes every TPDO1 from here on
        for net in nets:
            net.nmt.send_command(cia301.NMT_START_REMOTE_NODE)
        time.sleep(0.05)
        actual = np.zeros(len(actuation.motor_ids), dtype=np.int64)
        got = _parallel(lambda link: enable_operation(link, ctl.state_timeout_s), links, 60.0)
        for (_node, i), pos in zip(slots, got, strict=True):
            actual[i] = int(pos)
        targets = table(actual, period_s)
        rpdo = [(node.rpdo[1], i) for node, i in slots]
        for pdo_map, i in rpdo:  # the current position first (controlword: enable op.)
            pdo_map["Controlword"].raw = 0x000F
            pdo_map["Target position"].raw = int(actual[i])
        tpdo = [node.tpdo[1] for node, _i in slots]
        n = targets.shape[0]
        last_ts = [m.timestamp for m in tpdo]
        missing = 0
        positions = np.zeros(len(slots), dtype=np.int64)
        cpu0 = time.process_time()
        wall0 = time.monotonic()
        for net in nets:
            net.sync.start(period_s)
        t_next = time.monotonic() + period_s / 2  # mid-period: RPDOs between SYNCs
        for k in range(n):
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            t_next += period_s
            row = targets[k]
            for pdo_map, i in rpdo:
                pdo_map["Target position"].raw = int(row[i])
                pdo_map.transmit()
            for j, m in enumerate(tpdo):
                _sw = m["Statusword"].raw
                positions[j] = m["Position actual value"].raw
                if m.timestamp == last_ts[j]:
                    missing += 1
                last_ts[j] = m.timestamp
        for net in nets:
            net.sync.stop()
        cpu = time.process_time() - cpu0
        wall = time.monotonic() - wall0
        _parallel(lambda link: disable(link, ctl.state_timeout_s), links, 60.0)
        for net in nets:
            net.nmt.send_command(cia301.NMT_ENTER_PRE_OPERATIONAL)
        return {
            "cycles": n,
            "wall_s": round(wall, 3),
            "process_cpu_per_cycle_ms": round(cpu / n * 1000.0, 4),
            "missing_feedback_node_cycles": missing,
        }
    finally:
        for net in nets:
            try:
                net.disconnect()
            except Exception:  # best effort at the end of a benchmark
                pass
