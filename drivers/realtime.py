"""Process-wide settings: the GIL switch interval and the scheduling priority, in one place.

Both settings belong to the process (the switch interval) or to a thread and the
threads it starts afterwards (the Linux scheduling policy), never to a bus, a wire or
a session: constructing any of those changes no interpreter setting.  A process entry
point opts in by entering :func:`process_settings` once (``hrm`` does, around every
command, see :func:`hrm_ctrl.cli.main`); the context applies the settings, yields what
it got (:class:`AppliedSettings`) and restores both on exit.

* **GIL switch interval** (``sys.setswitchinterval``, process-wide): CPython's default
  5 ms lets one busy thread keep the interpreter lock that long.  The stack's deadlines
  are much shorter: a SYNC every 10 ms at 100 Hz, the simulated drives answering it
  from their bus threads, an ``hrm_sim`` wire node waiting 135 us for a frame at
  1 Mbit/s.  :data:`SWITCH_INTERVAL_S` (0.2 ms) hands the lock over within a small
  fraction of a period for a few percent of interpreter overhead.
* **Scheduling priority** (Linux ``SCHED_FIFO``, best effort): needs ``CAP_SYS_NICE``
  or an ``RLIMIT_RTPRIO`` of at least the priority.  When refused the context carries
  on under normal scheduling and says why (:attr:`AppliedSettings.realtime_refusal`,
  one warning on the ``drivers.realtime`` logger).  It applies to the calling thread
  and to the threads it starts afterwards: entered by the supervisor thread only that
  thread runs under FIFO; entered at process start, every thread does.
* **Garbage collector** (:class:`GcHold`, process-wide): while drives depend on the
  process (from the start of a bring-up to the end of ``finish``), everything
  allocated before is frozen out of the cyclic collector, so a full collection walks
  only what was allocated since, not the whole heap (a pause of 120-240 ms in the test
  process, longer with the cores busy: a heartbeat timeout).
* **CPUs** (Linux CPU affinity, ``cpus``): the calling thread and the threads it starts
  afterwards run on those CPUs only.  ``hrm sim --cpus`` keeps a simulated box off the
  CPUs of the host's control loop, as the drives' own hardware would be (on a two-core
  machine a box thread woken on the host's CPU delays the next SYNC: BENCHMARKS.md).

>>> import sys
>>> before = sys.getswitchinterval()
>>> with process_settings(switch_interval_s=0.001) as s:
...     round(sys.getswitchinterval(), 6), s.realtime_granted
(0.001, False)
>>> sys.getswitchinterval() == before
True
>>> with process_settings(switch_interval_s=None) as s:   # leave the interval alone
...     s.switch_interval_s == before
True
"""

from __future__ import annotations

import gc
import logging
import math
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Any

from hrm_ctrl.errors import DriverError

log = logging.getLogger("drivers.realtime")

SWITCH_INTERVAL_S = 2e-4
"""GIL switch interval the stack's processes run with (CPython default: 5 ms).

A thread waiting for a CAN frame or a control deadline must get the interpreter lock
back within a fraction of a frame time (135 us at 1 Mbit/s) and of a control period
(10 ms at 100 Hz); 0.2 ms does, for a few percent of interpreter overhead.  A process
that runs many busy threads besides the control loop (the host with the simulated box in
the same interpreter) pays more for the hand-overs than it gains: its entry point passes a
longer interval (``hrm`` with an in-process box: ``hrm_ctrl.cli._simwire``)."""

NORMAL_PRIORITY = 0
"""Realtime priority 0: keep the normal (``SCHED_OTHER``) policy.  The default, because
``SCHED_FIFO`` needs a right most accounts lack and a FIFO thread that spins starves the
rest of the machine; it is opt-in (``[control] realtime_priority`` in ``box.toml``)."""

REALTIME_PRIORITY_MAX = 99
"""Highest ``SCHED_FIFO`` priority Linux accepts (its FIFO priorities are 1..99)."""

REALTIME_PRIORITY_SAFE_MAX = 49
"""Highest priority the stack's threads take (``box.toml``'s safe range of
``realtime_priority``): at 50 and above they would preempt the kernel's interrupt threads
(PREEMPT_RT), the CAN controller's too."""


