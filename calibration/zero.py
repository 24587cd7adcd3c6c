"""Pretension and motor zero (``hrm calibrate zero``, issue 12, part 1).

The arm lies in its straight zero fixture (the parking tube): every physical joint angle
is held at 0, so a rope's tension depends on its own motor only.  With ``u`` the
unstretched rope the drum has paid out and ``L`` the rope's free length on the straight
arm (box part + geometric length, :meth:`Actuation.free_lengths` at zero angles), the
rope layer's model (:mod:`hrm_ctrl.ropes.motor_map`, ``u = L / (1 + T/EA)``) gives

    T = EA (L - u) / u   (0 while slack),   u = u_ref - d (c - z) / c_mm

for motor count ``c`` (``d`` the motor's direction, ``c_mm`` its counts per mm, ``z`` the
zero).  The motor zero is the count at which the rope carries the pretension:
:func:`pretension_and_zero` finds it by closed loop on the tension sensors, one rope
group (the ropes of one joint) at a time, the three ropes of a group moving together:

1. read the group's tensions (the mean of ``n_samples`` frames measured once the drives
   have settled, by the board's own time stamps: :func:`read_tensions`, :class:`BoardClock`);
2. a slack rope (below :data:`TAUT_N`) is wound in by a search step small enough that
   even a rope :data:`EA_RATIO_MAX` times stiffer than described, taut at once, stays
   below the mid-point of target and limit (:func:`search_step_counts`); a taut rope
   takes a Newton step ``(T* - T) / k`` on the slope ``k`` = dT/dc fitted through its
   last three taut readings (the model's slope, :func:`tension_slope_N_per_count`, until
   the readings span 2 N), tightening steps capped like the search step;
3. repeat until every rope of the group is within ``tol_N`` of the target; the count at
   the target is then ``c + (T* - T) / k`` (the remaining error, extrapolated on the
   slope).

**Which zero.**  The rope layer's zero is the count at the pretension with the rope
geometry straight (the joint's two rope disks coaxial); the zero fixture holds exactly
that pose (``sim_bus/arm.py``), whatever the joint zero offsets (true = commanded +
offset: in the fixture the links stand at their offsets, which the kinematic calibration
finds), so at the pretension the count measured is the zero.  A target other than the
pretension is converted through the rope layer it is given (:func:`fixture_offset_counts`):
``zero = c(T*) - d c_mm (u_ref - u(0, T*))``, on its EA (on the longest rope 171 counts per
N of difference, so 1.7 counts per N per 1 % of EA error: run the stiffness calibration
first).

Refusals (:class:`RopeTensionError`, one line naming the rope and motor), after moving
the group back to where it started: a rope still slack at ``max_travel_counts`` from its
start, or one whose target lies beyond it or beyond the drum travel (slack or snapped
rope); a tension above ``max_tension_N`` (or above its value at the start, for a rope
that started higher); a rope whose tension does not follow its motor (slope outside
1/3 .. 3 times the model's: a crossed sensor channel, a jammed drum); a saturated or
invalid sensor channel; no convergence in ``max_iterations``.  A tension guard thread
(:class:`TensionGuard`) stops every axis while a move runs if a rope passes its limit.

**Noise and tolerance.**  One count moves a rope's tension by ``k = (EA + T)^2 /
(EA L c_mm)`` N: with the shipped robot (EA 30 kN, ``c_mm`` 2151.4) 0.027 N for joint 1's
ropes (``L`` = 524 mm) down to 0.0058 N for joint 12's (2395 mm), 0.0047 N with EA 20 %
softer.  The sensor's noise is sigma = 0.05 N per frame; the mean of 10 frames has at
most 0.035 N even if only every other frame is independent (the simulated board repeats
a sample for up to 50 ms), i.e. at most 8 counts of zero error on the softest, longest
rope, and ``tol_N`` = 0.2 N (4 frame sigmas, so a reading inside it is not noise) is at
most 43 counts before the extrapolation of step 3 removes all but its slope error.  So
the zero is within 50 counts with margin, the final tension within ``tol_N``.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> k = tension_slope_N_per_count(act, 30.0)
>>> round(float(k[0]), 4), round(float(k[-1]), 4)     # joint 1's rope, joint 12's (N/count)
(0.0267, 0.0058)
>>> int(search_step_counts(act, 30.0, 60.0)[0])        # from slack, at most 45 N taut
1127
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from drivers.safety.causes import StopKind
from drivers.safety.limits import jerk_limits
from drivers.session import DriveSession, SafetyStopError
from drivers.sources import CountsSource
from drivers.tension_sensor import TensionSample
from hrm_ctrl.errors import CalibrationError, HrmError
from hrm_ctrl.ropes.actuation import Actuation

# The board's flags (docs/sim.md, "tension frame"): bit 0 a channel saturated.
BOARD_FLAG_SATURATED = 0x01
SATURATION_N = 655.34  # the largest tension a frame can carry (u16 of 0.01 N, FFFF invalid)

DEFAULT_TOL_N = 0.2  # 4 sigma of one frame: see the module docstring
DEFAULT_MAX_TRAVEL_COUNTS = 12_000  # ~5.6 mm of rope either way from where a motor starts
DEFAULT_MAX_ITERATIONS = 12  # moves per group; ~3-6 are needed
DEFAULT_SPEED_COUNTS_PER_S = 50_000.0  # ~23 mm/s of rope
DEFAULT_N_SAMPLES = 10  # frames averaged per reading (0.1 s at the board's 100 Hz)
MAX_N_SAMPLES = 1000
TAUT_N = 1.0  # a reading below this is a slack rope (20 frame sigmas)
SLOPE_SPAN_N = 2.0  # readings spanning this much tension give a fitted slope
SLOPE_POINTS = 3  # the slope is fitted through a rope's last few taut readings
SLOPE_RANGE = (1.0 / 3.0, 3.0)  # fitted slope / model slope outside this: refused
EA_RATIO_MAX = 1.5  # a rope may be this much stiffer than described (search step)
SETTLE_S = 0.07  # after a move: the drives hold (HOLD_S) then frames count after this
HOLD_S = 0.03  # the last setpoint held at the end of a move
READ_TIMEOUT_S = 5.0  # longest wait for a reading's frames (10 of them take 0.1 s at
# 100 Hz; a loaded test machine once delivered none in 2 s to an in-process simulated board)
ACCEL_FRACTION = 0.5  # moves use at most this share of the motors' acceleration limit
START_MARGIN_N = 5.0  # a rope above max_tension_N at the start may rise this much above it


class RopeTensionError(CalibrationError):
    """A rope's tension cannot be brought where a calibration routine needs it (slack or
    snapped rope, a tension over its limit, a saturated or invalid sensor channel); the
    message names the rope and its motor."""


class TensionReader(Protocol):
    """What the routines need of the tension board (:class:`TensionSensorReader`)."""

    port: str

    def latest(self, now_s: float | None = None) -> TensionSample: ...


@dataclass(frozen=True)
class TensionReading:
    """The mean of ``n_samples`` frames: tensions (n,) N and their standard errors."""

    tensions_N: np.ndarray
    sem_N: np.ndarray
    n_samples: int


@dataclass(frozen=True)
class ZeroResult:
    """What :func:`pretension_and_zero` found, per motor (the rope layer's order)."""

    motor_ids: tuple[str, ...]
    zero_counts: np.ndarray  # (n,) int64: the new zeros, in the rope layer's convention
    fixture_counts: np.ndarray  # (n,) int64: the count at the target tension in the fixture
    before_counts: np.ndarray  # (n,) int64: the zero the rope layer had
    final_counts: np.ndarray  # (n,) int64: where each motor was left
    tension_N: np.ndarray  # (n,) final reading
    tension_error_N: np.ndarray  # (n,) final reading - target
    iterations: np.ndarray  # (n,) moves of the rope's group
    target_N: float
    tol_N: float
    moves: int  # streams played in all
    elapsed_s: float  # wall-clock time of the routine

    def __post_init__(self) -> None:
        read_only(self)

    @property
    def zero_shift_counts(self) -> np.ndarray:
        """New zero - the one before (n,)."""
        return self.zero_counts - self.before_counts

    def residuals(self) -> dict[str, float]:
        """The figures a calibration version keeps (``residuals``)."""
        shift = np.abs(self.zero_shift_counts)
        return {
            "target_N": self.target_N,
            "tol_N": self.tol_N,
            "max_abs_tension_error_N": float(np.abs(self.tension_error_N).max()),
            "max_abs_zero_shift_counts": float(shift.max()),
            "max_iterations": float(self.iterations.max()),
            "moves": float(self.moves),
        }


def read_only(result: object) -> None:
    """Make every array field of a (frozen) result read-only."""
    for value in vars(result).values():
        if isinstance(value, np.ndarray):
            value.setflags(write=False)


# ---- the model ---------------------------------------------------------------------------


def straight_free_length_mm(actuation: Actuation) -> np.ndarray:
    """Free rope lengths (n,) on the straight arm (every true joint angle 0), mm."""
    z = np.zeros(actuation.robot.n_joints)
    return np.asarray(actuation.free_lengths(z, z), dtype=float)


def tension_slope_N_per_count(actuation: Actuation, tension_N: Any, EA_N: Any = None) -> np.ndarray:
    """dT/dc (n,) of the fixture's model at tension ``tension_N``, signed by direction.

    From ``T = EA (L/u - 1)``: ``dT/du = -EA L / u^2`` and ``du/dc = -d / c_mm``; with
    ``L/u = 1 + T/EA`` this is ``d (EA + T)^2 / (EA L c_mm)``.  ``EA_N`` defaults to the
    rope layer's."""
    ea = np.asarray(actuation.routing.stiffness_EA_N if EA_N is None else EA_N, dtype=float)
    T = np.asarray(tension_N, dtype=float)
    L = straight_free_length_mm(actuation)
    m = actuation.motors
    return m.direction * (ea + T) ** 2 / (ea * L * m.counts_per_mm)


def fixture_offset_counts(actuation: Actuation, tension_N: float | None = None) -> np.ndarray:
    """Counts (n,) from each motor's zero in the rope layer's convention (the count at the
    pretension with the rope geometry straight) to its count at ``tension_N`` (default the
    pretension) in the fixture, which holds that same pose (true angles = the joint
    offsets): ``d c_mm (u_ref - u(0, T))``, through the rope layer's own model (its EA).
    0 at the pretension.

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> int(np.abs(fixture_offset_counts(act)).max()), int(fixture_offset_counts(act, 25.0)[0])
    (0, -188)
    """
    a0 = np.asarray(actuation.alpha_offset_rad, dtype=float)  # the rope geometry straight
    t0 = np.asarray(actuation.theta_offset_rad, dtype=float)
    at = actuation.counts_from_angles(a0, t0, tension_N, check=False)
    return np.asarray(at, dtype=np.int64) - np.asarray(actuation.motors.zero_offsets_counts)


def search_step_counts(actuation: Actuation, target_N: float, max_tension_N: float) -> np.ndarray:
    """Longest tightening step (n,) counts, positive: a slack rope that becomes taut at
    once, :data:`EA_RATIO_MAX` times stiffer than the model, ends at no more than
    ``(target + max) / 2``."""
    cap = 0.5 * (target_N + max_tension_N)
    k0 = np.abs(tension_slope_N_per_count(actuation, 0.0)) * EA_RATIO_MAX
    return np.maximum(np.floor(cap / k0), 1.0)


# ---- tension readings --------------------------------------------------------------------


class BoardClock:
    """When a frame was measured, on the host's clock, from the board's own time stamp.

    A frame's reception time is its measurement plus the delay of the line and of the
    reading thread (which a loaded host stretches to tens of ms: frames queued before a
    move ended must not pass for readings after it).  ``received_s - board_s`` is that
    delay plus a constant offset; its minimum over the frames seen (the least delayed)
    estimates the offset.  The board's 32-bit microsecond counter wraps (every 71.6 min).

    >>> c = BoardClock()
    >>> s = lambda us, rx: TensionSample(0, us, 0, np.zeros(1), rx)
    >>> c.measured_s(s(1_000_000, 11.030)), c.measured_s(s(1_010_000, 11.012))
    (11.03, 11.012)
    >>> c.measured_s(s(1_020_000, 11.090))      # delivered 70 ms late: measured at 11.022
    11.022
    """

    def __init__(self) -> None:
        self.offset_s: float | None = None
        self._last_us: int | None = None
        self._wraps = 0

    def measured_s(self, sample: TensionSample) -> float:
        us = int(sample.board_time_us)
        if self._last_us is not None and us < self._last_us - 2**31:
            self._wraps += 1
        self._last_us = us
        board_s = (us + self._wraps * 2**32) * 1e-6
        delay = float(sample.received_s) - board_s
        if self.offset_s is None or delay < self.offset_s:
            self.offset_s = delay
        return round(board_s + self.offset_s, 9)


def read_tensions(
    reader: TensionReader,
    motor_ids: Sequence[str],
    *,
    n_samples: int = DEFAULT_N_SAMPLES,
    after_s: float | None = None,
    timeout_s: float = READ_TIMEOUT_S,
    ropes: Sequence[int] | None = None,
    clock: BoardClock | None = None,
    poll_s: float = 0.002,
) -> TensionReading:
    """Mean of ``n_samples`` distinct frames measured after ``after_s`` (host monotonic
    time; default now; a frame's time is its board time stamp through ``clock``, a
    :class:`BoardClock` kept across readings, else its reception).  Refuses
    (:class:`RopeTensionError`) a channel of ``ropes`` (default all) that is invalid or
    saturated in any of them, and frames that do not come within ``timeout_s`` (a stale
    board raises the reader's own error)."""
    start = time.monotonic() if after_s is None else float(after_s)
    deadline = max(start, time.monotonic()) + timeout_s
    rows: list[np.ndarray] = []
    flags = 0
    last_seq: int | None = None
    while len(rows) < n_samples:
        now = time.monotonic()
        if now < start:
            time.sleep(min(start - now, 0.05))
            continue
        if now > deadline:
            raise RopeTensionError(
                f"tension sensor {reader.port}: {len(rows)} of {n_samples} frames in "
                f"{timeout_s:g} s"
            )
        s = reader.latest(now)
        if s.seq != last_seq:
            last_seq = s.seq
            measured = s.received_s if clock is None else clock.measured_s(s)
            if measured >= start:
                rows.append(np.asarray(s.tensions_N, dtype=float))
                flags |= int(s.flags)
        time.sleep(poll_s)
    t = np.stack(rows)
    if t.shape[1] != len(motor_ids):
        raise RopeTensionError(
            f"tension sensor {reader.port}: {t.shape[1]} channels, {len(motor_ids)} ropes"
        )
    idx = np.arange(len(motor_ids)) if ropes is None else np.asarray(ropes, dtype=np.int64)
    bad = [int(i) for i in idx if not np.isfinite(t[:, i]).all()]
    if bad:
        raise RopeTensionError(
            f"rope {motor_ids[bad[0]]}: tension channel invalid (sensor {reader.port})"
        )
    if flags & BOARD_FLAG_SATURATED:
        sat = [int(i) for i in idx if t[:, i].max() >= SATURATION_N - 0.005]
        if sat:
            raise RopeTensionError(
                f"rope {motor_ids[sat[0]]}: tension sensor saturated (>= {SATURATION_N:g} N)"
            )
    mean = t.mean(axis=0)
    sem = t.std(axis=0, ddof=1) / math.sqrt(len(rows)) if len(rows) > 1 else np.zeros_like(mean)
    return TensionReading(mean, sem, len(rows))


class TensionGuard:
    """While a routine runs: every ``period_s`` the newest frame's tensions against a
    limit per rope; a rope above its limit (or an invalid channel, or a stale board) is
    a ``tension`` stop cause of the session (every axis quick-stopped), reported once."""

    def __init__(
        self,
        session: DriveSession,
        reader: TensionReader,
        limits_N: np.ndarray,
        period_s: float = 0.01,
    ) -> None:
        self.session = session
        self.reader = reader
        self.limits_N = np.asarray(limits_N, dtype=float)
        self.period_s = float(period_s)
        self.fault: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tension-guard", daemon=True)

    def check(self) -> str | None:
        """One check: why the newest frame is a fault (one line), or None."""
        ids = self.session.actuation.motor_ids
        try:
            t = np.asarray(self.reader.latest().tensions_N, dtype=float)
        except HrmError as exc:
            return str(exc)
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            return f"rope {ids[int(bad[0])]}: tension channel invalid"
        over = np.flatnonzero(t > self.limits_N)
        if over.size:
            i = int(over[0])
            return f"rope {ids[i]}: tension {t[i]:.1f} N above {self.limits_N[i]:.1f} N"
        return None

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            text = self.check()
            if text is not None:
                self.fault = text
                self.session.monitor.report(StopKind.TENSION, text)
                return

    def __enter__(self) -> TensionGuard:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)


