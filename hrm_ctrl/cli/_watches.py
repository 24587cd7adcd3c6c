"""Wiring the feedback watches into a drive session (``hrm run``, ``hrm demo``).

While the drives are enabled, two threads beside the supervisor watch the arm
(``drivers.safety.watches``): the tension-sensor board when the bus configuration has
a ``[tension]`` table (``--sim`` wires the simulated box's board), and the rope layer's
consistency check (:class:`hrm_ctrl.ropes.estimator.RopeConsistencyCheck`, injected into
the drivers' :class:`~drivers.safety.watches.RopeWatch`) on the feedback every
``ROPE_EVERY_CYCLES`` control periods.  Either reports through the session's monitor,
and the supervisor stops every axis; the run record keeps their summaries
(``watches``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from drivers.config import BoxConfig
from hrm_ctrl.ropes.actuation import Actuation


@contextmanager
def feedback_watches(
    config: BoxConfig,
    actuation: Actuation,
    box: Any,
    *,
    tension: bool = True,
    ropes: bool = True,
    start: bool = True,
) -> Iterator[Any]:
    """The watches of ``box`` (a :class:`drivers.session.DriveSession`): the tension
    board's port is opened at once (a bad port is refused before anything is sent),
    the watches start now (``start``) or when the caller calls ``.start()`` after the
    bring-up; on leaving they stop and their summaries go into the run record.
    ``tension`` / ``ropes`` False leave a watch out (the benchmark compares them)."""
    from drivers.safety.causes import StopKind
    from drivers.safety.watches import ROPE_EVERY_CYCLES, FeedbackWatches, RopeWatch
    from drivers.tension_sensor import TensionSensorReader, TensionWatch
    from hrm_ctrl.ropes.estimator import RopeConsistencyCheck

    monitor = box.monitor
    # the watches' threads get the session's scheduling (SCHED_FIFO when it has it)
    watches = FeedbackWatches(scheduling=box.thread_scheduling)
    try:
        t = config.tension
        if t is not None and tension:
            with box.thread_scheduling():
                reader = TensionSensorReader(
                    t.port, actuation.n_motors, baudrate=t.baudrate, stale_after_s=t.stale_s
                ).open()
            watch = TensionWatch(
                reader,
                actuation.motor_ids,
                lambda text: monitor.report(StopKind.TENSION, text),
                min_N=t.slack_N,
                max_N=t.limit_N,
                max_bad_per_s=t.garbage_per_s,
                # The port was opened before the bring-up: by the time the watch starts
                # the board has had a second to answer, so no grace for a silent one.
                grace_s=0.0,
            )
            watches.add("tension", watch, close=reader.close)
        if ropes:
            period_s = config.control.period_s * ROPE_EVERY_CYCLES
            check = RopeConsistencyCheck(actuation, rate_hz=1.0 / period_s)
            watches.add(
                "rope_consistency",
                RopeWatch(monitor, check, lambda: box.supervisor.targets, period_s),
            )
        if start:
            watches.start()
        yield watches
    finally:
        watches.stop()
        box.record_extra["watches"] = watches.summary()
