"""Jerk-limited moves a source makes itself (Ruckig, offline): from rest to rest in
counts (:func:`move_table`), along a path in counts (:func:`path_move`), and the stop of
a table that ends moving (:func:`stop_table`).  Every sampled, rounded speed, second
and third difference is within the motors' limits, checked on the integers: a move that
breaks one is planned again, slower (:func:`timed_rest_to_rest`, the one retry loop).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.safety.limits import MAX_SOURCE_DURATION_S, SetpointError, check_duration

MOVE_MARGIN = 0.95  # moves are planned for this share of the rounding-corrected limits
MOVE_RETRIES = 4  # a sampled move that still breaks a limit is planned again, slower
MOVE_SLOWDOWN = 0.8  # by this factor on its limits each time


def move_limits(
    v_motor: np.ndarray, a_motor: np.ndarray, j_motor: np.ndarray, period_s: float,
    v_cap: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Limits a move is planned for, so that its rounded samples keep the motors' limits:
    a sampled speed is off by at most one count per period, a second difference by two,
    a third difference by four.

    >>> v, a, j = move_limits(np.array([200.0]), np.array([3e4]), np.array([1e7]), 0.01, None)
    >>> v.round(1).tolist(), a.round(1).tolist(), j.round(1).tolist()
    ([95.0], [9500.0], [5700000.0])
    """
    v = MOVE_MARGIN * (np.asarray(v_motor, np.float64) - 1.0 / period_s)
    if v_cap is not None:
        v = np.minimum(v, np.asarray(v_cap, np.float64))
    a = MOVE_MARGIN * (np.asarray(a_motor, np.float64) - 2.0 / period_s**2)
    j = MOVE_MARGIN * (np.asarray(j_motor, np.float64) - 4.0 / period_s**3)
    if not ((v > 0).all() and (a > 0).all() and (j > 0).all()):
        raise SetpointError(
            f"move: speed, acceleration or jerk limits too small for whole counts at a "
            f"{period_s:g} s control period"
        )
    return v, a, j


def calculate(inp: Any, n: int, what: str) -> Any:
    """Ruckig's offline trajectory for ``inp``; if the motors cannot all finish together
    (time synchronisation fails), each on its own.  A failure: one-line SetpointError."""
    from ruckig import Result, Ruckig, RuckigError, Synchronization, Trajectory

    for attempt in range(2):
        traj = Trajectory(n)
        try:
            result = Ruckig(n).calculate(inp, traj)
        except RuckigError as exc:
            result = str(exc).strip().splitlines()[0] if str(exc).strip() else "error"
        if result in (Result.Working, Result.Finished):
            return traj
        if attempt == 0:
            inp.synchronization = Synchronization.No
    raise SetpointError(f"{what}: no jerk-limited trajectory within the limits ({result})")


def sample(trajectory: Any, n_rows: int, period_s: float, n: int) -> np.ndarray:
    """Positions of a ruckig trajectory at periods 1..n_rows (after the end: its end)."""
    out = np.empty((n_rows, n))
    end = float(trajectory.duration)
    for k in range(n_rows):
        out[k] = trajectory.at_time(min((k + 1) * period_s, end))[0]
    return out


def within(
    rows: np.ndarray, start: np.ndarray, period_s: float, v_motor: np.ndarray,
    a_motor: np.ndarray, j_motor: np.ndarray | None = None,
) -> bool:  # fmt: skip
    """Rows after ``start`` (at rest), ending at rest, within the motors' speed,
    acceleration and (if given) jerk (the sampled, rounded differences).

    >>> within(np.array([[1], [3], [4], [4]]), np.array([0]), 1.0, np.array([2.0]),
    ...        np.array([1.0]))
    True
    >>> within(np.array([[1], [3], [4], [4]]), np.array([0]), 1.0, np.array([2.0]),
    ...        np.array([1.0]), np.array([1.0]))      # third differences 1 0 -3 ...
    False
    """
    seq = np.concatenate([start[None], start[None], start[None], rows, rows[-1:], rows[-1:]])
    d1 = np.diff(seq, axis=0)
    d2 = np.diff(d1, axis=0)
    ok = bool(
        (np.abs(d1) <= v_motor * period_s).all() and (np.abs(d2) <= a_motor * period_s**2).all()
    )
    if ok and j_motor is not None:
        ok = bool((np.abs(np.diff(d2, axis=0)) <= j_motor * period_s**3).all())
    return bool(ok)