class GcHold:
    """Keeps the process's heap out of the cyclic garbage collector while held.

    A full (generation 2) collection walks every tracked object while holding the
    interpreter lock: in the test process 120-240 ms (measured with ``gc.callbacks``
    over ``tests/drivers``), longer with both cores busy, during which no receive
    thread stamps a heartbeat and an in-process box sends none: the heartbeat watchdog
    (350 ms) stopped every axis of an idle box on a 363 ms gap.  :meth:`acquire`
    freezes what exists (``gc.freeze``, cheap: the generations are moved to the
    permanent one as whole lists), so the collections that follow walk only what was
    allocated since; no ``gc.collect()`` first (at a second bring-up the drives are
    enabled: that collection would be the very pause).  The last :meth:`release` of the
    process unfreezes (``gc.unfreeze``).  Holds are counted across the process (two
    sessions in one process): one release never unfreezes another's hold.  Only the
    first hold freezes: what a long session allocates later (between streams too) is
    collected as usual, and cyclic garbage that existed at the freeze waits for the
    last release, so memory stays bounded however many streams a session plays.

    >>> a, b = GcHold(), GcHold()
    >>> a.acquire(); b.acquire(); frozen = gc.get_freeze_count() > 0
    >>> a.release(); still = gc.get_freeze_count() > 0
    >>> b.release(); frozen, still, GcHold.holders()
    (True, True, 0)
    >>> a.release()  # not held: nothing to undo
    """

    _lock = threading.Lock()
    _holders = 0

    def __init__(self) -> None:
        self.held = False

    @classmethod
    def holders(cls) -> int:
        """How many holds the process has now."""
        return cls._holders

    def acquire(self) -> None:
        """Hold; the first hold of the process freezes the heap."""
        with GcHold._lock:
            if self.held:
                return
            self.held = True
            GcHold._holders += 1
            if GcHold._holders == 1:
                gc.freeze()

    def release(self) -> None:
        """Give up this hold; the last one in the process unfreezes the heap."""
        with GcHold._lock:
            if not self.held:
                return
            self.held = False
            GcHold._holders -= 1
            if GcHold._holders == 0:
                gc.unfreeze()


class ProcessSettingsError(DriverError):
    """A process setting asked of :func:`process_settings` is out of range."""


MAX_CPU = 4095
"""Highest CPU number accepted in a CPU list (Linux's default NR_CPUS range)."""


def parse_cpus(text: str, where: str = "--cpus") -> frozenset[int]:
    """A CPU list as ``taskset -c`` writes it (``1``, ``0,2``, ``2-3``), each CPU one this
    process may run on; else a one-line :class:`ProcessSettingsError`.

    >>> sorted(parse_cpus("0"))
    [0]
    >>> parse_cpus("1-0")
    Traceback (most recent call last):
    ...
    drivers.realtime.ProcessSettingsError: --cpus: '1-0' is not a CPU list (e.g. 1, 0,2 or 2-3)
    """
    cpus: set[int] = set()
    for part in text.split(","):
        lo, _, hi = part.strip().partition("-")
        try:
            a, b = int(lo), int(hi) if hi else int(lo)
        except ValueError:
            a, b = 1, 0
        if not 0 <= a <= b <= MAX_CPU:
            raise ProcessSettingsError(f"{where}: {text!r} is not a CPU list (e.g. 1, 0,2 or 2-3)")
        cpus.update(range(a, b + 1))
    usable = available_cpus()
    missing = sorted(cpus - usable)
    if missing:
        raise ProcessSettingsError(
            f"{where}: CPU {missing[0]} is not available to this process "
            f"(available: {','.join(str(c) for c in sorted(usable))})"
        )
    return frozenset(cpus)


def split_cpus() -> tuple[frozenset[int], frozenset[int]] | None:
    """The CPUs this thread may use in two parts, (host, box): a simulated box in a process
    of its own on the highest one, the host's control loop on the others, as the drives'
    own hardware would leave the control PC alone; None with a single CPU.

    >>> parts = split_cpus()
    >>> parts is None or (parts[0].isdisjoint(parts[1]) and len(parts[1]) == 1)
    True
    """
    cpus = available_cpus()
    if len(cpus) < 2:
        return None
    box = frozenset({max(cpus)})
    return cpus - box, box


