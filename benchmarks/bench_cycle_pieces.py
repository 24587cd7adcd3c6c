"""Where the microseconds of one control cycle go, in place: ``bench_drivers.py``'s run
with the pieces of the cycle timed where they run (``time.perf_counter`` around each
method, in the real threads, on the real buses), not alone in a loop.

Each piece is a method of the stack (supervisor steps, the receive path, the sends, the
hrm_ipc calls); the wrapper adds about a microsecond a call.  Pieces a version of the code
does not have are left out, so the same script times the code before and after a change
(``PYTHONPATH`` on an export of the older commit).  Prints JSON: per piece the time per
cycle (all its calls), calls per cycle, median and p90 of one call, in microseconds, and
``bench_drivers.py``'s own figures of the run.

Run: ``python benchmarks/bench_cycle_pieces.py [bench_drivers options, e.g. --box-process
--duration 30 --bringups 1 --no-reference]``.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import importlib
import io
import json
import runpy
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
PIECES = {
    "drivers.safety.supervisor:Supervisor": (
        "_stream_cycle", "_watchdogs", "_send_syncs", "_checked", "_send_rpdos",
    ),
    "drivers.safety.monitor:NodeMonitor": ("check", "on_tpdo", "on_tpdo_batch", "on_heartbeat"),
    "drivers.receive:BusPoller": ("poll",),
    "drivers.receive:BusReceiver": ("on_batch", "on_message_received"),
    "drivers.bus:BusPort": ("send", "send_many", "send_batch"),
    "drivers.bus:TrafficLog": ("_drain", "_flush"),
    "drivers.cycle:BusLayout": ("rpdo_frames", "rpdo_batch"),
    "sim_bus.ipc:IpcBus": ("_recv_internal", "recv_batches", "_transmit"),
}  # fmt: skip


def wrap_all(times: dict[str, list[float]]) -> list[str]:
    """Time every piece that exists in this version of the code; return their names."""
    clock = time.perf_counter
    names = []
    for where, methods in PIECES.items():
        module, cls_name = where.split(":")
        try:
            cls = getattr(importlib.import_module(module), cls_name)
        except (ImportError, AttributeError):
            continue
        for name in methods:
            fn = cls.__dict__.get(name)
            if fn is None:
                continue
            key = f"{cls_name}.{name}"
            bucket = times[key]

            @functools.wraps(fn)
            def timed(*a: Any, _fn: Any = fn, _b: list[float] = bucket, **k: Any) -> Any:
                t = clock()
                try:
                    return _fn(*a, **k)
                finally:
                    _b.append(clock() - t)

            setattr(cls, name, timed)
            names.append(key)
    return names


def main() -> None:
    sys.path.insert(0, str(HERE))
    times: dict[str, list[float]] = collections.defaultdict(list)
    names = wrap_all(times)
    sys.argv = ["bench_drivers.py", *sys.argv[1:]]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        runpy.run_path(str(HERE / "bench_drivers.py"), run_name="__main__")
    run = json.loads(out.getvalue())
    n = max(1, len(times.get("Supervisor._stream_cycle", ())))
    pieces = {}
    for key in names:
        v = np.array(times.get(key, ()), dtype=float) * 1e6
        if len(v) == 0:
            continue
        pieces[key] = {
            "us_per_cycle": round(float(v.sum()) / n, 1),
            "calls_per_cycle": round(len(v) / n, 2),
            "median_us": round(float(np.median(v)), 1),
            "p90_us": round(float(np.percentile(v, 90)), 1),
        }
    pieces = dict(sorted(pieces.items(), key=lambda kv: -kv[1]["us_per_cycle"]))
    print(
        json.dumps(
            {
                "benchmark": "bench_cycle_pieces",
                "cycles": n,
                "pieces": pieces,
                "stream": run["stream"],
                "cpu_per_cycle_ms": run["cpu_per_cycle_ms"],
                "box_core_fraction": run["box_core_fraction"],
                "setup": run["setup"],
                "machine": run["machine"],
                "loadavg": run["loadavg"],
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
