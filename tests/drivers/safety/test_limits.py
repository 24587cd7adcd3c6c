"""The control loop's per-setpoint check (drivers.safety.limits.CycleLimits): its cheap
test passes a setpoint only when the full check (the rope layer's ``check_counts``, then
the acceleration) does, and the check refuses exactly what the full check refuses, with
the same error, for the real rope layer and for test doubles."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from drivers.safety.limits import CycleLimits, SetpointError, accel_limits, acceleration_text
from drivers.safety.subset import ActuationSubset
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation

T = 0.01
ACT = load_actuation(default_robot())
N = ACT.n_motors
CYC = CycleLimits(ACT, T)
LO = np.asarray(ACT.counts_min, dtype=np.int64)
HI = np.asarray(ACT.counts_max, dtype=np.int64)
V = np.floor(ACT.max_rate_counts_per_s * T + 1e-6).astype(np.int64)  # counts a period
A = np.floor(ACT.max_accel_counts_per_s2 * T**2).astype(np.int64)  # counts a period^2
I64 = np.iinfo(np.int64)

Case = tuple[np.ndarray, np.ndarray, np.ndarray]
Outcome = tuple[type, str] | None


def old_check(limits: Any, period_s: float, target: Any, previous: Any, before: Any) -> None:
    """The supervisor's check before CycleLimits (Supervisor._checked), verbatim."""
    accel = accel_limits(limits, fallback=False)
    limits.check_counts(target, previous=previous, dt_s=period_s)
    if accel is not None:
        t = np.asarray(target, dtype=np.int64)
        acc = np.abs(t - 2 * previous + before) / period_s**2
        hard = acc > accel
        if hard.any():
            i = int(np.flatnonzero(hard)[0])
            raise SetpointError(acceleration_text(limits, i, float(acc[i])))


def outcome(check: Any, *args: Any) -> Outcome:
    try:
        check(*args)
    except Exception as exc:
        return type(exc), str(exc)
    return None


def assert_same(cyc: CycleLimits, target: Any, previous: Any, before: Any) -> Outcome:
    """The new check decides as the old one; its fast test passes only what the old one
    passes.  Returns the old check's outcome."""
    expected = outcome(old_check, cyc.limits, cyc.period_s, target, previous, before)
    assert outcome(cyc.check, target, previous, before) == expected
    if cyc.passes(target, previous, before):
        assert expected is None
    return expected


def cycle(t: Any, v: Any, a: Any) -> Case:
    """Target ``t``, change ``v = t - previous`` and second difference
    ``a = t - 2 previous + before``, per motor."""
    t = np.array(t, dtype=np.int64)
    p = t - np.array(v, dtype=np.int64)
    b = np.array(a, dtype=np.int64) - t + 2 * p
    return t, p, b


# a typical in-limits setpoint of all 36 motors: mid-travel, a moderate speed, accelerating
TYPICAL_T = np.linspace(-300_000, 300_000, N).astype(np.int64)
TYPICAL_V = np.linspace(-2_000, 2_000, N).astype(np.int64)
TYPICAL_A = np.linspace(-100, 100, N).astype(np.int64)


def pinned(i: int = 5, t: int | None = None, v: int | None = None, a: int | None = None) -> Case:
    """The typical setpoint with motor ``i``'s target, change or second difference set."""
    tt, vv, aa = TYPICAL_T.copy(), TYPICAL_V.copy(), TYPICAL_A.copy()
    if t is not None:
        tt[i] = t
    if v is not None:
        vv[i] = v
    if a is not None:
        aa[i] = a
    return cycle(tt, vv, aa)