# ---- moves -------------------------------------------------------------------------------


def move_table(
    start: np.ndarray,
    end: np.ndarray,
    speed_counts_per_s: np.ndarray,
    accel_counts_per_s2: np.ndarray,
    period_s: float,
    jerk_counts_per_s3: np.ndarray | None = None,
) -> np.ndarray:
    """Rows (excluding ``start``, ending at ``end``) of a minimum-jerk move, ``s(tau) =
    10 tau^3 - 15 tau^4 + 6 tau^5``: peak speed ``1.875 D / T``, peak acceleration
    ``5.774 D / T^2``, peak jerk ``60 D / T^3``, all from rest to rest, ``T`` the shortest
    whole number of periods within every motor's speed, acceleration and (if given) jerk.

    >>> move_table(np.array([0]), np.array([100]), np.array([1e4]), np.array([1e5]), 0.01)[
    ...     :, 0].tolist()
    [2, 10, 28, 50, 72, 90, 98, 100]
    """
    start = np.asarray(start, dtype=np.int64)
    delta = (np.asarray(end, dtype=np.int64) - start).astype(np.float64)
    D = np.abs(delta)
    t_v = 1.875 * D / np.asarray(speed_counts_per_s, dtype=float)
    t_a = np.sqrt(5.7735 * D / np.asarray(accel_counts_per_s2, dtype=float))
    t_j = (
        np.zeros(1)
        if jerk_counts_per_s3 is None
        else np.cbrt(60.0 * D / np.asarray(jerk_counts_per_s3, dtype=float))
    )
    T = float(max(np.max(t_v), np.max(t_a), np.max(t_j), period_s))
    n = max(1, math.ceil(T / period_s - 1e-9))
    tau = np.arange(1, n + 1, dtype=np.float64)[:, None] / n
    s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)
    return (start[None, :] + np.rint(s * delta[None, :])).astype(np.int64)


