"""One control cycle of driving: the operator's command to the arm's next angles.

Every control period the :class:`Driver` takes the steer command (capped by its
:class:`~hrm_ctrl.drive.command.SteerLimits`), ramps the advance speed toward it within
``accel_mm_s2`` (hold-to-move: no command ramps it to zero, so a released key stops the
tip within the deceleration limit), grows the trail where the tip advances past its end
(turning by ``rate / advance cap`` per mm: at full speed the tip turns at the commanded
rate; a steer behind the trail's end cuts the trail there and draws a new branch), and
asks the online planner for the step.  A refused step holds the arm where it was: the
speed drops to zero, the trail drawn this cycle is taken back, and the refusal is the
cycle's status.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.drive.command import SteerCommand, SteerLimits
>>> from hrm_ctrl.drive.online import OnlinePlanner
>>> from hrm_ctrl.drive.trail import Trail
>>> trail = Trail.starting_at(np.array([1200.0, 100.0, 300.0]), np.array([1.0, 0.0, 0.0]))
>>> drv = Driver(OnlinePlanner(default_robot(), trail), SteerLimits(), 0.01)
>>> for _ in range(100): s = drv.cycle(SteerCommand(0.0, 0.0, 20.0))
>>> round(drv.speed_mm_s, 6), round(drv.planner.travel, 3)       # 0.5 s ramp, then 20 mm/s
(20.0, 15.1)
>>> for _ in range(60): s = drv.cycle(SteerCommand())             # released: stops in 0.5 s
>>> drv.speed_mm_s, round(drv.planner.travel, 3)
(0.0, 20.0)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.drive.command import DriveError, SteerCommand, SteerLimits
from hrm_ctrl.drive.online import OnlinePlanner, Refusal


@dataclass(frozen=True)
class CycleStatus:
    """What one cycle did: the travel, the speed, the arm's worst clearance (mm, inf
    without an environment) and the refusal that holds the arm (None when it moved or
    stands still by request)."""

    travel_mm: float
    speed_mm_s: float
    clearance_mm: float
    refusal: Refusal | None

    def line(self) -> str:
        """The status line."""
        c = "" if math.isinf(self.clearance_mm) else f"  clearance {self.clearance_mm:5.1f} mm"
        head = f"travel {self.travel_mm:7.1f} mm  speed {self.speed_mm_s:5.1f} mm/s{c}"
        return head if self.refusal is None else f"{head}  HOLD: {self.refusal.text}"


class Driver:
    """The cycle of follow-the-leader driving (see the module)."""

    def __init__(self, planner: OnlinePlanner, limits: SteerLimits, period_s: float) -> None:
        if not (math.isfinite(period_s) and 0.0 < period_s <= 1.0):
            raise DriveError(f"control period must be in (0, 1] s, got {period_s}")
        self.planner = planner
        self.limits = limits
        self.period_s = float(period_s)
        self.speed_mm_s = 0.0
        self.refusal: Refusal | None = None

    @property
    def q(self) -> np.ndarray:
        """The arm's angles (alpha_1..12, theta_1..12) after the last cycle."""
        return self.planner.q

    def cycle(self, command: SteerCommand) -> CycleStatus:
        """One control cycle under ``command`` (capped); returns its status."""
        cmd = command.capped(self.limits)
        dt = self.period_s
        dv = self.limits.accel_mm_s2 * dt
        v = self.speed_mm_s + max(-dv, min(dv, cmd.advance_mm_s - self.speed_mm_s))
        if abs(v) < 1e-12:
            v = 0.0
        p = self.planner
        trail = p.trail
        ds = v * dt
        if ds == 0.0:
            self.speed_mm_s = 0.0
            self.refusal = None
            return self._status(None)
        target = p.travel + ds
        if target < 0.0 < p.travel:  # retracting onto the trail's start: stop there
            target, v = 0.0, 0.0
        steer = cmd.yaw_rate_rad_s != 0.0 or cmd.pitch_rate_rad_s != 0.0
        grown = 0.0
        restore: tuple[float, np.ndarray, np.ndarray] | None = None
        if ds > 0.0 and (steer or target > trail.length):
            if steer and p.travel < trail.length - 1e-9:
                trail.cut(p.travel)  # a new branch from the tip
                p.forget_beyond(p.travel)
            grown = target - trail.length
            if grown > 0.0:
                restore = (trail.length, trail.heading, trail.up)
                cap = self.limits.advance_mm_s
                trail.extend(grown, cmd.yaw_rate_rad_s / cap, cmd.pitch_rate_rad_s / cap)
                target = min(target, trail.length)  # an arc's chords are a little shorter
        refusal = p.step_to(target)
        if refusal is not None:
            if restore is not None:  # take back what was drawn beyond the tip
                if p.travel <= restore[0]:
                    trail.cut(restore[0])
                    trail.set_heading(restore[1], restore[2])
                else:
                    trail.cut(p.travel)
            self.speed_mm_s = 0.0
            self.refusal = refusal
            return self._status(refusal)
        self.speed_mm_s = v
        self.refusal = None
        return self._status(None)

    def _status(self, refusal: Refusal | None) -> CycleStatus:
        p = self.planner
        return CycleStatus(p.travel, self.speed_mm_s, p.clearance_mm, refusal)