@st.composite
def cycles(draw: st.DrawFn) -> Case:
    """Setpoints within the limits, some motors set at or just across one of them, now
    and then one raw int64 value anywhere (even where the differences wrap around)."""
    t = draw(arrays(np.int64, N, elements=st.integers(-420_000, 420_000)))
    v = draw(arrays(np.int64, N, elements=st.integers(-4_000, 4_000)))
    a = draw(arrays(np.int64, N, elements=st.integers(-200, 200)))
    tweaks = st.tuples(
        st.integers(0, N - 1),
        st.sampled_from(["position", "rate", "accel"]),
        st.integers(-3, 3),
        st.booleans(),
    )
    for i, kind, d, low in draw(st.lists(tweaks, max_size=3)):
        if kind == "position":
            t[i] = LO[i] - d if low else HI[i] + d
        elif kind == "rate":
            v[i] = -(V[i] + d) if low else V[i] + d
        else:
            a[i] = -(A[i] + d) if low else A[i] + d
    target, previous, before = cycle(t, v, a)
    for i, which, value in draw(
        st.lists(
            st.tuples(st.integers(0, N - 1), st.integers(0, 2), st.integers(I64.min, I64.max)),
            max_size=1,
        )
    ):
        (target, previous, before)[which][i] = value
    return target, previous, before


@settings(max_examples=200, derandomize=True, deadline=None)
@given(cycles())
@example(pinned())  # typical
@example(pinned(v=int(V[5])))  # exactly at the rate limit
@example(pinned(v=int(V[5]) + 1))  # one count over
@example(pinned(v=-int(V[5]) - 1))
@example(pinned(t=int(HI[5])))  # exactly at a position limit
@example(pinned(t=int(HI[5]) + 1))  # one over
@example(pinned(t=int(LO[5])))
@example(pinned(t=int(LO[5]) - 1))
@example(pinned(a=int(A[5])))  # acceleration at the (whole-count) limit
@example(pinned(a=int(A[5]) + 1))  # over
@example(pinned(a=-int(A[5]) - 1))
@example(pinned(t=int(HI[5]) + 1, v=int(V[5]) + 1, a=int(A[5]) + 1))  # position first
@example(pinned(v=int(V[5]) + 1, a=int(A[5]) + 1))  # then the speed
@example(cycle(np.zeros(N), np.zeros(N), np.zeros(N)))
@example((np.zeros(N, np.int64), np.full(N, I64.min), np.zeros(N, np.int64)))  # wraps
@example((np.zeros(N, np.int64), np.full(N, 2**62), np.zeros(N, np.int64)))
def test_the_check_decides_as_the_old_check_on_the_rope_layer(case: Case) -> None:
    assert_same(CYC, *case)


def test_a_typical_setpoint_takes_the_fast_test_and_the_limits_go_to_the_slow_path() -> None:
    assert CYC.fast and CYC.second is not None
    assert (CYC.lo == LO).all() and (CYC.hi == HI).all()
    assert (CYC.step == V - 1).all()  # 4096 counts a period exactly: left to the slow path
    assert (CYC.second == A).all()  # 204.8 counts a period^2: 204 passes
    assert CYC.passes(*pinned())
    assert not CYC.passes(*pinned(v=int(V[5])))
    assert assert_same(CYC, *pinned(v=int(V[5]))) is None
    assert CYC.passes(*pinned(t=int(HI[5]), v=0))


@pytest.mark.parametrize(
    "target",
    [TYPICAL_T.astype(np.float64), TYPICAL_T.tolist(), TYPICAL_T.astype(np.int32)],
    ids=["float64", "list", "int32"],
)
def test_other_setpoint_types_take_the_slow_path(target: Any) -> None:
    _t, p, b = pinned()
    assert not CYC.passes(target, p, b)
    assert_same(CYC, target, p, b)
    assert assert_same(CYC, np.asarray(target) + 10**6, p, b) is not None


def test_a_motor_subset_checks_as_the_rope_layer() -> None:
    sub = ActuationSubset(ACT, ("j01r0", "j07r2"))
    cyc = CycleLimits(sub, T)
    assert cyc.fast and cyc.second is not None
    p, b = np.array([1000, -1000]), np.array([900, -900])
    assert cyc.passes(np.array([1100, -1100]), p, b)
    for target in ([1100, -1100], [1000 + 4097, -1000], [1000, int(sub.counts_min[1]) - 1]):
        assert_same(cyc, np.array(target), p, b)
    assert assert_same(cyc, np.array([1100 + 205, -1100]), p, b) is not None


