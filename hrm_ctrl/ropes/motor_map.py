"""Rope length <-> drum <-> encoder counts, and the elastic stretch of a rope.

A rope's free length runs from its drum in the box (``box_length``) along the arm
to its anchor (the geometric length of :mod:`hrm_ctrl.ropes.length`).  Under a
tension T a rope of unstretched length u is ``u (1 + T / EA)`` long, so to hold
a free length ``L`` at tension T the drum must have paid out ``u = L / (1 + T/EA)``.
The motor winds rope in as its count grows (direction +1):

    counts = zero_offset + direction * counts_per_mm * (u_ref - u)

with ``counts_per_mm = gear_ratio * counts_per_turn / (2 pi drum_radius)`` and
``u_ref`` the paid-out length on the straight arm at the pretension (the
calibration zero).

The ``[motors]`` table of the robot description (all optional, defaults below):
``drum_radius_mm`` (10), ``gear_ratio`` (33, motor turns per drum turn),
``counts_per_turn`` (4096, encoder counts per motor turn), ``max_speed_rpm``
(6000, motor shaft), ``max_accel_rpm_per_s`` (30 000, motor shaft: full speed in
0.2 s), ``max_jerk_rpm_per_s2`` (600 000: full acceleration in 0.05 s),
``travel_in_mm`` / ``travel_out_mm`` (200 / 200: rope the drum can wind in / pay out
from the zero position) and ``direction`` (+1, -1, or a table ``{ j03r1 = -1, ... }``
per motor).  Every number has a range (:data:`MOTOR_RANGES`: speeds, accelerations and
jerks a motor can have, no 1e300); outside it the description is refused naming the key.

Why 30 000 rpm/s: a small servo (a few hundred W, rotor inertia about 1e-5 kg m^2,
peak torque about 1 N m) could spin its own rotor up far faster, but behind a 33:1
gearbox and a 10 mm drum it moves the rope at 952 mm/s^2 at this limit (2 048 000
counts/s^2), which keeps the arm's joints well inside what the ropes, the gearbox
backlash and the drives' following (the simulated drive follows at up to 2e7
counts/s^2) take; servo drives ship with ramps of 10 000 - 100 000 rpm/s.  The jerk
limit shapes the point-to-point moves of the drivers (lead-in, jog, end of a
source); the plan's own time parameterisation limits speed and acceleration.

>>> m = DEFAULT_MOTORS
>>> m["max_accel_rpm_per_s"] / 60.0 * m["counts_per_turn"]        # counts/s^2
2048000.0

>>> round(float(unstretched_length_mm(2500.0, 30.0, 30000.0)), 4)   # 2.5 m at 30 N, EA 30 kN
2497.5025
>>> round(float(rope_tension_N(2500.0, 2497.5025, 30000.0)), 3)
30.0
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError

DEFAULT_MOTORS: dict[str, float] = {
    "drum_radius_mm": 10.0,
    "gear_ratio": 33.0,
    "counts_per_turn": 4096.0,
    "max_speed_rpm": 6000.0,
    "max_accel_rpm_per_s": 30000.0,
    "max_jerk_rpm_per_s2": 600000.0,
    "travel_in_mm": 200.0,
    "travel_out_mm": 200.0,
}


# The range of every [motors] number: wide enough for any motor, gearbox and drum of a rope
# box, far below the numbers only a typo makes (1e300 rpm overflows the time
# parameterisation).  Speed 1 .. 100 000 rpm (the fastest small servos run at 20 000 -
# 50 000); acceleration 1 .. 1e6 rpm/s (a small servo's own rotor at its peak torque, ten
# times the steepest ramp drives ship with); jerk 1000 .. 1e9 rpm/s^2 (that acceleration in
# 1 ms; below 1000 a jerk-limited lead-in of the drum travel would take hours); a drum of
# up to 1000 mm radius, a gear ratio of 1e-3 .. 1e4, an encoder of 1 .. 2^32 counts per
# turn; the drum travel up to the robot description's 100 m (and the drives' 32 bits).
MOTOR_RANGES: dict[str, tuple[float, float]] = {
    "drum_radius_mm": (0.0, 1000.0),  # a small radius: the drives' 32 bits decide
    "gear_ratio": (1e-3, 1e4),
    "counts_per_turn": (1.0, 2.0**32),
    "max_speed_rpm": (1.0, 1e5),
    "max_accel_rpm_per_s": (1.0, 1e6),
    "max_jerk_rpm_per_s2": (1e3, 1e9),
    "travel_in_mm": (0.0, 1e5),
    "travel_out_mm": (0.0, 1e5),
}


# A drive's position (CiA 402 0x607A, 0x6064) is a 32-bit signed count: every count a motor
# may be sent (zero offset + the drum travel either way) must fit it.
POSITION_COUNTS_MAX = 2**31 - 1


class MotorConfigError(RopeError):
    """The ``[motors]`` table is malformed or names an unknown motor."""


def unstretched_length_mm(free_length_mm: Any, tension_N: Any, EA_N: Any) -> Any:
    """Unstretched rope length that is ``free_length_mm`` long under ``tension_N``."""
    return free_length_mm / (1.0 + np.asarray(tension_N) / EA_N)


def stretched_length_mm(unstretched_mm: Any, tension_N: Any, EA_N: Any) -> Any:
    """Length of a rope of unstretched length ``unstretched_mm`` under ``tension_N``.

    >>> float(stretched_length_mm(1000.0, 300.0, 30000.0))
    1010.0
    """
    return unstretched_mm * (1.0 + np.asarray(tension_N) / EA_N)


def rope_tension_N(free_length_mm: Any, unstretched_mm: Any, EA_N: Any) -> Any:
    """Tension of a rope stretched from ``unstretched_mm`` to ``free_length_mm``; 0 if slack.

    The stretch/tension relation the simulated box uses: the drum fixes the
    unstretched length (from the counts), the arm's pose fixes the free length.

    >>> np.round(rope_tension_N(np.array([1010.0, 990.0]), 1000.0, 30000.0), 9).tolist()
    [300.0, 0.0]
    """
    strain = np.asarray(free_length_mm) / np.asarray(unstretched_mm) - 1.0
    return np.maximum(EA_N * strain, 0.0) + 0.0


@dataclass(frozen=True, eq=False)
class MotorMap:
    """Per-motor conversion constants (read-only arrays, one entry per rope motor)."""

    counts_per_mm: np.ndarray  # (n,) counts per mm of rope wound
    direction: np.ndarray  # (n,) +1 / -1
    zero_offsets_counts: np.ndarray  # (n,) int64 counts at the zero position
    u_ref: np.ndarray  # (n,) unstretched paid-out length at the zero position (mm)
    travel_in_mm: float
    travel_out_mm: float
    max_speed_rpm: float
    counts_per_turn: float
    max_accel_rpm_per_s: float = DEFAULT_MOTORS["max_accel_rpm_per_s"]
    max_jerk_rpm_per_s2: float = DEFAULT_MOTORS["max_jerk_rpm_per_s2"]

    def counts_from_unstretched(self, u: np.ndarray) -> np.ndarray:
        """Encoder counts (int64) for paid-out unstretched lengths ``u`` (..., n)."""
        c = self.zero_offsets_counts + self.direction * self.counts_per_mm * (self.u_ref - u)
        return np.rint(c).astype(np.int64)

    def unstretched_from_counts(self, counts: np.ndarray) -> np.ndarray:
        """Paid-out unstretched lengths (mm) for encoder counts (..., n)."""
        c = np.asarray(counts, dtype=float) - self.zero_offsets_counts
        return self.u_ref - self.direction * c / self.counts_per_mm

    @property
    def counts_min(self) -> np.ndarray:
        return np.minimum(self._limit(self.travel_in_mm), self._limit(-self.travel_out_mm))

    @property
    def counts_max(self) -> np.ndarray:
        return np.maximum(self._limit(self.travel_in_mm), self._limit(-self.travel_out_mm))

    def _limit(self, wound_mm: float) -> np.ndarray:
        return self.zero_offsets_counts + np.trunc(
            self.direction * self.counts_per_mm * wound_mm
        ).astype(np.int64)

    @property
    def max_rate_counts_per_s(self) -> np.ndarray:
        rate = self.max_speed_rpm / 60.0 * self.counts_per_turn
        return np.full(self.direction.shape, rate)

    @property
    def max_accel_counts_per_s2(self) -> np.ndarray:
        """Acceleration limit per motor, ``max_accel_rpm_per_s / 60 * counts_per_turn``."""
        accel = self.max_accel_rpm_per_s / 60.0 * self.counts_per_turn
        return np.full(self.direction.shape, accel)

    @property
    def max_jerk_counts_per_s3(self) -> np.ndarray:
        """Jerk limit per motor, ``max_jerk_rpm_per_s2 / 60 * counts_per_turn``."""
        jerk = self.max_jerk_rpm_per_s2 / 60.0 * self.counts_per_turn
        return np.full(self.direction.shape, jerk)


def _num(table: Mapping[str, Any], key: str, where: str, *, positive: bool = True) -> float:
    value = table.get(key, DEFAULT_MOTORS[key])
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise MotorConfigError(f"{where}.{key}: expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x) or (positive and x <= 0.0) or x < 0.0:
        raise MotorConfigError(f"{where}.{key}: must be a finite number > 0, got {value!r}")
    low, high = MOTOR_RANGES[key]
    if not low <= x <= high:
        raise MotorConfigError(
            f"{where}.{key}: {x:.6g} is out of range "
            f"({low:g} {'<' if low == 0.0 else '<='} value <= {high:g})"
        )
    return x


def _directions(value: Any, ids: Sequence[str], where: str) -> np.ndarray:
    n = len(ids)
    if isinstance(value, Mapping):
        out = np.ones(n)
        for key, v in value.items():
            if key not in ids:
                raise MotorConfigError(f"{where}.direction: unknown motor id {key!r}")
            out[ids.index(key)] = _sign(v, f"{where}.direction.{key}")
        return out
    if isinstance(value, list):
        if len(value) != n:
            raise MotorConfigError(f"{where}.direction: list must have {n} values")
        return np.array([_sign(v, f"{where}.direction[{i}]") for i, v in enumerate(value)])
    return np.full(n, _sign(value, f"{where}.direction"))


def _sign(v: Any, where: str) -> float:
    if isinstance(v, bool) or v not in (1, -1):
        raise MotorConfigError(f"{where}: must be +1 or -1, got {v!r}")
    return float(v)


def zero_offsets_from(value: Any, ids: Sequence[str]) -> np.ndarray:
    """Zero offsets as an int64 array from None, a sequence of n ints or ``{id: counts}``.

    >>> zero_offsets_from({"b": 7}, ["a", "b"]).tolist()
    [0, 7]
    """
    n = len(ids)
    out = np.zeros(n, dtype=np.int64)
    if value is None:
        return out
    if isinstance(value, Mapping):
        for key, v in value.items():
            if key not in ids:
                raise RopeError(f"zero offsets: unknown motor id {key!r}")
            out[ids.index(key)] = _int(v, f"zero offsets: {key}")
        return out
    arr = np.asarray(value)
    if arr.shape != (n,):
        raise RopeError(f"zero offsets: expected {n} values, got shape {arr.shape}")
    return np.array([_int(v, f"zero offsets[{i}]") for i, v in enumerate(arr.tolist())], np.int64)


def _int(v: Any, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v != int(v):
        raise RopeError(f"{where}: expected an integer count, got {v!r}")
    if abs(v) > POSITION_COUNTS_MAX:
        raise RopeError(f"{where}: {v!r} is beyond the drives' 32-bit position")
    return int(v)


def motor_map_from_table(
    table: Mapping[str, Any],
    ids: Sequence[str],
    u_ref: np.ndarray,
    zero_offsets_counts: Any = None,
    source: str = "[motors]",
) -> MotorMap:
    """Validate a ``[motors]`` table (may be empty: defaults) and build the map."""
    where = f"{source}: [motors]"
    if not isinstance(table, Mapping):
        raise MotorConfigError(f"{where} must be a table")
    for key in table:
        if key not in DEFAULT_MOTORS and key != "direction":
            raise MotorConfigError(f"{where}: unknown key {key!r}")
    ids = list(ids)
    vals = {k: _num(table, k, where) for k in DEFAULT_MOTORS}
    cpm = vals["gear_ratio"] * vals["counts_per_turn"] / (2.0 * math.pi * vals["drum_radius_mm"])
    travel = max(vals["travel_in_mm"], vals["travel_out_mm"])
    span = cpm * travel
    if not span <= POSITION_COUNTS_MAX:  # inf or nan included
        raise MotorConfigError(
            f"{where}: {cpm:.4g} counts/mm over {travel:g} mm of drum travel is {span:.4g} "
            f"counts, beyond the drives' 32-bit position (at most {POSITION_COUNTS_MAX})"
        )
    n = len(ids)
    arrays = {
        "counts_per_mm": np.full(n, cpm),
        "direction": _directions(table.get("direction", 1), ids, where),
        "zero_offsets_counts": zero_offsets_from(zero_offsets_counts, ids),
        "u_ref": np.array(u_ref, dtype=float),
    }
    for arr in arrays.values():
        arr.setflags(write=False)
    return MotorMap(
        travel_in_mm=vals["travel_in_mm"],
        travel_out_mm=vals["travel_out_mm"],
        max_speed_rpm=vals["max_speed_rpm"],
        counts_per_turn=vals["counts_per_turn"],
        max_accel_rpm_per_s=vals["max_accel_rpm_per_s"],
        max_jerk_rpm_per_s2=vals["max_jerk_rpm_per_s2"],
        **arrays,
    )