def timed_rest_to_rest(
    target: np.ndarray,
    limits: tuple[np.ndarray, np.ndarray, np.ndarray],
    period_s: float,
    rows_of: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    start: np.ndarray,
    motor_limits: tuple[np.ndarray, np.ndarray, np.ndarray],
    what: str,
) -> tuple[np.ndarray, np.ndarray]:
    """A jerk-limited move of ``len(target)`` degrees of freedom from 0 at rest to
    ``target`` at rest within ``limits`` (speed, acceleration, jerk per degree of
    freedom), sampled every control period after the start; ``rows_of(samples)`` makes
    the motors' counts of the (n_rows, dof) samples (and what else goes with them).
    Planned again, slower, while the counts leave the ``motor_limits`` (speed,
    acceleration and jerk of each motor, from rest at ``start`` to rest at the end):
    returns the first ``rows_of`` that keeps them.

    >>> lim = (np.array([50.0]), np.array([2000.0]), np.array([1e5]))
    >>> rows, s = timed_rest_to_rest(np.array([100.0]), lim, 0.01,
    ...     lambda s: (np.rint(s).astype(np.int64), s), np.array([0]),
    ...     (np.array([200.0]), np.array([4e4]), np.array([5e6])), "move")
    >>> int(rows[-1, 0]), len(rows) > 2
    (100, True)
    """
    from ruckig import InputParameter

    n = target.shape[0]
    v, a, j = limits
    for _ in range(MOVE_RETRIES + 1):
        inp = InputParameter(n)
        inp.current_position = [0.0] * n
        inp.current_velocity = [0.0] * n
        inp.current_acceleration = [0.0] * n
        inp.target_position = target.tolist()
        inp.target_velocity = [0.0] * n
        inp.target_acceleration = [0.0] * n
        inp.max_velocity = v.tolist()
        inp.max_acceleration = a.tolist()
        inp.max_jerk = j.tolist()
        traj = calculate(inp, n, what)
        n_rows = max(1, math.ceil(float(traj.duration) / period_s - 1e-9))
        if n_rows * period_s > MAX_SOURCE_DURATION_S:
            raise SetpointError(f"{what}: {n_rows * period_s:.4g} s exceeds the longest run")
        rows, extra = rows_of(sample(traj, n_rows, period_s, n))
        if within(rows, start, period_s, *motor_limits):
            return rows, extra
        v, a, j = v * MOVE_SLOWDOWN, a * MOVE_SLOWDOWN**2, j * MOVE_SLOWDOWN**3
    raise SetpointError(f"{what}: no sampled trajectory within the motors' limits")


