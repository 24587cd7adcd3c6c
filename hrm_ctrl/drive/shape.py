"""Shape feedback of a drive: where the arm really is, against the planned shape and the trail.

:class:`ShapeFeedback` runs the rope layer's state estimator
(:class:`hrm_ctrl.ropes.estimator.RopeStateEstimator`: an EKF over the 24 angles from the
motors' actual counts and, where a tension board is read, the ropes' tensions, which
give their stretch) on feedback samples, and compares the estimated arm (forward
kinematics of the estimate) with

* the planned shape: the largest distance of an estimated joint centre (O_2..O_13, the
  end point last) from the same joint of the online planner's configuration at the time
  of the sample (a moving arm lags its plan by the drives' following and the shaping:
  that lag is part of the figure), and the end point's distance alone;
* the trail: the estimated end point's distance from the trail's polyline (the tip
  should be on the trail wherever along it the tip is, so this figure carries no lag).

:class:`ShapeWatch` takes a sample every ``period_s`` on its own thread (never the
control loop's) from two callables: the feedback (counts, tensions or None) and the plan
(the planner's angles and the trail's points, None while the drive has not started: the
lead-in); it keeps the last sample and the worst figures.  :func:`box_feedback` reads a
drive session's feedback (the monitor's actual positions, the tension board's newest
sample through the session's watches).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> a, t = np.full(12, 0.05), np.full(12, -0.02)
>>> fb = ShapeFeedback(act, rate_hz=10.0)
>>> trail = fb.centres(a, t)[-3:]          # a trail through the end point
>>> s = fb.update(act.counts_from_angles(a, t), None, a, t, trail, 0.0)
>>> s.tip_from_trail_mm < 0.05 and s.shape_mm < 0.05
True
>>> point_to_polyline(np.array([1.0, 1.0, 0.0]), np.array([[0.0, 0, 0], [2, 0, 0]]))
1.0
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.estimator import RopeStateEstimator

SHAPE_PERIOD_S = 0.1  # a sample every 0.1 s: the status line's 10 Hz


def point_to_polyline(p: np.ndarray, points: np.ndarray) -> float:
    """The distance of point ``p`` (3,) from the polyline through ``points`` (n, 3)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] == 1:
        return float(np.linalg.norm(p - pts[0]))
    a, b = pts[:-1], pts[1:]
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    w = np.einsum("ij,ij->i", p - a, ab) / np.where(L2 > 0.0, L2, 1.0)
    np.clip(w, 0.0, 1.0, out=w)
    d = a + w[:, None] * ab - p
    return float(np.sqrt(np.einsum("ij,ij->i", d, d).min()))


@dataclass(frozen=True)
class ShapeSample:
    """One comparison (mm): the estimated end point's distance from the trail, the
    largest distance of an estimated joint centre from the planned one, the end point's
    from the planned end point; the travel of the plan compared; whether tensions were
    used (the ropes' stretch)."""

    t_s: float
    travel_mm: float
    tip_from_trail_mm: float
    shape_mm: float
    tip_from_plan_mm: float
    tensions: bool

    def line(self) -> str:
        """The status line's part."""
        return (
            f"tip {self.tip_from_trail_mm:.2f} mm off the trail, shape {self.shape_mm:.2f} mm "
            "off the plan"
        )


