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

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from drivers.bus import BusPort
from drivers.protocol import batch, cia301, cia402
from drivers.receive import BusPoller, BusReader
from drivers.safety.monitor import StopCause
from hrm_ctrl.errors import HrmError

_RPDO = cia402.RPDO_TARGET
LATE_THRESHOLD_S = 0.002
MAX_NOTABLE_CYCLES = 2000  # late or missing-feedback cycles kept with their times, per stream
STOP_CONFIRM_CYCLES = 10
SYNC_MARGIN_S = 0.0005


@dataclass
class BusLayout:
    """The nodes of one bus in the box's global motor order."""

    port: BusPort
    index: np.ndarray  # global motor indices on this bus
    node_ids: np.ndarray
    notifier: BusReader | BusPoller | None = None  # who reads the bus (.exception: None alive)
    burst_s: float = 0.0  # wire time of one cycle's worst-case traffic on this bus

    def __post_init__(self) -> None:
        self.rpdo_ids = [cia301.COB_RPDO1 + int(n) for n in self.node_ids]
        # this bus's RPDO1s as one record array, refilled every cycle (rpdo_batch)
        self._rpdo = batch.rpdo_batch(np.asarray(self.rpdo_ids, dtype=np.uint32), 0, 0)
        self._rpdo_view = self._rpdo.view(batch.RPDO_VIEW)

    def rpdo_batch(self, controlword: int, targets: np.ndarray) -> np.ndarray:
        """This bus's RPDO frames for global target vector ``targets`` as one record array
        (:data:`drivers.protocol.batch.FRAME_DTYPE`; the same frames as
        :meth:`rpdo_frames`, filled into a buffer the layout keeps: valid until the next
        call).  A target outside INTEGER32 raises :class:`FrameError`.

        >>> from drivers.bus import BusPort
        >>> lay = BusLayout(BusPort("b", None), np.array([1, 0]), np.array([5, 6]))
        >>> b = lay.rpdo_batch(15, np.array([-1, 7]))
        >>> [(hex(i), bytes(d[:6]).hex()) for i, d in zip(b["id"], b["data"])]
        [('0x205', '0f0007000000'), ('0x206', '0f00ffffffff')]
        """
        tg = np.asarray(targets)[self.index]
        _RPDO.fill(self._rpdo_view, controlword=int(controlword), target=tg)
        return self._rpdo

    def rpdo_frames(self, controlword: int | np.ndarray, targets: np.ndarray) -> list[can.Message]:
        """RPDO frames of this bus for global target vector ``targets`` (one payload
        per node; a target outside INTEGER32 raises :class:`FrameError`).

        >>> from drivers.bus import BusPort
        >>> lay = BusLayout(BusPort("b", None), np.array([1, 0]), np.array([5, 6]))
        >>> [(hex(m.arbitration_id), m.data.hex()) for m in lay.rpdo_frames(15, np.array([-1, 7]))]
        [('0x205', '0f0007000000'), ('0x206', '0f00ffffffff')]
        """
        tg = np.asarray(targets)[self.index]
        _RPDO.check_many("target", tg)
        cws = np.broadcast_to(np.asarray(controlword), (len(self.index),))
        payloads = [_RPDO.pack(c, t) for c, t in zip(cws.tolist(), tg.tolist(), strict=True)]
        return [
            can.Message(arbitration_id=cid, data=data, is_extended_id=False, check=False)
            for cid, data in zip(self.rpdo_ids, payloads, strict=True)
        ]


#: events a run keeps at most (another master flooding the bus cannot grow a run record)
MAX_EVENTS = 100_000


