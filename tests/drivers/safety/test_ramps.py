"""The quick stop's laws (drivers/safety/ramps.py) on random states: a controlled stop
reaches rest within the motors' speed, acceleration and jerk in whole counts, never
turning back; a fault stop brakes at the acceleration limit."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from drivers.safety.ramps import braked, eased


@settings(max_examples=200, deadline=None)
@given(
    v=st.integers(-4096, 4096),
    a=st.integers(-204, 204),
    V=st.integers(4096, 6000),
    A=st.integers(40, 204),
    J=st.integers(1, 40),
)
@example(v=4096, a=0, V=4096, A=204, J=40)  # full speed, the default motors
@example(v=1377, a=63, V=4096, A=204, J=40)  # still speeding up (a jog on the wire)
def test_a_controlled_stop_keeps_every_limit_to_rest(v: int, a: int, V: int, A: int, J: int):
    a = int(np.clip(a, -A, A))
    direction = int(np.sign(v)) if v else -int(np.sign(a))  # at rest: against its acceleration
    w, b = abs(v), a * direction
    n = max(int(np.ceil(-b / J)) - 1, 0) if b < 0 else 0
    m = max(int(np.ceil(b / J)) - 1, 0) if b > 0 else 0
    if w + n * b + J * n * (n + 1) // 2 < 0 or w + m * b - J * m * (m + 1) // 2 > V:
        return  # braking too hard to ease off before rest, or speeding up too hard to ease
        # off before the speed limit: not a history within the jerk limit
    if abs(v - a) > V:
        return
    pos, vel, acc = np.array([0]), np.array([v]), np.array([a])
    rows = [pos - vel - (vel - acc), pos - vel, pos]  # the three targets before the stop
    for _ in range(400):
        pos, vel, acc = eased(pos, vel, acc, np.array([V]), np.array([A]), np.array([J]))
        rows.append(pos)
        if vel[0] == 0 and acc[0] == 0:
            break
    else:
        raise AssertionError("never at rest")
    x = np.concatenate([*rows, pos, pos])
    d1 = np.diff(x)
    assert np.abs(d1).max() <= V
    assert np.abs(np.diff(x[1:], 2)).max() <= A
    assert np.abs(np.diff(x, 3)).max() <= J
    assert (d1[2:] * direction >= 0).all()  # never turns back


def test_a_fault_stop_brakes_at_the_acceleration_limit() -> None:
    pos, vel = np.array([0, 0]), np.array([4096, -30])
    seen = []
    for _ in range(25):
        pos, vel = braked(pos, vel, np.array([204, 204]))
        seen.append(vel.copy())
    speeds = np.array(seen)
    assert speeds[0].tolist() == [3892, 0] and (speeds[20:] == 0).all()
