"""The modal backbone curve, Eqs. (5)-(9).

A curve of length ``l`` from ``X0`` with unit tangent (Eq. 6)
``u = (sin K cos T, cos K cos T, sin T)`` whose angles follow the mode shapes of Eq. (7):

    K(s) = a1 sin(2 pi s) + a2 (1 - cos(2 pi s)) + b1k (1 - sin(pi s / 2)) + b2k sin(pi s / 2)
    T(s) = a3 (1 - cos(2 pi s))                  + b1t (1 - sin(pi s / 2)) + b2t sin(pi s / 2)

so ``(K, T) = (b1k, b1t)`` at ``s = 0`` and ``(b2k, b2t)`` at ``s = 1``.  Eq. (5)
integrates ``l u`` by the trapezoidal rule over ``Q`` equal parts; Eq. (9) is the
3x3 Jacobian of the end point ``X(1)`` with respect to ``a = (a1, a2, a3)``,
computed here analytically on the same quadrature, so it is the exact derivative
of the discretised end point.

The printed Newton step (Eq. 8) diverges from a cold start when K stays near
pi/2 (``NOTES.md``); :func:`solve_modal_factors` damps it (Levenberg-Marquardt),
warm-starts from the previous path step, and raises :class:`UnreachableError`
saying why when the target cannot be reached.

>>> basis = ModalBasis(200)
>>> b = Boundary(np.pi / 2, 0.0, np.pi / 2, 0.0)         # start and end along +x0
>>> sol = solve_modal_factors(basis, np.zeros(3), np.array([900.0, 100.0, 200.0]), 1000.0, b)
>>> float(np.linalg.norm(sol.end - [900.0, 100.0, 200.0])) < 1e-8
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.errors import UnreachableError

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class Boundary:
    """Start and end angles of the curve: (b1k, b1t) at s = 0, (b2k, b2t) at s = 1."""

    b1k: float
    b1t: float
    b2k: float
    b2t: float


class ModalBasis:
    """Mode shapes and trapezoid weights sampled at ``S = [0, 1/Q, ..., 1]``.

    Immutable after construction; one instance serves every solve with that Q.

    >>> B = ModalBasis(4)
    >>> B.S.tolist()
    [0.0, 0.25, 0.5, 0.75, 1.0]
    >>> float(B.w.sum())
    1.0
    """

    def __init__(self, Q: int) -> None:
        if Q < 2:
            raise ValueError("Q must be >= 2")
        self.Q = int(Q)
        S = np.linspace(0.0, 1.0, self.Q + 1)
        self.S = S
        self.sin2 = np.sin(TWO_PI * S)  # dK/da1
        self.cos2 = 1.0 - np.cos(TWO_PI * S)  # dK/da2 and dT/da3
        self.rise = np.sin(0.5 * math.pi * S)
        self.fall = 1.0 - self.rise
        w = np.full(self.Q + 1, 1.0 / self.Q)
        w[0] = w[-1] = 0.5 / self.Q
        self.w = w
        self.W = np.stack((w, w * self.sin2, w * self.cos2), axis=1)  # (Q+1, 3)
        self.SC = np.stack((self.sin2, self.cos2))  # (2, Q+1): K's mode shapes
        self.wcos2 = w * self.cos2
        for arr in (S, self.sin2, self.cos2, self.rise, self.fall, w, self.W, self.wcos2, self.SC):
            arr.setflags(write=False)

    def mode_angles(self, a: np.ndarray, b: Boundary) -> tuple[np.ndarray, np.ndarray]:
        """Eq. (7): K(S) and T(S) at the sample points; ``a`` of shape (..., 3)
        gives arrays of shape (..., Q + 1)."""
        a = np.asarray(a, dtype=float)
        a1, a2, a3 = a[..., 0, None], a[..., 1, None], a[..., 2, None]
        K = a1 * self.sin2 + a2 * self.cos2 + (b.b1k * self.fall + b.b2k * self.rise)
        T = a3 * self.cos2 + (b.b1t * self.fall + b.b2t * self.rise)
        return K, T


def tangent(K: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Eq. (6): unit tangent, shape (..., 3).

    >>> tangent(np.array(np.pi / 2), np.array(0.0)).round(12).tolist()
    [1.0, 0.0, 0.0]
    """
    cT = np.cos(T)
    return np.stack((np.sin(K) * cT, np.cos(K) * cT, np.sin(T)), axis=-1)