class FixtureMover:
    """Moves of a session's drives to given counts, and the tension readings after them."""

    def __init__(
        self,
        session: DriveSession,
        reader: TensionReader,
        *,
        speed_counts_per_s: float = DEFAULT_SPEED_COUNTS_PER_S,
        n_samples: int = DEFAULT_N_SAMPLES,
        guard: TensionGuard | None = None,
        name: str = "calibration",
    ) -> None:
        if not (isinstance(n_samples, int | np.integer) and 2 <= n_samples <= MAX_N_SAMPLES):
            raise CalibrationError(f"{name}: n_samples must be 2..{MAX_N_SAMPLES}, got {n_samples}")
        if not (math.isfinite(speed_counts_per_s) and speed_counts_per_s > 0):
            raise CalibrationError(f"{name}: speed must be > 0 counts/s, got {speed_counts_per_s}")
        self.session = session
        self.reader = reader
        self.actuation = session.actuation
        self.n_samples = int(n_samples)
        self.guard = guard
        self.name = name
        act = self.actuation
        self.speed = np.minimum(float(speed_counts_per_s), 0.5 * act.max_rate_counts_per_s)
        accel = getattr(act, "max_accel_counts_per_s2", None)
        self.accel = (
            np.full(act.n_motors, 1.0e6)
            if accel is None
            else ACCEL_FRACTION * np.asarray(accel, dtype=float)
        )
        self.moves = 0
        self.settled_at = time.monotonic()
        self.clock = BoardClock()

    @property
    def held(self) -> np.ndarray:
        """The counts the drives hold now."""
        targets = self.session.supervisor.targets
        if targets is None:
            raise CalibrationError(f"{self.name}: the drives hold no known position")
        return np.asarray(targets, dtype=np.int64).copy()

    def move(self, target: np.ndarray) -> None:
        """Play a minimum-jerk move from the held counts to ``target`` (checked against
        every limit by the source and the supervisor), ending with :data:`HOLD_S` held."""
        held = self.held
        target = np.asarray(target, dtype=np.int64)
        if np.array_equal(held, target):
            return
        period = self.session.control.period_s
        # the body starts on the held counts, so the source adds no lead-in of its own (a
        # lead-in goes by the pose the counts show, which the fixture does not let the arm
        # take: the ropes' counts there are what this calibration is finding out)
        # the jerk: ACCEL_FRACTION of each motor's, less the four counts a period cubed
        # that rounding may add to a third difference
        jerk = ACCEL_FRACTION * (jerk_limits(self.actuation) - 4.0 / period**3)
        rows = move_table(held, target, self.speed, self.accel, period, np.maximum(jerk, 1.0))
        body = np.vstack([held[None, :], rows])
        source = CountsSource(self.actuation, body, period, name=self.name, hold_s=HOLD_S)
        try:
            self.session.stream(source)
        except SafetyStopError:
            if self.guard is not None and self.guard.fault is not None:
                raise RopeTensionError(f"{self.name}: stopped: {self.guard.fault}") from None
            raise
        self.moves += 1
        self.settled_at = time.monotonic() + SETTLE_S

    def read(self, ropes: Sequence[int] | None = None) -> TensionReading:
        """The tensions once the last move has settled."""
        return read_tensions(
            self.reader,
            self.actuation.motor_ids,
            n_samples=self.n_samples,
            after_s=self.settled_at,
            ropes=ropes,
            clock=self.clock,
        )


