"""The simulated arm: motor positions → rope lengths → joint angles → joint centres.

Where the arm really is follows from where the motors really are (the drive
simulators' actual positions, not the host's setpoints): the rope layer's
inverse (:meth:`hrm_ctrl.ropes.actuation.Actuation.angles_from_counts`, with rope
stretch at the ropes' tension) gives the 24 joint angles, the planner's FK the
true joint centres.

Tension per rope: the pretension less ``EA · residual / free length`` (the
inverse's residual is how much longer a rope is than the configuration needs:
a slack rope loses tension, a short one gains), never below 0, plus a little
sensor noise.  A snapped rope carries no tension and its joint drifts away from it
(the other ropes of the joint pull it) at ``snap_drift_rad_per_s`` until the
joint limit.

>>> import numpy as np
>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> arm = SimArm(act, noise_N=0.0)
>>> a = np.full(12, 0.2); t = np.full(12, -0.1)
>>> s = arm.state(act.counts_from_angles(a, t), now=0.0)
>>> bool(np.abs(s.alpha - a).max() < 1e-3), s.centres.shape
(True, (13, 3))
>>> float(s.tension_N.min()) > 29.0     # pretension 30 N, ropes consistent
True
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.errors import SimError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.ropes.actuation import Actuation


@dataclass(frozen=True)
class ArmState:
    """The simulated arm at one instant (mm, rad, N)."""

    t: float
    counts: np.ndarray  # (n,) actual motor positions
    alpha: np.ndarray  # (12,)
    theta: np.ndarray  # (12,)
    centres: np.ndarray  # (13, 3) joint centres O_1..O_12 and end point
    tension_N: np.ndarray  # (n,)
    residual_mm: np.ndarray  # (n,)


class SimArm:
    """Arm state from motor counts, with snapped ropes (thread-safe)."""

    def __init__(
        self,
        actuation: Actuation,
        *,
        noise_N: float = 0.05,
        snap_drift_rad_per_s: float = 0.2,
        seed: int = 0,
    ) -> None:
        self.actuation = actuation
        self.noise_N = float(noise_N)
        self.snap_drift_rad_per_s = float(snap_drift_rad_per_s)
        self._rng = np.random.default_rng(seed)
        self._snapped: dict[int, float] = {}  # motor index -> time of the snap
        self._lock = threading.Lock()
        self._warm: tuple[np.ndarray, np.ndarray] | None = None
        self._cache: tuple[np.ndarray, tuple[np.ndarray, ...]] | None = None
        pre = np.broadcast_to(
            np.asarray(actuation.routing.pretension_N, dtype=float), (actuation.n_motors,)
        )
        self.pretension_N = pre.copy()
        self.stiffness_EA_N = np.broadcast_to(
            np.asarray(actuation.routing.stiffness_EA_N, dtype=float), (actuation.n_motors,)
        ).copy()

    def snap(self, motor: int | str, now: float) -> None:
        """Fault injection: the rope of ``motor`` (index or id) breaks at ``now``."""
        i = self.motor_index(motor)
        with self._lock:
            self._snapped.setdefault(i, now)

    def repair(self) -> None:
        with self._lock:
            self._snapped.clear()

    @property
    def snapped(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(sorted(self._snapped))

    def motor_index(self, motor: int | str) -> int:
        ids = self.actuation.motor_ids
        if isinstance(motor, str):
            if motor not in ids:
                raise SimError(f"unknown rope motor '{motor}'")
            return ids.index(motor)
        if not 0 <= int(motor) < len(ids):
            raise SimError(f"rope motor index {motor} outside 0..{len(ids) - 1}")
        return int(motor)

    def state(self, counts: np.ndarray, now: float) -> ArmState:
        """The arm for actual motor positions ``counts`` (n,) at time ``now``."""
        act = self.actuation
        c = np.asarray(counts, dtype=np.int64)
        with self._lock:
            warm = self._warm
            snapped = dict(self._snapped)
        cache = self._cache
        if cache is not None and np.array_equal(cache[0], c):
            alpha, theta, res, tension = (v.copy() for v in cache[1])  # motors did not move
        else:
            a0, t0 = warm if warm is not None else (None, None)
            alpha, theta, res = act.angles_from_counts(c, self.pretension_N, a0, t0)
            alpha = np.asarray(alpha, dtype=float).copy()
            theta = np.asarray(theta, dtype=float).copy()
            res = np.asarray(res, dtype=float)
            free = act.free_lengths(alpha, theta)
            tension = np.maximum(self.pretension_N - self.stiffness_EA_N * res / free, 0.0)
            with self._lock:
                self._warm = (alpha.copy(), theta.copy())
            self._cache = (c.copy(), (alpha.copy(), theta.copy(), res.copy(), tension.copy()))
        for i, t_snap in snapped.items():
            j = int(act.joint_of_motor[i])
            alpha[j], theta[j] = self._drift(alpha, theta, i, j, max(0.0, now - t_snap))
            tension[i] = 0.0
        if self.noise_N > 0:
            tension = np.maximum(tension + self._rng.normal(0.0, self.noise_N, tension.shape), 0.0)
            for i in snapped:
                tension[i] = 0.0
        centres = joint_centres(act.robot, alpha, theta)
        return ArmState(now, c, alpha, theta, centres, tension, res)

    def _drift(
        self, alpha: np.ndarray, theta: np.ndarray, rope: int, joint: int, dt: float
    ) -> tuple[float, float]:
        """Joint ``joint`` turned by ``rate·dt`` in the direction that lengthens ``rope``."""
        act = self.actuation
        h = 1e-4
        base = float(act.rope_lengths(alpha, theta)[rope])
        ga, gt = 0.0, 0.0
        for k, (da, dtt) in enumerate(((h, 0.0), (0.0, h))):
            a2, t2 = alpha.copy(), theta.copy()
            a2[joint] += da
            t2[joint] += dtt
            g = (float(act.rope_lengths(a2, t2)[rope]) - base) / h
            if k == 0:
                ga = g
            else:
                gt = g
        norm = float(np.hypot(ga, gt)) or 1.0
        step = self.snap_drift_rad_per_s * dt
        lim_a = act.robot.limit_alpha * 0.999
        lim_t = act.robot.limit_theta * 0.999
        a_new = float(np.clip(alpha[joint] + step * ga / norm, -lim_a, lim_a))
        t_new = float(np.clip(theta[joint] + step * gt / norm, -lim_t, lim_t))
        return a_new, t_new
