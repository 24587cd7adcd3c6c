"""Soak test of issue 13 (markers ``soak`` and ``slow``, not in the default run: ``pytest -m
soak tests/drivers/test_soak.py``; ``HRM_SOAK_S`` sets its length, default 600 s): the
36-drive 100 Hz cycle against the simulated box in its own process over ``hrm_ipc``, at the
production watchdogs of ``drivers/data/box.toml``, through the same :func:`run` that
``benchmarks/bench_drivers.py --soak`` uses.  Where ``SCHED_FIFO`` is allowed, the session's
threads and the box run under it at priority :data:`RT_PRIORITY` (``realtime_priority``, as
on a rig: a kernel thread at normal priority, DAMON's on the VM of ``BENCHMARKS.md``, no
longer holds the SYNC back), and a stall probe (``hrm_ctrl.hil.stalls``) watches every CPU.

It asserts the issue's targets, which a quiet 2-core machine is expected to meet and a loaded
one is not: no stop at all (no spurious watchdog), SYNC jitter p99 <= 0.5 ms, every frame on
the wire in the CAN logs (sent + received, none lost), host memory flat (RSS sampled every
10 s), host CPU <= 1 ms per cycle; and no cycle more than 2 ms late, no missing-feedback
node-cycle, except on a stall of the machine itself that the probe saw (a VM's vCPUs
descheduled: no program in it can be on time then; without the probe, none at all), or in
the cycle after one that such a stall made late, as late as that cycle's RPDOs hold its
SYNC (``hrm_ctrl.hil.stalls.explained`` with the supervisor's ``sync_delay_s``)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest

from drivers.cycle import MAX_NOTABLE_CYCLES

REPO = Path(__file__).resolve().parents[2]
SOAK_S = float(os.environ.get("HRM_SOAK_S", "600") or 600)
RSS_GROWTH_MB = 5.0  # flat: a leak of one small object per frame (7,800 frames/s) is far more
HOST_CPU_MS = 1.0  # per 10 ms cycle (issue 13)
JITTER_P99_MS = 0.5
LATE_MS = 2.0
RT_PRIORITY = 10


def fifo_allowed() -> bool:
    return subprocess.run(["chrt", "-f", "1", "true"], capture_output=True).returncode == 0


def bench() -> Any:
    spec = importlib.util.spec_from_file_location(
        "bench_drivers", REPO / "benchmarks" / "bench_drivers.py"
    )
    if spec is None or spec.loader is None:
        raise RuntimeError("benchmarks/bench_drivers.py not found")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.soak
@pytest.mark.slow
@pytest.mark.timeout(SOAK_S * 2 + 120)
def test_a_long_stream_against_a_box_process_meets_the_production_targets(
    tmp_path: Path, hrm_process_settings: None
) -> None:
    # hrm_process_settings: the GIL switch interval every hrm process runs with, as
    # bench_drivers.py's main sets it (without it the test ran at CPython's 5 ms)
    rt = RT_PRIORITY if fifo_allowed() else 0
    out = bench().run(
        SOAK_S,
        box_process=True,
        wire="ipc",
        rss_sample_s=10.0,
        work=tmp_path,
        rt_priority=rt,
        box_rt_priority=rt,
        stall_probe=bool(rt),
    )
    rss = out["rss_mb"]
    figures = {k: out[k] for k in ("stream", "cpu_per_cycle_ms", "box_core_fraction")}
    figures["rss_mb"] = {k: v for k, v in rss.items() if k != "samples"}
    figures["machine_stalls"] = out["machine_stalls"]
    print(json.dumps(figures))  # the run's figures, for `-rP` / `-s`
    stream = out["stream"]
    assert stream["completed"], stream["stop_causes"]
    assert stream["cycles"] == round(SOAK_S * 100)
    assert stream["jitter_ms"]["p99"] <= JITTER_P99_MS, stream["jitter_ms"]
    stalls = out["machine_stalls"]
    if stalls is not None and stalls["available"]:
        assert stalls["notable_cycles_kept"] < MAX_NOTABLE_CYCLES, stalls  # none dropped
        assert stalls["late_cycles_otherwise"] == 0, stalls
        assert stalls["missing_node_cycles_otherwise"] == 0, stalls
    else:
        assert stream["missing_feedback_node_cycles"] == 0, stream
        assert stream["sync_lateness_ms"]["max"] <= LATE_MS, stream["sync_lateness_ms"]
    logs = out["can_log_frames"]
    assert logs["lost"] == [0, 0]
    assert logs["in_logs"] == [
        s + r for s, r in zip(logs["sent"], logs["received_by_readers"], strict=True)
    ]
    assert len(rss["samples"]) >= SOAK_S // 10
    # from the moment the run's own setpoint table exists (built when the stream starts)
    assert rss["host_end"] - rss["host_after_table"] <= RSS_GROWTH_MB, rss
    assert out["cpu_per_cycle_ms"]["host_process"] <= HOST_CPU_MS, out["cpu_per_cycle_ms"]
