"""The targets of a quick stop, one control period at a time: each motor from its speed
(and acceleration) to rest, in whole counts.

Two laws, chosen by what stopped the box (:func:`is_controlled_stop`):

- a *fault stop* (a drive, a bus, a limit, a rope: anything but the operator) slows
  every motor by its acceleration limit at once (:func:`braked`): the shortest stop
  the motors' acceleration allows, whatever the jerk;
- a *controlled stop* (the operator, a signal) also keeps every motor's jerk
  (:func:`eased`): the deceleration builds up at the jerk limit, and eases off so that
  speed and acceleration reach zero together; at most ``A/J`` (0.05 s with the default
  motors) longer than a fault stop.

Both work on the integers that are sent (counts per period, per period squared and
cubed), with NumPy over the motors and no loop.  A fault stop is the one motion the box
sends that does not keep the motors' jerk limit, by design (the shortest stop first).

:func:`jerk_window` is the same law for a source that follows a path (a pause of a
plan's playback): the setpoints each motor may take next so that its third difference
keeps the jerk limit, its second the acceleration limit, and its speed can still be
eased off before the speed limit (a history from which :func:`eased` stops within the
jerk limit too).

>>> pos, vel, acc = np.array([0]), np.array([40]), np.array([0])
>>> seq = []
>>> for _ in range(12):
...     pos, vel, acc = eased(pos, vel, acc, np.array([4096]), np.array([20]), np.array([5]))
...     seq.append(int(pos[0]))
>>> seq[-3:] == [seq[-1]] * 3, int(np.abs(np.diff([0, 0, 0] + seq, 3)).max()) <= 5 + 40
(True, True)
"""

from __future__ import annotations

import numpy as np

from drivers.safety.causes import StopCause, StopKind

#: the stop causes after which the stop keeps the motors' jerk (nothing is wrong with a
#: drive, a bus, a limit or a rope)
CONTROLLED_STOPS = frozenset({StopKind.OPERATOR, StopKind.SIGNAL})


def is_controlled_stop(causes: list[StopCause]) -> bool:
    """Every cause an operator's or a signal's (then the stop keeps the jerk limit).

    >>> is_controlled_stop([StopCause(StopKind.OPERATOR, "stop requested")])
    True
    >>> is_controlled_stop([StopCause(StopKind.OPERATOR, "x"), StopCause(StopKind.EMCY, "y")])
    False
    """
    return bool(causes) and all(c.kind in CONTROLLED_STOPS for c in causes)