class Limits:
    """A double without acceleration limits: 100 counts either way, 10 counts a period."""

    motor_ids = ("m0", "m1")
    counts_min = np.array([-100, -100])
    counts_max = np.array([100, 100])
    max_rate_counts_per_s = np.array([1000.0, 1000.0])
    max_accel_counts_per_s2: np.ndarray | None = None
    max_jerk_counts_per_s3: np.ndarray | None = None

    def motor_label(self, i: int) -> str:
        return self.motor_ids[i]

    def check_counts(self, counts: Any, previous: Any = None, dt_s: Any = None) -> None:
        c = np.asarray(counts)
        if np.any(c < self.counts_min) or np.any(c > self.counts_max):
            raise SetpointError("outside [-100, 100]")
        if dt_s is not None and np.any(np.abs(c - previous) / dt_s > self.max_rate_counts_per_s):
            raise SetpointError("too fast")


class AccelLimits(Limits):
    max_accel_counts_per_s2 = np.array([2e5, 2e5])  # 20 counts a period^2


class NoRate:
    """A double without rate limits (not numbers: no speed is refused)."""

    motor_ids = ("m0", "m1")
    counts_min = np.array([-100, -100])
    counts_max = np.array([100, 100])
    max_rate_counts_per_s = np.array([np.nan, np.nan])
    max_accel_counts_per_s2 = None
    max_jerk_counts_per_s3 = None

    def motor_label(self, i: int) -> str:
        return self.motor_ids[i]

    def check_counts(self, counts: Any, previous: Any = None, dt_s: Any = None) -> None:
        if np.any(np.abs(np.asarray(counts)) > 100):
            raise SetpointError("outside [-100, 100]")


@pytest.mark.parametrize(
    ("target", "previous", "before", "refused"),
    [
        ([0, 0], [0, 0], [0, 0], None),
        ([9, -9], [0, 0], [9, -9], None),  # any second difference: none is checked
        ([10, 0], [0, 0], [0, 0], None),  # exactly at the rate limit
        ([11, 0], [0, 0], [0, 0], "too fast"),
        ([100, 0], [95, 0], [0, 0], None),  # exactly at a position limit
        ([101, 0], [95, 0], [0, 0], "outside [-100, 100]"),
        ([-101, 0], [-95, 0], [0, 0], "outside [-100, 100]"),
    ],
)
def test_a_double_without_acceleration_limits(
    target: list[int], previous: list[int], before: list[int], refused: str | None
) -> None:
    cyc = CycleLimits(Limits(), T)
    assert cyc.fast and cyc.accel is None and cyc.second is None
    t, p, b = (np.array(x, dtype=np.int64) for x in (target, previous, before))
    got = assert_same(cyc, t, p, b)
    assert got == (None if refused is None else (SetpointError, refused))
    if abs(target[0] - previous[0]) < 10 and abs(target[0]) <= 100:
        assert cyc.passes(t, p, b)


@pytest.mark.parametrize(("second", "refused"), [(19, False), (20, False), (21, True)])
def test_a_double_with_acceleration_limits_at_and_over_them(second: int, refused: bool) -> None:
    cyc = CycleLimits(AccelLimits(), T)
    assert cyc.fast and cyc.second is not None and cyc.second.tolist() == [19, 19]
    t, p, b = cycle([50, 0], [5, 0], [second, 0])
    got = assert_same(cyc, t, p, b)
    assert (got is not None) == refused
    if refused:
        assert got == (SetpointError, acceleration_text(AccelLimits(), 0, second / T**2))
    assert cyc.passes(t, p, b) == (second < 20)


def test_a_double_without_rate_limits_takes_the_slow_path_only() -> None:
    cyc = CycleLimits(NoRate(), T)
    assert not cyc.fast
    rest = np.zeros(2, dtype=np.int64)
    assert not cyc.passes(rest, rest, rest)
    assert assert_same(cyc, np.array([50, 0]), rest, rest) is None
    assert assert_same(cyc, np.array([101, 0]), rest, rest) == (
        SetpointError,
        "outside [-100, 100]",
    )


@pytest.mark.parametrize("period_s", [0.0, -0.01, float("nan")])
def test_a_period_that_is_no_positive_number_takes_the_slow_path_only(period_s: float) -> None:
    cyc = CycleLimits(ACT, period_s)
    assert not cyc.fast
    assert outcome(cyc.check, *pinned()) == outcome(old_check, ACT, period_s, *pinned())