def groups_of(actuation: Actuation, joints: Sequence[int] | None = None) -> list[np.ndarray]:
    """The motor indices of each joint's ropes (0-based joints; default every joint).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> [g.tolist() for g in groups_of(load_actuation(default_robot()), [0, 11])]
    [[0, 1, 2], [33, 34, 35]]
    """
    jm = np.asarray(actuation.joint_of_motor)
    n_j = actuation.robot.n_joints
    chosen = list(range(n_j)) if joints is None else list(joints)
    bad = [j for j in chosen if not (isinstance(j, int | np.integer) and 0 <= j < n_j)]
    if bad or len(set(chosen)) != len(chosen):
        raise CalibrationError(f"joints must be distinct 0-based joints 0..{n_j - 1}, got {chosen}")
    return [np.flatnonzero(jm == j) for j in chosen if np.any(jm == j)]


def _label(actuation: Actuation, i: int) -> str:
    return actuation.motor_label(int(i))


# ---- the routine -------------------------------------------------------------------------


def pretension_and_zero(
    session: DriveSession,
    tension: TensionReader,
    actuation: Actuation,
    *,
    target_N: float | None = None,
    tol_N: float = DEFAULT_TOL_N,
    max_travel_counts: int = DEFAULT_MAX_TRAVEL_COUNTS,
    max_tension_N: float | None = None,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    speed_counts_per_s: float = DEFAULT_SPEED_COUNTS_PER_S,
    n_samples: int = DEFAULT_N_SAMPLES,
    joints: Sequence[int] | None = None,
    progress: Callable[[str], None] | None = None,
) -> ZeroResult:
    """Bring every rope (of ``joints``, 0-based; default all) to ``target_N`` (default the
    routing's pretension) in the zero fixture and return each motor's count there (see
    the module docstring).  ``session`` is ENABLED (brought up) and is left ENABLED, every
    rope held near its target; ``max_tension_N`` defaults to twice the target.  Other
    motors than the chosen joints' keep their zero from the rope layer."""
    t_start = time.monotonic()
    ids = actuation.motor_ids
    n = actuation.n_motors
    target = float(actuation.routing.pretension_N if target_N is None else target_N)
    limit = 2.0 * target if max_tension_N is None else float(max_tension_N)
    if not (math.isfinite(target) and target > TAUT_N):
        raise CalibrationError(f"zero: target tension must be > {TAUT_N:g} N, got {target}")
    if not (math.isfinite(tol_N) and 0.0 < tol_N < target / 2):
        raise CalibrationError(f"zero: tol_N must be in (0, {target / 2:g}) N, got {tol_N}")
    if not (math.isfinite(limit) and limit > target + tol_N):
        raise CalibrationError(f"zero: max_tension_N {limit} must exceed the target {target:g}")
    if not (isinstance(max_travel_counts, int | np.integer) and max_travel_counts > 0):
        raise CalibrationError(f"zero: max_travel_counts must be > 0, got {max_travel_counts}")
    if not (isinstance(max_iterations, int | np.integer) and 1 <= max_iterations <= 100):
        raise CalibrationError(f"zero: max_iterations must be 1..100, got {max_iterations}")
    if tuple(session.actuation.motor_ids) != tuple(ids):
        raise CalibrationError("zero: the session drives other motors than the rope layer's")
    before = np.asarray(actuation.motors.zero_offsets_counts, dtype=np.int64).copy()
    zero = before.copy()
    at_target = None if abs(target - float(actuation.routing.pretension_N)) < 1e-12 else target
    offset = fixture_offset_counts(actuation, at_target)
    fixture = before + offset
    T_final = np.full(n, np.nan)
    iters = np.zeros(n, dtype=np.int64)
    groups = groups_of(actuation, joints)

    first = read_tensions(tension, ids, n_samples=n_samples)
    limits = np.maximum(limit, first.tensions_N + START_MARGIN_N)
    step_max = search_step_counts(actuation, target, limit)
    with TensionGuard(session, tension, limits) as guard:
        mover = FixtureMover(
            session, tension, speed_counts_per_s=speed_counts_per_s,
            n_samples=n_samples, guard=guard, name="zero",
        )  # fmt: skip
        for g in groups:
            c_zero, T_g, _slopes = _zero_group(
                mover, actuation, g, target, tol_N, limits, step_max,
                int(max_travel_counts), max_iterations, iters,
            )  # fmt: skip
            fixture[g], T_final[g] = c_zero, T_g
            zero[g] = c_zero - offset[g]
            if progress is not None:
                j = int(actuation.joint_of_motor[g[0]]) + 1
                shifts = " ".join(f"{int(zero[i] - before[i]):+d}" for i in g)
                err = float(np.abs(T_g - target).max())
                progress(
                    f"joint {j:2d} ({' '.join(ids[i] for i in g)}): {int(iters[g[0]])} moves, "
                    f"zero shift {shifts} counts, tension error {err:.3f} N"
                )
    T_out = np.where(np.isnan(T_final), first.tensions_N, T_final)  # not calibrated: as found
    return ZeroResult(
        motor_ids=tuple(ids),
        zero_counts=zero,
        fixture_counts=fixture,
        before_counts=before,
        final_counts=mover.held,
        tension_N=T_out,
        tension_error_N=T_out - target,
        iterations=iters,
        target_N=target,
        tol_N=float(tol_N),
        moves=mover.moves,
        elapsed_s=time.monotonic() - t_start,
    )