def braked(pos: np.ndarray, vel: np.ndarray, decel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The next position and speed (counts, counts per period) of a fault stop: each
    motor's speed less its deceleration ``decel`` (counts per period squared), at once.

    >>> braked(np.array([10, 0]), np.array([7, -5]), np.array([3, 3]))
    (array([14, -2]), array([ 4, -2]))
    """
    vel = np.sign(vel) * np.maximum(np.abs(vel) - decel, 0)
    return pos + vel, vel


def _lost_easing_off(b: np.ndarray, J: np.ndarray) -> np.ndarray:
    """The speed (counts per period) a motor still loses while its deceleration ``-b``
    (``b <= 0``) is brought back to 0 at ``J`` a period: ``b + J, b + 2J, ...`` while
    negative (``n b + J n (n + 1) / 2``, ``n = ceil(-b / J) - 1``)."""
    n = np.maximum(np.ceil(-b / J) - 1, 0)
    return n * b + J * n * (n + 1) / 2


def jerk_window(
    prev: np.ndarray,
    before: np.ndarray,
    before2: np.ndarray,
    V: np.ndarray,
    A: np.ndarray,
    J: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest next setpoint of each motor (whole counts) after ``before2``,
    ``before``, ``prev``: its acceleration (second difference) within ``J`` of the last
    one and within ``A``, its speed within ``V`` and still able to ease its acceleration
    off at ``J`` a period before it passes ``V`` either way (``V``, ``A``, ``J`` in counts
    per period, squared, cubed).  Never empty after a history that keeps these (the
    acceleration eased off at ``J`` is always in it).

    >>> z = np.array([0])
    >>> jerk_window(z, z, z, np.array([100]), np.array([20]), np.array([5]))
    (array([-5]), array([5]))
    >>> jerk_window(np.array([95]), np.array([0]), np.array([-90]), np.array([100]),
    ...             np.array([20]), np.array([5]))   # at 95 a period, speeding up by 5
    (array([190]), array([195]))
    """
    vel = prev - before
    acc = vel - (before - before2)
    lo = np.maximum(np.maximum(acc - J, -A), -_eased_within(V + vel, J))
    hi = np.minimum(np.minimum(acc + J, A), _eased_within(V - vel, J))
    stuck = lo > hi  # not a history within the limits: the acceleration eased off
    eased_off = np.clip(0, acc - J, acc + J)
    base = 2 * prev - before
    return base + np.where(stuck, eased_off, lo), base + np.where(stuck, eased_off, hi)


def _eased_within(room: np.ndarray, J: np.ndarray) -> np.ndarray:
    """The largest acceleration ``a`` (whole counts per period squared) after which the
    speed gains at most ``room`` more, the acceleration then eased off at ``J`` a period
    (``a + (a - J) + (a - 2J) + ...`` while positive): with ``k`` whole steps of ``J``
    below it (the largest ``k`` with ``J k (k + 1) / 2 <= room``), ``a <= (room +
    J k (k + 1) / 2) / (k + 1)``.

    >>> _eased_within(np.array([5, 9, 10, 14, 15, -3]), np.array([5, 5, 5, 5, 5, 5])).tolist()
    [5, 7, 7, 9, 10, -3]
    """
    room = np.asarray(room, dtype=np.int64)
    J = np.asarray(J, dtype=np.int64)
    r = np.maximum(room, 0)
    k = np.floor((np.sqrt(1.0 + 8.0 * r / J) - 1.0) / 2.0).astype(np.int64)
    k = np.where(J * k * (k + 1) // 2 > r, k - 1, k)  # float rounding, either way
    k = np.where(J * (k + 1) * (k + 2) // 2 <= r, k + 1, k)
    k = np.maximum(k, 0)
    return np.where(room < 0, room, (r + J * k * (k + 1) // 2) // (k + 1))


def eased(
    pos: np.ndarray,
    vel: np.ndarray,
    acc: np.ndarray,
    V: np.ndarray,
    A: np.ndarray,
    J: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The next position, speed and acceleration (whole counts per period, squared) of a
    controlled stop: each motor's next acceleration within ``J`` of its last and ``A`` of
    zero, its speed within ``V``, the strongest braking from which the deceleration can
    still be eased off at ``J`` before the speed passes zero (then it lands at rest with
    no acceleration).  A motor that cannot (it already brakes harder than that: not a
    jerk-limited history) eases off at ``J``, and never turns back: its speed stops at
    zero.

    >>> eased(np.array([0]), np.array([10]), np.array([0]), np.array([50]), np.array([4]),
    ...       np.array([2]))
    (array([8]), array([8]), array([-2]))
    """
    direction = np.where(vel != 0, np.sign(vel), -np.sign(acc))
    w = direction * vel  # speed along the motion (>= 0)
    b = direction * acc  # acceleration along it
    lo = np.maximum(b - J, -A)
    hi = np.minimum(b + J, V - w)
    width = int(np.max(hi - lo, initial=0)) + 1
    cand = lo[None, :] + np.arange(max(width, 1))[:, None]  # (candidates, motors)
    valid = cand <= hi[None, :]
    nxt = w[None, :] + cand
    ok = valid & (nxt >= 0) & (nxt + _lost_easing_off(np.minimum(cand, 0), J[None, :]) >= 0)
    first = np.argmax(ok, axis=0)
    chosen = np.where(ok.any(axis=0), lo + first, hi)  # none: ease off as fast as allowed
    chosen = np.maximum(chosen, -w)  # never past rest
    b_new = np.where((w == 0) & (b == 0), 0, chosen)
    acc_new = direction * b_new
    vel_new = vel + acc_new
    return pos + vel_new, vel_new, acc_new


__all__ = ["CONTROLLED_STOPS", "braked", "eased", "is_controlled_stop", "jerk_window"]
