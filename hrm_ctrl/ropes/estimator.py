"""State estimator: 24 joint angles and rates from noisy motor-position feedback.

An extended Kalman filter (filterpy's ``ExtendedKalmanFilter``) over the whole
arm: state ``(alpha_1, theta_1, ..., alpha_12, theta_12, rates...)`` (48), a
constant-velocity model driven by white angular acceleration, and the 36 rope
lengths implied by the motor counts as the measurement.  The measurement
function is the exact rope-length map and its Jacobian is analytic (the same
one the inverse uses), so one update costs one forward map plus a 36x36 solve.
Why this and not a UKF or a chain of per-joint filters: ``docs/ropes.md``.

Consistency: every update reports each rope's innovation (measured minus
predicted length, mm, and normalised by ``sqrt(S_mm)``) and, per rope, the
residual of the triangular rope inverse of the same sample (warm-started at
the filter's estimate), standardised by the measurement noise and by the rope's
share of its joint's redundancy (:func:`~hrm_ctrl.ropes.inverse.standardized_residual`).
Its exponential average (``flag_window`` updates) is the consistency figure,
about 1 for healthy ropes.  Because the inverse is triangular, a slack, broken
or slipped rope leaves the joints before its own exact: the first joint (from
the base) whose ropes exceed ``flag_sigma`` is the faulty one, and within it
the ropes with the largest figure are flagged (all three with 3 ropes per
joint, whose single redundant length cannot tell them apart; the faulty one
with 4).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> est = RopeStateEstimator(act, rate_hz=100.0)
>>> c = act.counts_from_angles(np.full(12, 0.2), np.full(12, -0.1))
>>> est.initialise(c)
>>> for _ in range(5):
...     out = est.update(c)
>>> bool(np.abs(out.alpha - 0.2).max() < 1e-3 and out.flagged == ())
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.inverse import load_fallback_solver, solve_angles, standardized_residual
from hrm_ctrl.ropes.length import lengths_and_jacobian

# Ropes of the flagged joint whose figure is within this share of the joint's largest
# are named (they explain the inconsistency about equally well).
FLAG_SHARE = 0.8


def rope_misfit(act: Actuation, sol: Any, sigma_mm: float) -> np.ndarray:
    """Each rope's standardized length residual of an angle solution ``sol``, in units
    of the length noise ``sigma_mm`` (the consistency figure a rope fault raises)."""
    return (
        standardized_residual(
            act.geometry,
            act.joint_of_motor,
            sol.alpha,
            sol.theta,
            sol.residual,
            jacobian=sol.jacobian,
            pad=act.pad,
        )
        / sigma_mm
    )


@dataclass(frozen=True)
class Estimate:
    """One estimator output (angles rad, rates rad/s, lengths mm)."""

    alpha: np.ndarray  # (12,)
    theta: np.ndarray  # (12,)
    alpha_rate: np.ndarray  # (12,)
    theta_rate: np.ndarray  # (12,)
    innovation_mm: np.ndarray  # (n,) measured - predicted rope length
    normalized_innovation: np.ndarray  # (n,) innovation / sqrt(S_mm)
    residual_mm: np.ndarray  # (n,) residual of the rope inverse of this sample (mm)
    consistency: np.ndarray  # (n,) sqrt of the averaged squared standardised inverse residual
    flagged_joint: int | None  # 1-based first joint whose ropes are inconsistent, or None
    flagged: tuple[str, ...]  # motor ids of that joint that explain the inconsistency


class RopeStateEstimator:
    """EKF over the whole arm from rope-motor counts (one instance per run).

    Args:
        actuation: the rope layer of the arm.
        rate_hz: control (update) rate.
        count_noise: standard deviation of the position feedback (counts).
        model_noise_mm: rope-length model error added to the measurement noise (mm).
        accel_noise: standard deviation of the angular acceleration (rad/s^2).
        flag_sigma: consistency level above which a rope is flagged.
        flag_window: number of updates the consistency average spans.
    """

    def __init__(
        self,
        actuation: Actuation,
        rate_hz: float = 100.0,
        count_noise: float = 3.0,
        model_noise_mm: float = 0.01,
        accel_noise: float = 5.0,
        flag_sigma: float = 5.0,
        flag_window: int = 10,
    ) -> None:
        for name, v in (
            ("rate_hz", rate_hz),
            ("count_noise", count_noise),
            ("accel_noise", accel_noise),
            ("flag_sigma", flag_sigma),
            ("flag_window", flag_window),
        ):
            if not (np.isfinite(v) and v > 0):
                raise RopeError(f"estimator: {name} must be > 0, got {v!r}")
        if not (np.isfinite(model_noise_mm) and model_noise_mm >= 0):
            raise RopeError(f"estimator: model_noise_mm must be >= 0, got {model_noise_mm!r}")
        self.act = actuation
        load_fallback_solver()  # update() may need it at any cycle: import it before
        n_j = actuation.robot.n_joints
        self.n_x = 2 * n_j
        n = actuation.n_motors
        dt = 1.0 / rate_hz
        self.dt_s = dt
        self.flag_sigma = float(flag_sigma)
        self._ewma = 1.0 / float(flag_window)
        ekf = ExtendedKalmanFilter(dim_x=2 * self.n_x, dim_z=n)
        I = np.eye(self.n_x)
        ekf.F = np.block([[I, dt * I], [np.zeros_like(I), I]])
        q = accel_noise**2
        ekf.Q = np.block(
            [[q * dt**4 / 4.0 * I, q * dt**3 / 2.0 * I], [q * dt**3 / 2.0 * I, q * dt**2 * I]]
        )
        sigma_mm = np.hypot(count_noise / actuation.motors.counts_per_mm, model_noise_mm)
        ekf.R = np.diag(sigma_mm**2)
        self.sigma_mm = sigma_mm
        self.ekf = ekf
        self._cache: tuple[np.ndarray, np.ndarray] | None = None
        self._stat = np.ones(n)
        self.initialised = False

    def initialise(self, counts: Any, tension_N: Any = None, angle_sigma: float = 0.01) -> None:
        """Start from the rope inverse of one feedback sample, at rest."""
        a, t, _ = self.act.angles_from_counts(counts, tension_N)
        a, t = self.act.commanded_angles(a, t)  # the filter runs in the rope geometry's angles
        x = np.zeros((2 * self.n_x, 1))
        x[0 : self.n_x : 2, 0] = a
        x[1 : self.n_x : 2, 0] = t
        self.ekf.x = x
        self.ekf.P = np.diag(np.r_[np.full(self.n_x, angle_sigma**2), np.full(self.n_x, 0.1**2)])
        self._stat = np.ones(self.act.n_motors)
        self.initialised = True

    def _hjac(self, x: np.ndarray) -> np.ndarray:
        ang = x[: self.n_x, 0].reshape(1, -1, 2)
        s, J, _ = lengths_and_jacobian(self.act.geometry, ang[..., 0], ang[..., 1])
        self._cache = (s[0][:, None], J[0])
        H = np.zeros((self.act.n_motors, 2 * self.n_x))
        H[:, : self.n_x] = J[0]
        return H

    def _hx(self, x: np.ndarray) -> np.ndarray:
        if self._cache is None:  # pragma: no cover - filterpy calls HJacobian first
            self._hjac(x)
        return self._cache[0]  # type: ignore[index]

    def update(self, counts: Any, tension_N: Any = None) -> Estimate:
        """Predict one control period and correct with one feedback sample (n counts)."""
        if not self.initialised:
            raise RopeError("estimator: call initialise() with a first feedback sample")
        z = self.act.lengths_from_counts(counts, tension_N)
        if z.shape != (self.act.n_motors,):
            raise RopeError(f"estimator: expected {self.act.n_motors} counts, got {z.shape}")
        ekf = self.ekf
        ekf.predict()
        self._cache = None
        ekf.update(z[:, None], self._hjac, self._hx)
        nu = ekf.y[:, 0]
        nis = nu / np.sqrt(np.diag(ekf.S))
        x = ekf.x[:, 0]
        a, t = x[0 : self.n_x : 2], x[1 : self.n_x : 2]
        act = self.act
        sol = solve_angles(  # warm-started at the filter's estimate: on a fast move that
            # lags the sample, and two Newton steps left a consistent sample 36 sigma off
            act.geometry,
            act.joint_of_motor,
            z,
            a,
            t,
            act.pad,
            robust=False,
            max_iterations=SAMPLE_ITERATIONS,
        )
        zstd = rope_misfit(act, sol, self.sigma_mm)
        if np.abs(zstd).max() > self.flag_sigma:
            # Confirm from the rope inverse's own start before it counts: on a fast move the
            # filter lags (or its linearisation runs off), and a warm start there can end in
            # a misfit the sample does not have (a consistent sample read 109 sigma).
            try:
                cold = solve_angles(act.geometry, act.joint_of_motor, z, pad=act.pad)
            except RopeError:
                cold = None  # no configuration from there either: the warm result stands
            if cold is not None:
                zcold = rope_misfit(act, cold, self.sigma_mm)
                if np.abs(zcold).max() < np.abs(zstd).max():
                    sol, zstd = cold, zcold
                    x[0 : self.n_x : 2] = cold.alpha  # x views the filter's state: it
                    x[1 : self.n_x : 2] = cold.theta  # restarts from the cold solution
        self._stat += self._ewma * (zstd**2 - self._stat)
        cons = np.sqrt(self._stat)
        joint_cons = np.zeros(act.robot.n_joints)
        np.maximum.at(joint_cons, act.joint_of_motor, cons)
        bad = np.flatnonzero(joint_cons > self.flag_sigma)
        flagged_joint: int | None = None
        flagged: tuple[str, ...] = ()
        if bad.size:
            k = int(bad[0])
            own = np.flatnonzero(act.joint_of_motor == k)
            top = own[cons[own] >= FLAG_SHARE * joint_cons[k]]
            flagged_joint = k + 1
            flagged = tuple(act.motor_ids[i] for i in top)
        return Estimate(  # true angles: the rope geometry's plus the joint zero offsets
            alpha=a + act.alpha_offset_rad,
            theta=t + act.theta_offset_rad,
            alpha_rate=x[self.n_x :: 2].copy(),
            theta_rate=x[self.n_x + 1 :: 2].copy(),
            innovation_mm=nu.copy(),
            normalized_innovation=nis,
            residual_mm=sol.residual,
            consistency=cons,
            flagged_joint=flagged_joint,
            flagged=flagged,
        )


# Newton steps of the per-sample rope inverse (it stops once converged: usually 1-2)
SAMPLE_ITERATIONS = 6
# A commanded configuration counts as consistent when its rope lengths fit one
# configuration to within the feedback's own noise (standardised residual, in sigma).
GATE_SIGMA = 1.0
REFERENCE_ITERATIONS = 3  # Newton steps per reference solve, warm-started at the last one
# How long consistent samples are not checked after an inconsistent command: the drives
# lag their targets, so the first feedback after a lead-in still shows its last rows.
SETTLE_S = 0.05


# A commanded row counts as on a compensated table's path within this distance (counts,
# the whole arm's): a pausable playback's setpoints leave the rows' polyline by their
# rounding (2 counts) and its cubic between rows (an eighth of a row's second difference:
# 4 counts on the compensated bent pipe)
ON_PATH_COUNTS = 8.0
# Rows searched for a commanded row either side of the last one found (a playback moves at
# most a row per control period: at 20 Hz, 5 rows a check; a pause or a way back less)
SEARCH_ROWS = 64
# Rows behind the commanded one (and ahead) searched for the feedback's place on the path:
# the drives lag their targets by a period or two; as far back as the session waits for a
# missing TPDO on the simulated box (25 periods), so a slow drive is not misread as a rope
LAG_ROWS = 25
LEAD_ROWS = 2


@dataclass(frozen=True, eq=False)
class Compensation:
    """What a feed-forward (:mod:`hrm_ctrl.ropes.feedforward`) added to the rows of a
    table the drives play: ``counts`` (rows, n) the commanded rows, ``added`` (rows, n)
    what the compensation added to each (``counts - added``: the rows at the pretension,
    each one configuration).  Its place along the rows (:meth:`locate`) tells what was
    added to a setpoint between two rows, or to a feedback sample that lags them.

    >>> rows = np.array([[0, 0], [10, 0], [20, 0]]); added = np.array([[0, 0], [2, 4], [4, 8]])
    >>> comp = Compensation.of(rows, added)
    >>> comp.locate(np.array([15, 1]), 0, 3)
    (1, 0.5, 1.0)
    >>> comp.added_at(1, 0.5).tolist()
    [3.0, 6.0]
    """

    counts: np.ndarray
    added: np.ndarray

    @classmethod
    def of(cls, counts: Any, added: Any) -> Compensation:
        c = np.asarray(counts, dtype=np.int64)
        a = np.asarray(added, dtype=np.int64)
        if c.ndim != 2 or c.shape != a.shape or c.shape[0] < 1:
            raise RopeError(
                f"compensation: rows and what was added must be (rows, n) alike, got "
                f"{c.shape} and {a.shape}"
            )
        return cls(c, a)

    @property
    def n_rows(self) -> int:
        return int(self.counts.shape[0])

    def locate(self, counts: np.ndarray, lo: int, hi: int) -> tuple[int, float, float]:
        """``(row, s, distance)``: the point of the rows' polyline nearest ``counts`` (n)
        among the segments from rows ``lo`` .. ``hi - 1`` (clipped to the table), at ``s``
        (0..1) of the way from ``row`` to the next, ``distance`` counts away."""
        n = self.n_rows
        lo = max(0, min(lo, n - 1))
        hi = max(lo + 1, min(hi, n))
        a = self.counts[lo:hi].astype(np.float64)
        b = self.counts[lo + 1 : hi + 1].astype(np.float64)
        if b.shape[0] < a.shape[0]:  # the last row: a segment of no length
            b = np.vstack([b, a[-1:]])
        d = b - a
        x = np.asarray(counts, dtype=np.float64) - a
        dd = np.einsum("rk,rk->r", d, d)
        s = np.clip(np.einsum("rk,rk->r", x, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        dist = np.sqrt(np.einsum("rk,rk->r", x - s[:, None] * d, x - s[:, None] * d))
        k = int(np.argmin(dist))
        return lo + k, float(s[k]), float(dist[k])

    def added_at(self, row: int, s: float) -> np.ndarray:
        """What was added at ``s`` of the way from ``row`` to the next (n, float)."""
        nxt = min(row + 1, self.n_rows - 1)
        return self.added[row] + s * (self.added[nxt] - self.added[row])


class RopeConsistencyCheck:
    """The estimator's per-rope consistency flag as a watch on feedback samples.

    ``check(counts, reference)`` (also the instance's call) runs one
    :meth:`RopeStateEstimator.update` on a feedback sample (n counts, the drives' actual
    positions of one SYNC) and returns a one-line fault naming the flagged joint and its
    ropes, or None.  ``reference`` is what the drives were commanded to hold at that
    SYNC: the figure means something only when that command is itself one
    configuration.  A lead-in ramp or a jog is linear in counts and fits none (up to
    0.45 mm off on the bent pipe's lead-in, 45 sigma), so while the reference's own
    standardised residual exceeds ``gate_sigma`` the sample is not checked (counted in
    :attr:`gated`), nor are those of the next ``settle_s`` (the drives lag their
    targets), and the filter restarts from the next sample.  A rope fault shows in
    the feedback only: a slipped, broken or offset rope, or an encoder that is off.

    A compensated playback (``compensation``, :class:`Compensation`: the feed-forward's
    rows and what it added to each) fits no configuration at the pretension; what it
    added is taken off first.  The reference is found on the rows' path near the last
    one found (within :data:`ON_PATH_COUNTS`; off it, a lead-in, it is checked as it is:
    counted in :attr:`off_path`) and the feedback where it stands on that path, up to
    :data:`LAG_ROWS` behind (the drives lag their targets, and what was added changes
    along the rows: taking the reference's row for a feedback a row behind read 4.8 on
    the compensated bent pipe, two rows behind stopped it); each less what was added
    there.  A rope that is off is off in the feedback either way and is caught as without
    compensation.

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> check = RopeConsistencyCheck(act, rate_hz=20.0)
    >>> c = act.counts_from_angles(np.full(12, 0.2), np.full(12, -0.1))
    >>> [check(c, c) for _ in range(3)]
    [None, None, None]
    >>> bad = c.copy(); bad[13] += 1075                      # j05r1 off by 0.5 mm
    >>> text = check(bad, c)
    >>> text[: text.index(": l")]
    'rope consistency: joint 5, ropes j05r0, j05r1, j05r2'
    >>> text[text.index("(") :]
    '(figure 10.2 > 5; a rope slipped or broke, or an encoder is off)'
    >>> lead_in = (c * 0.5).astype(np.int64)                  # halfway along a counts ramp
    >>> check(lead_in, lead_in), check(c, c), check.gated   # + 1 settling sample
    (None, None, 2)
    """

    def __init__(
        self,
        actuation: Actuation,
        rate_hz: float = 20.0,
        *,
        gate_sigma: float = GATE_SIGMA,
        settle_s: float = SETTLE_S,
        compensation: Compensation | None = None,
        **estimator_options: Any,
    ) -> None:
        if not (np.isfinite(gate_sigma) and gate_sigma > 0):
            raise RopeError(f"consistency check: gate_sigma must be > 0, got {gate_sigma!r}")
        self.act = actuation
        self.estimator = RopeStateEstimator(actuation, rate_hz, **estimator_options)
        self.gate_sigma = float(gate_sigma)
        if not (np.isfinite(settle_s) and settle_s >= 0):
            raise RopeError(f"consistency check: settle_s must be >= 0, got {settle_s!r}")
        self.settle_samples = math.ceil(settle_s * rate_hz - 1e-9)
        self._settle = 0
        self.evaluations = 0  # samples checked
        self.gated = 0  # samples not checked: the command itself was inconsistent
        self.restarts = 0
        self.max_figure = 0.0  # largest consistency figure seen on a checked sample
        self.last: Estimate | None = None
        self._restart = True
        self._ref: np.ndarray | None = None
        self._ref_ok = False
        self._warm: tuple[np.ndarray, np.ndarray] | None = None
        self.compensation = compensation
        self.compensated = 0  # samples with what the feed-forward added taken off
        self.off_path = 0  # compensated playback, a reference not on its rows: as it is
        self._row = 0  # the row the last reference was found at

    def reference_consistent(self, reference: Any) -> bool:
        """Whether commanded counts are one configuration (within ``gate_sigma``)."""
        ref = np.asarray(reference, dtype=np.int64)
        if self._ref is not None and np.array_equal(ref, self._ref):
            return self._ref_ok  # a hold: same command as last time
        act = self.act
        z = act.lengths_from_counts(ref)
        try:
            if self._warm is None:
                sol = solve_angles(act.geometry, act.joint_of_motor, z, pad=act.pad)
            else:
                sol = solve_angles(
                    act.geometry,
                    act.joint_of_motor,
                    z,
                    *self._warm,
                    act.pad,
                    robust=False,
                    max_iterations=REFERENCE_ITERATIONS,
                )
        except RopeError:
            self._warm, self._ref, self._ref_ok = None, ref.copy(), False
            return False
        zstd = rope_misfit(act, sol, self.estimator.sigma_mm)
        self._warm = (np.asarray(sol.alpha), np.asarray(sol.theta))
        self._ref = ref.copy()
        self._ref_ok = bool(np.all(np.abs(zstd) <= self.gate_sigma))
        return self._ref_ok

    def uncompensated(self, counts: Any, reference: Any) -> tuple[np.ndarray, np.ndarray]:
        """A feedback sample and its reference less what the feed-forward added where each
        stands on the compensated rows' path (as they are when the reference is off it)."""
        comp = self.compensation
        fb = np.asarray(counts, dtype=np.int64)
        ref = np.asarray(reference, dtype=np.int64)
        if comp is None:
            return fb, ref
        row, s, dist = comp.locate(ref, self._row, self._row + SEARCH_ROWS)
        if dist > ON_PATH_COUNTS:  # not ahead: a pause, a way back
            row, s, dist = comp.locate(ref, self._row - SEARCH_ROWS, self._row + 1)
        if dist > ON_PATH_COUNTS:
            self.off_path += 1
            return fb, ref
        self._row = row
        f_row, f_s, _ = comp.locate(fb, row - LAG_ROWS, row + LEAD_ROWS + 1)
        self.compensated += 1
        return (
            fb - np.rint(comp.added_at(f_row, f_s)).astype(np.int64),
            ref - np.rint(comp.added_at(row, s)).astype(np.int64),
        )

    def check(self, counts: Any, reference: Any = None) -> str | None:
        """One feedback sample: a one-line fault, or None (see the class docstring)."""
        if reference is not None and self.compensation is not None:
            counts, reference = self.uncompensated(counts, reference)
        if reference is not None and not self.reference_consistent(reference):
            self.gated += 1
            self._restart = True
            self._settle = self.settle_samples
            return None
        if self._settle > 0:
            self._settle -= 1
            self.gated += 1
            return None
        if self._restart:
            self.estimator.initialise(counts)
            self.restarts += 1
            self._restart = False
        out = self.estimator.update(counts)
        self.last = out
        self.evaluations += 1
        self.max_figure = max(self.max_figure, float(out.consistency.max()))
        if out.flagged_joint is None:
            return None
        own = np.flatnonzero(self.act.joint_of_motor == out.flagged_joint - 1)
        figure = float(out.consistency[own].max())
        many = "s" if len(out.flagged) > 1 else ""
        return (
            f"rope consistency: joint {out.flagged_joint}, rope{many} {', '.join(out.flagged)}: "
            f"lengths do not fit the other ropes (figure {figure:.1f} > "
            f"{self.estimator.flag_sigma:g}; a rope slipped or broke, or an encoder is off)"
        )

    __call__ = check

    def summary(self) -> dict[str, Any]:
        """What a run record keeps of the check."""
        return {
            "evaluations": self.evaluations,
            "gated": self.gated,
            "restarts": self.restarts,
            "max_figure": round(self.max_figure, 3),
            "flag_sigma": self.estimator.flag_sigma,
            "gate_sigma": self.gate_sigma,
            "settle_samples": self.settle_samples,
            "rate_hz": 1.0 / self.estimator.dt_s,
            "compensated": None
            if self.compensation is None
            else {"samples": self.compensated, "off_path": self.off_path},
        }
