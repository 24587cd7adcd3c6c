"""The rope layer as the drivers see it: three typed Protocols, one inside the next.

The drivers may not import the rope layer (``hrm_ctrl.ropes``): they type against these
Protocols and the rope layer implements them structurally.  Each consumer asks for the
smallest one it needs, so what it may call is chosen by its type, never by probing:

* :class:`MotorLimits`: the rope motors' names and limits and the check of a setpoint
  against them (the supervisor, the session, a pausable playback).  A test double of the
  limits implements this alone.
* :class:`RopeModel`: the motors' limits and the joints they move (a jog's and a table's
  checks map counts to joint angles).  The rope layer's ``Actuation`` implements it,
  and so does a motor subset (:class:`drivers.safety.subset.ActuationSubset`: the other
  motors held still).
* :class:`ArmRopeModel`: the model of every rope of the arm (rope tensions, lines in
  joint space, the pose the counts show), which only the whole rope layer has; a
  :class:`RopeModel` gives it as :attr:`RopeModel.whole_arm`, ``None`` for a subset (its
  other ropes are not commanded: their tensions are unknown).

Arrays are NumPy: counts (..., n motors) int64, joint angles (..., n joints) rad (true
angles), tensions (..., n) N.  ``hrm_ctrl.ropes.actuation.Actuation`` implements all
three (tests/drivers/test_rope_model.py checks it, a subset and the test doubles).

>>> import numpy as np
>>> class Lim:  # a double: limits only
...     motor_ids = ("m0",); counts_min = np.array([-9]); counts_max = np.array([9])
...     max_rate_counts_per_s = np.array([1e3]); max_accel_counts_per_s2 = None
...     max_jerk_counts_per_s3 = None
...     def motor_label(self, i): return self.motor_ids[i]
...     def check_counts(self, counts, previous=None, dt_s=None): pass
>>> isinstance(Lim(), MotorLimits), isinstance(Lim(), RopeModel)
(True, False)
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["ArmRopeModel", "JointPath", "MotorLimits", "RopeModel"]


@runtime_checkable
class MotorLimits(Protocol):
    """The rope motors' limits, in the rope layer's motor order (one entry per motor)."""

    @property
    def motor_ids(self) -> tuple[str, ...]:
        """Motor ids (``"jKKrM"`` for the rope layer's)."""
        ...

    @property
    def counts_min(self) -> np.ndarray:
        """(n,) int64: the lowest setpoint of each motor (software position limit)."""
        ...

    @property
    def counts_max(self) -> np.ndarray:
        """(n,) int64: the highest setpoint of each motor."""
        ...

    @property
    def max_rate_counts_per_s(self) -> np.ndarray:
        """(n,) float: each motor's speed limit."""
        ...

    @property
    def max_accel_counts_per_s2(self) -> np.ndarray | None:
        """(n,) float: each motor's acceleration limit; ``None``: none is checked (a double)."""
        ...

    @property
    def max_jerk_counts_per_s3(self) -> np.ndarray | None:
        """(n,) float: each motor's jerk limit for the moves a source plans; ``None``:
        derived from the acceleration (``drivers.safety.limits.jerk_limits``)."""
        ...

    def motor_label(self, i: int) -> str:
        """Motor ``i`` as a message names it (``"j05r2 (joint 5, rope 2)"``)."""
        ...

    def check_counts(
        self, counts: ArrayLike, previous: ArrayLike | None = None, dt_s: ArrayLike | None = None
    ) -> None:
        """Raise (an ``HrmError``, one line naming the motor and, for a table, the step)
        when a setpoint (n,) or a table (steps, n) leaves the position limits or, with
        ``dt_s``, moves faster than a motor's speed from ``previous`` / row to row."""
        ...


@runtime_checkable
class RopeModel(MotorLimits, Protocol):
    """The motors' limits and the joints they move: counts <-> joint angles."""

    @property
    def n_joints(self) -> int:
        """Universal joints of the arm (alpha and theta each)."""
        ...

    @property
    def whole_arm(self) -> ArmRopeModel | None:
        """The model of every rope of the arm when these motors are all of them (the rope
        layer itself); ``None`` for a motor subset: the other ropes are not commanded, so
        their tensions and the pose are not known beyond the joint limits."""
        ...

    def counts_from_angles(
        self, alpha: ArrayLike, theta: ArrayLike, tension_N: ArrayLike | None = None
    ) -> np.ndarray:
        """Setpoints (..., n) int64 of these motors for joint angles (..., n_joints) at
        ``tension_N`` (default: the pretension)."""
        ...

    def angles_from_counts(self, counts: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(alpha, theta, residual)`` the counts (..., n) show: joint angles (...,
        n_joints) and each rope's length misfit (a subset: the other motors held at 0
        counts, within their limits)."""
        ...

    def check_angles(self, alpha: ArrayLike, theta: ArrayLike) -> None:
        """Raise (an ``HrmError``, one line naming the step and joint) for NaN or angles
        outside the joint limits."""
        ...


@runtime_checkable
class JointPath(Protocol):
    """A straight line in joint space sampled at equal steps (``Actuation.joint_line``):
    float counts (K + 1, n) and the configuration of every sample (K + 1, n_joints)."""

    @property
    def counts(self) -> np.ndarray: ...

    @property
    def alpha(self) -> np.ndarray: ...

    @property
    def theta(self) -> np.ndarray: ...


@runtime_checkable
class ArmRopeModel(RopeModel, Protocol):
    """The rope model of the whole arm (every rope commanded): what a move does to the
    ropes' tensions, and lines in joint space to move along."""

    @property
    def limit_alpha(self) -> float:
        """|alpha| of every joint stays below this (rad)."""
        ...

    @property
    def limit_theta(self) -> float:
        """|theta| of every joint stays below this (rad)."""
        ...

    @property
    def command_tension_N(self) -> tuple[float, float]:
        """``(low, high)``: the band the modelled rope tensions of a move must keep."""
        ...

    def tensions_from_counts(
        self, counts: ArrayLike, alpha0: ArrayLike | None = None, theta0: ArrayLike | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(alpha, theta, tension_N)`` of the free arm at ``counts`` (..., n), the
        inverse warm-started from ``alpha0`` / ``theta0`` (n_joints,) where given."""
        ...

    def tensions_at(self, counts: ArrayLike, alpha: ArrayLike, theta: ArrayLike) -> np.ndarray:
        """Each rope's tension (..., n) with the arm held at ``alpha`` / ``theta``."""
        ...

    def rounded_outside(
        self, counts: ArrayLike, alpha: ArrayLike, theta: ArrayLike
    ) -> tuple[int, str] | None:
        """The first row of whole ``counts`` (rows, n), made from ``alpha`` / ``theta``
        within the joint limits, that rounding takes outside them, and why; or None."""
        ...

    def pose_of_counts(self, counts: ArrayLike, what: str) -> tuple[np.ndarray, np.ndarray]:
        """``(alpha, theta)`` the counts (n,) show, for a move to start from (``what``
        names the end in a refusal)."""
        ...

    def joint_line(
        self,
        from_counts: ArrayLike,
        to_counts: ArrayLike,
        *,
        from_pose: tuple[ArrayLike, ArrayLike] | None = None,
        to_pose: tuple[ArrayLike, ArrayLike] | None = None,
    ) -> JointPath:
        """The straight line in joint space from the configuration ``from_counts`` show
        (or ``from_pose``) to the one ``to_counts`` show (or ``to_pose``), first and last
        sample exactly the given counts."""
        ...
