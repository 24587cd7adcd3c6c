"""Small operator moves in joint space (the console's ``jog JOINT AXIS DEG`` and ``home``):
where the rope motors go, checked against the joint, rope and motor limits before
anything moves.

**A joint jog** turns one angle of one universal joint by a few degrees.  The joint
angles now come from the feedback (the drives' actual counts through the rope layer's
inverse, :meth:`Actuation.angles_from_counts`); the jog changes one of them; the motors
go by the rope layer's count difference between the two configurations, added to what the
drives hold (so the estimate's own error, and the ropes' tensions, are left as they are):
``target = held + counts(q') - counts(q)``.  Refused with one line (:class:`JogError`)
when the jog is larger than :data:`MAX_JOINT_JOG_DEG`, would leave a joint limit, or
would put a motor outside its drum travel.

**Home** is the calibrated zero configuration (every angle 0: the straight arm, whose
counts are the calibration's motor zeros) reached by a checked, time-parameterised
trajectory from the configuration now (:func:`home_setpoints`: the rope layer's one
plan-to-counts path with a two-step plan).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> held = np.zeros(act.n_motors, dtype=np.int64)
>>> jog = joint_jog(act, held, held, 5, "theta", 2.0)
>>> round(math.degrees(jog.theta_to[4]), 3), int(np.count_nonzero(jog.target_counts))
(2.0, 24)
>>> joint_jog(act, held, held, 5, "theta", 12.0)   # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.ropes.jog.JogError: jog 5 theta +12 deg: larger than a jog's 10 deg ...
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError
from hrm_ctrl.kinematics import end_point
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.setpoints import PlanSetpoints, plan_setpoints

# A jog is a small move (larger ones are plans): 10 deg of a joint moves its ropes by
# about 4700 counts (2.2 mm of rope; measured on the shipped description: 4692 counts for
# joint 1 alpha, 4623 for joints 6 and 12).
MAX_JOINT_JOG_DEG = 10.0
MAX_MOTOR_JOG_COUNTS = 5000  # the rope travel of a 10 deg joint jog (see above)
HOME_PATH_SAMPLES = 16  # the tip's path length home is measured on this many chords
MIN_HOME_TRAVEL_MM = 1.0  # the travel a home move is timed on, at least (tip hardly moving)


class JogError(RopeError):
    """A jog or home move refused: too large, outside a joint, rope or motor limit."""


class JogAxis(StrEnum):
    """The two angles of a universal joint (the plan file's names)."""

    ALPHA = "alpha"
    THETA = "theta"


@dataclass(frozen=True, eq=False)
class JointJog:
    """A checked joint jog: the joint (1-based), its axis, the angles before (from the
    feedback) and after (rad, (n_joints,) each), and the motors' target counts."""

    joint: int
    axis: JogAxis
    delta_rad: float
    alpha_from: np.ndarray
    theta_from: np.ndarray
    alpha_to: np.ndarray
    theta_to: np.ndarray
    target_counts: np.ndarray


def parse_axis(text: str) -> JogAxis:
    """``alpha`` / ``theta`` (also ``a`` / ``t``), else :class:`JogError`.

    >>> parse_axis("t"), parse_axis("ALPHA")
    (<JogAxis.THETA: 'theta'>, <JogAxis.ALPHA: 'alpha'>)
    """
    t = text.strip().lower()
    for axis in JogAxis:
        if t in (axis.value, axis.value[0]):
            return axis
    raise JogError(f"axis {text!r}: alpha or theta")


def _signed(value: float) -> str:
    return f"{value:+g}"


def joint_jog(
    act: Actuation,
    held_counts: Any,
    actual_counts: Any,
    joint: int,
    axis: JogAxis | str,
    delta_deg: float,
    *,
    max_deg: float = MAX_JOINT_JOG_DEG,
) -> JointJog:
    """The checked targets of turning ``joint`` (1-based) about ``axis`` by ``delta_deg``
    from the configuration the feedback ``actual_counts`` shows, the drives holding
    ``held_counts`` (module docstring).  Raises :class:`JogError` (one line naming the
    jog and the limit) for a bad joint, a jog larger than ``max_deg`` or one that leaves
    a joint limit or a motor's drum travel."""
    axis = parse_axis(axis) if isinstance(axis, str) else axis
    n_j = act.robot.n_joints
    what = f"jog {joint} {axis.value} {_signed(delta_deg)} deg"
    if not 1 <= joint <= n_j:
        raise JogError(f"{what}: joint must be 1..{n_j}")
    if not math.isfinite(delta_deg) or delta_deg == 0.0:
        raise JogError(f"{what}: the angle must be a finite, non-zero number of degrees")
    if abs(delta_deg) > max_deg:
        raise JogError(f"{what}: larger than a jog's {max_deg:g} deg (use a plan)")
    held = np.asarray(held_counts, dtype=np.int64)
    actual = np.asarray(actual_counts, dtype=np.int64)
    if held.shape != (act.n_motors,) or actual.shape != (act.n_motors,):
        raise JogError(f"{what}: expected {act.n_motors} motor counts")
    try:
        alpha, theta = act.pose_of_counts(actual, "where the arm is")
    except RopeError as exc:
        raise JogError(f"{what}: {exc}") from None
    a2, t2 = alpha.copy(), theta.copy()
    (a2 if axis is JogAxis.ALPHA else t2)[joint - 1] += math.radians(delta_deg)
    try:
        act.check_angles(a2, t2)
    except RopeError as exc:
        raise JogError(f"{what}: {exc}") from None
    c_from = act.counts_from_angles(alpha, theta, check=False)
    c_to = act.counts_from_angles(a2, t2, check=False)
    target = held + (c_to - c_from)
    try:
        act.check_counts(target)
    except RopeError as exc:
        raise JogError(f"{what}: {exc}") from None
    for arr in (alpha, theta, a2, t2, target):
        arr.setflags(write=False)
    return JointJog(joint, axis, math.radians(delta_deg), alpha, theta, a2, t2, target)


def check_motor_jog(act: Actuation, motor: str, counts: int, held_counts: Any) -> int:
    """The index of ``motor`` for a jog of ``counts`` from ``held_counts``, checked:
    a known motor, at most :data:`MAX_MOTOR_JOG_COUNTS`, within its drum travel
    (:class:`JogError` otherwise; the joint limits along the move are the jog source's
    to check).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> check_motor_jog(act, "j01r2", 800, np.zeros(36, dtype=np.int64))
    2
    >>> check_motor_jog(act, "j01r2", 8000, np.zeros(36, dtype=np.int64))
    ... # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hrm_ctrl.ropes.jog.JogError: jog j01r2 +8000 counts: larger than a jog's 5000 counts ...
    """
    what = f"jog {motor} {_signed(counts)} counts"
    if motor not in act.motor_ids:
        raise JogError(f"{what}: unknown rope motor (e.g. {act.motor_ids[0]})")
    if counts == 0:
        raise JogError(f"{what}: the move must be a non-zero number of counts")
    if abs(counts) > MAX_MOTOR_JOG_COUNTS:
        raise JogError(f"{what}: larger than a jog's {MAX_MOTOR_JOG_COUNTS} counts (use a plan)")
    i = act.motor_ids.index(motor)
    target = np.asarray(held_counts, dtype=np.int64).copy()
    target[i] += int(counts)
    try:
        act.check_counts(target)
    except RopeError as exc:
        raise JogError(f"{what}: {exc}") from None
    return i


def home_setpoints(
    act: Actuation,
    actual_counts: Any,
    *,
    period_s: float,
    speed_mm_per_s: float,
) -> PlanSetpoints:
    """The counts of every control period from the configuration ``actual_counts`` shows
    to the zero configuration (every joint angle 0), a straight line in joint space timed
    within every motor's speed and acceleration and the tip at most ``speed_mm_per_s``
    (:func:`~hrm_ctrl.ropes.setpoints.plan_setpoints`, which checks the joint and rope
    limits at every control period).  A home from where the arm already is raises
    :class:`JogError`."""
    actual = np.asarray(actual_counts, dtype=np.int64)
    try:
        alpha, theta = act.pose_of_counts(actual, "where the arm is")
    except RopeError as exc:
        raise JogError(f"home: {exc}") from None
    zero = np.zeros_like(alpha)
    if np.array_equal(act.counts_from_angles(zero, zero, check=False), actual):
        raise JogError("home: the arm is at its zero configuration already")
    s = np.linspace(1.0, 0.0, HOME_PATH_SAMPLES + 1)[:, None]
    tips = np.array([end_point(act.robot, alpha * k, theta * k) for k in s[:, 0]], dtype=np.float64)
    travel = max(float(np.linalg.norm(np.diff(tips, axis=0), axis=1).sum()), MIN_HOME_TRAVEL_MM)
    return plan_setpoints(
        act,
        [0.0, travel],
        np.vstack([alpha, zero]),
        np.vstack([theta, zero]),
        period_s=period_s,
        speed_mm_per_s=speed_mm_per_s,
        where="home",
    )
