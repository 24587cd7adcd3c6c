"""The rope layer's façade: joint angles <-> rope lengths <-> motor counts, and limits.

Built once from the immutable :class:`~hrm_ctrl.model.RobotModel` (its ``[ropes]``
and ``[motors]`` tables) and the calibration's zero offsets; every array is
read-only and every method is vectorised over leading batch dimensions.

Joint angles in and out of every method are *true* joint angles.  A calibration's joint
zero offsets (issue 12: true angle = commanded angle + offset) are applied here: the rope
geometry (``geometry``, ``routing``) works in commanded angles, so
``counts_from_angles(q)`` evaluates it at ``q - offset`` and ``angles_from_counts`` adds
the offset back; the planner, the setpoints and the estimator's callers all see true
angles.  The joint limits are checked on the true angles.

>>> from hrm_ctrl.model import default_robot
>>> act = load_actuation(default_robot())
>>> act.n_motors, act.motor_ids[0], int(act.joint_of_motor[-1])
(36, 'j01r0', 11)
>>> c = act.counts_from_angles(np.zeros(12), np.zeros(12))
>>> c.dtype.name, int(np.abs(c).max())          # straight arm at pretension = calibration zero
('int64', 0)
>>> a = np.full(12, 0.3); t = np.full(12, -0.2)
>>> a2, t2, res = act.angles_from_counts(act.counts_from_angles(a, t))
>>> bool(np.abs(a2 - a).max() < 1e-3 and np.abs(t2 - t).max() < 1e-3)   # counts are quantised
True
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError
from hrm_ctrl.model import RobotModel
from hrm_ctrl.ropes.inverse import newton_step, padded_index, solve_angles
from hrm_ctrl.ropes.length import RopeGeometry, lengths_and_jacobian, rope_geometry
from hrm_ctrl.ropes.length import rope_lengths as _rope_lengths
from hrm_ctrl.ropes.motor_map import (
    MotorMap,
    motor_map_from_table,
    rope_tension_N,
    unstretched_length_mm,
)
from hrm_ctrl.ropes.routing import MAX_EA_N, MIN_EA_N, RopeRouting, routing_from_model

# Rows of counts whose angles are this close to a joint limit are mapped back from the
# whole counts (rounding moves a joint by a few 1e-5 rad: 2.5e-5 rad measured at 60 deg).
NEAR_LIMIT_RAD = 1.0e-3
# A joint line is sampled this often (its counts linear between samples): on a line from
# the straight arm to +-44 deg everywhere a chord then leaves the exact counts by < 1 count.
JOINT_LINE_SAMPLES = 256
# The ends of a joint line may decode this far outside the joint limits and are taken as
# at the limit: in the corners of the range whole counts hardly tell the angles apart
# (fits 6 deg apart within 1e-4 mm, hrm_ctrl.ropes.inverse).
END_OUTSIDE_TOL_RAD = math.radians(10.0)
POSE_CONTINUATION_STEPS = 8  # a cold inverse that fails is followed from the straight arm
MAX_JOINT_LINE_SAMPLES = 100_000


class RopeLimitError(RopeError):
    """A configuration or setpoint breaks a joint, drum-travel, motor-speed or
    motor-acceleration limit."""


@dataclass(frozen=True, eq=False)
class JointLine:
    """A straight line in joint space (:meth:`Actuation.joint_line`), sampled at equal
    steps: ``counts`` (K + 1, n) float, the configuration of every sample ``alpha`` /
    ``theta`` (K + 1, 12) (true angles, rad)."""

    counts: np.ndarray
    alpha: np.ndarray
    theta: np.ndarray


@dataclass(frozen=True, eq=False)
class Actuation:
    """Rope actuation of one arm (immutable).

    Attributes (contract): ``robot``, ``motor_ids`` (one per rope motor, "jKKrM"),
    ``joint_of_motor`` (0-based joint each rope ends at), ``counts_min`` /
    ``counts_max`` (int64 software position limits), ``max_rate_counts_per_s``,
    ``max_accel_counts_per_s2`` and ``max_jerk_counts_per_s3`` (per motor).
    Extra: ``routing``, ``geometry``, ``motors`` (conversion constants).

    It is the drivers' whole rope model: it implements ``drivers.rope_model.ArmRopeModel``
    (and so ``RopeModel`` and ``MotorLimits``) structurally, every member typed there.
    """

    robot: RobotModel
    motor_ids: tuple[str, ...]
    joint_of_motor: np.ndarray
    counts_min: np.ndarray
    counts_max: np.ndarray
    max_rate_counts_per_s: np.ndarray
    max_accel_counts_per_s2: np.ndarray
    max_jerk_counts_per_s3: np.ndarray
    routing: RopeRouting
    geometry: RopeGeometry
    motors: MotorMap
    pad: np.ndarray
    pre_c0: np.ndarray  # (n,) counts = pre_c0 - pre_k * length at the pretension
    pre_k: np.ndarray
    linear_inverse: np.ndarray  # (24, n): angles ~ linear_inverse @ (L - straight), small angles
    alpha_offset_rad: np.ndarray  # (12,) joint zero offsets: true angle = commanded + offset
    theta_offset_rad: np.ndarray  # (12,)

    @property
    def n_motors(self) -> int:
        return len(self.motor_ids)

    @property
    def n_joints(self) -> int:
        """Universal joints of the arm (the robot's)."""
        return self.robot.n_joints

    @property
    def limit_alpha(self) -> float:
        """|alpha| of every joint stays below this (rad, the robot's)."""
        return self.robot.limit_alpha

    @property
    def limit_theta(self) -> float:
        """|theta| of every joint stays below this (rad, the robot's)."""
        return self.robot.limit_theta

    @property
    def command_tension_N(self) -> tuple[float, float]:
        """``(low, high)``: the band a commanded move keeps the modelled tensions in (the
        routing's ``command_tension_N``)."""
        return self.routing.command_tension_N

    @property
    def whole_arm(self) -> Actuation:
        """The rope model of the whole arm: this one (every rope is commanded; a motor
        subset, ``drivers.safety.subset.ActuationSubset``, has none)."""
        return self

    def motor_label(self, i: int) -> str:
        """``"j05r2 (joint 5, rope 2)"`` for motor index i."""
        mid = self.motor_ids[i]
        return f"{mid} (joint {int(self.joint_of_motor[i]) + 1}, rope {mid.split('r')[-1]})"

    # ---- geometry -------------------------------------------------------------------------

    def _angles(self, alpha: Any, theta: Any) -> tuple[np.ndarray, np.ndarray]:
        a = np.asarray(alpha, dtype=float)
        t = np.asarray(theta, dtype=float)
        n = self.robot.n_joints
        if a.shape[-1:] != (n,) or t.shape != a.shape:
            raise RopeError(f"alpha and theta must have shape (..., {n}), got {a.shape}, {t.shape}")
        return a, t

    def commanded_angles(self, alpha: Any, theta: Any) -> tuple[np.ndarray, np.ndarray]:
        """The rope geometry's (commanded) angles of true joint angles: ``q - offset``."""
        a, t = self._angles(alpha, theta)
        return a - self.alpha_offset_rad, t - self.theta_offset_rad

    def rope_lengths(self, alpha: Any, theta: Any) -> np.ndarray:
        """Geometric rope lengths (..., n) in mm from the base disk to each anchor, at
        true joint angles."""
        return _rope_lengths(self.geometry, *self.commanded_angles(alpha, theta))

    def free_lengths(self, alpha: Any, theta: Any) -> np.ndarray:
        """Free rope lengths (..., n) in mm, drum to anchor (box part + geometric)."""
        return self.routing.box_length + self.rope_lengths(alpha, theta)

    def check_angles(self, alpha: Any, theta: Any) -> None:
        """Raise :class:`RopeLimitError` naming step and joint for NaN or out-of-limit angles."""
        a, t = self._angles(alpha, theta)
        if (np.abs(a) < self.robot.limit_alpha).all() and (
            np.abs(t) < self.robot.limit_theta
        ).all():
            return
        for name, v, lim in (
            ("alpha", a, self.robot.limit_alpha),
            ("theta", t, self.robot.limit_theta),
        ):
            bad = ~(np.abs(v) < lim)  # also catches NaN
            if bad.any():
                idx = np.argwhere(bad)[0]
                where = f"step {int(idx[0])}: " if v.ndim == 2 else ""
                val = float(v[tuple(idx)])
                what = (
                    "is not a finite number"
                    if not np.isfinite(val)
                    else f"({math.degrees(val):.4g} deg) is outside the joint limit "
                    f"+-{np.degrees(lim):.6g} deg"
                )
                raise RopeLimitError(
                    f"{where}joint {int(idx[-1]) + 1}: {name} = {val:.6g} rad {what}"
                )

    def joint_line(
        self,
        from_counts: Any,
        to_counts: Any,
        *,
        from_pose: tuple[Any, Any] | None = None,
        to_pose: tuple[Any, Any] | None = None,
        n_samples: int = JOINT_LINE_SAMPLES,
    ) -> JointLine:
        """The straight line in joint space, ``n_samples + 1`` samples: float counts from
        the configuration ``from_counts`` shows to the one ``to_counts`` shows
        (:meth:`pose_of_counts`), at equal steps of the line: each sample the
        pretension counts of its configuration plus the ends' misfits (given minus
        pretension counts) blended linearly along the line, so the first sample is
        ``from_counts`` and the last ``to_counts`` exactly (a rope slack or strained where
        the arm is now comes to the pretension on the way).  ``from_pose`` / ``to_pose``
        (alpha, theta), an end's configuration where it is known (a plan's first step, a
        jog's), is taken instead of the rope inverse's (in the corners of the joint range
        the counts hardly tell the angles apart).  The path of a lead-in
        (``drivers.sources.CountsSource``): rope lengths are not linear in the angles, so
        the straight line in *counts* between two bent poses is a set of rope lengths no
        pose takes up at its pretension (from the straight arm to +-44 deg on every joint:
        ropes at 164 N, pretensioned to 30 N).  The joint box is convex: a line between
        two configurations within the joint limits stays within them.  Raises
        :class:`RopeLimitError` when an end is outside the joint limits (by more than
        :data:`END_OUTSIDE_TOL_RAD` for one the inverse finds) or no pose fits it.

        >>> from hrm_ctrl.model import default_robot
        >>> act = load_actuation(default_robot())
        >>> a = np.full(12, math.radians(44.0))
        >>> end = act.counts_from_angles(a, -a)
        >>> line = act.joint_line(np.zeros(36, dtype=np.int64), end)
        >>> c = line.counts
        >>> bool((c[0] == 0).all() and (c[-1] == end).all()), c.shape, line.alpha.shape
        (True, (257, 36), (257, 12))
        >>> tension = act.tensions_from_counts(np.rint(c).astype(np.int64))[2]
        >>> round(float(tension.max()), 1) <= 30.1
        True
        """
        c0 = np.asarray(self._counts(from_counts), dtype=np.int64)
        c1 = np.asarray(self._counts(to_counts), dtype=np.int64)
        if c0.shape != (self.n_motors,) or c1.shape != (self.n_motors,):
            raise RopeError(f"joint line: expected {self.n_motors} motor counts at each end")
        if not (isinstance(n_samples, int) and 1 <= n_samples <= MAX_JOINT_LINE_SAMPLES):
            raise RopeError(
                f"joint line: samples must be 1..{MAX_JOINT_LINE_SAMPLES}, got {n_samples!r}"
            )
        ends = np.vstack([c0, c1])
        a0, t0 = self._end_pose(c0, from_pose, "where the arm is")
        a1, t1 = self._end_pose(c1, to_pose, "the target")
        alpha, theta = np.vstack([a0, a1]), np.vstack([t0, t1])
        s = np.linspace(0.0, 1.0, n_samples + 1)[:, None]
        a = alpha[0] + s * (alpha[1] - alpha[0])
        t = theta[0] + s * (theta[1] - theta[0])
        pre = self.pre_c0 - self.pre_k * self.rope_lengths(a, t)
        misfit = ends - pre[[0, -1]]
        line = pre + (1.0 - s) * misfit[0] + s * misfit[1]
        line[0], line[-1] = c0, c1
        return JointLine(counts=line, alpha=a, theta=t)

    def _end_pose(
        self, counts: np.ndarray, pose: tuple[Any, Any] | None, what: str
    ) -> tuple[np.ndarray, np.ndarray]:
        """A joint line's end: its known configuration (checked), else the counts'."""
        if pose is None:
            return self.pose_of_counts(counts, what)
        a, t = self._angles(*pose)
        try:
            self.check_angles(a, t)
        except RopeLimitError as exc:
            raise RopeLimitError(f"{what}: {exc}") from None
        return a, t

    def pose_of_counts(self, counts: Any, what: str) -> tuple[np.ndarray, np.ndarray]:
        """The pose ``counts`` (n,) show, for a move to start from (a joint line's end, a
        jog, home): the rope inverse's, brought twice :data:`NEAR_LIMIT_RAD` inside the
        joint limits.  In the corners of the range the lengths fold: whole counts do not
        tell the angles apart better than a fraction of a degree there
        (``hrm_ctrl.ropes.inverse``), and a cold start of the inverse can settle degrees
        away, outside the limits, or not converge; the inverse is then followed from the
        straight arm's counts to ``counts`` in :data:`POSE_CONTINUATION_STEPS` steps, each
        warm-started from the last.  A pose more than :data:`END_OUTSIDE_TOL_RAD` outside
        the limits, or none, raises :class:`RopeLimitError` (``what`` names the end).

        >>> from hrm_ctrl.model import default_robot
        >>> act = load_actuation(default_robot())
        >>> q = math.radians(59.0) * np.array([1.0, -1.0] * 12)
        >>> c = act.counts_from_angles(q[:12], q[12:])
        >>> a, t = act.pose_of_counts(c, "here")
        >>> bool(np.abs(np.concatenate([a, t]) - q).max() < math.radians(1.0))
        True
        """
        c = np.asarray(self._counts(counts), dtype=np.float64)
        lim_a, lim_t = self.robot.limit_alpha, self.robot.limit_theta

        def inside(a: np.ndarray, t: np.ndarray) -> bool:
            return bool((np.abs(a) < lim_a).all() and (np.abs(t) < lim_t).all())

        try:
            a, t, _res = self.angles_from_counts(c)
            settled = inside(a, t)
        except RopeError:
            settled = False
        if not settled:  # continuation from the straight arm
            z = np.zeros(self.robot.n_joints)
            c_zero = self.counts_from_angles(z, z, check=False).astype(np.float64)
            a, t = z, z
            try:
                for k in range(1, POSE_CONTINUATION_STEPS + 1):
                    c_k = c_zero + (c - c_zero) * (k / POSE_CONTINUATION_STEPS)
                    a, t, _res = self.angles_from_counts(c_k, None, a, t)
            except RopeError as exc:
                raise RopeLimitError(f"{what}: {exc}") from None
        too_far = (np.abs(a) > lim_a + END_OUTSIDE_TOL_RAD).any() or (
            np.abs(t) > lim_t + END_OUTSIDE_TOL_RAD
        ).any()
        if too_far:
            try:
                self.check_angles(a, t)
            except RopeLimitError as exc:
                raise RopeLimitError(f"{what}: {exc}") from None
        inner_a, inner_t = lim_a - 2 * NEAR_LIMIT_RAD, lim_t - 2 * NEAR_LIMIT_RAD
        return np.clip(a, -inner_a, inner_a), np.clip(t, -inner_t, inner_t)

    def rounded_outside(self, counts: Any, alpha: Any, theta: Any) -> tuple[int, str] | None:
        """The first row of whole ``counts`` (rows, n), made from ``alpha`` / ``theta``
        (rows, 12) within the (open) joint limits, whose rounding takes the arm outside
        them, and why; ``None`` if no row does.  Rounding moves a rope by at most half a
        count, a few 1e-5 rad of joint angle, so only rows within
        :data:`NEAR_LIMIT_RAD` of a limit are mapped back (the inverse, warm-started).

        >>> from hrm_ctrl.model import default_robot
        >>> act = load_actuation(default_robot())
        >>> a = np.zeros((1, 12)); a[0, 0] = math.radians(59.999999)
        >>> c = act.counts_from_angles(a, np.zeros((1, 12)))
        >>> act.rounded_outside(c, a, np.zeros((1, 12)))   # doctest: +ELLIPSIS
        (0, 'joint 1: alpha = 1.0472... rad (60 deg) is outside the joint limit +-60 deg')
        """
        a, t = self._angles(alpha, theta)
        a, t = a.reshape(-1, a.shape[-1]), t.reshape(-1, t.shape[-1])
        c = np.asarray(counts, dtype=np.int64).reshape(a.shape[0], -1)
        lim_a, lim_t = self.robot.limit_alpha, self.robot.limit_theta
        margin_a, margin_t = lim_a - NEAR_LIMIT_RAD, lim_t - NEAR_LIMIT_RAD
        near = ((np.abs(a) > margin_a) | (np.abs(t) > margin_t)).any(axis=1)
        if not near.any():
            return None
        rows = np.flatnonzero(near)
        a2, t2, _res = self.angles_from_counts(c[rows], None, a[rows], t[rows])
        bad = ~((np.abs(a2) < lim_a) & (np.abs(t2) < lim_t)).all(axis=1)
        if not bad.any():
            return None
        k = int(np.flatnonzero(bad)[0])
        try:
            self.check_angles(a2[k], t2[k])
        except RopeLimitError as exc:
            return int(rows[k]), str(exc)
        return None  # pragma: no cover - check_angles refuses what bad found

    # ---- counts ---------------------------------------------------------------------------

    def _tension(self, tension_N: Any) -> Any:
        if tension_N is None:
            return self.routing.pretension_N
        T = np.asarray(tension_N, dtype=float)
        if not np.all(np.isfinite(T)) or np.any(T < 0.0):
            raise RopeError("rope tension must be finite and >= 0 N")
        return T

    def counts_from_angles(
        self, alpha: Any, theta: Any, tension_N: Any = None, *, check: bool = True
    ) -> np.ndarray:
        """Motor setpoints (..., n) int64 for a configuration, corrected for rope stretch.

        ``tension_N`` (scalar or (..., n)) defaults to the pretension.  With
        ``check`` (default) NaN / out-of-limit angles and setpoints outside the drum
        travel raise :class:`RopeLimitError` naming step, joint and rope.
        """
        a, t = self._angles(alpha, theta)
        if (
            check
            and a.size
            and not (
                np.abs(a).max() < self.robot.limit_alpha
                and np.abs(t).max() < self.robot.limit_theta
            )
        ):
            self.check_angles(a, t)  # raises, naming step and joint
        L = _rope_lengths(self.geometry, a - self.alpha_offset_rad, t - self.theta_offset_rad)
        if tension_N is None:  # pretension: counts are affine in the lengths (precomputed)
            c = self.pre_c0 - self.pre_k * L
            counts = np.rint(c, out=c).astype(np.int64)
        else:
            u = unstretched_length_mm(
                self.routing.box_length + L,
                self._tension(tension_N),
                self.routing.stiffness_EA_N,
            )
            counts = self.motors.counts_from_unstretched(u)
        if check and not ((counts >= self.counts_min).all() and (counts <= self.counts_max).all()):
            self.check_counts(counts)  # raises, naming step and motor
        return counts

    def unstretched_from_counts(self, counts: Any) -> np.ndarray:
        """Paid-out unstretched rope length (..., n) in mm for motor counts."""
        return self.motors.unstretched_from_counts(self._counts(counts))

    def lengths_from_counts(self, counts: Any, tension_N: Any = None) -> np.ndarray:
        """Geometric rope lengths (..., n) in mm implied by counts at the given tension."""
        u = self.unstretched_from_counts(counts)
        T = self._tension(tension_N)
        return u * (1.0 + T / self.routing.stiffness_EA_N) - self.routing.box_length

    def angles_from_counts(
        self,
        counts: Any,
        tension_N: Any = None,
        alpha0: Any = None,
        theta0: Any = None,
        *,
        robust: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True joint angles from motor counts: ``(alpha (...,12), theta (...,12), residual
        (...,n))``.

        Uses the triangular rope structure (least squares per joint);
        ``alpha0``/``theta0`` (true angles) warm-start it.  The residual is measured minus
        modelled geometric length per rope.  ``robust=False`` skips the slow
        joint-by-joint fallback for inconsistent data (see
        :func:`~hrm_ctrl.ropes.inverse.solve_angles`), e.g. when tracking a faulty arm.
        """
        L = self.lengths_from_counts(counts, tension_N)
        if alpha0 is None and theta0 is None:  # start from the small-angle inverse
            x0 = (L - self.geometry.straight) @ self.linear_inverse.T
            lim = np.array([self.robot.limit_alpha, self.robot.limit_theta] * self.robot.n_joints)
            np.clip(x0, -lim, lim, out=x0)
            alpha0, theta0 = x0[..., 0::2], x0[..., 1::2]
        else:
            alpha0, theta0 = self.commanded_angles(alpha0, theta0)
        sol = solve_angles(
            self.geometry, self.joint_of_motor, L, alpha0, theta0, self.pad, robust=robust
        )
        return sol.alpha + self.alpha_offset_rad, sol.theta + self.theta_offset_rad, sol.residual

    def tensions_from_counts(
        self, counts: Any, alpha0: Any = None, theta0: Any = None, *, robust: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rope layer's model of the free arm at motor ``counts``: ``(alpha, theta,
        tension_N)``, the joints where their ropes' length misfit is least
        (:meth:`angles_from_counts`) and each rope's tension there, ``T = EA (F - u) / u``
        (``F`` the free length the pose needs, ``u`` the unstretched rope the drum has
        paid out, :func:`~hrm_ctrl.ropes.motor_map.rope_tension_N`; 0 when slack).
        Counts made from angles at the pretension give the pretension; moving one rope
        alone changes its joint's tensions (the simulated box's arm is this model).
        ``alpha0`` / ``theta0`` warm-start the inverse (near the joint-range corners a
        cold start can settle in a spurious minimum outside the limits).

        >>> from hrm_ctrl.model import default_robot
        >>> act = load_actuation(default_robot())
        >>> c = np.zeros(act.n_motors, dtype=np.int64)
        >>> c[0] = -2000                      # pay out 0.93 mm of joint 1's rope 0
        >>> np.round(act.tensions_from_counts(c)[2][:4], 1).tolist()  # j02r0 passes joint 1
        [10.9, 12.2, 12.2, 29.4]
        """
        alpha, theta, _res = self.angles_from_counts(counts, None, alpha0, theta0, robust=robust)
        return alpha, theta, self.tensions_at(counts, alpha, theta)

    def tensions_at(self, counts: Any, alpha: Any, theta: Any) -> np.ndarray:
        """Each rope's tension (..., n) with the arm held at ``alpha`` / ``theta`` (true
        angles) and the motors at ``counts``: ``T = EA (F - u) / u``, 0 when slack (as
        :meth:`tensions_from_counts`, for a pose known already).

        >>> from hrm_ctrl.model import default_robot
        >>> act = load_actuation(default_robot())
        >>> z = np.zeros(12)
        >>> c = act.counts_from_angles(z, z); c[0] += 2151   # 1 mm of rope wound in
        >>> round(float(act.tensions_at(c, z, z)[0]), 1)    # the arm held straight
        87.5
        """
        tension = rope_tension_N(
            self.free_lengths(alpha, theta),
            self.unstretched_from_counts(counts),
            self.routing.stiffness_EA_N,
        )
        return np.asarray(tension, dtype=np.float64)

    def _counts(self, counts: Any) -> np.ndarray:
        c = np.asarray(counts)
        if c.shape[-1:] != (self.n_motors,):
            raise RopeError(f"expected {self.n_motors} motor counts, got shape {c.shape}")
        if c.dtype.kind == "f" and not np.all(np.isfinite(c)):
            raise RopeError("motor counts must be finite")
        return c

    def check_counts(self, counts: Any, previous: Any = None, dt_s: Any = None) -> None:
        """Raise :class:`RopeLimitError` for a setpoint outside the position limits or too fast.

        ``counts`` is (n,) or a table (steps, n); for a table the step (row) is
        named.  With ``dt_s`` the change from ``previous`` (n,) to the first row
        and between consecutive rows is rate-checked, and the change of that rate from
        one change to the next against ``max_accel_counts_per_s2`` (for a constant
        ``dt_s`` exactly the second difference over ``dt_s**2``; the speed before
        ``previous`` is not known here, so the first change is not acceleration-checked:
        ``drivers.safety.limits.check_acceleration`` checks a start from rest); ``dt_s``
        is a scalar or, for a table, one interval per change (steps - 1, or steps with
        ``previous``).
        """
        c = self._counts(counts)
        table = c.reshape(-1, self.n_motors)
        is_table = c.ndim == 2
        if not ((table >= self.counts_min).all() and (table <= self.counts_max).all()):
            step, i = (
                int(v)
                for v in np.argwhere((table < self.counts_min) | (table > self.counts_max))[0]
            )
            where = f"step {step}: " if is_table else ""
            raise RopeLimitError(
                f"{where}motor {self.motor_label(i)}: setpoint {int(table[step, i])} counts "
                "outside "
                f"[{int(self.counts_min[i])}, {int(self.counts_max[i])}] (drum travel "
                f"{self.motors.travel_in_mm:g} mm in / {self.motors.travel_out_mm:g} mm out)"
            )
        if dt_s is None:
            return
        seq = table
        first = 1
        if previous is not None:
            seq = np.concatenate([self._counts(previous).reshape(1, -1), table], axis=0)
            first = 0
        n_changes = seq.shape[0] - 1
        dt = np.asarray(dt_s, dtype=float)
        if dt.ndim == 0:
            dt = np.full(n_changes, float(dt))
        if dt.shape != (n_changes,) or not np.all(dt > 0.0):
            raise RopeError(f"dt_s must be > 0 s, one per change ({n_changes}), got {dt_s!r}")
        if n_changes == 0:
            return
        change = np.diff(seq.astype(np.float64), axis=0)
        rate = np.abs(change) / dt[:, None]
        fast = rate > self.max_rate_counts_per_s
        if fast.any():
            row, i = (int(v) for v in np.argwhere(fast)[0])
            where = f"step {row + first}: " if is_table else ""
            raise RopeLimitError(
                f"{where}motor {self.motor_label(i)}: moves {rate[row, i]:.0f} counts/s, "
                "faster than "
                f"the motor's {float(self.max_rate_counts_per_s[i]):.0f} counts/s"
            )
        if n_changes < 2:
            return
        # acceleration: the change of speed from one change to the next (the second
        # difference over the mean interval), named by the row that ends the second change
        acc = np.abs(np.diff(change / dt[:, None], axis=0)) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
        hard = acc > self.max_accel_counts_per_s2
        if hard.any():
            row, i = (int(v) for v in np.argwhere(hard)[0])
            where = f"step {row + 1 + first}: " if is_table else ""
            raise RopeLimitError(
                f"{where}motor {self.motor_label(i)}: accelerates {acc[row, i]:.0f} "
                "counts/s^2, more than "
                f"the motor's {float(self.max_accel_counts_per_s2[i]):.0f} counts/s^2"
            )


def load_actuation(
    robot: RobotModel,
    zero_offsets_counts: Any = None,
    *,
    rope_EA_N: Any = None,
    alpha_offset_rad: Any = None,
    theta_offset_rad: Any = None,
) -> Actuation:
    """Build the rope actuation of ``robot``.

    ``zero_offsets_counts``: the calibration's counts at the zero position (straight
    arm at pretension), as n ints or ``{motor_id: counts}``; default all 0.
    ``rope_EA_N``: the calibration's axial rigidity per rope (n numbers or
    ``{rope_id: EA}`` naming every rope), replacing the routing's.
    ``alpha_offset_rad`` / ``theta_offset_rad``: the joint zero offsets (12 each, rad;
    default 0): true angle = commanded angle + offset (see the module docstring).
    Raises :class:`RopeError` (subclasses) on a malformed routing or motor table.

    >>> from hrm_ctrl.model import default_robot
    >>> off = np.radians(np.linspace(-1.0, 1.0, 12))
    >>> act = load_actuation(default_robot(), alpha_offset_rad=off)
    >>> nominal = load_actuation(default_robot())
    >>> q = np.full(12, 0.3)
    >>> bool(np.array_equal(act.counts_from_angles(q, q), nominal.counts_from_angles(q - off, q)))
    True
    """
    routing = routing_from_model(robot)
    if rope_EA_N is not None:
        routing = dataclasses.replace(
            routing, stiffness_EA_N=_per_rope(rope_EA_N, routing.rope_ids, robot.source)
        )
    geom = rope_geometry(routing)
    u_ref = unstretched_length_mm(
        routing.box_length + geom.straight, routing.pretension_N, routing.stiffness_EA_N
    )
    motors = motor_map_from_table(
        robot.tables.get("motors", {}), routing.rope_ids, u_ref, zero_offsets_counts, robot.source
    )
    scale = 1.0 / (1.0 + routing.pretension_N / routing.stiffness_EA_N)
    pre_k = motors.direction * motors.counts_per_mm * scale
    pre_c0 = (
        motors.zero_offsets_counts
        + motors.direction * motors.counts_per_mm * motors.u_ref
        - pre_k * routing.box_length
    )
    pad = padded_index(routing.joint_of_rope, robot.n_joints)
    z = np.zeros((1, robot.n_joints))
    _, J0, _ = lengths_and_jacobian(geom, z, z)
    eye = np.eye(routing.n_ropes)
    lin = np.stack([newton_step(J0, eye[m][None], pad)[0] for m in range(routing.n_ropes)], axis=1)
    arrays = {
        "alpha_offset_rad": _joint_offsets(alpha_offset_rad, robot, "alpha_offset_rad"),
        "theta_offset_rad": _joint_offsets(theta_offset_rad, robot, "theta_offset_rad"),
        "linear_inverse": lin,
        "pre_c0": pre_c0,
        "pre_k": pre_k,
        "counts_min": motors.counts_min,
        "counts_max": motors.counts_max,
        "max_rate_counts_per_s": motors.max_rate_counts_per_s,
        "max_accel_counts_per_s2": motors.max_accel_counts_per_s2,
        "max_jerk_counts_per_s3": motors.max_jerk_counts_per_s3,
        "pad": pad,
    }
    for arr in arrays.values():
        arr.setflags(write=False)
    return Actuation(
        robot=robot,
        motor_ids=routing.rope_ids,
        joint_of_motor=routing.joint_of_rope,
        routing=routing,
        geometry=geom,
        motors=motors,
        **arrays,
    )


def _per_rope(values: Any, ids: tuple[str, ...], where: str) -> np.ndarray:
    """Per-rope axial rigidity (N): n numbers, or a table naming every rope id."""
    if isinstance(values, Mapping):
        unknown = sorted(set(values) - set(ids))
        missing = [i for i in ids if i not in values]
        if unknown or missing:
            raise RopeError(
                f"{where}: rope_EA_N names unknown ropes {unknown[:4]} / misses {missing[:4]}"
            )
        values = [values[i] for i in ids]
    ea = np.array(values, dtype=float)
    if ea.shape != (len(ids),):
        raise RopeError(f"{where}: rope_EA_N must have {len(ids)} values, got shape {ea.shape}")
    bad = np.flatnonzero(~(np.isfinite(ea) & (ea >= MIN_EA_N) & (ea <= MAX_EA_N)))
    if bad.size:
        i = int(bad[0])
        v = float(ea[i])
        raise RopeError(
            f"{where}: rope_EA_N of rope {ids[i]} is {v!r}, not a number in "
            f"{MIN_EA_N:g}..{MAX_EA_N:g} N"
        )
    ea.setflags(write=False)
    return ea


def _joint_offsets(values: Any, robot: RobotModel, what: str) -> np.ndarray:
    """A joint zero offset per joint (rad), zeros by default."""
    n = robot.n_joints
    off = np.zeros(n) if values is None else np.array(values, dtype=float)
    if off.shape != (n,) or not np.all(np.isfinite(off)):
        raise RopeError(
            f"{robot.source}: {what} must be {n} finite angles (rad), got shape {off.shape}"
            + ("" if off.shape != (n,) else " with a value that is not finite")
        )
    return off