def cpu_list(cpus: frozenset[int]) -> str:
    """A CPU set as ``--cpus`` takes it.

    >>> cpu_list(frozenset({3, 0, 1}))
    '0,1,3'
    """
    return ",".join(str(c) for c in sorted(cpus))


def available_cpus() -> frozenset[int]:
    """The CPUs this thread may run on (all of them where the platform cannot tell)."""
    if hasattr(os, "sched_getaffinity"):
        return frozenset(os.sched_getaffinity(0))
    return frozenset(range(os.cpu_count() or 1))


@dataclass(frozen=True)
class AppliedSettings:
    """What :func:`process_settings` put in force (yielded by the context)."""

    switch_interval_s: float  # the GIL switch interval inside the context
    previous_switch_interval_s: float  # restored on exit
    realtime_priority: int  # SCHED_FIFO priority asked for (0: none asked)
    realtime_granted: bool  # the calling thread runs under SCHED_FIFO at that priority
    realtime_refusal: str | None = None  # why it was not granted (None: granted or not asked)
    cpus: frozenset[int] | None = None  # the CPUs the calling thread is kept on (None: all)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: the environment variable that sets every stack process's GIL switch interval (seconds)
SWITCH_INTERVAL_ENV = "HRM_SWITCH_INTERVAL_S"


def machine_switch_interval(switch_interval_s: float) -> float:
    """``switch_interval_s``, unless the machine sets its own (:data:`SWITCH_INTERVAL_ENV`):
    where a system call costs 30-40 us (a User-Mode-Linux guest, ``tools/vcan-guest``) the
    0.2 ms hand-overs between a session's threads took the one CPU from the drives' box
    process and the drives missed the host's heartbeat; 1 ms there brought it up.

    >>> machine_switch_interval(2e-4) if SWITCH_INTERVAL_ENV not in os.environ else 2e-4
    0.0002
    """
    text = os.environ.get(SWITCH_INTERVAL_ENV, "")
    if not text:
        return switch_interval_s
    try:
        value = float(text)
    except ValueError:
        raise ProcessSettingsError(f"{SWITCH_INTERVAL_ENV}: {text!r} is not a number") from None
    return check_switch_interval(value, SWITCH_INTERVAL_ENV)


def check_switch_interval(switch_interval_s: float, where: str = "switch_interval_s") -> float:
    """A usable GIL switch interval in seconds (finite, > 0), else a one-line error.

    >>> check_switch_interval(0.0)
    Traceback (most recent call last):
    ...
    drivers.realtime.ProcessSettingsError: switch_interval_s: must be a finite number > 0 s, got 0.0
    """
    if (
        isinstance(switch_interval_s, bool)
        or not isinstance(switch_interval_s, int | float)
        or not math.isfinite(switch_interval_s)
        or switch_interval_s <= 0
    ):
        raise ProcessSettingsError(
            f"{where}: must be a finite number > 0 s, got {switch_interval_s!r}"
        )
    return float(switch_interval_s)


def check_realtime_priority(priority: int, where: str = "realtime_priority") -> int:
    """A usable realtime priority (0 = normal scheduling, else 1..99), else a one-line error.

    >>> check_realtime_priority(100)
    Traceback (most recent call last):
    ...
    drivers.realtime.ProcessSettingsError: realtime_priority: must be an integer in 0..99, got 100
    """
    if (
        isinstance(priority, bool)
        or not isinstance(priority, int)
        or not NORMAL_PRIORITY <= priority <= REALTIME_PRIORITY_MAX
    ):
        raise ProcessSettingsError(
            f"{where}: must be an integer in {NORMAL_PRIORITY}..{REALTIME_PRIORITY_MAX}, "
            f"got {priority!r}"
        )
    return priority


CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"
"""Linux's PM QoS CPU latency interface: a 32-bit value written to it is the longest CPU
wake-up latency (us) the system accepts while the file stays open."""

