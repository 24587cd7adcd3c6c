"""Driving on a box: the online step of every control cycle as the drives' setpoint.

:class:`DriveSource` is a :class:`drivers.sources.SetpointSource` the session plays
(``session.stream(source)``).  Started from the drives' actual positions it first plays
the lead-in a plan plays (:class:`drivers.sources.CountsSource` with the trail's first
configuration as its one body row: a jerk-limited line in joint space, checked by the
rope model); then, every control slot, it runs one :meth:`Driver.cycle
<hrm_ctrl.drive.driver.Driver.cycle>` under the operator's command and turns the arm's
angles into motor counts through the rope layer's checked mapping
(:meth:`~hrm_ctrl.ropes.actuation.Actuation.counts_from_angles`: joint limits, drum
travel), and shapes them within every motor's speed, acceleration and jerk
(:class:`Shaper`: smoothed alike for every motor, jerk-limited where the smoothing is not
enough; the session's supervisor checks every setpoint again).  A refused step (the
planner's refusal, a rope or motor limit) is not sent: the motors stop from the speed they
have, jerk-limited within their limits (:func:`drivers.sources.stop_table`), and
hold there until the drive ends.  With ``go_on`` (the console's ``drive``) a refusal of
the planner holds the arm instead at the last step it accepted (the motors brought to rest
there, jerk-limited, as the shaping brings them to any step) and the drive goes on: the
next step the planner accepts (a retract, another steer) moves it again; a rope or motor
limit still ends the drive.  When the key script ends (or :meth:`DriveSource.request_end`
is called: the command goes to rest first, within the advance ramp) the motors stop the
same way if they still move, then hold ``hold_s``.  :attr:`DriveSource.last_status` is the
last cycle's :class:`~hrm_ctrl.drive.driver.CycleStatus` (for a status line).

The key script's time is the drive's own clock: slot ``k`` after the lead-in is
``k * period`` s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.safety.limits import SetpointError, accel_limits, jerk_limits
from drivers.sources import CountsSource
from drivers.sources.moves import move_limits
from hrm_ctrl.drive.command import STOP, DriveError, SteerCommand
from hrm_ctrl.drive.driver import CycleStatus, Driver, DriveSummary
from hrm_ctrl.errors import HrmError
from hrm_ctrl.ropes.actuation import Actuation

SHAPER_SCALE_COUNTS = 1000.0  # Ruckig's unit of the shaping (its tolerances are absolute)
SMOOTH_STAGES = 3  # the shaping's moving averages in cascade
SMOOTH_CYCLES = 4  # each over this many control cycles: 4.5 cycles' delay in all


class Shaper:
    """The time shaping of online setpoints.  Every cycle the online step's counts go
    through a smoothing every motor shares (three moving averages of :data:`SMOOTH_CYCLES`
    each, in cascade: the same delay for every motor, so the counts stay one
    configuration of the arm, 4.5 cycles behind the step, and the step-to-step jitter of
    the online fit, up to 20 times a motor's jerk limit, is filtered out); the smoothed
    counts, rounded, are the setpoint when they keep every motor within its speed,
    acceleration and jerk (:func:`drivers.sources.moves.move_limits`, with the margins
    for whole counts) from the setpoints before, else a jerk-limited step toward them
    (Ruckig's online update from the motors' position, speed and acceleration, the motors
    time-synchronised; each on its own where that finds no trajectory, counted in
    :attr:`unsynchronised`).  :meth:`stop` brakes to rest the same way (velocity
    interface, target 0).  (Ruckig alone, each motor chasing the raw step, lagged each by
    its own time and put the tip of the arm the counts make up to 4.3 mm off the trail on
    the bent pipe by its keys, 2.2 mm time-synchronised; smoothed, 0.04 mm.)

    >>> sh = Shaper(np.zeros(1, np.int64), 0.01, np.full(1, 4e5), np.full(1, 2e6),
    ...             np.full(1, 4e7))
    >>> rows = [int(sh.toward(np.array([1000]), np.array([0.0]))[0]) for _ in range(60)]
    >>> rows[-1], bool(np.all(np.abs(np.diff(rows, 2)) <= 2e6 * 1e-4))
    (1000, True)
    """

    def __init__(
        self, rest: np.ndarray, period_s: float, v_max: np.ndarray, a_max: np.ndarray,
        j_max: np.ndarray,
    ) -> None:  # fmt: skip
        from ruckig import InputParameter, OutputParameter, Ruckig, Synchronization

        n = rest.shape[0]
        v, a, j = move_limits(v_max, a_max, j_max, period_s, None)
        self._v = v
        self._T = float(period_s)
        self._per_cycle = (v * period_s, a * period_s**2, j * period_s**3)
        self._otg = Ruckig(n, period_s)
        self._inp = InputParameter(n)
        self._out = OutputParameter(n)
        self._scale = SHAPER_SCALE_COUNTS
        self._origin = rest.astype(np.float64)
        self._inp.current_position = [0.0] * n
        self._inp.current_velocity = [0.0] * n
        self._inp.current_acceleration = [0.0] * n
        self._inp.max_velocity = (v / self._scale).tolist()
        self._inp.max_acceleration = (a / self._scale).tolist()
        self._inp.max_jerk = (j / self._scale).tolist()
        self._inp.synchronization = Synchronization.Time
        self._n = n
        self.unsynchronised = 0  # updates the motors could not finish together
        self.limited = 0  # cycles the smoothed counts needed Ruckig's step
        # the smoothing: STAGES moving averages of SMOOTH_CYCLES, as running sums
        m = SMOOTH_CYCLES
        self._ring = np.repeat(self._origin[None, None, :], SMOOTH_STAGES, axis=0)
        self._ring = np.repeat(self._ring, m, axis=1)  # (stages, m, n)
        self._sum = self._ring.sum(axis=1)  # (stages, n)
        self._slot = 0
        self._x = np.empty(n)
        self._sent = np.repeat(rest[None, :].astype(np.int64), 3, axis=0)  # the last 3
        self._d = np.empty(n, dtype=np.int64)

    def _update(self) -> np.ndarray:
        from ruckig import Result, Synchronization

        result = self._otg.update(self._inp, self._out)
        if result not in (Result.Working, Result.Finished):  # each motor on its own
            self.unsynchronised += 1
            self._inp.synchronization = Synchronization.No
            result = self._otg.update(self._inp, self._out)
            self._inp.synchronization = Synchronization.Time
        if result not in (Result.Working, Result.Finished):
            raise SetpointError(f"drive: no jerk-limited step within the limits ({result})")
        self._out.pass_to_input(self._inp)
        x = np.asarray(self._out.new_position) * self._scale + self._origin
        return self._sent_row(np.rint(x).astype(np.int64))

    def _sent_row(self, row: np.ndarray) -> np.ndarray:
        self._sent[2] = self._sent[1]
        self._sent[1] = self._sent[0]
        self._sent[0] = row
        return row

    def _smoothed(self, counts: np.ndarray) -> np.ndarray:
        """The counts through the smoothing (one cycle's input)."""
        x = self._x
        x[:] = counts
        k = self._slot
        m = SMOOTH_CYCLES
        for st in range(SMOOTH_STAGES):
            self._sum[st] += x - self._ring[st, k]
            self._ring[st, k] = x
            np.divide(self._sum[st], m, out=x)
        self._slot = (k + 1) % m
        return x

    def _within(self, row: np.ndarray) -> bool:
        """Whether ``row`` after the last three setpoints keeps every motor's limits."""
        p1, p2, p3 = self._sent
        v, a, j = self._per_cycle
        d = self._d
        np.subtract(row, p1, out=d)
        if np.any(np.abs(d) > v):
            return False
        d -= p1 - p2
        if np.any(np.abs(d) > a):
            return False
        d -= (p1 - p2) - (p2 - p3)
        return not np.any(np.abs(d) > j)

    def toward(self, counts: np.ndarray, rate_counts_per_s: np.ndarray) -> np.ndarray:
        """The next setpoint toward ``counts`` moving at ``rate_counts_per_s``."""
        from ruckig import ControlInterface

        smooth = self._smoothed(counts)
        row = np.rint(smooth).astype(np.int64)
        s, T = self._scale, self._T
        if self._within(row):  # the smoothed counts as they are; Ruckig's state follows
            p1, p2 = self._sent[0], self._sent[1]
            self._inp.current_position = ((row - self._origin) / s).tolist()
            self._inp.current_velocity = ((row - p1) / (T * s)).tolist()
            self._inp.current_acceleration = ((row - 2 * p1 + p2) / (T * T * s)).tolist()
            return self._sent_row(row)
        self.limited += 1
        self._inp.control_interface = ControlInterface.Position
        self._inp.target_position = ((smooth - self._origin) / s).tolist()
        self._inp.target_velocity = (np.clip(rate_counts_per_s, -self._v, self._v) / s).tolist()
        self._inp.target_acceleration = [0.0] * counts.shape[0]
        return self._update()

    def stop(self) -> np.ndarray:
        """The next setpoint of the stop (to rest, then where it rests)."""
        from ruckig import ControlInterface

        self._inp.control_interface = ControlInterface.Velocity
        n = self._n
        self._inp.target_velocity = [0.0] * n
        self._inp.target_acceleration = [0.0] * n
        return self._update()

    @property
    def at_rest(self) -> bool:
        """Whether every motor is at rest."""
        return not np.any(np.abs(np.asarray(self._inp.current_velocity)) > 1e-6)


class DriveSource:
    """The driver's online steps as setpoints (see the module).  ``command_at(t_s)`` is the
    operator's command at drive time ``t_s``; the drive runs until ``end_s``."""

    name = "drive"

    def __init__(
        self,
        driver: Driver,
        actuation: Actuation,
        command_at: Callable[[float], SteerCommand],
        end_s: float,
        *,
        hold_s: float = 0.2,
        go_on: bool = False,
    ) -> None:
        if not (math.isfinite(end_s) and end_s >= 0.0):
            raise DriveError(f"drive: the drive's end must be a time >= 0 s, got {end_s}")
        if not (math.isfinite(hold_s) and hold_s >= 0.0):
            raise DriveError(f"drive: the final hold must be >= 0 s, got {hold_s}")
        self.driver = driver
        self.actuation = actuation
        self.command_at = command_at
        self.end_s = float(end_s)
        self.hold_s = float(hold_s)
        self.go_on = bool(go_on)
        n = len(actuation.motor_ids)
        self._lead = np.zeros((0, n), dtype=np.int64)
        self._shaper: Shaper | None = None
        self._target = np.zeros(n, dtype=np.int64)  # the online step's counts
        self._rate = np.zeros(n, dtype=np.float64)  # and their change per second
        self._stopping_from = -1  # the slot the stop began at (-1: driving)
        self._rest_cycles = 0  # slots at rest after the stop
        self._n_drive = 0
        self.n_lead_in = 0
        self.cycles = 0  # online steps taken
        self.refusals: list[tuple[int, str]] = []
        self.stop_reason: str | None = None
        self.worst_clearance_mm = math.inf
        self.step_cpu_ms: list[float] = []
        self.shaping_lag_counts = 0  # the largest |setpoint - online step's counts|
        self.last_setpoint = np.zeros(n, dtype=np.int64)  # the last setpoint given
        self.last_status: CycleStatus | None = None  # the last online step's status
        self._end_requested = False
        self._holding = False  # go_on: the planner refused what is asked
        self._held_command: SteerCommand | None = None

    def request_end(self) -> None:
        """End the drive (from another thread): the command goes to rest within the
        advance ramp, the motors come to rest, then the hold."""
        self._end_requested = True

    @property
    def end_requested(self) -> bool:
        return self._end_requested

    def _check_period(self, period_s: float) -> None:
        if abs(period_s - self.driver.period_s) > 1e-9 * period_s:
            raise SetpointError(
                f"drive: the driver's period is {self.driver.period_s:g} s, the control "
                f"period is {period_s:g} s"
            )

    def precheck(self, period_s: float) -> None:
        """The driver's period is the control period; the trail's first configuration has
        counts within every rope limit."""
        self._check_period(period_s)
        self._counts_now()

    def _counts_now(self) -> np.ndarray:
        p = self.driver.planner
        try:
            return np.asarray(self.actuation.counts_from_angles(p.alpha, p.theta), np.int64)
        except HrmError as exc:
            raise SetpointError(f"drive: travel {p.travel:.1f} mm: {exc}") from None

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self._check_period(period_s)
        p = self.driver.planner
        first = self._counts_now()
        lead = CountsSource(
            self.actuation,
            first[None, :],
            period_s,
            name="drive",
            hold_s=0.0,
            first_pose=(p.alpha.copy(), p.theta.copy()),
        )
        lead.start(np.asarray(actual_counts, dtype=np.int64), period_s)
        self._lead = lead.table
        self.n_lead_in = lead.n_lead_in
        rest = self._lead[-1] if self._lead.shape[0] else np.asarray(actual_counts, np.int64)
        act = self.actuation
        self._shaper = Shaper(
            rest,
            period_s,
            np.asarray(act.max_rate_counts_per_s, dtype=np.float64),
            np.asarray(accel_limits(act), dtype=np.float64),
            np.asarray(jerk_limits(act), dtype=np.float64),
        )
        self._target = rest.copy()
        self._rate[:] = 0.0
        self._n_drive = math.floor(self.end_s / period_s + 1e-9) + 1
        self._stopping_from = -1
        self._rest_cycles = 0

    @property
    def n_cycles(self) -> int:
        """At most: the lead-in, the drive, and a stop and hold of up to 5 s."""
        margin = round(5.0 / self.driver.period_s)
        return int(self._lead.shape[0] + self._n_drive + margin)

    def _stop_row(self, k: int, reason: str | None) -> np.ndarray | None:
        """Slot ``k`` of the stop (to rest within the motors' limits), then the hold."""
        assert self._shaper is not None
        if self._stopping_from < 0:
            self._stopping_from = k
            if reason is not None and self.stop_reason is None:
                self.stop_reason = reason
        if self._shaper.at_rest:
            self._rest_cycles += 1
            if self._rest_cycles > max(1, round(self.hold_s / self.driver.period_s)):
                return None
        return self._shaper.stop()

    def _refuse(self, j: int, text: str) -> None:
        if not self.refusals or self.refusals[-1][1] != text:
            self.refusals.append((j, text))

    def setpoint(self, k: int) -> np.ndarray | None:
        n_lead = self._lead.shape[0]
        if k < n_lead:
            row: np.ndarray | None = self._lead[k]
        elif self._stopping_from >= 0 or k - n_lead >= self._n_drive:
            row = self._stop_row(k, None)
        else:
            row = self._drive_row(k, k - n_lead)
        if row is not None:
            self.last_setpoint = row
        return row

    def _drive_row(self, k: int, j: int) -> np.ndarray | None:
        """Slot ``k``, drive cycle ``j``: the online step, shaped."""
        assert self._shaper is not None
        c0 = time.thread_time()
        ending = self._end_requested
        command = STOP if ending else self.command_at(j * self.driver.period_s)
        status = self.driver.cycle(command)
        self.last_status = status
        self.cycles += 1
        self.worst_clearance_mm = min(self.worst_clearance_mm, status.clearance_mm)
        if ending and status.speed_mm_s == 0.0 and self._shaper.at_rest:
            self._n_drive = j  # at rest on the last step: the stop and the hold follow
            return self._stop_row(k, None)
        try:
            if status.refusal is not None:
                if self.go_on:  # hold at the last step accepted; the drive goes on
                    if not self._holding:  # once each time a hold begins
                        self.refusals.append((j, status.refusal.text))
                    self._holding = True
                    self._held_command = command
                    self._rate[:] = 0.0
                    row = self._shaper.toward(self._target, self._rate)
                    self.step_cpu_ms.append((time.thread_time() - c0) * 1e3)
                    return row
                raise DriveError(status.refusal.text)
            counts = self._counts_now()
        except HrmError as exc:
            self._refuse(j, str(exc))
            self.step_cpu_ms.append((time.thread_time() - c0) * 1e3)
            return self._stop_row(k, str(exc))
        if command != self._held_command:  # a hold lasts while the same is asked
            self._holding = False
        np.subtract(counts, self._target, out=self._rate, casting="unsafe")
        self._rate /= self.driver.period_s
        self._target = counts
        row = self._shaper.toward(counts, self._rate)
        self.shaping_lag_counts = max(self.shaping_lag_counts, int(np.abs(row - counts).max()))
        self.step_cpu_ms.append((time.thread_time() - c0) * 1e3)
        return row

    def summary(self) -> DriveSummary:
        """How the drive went (the online steps' CPU time includes the counts and the
        shaping)."""
        a = np.asarray(self.step_cpu_ms) if self.step_cpu_ms else np.zeros(1)
        p = self.driver.planner
        return DriveSummary(
            cycles=self.cycles,
            travel_mm=p.travel,
            trail_length_mm=p.trail.length,
            worst_clearance_mm=self.worst_clearance_mm,
            refusals=tuple(self.refusals),
            step_cpu_ms={
                "p50": round(float(np.percentile(a, 50)), 3),
                "p99": round(float(np.percentile(a, 99)), 3),
                "max": round(float(a.max()), 3),
            },
        )

    def describe(self) -> dict[str, Any]:
        return {
            "source": self.name,
            "lead_in_cycles": self.n_lead_in,
            "drive_cycles": self.cycles,
            "travel_mm": round(self.driver.planner.travel, 6),
            "stop_reason": self.stop_reason,
            "refusals": [{"cycle": j, "text": t} for j, t in self.refusals],
            "shaping_lag_counts": self.shaping_lag_counts,
            "unsynchronised_updates": 0 if self._shaper is None else self._shaper.unsynchronised,
            "ruckig_cycles": 0 if self._shaper is None else self._shaper.limited,
            "last_setpoint": self.last_setpoint.tolist(),
        }
