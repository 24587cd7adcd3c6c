"""What one control cycle sends and measures: the frames of a bus, the events and
timing of a run, how a stream ended.

The control loop itself is :class:`drivers.safety.supervisor.Supervisor`, the one
thread that owns the cycle: at every deadline of a fixed grid ``t0 + g T`` it
evaluates the watchdogs, sends the SYNC on every bus (which applies the RPDOs sent
during the previous period), then checks the next setpoint against the rope
layer's limits and sends every node's RPDO (one ``BusPort.send_many`` per bus: one
datagram on ``hrm_ipc``).  So every period carries each node's RPDO and then the SYNC
that applies it, and the RPDOs have the rest of the period to reach the wire: a SYNC
(0x080) sent right behind a burst of RPDOs (0x2xx) could overtake them on a controller
that sends pending frames in identifier order.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from drivers.bus import BusPort
from drivers.protocol import cia301, cia402
from drivers.safety.monitor import StopCause
from hrm_ctrl.errors import HrmError

_RPDO_PACK = cia402.RPDO_TARGET_LAYOUT.pack
LATE_THRESHOLD_S = 0.002
STOP_CONFIRM_CYCLES = 10
SYNC_MARGIN_S = 0.0005


@dataclass
class BusLayout:
    """The nodes of one bus in the box's global motor order."""

    port: BusPort
    index: np.ndarray  # global motor indices on this bus
    node_ids: np.ndarray
    notifier: Any = None  # the bus's receive thread: has ``.exception`` (None: alive)
    burst_s: float = 0.0  # wire time of one cycle's worst-case traffic on this bus

    def __post_init__(self) -> None:
        self.rpdo_ids = [cia301.COB_RPDO1 + int(n) for n in self.node_ids]

    def rpdo_frames(self, controlword: int | np.ndarray, targets: np.ndarray) -> list[can.Message]:
        """RPDO frames of this bus for global target vector ``targets`` (one ``struct``
        pack per node; a target outside INTEGER32 raises :class:`FrameError`).

        >>> from drivers.bus import BusPort
        >>> lay = BusLayout(BusPort("b", None), np.array([1, 0]), np.array([5, 6]))
        >>> [(hex(m.arbitration_id), m.data.hex()) for m in lay.rpdo_frames(15, np.array([-1, 7]))]
        [('0x205', '0f0007000000'), ('0x206', '0f00ffffffff')]
        """
        tg = np.asarray(targets)[self.index].astype(np.int64, copy=False).tolist()
        if tg and (min(tg) < cia402.INT32_MIN or max(tg) > cia402.INT32_MAX):
            raise cia402.FrameError("target position outside INTEGER32")
        pack = _RPDO_PACK
        if np.ndim(controlword) == 0:
            cw = int(controlword) & 0xFFFF
            payloads = [pack(cw, t) for t in tg]
        else:
            cws = np.broadcast_to(np.asarray(controlword), (len(self.index),)).tolist()
            payloads = [pack(c & 0xFFFF, t) for c, t in zip(cws, tg, strict=True)]
        return [
            can.Message(arbitration_id=cid, data=data, is_extended_id=False, check=False)
            for cid, data in zip(self.rpdo_ids, payloads, strict=True)
        ]


@dataclass
class EventLog:
    """Timestamped events of a run (thread-safe append)."""

    t0: float = field(default_factory=time.monotonic)
    events: list[dict[str, Any]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, kind: str, text: str, **extra: Any) -> None:
        with self._lock:
            self.events.append(
                {"t_s": round(time.monotonic() - self.t0, 6), "kind": kind, "text": text, **extra}
            )

    def to_list(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.events)


class CycleStats:
    """Per-cycle timing of a stream.

    >>> st = CycleStats(0.01)
    >>> for k, late in enumerate([0.0002, 0.0004, 0.003]):
    ...     st.add(k * 0.01, k * 0.01, k * 0.01 + late, 0.001)
    >>> s = st.summary()
    >>> s["cycles"], s["late_cycles"], round(s["jitter_max_s"] * 1000, 1)
    (3, 1, 2.6)
    """

    def __init__(self, period_s: float, late_threshold_s: float = LATE_THRESHOLD_S) -> None:
        self.period_s = period_s
        self.late_threshold_s = late_threshold_s
        self.deadline: list[float] = []
        self.woke: list[float] = []
        self.sync_sent: list[float] = []
        self.cpu_s: list[float] = []
        self.skipped_slots = 0
        self.realtime = False
        self.missing_feedback = 0
        self.process_cpu_s = 0.0

    def add(self, deadline: float, woke: float, sync_sent: float, cpu_s: float) -> None:
        self.deadline.append(deadline)
        self.woke.append(woke)
        self.sync_sent.append(sync_sent)
        self.cpu_s.append(cpu_s)

    @property
    def n_cycles(self) -> int:
        return len(self.deadline)

    def summary(self) -> dict[str, Any]:
        """Lateness = SYNC sent minus its deadline (wake lateness: supervisor awake minus
        deadline); jitter = |period - T| between consecutive SYNCs; CPU = supervisor thread
        time per cycle; process CPU includes receive threads and log writers."""
        n = self.n_cycles
        out: dict[str, Any] = {
            "cycles": n,
            "period_s": self.period_s,
            "late_threshold_s": self.late_threshold_s,
            "skipped_slots": self.skipped_slots,
            "realtime_scheduling": self.realtime,
            "missing_feedback_node_cycles": self.missing_feedback,
        }
        if n == 0:
            return out
        late = np.asarray(self.sync_sent) - np.asarray(self.deadline)
        wake = np.asarray(self.woke) - np.asarray(self.deadline)
        cpu = np.asarray(self.cpu_s)
        out.update(
            {
                "wake_lateness_p99_s": float(np.percentile(wake, 99)),
                "wake_lateness_max_s": float(wake.max()),
                "lateness_p50_s": float(np.percentile(late, 50)),
                "lateness_p99_s": float(np.percentile(late, 99)),
                "lateness_max_s": float(late.max()),
                "late_cycles": int(np.count_nonzero(late > self.late_threshold_s)),
                "cpu_per_cycle_mean_s": float(cpu.mean()),
                "cpu_per_cycle_p99_s": float(np.percentile(cpu, 99)),
                "process_cpu_per_cycle_s": self.process_cpu_s / n,
            }
        )
        if n >= 2:
            jitter = np.abs(np.diff(np.asarray(self.sync_sent)) - self.period_s)
            out.update(
                {
                    "jitter_p50_s": float(np.percentile(jitter, 50)),
                    "jitter_p99_s": float(np.percentile(jitter, 99)),
                    "jitter_max_s": float(jitter.max()),
                    "drift_s": float(
                        (self.sync_sent[-1] - self.sync_sent[0])
                        - (self.deadline[-1] - self.deadline[0])
                    ),
                }
            )
        return out


@dataclass
class StreamResult:
    """How a stream ended."""

    completed: bool
    cycles: int
    causes: list[StopCause]
    stats: dict[str, Any]
    last_targets: np.ndarray
    stop_latency_s: float | None = None
    stop_confirmed: bool | None = None
    final_statuswords: list[int] = field(default_factory=list)
    error: HrmError | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "completed": self.completed,
            "cycles": self.cycles,
            "causes": [x.to_dict() for x in self.causes],
            "stop_latency_s": self.stop_latency_s,
            "stop_confirmed": self.stop_confirmed,
            "final_statuswords": self.final_statuswords,
            "stats": self.stats,
            "error": None if self.error is None else str(self.error),
        }