CPU_LATENCY_NO_REQUEST_US = 2_000_000_000
"""The kernel's own "no constraint" (``PM_QOS_CPU_LATENCY_DEFAULT_VALUE``, 2000 s): a
``cpu_wakeup_latency_us`` this large opens nothing."""


class CpuLatencyRequest:
    """Hold a PM QoS CPU latency request of ``max_us`` microseconds until :meth:`close`
    (the kernel drops it when the file closes, a killed process included).

    At 0 an idle CPU polls instead of halting, so a thread woken by its timer or a frame
    runs at once: no exit from a deep C-state on a PC, and on a virtual machine no halted
    vCPU for the hypervisor to schedule back in (on the 2-core VM of BENCHMARKS.md, four
    20 s runs of the stall probe each way: 21, 34, 206 and 54 stalls over 0.5 ms with the
    request, 96, 770, 362 and 127 without).  The price is that idle CPUs
    spin (power, heat, a hypervisor's CPU time): it is opt-in, ``[control]
    cpu_wakeup_latency_us``, as cyclictest's ``--latency``.  Needs write access to
    :data:`CPU_LATENCY_DEVICE` (root); refused, the request is not held and
    :attr:`refusal` says why (one warning), as a refused ``SCHED_FIFO`` is.

    >>> import tempfile
    >>> with tempfile.NamedTemporaryFile() as f:
    ...     r = CpuLatencyRequest(0, f.name)
    ...     held, data = r.held, open(f.name, "rb").read()
    ...     r.close()
    >>> held, data == bytes(4), r.held   # 0 as a native 32-bit integer
    (True, True, False)
    >>> CpuLatencyRequest(CPU_LATENCY_NO_REQUEST_US).held   # no request: nothing opened
    False
    """

    def __init__(self, max_us: int, path: str = CPU_LATENCY_DEVICE) -> None:
        self.max_us = int(max_us)
        self.path = path
        self.refusal: str | None = None
        self._fd: int | None = None
        if not 0 <= self.max_us < CPU_LATENCY_NO_REQUEST_US:
            return
        fd: int | None = None
        try:
            fd = os.open(path, os.O_WRONLY)
            os.write(fd, self.max_us.to_bytes(4, sys.byteorder, signed=True))
        except OSError as exc:
            if fd is not None:
                os.close(fd)
            self.refusal = (
                f"CPU latency request {self.max_us} us refused ({path}: {exc.strerror or exc})"
            )
            log.warning("%s; CPUs may sleep", self.refusal)
            return
        self._fd = fd

    @property
    def held(self) -> bool:
        """Whether the request is in force."""
        return self._fd is not None

    def close(self) -> None:
        """Give the request back (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def step_below_starter() -> int:
    """Put the calling thread one ``SCHED_FIFO`` priority below the one it inherited (at
    least 1), if it runs under FIFO; return its priority now (0: normal scheduling).

    For a session's helper threads (the CAN log writers): under FIFO at the supervisor's
    own priority, a writer packing a batch holds the CPU until it blocks, and the
    supervisor, woken at its deadline on the same CPU, waits for it (threads of equal FIFO
    priority do not preempt one another).  One step below, the supervisor preempts it and
    gets the interpreter lock within the switch interval.  Lowering one's own priority
    needs no privilege.

    >>> step_below_starter()   # a thread under normal scheduling stays so
    0
    """
    try:
        if os.sched_getscheduler(0) != os.SCHED_FIFO:
            return NORMAL_PRIORITY
        priority = os.sched_getparam(0).sched_priority
        if priority > 1:
            priority -= 1
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return priority
    except (OSError, AttributeError):  # no FIFO on this platform: nothing to step down
        return NORMAL_PRIORITY


def realtime_permitted(priority: int) -> bool:
    """Whether a thread of this process may run under ``SCHED_FIFO`` at ``priority``: tried
    in a thread of its own that ends at once (nothing of the caller changes, nothing is
    logged).

    >>> realtime_permitted(1) in (True, False)
    True
    """
    granted: list[bool] = []

    def probe() -> None:
        restore, _ = _raise_priority(check_realtime_priority(priority))
        granted.append(restore is not None)

    thread = threading.Thread(target=probe, name="realtime-probe", daemon=True)
    thread.start()
    thread.join()
    return bool(granted and granted[0])


def _set_switch_interval(seconds: float) -> None:
    """Set the GIL switch interval to the nearest whole microsecond.

    CPython keeps the interval in whole microseconds and truncates ``1e6 * seconds``:
    setting back the value ``sys.getswitchinterval()`` returned could lose a
    microsecond each time (0.0002 s reads back as 0.00019999999999999998).  Aiming at
    the middle of the microsecond makes every restore exact."""
    microseconds = max(1, round(seconds * 1e6))
    sys.setswitchinterval((microseconds + 0.5) * 1e-6)


def _raise_priority(priority: int) -> tuple[Callable[[], None] | None, str | None]:
    """Put the calling thread under SCHED_FIFO at ``priority``.

    Returns (a function restoring the previous policy, None) when granted, else
    (None, why not)."""
    if not hasattr(os, "sched_setscheduler") or not hasattr(os, "SCHED_FIFO"):
        return None, f"SCHED_FIFO is not available on this platform ({sys.platform})"
    try:
        policy = os.sched_getscheduler(0)
        param = os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return None, f"SCHED_FIFO priority {priority} refused ({exc.strerror or exc})"

    def restore() -> None:
        try:
            os.sched_setscheduler(0, policy, param)
        except OSError as exc:  # pragma: no cover - lowering one's own priority is allowed
            log.warning("could not restore the scheduling policy: %s", exc)

    return restore, None


@contextmanager
def process_settings(
    switch_interval_s: float | None = SWITCH_INTERVAL_S,
    realtime_priority: int = NORMAL_PRIORITY,
    cpus: frozenset[int] | None = None,
) -> Iterator[AppliedSettings]:
    """Apply the GIL switch interval and the scheduling priority; restore both on exit.

    Args:
        switch_interval_s: GIL switch interval for the whole process, or ``None`` to
            leave it as it is (e.g. when a thread only raises its own priority); the
            machine's own (:func:`machine_switch_interval`) where it sets one.
        realtime_priority: ``SCHED_FIFO`` priority 1..99 for the calling thread (and the
            threads it starts inside the context), best effort; 0 leaves the policy alone.
        cpus: the CPUs the calling thread (and the threads it starts inside the context)
            runs on (:func:`parse_cpus`); ``None`` leaves the affinity alone.

    Yields the :class:`AppliedSettings`.  Raises :class:`ProcessSettingsError` on an
    out-of-range argument (before changing anything).  Enter it once per process (or
    per thread for the priority alone): the switch interval is process-wide, so a
    context restores the value it found, whatever other threads did meanwhile.
    """
    new_interval = (
        None
        if switch_interval_s is None
        else machine_switch_interval(check_switch_interval(switch_interval_s))
    )
    priority = check_realtime_priority(realtime_priority)
    if cpus is not None and (not cpus or not cpus <= available_cpus()):
        raise ProcessSettingsError(
            f"cpus: {sorted(cpus)} is not a non-empty set of CPUs this process may run on"
        )
    previous = sys.getswitchinterval()
    restore_sched: Callable[[], None] | None = None
    refusal: str | None = None
    previous_cpus = None
    if cpus is not None and hasattr(os, "sched_setaffinity"):
        previous_cpus = os.sched_getaffinity(0)
        os.sched_setaffinity(0, cpus)
    if new_interval is not None:
        _set_switch_interval(new_interval)
    try:
        if priority > NORMAL_PRIORITY:
            restore_sched, refusal = _raise_priority(priority)
            if refusal is not None:
                log.warning("%s; running under normal scheduling", refusal)
        yield AppliedSettings(
            switch_interval_s=sys.getswitchinterval(),
            previous_switch_interval_s=previous,
            realtime_priority=priority,
            realtime_granted=restore_sched is not None,
            realtime_refusal=refusal,
            cpus=None if previous_cpus is None else frozenset(cpus or ()),
        )
    finally:
        if restore_sched is not None:
            restore_sched()
        if previous_cpus is not None:
            os.sched_setaffinity(0, previous_cpus)
        if new_interval is not None:
            _set_switch_interval(previous)
