"""The CAN log writer's cost per frame (``drivers.bus.TrafficLog``): a control cycle's
frames (36 TPDOs received, 36 RPDOs and a SYNC sent) handed over as ``can.Message``
objects and as batches (``log_batch``), written in this thread (queue drain, formatting,
compression, the write(2) and the header) with a flush every 10 cycles as ``FLUSH_S``
does.  Thread CPU time, best of ``--reps``, in microseconds per frame.

The same script times the code before and after a change of the writer (``PYTHONPATH`` on
an export of the older commit).  Prints JSON.

Run: ``python benchmarks/bench_canlog.py [--reps 30] [--format blf]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _machine import machine  # noqa: E402

CYCLES_PER_FLUSH = 10  # FLUSH_S = 0.1 s at 100 Hz


def cycle_messages(t0: float) -> list[can.Message]:
    """One cycle's frames: 36 TPDOs (8 bytes), a SYNC and 36 RPDOs (6 bytes)."""
    rx = [
        can.Message(timestamp=t0, arbitration_id=0x181 + k, data=bytes(range(k, k + 8)),
                    is_extended_id=False)
        for k in range(36)
    ]  # fmt: skip
    tx = [can.Message(timestamp=t0, arbitration_id=0x080, is_extended_id=False, is_rx=False)]
    tx += [
        can.Message(timestamp=t0, arbitration_id=0x201 + k, data=bytes([k] * 6),
                    is_extended_id=False, is_rx=False)
        for k in range(36)
    ]  # fmt: skip
    return rx + tx


def cycle_batches(t0: float) -> list[tuple[np.ndarray, bool]]:
    """The same cycle as two record arrays (received, sent)."""
    from drivers.protocol.batch import FRAME_DTYPE

    msgs = cycle_messages(t0)
    out = []
    for part, is_rx in ((msgs[:36], True), (msgs[36:], False)):
        a = np.zeros(len(part), FRAME_DTYPE)
        a["timestamp"] = [m.timestamp for m in part]
        a["id"] = [m.arbitration_id for m in part]
        a["dlc"] = [m.dlc for m in part]
        a["data"] = [list(bytes(m.data).ljust(8, b"\0")) for m in part]
        out.append((a, is_rx))
    return out


def writer_cost(fmt: str, reps: int, as_batch: bool, work: Path) -> float:
    """Microseconds of this thread's CPU per frame to drain and flush 10 cycles."""
    from drivers.bus import TrafficLog

    log = TrafficLog(work / f"bench_{as_batch}.{fmt}", channel=1)
    log._stopping = True  # its own writer thread ends: this thread drains the queue
    log._wake.set()
    log._thread.join(5.0)
    q = log._queue
    best = math.inf
    n = 0
    for _ in range(reps):
        t0 = time.time()
        if as_batch:
            entries: list[Any] = []
            for _c in range(CYCLES_PER_FLUSH):
                entries += [(a.copy(), rx) for a, rx in cycle_batches(t0)]
            n = sum(len(a) for a, _rx in entries)
        else:
            entries = [m for _c in range(CYCLES_PER_FLUSH) for m in cycle_messages(t0)]
            n = len(entries)
        q.extend(entries)
        t = time.thread_time()
        log._drain()
        log._flush()
        best = min(best, time.thread_time() - t)
    log._stopping = False
    log.stop()
    assert log.write_errors == 0, log.first_error
    assert len(list(can.LogReader(log.path))) == reps * n
    return best / n * 1e6


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reps", type=int, default=30)
    p.add_argument("--format", default="blf")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        out = {
            "format": args.format,
            "frames_per_flush": CYCLES_PER_FLUSH * 73,
            "us_per_frame_messages": round(writer_cost(args.format, args.reps, False, work), 3),
            "us_per_frame_batches": round(writer_cost(args.format, args.reps, True, work), 3),
            "python_can": can.__version__,
            "machine": machine(),
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
