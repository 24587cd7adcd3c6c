"""What the operator asks of the tip: the steer command and its caps.

A :class:`SteerCommand` is what an input device (keyboard, gamepad, a scripted key
file) produces every control cycle and what the online planner consumes: the tip's yaw
and pitch rates (rad/s, signed, about the tip's own axes: yaw turns the heading about
the trail's "up" normal, pitch about its "side" normal) and the advance speed along the
trail (mm/s, signed: negative retracts along the same trail).  Commands are always
capped by :class:`SteerLimits` before use (:meth:`SteerCommand.capped`), so no device
can ask for more than the caps.

A device with analog axes gives each axis in ``[-1, 1]``
(:meth:`SteerCommand.from_axes`); a key held is ``+1`` or ``-1`` on its axis.

Hold-to-move: the planner treats "no command" (:data:`STOP`) as a request to stop and
ramps the advance speed down within the motors' deceleration; steering only turns the
trail while the tip advances (the turn per mm is ``rate / speed``).

>>> lim = SteerLimits()
>>> SteerCommand.from_axes(1.0, 0.0, 0.5, lim)
SteerCommand(yaw_rate_rad_s=0.3, pitch_rate_rad_s=0.0, advance_mm_s=10.0)
>>> SteerCommand(9.0, -9.0, -99.0).capped(lim)
SteerCommand(yaw_rate_rad_s=0.3, pitch_rate_rad_s=-0.3, advance_mm_s=-20.0)
>>> STOP.is_stop
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from hrm_ctrl.errors import PlanningError


class DriveError(PlanningError):
    """A drive input (key file, steer limits, trail) is malformed or out of range."""


class SteerAxis(StrEnum):
    """The three things an operator controls."""

    YAW = "yaw"
    PITCH = "pitch"
    ADVANCE = "advance"


@dataclass(frozen=True, slots=True)
class SteerLimits:
    """Caps on a steer command: the largest tip turn rates and advance speed (both ways).

    ``accel_mm_s2`` is the advance speed's ramp, up and down (hold-to-move stops within it).
    """

    yaw_rate_rad_s: float = 0.3
    pitch_rate_rad_s: float = 0.3
    advance_mm_s: float = 20.0
    accel_mm_s2: float = 40.0

    def __post_init__(self) -> None:
        for name in ("yaw_rate_rad_s", "pitch_rate_rad_s", "advance_mm_s", "accel_mm_s2"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise DriveError(f"steer limits: {name}: expected a number > 0, got {v!r}")


def _clip(v: float, cap: float) -> float:
    if not math.isfinite(v):
        return 0.0
    return max(-cap, min(cap, v))


@dataclass(frozen=True, slots=True)
class SteerCommand:
    """Tip yaw rate, pitch rate (rad/s) and advance speed (mm/s, negative retracts)."""

    yaw_rate_rad_s: float = 0.0
    pitch_rate_rad_s: float = 0.0
    advance_mm_s: float = 0.0

    @classmethod
    def from_axes(
        cls, yaw: float, pitch: float, advance: float, limits: SteerLimits
    ) -> SteerCommand:
        """A command from normalised axes in ``[-1, 1]`` (clipped), scaled by the caps."""
        return cls(
            _clip(yaw, 1.0) * limits.yaw_rate_rad_s,
            _clip(pitch, 1.0) * limits.pitch_rate_rad_s,
            _clip(advance, 1.0) * limits.advance_mm_s,
        )

    def capped(self, limits: SteerLimits) -> SteerCommand:
        """This command within ``limits`` (a NaN or inf component counts as 0)."""
        return SteerCommand(
            _clip(self.yaw_rate_rad_s, limits.yaw_rate_rad_s),
            _clip(self.pitch_rate_rad_s, limits.pitch_rate_rad_s),
            _clip(self.advance_mm_s, limits.advance_mm_s),
        )

    @property
    def is_stop(self) -> bool:
        """No motion asked."""
        return (
            self.yaw_rate_rad_s == 0.0 and self.pitch_rate_rad_s == 0.0 and self.advance_mm_s == 0.0
        )


STOP = SteerCommand()
