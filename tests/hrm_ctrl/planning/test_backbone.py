"""The modal backbone, Eqs. (5)-(9), and its damped solver."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import UnreachableError
from hrm_ctrl.planning.backbone import (
    Boundary,
    ModalBasis,
    backbone_points,
    end_point_and_jacobian,
    solve_modal_cold,
    solve_modal_factors,
)

BASIS = ModalBasis(200)
small = st.floats(-1.0, 1.0)
ang = st.floats(-1.5, 1.5)


@settings(max_examples=40)
@given(st.tuples(small, small, small), st.tuples(ang, ang, ang, ang), st.floats(100, 2500))
def test_jacobian_matches_finite_differences(a, b, l) -> None:
    a = np.array(a)
    bd = Boundary(*b)
    _X, J = end_point_and_jacobian(BASIS, np.zeros(3), l, a, bd)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        Xp, _ = end_point_and_jacobian(BASIS, np.zeros(3), l, a + e, bd)
        Xm, _ = end_point_and_jacobian(BASIS, np.zeros(3), l, a - e, bd)
        np.testing.assert_allclose((Xp - Xm) / 2e-6, J[:, k], atol=1e-5 * l)


@settings(max_examples=30)
@given(st.tuples(small, small, small), st.tuples(ang, ang, ang, ang), st.floats(100, 2500))
def test_curve_has_length_l_and_the_boundary_tangents(a, b, l) -> None:
    bd = Boundary(*b)
    P = backbone_points(BASIS, np.array([1.0, 2.0, 3.0]), l, np.array(a), bd)
    seg = np.diff(P, axis=0)
    assert np.linalg.norm(seg, axis=1).sum() == pytest.approx(l, rel=1e-3)
    X, _ = end_point_and_jacobian(BASIS, np.array([1.0, 2.0, 3.0]), l, np.array(a), bd)
    np.testing.assert_allclose(P[-1], X, atol=1e-9)  # Eq. (5) at s = 1
    for (K, T), d in (((bd.b1k, bd.b1t), seg[0]), ((bd.b2k, bd.b2t), seg[-1])):
        u = np.array([math.sin(K) * math.cos(T), math.cos(K) * math.cos(T), math.sin(T)])
        assert float(u @ d / np.linalg.norm(d)) > 0.99


def test_cold_start_reaches_the_bent_pipe_entry_at_full_length() -> None:
    """NOTES.md: the plain Newton step diverges from a = 0 here; the damped one does not."""
    A = np.array([1200.0, 100.0, 300.0])
    b = Boundary(math.pi / 2, 0.0, math.pi / 2, 0.0)
    sol = solve_modal_factors(BASIS, np.zeros(3), A, 2007.0, b)
    assert sol.residual < 1e-9
    P = backbone_points(BASIS, np.zeros(3), 2007.0, sol.a, b)
    np.testing.assert_allclose(P[-1], A, atol=1e-8)


def plain_newton(X_D, l, b, iters=50):
    """Eq. (8) with omega = 1, for comparison."""
    a = np.zeros(3)
    for _ in range(iters):
        X, J = end_point_and_jacobian(BASIS, np.zeros(3), l, a, b)
        a = a + np.linalg.solve(J, X_D - X)
    X, _ = end_point_and_jacobian(BASIS, np.zeros(3), l, a, b)
    return float(np.linalg.norm(X - X_D))


@pytest.mark.parametrize("l", [2007.0, 1500.0, 1333.0])
def test_plain_newton_fails_where_the_damped_solver_converges(l: float) -> None:
    """NOTES.md: from a = 0 the printed step (Eq. 8) does not converge here."""
    A = np.array([1200.0, 100.0, 300.0])
    b = Boundary(math.pi / 2, 0.0, math.pi / 2, 0.0)
    with np.errstate(all="ignore"):
        assert not plain_newton(A, l, b) < 1.0
    assert solve_modal_factors(BASIS, np.zeros(3), A, l, b).residual < 1e-9


def test_cold_start_with_turned_end_angles_needs_continuation() -> None:
    A = np.array([1200.0, 100.0, 300.0])
    b = Boundary(math.pi / 2, 0.0, math.atan2(270.0, 90.0), 0.0)  # cabins: along A->B
    with pytest.raises(UnreachableError):
        solve_modal_factors(BASIS, np.zeros(3), A, 2007.0, b)
    sol = solve_modal_cold(BASIS, np.zeros(3), A, 2007.0, b)
    assert sol.residual < 1e-9


def test_too_short_a_curve_is_unreachable_and_says_why() -> None:
    b = Boundary(math.pi / 2, 0.0, math.pi / 2, 0.0)
    with pytest.raises(UnreachableError, match=r"only 1000\.000 mm long"):
        solve_modal_factors(BASIS, np.zeros(3), np.array([1200.0, 100.0, 300.0]), 1000.0, b)
    with pytest.raises(UnreachableError, match="cannot reach"):
        solve_modal_cold(BASIS, np.zeros(3), np.array([1200.0, 100.0, 300.0]), 1250.0, b)
