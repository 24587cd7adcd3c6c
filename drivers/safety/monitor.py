"""Watchdogs on what the drives send: feedback TPDOs, heartbeats, boot-ups, EMCYs.

A :class:`NodeMonitor` holds one slot per rope motor (the rope layer's order).
Bus receive threads call the ``on_*`` callbacks; the supervisor calls
:meth:`NodeMonitor.check` once per control cycle, which evaluates every watchdog
with NumPy over all nodes at once and returns the causes that must stop the
box (an empty list when all is well).  Callbacks that see a cause between cycles
set :attr:`NodeMonitor.wake` so the supervisor reacts at once.

The receive path also keeps the feedback of the last clean cycle (every node's TPDO
of one SYNC, with the targets that SYNC applied): the last TPDO of such a cycle copies
the positions into a preallocated buffer that a watch reads at any time
(:meth:`NodeMonitor.feedback_snapshot`, :func:`drivers.safety.watches.take_snapshot`).

>>> mon = NodeMonitor(["m0", "m1"], missing_tpdo_cycles=1, heartbeat_timeout_s=0.3)
>>> mon.on_tpdo(0, bytes.fromhex("370264000000"), seq=0)
>>> [c.text for c in mon.check(now=0.0, last_seq=0, heartbeats_armed_at=None)]
['m1: no TPDO for 1 cycle(s)']
"""

from __future__ import annotations

import collections
import math
import os
import select
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.protocol.batch import TPDO_VIEW
from drivers.protocol.cia301 import (
    NMT_STATE_BOOTUP,
    NMT_STATE_NAMES,
    NMT_STATE_OPERATIONAL,
    Emergency,
    FrameError,
    parse_emcy,
    parse_guarding_answer,
    parse_heartbeat,
)
from drivers.protocol.cia402 import (
    STATE_PATTERNS,
    SW_FAULT,
    TPDO_FEEDBACK_LAYOUT,
    TPDO_FEEDBACK_SIZE,
    State402,
    decode_states,
    parse_tpdo,
)
from drivers.safety.causes import StopCause, StopKind

#: causes queued between checks at most (a node flooding EMCYs cannot grow the queue)
MAX_QUEUED_CAUSES = 1024
#: EMCYs kept for the run record at most (the rest counted in ``emergencies_dropped``)
MAX_EMERGENCIES = 1000

_TPDO_SIZE = TPDO_FEEDBACK_SIZE
# the statusword pattern of OPERATION_ENABLED (the table's only one for that state)
((_OE_MASK, _OE_VALUE),) = [
    (m, v) for m, v, st in STATE_PATTERNS if st is State402.OPERATION_ENABLED
]
_TPDO_UNPACK = TPDO_FEEDBACK_LAYOUT.unpack


class WakeEvent:
    """A ``threading.Event`` that is also a descriptor (an eventfd, readable while set), so
    the supervisor waits for it, its deadline and its buses' frames in one ``select``.

    >>> ev = WakeEvent()
    >>> ev.wait(0.0), ev.set(), ev.is_set(), ev.wait(1.0)
    (False, None, True, True)
    >>> ev.clear(); ev.is_set(), select.select([ev], [], [], 0.0)[0] == []
    (False, True)
    """

    def __init__(self) -> None:
        self._fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._flag = False
        # set/clear (any thread) against close: never a write to a closed, reused fd
        self._fd_lock = threading.Lock()

    def fileno(self) -> int:
        return self._fd

    def set(self) -> None:
        self._flag = True
        with self._fd_lock:
            if self._fd >= 0:
                os.eventfd_write(self._fd, 1)

    def clear(self) -> None:
        self._flag = False
        with self._fd_lock:
            if self._fd < 0:
                return
            try:
                os.eventfd_read(self._fd)
            except BlockingIOError:
                pass

    def is_set(self) -> bool:
        return self._flag

    def wait(self, timeout: float | None = None) -> bool:
        """Whether the event is set, waiting at most ``timeout`` s for it."""
        fd = self._fd  # read once: close() may run meanwhile
        if not self._flag and fd >= 0:
            try:
                select.select([fd], [], [], timeout)
            except (OSError, ValueError):  # closed under the wait: the owner is closing
                pass
        return self._flag

    def close(self) -> None:
        """Release the descriptor (idempotent; afterwards ``set`` only sets the flag).
        Its owner closes it when its waiter is gone: not left to the garbage collector,
        one descriptor per session would pile up between collections.

        >>> ev = WakeEvent(); ev.close(); ev.close(); ev.set(); ev.is_set(), ev.fileno()
        (True, -1)
        """
        with self._fd_lock:
            fd, self._fd = self._fd, -1
            if fd >= 0:
                os.close(fd)

    def __del__(self) -> None:
        fd, self._fd = getattr(self, "_fd", -1), -1
        if fd >= 0:
            os.close(fd)


