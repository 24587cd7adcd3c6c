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

A collection keeps its poses as they are measured (:class:`PoseJournal`: one JSON file
rewritten atomically after each pose, named by what identifies the collection,
:func:`journal_key`): a collection that stops (a safety stop, the operator, a crash)
resumes from them, driving only the poses still missing.

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
    on_pose: Callable[[int, np.ndarray, np.ndarray, np.ndarray], None] | None = None,
) -> PoseData:
    """Drive the arm to each target configuration (true angles, (N, 12) each), hold
    ``settle_s``, read ``reader.measure(samples)`` (moves at ``rate_fraction`` of the motor
    limits, at most 1), and at the end (``return_home``) move back to the configuration the
    arm started in; return the poses (commanded angles and
    measured points, see the module docstring).  ``progress(k, N, point)`` is called after
    each pose, and ``on_pose(k, alpha, theta, point)`` with the pose as it is kept
    (commanded angles (12,) each, the instrument's point): a :class:`PoseJournal` writes it
    down, so a collection that stops keeps what it measured.  A safety stop raises what the
    session raises (nothing is measured after)."""
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
        if on_pose is not None:
            a_k, t_k = actuation.commanded_angles(reached[0, k], reached[1, k])
            on_pose(k, np.asarray(a_k), np.asarray(t_k), points[k].copy())
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


JOURNAL_FORMAT = "hrm-collect/1"


def journal_key(alpha: np.ndarray, theta: np.ndarray, *about: str) -> str:
    """What identifies a collection (its target configurations, in order, and ``about``:
    the arm it drives, the calibration it starts from): 16 hex digits.

    >>> z = np.zeros((2, 12))
    >>> journal_key(z, z, "sim") == journal_key(z, z, "sim") != journal_key(z, z, "real")
    True
    """
    import hashlib

    h = hashlib.sha256()
    for arr in (alpha, theta):
        h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
    for text in about:
        h.update(b"\0" + text.encode())
    return h.hexdigest()[:16]


class PoseJournal:
    """The poses of one collection, kept in ``path`` as they are measured (a JSON file,
    ``hrm-collect/1``, rewritten atomically after each pose: a stop, a crash or a power
    cut leaves the poses measured before it) and read back to resume: :attr:`kept` are
    the first poses of the collection ``key`` of ``n`` poses (commanded angles (k, 12)
    each, points (k, 3) in the base frame).  A file of another collection, or one that is
    not a journal, is refused (:class:`CalibrationDataError` naming it), never overwritten.

    >>> import tempfile
    >>> from pathlib import Path
    >>> d = Path(tempfile.mkdtemp())
    >>> j = PoseJournal(d / "c.json", "k1", 3)
    >>> j.add(np.zeros(12), np.ones(12), np.array([1.0, 2.0, 3.0]))
    >>> again = PoseJournal(d / "c.json", "k1", 3)
    >>> len(again), again.kept.points_mm.tolist()
    (1, [[1.0, 2.0, 3.0]])
    >>> PoseJournal(d / "c.json", "k2", 3)
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.CalibrationDataError: ...c.json: the poses of another collection (not ...)
    """

    def __init__(self, path: Any, key: str, n: int) -> None:
        from pathlib import Path

        self.path = Path(path)
        self.key = key
        self.n = int(n)
        self._rows: list[tuple[list[float], list[float], list[float]]] = []
        if self.path.exists():
            self._rows = self._read()

    def _read(self) -> list[tuple[list[float], list[float], list[float]]]:
        import json

        where = str(self.path)
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise CalibrationDataError(f"{where}: not a pose journal ({exc})") from exc
        if not isinstance(doc, dict) or doc.get("format") != JOURNAL_FORMAT:
            raise CalibrationDataError(f"{where}: not a pose journal (format {JOURNAL_FORMAT})")
        if doc.get("key") != self.key or doc.get("poses") != self.n:
            raise CalibrationDataError(
                f"{where}: the poses of another collection (not resumed: move it away, or run "
                "the collection it was made for)"
            )
        rows = doc.get("measured")
        if not isinstance(rows, list) or len(rows) > self.n:
            raise CalibrationDataError(f"{where}: measured: a list of at most {self.n} poses")
        out = []
        for i, r in enumerate(rows):
            try:
                a, t, p = (np.asarray(r[k], dtype=float) for k in ("alpha_rad", "theta_rad",
                                                                   "point_mm"))  # fmt: skip
            except (TypeError, KeyError, ValueError):
                raise CalibrationDataError(f"{where}: measured[{i}]: not a pose") from None
            n_j = len(a)
            if a.shape != (n_j,) or t.shape != (n_j,) or p.shape != (3,):
                raise CalibrationDataError(f"{where}: measured[{i}]: not a pose")
            if not (np.isfinite(a).all() and np.isfinite(t).all() and np.isfinite(p).all()):
                raise CalibrationDataError(f"{where}: measured[{i}]: not finite")
            out.append((a.tolist(), t.tolist(), p.tolist()))
        return out

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def kept(self) -> PoseData:
        """The poses kept so far (empty arrays when none)."""
        n_j = len(self._rows[0][0]) if self._rows else 0
        a = np.array([r[0] for r in self._rows], dtype=float).reshape(-1, n_j)
        t = np.array([r[1] for r in self._rows], dtype=float).reshape(-1, n_j)
        p = np.array([r[2] for r in self._rows], dtype=float).reshape(-1, 3)
        return PoseData(a, t, p, str(self.path))

    def add(self, alpha: np.ndarray, theta: np.ndarray, point_mm: np.ndarray) -> None:
        """Keep one more pose (written before this returns)."""
        import json

        from hrm_ctrl.files import write_atomic

        row = tuple(np.asarray(x, dtype=float).tolist() for x in (alpha, theta, point_mm))
        self._rows.append(row)  # type: ignore[arg-type]
        doc = {
            "format": JOURNAL_FORMAT,
            "key": self.key,
            "poses": self.n,
            "measured": [{"alpha_rad": a, "theta_rad": t, "point_mm": p} for a, t, p in self._rows],
        }
        write_atomic(self.path, json.dumps(doc) + "\n")

    def remove(self) -> None:
        """The collection is complete (its pose file written): the journal goes."""
        self.path.unlink(missing_ok=True)
