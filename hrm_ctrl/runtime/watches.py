"""The feedback watches of a drive session (:func:`hrm_ctrl.runtime.box.open_box` wires them).

While the drives are enabled, two threads beside the supervisor watch the arm
(``drivers.safety.watches``): the tension-sensor board when the bus configuration has
a ``[tension]`` table (the simulated box's board on ``--sim``), and the rope layer's
consistency check (:class:`hrm_ctrl.ropes.estimator.RopeConsistencyCheck`, injected into
the drivers' :class:`~drivers.safety.watches.RopeWatch`) on the feedback every
``ROPE_EVERY_CYCLES`` control periods.  Either reports through the session's monitor,
and the supervisor stops every axis; the run record keeps their summaries
(``watches``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from drivers.config import BoxConfig
from drivers.safety.watches import FeedbackWatches
from hrm_ctrl.ropes.actuation import Actuation

if TYPE_CHECKING:
    from drivers.session import DriveSession
    from drivers.tension_sensor import TensionSensorReader


def watches_of(
    config: BoxConfig,
    actuation: Actuation,
    session: DriveSession,
    *,
    reader: TensionSensorReader | None = None,
    tension: bool = True,
    ropes: bool = True,
    grace_s: float = 0.0,
) -> FeedbackWatches:
    """The watches of ``session``, not started: the tension board's over ``reader`` (None:
    its port opened here, closed when the watches stop; a bad port is refused now) when
    the configuration has a ``[tension]`` table and ``tension``, and the rope consistency
    check when ``ropes``.  ``grace_s``: how long after its start the tension watch waits
    for the board's first frame (0: the port has been open since before the bring-up)."""
    from drivers.safety.causes import StopKind
    from drivers.safety.watches import ROPE_EVERY_CYCLES, RopeWatch
    from drivers.tension_sensor import TensionSensorReader, TensionWatch
    from hrm_ctrl.ropes.estimator import RopeConsistencyCheck

    monitor = session.monitor
    # the watches' threads get the session's scheduling (SCHED_FIFO when it has it)
    watches = FeedbackWatches(scheduling=session.thread_scheduling)
    t = config.tension
    if t is not None and tension:
        close = None
        if reader is None:
            with session.thread_scheduling():
                reader = TensionSensorReader(
                    t.port, actuation.n_motors, baudrate=t.baudrate, stale_after_s=t.stale_s
                ).open()
            close = reader.close
        watch = TensionWatch(
            reader,
            actuation.motor_ids,
            lambda text: monitor.report(StopKind.TENSION, text),
            min_N=t.slack_N,
            max_N=t.limit_N,
            max_bad_per_s=t.garbage_per_s,
            grace_s=grace_s,
        )
        watches.add("tension", watch, close=close)
    if ropes:
        period_s = config.control.period_s * ROPE_EVERY_CYCLES
        check = RopeConsistencyCheck(actuation, rate_hz=1.0 / period_s)
        watches.add(
            "rope_consistency",
            RopeWatch(monitor, check, lambda: session.supervisor.targets, period_s),
        )
    return watches


@contextmanager
def feedback_watches(
    config: BoxConfig,
    actuation: Actuation,
    box: DriveSession,
    *,
    tension: bool = True,
    ropes: bool = True,
    start: bool = True,
    grace_s: float = 0.0,
) -> Iterator[FeedbackWatches]:
    """The watches of ``box`` (a :class:`drivers.session.DriveSession`,
    :func:`watches_of`): the tension board's port is opened at once (a bad port is
    refused before anything is sent), the watches start now (``start``) or when the
    caller calls ``.start()`` after the bring-up; on leaving they stop and their summaries
    go into the run record.  ``tension`` / ``ropes`` False leave a watch out (the
    benchmark compares them)."""
    watches = FeedbackWatches(scheduling=box.thread_scheduling)
    try:
        watches = watches_of(config, actuation, box, tension=tension, ropes=ropes, grace_s=grace_s)
        if start:
            watches.start()
        yield watches
    finally:
        watches.stop()
        box.record_extra["watches"] = watches.summary()
