"""Collecting kinematic calibration data: drive the arm through configurations and read an
instrument at each.

:func:`collect_poses` takes a drive session that is brought up (anything with ``actual``,
the drives' counts at enable, and ``stream(source)``, as :class:`drivers.session.DriveSession`)
and an instrument (anything with ``measure(n)``, the end point averaged over ``n``
samples, in the instrument's frame, mm, as ``drivers.tracker.TrackerReader``).  For each
target configuration it streams one move (:func:`move_table`) and a hold while the arm
settles, then measures.  Nothing here knows whether the box is real or simulated.

The poses it returns are the contract of :func:`calibration.kinematic.read_pose_csv`: the
*commanded* angles, i.e. the rope geometry's (:meth:`Actuation.commanded_angles`: less the
zero offsets the rope layer was built with, so the fit, made against the robot
description, estimates the offsets themselves, not a correction of the active ones) of the
counts commanded at each pose (the rope layer's inverse of the rounded counts, not the
target angles: a count is 0.5 um of rope, 4e-5 rad at the hole radius, which over 24
joints and a 2 m arm is tens of um at the end point), and the measured points.

A move interpolates the joint angles with the minimum-jerk profile
``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`` (rest to rest: speed and acceleration 0 at
both ends), each cycle's counts through the rope layer, so every cycle is one
configuration of the arm (a straight line in counts is not, and strains the ropes).  Its
duration is the longest a motor needs at ``rate_fraction`` of its speed limit (peak speed
``1.875 d / T`` for a travel of ``d`` counts), acceleration (``5.774 d / T^2``) and jerk
(``60 d / T^3``) limits; the table is checked against every rope limit and made slower
(x1.5, a few times) if the rope geometry's curvature still breaks one.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> z = np.zeros(12)
>>> table = move_table(act, (z, z), (z + 0.2, z - 0.1), 0.01)
>>> bool(np.array_equal(table[-1], act.counts_from_angles(z + 0.2, z - 0.1))), len(table) > 10
(True, True)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from calibration.kinematic import PoseData
from drivers.sources import CountsSource
from hrm_ctrl.errors import CalibrationDataError, HrmError
from hrm_ctrl.ropes.actuation import Actuation

RATE_FRACTION = 0.5  # of each motor's speed, acceleration and jerk limits
SETTLE_S = 0.5  # hold at each pose before the instrument reads it
MAX_SLOWDOWNS = 5
MAX_POSES = 1000  # a collection drives the arm: at a few seconds a pose, about an hour

# peak |s'|, |s''|, |s'''| of the minimum-jerk profile on tau in [0, 1]
_PEAK_SPEED = 1.875
_PEAK_ACCEL = 10.0 / math.sqrt(3.0)
_PEAK_JERK = 60.0


class SessionLike(Protocol):
    """What :func:`collect_poses` needs of a drive session (brought up)."""

    actual: np.ndarray | None

    def stream(self, source: Any) -> Any: ...


class PointReader(Protocol):
    """An instrument: the end point in its frame (mm), averaged over ``n`` samples."""

    def measure(self, n: int) -> Any: ...


def _limit(actuation: Any, name: str, fraction: float) -> np.ndarray:
    v = getattr(actuation, name, None)
    if v is None:
        return np.full(len(actuation.motor_ids), np.inf)
    return np.asarray(v, dtype=np.float64) * fraction


def move_table(
    actuation: Actuation,
    start: tuple[np.ndarray, np.ndarray],
    end: tuple[np.ndarray, np.ndarray],
    period_s: float,
    *,
    rate_fraction: float = RATE_FRACTION,
) -> np.ndarray:
    """Counts (cycles, n) of a rest-to-rest move from true angles ``start`` (the table's
    first row) to ``end`` (its last row); see the module docstring.  Where the drives are
    not at the first row (the first move, from wherever the arm was enabled), the
    :class:`~drivers.sources.CountsSource` that plays it leads in to it."""
    a0, t0 = (np.asarray(x, dtype=float) for x in start)
    a1, t1 = (np.asarray(x, dtype=float) for x in end)
    c0 = actuation.counts_from_angles(a0, t0)
    c1 = actuation.counts_from_angles(a1, t1)
    d = np.abs(c1 - c0).astype(np.float64)
    v = _limit(actuation, "max_rate_counts_per_s", rate_fraction)
    acc = _limit(actuation, "max_accel_counts_per_s2", rate_fraction)
    jerk = _limit(actuation, "max_jerk_counts_per_s3", rate_fraction)
    duration_s = float(
        max(
            np.max(_PEAK_SPEED * d / v),
            np.max(np.sqrt(_PEAK_ACCEL * d / acc)),
            np.max(np.cbrt(_PEAK_JERK * d / jerk)),
            period_s,
        )
    )
    error: HrmError | None = None
    for _ in range(MAX_SLOWDOWNS + 1):
        n = max(2, math.ceil(duration_s / period_s))
        tau = np.arange(1, n + 1, dtype=np.float64)[:, None] / n
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
        body = actuation.counts_from_angles(a0 + s * (a1 - a0), t0 + s * (t1 - t0))
        body[-1] = c1
        table = np.concatenate([c0[None, :], body], axis=0)
        try:
            actuation.check_counts(table, dt_s=period_s)
            return table
        except HrmError as exc:
            error = exc
            duration_s *= 1.5
    raise CalibrationDataError(f"calibration move: no table within the motor limits: {error}")


def _point_of(measurement: Any) -> np.ndarray:
    """The (3,) point of an instrument's measurement (an array, or an object with
    ``point_mm`` or ``mean_mm``)."""
    for name in ("point_mm", "mean_mm"):
        if hasattr(measurement, name):
            measurement = getattr(measurement, name)
            break
    p = np.asarray(measurement, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise CalibrationDataError(f"instrument: a measurement is not one finite point: {p!r}")
    return p


def travel_order(alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """An order of the configurations (N, 12) each that keeps the moves short: from the
    straight arm, always on to the nearest not yet visited (largest joint-angle change);
    the set of poses, and so the fit, is the same in any order.

    >>> a = np.array([[0.5] * 12, [0.1] * 12, [0.3] * 12]); t = np.zeros((3, 12))
    >>> travel_order(a, t).tolist()
    [1, 2, 0]
    """
    q = np.concatenate([np.asarray(alpha, float), np.asarray(theta, float)], axis=1)
    left = list(range(len(q)))
    here = np.zeros(q.shape[1])
    order: list[int] = []
    while left:
        d = np.abs(q[left] - here).max(axis=1)
        k = left.pop(int(np.argmin(d)))
        order.append(k)
        here = q[k]
    return np.array(order, dtype=np.int64)


def collect_poses(
    session: SessionLike,
    actuation: Actuation,
    reader: PointReader,
    alpha: np.ndarray,
    theta: np.ndarray,
    *,
    period_s: float,
    samples: int = 10,
    settle_s: float = SETTLE_S,
    rate_fraction: float = RATE_FRACTION,
    return_home: bool = True,
    source: str = "collected",
    progress: Callable[[int, int, np.ndarray], None] | None = None,
) -> PoseData:
    """Drive the arm to each target configuration (true angles, (N, 12) each), hold
    ``settle_s``, read ``reader.measure(samples)`` (moves at ``rate_fraction`` of the motor
    limits, at most 1), and at the end (``return_home``) move back to the configuration the
    arm started in; return the poses (commanded angles and
    measured points, see the module docstring).  ``progress(k, N, point)`` is called after
    each pose.  A safety stop raises what the session raises (nothing is measured after)."""
    a = np.asarray(alpha, dtype=float)
    t = np.asarray(theta, dtype=float)
    nj = actuation.robot.n_joints
    if a.ndim != 2 or a.shape[1] != nj or t.shape != a.shape or not 1 <= len(a) <= MAX_POSES:
        raise CalibrationDataError(
            f"collect: targets must be (N, {nj}) angles, 1 <= N <= {MAX_POSES}, got "
            f"{a.shape} and {t.shape}"
        )
    if not (isinstance(samples, int) and samples >= 1):
        raise CalibrationDataError(f"collect: samples must be an integer >= 1, got {samples!r}")
    if not (math.isfinite(rate_fraction) and 0.0 < rate_fraction <= 1.0):
        raise CalibrationDataError(f"collect: rate_fraction must be in (0, 1], got {rate_fraction}")
    actuation.check_angles(a, t)  # every target inside the joint limits, before moving
    if session.actual is None:
        raise CalibrationDataError("collect: the session is not brought up (no actual counts)")
    here = actuation.angles_from_counts(np.asarray(session.actual, dtype=np.int64))[:2]
    start = here
    points = np.empty((len(a), 3))
    reached = np.empty((2, len(a), nj))  # the true angles the commanded counts mean
    for k in range(len(a)):
        table = move_table(actuation, here, (a[k], t[k]), period_s, rate_fraction=rate_fraction)
        src = CountsSource(
            actuation,
            table,
            period_s,
            name=f"calibration pose {k + 1}",
            hold_s=settle_s,
            info={"pose": k + 1, "of": len(a)},
        )
        session.stream(src)
        points[k] = _point_of(reader.measure(samples))
        here = (a[k], t[k])
        reached[0, k], reached[1, k] = actuation.angles_from_counts(table[-1], None, *here)[:2]
        if progress is not None:
            progress(k + 1, len(a), points[k])
    if return_home:  # back where the arm started, along a joint path (a move in counts
        # strains the ropes of a bent arm: a later lead-in would start from a bent pose)
        table = move_table(actuation, here, start, period_s, rate_fraction=rate_fraction)
        session.stream(
            CountsSource(actuation, table, period_s, name="calibration: back to the start")
        )
    a_cmd, t_cmd = actuation.commanded_angles(reached[0], reached[1])
    return PoseData(np.array(a_cmd), np.array(t_cmd), points, source)