@dataclass(frozen=True)
class FeedbackSnapshot:
    """Every node's actual position after SYNC ``seq`` (its one answer to it) and the
    targets that SYNC applied (None: the supervisor gave none with it)."""

    seq: int
    counts: np.ndarray
    reference: np.ndarray | None


def _relative(t: float, reset_at: float) -> str:
    """``0.250 s before the reset`` / ``... after the reset``."""
    if t < reset_at:
        return f"{reset_at - t:.3f} s before the reset"
    return f"{t - reset_at:.3f} s after the reset"


class NodeMonitor:
    """Per-node receive state and watchdogs (one slot per rope motor)."""

    def __init__(
        self,
        labels: list[str],
        missing_tpdo_cycles: int,
        heartbeat_timeout_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        n = len(labels)
        self.clock = clock
        self.labels = list(labels)
        self.missing_tpdo_cycles = int(missing_tpdo_cycles)
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self.statusword = np.zeros(n, dtype=np.int64)
        self.position = np.zeros(n, dtype=np.int64)
        self.rx_seq = np.full(n, -1, dtype=np.int64)  # SYNC sequence of the last TPDO
        self.n_tpdo = np.zeros(n, dtype=np.int64)
        # What every node had answered when SYNC ``sync_mark`` went out (:meth:`sync_sent`):
        # its TPDO count, and whether every node's answer to the SYNC before was in.
        self.n_at_sync = np.zeros(n, dtype=np.int64)
        self.prev_complete = False
        self.sync_mark = -1  # the SYNC these were noted for (-1: being noted, or none)
        self._answers = np.zeros(n, dtype=np.int64)  # work buffers of sync_sent
        self._answered = np.zeros(n, dtype=bool)
        self._labelled = np.zeros(n, dtype=bool)
        # The targets SYNC ``sync_mark`` applied (given to sync_sent; valid when flagged).
        self._sync_targets = np.zeros(n, dtype=np.int64)
        self._sync_has_targets = False
        # The TPDO stores of the receive threads (one per bus) against each other, so the
        # last TPDO of a cycle sees every other one whole (never a position without its
        # count); never taken by the supervisor or a watch.
        self._rx_lock = threading.Lock()
        self._label = -1  # the SYNC label of the TPDOs counted in _label_count
        self._label_count = 0
        # The feedback of the last clean cycle (_record_snapshot): two slots written in
        # turn, slot ``v & 1`` published when ``_snap_version`` is v (0: none yet), so a
        # reader (feedback_snapshot) copies one slot while the next is written into the
        # other, and the receive path never waits for a reader.
        self._snap_version = 0
        self._snap_seq = [-1, -1]
        self._snap_has_targets = [False, False]
        self._snap_counts = np.zeros((2, n), dtype=np.int64)
        self._snap_targets = np.zeros((2, n), dtype=np.int64)
        self._snap_answers = np.zeros(n, dtype=np.int64)  # work buffer
        self._snap_ok = np.zeros(n, dtype=bool)  # work buffer
        # ``clock()`` when the receive thread handled the last heartbeat (so a stamp can
        # be newer than the ``now`` a concurrent check was given: see check())
        self.hb_time = np.full(n, -math.inf)
        self.hb_state = np.full(n, -1, dtype=np.int64)
        # the last malformed heartbeat of each node: when, and what was wrong with it
        self.hb_bad: list[tuple[float, str] | None] = [None] * n
        # nodes the host guards (node guarding, no heartbeat consumer): their frames on
        # 0x700 + id are answers, and the toggle bit each node's next answer must carry
        self.guarded = np.zeros(n, dtype=bool)
        self.guard_toggle = np.zeros(n, dtype=np.int64)
        self.booted = np.zeros(n, dtype=bool)
        # boot-up frames per node since :meth:`reset_boot`: more than one after one reset
        # is two devices answering as that node (a second box on the bus, a node-id clash)
        self.bootups = np.zeros(n, dtype=np.int64)
        # a boot-up since the drives were configured (:meth:`configured`): the node lost
        # its SDO configuration (heartbeats, limits, PDO maps, CSP) and is not enabled
        self.rebooted = np.zeros(n, dtype=bool)
        self.missing_run = np.zeros(n, dtype=np.int64)
        self.missing_total = 0
        self.seq = -1  # SYNC sequence number last sent (set by the supervisor)
        # Boot-ups, NMT states and fault bits are stop causes while armed; set only by
        # the supervisor (drives enabled, idle or streaming).
        self.armed = False
        # Frames of another master are stop causes from the drives' configuration until
        # the session ends (not only while armed): set by the session.
        self.guarding = False
        # Monotonic time heartbeat supervision started (end of bring-up; None: not yet).
        # Kept across idle periods and streams, so a stream never restarts the timeout.
        self.hb_armed_at: float | None = None
        self.boot_event = threading.Event()
        self.wake = WakeEvent()
        self._async_causes: collections.deque[StopCause] = collections.deque()
        self._causes_lock = threading.Lock()  # _queue (receive threads) against take
        self.causes_dropped = 0  # queued past MAX_QUEUED_CAUSES (the first ones are kept)
        self.emergencies: list[Emergency] = []  # the first MAX_EMERGENCIES
        self.emergencies_dropped = 0

    @property
    def n(self) -> int:
        return len(self.labels)

    # ---------------------------------------------------------- receive callbacks
    def _queue(self, cause: StopCause) -> None:
        """Queue a cause (at most ``MAX_QUEUED_CAUSES``: a node flooding the bus with
        EMCYs cannot grow it; one queued cause is enough to stop) and wake the supervisor."""
        with self._causes_lock:
            if len(self._async_causes) < MAX_QUEUED_CAUSES:
                self._async_causes.append(cause)
            else:
                self.causes_dropped += 1
        self.wake.set()

    def _async_cause(self, kind: StopKind, idx: int, text: str) -> None:
        self._queue(StopCause(kind, f"{self.labels[idx]}: {text}", self.labels[idx], self.clock()))

    def report(self, kind: StopKind, text: str) -> None:
        """A stop cause found outside the receive callbacks (e.g. a failed send)."""
        self._queue(StopCause(kind, text, None, self.clock()))

    def sync_sent(self, seq: int, targets: np.ndarray | None = None) -> None:
        """SYNC ``seq`` is about to go out (the supervisor), applying ``targets`` (the
        counts whose RPDOs went out before it; None: none given): label what arrives from
        now on with it, and note each node's TPDO count and whether the cycle before was
        clean: every node answered SYNC ``seq - 1`` exactly once before this one went out.
        A TPDO is labelled with the SYNC last sent when it arrives, so a drive that answers
        a SYNC late answers it under the next one's label: the feedback of one SYNC
        (:meth:`feedback_snapshot`) is recorded only after a clean cycle, once every node
        has answered exactly once since.

        >>> mon = NodeMonitor(["m0", "m1"], missing_tpdo_cycles=3, heartbeat_timeout_s=0.3)
        >>> mon.sync_sent(0)
        >>> for i in (0, 1):
        ...     mon.on_tpdo(i, bytes.fromhex("370264000000"))
        >>> mon.sync_sent(1)                      # SYNC 0 answered once by each: clean
        >>> mon.prev_complete, mon.sync_mark, mon.n_at_sync.tolist()
        (True, 1, [1, 1])
        >>> mon.on_tpdo(0, bytes.fromhex("370264000000"))
        >>> mon.sync_sent(2)                      # node 1 did not answer SYNC 1 in time
        >>> mon.prev_complete
        False
        """
        was = self.sync_mark
        self.sync_mark = -1  # a reader in between sees the notes as not for any SYNC
        np.subtract(self.n_tpdo, self.n_at_sync, out=self._answers)
        np.equal(self._answers, 1, out=self._answered)
        np.equal(self.rx_seq, seq - 1, out=self._labelled)
        self.prev_complete = (
            was == seq - 1
            and bool(self._answered.all())
            and bool(self._labelled.all())
            # n TPDOs under its label, no more: a receive batch holding one node's two
            # answers counts once in n_tpdo
            and self._label == seq - 1
            and self._label_count == len(self.labels)
        )
        if targets is not None:
            np.copyto(self._sync_targets, targets)
        self._sync_has_targets = targets is not None
        np.copyto(self.n_at_sync, self.n_tpdo)
        self.sync_mark = seq
        self.seq = seq

    def on_tpdo(self, idx: int, data: bytes | bytearray, seq: int | None = None) -> None:
        """TPDO1 (statusword, position actual) from the node in slot ``idx`` (the
        receive path's hot spot: one ``struct`` unpack, four array stores; once a cycle,
        at the n-th TPDO of one SYNC, :meth:`_record_snapshot`)."""
        if len(data) == _TPDO_SIZE:
            sw, pos = _TPDO_UNPACK(data)
        else:
            try:
                sw, pos = parse_tpdo(data)  # names what is wrong
            except FrameError as exc:
                self._async_cause(StopKind.BAD_FRAME, idx, str(exc))
                return
        with self._rx_lock:
            label = self.seq if seq is None else seq
            self.statusword[idx] = sw
            self.position[idx] = pos
            self.rx_seq[idx] = label
            self.n_tpdo[idx] += 1
            if label != self._label:
                self._label, self._label_count = label, 1
            else:
                self._label_count += 1
            if self._label_count == len(self.labels):
                self._record_snapshot(label)
        if sw & SW_FAULT and self.armed:
            self._async_cause(StopKind.FAULT, idx, f"statusword 0x{sw:04X} has the fault bit set")

    def on_tpdo_batch(self, slots: np.ndarray, frames: np.ndarray) -> None:
        """The TPDO1s of a batch (:data:`drivers.protocol.batch.FRAME_DTYPE` records of
        6 data bytes, one per entry of ``slots``) at once: what :meth:`on_tpdo` does for
        each, in a few NumPy calls.

        >>> from drivers.protocol.batch import from_messages
        >>> from drivers.protocol.cia402 import make_tpdo_feedback
        >>> mon = NodeMonitor(["m0", "m1"], missing_tpdo_cycles=1, heartbeat_timeout_s=0.3)
        >>> mon.seq = 4
        >>> frames = from_messages(
        ...     [make_tpdo_feedback(2, 0x0237, -5), make_tpdo_feedback(1, 0x0237, 9)])
        >>> mon.on_tpdo_batch(np.array([1, 0]), frames)
        >>> mon.position.tolist(), mon.rx_seq.tolist(), mon.n_tpdo.tolist()
        ([9, -5], [4, 4], [1, 1])
        """
        v = frames.view(TPDO_VIEW)
        sw = v["statusword"]
        with self._rx_lock:
            label = self.seq
            self.statusword[slots] = sw
            self.position[slots] = v["position"]
            self.rx_seq[slots] = label
            self.n_tpdo[slots] += 1  # (a node twice in one batch counts once ...)
            if label != self._label:  # (... but twice here: no snapshot of that cycle)
                self._label, self._label_count = label, len(slots)
            else:
                self._label_count += len(slots)
            if self._label_count == len(self.labels):
                self._record_snapshot(label)
        if self.armed:
            bad = np.flatnonzero(sw & SW_FAULT)
            for k in bad.tolist():
                self._async_cause(
                    StopKind.FAULT,
                    int(slots[k]),
                    f"statusword 0x{int(sw[k]):04X} has the fault bit set",
                )

    def _record_snapshot(self, label: int) -> None:
        """The receive path (under ``_rx_lock``) when the n-th TPDO labelled SYNC
        ``label`` is in: record every node's position as that SYNC's feedback when the
        cycle is clean (the rules of :meth:`sync_sent`: the cycle before was clean, and
        every node has answered exactly once since SYNC ``label`` went out, under its
        label), with the targets it applied, in the slot not published, then publish it.
        A few NumPy calls into preallocated buffers, once a cycle.  The supervisor notes
        the next SYNC without waiting for this: notes changed meanwhile
        (``sync_mark`` no longer ``label``) leave the slot unpublished."""
        if label < 0 or self.sync_mark != label or not self.prev_complete:
            return
        np.subtract(self.n_tpdo, self.n_at_sync, out=self._snap_answers)
        np.equal(self._snap_answers, 1, out=self._snap_ok)
        if not self._snap_ok.all():
            return
        np.equal(self.rx_seq, label, out=self._snap_ok)
        if not self._snap_ok.all():
            return
        k = (self._snap_version + 1) & 1
        np.copyto(self._snap_counts[k], self.position)
        has_targets = self._sync_has_targets
        if has_targets:
            np.copyto(self._snap_targets[k], self._sync_targets)
        if self.sync_mark != label:  # the next SYNC's notes began: targets may be its
            return
        self._snap_seq[k] = label
        self._snap_has_targets[k] = has_targets
        self._snap_version += 1  # published

    @property
    def clean_cycles(self) -> int:
        """Clean cycles recorded so far (:meth:`feedback_snapshot`)."""
        return self._snap_version

    def feedback_snapshot(self, tries: int = 4) -> FeedbackSnapshot | None:
        """The feedback of the last clean cycle (copies), or None when there was none
        yet (or the receive path published ``tries`` times while it was copied: it
        publishes once a SYNC).

        >>> mon = NodeMonitor(["m0", "m1"], missing_tpdo_cycles=3, heartbeat_timeout_s=0.3)
        >>> for seq in (0, 1):                   # SYNC 0 answered by each: SYNC 1 clean
        ...     mon.sync_sent(seq, np.array([100, 200]))
        ...     for i in (0, 1):
        ...         mon.on_tpdo(i, bytes.fromhex("370264000000"))
        >>> snap = mon.feedback_snapshot()
        >>> snap.seq, snap.counts.tolist(), snap.reference.tolist()
        (1, [100, 100], [100, 200])
        >>> mon.sync_sent(2)
        >>> mon.on_tpdo(0, bytes.fromhex("370264000000"))   # node 1 not in: no record
        >>> mon.sync_sent(3)
        >>> for i in (0, 1):                     # SYNC 2 was not clean: nor is SYNC 3
        ...     mon.on_tpdo(i, bytes.fromhex("370264000000"))
        >>> mon.feedback_snapshot().seq          # the last clean cycle's
        1
        """
        for _ in range(max(1, tries)):
            v = self._snap_version
            if v == 0:
                return None
            k = v & 1
            seq = self._snap_seq[k]
            counts = self._snap_counts[k].copy()
            ref = self._snap_targets[k].copy() if self._snap_has_targets[k] else None
            if self._snap_version == v:  # not written meanwhile (the other slot is)
                return FeedbackSnapshot(seq, counts, ref)
        return None

    def guard(self, slots: Sequence[int]) -> None:
        """The nodes in ``slots`` are guarded (node guarding instead of heartbeats): their
        frames on 0x700 + node id are answers with a toggle bit (a boot-up aside)."""
        self.guarded[np.asarray(slots, dtype=np.int64)] = True

    def on_heartbeat(self, idx: int, data: bytes | bytearray) -> None:
        """Heartbeat or boot-up frame from the node in slot ``idx`` (of a guarded node:
        its node-guarding answer, :meth:`on_guarding_answer`)."""
        if self.guarded[idx] and bytes(data) != bytes((NMT_STATE_BOOTUP,)):
            self.on_guarding_answer(idx, data)
            return
        try:
            state = parse_heartbeat(data)
        except FrameError as exc:
            self._bad_state_frame(idx, exc)
            return
        self.hb_time[idx] = self.clock()
        self.hb_state[idx] = state
        if state == NMT_STATE_BOOTUP:
            self.guard_toggle[idx] = 0  # the first answer after a reset: toggle 0
            self.booted[idx] = True
            self.bootups[idx] += 1
            self.rebooted[idx] = True
            if self.booted.all():
                self.boot_event.set()
            if self.armed:
                self._async_cause(
                    StopKind.BOOTUP, idx, "node rebooted (boot-up frame) while enabled"
                )
        elif self.armed:
            self._require_operational(idx, state, "heartbeat")

    def on_guarding_answer(self, idx: int, data: bytes | bytearray) -> None:
        """A guarded node's answer to a guarding request: taken as its heartbeat (its
        state, and its time for the heartbeat timeout: no answer within it is a lost
        heartbeat), its toggle bit checked: 0 after a boot-up, then alternating; a toggle
        other than expected (an answer lost, or one answered twice) is a stop cause while
        armed, like a lost heartbeat.

        >>> mon = NodeMonitor(["m0"], missing_tpdo_cycles=1, heartbeat_timeout_s=0.3)
        >>> mon.guard([0]); mon.armed = True
        >>> for byte in (0x05, 0x85, 0x85):
        ...     mon.on_guarding_answer(0, bytes([byte]))
        >>> [c.text for c in mon.check(now=0.0, last_seq=-1, heartbeats_armed_at=None)]
        ['m0: node-guarding answer with toggle bit 1, expected 0 (an answer lost or repeated)']
        """
        try:
            state, toggle = parse_guarding_answer(data)
        except FrameError as exc:
            self._bad_state_frame(idx, exc)
            return
        self.hb_time[idx] = self.clock()
        self.hb_state[idx] = state
        expected = int(self.guard_toggle[idx])
        self.guard_toggle[idx] = toggle ^ 1
        if not self.armed:
            return
        if toggle != expected:
            self._async_cause(
                StopKind.HEARTBEAT,
                idx,
                f"node-guarding answer with toggle bit {toggle}, expected {expected} "
                "(an answer lost or repeated)",
            )
        else:
            self._require_operational(idx, state, "node guarding")

    def _bad_state_frame(self, idx: int, exc: FrameError) -> None:
        """A malformed heartbeat or guarding answer: kept for the status, a stop cause."""
        self.hb_bad[idx] = (self.clock(), str(exc))
        self._async_cause(StopKind.BAD_FRAME, idx, str(exc))

    def _require_operational(self, idx: int, state: int, source: str) -> None:
        """While armed, an NMT state other than OPERATIONAL (from ``source``: the
        heartbeat or the guarding answer) is a stop cause."""
        if state != NMT_STATE_OPERATIONAL:
            name = NMT_STATE_NAMES.get(state, f"0x{state:02X}")
            self._async_cause(StopKind.HEARTBEAT, idx, f"{source} reports NMT state {name}")

    def on_emcy(self, idx: int, node_id: int, data: bytes | bytearray) -> None:
        """EMCY frame: a fault, except error code 0x0000 ('error reset / no error') with
        an error register of 0 (a reset that leaves a register bit set leaves an error)."""
        try:
            emcy = parse_emcy(node_id, data)
        except FrameError as exc:
            self._async_cause(StopKind.BAD_FRAME, idx, str(exc))
            return
        if len(self.emergencies) < MAX_EMERGENCIES:
            self.emergencies.append(emcy)
        else:
            self.emergencies_dropped += 1
        if emcy.error_code != 0:
            self._async_cause(StopKind.EMCY, idx, emcy.describe())
        elif emcy.error_register != 0:
            self._async_cause(StopKind.EMCY, idx, emcy.describe() + " (an error remains)")

    def drain(self) -> list[StopCause]:
        """Take the causes queued by the receive callbacks (e.g. before a stream starts)."""
        out = []
        while self._async_causes:
            out.append(self._async_causes.popleft())
        self.wake.clear()
        return out

    def take(self, kinds: frozenset[StopKind]) -> list[StopCause]:
        """Take the queued causes of ``kinds``, leaving the others queued."""
        with self._causes_lock:
            taken = [c for c in self._async_causes if c.kind in kinds]
            if taken:
                kept = [c for c in self._async_causes if c.kind not in kinds]
                self._async_causes.clear()
                self._async_causes.extend(kept)
        return taken

    def queued(self) -> list[StopCause]:
        """The causes queued now (left queued)."""
        return list(self._async_causes)

    def configured(self) -> None:
        """Every drive was just configured: a boot-up from now on means a drive lost
        its configuration (:attr:`rebooted`)."""
        self.rebooted[:] = False

    def reset_boot(self) -> None:
        self.booted[:] = False
        self.bootups[:] = 0
        self.boot_event.clear()

    def describe_duplicate_boot(self) -> list[str]:
        """Each node that sent more than one boot-up since :meth:`reset_boot`: after one NMT
        reset a node boots once, so two boot-ups are two devices with its node id.

        >>> mon = NodeMonitor(["m0 (bus can0 node 1)", "m1 (bus can0 node 2)"], 3, 0.35)
        >>> mon.reset_boot()
        >>> for idx in (0, 1, 0):
        ...     mon.on_heartbeat(idx, bytes([0x00]))
        >>> mon.describe_duplicate_boot()
        ['m0 (bus can0 node 1): 2 boot-ups']
        """
        return [
            f"{self.labels[i]}: {int(self.bootups[i])} boot-ups"
            for i in np.flatnonzero(self.bootups > 1).tolist()
        ]

    def describe_missing_boot(self, reset_at: float) -> list[str]:
        """Each node without a boot-up since :meth:`reset_boot`, with what was last heard
        of it relative to ``reset_at`` (the clock reading when the NMT reset went out):
        a node never heard is unpowered or not on the bus; one heard after the reset
        in another state booted without its boot-up frame reaching us.

        >>> mon = NodeMonitor(["m0", "m1", "m2"], missing_tpdo_cycles=1,
        ...                   heartbeat_timeout_s=0.3, clock=lambda: 10.0)
        >>> mon.on_heartbeat(1, bytes([0x05]))
        >>> mon.on_heartbeat(2, bytes([0x00]))
        >>> mon.describe_missing_boot(reset_at=10.25)
        ['m0: never heard', 'm1: last heard 0.250 s before the reset, OPERATIONAL']
        >>> mon.on_heartbeat(0, bytes([0x85]))          # a state no node reports
        >>> mon.describe_missing_boot(reset_at=10.25)[0]  # doctest: +ELLIPSIS
        'm0: heard only a malformed heartbeat, 0.250 s before the reset (heartbeat ...)'
        """
        out = []
        for i in np.flatnonzero(~self.booted).tolist():
            t, state = float(self.hb_time[i]), int(self.hb_state[i])
            if not math.isfinite(t):
                bad = self.hb_bad[i]
                if bad is None:
                    out.append(f"{self.labels[i]}: never heard")
                else:
                    out.append(
                        f"{self.labels[i]}: heard only a malformed heartbeat, "
                        f"{_relative(bad[0], reset_at)} ({bad[1]})"
                    )
                continue
            name = NMT_STATE_NAMES.get(state, f"0x{state:02X}")
            out.append(f"{self.labels[i]}: last heard {_relative(t, reset_at)}, {name}")
        return out

    # ---------------------------------------------------------- per-cycle check
    def check(
        self, now: float, last_seq: int, heartbeats_armed_at: float | None
    ) -> list[StopCause]:
        """Evaluate every watchdog; ``last_seq`` is the SYNC whose TPDOs are due.

        ``heartbeats_armed_at``: monotonic time heartbeat supervision started
        (None: not supervised yet).
        """
        causes: list[StopCause] = []
        while self._async_causes:
            causes.append(self._async_causes.popleft())
        if last_seq >= 0:
            # The usual cycle takes few NumPy calls (each costs microseconds, more on a
            # cold cache): every TPDO in, every node OPERATION_ENABLED, no heartbeat late.
            got = self.rx_seq >= last_seq
            if got.all():
                self.missing_run.fill(0)
            else:
                self.missing_run = np.where(got, 0, self.missing_run + 1)
                self.missing_total += int(np.count_nonzero(~got))
                for i in np.flatnonzero(self.missing_run >= self.missing_tpdo_cycles):
                    causes.append(
                        StopCause(
                            StopKind.TPDO_MISSING,
                            f"{self.labels[i]}: no TPDO for {int(self.missing_run[i])} cycle(s)",
                            self.labels[i],
                            now,
                        )
                    )
            # OPERATION_ENABLED by its one statusword pattern; the full decode only for
            # the nodes that are not (decode_states is ~20 us for 36 nodes)
            bad = (self.statusword & _OE_MASK) != _OE_VALUE
            if bad.any():
                # one copy for the test, the decode and the message: a TPDO handled in
                # between must not give a stop whose message shows the drive enabled.
                # Only the nodes whose TPDO of the due SYNC is in: an older statusword
                # (e.g. SWITCH_ON_DISABLED from before an enable, its node's first TPDO
                # of the stream late) says nothing of the drive now; the late node is the
                # missing-TPDO watch's (seen: a jog after reset-fault and enable stopped
                # on 16 such stale words while the box was behind)
                words = self.statusword.copy()
                bad = ((words & _OE_MASK) != _OE_VALUE) & (self.rx_seq >= last_seq)
                states = decode_states(words)
                for i in np.flatnonzero(bad):
                    sw = int(words[i])
                    kind = StopKind.FAULT if sw & SW_FAULT else StopKind.STATE
                    causes.append(
                        StopCause(
                            kind,
                            f"{self.labels[i]}: statusword 0x{sw:04X} "
                            f"({State402(int(states[i])).name}), expected OPERATION_ENABLED",
                            self.labels[i],
                            now,
                        )
                    )
        if (
            heartbeats_armed_at is not None
            # the oldest heartbeat decides whether any is late (max() is monotonic)
            and now - max(float(self.hb_time.min()), heartbeats_armed_at) > self.heartbeat_timeout_s
        ):
            # The receive threads stamp hb_time while this runs: decide and name the age
            # from ONE copy (a later read could show a heartbeat stamped after ``now``:
            # a negative age), then let a heartbeat processed since that copy clear its
            # node (stamped after ``now``: it is not lost).
            stamps = np.array(self.hb_time)
            timeout_s = self.heartbeat_timeout_s
            late = (now - np.maximum(stamps, heartbeats_armed_at)) > timeout_s
            idx = np.flatnonzero(late)
            fresh = np.asarray(self.hb_time[idx])  # re-read: what arrived meanwhile
            idx = idx[(now - np.maximum(fresh, heartbeats_armed_at)) > timeout_s]
            for i in idx:
                age = now - stamps[i]
                what = (
                    "never received" if not math.isfinite(age) else f"last {age * 1000:.0f} ms ago"
                )
                causes.append(
                    StopCause(
                        StopKind.HEARTBEAT,
                        f"{self.labels[i]}: heartbeat lost ({what}, timeout "
                        f"{self.heartbeat_timeout_s * 1000:.0f} ms)",
                        self.labels[i],
                        now,
                    )
                )
        return causes