@dataclass
class EventLog:
    """Timestamped events of a run (thread-safe append)."""

    t0: float = field(default_factory=time.monotonic)
    events: list[dict[str, Any]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    dropped: int = 0  # events past MAX_EVENTS (the first ones are kept)

    def add(self, kind: str, text: str, **extra: Any) -> None:
        with self._lock:
            if len(self.events) >= MAX_EVENTS:
                self.dropped += 1
                return
            self.events.append(
                {"t_s": round(time.monotonic() - self.t0, 6), "kind": kind, "text": text, **extra}
            )

    def to_list(self) -> list[dict[str, Any]]:
        """The events, and one last ``events_dropped`` event when some were not kept."""
        with self._lock:
            out = list(self.events)
            if self.dropped:
                out.append(
                    {"t_s": round(time.monotonic() - self.t0, 6), "kind": "events_dropped",
                     "text": f"{self.dropped} more events not kept (at most {MAX_EVENTS})"}
                )  # fmt: skip
            return out


class TimeHistogram:
    """Counts of durations in fixed bins: a stream's memory stays flat however long it runs.

    Bins of :data:`HIST_BIN_S` (10 us) from :data:`HIST_LO_S` (-1 ms) over
    :data:`HIST_BINS` bins (to 99 ms); a value outside lands in the end bin and the exact
    minimum and maximum are kept beside.  A quantile is the upper edge of the bin where
    the cumulative count reaches it, so it errs high by less than one bin (never lower
    than the true quantile of the values within range); the maximum is exact.

    >>> h = TimeHistogram()
    >>> for x in (0.0001, 0.0002, 0.0003, 0.0040):
    ...     h.add(x)
    >>> h.n, round(h.quantile(50) * 1e3, 3), round(h.quantile(99) * 1e3, 3), h.max
    (4, 0.21, 4.0, 0.004)
    """

    __slots__ = ("counts", "max", "min", "n", "total")

    def __init__(self) -> None:
        self.counts = np.zeros(HIST_BINS, dtype=np.int64)
        self.n = 0
        self.total = 0.0
        self.max = -math.inf
        self.min = math.inf

    def add(self, x: float) -> None:
        i = int((x - HIST_LO_S) * _HIST_PER_S)
        self.counts[0 if i < 0 else HIST_BINS - 1 if i >= HIST_BINS else i] += 1
        self.n += 1
        self.total += x
        if x > self.max:
            self.max = x
        if x < self.min:
            self.min = x

    def quantile(self, q_percent: float) -> float:
        """The ``q_percent`` quantile (0..100), to within one bin above; NaN when empty."""
        if self.n == 0:
            return math.nan
        rank = max(1, math.ceil(self.n * q_percent / 100.0))
        i = int(np.searchsorted(np.cumsum(self.counts), rank))
        if i >= HIST_BINS - 1:  # the end bin holds everything beyond the range
            return self.max
        edge = HIST_LO_S + (i + 1) * HIST_BIN_S
        return float(min(max(edge, self.min), self.max))

    @property
    def mean(self) -> float:
        return self.total / self.n if self.n else math.nan


HIST_BIN_S = 1e-5
"""Width of a :class:`TimeHistogram` bin (10 us: a 36-drive SYNC burst is ~1 ms)."""
HIST_LO_S = -1e-3
"""Lower edge of the first bin (a SYNC a little before its grid slot reads negative)."""
HIST_BINS = 10_000
"""Bins per histogram (-1 ms .. 99 ms; 80 kB each, four per stream)."""
_HIST_PER_S = 1.0 / HIST_BIN_S


class CycleStats:
    """Per-cycle timing of a stream, in bounded memory.

    Each cycle goes into four :class:`TimeHistogram` (SYNC lateness, wake lateness, the
    supervisor's CPU time, SYNC-to-SYNC jitter) and two counters (late cycles, exactly;
    the first and last SYNC for the drift): a 10-minute soak holds as much as a 1 s jog
    (the lists of Python floats it kept before grew ~1 MB a minute).  Percentiles are
    to one bin (10 us), maxima exact.  The notable cycles, late ones and those that found
    TPDOs missing, are kept with their deadlines (the first :data:`MAX_NOTABLE_CYCLES`),
    to be set beside what else happened then (``hrm_ctrl.hil.stalls``).

    >>> st = CycleStats(0.01)
    >>> for k, late in enumerate([0.0002, 0.0004, 0.003]):
    ...     st.add(k * 0.01, k * 0.01, k * 0.01 + late, 0.001, missing_total=2 * (k >= 1))
    >>> s = st.summary()
    >>> s["cycles"], s["late_cycles"], round(s["jitter_max_s"] * 1000, 1)
    (3, 1, 2.6)
    >>> s["notable_cycles"]   # (deadline_s, lateness_s, TPDOs found missing, woke_s, cpu_s)
    [(0.01, 0.0004, 2, 0.0, 0.001), (0.02, 0.003, 0, 0.0, 0.001)]
    """

    def __init__(self, period_s: float, late_threshold_s: float = LATE_THRESHOLD_S) -> None:
        self.period_s = period_s
        self.late_threshold_s = late_threshold_s
        self.lateness = TimeHistogram()  # SYNC sent minus its deadline
        self.wake = TimeHistogram()  # supervisor awake minus the deadline
        self.cpu = TimeHistogram()  # supervisor thread time
        self.jitter = TimeHistogram()  # |SYNC-to-SYNC - period|
        self.late_cycles = 0
        self._first: tuple[float, float] | None = None  # (deadline, sync sent)
        self._last: tuple[float, float] = (math.nan, math.nan)
        self.skipped_slots = 0
        self.realtime = False
        self.missing_feedback = 0
        self.process_cpu_s = 0.0
        # (deadline, SYNC lateness, TPDOs found missing, wake lateness, supervisor CPU):
        # a late cycle whose wake lateness is most of it waited to be run; one that woke
        # on time and then spent its lateness in the supervisor's CPU time did work
        self.notable: list[tuple[float, float, int, float, float]] = []
        self._missing_seen: int | None = None

    def add(
        self,
        deadline: float,
        woke: float,
        sync_sent: float,
        cpu_s: float,
        missing_total: int = 0,
    ) -> None:
        """One cycle; ``missing_total``: the monitor's running count of TPDOs found
        missing (its growth since the last cycle is this cycle's)."""
        late = sync_sent - deadline
        self.lateness.add(late)
        self.wake.add(woke - deadline)
        self.cpu.add(cpu_s)
        missing = 0 if self._missing_seen is None else missing_total - self._missing_seen
        self._missing_seen = missing_total
        if late > self.late_threshold_s:
            self.late_cycles += 1
        if (late > self.late_threshold_s or missing) and len(self.notable) < MAX_NOTABLE_CYCLES:
            self.notable.append(
                (deadline, round(late, 6), missing, round(woke - deadline, 6), round(cpu_s, 6))
            )
        if self._first is None:
            self._first = (deadline, sync_sent)
        else:
            self.jitter.add(abs(sync_sent - self._last[1] - self.period_s))
        self._last = (deadline, sync_sent)

    @property
    def n_cycles(self) -> int:
        return self.lateness.n

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
        out.update(
            {
                "wake_lateness_p99_s": self.wake.quantile(99),
                "wake_lateness_max_s": self.wake.max,
                "lateness_p50_s": self.lateness.quantile(50),
                "lateness_p99_s": self.lateness.quantile(99),
                "lateness_max_s": self.lateness.max,
                "late_cycles": self.late_cycles,
                "cpu_per_cycle_mean_s": self.cpu.mean,
                "cpu_per_cycle_p99_s": self.cpu.quantile(99),
                "process_cpu_per_cycle_s": self.process_cpu_s / n,
                "notable_cycles": self.notable,
            }
        )
        if n >= 2 and self._first is not None:
            out.update(
                {
                    "jitter_p50_s": self.jitter.quantile(50),
                    "jitter_p99_s": self.jitter.quantile(99),
                    "jitter_max_s": self.jitter.max,
                    "drift_s": (self._last[1] - self._first[1]) - (self._last[0] - self._first[0]),
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
    stop_syncs_after_detection: int | None = None  # setpoint SYNCs between cause and stop
    stop_confirmed: bool | None = None
    final_statuswords: list[int] = field(default_factory=list)
    error: HrmError | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "completed": self.completed,
            "cycles": self.cycles,
            "causes": [x.to_dict() for x in self.causes],
            "stop_latency_s": self.stop_latency_s,
            "stop_syncs_after_detection": self.stop_syncs_after_detection,
            "stop_confirmed": self.stop_confirmed,
            "final_statuswords": self.final_statuswords,
            "stats": self.stats,
            "error": None if self.error is None else str(self.error),
        }