def backbone_points(
    basis: ModalBasis, X0: np.ndarray, l: float | np.ndarray, a: np.ndarray, b: Boundary
) -> np.ndarray:
    """Eq. (5): the Q + 1 points of the curve, by the cumulative trapezoidal rule.

    Vectorised: ``a`` (..., 3) and ``l`` (...) give points of shape (..., Q + 1, 3).

    >>> B = ModalBasis(10)
    >>> P = backbone_points(B, np.zeros(3), 100.0, np.zeros(3), Boundary(np.pi/2, 0, np.pi/2, 0))
    >>> P[-1].round(9).tolist()
    [100.0, 0.0, 0.0]
    """
    K, T = basis.mode_angles(a, b)
    u = tangent(K, T)  # (..., Q+1, 3)
    h = np.asarray(l, dtype=float)[..., None, None] / basis.Q
    steps = 0.5 * h * (u[..., 1:, :] + u[..., :-1, :])
    out = np.empty(u.shape)
    out[..., 0, :] = X0
    np.cumsum(steps, axis=-2, out=out[..., 1:, :])
    out[..., 1:, :] += X0
    return out


def end_point_and_jacobian(
    basis: ModalBasis, X0: np.ndarray, l: float, a: np.ndarray, b: Boundary
) -> tuple[np.ndarray, np.ndarray]:
    """The end point X(1) (Eq. 5 at s = 1) and J_a(a, 1) of Eq. (9).

    With ``du/dK = (cK cT, -sK cT, 0)`` and ``du/dT = (-sK sT, -cK sT, cT)``,
    ``dX(1)/da1 = l int du/dK sin(2 pi s) ds`` and so on: all of them are one
    product of five tangent terms with the three weighted mode shapes.

    >>> B = ModalBasis(400)
    >>> bd = Boundary(1.0, 0.2, 1.4, -0.1)
    >>> a = np.array([0.3, -0.2, 0.1]); X, J = end_point_and_jacobian(B, np.zeros(3), 500.0, a, bd)
    >>> e = 1e-6; Xp, _ = end_point_and_jacobian(B, np.zeros(3), 500.0, a + [e, 0, 0], bd)
    >>> bool(np.allclose((Xp - X) / e, J[:, 0], atol=1e-3))
    True
    """
    return _EndPoint(basis, b).evaluate(X0, l, np.asarray(a, dtype=float))