def _fitted_slope(points: list[tuple[int, float]], k_model: float) -> float:
    """dT/dc through a rope's last :data:`SLOPE_POINTS` taut readings, or ``k_model`` while
    they span less than :data:`SLOPE_SPAN_N`."""
    if len(points) < 2:
        return k_model
    recent = points[-SLOPE_POINTS:]
    c = np.array([p[0] for p in recent], dtype=float)
    T = np.array([p[1] for p in recent], dtype=float)
    if T.max() - T.min() < SLOPE_SPAN_N or np.ptp(c) == 0:
        return k_model
    return float(np.polyfit(c - c.mean(), T, 1)[0])


def _zero_group(
    mover: FixtureMover,
    act: Actuation,
    g: np.ndarray,
    target: float,
    tol_N: float,
    limits: np.ndarray,
    step_max: np.ndarray,
    max_travel: int,
    max_iterations: int,
    iters: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closed loop of one group: (zero counts, final tensions, slopes) of its ropes."""
    start = mover.held
    c = start.copy()
    lo, hi = np.asarray(act.counts_min), np.asarray(act.counts_max)
    d = np.asarray(act.motors.direction)
    points: dict[int, list[tuple[int, float]]] = {int(i): [] for i in g}
    k = {int(i): 0.0 for i in g}

    def refuse(i: int, why: str) -> RopeTensionError:
        try:  # back to where the group started, when the session can still move
            if mover.session.enabled:
                mover.move(start)
        except HrmError:
            pass
        return RopeTensionError(f"zero: rope {_label(act, i)}: {why}")

    reading = mover.read(g)
    it = 0
    while True:
        T = reading.tensions_N
        for i in g:
            ii = int(i)
            if T[ii] > limits[ii]:
                raise refuse(ii, f"tension {T[ii]:.1f} N above the limit {limits[ii]:.1f} N")
            if T[ii] >= TAUT_N:
                points[ii].append((int(c[ii]), float(T[ii])))
            k_model = float(tension_slope_N_per_count(act, max(T[ii], 0.0))[ii])
            k[ii] = _fitted_slope(points[ii], k_model)
            ratio = k[ii] / k_model
            if not SLOPE_RANGE[0] <= ratio <= SLOPE_RANGE[1]:
                raise refuse(
                    ii,
                    f"tension does not follow the motor ({k[ii]:.4g} N/count, the model "
                    f"{k_model:.4g}): crossed sensor channel, jammed drum or slipping rope",
                )
        slopes = np.array([k[int(i)] for i in g])
        err = T[g] - target
        if np.all(np.abs(err) < tol_N):
            zero = np.rint(c[g] - err / slopes).astype(np.int64)
            return zero, T[g].copy(), slopes
        if it == max_iterations:
            worst = int(g[int(np.argmax(np.abs(err)))])
            raise refuse(
                worst,
                f"tension {T[worst]:.2f} N not within {tol_N:g} N of {target:g} N after "
                f"{max_iterations} moves",
            )
        new = c.copy()
        for i in g:
            ii = int(i)
            if abs(T[ii] - target) < tol_N:
                continue
            moved_in = int(d[ii] * (int(c[ii]) - int(start[ii])))  # wound in since the start
            if T[ii] < TAUT_N:  # slack: wind in by a safe search step
                left = max_travel - moved_in
                if left <= 0:
                    raise refuse(
                        ii,
                        f"no tension after {max_travel} counts of travel (reads "
                        f"{T[ii]:.2f} N): slack or snapped rope",
                    )
                step = d[ii] * min(step_max[ii], left)
            else:
                step = (target - T[ii]) / k[ii]
                if abs(int(c[ii]) + step - int(start[ii])) > max_travel:
                    raise refuse(
                        ii,
                        f"{target:g} N lies beyond {max_travel} counts of travel (reads "
                        f"{T[ii]:.2f} N {moved_in:+d} counts wound in)",
                    )
                if step * d[ii] > step_max[ii]:  # tightening: capped like a search step
                    step = d[ii] * step_max[ii]
            want = int(np.rint(c[ii] + step))
            if not lo[ii] <= want <= hi[ii]:
                raise refuse(
                    ii,
                    f"{target:g} N lies beyond the drum travel [{int(lo[ii])}, {int(hi[ii])}] "
                    f"(reads {T[ii]:.2f} N at {int(c[ii])} counts)",
                )
            new[ii] = want
        mover.move(new)
        c = new
        it += 1
        iters[g] += 1
        reading = mover.read(g)
