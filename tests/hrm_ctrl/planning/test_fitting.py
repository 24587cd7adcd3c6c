"""Sec. 3.3 (fitting) and Sec. 3.4 (joint angles)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning import fitting
from hrm_ctrl.planning.fitting import (
    fit_joint_centres,
    fit_joint_centres_batch,
    fit_joint_centres_on_segments,
    sphere_segment_intersection,
)
from hrm_ctrl.planning.joint_angles import joint_angles_from_centres

MODEL = default_robot()


def helix(radius: float, pitch: float, length: float, n: int = 2000) -> np.ndarray:
    """A helix starting at the origin along +x (arc length ``length``)."""
    c = np.hypot(2 * np.pi * radius, pitch)
    phi = np.linspace(0.0, length / c * 2 * np.pi, n)
    return np.stack(
        (phi / (2 * np.pi) * pitch, radius * np.sin(phi), radius * (1 - np.cos(phi))), axis=1
    )


@settings(max_examples=25, deadline=None)
@given(st.floats(400.0, 3000.0), st.floats(200.0, 4000.0))
def test_fitted_joints_have_link_lengths_and_lie_on_the_curve(radius: float, pitch: float) -> None:
    curve = helix(radius, pitch, MODEL.length)
    O, seg = fit_joint_centres_on_segments(curve, MODEL.links)
    np.testing.assert_allclose(np.linalg.norm(np.diff(O, axis=0), axis=1), MODEL.links, rtol=1e-9)
    np.testing.assert_allclose(O[0], curve[0])
    np.testing.assert_allclose(O[-1], curve[-1])
    for i in range(2, 13):  # O_3 .. O_13 on their segments
        k = seg[i]
        A, B = curve[k], curve[k + 1]
        t = np.dot(O[i] - A, B - A) / np.dot(B - A, B - A)
        assert -1e-9 <= t <= 1 + 1e-9
        np.testing.assert_allclose(O[i], A + t * (B - A), atol=1e-7)
    # the batch fit (all steps at once) gives the same joints as the bisection
    Ob, segb = fit_joint_centres_batch(curve[None], MODEL.links, O[1][None])
    np.testing.assert_allclose(Ob[0], O, atol=1e-9)
    assert (segb[0, 2:] == seg[2:]).all()


@settings(max_examples=25, deadline=None)
@given(st.floats(400.0, 3000.0), st.floats(200.0, 4000.0))
def test_fk_of_fitted_angles_reproduces_the_joint_centres(radius: float, pitch: float) -> None:
    curve = helix(radius, pitch, MODEL.length)
    O = fit_joint_centres(curve, MODEL.links)
    alpha, theta = joint_angles_from_centres(MODEL, O)
    np.testing.assert_allclose(joint_centres(MODEL, alpha, theta), O, atol=1e-8)


@settings(max_examples=50)
@given(st.lists(st.floats(-1.0, 1.0), min_size=24, max_size=24))
def test_closed_vector_inverts_fk(angles: list[float]) -> None:
    a, t = np.array(angles[:12]), np.array(angles[12:])
    a2, t2 = joint_angles_from_centres(MODEL, joint_centres(MODEL, a, t))
    np.testing.assert_allclose(a2, a, atol=1e-9)
    np.testing.assert_allclose(t2, t, atol=1e-9)


def test_sphere_segment_intersection_is_exact() -> None:
    C = np.array([1.0, 2.0, 3.0])
    P, Q = np.array([11.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0])
    t = sphere_segment_intersection(C, P, Q, 4.0)
    assert np.linalg.norm(P + t * (Q - P) - C) == pytest.approx(4.0, abs=1e-12)


def test_too_short_a_curve_cannot_be_fitted() -> None:
    curve = np.array([[0.0, 0, 0], [1000.0, 0, 0]])
    with pytest.raises(PlanningError, match="too short"):
        fit_joint_centres(curve, MODEL.links)


def test_joint_two_sits_on_its_circle_nearest_the_curve() -> None:
    curve = helix(600.0, 800.0, MODEL.length)
    O = fit_joint_centres(curve, MODEL.links)
    assert np.linalg.norm(O[1] - O[0]) == pytest.approx(MODEL.links[0])
    assert np.linalg.norm(O[2] - O[1]) == pytest.approx(MODEL.links[1])


def fit_by_full_scan(curve: np.ndarray, links: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joints n..3 as Sec. 3.3 states them, every curve point looked at: the last point
    (towards the tip) at least l_i from the joint after it, the curve's first point at least
    that far, and the sphere's crossing of the segment after it."""
    n = len(links)
    O = np.empty((n + 1, 3))
    seg = np.full(n + 1, len(curve) - 2)
    O[n], O[0] = curve[-1], curve[0]
    P, j = curve[-1], len(curve) - 2
    for i in range(n - 1, 1, -1):
        r = float(links[i])
        d = np.linalg.norm(curve[: j + 1] - P, axis=1)
        far = np.flatnonzero(d >= r)
        if d[0] < r or not len(far):
            raise PlanningError("too short")
        k = int(far[-1])
        nxt = curve[k + 1] if k + 1 <= j else P
        P = curve[k] + sphere_segment_intersection(P, curve[k], nxt, r) * (nxt - curve[k])
        O[i], seg[i], j = P, k, k
    return O, seg


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_fit_walked_back_by_arc_length_is_the_full_scan(seed: int) -> None:
    """Random curves of uneven spacing, some folding back: joints 3..13 and their segments
    as looking at every point finds them (or the same refusal); joint 2, on its circle,
    is left out (a curve too long for it is refused after joints 3..13 are placed)."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(30, 3000))
    turn = rng.uniform(0.0, 0.5) * 20 / np.sqrt(k)
    h = np.cumsum(rng.normal(size=(k, 3)) * turn, axis=0) + np.array([3.0, 0, 0])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    ds = rng.uniform(0.1, 1.0, size=k)
    ds *= rng.uniform(1900.0, 2150.0) / ds.sum()
    curve = np.vstack((np.zeros(3), np.cumsum(h * ds[:, None], axis=0)))
    with pytest.MonkeyPatch.context() as mp:  # joint 2 anywhere: joints 3..13 compared
        mp.setattr(fitting, "circle_point_nearest", lambda O1, O3, l1, l2, ref: O1)
        try:
            want = fit_by_full_scan(curve, MODEL.links)
        except PlanningError:
            with pytest.raises(PlanningError, match="too short"):
                fitting.fit_joint_centres_on_segments(curve, MODEL.links)
            return
        O, seg = fitting.fit_joint_centres_on_segments(curve, MODEL.links)
    np.testing.assert_allclose(O[2:], want[0][2:], atol=1e-9)
    assert (seg[2:] == want[1][2:]).all()