class _EndPoint:
    """Per-solve work buffers for Eqs. (5) and (9) at s = 1 (the boundary terms of
    Eq. (7) precomputed), so one evaluation is a handful of vector operations."""

    def __init__(self, basis: ModalBasis, b: Boundary) -> None:
        self.basis = basis
        self.cK = b.b1k * basis.fall + b.b2k * basis.rise
        self.cT = b.b1t * basis.fall + b.b2t * basis.rise
        self.SC = basis.SC
        self.terms = np.empty((5, basis.Q + 1))

    def evaluate(self, X0: np.ndarray, l: float, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        K = a[:2] @ self.SC
        K += self.cK
        T = a[2] * self.basis.cos2
        T += self.cT
        sK, cK, sT, cT = np.sin(K), np.cos(K), np.sin(T), np.cos(T)
        t = self.terms
        np.multiply(sK, cT, out=t[0])
        np.multiply(cK, cT, out=t[1])
        t[2] = sT
        np.multiply(sK, sT, out=t[3])
        np.multiply(cK, sT, out=t[4])
        M = t @ self.basis.W  # (5, 3): weights w, w sin2, w cos2
        M *= l
        X = X0 + M[:3, 0]
        J = np.array(
            [
                [M[1, 1], M[1, 2], -M[3, 2]],
                [-M[0, 1], -M[0, 2], -M[4, 2]],
                [0.0, 0.0, l * float(self.basis.wcos2 @ cT)],
            ]
        )
        return X, J


@dataclass(frozen=True)
class ModalSolution:
    """Result of :func:`solve_modal_factors`."""

    a: np.ndarray
    end: np.ndarray
    residual: float
    iterations: int


def solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with A x = b for a 3x3 A, by Cramer's rule on floats (faster than LAPACK at
    this size); raises ``ZeroDivisionError`` for a singular A.

    >>> solve3(np.array([[2.0, 0, 0], [0, 4, 0], [1, 0, 1]]), np.array([2.0, 8, 3])).tolist()
    [1.0, 2.0, 2.0]
    """
    (a, b_, c), (d, e, f), (g, h, i) = A.tolist()
    x, y, z = b.tolist()
    co0, co1, co2 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * co0 + b_ * co1 + c * co2
    return np.array(
        [
            (x * co0 + b_ * (f * z - y * i) + c * (y * h - e * z)) / det,
            (a * (y * i - f * z) + x * co1 + c * (d * z - y * g)) / det,
            (a * (e * z - y * h) + b_ * (y * g - d * z) + x * co2) / det,
        ]
    )


def solve_modal_factors(
    basis: ModalBasis,
    X0: np.ndarray,
    X_D: np.ndarray,
    l: float,
    b: Boundary,
    a0: np.ndarray | None = None,
    *,
    tol: float = 1e-7,
    max_iter: int = 200,
) -> ModalSolution:
    """Modal participation factors a with X(1; a) = X_D (Eq. 8, damped).

    Levenberg-Marquardt on ``F(a) = X(1; a) - X_D``: the step
    ``(J^T J + mu I) da = -J^T F`` is Eq. (8) with omega = 1 when mu -> 0 and
    a short gradient step when mu is large; mu shrinks after every step that
    lowers |F| and grows after one that does not.  ``a0`` warm-starts it.
    ``tol`` (mm) is the distance left to the target.

    Raises :class:`UnreachableError` when ``|X_D - X0| > l`` (no curve of that
    length reaches), or when the iteration stalls (the mode shapes cannot bend
    the curve onto the target with these end angles).
    """
    X0 = np.asarray(X0, dtype=float)
    X_D = np.asarray(X_D, dtype=float)
    gap = float(np.linalg.norm(X_D - X0))
    if not l > 0.0:
        raise UnreachableError(f"backbone length must be > 0 mm, got {l:.3f}")
    if gap > l * (1.0 - 1e-9):
        raise UnreachableError(
            f"target {np.round(X_D, 3).tolist()} is {gap:.3f} mm from the base but the "
            f"modal curve is only {l:.3f} mm long"
        )
    ev = _EndPoint(basis, b)
    a = np.zeros(3) if a0 is None else np.array(a0, dtype=float)
    X, J = ev.evaluate(X0, l, a)
    F = X - X_D
    f2 = float(F @ F)
    JtJ = J.T @ J
    scale = float(JtJ[0, 0] + JtJ[1, 1] + JtJ[2, 2])
    mu = 1e-6 * scale + 1e-12
    it = 0
    tol2 = tol * tol
    while f2 > tol2:
        if it >= max_iter or mu > 1e12 * (scale + 1.0):
            raise UnreachableError(
                f"modal backbone of length {l:.1f} mm cannot reach "
                f"{np.round(X_D, 3).tolist()} with end angles (K, T) = "
                f"({math.degrees(b.b2k):.1f}, {math.degrees(b.b2t):.1f}) deg: "
                f"{math.sqrt(f2):.3g} mm left after {it} iterations"
            )
        it += 1
        damped = JtJ.copy()
        damped[0, 0] += mu
        damped[1, 1] += mu
        damped[2, 2] += mu
        a_new = a + solve3(damped, -(J.T @ F))
        X_new, J_new = ev.evaluate(X0, l, a_new)
        F_new = X_new - X_D
        f2_new = float(F_new @ F_new)
        if f2_new < f2:
            a, J, F, f2 = a_new, J_new, F_new, f2_new
            X = X_new
            JtJ = J.T @ J
            scale = float(JtJ[0, 0] + JtJ[1, 1] + JtJ[2, 2])
            mu = max(mu * 0.1, 1e-15 * scale)
        else:
            mu *= 10.0
    return ModalSolution(a=a, end=X, residual=math.sqrt(f2), iterations=it)


CONTINUATION_STEPS = 12
MULTISTART = tuple(
    np.array([a1, 0.0, a3]) for a1 in (1.0, -1.0, 0.5, -0.5, 1.5, -1.5) for a3 in (0.0, 0.3, -0.3)
)


def solve_modal_cold(
    basis: ModalBasis, X0: np.ndarray, X_D: np.ndarray, l: float, b: Boundary
) -> ModalSolution:
    """Solve without a previous solution to start from.

    First the damped iteration from a = 0; if that stalls, continuation in the end
    angles: start with the end angles equal to the start angles and turn them to
    (b2k, b2t) in ``CONTINUATION_STEPS`` warm-started solves; last, a small set of
    starting points.  Raises the first :class:`UnreachableError` if all fail.
    The reported iterations count every solve made.
    """
    try:
        return solve_modal_factors(basis, X0, X_D, l, b)
    except UnreachableError as first:
        error = first
    total = 0
    try:
        a = None
        for s in np.linspace(0.0, 1.0, CONTINUATION_STEPS + 1):
            bs = Boundary(b.b1k, b.b1t, b.b1k + s * (b.b2k - b.b1k), b.b1t + s * (b.b2t - b.b1t))
            sol = solve_modal_factors(basis, X0, X_D, l, bs, a0=a)
            a = sol.a
            total += sol.iterations
        return ModalSolution(sol.a, sol.end, sol.residual, total)
    except UnreachableError:
        pass
    for a0 in MULTISTART:
        try:
            sol = solve_modal_factors(basis, X0, X_D, l, b, a0=a0)
            return ModalSolution(sol.a, sol.end, sol.residual, total + sol.iterations)
        except UnreachableError:
            continue
    raise error
