"""Opening a box: the one way every entry point gets a drive session.

:func:`open_box` opens the box a command drives (its real buses from a
:class:`~drivers.config.BoxConfig`, a box in its own process whose buses the configuration
names, or a simulated box: :class:`~hrm_ctrl.runtime.simulated.SimulatedBox` to start one
for this block, in its own process by default or in this one,
:class:`~hrm_ctrl.runtime.simulated.RunningSim` for one that outlives it),
with its :class:`~drivers.session.DriveSession` (CAN logs, run record) and its feedback
watches (:mod:`hrm_ctrl.runtime.watches`), and brings the drives up.  Before anything
opens, every drive's device file is checked against what hrm needs
(:func:`drivers.device_check.check_box`, as ``hrm box check``): a refusal is one line, and
nothing is opened or sent.

A box in its own process (``hrm sim --control``) is either started for the block
(:class:`~hrm_ctrl.runtime.process_box.ProcessBox`; the session's threads then keep off its
CPU) or started elsewhere (the HIL fixtures' session-wide box): then the configuration names
its buses, as for real ones.

The session opens whole or not at all (interrupts deferred); on any exit (the block ends,
an exception in it, SIGTERM or Ctrl-C as an interrupt in it) the box closes in this order:

1. the watches stop (their summaries go into the run record);
2. the session finishes and closes (:meth:`DriveSession.__exit__`: after a signal every
   axis is quick-stopped first; every drive disabled, NMT pre-operational, host heartbeat
   off; then the buses and CAN logs close and the run record is written);
3. the simulated box started for the block (in this process, or its own) stops.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.runtime.process_box import BoxProcess, ProcessBox, simulated_box_process
from hrm_ctrl.runtime.simulated import (
    PROCESS_WIRE,
    SIM_LISTEN_S,
    RunningSim,
    SimControl,
    SimulatedBox,
    running_box,
)

if TYPE_CHECKING:
    from drivers.config import BoxConfig
    from drivers.identity import BoxIdentity
    from drivers.safety.limits import LimitChecker
    from drivers.safety.watches import FeedbackWatches
    from drivers.session import CalibrationRef, DriveSession
    from hrm_ctrl.ropes.actuation import Actuation
    from hrm_ctrl.ropes.estimator import Compensation


@dataclass(frozen=True)
class SessionOptions:
    """The drive session's parameters: where its CAN logs and run record go (``log_dir``;
    None: nowhere) in which format (``log_suffix``), its ``run_name`` (None: the time),
    ``take_over`` (reset the drives even when another master is heard), the
    ``calibration`` used and ``allow_uncalibrated``, the listen before the first reset
    (``listen_s``; None: the session's default, shorter on the in-process box), and what
    the run record keeps besides (``record_extra``)."""

    log_dir: Path | str | None = None
    log_suffix: str = ".blf"
    run_name: str | None = None
    take_over: bool = False
    calibration: CalibrationRef | None = None
    allow_uncalibrated: bool = False
    listen_s: float | None = None
    record_extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class WatchOptions:
    """Which feedback watches run while the drives are enabled: the tension board's (when
    the configuration has a ``[tension]`` table) and the rope consistency check; the
    tension watch's ``grace_s`` for the board's first frame; the rope layer they watch
    (``actuation``; None: the session's); what a feed-forward added to the rows played
    (``compensation``, :class:`hrm_ctrl.ropes.estimator.Compensation`; None: nothing),
    which the rope consistency check takes off."""

    tension: bool = True
    ropes: bool = True
    grace_s: float = 0.0
    actuation: Actuation | None = None
    compensation: Compensation | None = None


NO_WATCHES = WatchOptions(tension=False, ropes=False)


@dataclass
class OpenBox:
    """An open box: its ``session``, its ``watches`` (started by :meth:`bring_up`), the
    ``config`` the session runs on (rewritten onto the simulated box's buses with one)
    and the simulated box started or used for it (``sim``: its controls,
    :class:`~hrm_ctrl.runtime.simulated.SimControl`: a
    :class:`~hrm_ctrl.runtime.process_box.BoxProcess` for a box in its own process; None
    on real buses)."""

    session: DriveSession
    watches: FeedbackWatches
    config: BoxConfig
    sim: SimControl | BoxProcess | None = None

    def bring_up(self, bring_up: Callable[[DriveSession], object] | None = None) -> None:
        """Bring the drives up (``bring_up(session)``; default
        :meth:`DriveSession.bring_up`), then start the watches.  The bring-up runs at the
        scheduling of the session's threads (``SCHED_FIFO`` where it got it, as with
        ``--sim``), and so do the threads it starts (its SDO transfers in parallel): at
        normal priority beside two CPU burners (load 16-28) 15 drives' SDO answers went
        unread for the 1 s SDO timeout."""
        with self.session.thread_scheduling():
            if bring_up is None:
                self.session.bring_up()
            else:
                bring_up(self.session)
        self.watches.start()


def caller_scheduling(session: DriveSession) -> contextlib.AbstractContextManager[object]:
    """The scheduling of the thread that works with an open ``session`` (computing between
    its moves, reading an instrument): with the session's threads under ``SCHED_FIFO`` (as
    with ``--sim`` where permitted), ``SCHED_FIFO`` one below theirs; else as it is.

    The session's threads share this thread's GIL: computing at normal priority while the
    watches ran and preempted by the machine's other work, it held the GIL while it
    waited, and the watches' reader fell behind the tension board (the console's ``run``
    beside two CPU burners at load 14-24: frames 583 and 826 ms old, the limit 500 ms).
    One below, not at theirs: a session's thread woken by a frame preempts it (at the same
    priority it would wait for a CPU until this thread blocked)."""
    from drivers.realtime import process_settings

    priority = session.scheduling.granted_priority - 1
    if priority < 1:
        return contextlib.nullcontext()
    return process_settings(switch_interval_s=None, realtime_priority=priority)


def identify_box(config: BoxConfig, actuation: LimitChecker, *, prog: str = "hrm") -> BoxIdentity:
    """The identity of the box of ``config`` (real buses, or a box behind them): its
    drives configured (NMT reset, identity objects read, SDO configuration), never
    enabled, then the session closed (``hrm calibrate use VERSION --box``)."""
    options = SessionOptions()  # no calibration: nothing is enabled
    with open_box(config, actuation, options, watches=NO_WATCHES, bring_up=False, prog=prog) as box:
        box.session.configure()
        identity = box.session.box_identity
    assert identity is not None  # configure() reads it
    return identity


@contextlib.contextmanager
def open_box(
    config: BoxConfig,
    actuation: LimitChecker,
    options: SessionOptions,
    *,
    sim: SimulatedBox | RunningSim | ProcessBox | None = None,
    watches: WatchOptions = WatchOptions(),
    bring_up: bool | Callable[[DriveSession], object] = True,
    prog: str = "hrm",
) -> Iterator[OpenBox]:
    """The box of ``config`` opened for ``actuation`` (the rope layer, or a subset of it);
    see the module docstring for what opens and the order things close in.  With
    ``bring_up`` True (or a callable doing it, e.g. with a progress display) the drives are
    up and the watches running when the block starts; with False the caller calls
    :meth:`OpenBox.bring_up` (after opening what must be refused before anything is sent,
    e.g. a sensor's port)."""
    from drivers.device_check import check_box
    from drivers.interrupts import deferred_interrupts
    from drivers.realtime import process_settings
    from drivers.safety.watches import FeedbackWatches
    from drivers.session import DriveSession
    from hrm_ctrl.runtime.watches import feedback_watches

    # every drive's device file offers what hrm needs (hrm box check), before anything opens
    check_box(config).raise_if_refused()
    with contextlib.ExitStack() as stack:
        simbox: SimControl | BoxProcess | None = None
        listen_s = options.listen_s
        host_cpus = None
        if isinstance(sim, SimulatedBox) and sim.wire == PROCESS_WIRE:
            config, simbox = stack.enter_context(simulated_box_process(config, sim, prog))
        elif isinstance(sim, SimulatedBox):
            running = stack.enter_context(running_box(config, sim, prog))
            config, simbox = running.config, running.sim
        elif isinstance(sim, RunningSim):
            config, simbox = sim.config, sim.sim
        elif isinstance(sim, ProcessBox):
            process = sim.start()
            stack.callback(lambda: process.close())  # looked up at the exit
            simbox, host_cpus = process, process.host_cpus
            if config.tension is None:  # the box's board, at the [tension] defaults
                config = config.with_tension(port=str(process.ready["tension_port"]))
        if listen_s is None and isinstance(sim, SimulatedBox | RunningSim):
            listen_s = SIM_LISTEN_S  # private channels of a fresh name: no other master
        kw: dict[str, Any] = {} if listen_s is None else {"listen_s": listen_s}
        # every thread of the session (and its watches) on the CPUs a box process leaves
        # free; the caller's thread gets its own back
        placed = (
            contextlib.nullcontext()
            if host_cpus is None
            else process_settings(switch_interval_s=None, cpus=host_cpus)
        )
        with placed:  # the bring-up's threads too
            with deferred_interrupts():  # the session is open and entered, or not at all
                session = stack.enter_context(
                    DriveSession(
                        config,
                        actuation,
                        log_dir=options.log_dir,
                        log_suffix=options.log_suffix,
                        run_name=options.run_name,
                        take_over=options.take_over,
                        calibration=options.calibration,
                        allow_uncalibrated=options.allow_uncalibrated,
                        **kw,
                    )
                )
                session.record_extra.update(options.record_extra)
                if watches.tension or watches.ropes:
                    # the tension board's port opened first: a bad port is refused before any
                    # NMT reset
                    watched = actuation if watches.actuation is None else watches.actuation
                    running_watches = stack.enter_context(
                        feedback_watches(
                            config,
                            watched,  # type: ignore[arg-type]
                            session,
                            tension=watches.tension,
                            ropes=watches.ropes,
                            start=False,
                            grace_s=watches.grace_s,
                            compensation=watches.compensation,
                        )
                    )
                else:
                    running_watches = FeedbackWatches(scheduling=session.thread_scheduling)
            box = OpenBox(session, running_watches, config, simbox)
            if bring_up is True:
                box.bring_up()
            elif callable(bring_up):
                box.bring_up(bring_up)
        yield box
