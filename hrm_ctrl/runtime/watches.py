"""The feedback watches of a drive session (:func:`hrm_ctrl.runtime.box.open_box` wires them).

While the drives are enabled, two threads beside the supervisor watch the arm
(``drivers.safety.watches``): the tension-sensor board when the bus configuration has
a ``[tension]`` table (the simulated box's board on ``--sim``), and the rope layer's
consistency check (:class:`hrm_ctrl.ropes.estimator.RopeConsistencyCheck`, injected into
the drivers' :class:`~drivers.safety.watches.RopeWatch`) on the feedback every
``ROPE_EVERY_CYCLES`` control periods (on a compensated plan less what the feed-forward
added, :class:`~hrm_ctrl.ropes.estimator.Compensation`).  Either reports through the
session's monitor, and the supervisor stops every axis; the run record keeps their
summaries (``watches``).

**The likely cause.**  When every rope of one joint is slack at once within
:data:`SUSPECT_AFTER_ENABLE_S` of the enable while a calibration is in use, the tension
watch's stop message says so and names the calibration as the suspect
(:func:`slack_cause`): a broken rope slackens one rope, a calibration whose motor zeros
are not this arm's slackens a joint's ropes together as soon as the drives hold them.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np

from drivers.config import BoxConfig
from drivers.safety.watches import FeedbackWatches
from hrm_ctrl.ropes.actuation import Actuation

if TYPE_CHECKING:
    from drivers.run_record import CalibrationRef
    from drivers.session import DriveSession
    from drivers.tension_sensor import TensionSensorReader
    from hrm_ctrl.ropes.estimator import Compensation

SUSPECT_AFTER_ENABLE_S = 5.0  # "right after the enable": the drives have just taken hold


def slack_joint(tensions_N: np.ndarray, joint_of_motor: np.ndarray, min_N: float) -> int | None:
    """The first joint (0-based) every rope of which is below ``min_N``, or None.

    >>> slack_joint(np.array([30.0, 0.0, 0.1, 0.2]), np.array([0, 0, 1, 1]), 5.0)
    1
    >>> slack_joint(np.array([30.0, 0.0, 0.1, 20.0]), np.array([0, 0, 1, 1]), 5.0) is None
    True
    """
    low = tensions_N < min_N
    for j in np.unique(joint_of_motor).tolist():
        if low[joint_of_motor == j].all():
            return int(j)
    return None


def slack_cause(
    text: str,
    tensions_N: np.ndarray | None,
    motor_ids: Sequence[str],
    joint_of_motor: np.ndarray,
    min_N: float,
    calibration: CalibrationRef | None,
    since_enable_s: float | None,
) -> str:
    """The tension watch's stop ``text``, with the likely cause when a whole joint's ropes
    are slack at once right after the enable with a calibration in use.

    >>> from drivers.run_record import CalibrationRef
    >>> ref = CalibrationRef(3, "0" * 64, "store/v0003.json")
    >>> t = np.array([30.0, 30.0, 0.0, 0.2])
    >>> print(slack_cause("rope j02r0: tension 0.0 N below 5 N (slack or broken)", t,
    ...       ["j01r0", "j01r1", "j02r0", "j02r1"], np.array([0, 0, 1, 1]), 5.0, ref, 0.4))
    ... # doctest: +NORMALIZE_WHITESPACE
    rope j02r0: tension 0.0 N below 5 N (slack or broken); every rope of joint 2 (j02r0 0.0 N,
    j02r1 0.2 N) slack at once 0.4 s after the enable: likely the calibration in use
    (v0003, store/v0003.json), its motor zeros not this arm's, rather than broken ropes
    (hrm calibrate show; hrm calibrate zero)
    """
    if (
        calibration is None
        or tensions_N is None
        or since_enable_s is None
        or not 0.0 <= since_enable_s <= SUSPECT_AFTER_ENABLE_S
        or tensions_N.shape != (len(motor_ids),)
    ):
        return text
    j = slack_joint(tensions_N, joint_of_motor, min_N)
    if j is None:
        return text
    ropes = ", ".join(
        f"{motor_ids[i]} {tensions_N[i]:.1f} N" for i in np.flatnonzero(joint_of_motor == j)
    )
    return (
        f"{text}; every rope of joint {j + 1} ({ropes}) slack at once {since_enable_s:.1f} s "
        f"after the enable: likely the calibration in use (v{calibration.version:04d}, "
        f"{calibration.source}), its motor zeros not this arm's, rather than broken ropes "
        "(hrm calibrate show; hrm calibrate zero)"
    )


def watches_of(
    config: BoxConfig,
    actuation: Actuation,
    session: DriveSession,
    *,
    reader: TensionSensorReader | None = None,
    tension: bool = True,
    ropes: bool = True,
    grace_s: float = 0.0,
    compensation: Compensation | None = None,
) -> FeedbackWatches:
    """The watches of ``session``, not started: the tension board's over ``reader`` (None:
    its port opened here, closed when the watches stop; a bad port is refused now) when
    the configuration has a ``[tension]`` table and ``tension``, and the rope consistency
    check when ``ropes``.  ``grace_s``: how long after its start the tension watch waits
    for the board's first frame (0: the port has been open since before the bring-up).
    ``compensation``: what a feed-forward added to the rows played, taken off before the
    consistency check (:class:`~hrm_ctrl.ropes.estimator.RopeConsistencyCheck`)."""
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
        board = reader

        def on_fault(text: str) -> None:
            """Report the watch's fault, with its likely cause (:func:`slack_cause`); the
            report is made whatever the cause's reading meets."""
            try:
                tensions = board.latest().tensions_N
                armed = monitor.hb_armed_at
                since = None if armed is None else session.supervisor.clock() - armed
                text = slack_cause(
                    text,
                    tensions,
                    actuation.motor_ids,
                    np.asarray(actuation.joint_of_motor),
                    t.slack_N,
                    session.calibration,
                    since,
                )
            except Exception:  # stale or unreadable: the text says why already
                pass
            monitor.report(StopKind.TENSION, text)

        watch = TensionWatch(
            reader,
            actuation.motor_ids,
            on_fault,
            min_N=t.slack_N,
            max_N=t.limit_N,
            max_bad_per_s=t.garbage_per_s,
            grace_s=grace_s,
        )
        watches.add("tension", watch, close=close)
    if ropes:
        period_s = config.control.period_s * ROPE_EVERY_CYCLES
        check = RopeConsistencyCheck(actuation, rate_hz=1.0 / period_s, compensation=compensation)
        watches.add(
            "rope_consistency",
            RopeWatch(monitor, check, period_s),
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
    compensation: Compensation | None = None,
) -> Iterator[FeedbackWatches]:
    """The watches of ``box`` (a :class:`drivers.session.DriveSession`,
    :func:`watches_of`): the tension board's port is opened at once (a bad port is
    refused before anything is sent), the watches start now (``start``) or when the
    caller calls ``.start()`` after the bring-up; on leaving they stop and their summaries
    go into the run record.  ``tension`` / ``ropes`` False leave a watch out (the
    benchmark compares them); ``compensation`` as for :func:`watches_of`."""
    watches = FeedbackWatches(scheduling=box.thread_scheduling)
    try:
        watches = watches_of(
            config,
            actuation,
            box,
            tension=tension,
            ropes=ropes,
            grace_s=grace_s,
            compensation=compensation,
        )
        if start:
            watches.start()
        yield watches
    finally:
        watches.stop()
        box.record_extra["watches"] = watches.summary()