def move_table(
    start: np.ndarray,
    end: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
    speed_cap_counts_per_s: np.ndarray | None = None,
) -> np.ndarray:
    """A jerk-limited move (Ruckig, time-synchronised, offline) from ``start`` at rest to
    ``end`` at rest: the counts of every control period after ``start``, the last one
    ``end``; every sampled, rounded speed and second difference within the motors'
    limits (checked; a move that breaks one is planned again, slower).  Each motor is
    also kept below ``speed_cap_counts_per_s`` (e.g. a jog's speed).

    >>> t = move_table(np.array([0, 0]), np.array([1000, -400]), 0.01, np.full(2, 4e5),
    ...                np.full(2, 2e6), np.full(2, 4e7))
    >>> t[-1].tolist(), len(t) <= 12, bool((np.abs(np.diff(t[:, 0], 2)) <= 200).all())
    ([1000, -400], True, True)
    """
    start = np.asarray(start, dtype=np.int64)
    end = np.asarray(end, dtype=np.int64)
    n = start.shape[0]
    if np.array_equal(start, end):
        return np.zeros((0, n), dtype=np.int64)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    v, a, j = move_limits(v_m, a_m, max_jerk_counts_per_s3, period_s, speed_cap_counts_per_s)
    delta = (end - start).astype(np.float64)
    scale = max(float(np.abs(delta).max()), 1.0)  # Ruckig works in units of the move

    def rows_of(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows = start + np.rint(s * scale).astype(np.int64)
        rows[-1] = end
        return rows, s

    limits = (v / scale, a / scale, j / scale)
    j_m = np.asarray(max_jerk_counts_per_s3, np.float64)
    rows, _s = timed_rest_to_rest(delta / scale, limits, period_s, rows_of, start,
                                  (v_m, a_m, j_m), "move")  # fmt: skip
    return rows


def at_samples(x: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """``samples`` (K + 1, m) interpolated linearly at fractional sample indices ``x``.

    >>> at_samples(np.array([0.0, 0.5, 2.0]), np.array([[0.0], [10.0], [30.0]])).ravel()
    array([ 0.,  5., 30.])
    """
    pts = np.asarray(samples, dtype=np.float64)
    k_steps = pts.shape[0] - 1
    i = np.clip(np.asarray(x).astype(np.int64), 0, max(k_steps - 1, 0))
    w = (np.asarray(x) - i)[:, None]
    if k_steps == 0:
        return np.repeat(pts, len(i), axis=0)
    return pts[i] + w * (pts[i + 1] - pts[i])


def path_move(
    samples: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
    speed_cap_counts_per_s: np.ndarray | None = None,
    what: str = "move",
) -> tuple[np.ndarray, np.ndarray]:
    """A jerk-limited move along a path in counts, from rest at its first sample to rest
    at its last: ``samples`` (K + 1, motors) at equal steps of the path parameter ``s``
    in [0, 1], linear between samples (e.g. the rope layer's ``Actuation.joint_line``).
    ``s`` is timed by Ruckig within ``D_m ds/dt <= v_m``, ``D_m d2s/dt2 <= a_m`` and
    ``D_m d3s/dt3 <= j_m`` for every motor (``D_m`` its largest ``|dc_m/ds|``).  Returns
    the counts of every control period after the first sample, the last one the last
    sample, and where each row is along the path (its fractional sample index, 0 .. K:
    what else was sampled along it, e.g. a joint line's poses, :func:`at_samples`); each
    sampled, rounded speed and second difference checked against the motors' limits (a
    move that breaks one is timed again, slower).

    >>> line = np.linspace(0.0, 1.0, 9)[:, None] * np.array([[1000.0, -400.0]])
    >>> t, x = path_move(line, 0.01, np.full(2, 4e5), np.full(2, 2e6), np.full(2, 4e7))
    >>> t[-1].tolist(), bool((np.abs(np.diff(t[:, 0], 2)) <= 200).all()), float(x[-1])
    ([1000, -400], True, 8.0)
    """
    pts = np.asarray(samples, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] < 2 or not np.isfinite(pts).all():
        raise SetpointError(f"{what}: a path needs 2 or more finite samples, got {pts.shape}")
    k_steps = pts.shape[0] - 1
    start = np.rint(pts[0]).astype(np.int64)
    end = np.rint(pts[-1]).astype(np.int64)
    slope = np.abs(np.diff(pts, axis=0)).max(axis=0) * k_steps  # D_m, counts per unit s
    moving = slope > 0.0
    if not moving.any():
        return np.zeros((0, pts.shape[1]), dtype=np.int64), np.zeros(0)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    v, a, j = move_limits(v_m, a_m, max_jerk_counts_per_s3, period_s, speed_cap_counts_per_s)
    # the path parameter's limits: the tightest of the moving motors'
    v_s, a_s, j_s = (np.array([float((lim[moving] / slope[moving]).min())]) for lim in (v, a, j))

    def rows_of(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.clip(s[:, 0], 0.0, 1.0) * k_steps
        x[-1] = k_steps
        rows = np.rint(at_samples(x, pts)).astype(np.int64)
        rows[-1] = end
        return rows, x

    j_m = np.asarray(max_jerk_counts_per_s3, np.float64)
    return timed_rest_to_rest(np.array([1.0]), (v_s, a_s, j_s), period_s, rows_of, start,
                              (v_m, a_m, j_m), what)  # fmt: skip


def stop_table(
    previous: np.ndarray,
    last: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
) -> np.ndarray:
    """A jerk-limited stop (Ruckig, velocity interface) of a table that ends moving: from
    ``last`` at the speed ``(last - previous) / T`` to rest, the counts of every period
    after ``last`` (empty when it is at rest already).

    >>> t = stop_table(np.array([0]), np.array([100]), 0.01, np.full(1, 4e5),
    ...                np.full(1, 2e6), np.full(1, 4e7))
    >>> bool(t[0, 0] > 100 and (np.diff(t[-3:, 0]) >= 0).all() and t[-1, 0] == t[-2, 0])
    True
    """
    from ruckig import ControlInterface, InputParameter, Synchronization

    last = np.asarray(last, dtype=np.int64)
    vel = (last - np.asarray(previous, dtype=np.int64)).astype(np.float64) / period_s
    n = last.shape[0]
    if not vel.any():
        return np.zeros((0, n), dtype=np.int64)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    v, a, j = move_limits(v_m, a_m, max_jerk_counts_per_s3, period_s, None)
    v = np.maximum(v, np.abs(vel))  # the speed it has (within the motors' limit: checked)
    # Ruckig works in units of the stopping distance (at most this far)
    scale = max(float(np.max(np.abs(vel) * (np.abs(vel) / a + a / j))), 1.0)
    inp = InputParameter(n)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position = [0.0] * n
    inp.current_velocity = (vel / scale).tolist()
    inp.current_acceleration = [0.0] * n
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    inp.max_velocity = (v / scale).tolist()
    inp.max_acceleration = (a / scale).tolist()
    inp.max_jerk = (j / scale).tolist()
    inp.synchronization = Synchronization.No  # every motor stops as soon as it can
    traj = calculate(inp, n, "stop")
    n_rows = max(1, math.ceil(float(traj.duration) / period_s - 1e-9)) + 1
    return last + np.rint(sample(traj, n_rows, period_s, n) * scale).astype(np.int64)


SLOWED_MAX_TRIES = 40  # uniform slow-downs :func:`slowed_table` tries before it refuses


def cubic_at(rows: np.ndarray, s: np.ndarray) -> np.ndarray:
    """A table's rows interpolated at fractional rows ``s`` by the Catmull-Rom cubic (the
    rows themselves at whole ``s``; the first and last row held beyond the ends): its
    second derivative jumps at a row by about the rows' third difference, so sampling it
    keeps third differences near the table's, where a straight line between rows would
    make them as large as its second differences.

    >>> cubic_at(np.array([[0.0], [0.0], [10.0], [30.0]]), np.array([1.0, 1.5, 2.0]))[:, 0]
    array([ 0.  ,  3.75, 10.  ])
    """
    p = np.asarray(rows, dtype=np.float64)
    n = p.shape[0]
    i = np.clip(np.floor(s).astype(np.int64), 0, max(n - 2, 0))
    f = (np.asarray(s, dtype=np.float64) - i)[:, None]
    p0, p1 = p[np.maximum(i - 1, 0)], p[i]
    p2, p3 = p[np.minimum(i + 1, n - 1)], p[np.minimum(i + 2, n - 1)]
    return 0.5 * (
        2.0 * p1
        + (p2 - p0) * f
        + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * f**2
        + (3.0 * (p1 - p2) + p3 - p0) * f**3
    )


def slowed_table(
    rows: np.ndarray,
    period_s: float,
    max_rate_counts_per_s: np.ndarray,
    max_accel_counts_per_s2: np.ndarray,
    max_jerk_counts_per_s3: np.ndarray,
    what: str = "table",
) -> np.ndarray:
    """A table of counts from rest at its first row to rest at its last, played along the
    same path at one uniform rate (rows per period, at most 1: :func:`cubic_at` between
    rows, rounded) slow enough that every speed, second and third difference of the
    integers, from rest to rest, is within the motors' limits: the table itself when it
    keeps them, else slower by what the worst one exceeds (speed as the rate, acceleration
    as its square, jerk as its cube), tried again until it keeps them; a slowed table
    ends with its last row twice (at rest, as a table that ends is taken to be).

    >>> t = np.array([[0], [0], [40], [80], [80]])  # 40 counts a cycle at once: jerky
    >>> s = slowed_table(t, 0.01, np.full(1, 4e5), np.full(1, 2e6), np.full(1, 4e7))
    >>> int(s[0, 0]), int(s[-1, 0]), len(s) > len(t)
    (0, 80, True)
    >>> slowed_table(t[:2], 0.01, np.full(1, 4e5), np.full(1, 2e6), np.full(1, 4e7)).shape
    (2, 1)
    """
    table = np.asarray(rows, dtype=np.int64)
    v_m = np.asarray(max_rate_counts_per_s, np.float64)
    a_m = np.asarray(max_accel_counts_per_s2, np.float64)
    j_m = np.asarray(max_jerk_counts_per_s3, np.float64)
    n = table.shape[0]
    if n < 2:
        return table
    out, rate = table, 1.0
    for _ in range(SLOWED_MAX_TRIES):
        seq = np.concatenate([out[:1], out[:1], out[:1], out, out[-1:], out[-1:]])
        d1 = np.abs(np.diff(seq, axis=0))
        d2 = np.abs(np.diff(seq, n=2, axis=0))
        d3 = np.abs(np.diff(seq, n=3, axis=0))
        excess = max(
            float(np.max(d1 / (v_m * period_s))),
            math.sqrt(float(np.max(d2 / (a_m * period_s**2)))),
            math.cbrt(float(np.max(d3 / (j_m * period_s**3)))),
        )
        if excess <= 1.0:
            return out
        rate *= MOVE_MARGIN / excess
        m = math.ceil((n - 1) / rate)
        check_duration(what, m * period_s, period_s)
        s = np.arange(m + 1, dtype=np.float64) * ((n - 1) / m)
        out = np.rint(cubic_at(table, s)).astype(np.int64)
        out[0], out[-1] = table[0], table[-1]
        if not np.array_equal(out[-2], out[-1]):  # at rest at the end: its last row twice
            out = np.concatenate([out, out[-1:]])
    raise SetpointError(
        f"{what}: no uniform slow-down within the motors' limits after {SLOWED_MAX_TRIES} tries"
    )