class ShapeFeedback:
    """The estimator and the comparisons (see the module); one instance per drive."""

    def __init__(self, actuation: Actuation, rate_hz: float = 1.0 / SHAPE_PERIOD_S) -> None:
        self.act = actuation
        self.model = actuation.robot
        self.estimator = RopeStateEstimator(actuation, rate_hz=rate_hz)

    def centres(self, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Joint centres O_1..O_13 of a configuration (13, 3)."""
        return joint_centres(self.model, alpha, theta)

    def update(
        self,
        counts: np.ndarray,
        tension_N: np.ndarray | None,
        alpha: np.ndarray,
        theta: np.ndarray,
        trail_points: np.ndarray,
        travel_mm: float,
        t_s: float = 0.0,
    ) -> ShapeSample:
        """One feedback sample (``counts``, ``tension_N`` or None) against the planned
        configuration (``alpha``, ``theta``) and the trail's points."""
        est = self.estimator
        if not est.initialised:
            est.initialise(counts, tension_N)
        e = est.update(counts, tension_N)
        real = self.centres(e.alpha, e.theta)
        plan = self.centres(np.asarray(alpha), np.asarray(theta))
        d = np.linalg.norm(real[1:] - plan[1:], axis=1)
        return ShapeSample(
            t_s=t_s,
            travel_mm=float(travel_mm),
            tip_from_trail_mm=point_to_polyline(real[-1], trail_points),
            shape_mm=float(d.max()),
            tip_from_plan_mm=float(d[-1]),
            tensions=tension_N is not None,
        )


Feedback = Callable[[], "tuple[np.ndarray, np.ndarray | None] | None"]
Plan = Callable[[], "tuple[np.ndarray, np.ndarray, np.ndarray, float] | None"]


class ShapeWatch(threading.Thread):
    """Shape feedback every ``period_s`` on its own thread (see the module).
    ``feedback()`` gives (counts, tensions or None) or None (no sample yet), ``plan()``
    (alpha, theta, trail points, travel) or None (not driving yet).  :attr:`last` is the
    newest sample, :meth:`summary` the worst figures; :meth:`stop` ends it."""

    def __init__(
        self,
        feedback: Feedback,
        plan: Plan,
        shape: ShapeFeedback,
        period_s: float = SHAPE_PERIOD_S,
    ) -> None:
        super().__init__(name="hrm-drive-shape", daemon=True)
        self.feedback = feedback
        self.plan = plan
        self.shape = shape
        self.period_s = float(period_s)
        self.last: ShapeSample | None = None
        self.samples = 0
        self.worst_tip_mm = 0.0
        self.worst_shape_mm = 0.0
        self.error: str | None = None
        self.cpu_ms: list[float] = []
        self._quit = threading.Event()

    def sample(self) -> ShapeSample | None:
        """One sample now (None: no feedback or not driving yet)."""
        fb = self.feedback()
        plan = self.plan()
        if fb is None or plan is None:
            return None
        counts, tensions = fb
        alpha, theta, trail, travel = plan
        c0 = time.thread_time()
        s = self.shape.update(counts, tensions, alpha, theta, trail, travel, time.monotonic())
        self.cpu_ms.append((time.thread_time() - c0) * 1e3)
        self.last = s
        self.samples += 1
        self.worst_tip_mm = max(self.worst_tip_mm, s.tip_from_trail_mm)
        self.worst_shape_mm = max(self.worst_shape_mm, s.shape_mm)
        return s

    def run(self) -> None:
        next_t = time.monotonic()
        while not self._quit.is_set():
            try:
                self.sample()
            except Exception as exc:  # a read-out, never a reason to stop the arm
                self.error = f"shape feedback stopped: {exc}"
                return
            next_t += self.period_s
            self._quit.wait(max(0.0, next_t - time.monotonic()))

    def stop(self) -> None:
        self._quit.set()
        if self.is_alive():
            self.join(2.0)

    def summary(self) -> dict[str, Any]:
        """The worst and the last figures (mm), the samples, their CPU time (ms)."""
        last = self.last
        cpu = np.asarray(self.cpu_ms) if self.cpu_ms else np.zeros(1)
        return {
            "samples": self.samples,
            "tensions": None if last is None else last.tensions,
            "tip_from_trail_mm": {
                "max": round(self.worst_tip_mm, 3),
                "last": None if last is None else round(last.tip_from_trail_mm, 3),
            },
            "shape_mm": {
                "max": round(self.worst_shape_mm, 3),
                "last": None if last is None else round(last.shape_mm, 3),
            },
            "cpu_ms_p50": round(float(np.percentile(cpu, 50)), 3),
            "error": self.error,
        }


def box_feedback(session: Any, watches: Any) -> Feedback:
    """A drive session's feedback: the actual positions of one SYNC (every drive's
    answer to the same SYNC, :func:`drivers.safety.watches.take_snapshot`: a sample mixing
    two would put the ropes of a moving arm a period apart, which the estimator reads as
    millimetres at the tip) and, where the session's watches read a tension board, its
    newest sample (None when stale)."""
    from drivers.safety.watches import take_snapshot

    def read() -> tuple[np.ndarray, np.ndarray | None] | None:
        # the newest only: of the last SYNC, or of the one before while the last one's
        # answers are still coming in
        snap = take_snapshot(session.monitor, max_age=1)
        if snap is None:
            return None
        counts = np.asarray(snap.counts, dtype=np.int64)
        tw = None if watches is None else watches.watches.get("tension")
        reader = None if tw is None else tw.reader
        tensions = None
        if reader is not None:
            try:
                tensions = np.asarray(reader.latest().tensions_N, dtype=np.float64).copy()
            except Exception:  # stale or none yet: the counts alone
                tensions = None
            if tensions is not None and not np.isfinite(tensions).all():
                tensions = None
        return counts, tensions

    return read


def drive_plan(source: Any) -> Plan:
    """The plan a :class:`~hrm_ctrl.drive.stream.DriveSource` drives: its planner's
    angles and trail once the online steps have begun (None before: the lead-in)."""

    def read() -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        if source.cycles == 0:
            return None
        p = source.driver.planner
        q = np.array(p.q)  # copied at once: the control thread steps on
        n = q.shape[0] // 2
        return q[:n], q[n:], np.array(p.trail.points), float(p.travel)

    return read