@dataclass(frozen=True)
class DriveSummary:
    """How a drive went: cycles, the final travel, the trail's length, the worst
    clearance seen (inf without an environment), the refusals (one line each, the cycle it
    began) and the CPU time of the online steps (p50, p99, max; ms)."""

    cycles: int
    travel_mm: float
    trail_length_mm: float
    worst_clearance_mm: float
    refusals: tuple[tuple[int, str], ...]
    step_cpu_ms: dict[str, float]

    def to_dict(self) -> dict[str, object]:
        return {
            "cycles": self.cycles,
            "travel_mm": round(self.travel_mm, 6),
            "trail_length_mm": round(self.trail_length_mm, 6),
            "worst_clearance_mm": None
            if math.isinf(self.worst_clearance_mm)
            else round(self.worst_clearance_mm, 3),
            "refusals": [{"cycle": k, "text": t} for k, t in self.refusals],
            "step_cpu_ms": self.step_cpu_ms,
        }


def run_scripted(
    driver: Driver,
    command_at: Callable[[float], SteerCommand],
    end_s: float,
    *,
    on_status: Callable[[int, CycleStatus], None] | None = None,
) -> DriveSummary:
    """Drive on the simulated clock: cycle ``k`` at ``k * period`` under
    ``command_at(t_s)`` until ``end_s``; ``on_status(k, status)`` sees every cycle.  A
    refusal is listed once when it begins (the same text on the next cycles is the hold)."""
    import time

    cpu: list[float] = []
    refusals: list[tuple[int, str]] = []
    worst = math.inf
    last_text: str | None = None
    k = 0
    while k * driver.period_s <= end_s + 1e-9:
        c0 = time.thread_time()
        s = driver.cycle(command_at(k * driver.period_s))
        cpu.append((time.thread_time() - c0) * 1e3)
        worst = min(worst, s.clearance_mm)
        text = None if s.refusal is None else s.refusal.text
        if text is not None and text != last_text:
            refusals.append((k, text))
        last_text = text
        if on_status is not None:
            on_status(k, s)
        k += 1
    a = np.asarray(cpu) if cpu else np.zeros(1)
    return DriveSummary(
        cycles=k,
        travel_mm=driver.planner.travel,
        trail_length_mm=driver.planner.trail.length,
        worst_clearance_mm=worst,
        refusals=tuple(refusals),
        step_cpu_ms={
            "p50": round(float(np.percentile(a, 50)), 3),
            "p99": round(float(np.percentile(a, 99)), 3),
            "max": round(float(a.max()), 3),
        },
    )
