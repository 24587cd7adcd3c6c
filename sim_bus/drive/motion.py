"""CSP following of a simulated drive: the motor's position and velocity.

On each SYNC the applied target (clamped to the software position limits
0x607D, statusword bit 11 while clamped) is followed for one interpolation
period (0x60C2) with the drive's velocity and acceleration limits; quick stop
and fault reaction ramp down with the quick-stop deceleration, and every other
state holds the motor (brake).  A following error beyond 0x6065 faults the
drive with EMCY 0x8611.  Mode 8 (CSP) is the only motion mode; 0x6060 takes the modes the
device file declares in 0x6502 (the others: abort 0x06090030, as a real drive answers).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from drivers.protocol import cia301, cia402
from sim_bus.drive.objects import SdoAbort

if TYPE_CHECKING:
    from sim_bus.drive import DriveParams, DriveSim

State = cia402.State402

FOLLOWING_ERROR_WINDOW_OFF = 0xFFFFFFFF  # 0x6065 = UNSIGNED32 max: no following error check
DEFAULT_INTERPOLATION_PERIOD_S = 0.01  # used while 0x60C2 holds no positive period


class CspMotion:
    """Position, velocity and the motion flags of one drive's motor."""

    def __init__(self, drive: DriveSim, params: DriveParams) -> None:
        self._drive = drive
        self._od = drive.od
        self.params = params
        self.position = float(params.initial_position_counts)
        self.velocity = 0.0
        self.jammed = False  # fault injection: the motor cannot turn
        self.limit_active = False
        self.following_error = False
        self.last_motion = 0.0
        self._params = (DEFAULT_INTERPOLATION_PERIOD_S, FOLLOWING_ERROR_WINDOW_OFF, 0)
        self._params_at = -1  # the OD generation _params was read at

    def reset(self) -> None:
        """Power-on: no limit or following error shown (the motor stays where it is)."""
        self.limit_active = False
        self.following_error = False

    @property
    def mode(self) -> int:
        return self._parameters()[2]

    @property
    def position_counts(self) -> int:
        return int(max(cia402.INT32_MIN, min(cia402.INT32_MAX, round(self.position))))

    @property
    def interpolation_period_s(self) -> float:
        return self._parameters()[0]

    def _parameters(self) -> tuple[float, int, int]:
        """(interpolation period 0x60C2 in s, following error window 0x6065, mode of
        operation 0x6060), read again only when the object dictionary changed."""
        od = self._od
        if self._params_at != od.generation:
            value = od.int_value(cia402.OD_INTERPOLATION_TIME_PERIOD, 1)
            index = od.int_value(cia402.OD_INTERPOLATION_TIME_PERIOD, 2)
            period = value * 10.0**index
            self._params = (
                period if period > 0 else DEFAULT_INTERPOLATION_PERIOD_S,
                od.int_value(cia402.OD_FOLLOWING_ERROR_WINDOW),
                od.int_value(cia402.OD_MODES_OF_OPERATION),
            )
            self._params_at = od.generation
        return self._params

    def _target_and_limits(self) -> tuple[int, int, int]:
        """(target position 0x607A, software position limits 0x607D min and max)."""
        values = self._od.values
        return (
            int(values[(cia402.OD_TARGET_POSITION, 0)]),  # type: ignore[arg-type]
            int(values[(cia402.OD_SOFTWARE_POSITION_LIMIT, 1)]),  # type: ignore[arg-type]
            int(values[(cia402.OD_SOFTWARE_POSITION_LIMIT, 2)]),  # type: ignore[arg-type]
        )

    @property
    def target(self) -> float:
        """The target position clamped to the software position limits (when lo <= hi)."""
        t, lo, hi = self._target_and_limits()
        return float(min(max(t, lo), hi)) if lo <= hi else float(t)

    # ---------------------------------------------------------------- motion
    def advance(self, dt: float, now: float) -> None:
        """Move the motor for ``dt`` seconds according to the drive state."""
        self.last_motion = now
        sm = self._drive.state_machine
        raw, lo, hi = self._target_and_limits()  # no service below writes them
        target = float(min(max(raw, lo), hi)) if lo <= hi else float(raw)
        if self.jammed:
            self.velocity = 0.0
        elif sm.state == State.OPERATION_ENABLED and self.mode == cia402.MODE_CSP:
            self.limit_active = lo <= hi and not lo <= raw <= hi
            self._follow(target, dt, self.params.max_accel_counts_per_s2)
        elif sm.decelerating:
            self._brake(dt)
            if self.velocity == 0.0:
                sm.stopped()
        else:
            self.velocity = 0.0  # brake engaged / disabled
        if sm.state == State.OPERATION_ENABLED:
            window = self._parameters()[1]
            err = abs(target - self.position)
            if window != FOLLOWING_ERROR_WINDOW_OFF and err > window:
                self.following_error = True
                sm.fault(
                    cia402.EMCY_FOLLOWING_ERROR,
                    now,
                    f"following error {err:.0f} counts > window {window}",
                )

    def _follow(self, target: float, dt: float, accel: float) -> None:
        """Velocity- and acceleration-limited step towards ``target`` (time-optimal stop)."""
        vmax = self.params.max_velocity_counts_per_s
        e = target - self.position
        v_des = e / dt
        v_brake = math.sqrt(2.0 * accel * abs(e))
        v_des = math.copysign(min(abs(v_des), v_brake, vmax), e)
        dv = max(-accel * dt, min(accel * dt, v_des - self.velocity))
        self.velocity += dv
        self.position += self.velocity * dt
        if abs(target - self.position) < 0.5 and abs(self.velocity) <= accel * dt:
            self.position, self.velocity = target, 0.0

    def _brake(self, dt: float) -> None:
        dec = self.params.quick_stop_decel_counts_per_s2
        v = self.velocity
        if abs(v) <= dec * dt:
            self.position += v * dt / 2.0
            self.velocity = 0.0
        else:
            nv = v - math.copysign(dec * dt, v)
            self.position += (v + nv) * dt / 2.0
            self.velocity = nv

    # ---------------------------------------------------------------- objects
    def check_write(self, index: int, sub: int, value: int) -> None:
        if index == cia402.OD_MODES_OF_OPERATION and not self.mode_supported(value):
            raise SdoAbort(cia301.SDO_ABORT_INVALID_VALUE)

    def mode_supported(self, mode: int) -> bool:
        """Whether the drive takes mode of operation ``mode``: no mode (0), or one its device
        file declares in 0x6502 (bit n: mode n + 1; a file without 0x6502: CSP only).  The
        simulated motor moves in CSP only; in another declared mode it holds."""
        return mode == 0 or (1 <= mode <= 32 and self._declared_modes() >> (mode - 1) & 1 == 1)

    def _declared_modes(self) -> int:
        values = self._od.values
        key = (cia402.OD_SUPPORTED_DRIVE_MODES, 0)
        declared = values.get(key)
        return int(declared) if isinstance(declared, int) else 1 << (cia402.MODE_CSP - 1)
