"""Rope lengths -> joint angles, using the triangular structure of the coupling.

Joint 1's ropes see joint 1 only, joint 2's see joints 1-2, ... so the rope
equations ``L_m = sum_{j <= k(m)} s(x_j; rope m)`` are block lower triangular in
the joint angles ``x_j = (alpha_j, theta_j)``.  The inverse solves them joint by
joint: joint k's angles are the least-squares fit of joint k's ropes (2 unknowns,
n_k >= 2 equations) once joints 1..k-1 are known.

All joints are solved together by Newton's method on that sequential problem.
With ``J`` the Jacobian (block lower triangular, blocks ``J_kj``) and
``P_k = (J_kk^T J_kk)^-1 J_kk^T`` the least-squares inverse of joint k's own
block, one Newton step is the block forward substitution

    delta_k = P_k (r_k - sum_{j<k} J_kj delta_j),

which is the 24x24 unit block-lower-triangular system ``(P J) delta = P r``:
vectorised over joints, ropes and configurations, no Python loop per joint.  At
convergence ``P_k r_k = 0`` for every k, i.e. each joint's angles are the
least-squares fit of its own ropes; ``r`` is then the per-rope residual.

That fit can be a spurious local minimum near the corners of the joint range, where
the lengths fold: a joint's own ropes then barely tell two configurations apart
(the reported case, alpha_11 = theta_11 = -1.046875 rad, theta_12 = -1 rad: 1.6 degrees
off, 0.007 mm on the worst rope, 0.005 mm joint RMS).  A joint RMS residual above
:data:`RESIDUAL_TOL_MM` therefore counts as a possible wrong fit: a small one is
polished with ``scipy.optimize.least_squares`` on every rope equation at once (the
ropes of the joints further out cross the joint too and resolve the fold), a large
one or a polish that does not fit within the tolerance is solved again joint by
joint on squared lengths (see :func:`solve_angles`).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.routing import routing_from_model
>>> from hrm_ctrl.ropes.length import rope_geometry, rope_lengths
>>> rt = routing_from_model(default_robot())
>>> g = rope_geometry(rt)
>>> a = np.linspace(-0.9, 0.9, 12); t = np.linspace(0.8, -0.8, 12)
>>> sol = solve_angles(g, rt.joint_of_rope, rope_lengths(g, a, t))
>>> bool(np.allclose(sol.alpha, a, atol=1e-9) and np.allclose(sol.theta, t, atol=1e-9))
True
>>> float(np.abs(sol.residual).max()) < 1e-9
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dtrtrs as _dtrtrs

from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.length import (
    N9,
    RopeGeometry,
    _features9,
    _features27,
    lengths_and_jacobian,
    rope_lengths,
)

MAX_ITERATIONS = 30
STEP_TOL = 1e-8  # rad; Newton converges quadratically: the error left is ~1e-16
SWITCH_TOL = 1e-6  # rad: from squared-length to plain-length Newton
RESIDUAL_TOL_MM = 3e-3
"""A joint's RMS rope residual (mm) above this is taken for a possible wrong fit.

* Consistent data stay below it, so they never pay for the robust solve: lengths from
  motor counts (quantised at 2151 counts/mm with the shipped motor map) leave correct
  fits a joint RMS of 2e-4 mm (median) and 1.6e-3 mm at most (20,000 configurations
  over the whole joint range); exact lengths leave ~1e-11 mm.
* In joint angle: a joint's rope lengths change by 14.7 mm/rad at the straight arm
  (both singular values of its own 3x2 Jacobian), so 3e-3 mm left unexplained is
  2e-4 rad (0.012 deg), the angle resolution the counts give anyway; at
  alpha = theta = 1 rad the weaker direction drops to 0.6 mm/rad, and 3e-3 mm is
  5e-3 rad (0.3 deg).  Near the corners of the range the lengths fold and a residual
  of a few micrometres can sit next to a fit degrees away (the reported case:
  0.005 mm joint RMS, 1.6 deg), hence the tolerance is as low as the counts allow.  Below it a
  wrong fit cannot be told from quantisation at all (in the corners, fits 6 deg apart
  were seen within 1e-4 mm): the counts do not determine the angles there better.
"""
FALLBACK_RMS_MM = 0.01  # above this (or no convergence) straight to the joint-by-joint solve
POLISH_MAX_NFEV = 60  # least_squares evaluations per polish (a near miss takes ~10)
MAX_STEP = 0.5  # rad per iteration and angle (keeps Newton inside the joint's range)


class RopeInverseError(RopeError):
    """The rope lengths do not determine joint angles (no convergence, bad input)."""


@dataclass(frozen=True)
class InverseSolution:
    """Angles (..., 12) and the per-rope residual ``L - L(angles)`` (..., n) in mm."""

    alpha: np.ndarray
    theta: np.ndarray
    residual: np.ndarray
    iterations: int
    jacobian: np.ndarray | None = None  # (..., n, 24) at (within a Newton step of) the solution

    def joint_residual(self, joint_of_rope: np.ndarray) -> np.ndarray:
        """RMS residual of each joint's own ropes (..., 12) in mm."""
        n_j = int(np.max(joint_of_rope)) + 1
        flat = self.residual.reshape(-1, self.residual.shape[-1])
        return _joint_rms(flat, np.asarray(joint_of_rope), n_j).reshape(
            *self.residual.shape[:-1], n_j
        )


def padded_index(joint_of_rope: np.ndarray, n_joints: int) -> np.ndarray:
    """(12, n_max) rope index of each joint's ropes, padded with ``n`` (a zero row).

    >>> padded_index(np.array([0, 0, 1, 1, 1]), 2).tolist()
    [[0, 1, 5], [2, 3, 4]]
    """
    n = int(joint_of_rope.shape[0])
    counts = np.bincount(joint_of_rope, minlength=n_joints)
    out = np.full((n_joints, int(counts.max())), n, dtype=np.int64)
    for k in range(n_joints):
        rows = np.flatnonzero(joint_of_rope == k)
        out[k, : rows.size] = rows
    return out


def newton_step(
    J: np.ndarray, r: np.ndarray, pad: np.ndarray, identity_pad: bool | None = None
) -> np.ndarray:
    """One block-forward-substitution Newton step, shape (B, 24), from J (B, n, 24), r (B, n).

    ``identity_pad``: whether ``pad`` is the identity layout (every joint the same
    number of ropes, in order); computed if not given.
    """
    B, n, n_x = J.shape
    n_j, n_max = pad.shape
    Jr = np.concatenate([J, r[..., None]], axis=2)  # (B, n, 25)
    if identity_pad is None:
        identity_pad = n_j * n_max == n and _is_identity(pad)
    if identity_pad:
        Jx = Jr.reshape(B, n_j, n_max, n_x + 1)
    else:
        Jx = np.concatenate([Jr, np.zeros((B, 1, n_x + 1))], axis=1)[:, pad]
    own = Jx[:, :, :, :n_x].reshape(B, n_j, n_max, n_j, 2)[:, _DIAG[:n_j], :, _DIAG[:n_j], :]
    ownT = own.transpose(1, 0, 3, 2)  # (B, 12, 2, n_max)
    try:
        P = np.linalg.inv(ownT @ own.transpose(1, 0, 2, 3)) @ ownT  # (B, 12, 2, n_max)
    except np.linalg.LinAlgError:
        raise RopeInverseError(
            "a joint's ropes do not determine its two angles (singular)"
        ) from None
    Mr = (P @ Jx).reshape(B, 2 * n_j, n_x + 1)
    if B == 1:  # unit lower triangular: LAPACK forward substitution
        x, _ = _dtrtrs(Mr[0, :, :n_x], Mr[0, :, n_x:], lower=1, unitdiag=1)
        return x.reshape(1, n_x)
    return np.linalg.solve(Mr[..., :n_x], Mr[..., n_x:])[..., 0]


_DIAG = np.arange(64)


def _is_identity(pad: np.ndarray) -> bool:
    return bool(np.array_equal(pad.ravel(), np.arange(pad.size)))


def _coupled_newton(
    geom: RopeGeometry,
    Lb: np.ndarray,
    x: np.ndarray,
    pad: np.ndarray,
    max_iterations: int = MAX_ITERATIONS,
    identity_pad: bool | None = None,
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """Newton on the triangular rope equations in mm.

    Returns x, converged (B,), iterations and the Jacobian of the last iteration.
    """
    B, n_j = x.shape[0], geom.n_joints
    step = np.full(B, np.inf)
    iterations = 0
    J = np.empty(0)
    for it in range(1, max_iterations + 1):
        iterations = it
        s, J, _ = lengths_and_jacobian(geom, x[..., 0], x[..., 1])
        delta = newton_step(J, Lb - s, pad, identity_pad)
        np.clip(delta, -MAX_STEP, MAX_STEP, out=delta)
        x += delta.reshape(B, n_j, 2)
        step = np.abs(delta).max(axis=1)
        if float(step.max()) < STEP_TOL:
            break
    return x, step < STEP_TOL, iterations, J


def _sequential_squared(
    geom: RopeGeometry, joint_of_rope: np.ndarray, Lb: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Joint-by-joint Gauss-Newton on squared crossing lengths, from the straight arm.

    Slower than :func:`_coupled_newton` (a loop over joints) but free of the
    spurious least-squares minima that plain-length Newton meets near the corners
    of the joint range: the squared crossing ``C0 - 2 W . F(alpha, theta)`` is
    linear in the rotation entries.  Returns the angles (B, 12, 2) and whether
    every joint's iteration converged (B,).
    """
    B, n_j = Lb.shape[0], geom.n_joints
    x = np.zeros((B, n_j, 2))
    ok = np.ones(B, dtype=bool)
    prior = np.zeros_like(Lb) + geom.in_link  # constant in-link parts, then crossings
    for k in range(n_j):
        idx = np.flatnonzero(joint_of_rope == k)
        W9k = geom.W9[k][:, idx]
        t2 = (Lb[:, idx] - prior[:, idx]) ** 2
        xk = np.zeros((B, 2))
        mu = np.full(B, 1e-3)  # Levenberg-Marquardt damping, per configuration
        g, ja, jt = _squared_residual(W9k, t2, xk)
        cost = (g * g).sum(1)
        done = np.zeros(B, dtype=bool)
        for _ in range(4 * MAX_ITERATIONS):
            a11, a12, a22 = (ja * ja).sum(1), (ja * jt).sum(1), (jt * jt).sum(1)
            b1, b2 = -(ja * g).sum(1), -(jt * g).sum(1)
            d11, d22 = a11 * (1.0 + mu), a22 * (1.0 + mu)
            det = d11 * d22 - a12 * a12
            det = np.where(np.abs(det) > 1e-300, det, 1e-300)
            d = np.stack([(d22 * b1 - a12 * b2) / det, (d11 * b2 - a12 * b1) / det], axis=1)
            np.clip(d, -MAX_STEP, MAX_STEP, out=d)
            d[done] = 0.0
            g_new, ja_new, jt_new = _squared_residual(W9k, t2, xk + d)
            cost_new = (g_new * g_new).sum(1)
            accept = cost_new <= cost
            xk[accept] += d[accept]
            g[accept], ja[accept], jt[accept] = g_new[accept], ja_new[accept], jt_new[accept]
            small = np.abs(d).max(axis=1) < SWITCH_TOL * 1e-2
            stalled = accept & (cost - cost_new <= 1e-15 * (1.0 + cost))
            cost = np.where(accept, cost_new, cost)
            mu = np.where(accept, mu / 3.0, mu * 4.0)
            done |= small | stalled | (mu > 1e12)
            if done.all():
                break
        ok &= done & (mu <= 1e12)
        x[:, k] = xk
        prior += np.sqrt(np.maximum(_features9(xk[:, 0], xk[:, 1]) @ geom.W9[k], 0.0))
    return x, ok


def _squared_residual(
    W9k: np.ndarray, t2: np.ndarray, xk: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Squared own crossings minus squared targets (B, n_k) and their d/dalpha, d/dtheta."""
    B = xk.shape[0]
    G = _features27(xk[:, 0], xk[:, 1]).reshape(B, 3, N9).transpose(1, 0, 2) @ W9k
    return G[0] - t2, G[1], G[2]


def solve_angles(
    geom: RopeGeometry,
    joint_of_rope: np.ndarray,
    lengths: np.ndarray,
    alpha0: np.ndarray | None = None,
    theta0: np.ndarray | None = None,
    pad: np.ndarray | None = None,
    *,
    robust: bool = True,
    max_iterations: int | None = None,
) -> InverseSolution:
    """Joint angles whose geometric rope lengths best match ``lengths`` (..., n) mm.

    Fast path: Newton on all joints at once from ``alpha0``/``theta0`` (default:
    straight arm).  Where it leaves a joint's RMS residual above
    :data:`RESIDUAL_TOL_MM` (a spurious minimum near the joint-range corners, or
    inconsistent data):

    1. up to ``FALLBACK_RMS_MM`` (a near miss), the answer is polished with
       ``scipy.optimize.least_squares`` on all rope equations at once and kept if
       every joint then fits within :data:`RESIDUAL_TOL_MM`;
    2. otherwise (or without convergence) the configuration is solved again joint by
       joint on squared lengths and polished with Newton; the better fit is kept.

    Inconsistent data (a faulty rope) keep the joint-by-joint fit, in which a rope's
    error shows in its own joint first.  ``robust=False`` skips both (for a warm
    start already in the right basin, e.g. a filter's estimate, where a faulty rope
    must not cost the slow path every cycle); ``max_iterations`` caps the Newton
    steps and accepts the result (tracking).
    Raises :class:`RopeInverseError` on non-finite lengths or no convergence.
    """
    L = np.asarray(lengths, dtype=float)
    n_j = geom.n_joints
    joint_of_rope = np.asarray(joint_of_rope)
    if L.shape[-1:] != (geom.n_ropes,):
        raise RopeInverseError(f"expected {geom.n_ropes} rope lengths, got shape {L.shape}")
    if not np.all(np.isfinite(L)):
        bad = int(np.flatnonzero(~np.isfinite(L.reshape(-1, geom.n_ropes)).any(axis=0))[0])
        raise RopeInverseError(f"rope {bad}: length is not finite")
    batch = L.shape[:-1]
    Lb = L.reshape(-1, geom.n_ropes)
    B = Lb.shape[0]
    x = np.zeros((B, n_j, 2))
    if alpha0 is not None:
        x[..., 0] = _as_batch(alpha0, batch, B, n_j)
    if theta0 is not None:
        x[..., 1] = _as_batch(theta0, batch, B, n_j)
    if pad is None:
        pad = padded_index(joint_of_rope, n_j)
    ident = pad.size == geom.n_ropes and _is_identity(pad)
    x, ok, it, J = _coupled_newton(geom, Lb, x, pad, max_iterations or MAX_ITERATIONS, ident)
    if max_iterations is not None:
        ok[:] = True
    res = Lb - rope_lengths(geom, x[..., 0], x[..., 1])
    rms = _joint_rms(res, joint_of_rope, n_j).max(axis=1)
    if robust:
        for b in np.flatnonzero(ok & (rms > RESIDUAL_TOL_MM) & (rms <= FALLBACK_RMS_MM)):
            polished = _polish(geom, Lb[b], x[b])
            if polished is None:
                continue
            xp, rp, Jp = polished
            rms_p = float(_joint_rms(rp[None], joint_of_rope, n_j).max())
            if rms_p <= RESIDUAL_TOL_MM:
                x[b], res[b], J[b], rms[b] = xp, rp, Jp, rms_p
        suspect = ~ok | (rms > RESIDUAL_TOL_MM)
    else:
        suspect = np.zeros(B, dtype=bool)
    if suspect.any():
        Ls = Lb[suspect]
        x1, ok1 = _sequential_squared(geom, joint_of_rope, Ls)
        x2, ok2, it2, J2 = _coupled_newton(geom, Ls, x1.copy(), pad, MAX_ITERATIONS, ident)
        # Inconsistent data (large residuals) can keep the plain-length Newton from
        # settling; the joint-by-joint fit on squared lengths then stands as the answer.
        keep1 = ~ok2 & ok1
        if keep1.any():
            x2[keep1] = x1[keep1]
            J2[keep1] = lengths_and_jacobian(geom, x1[keep1][..., 0], x1[keep1][..., 1])[1]
            ok2 = ok2 | ok1
        res2 = Ls - rope_lengths(geom, x2[..., 0], x2[..., 1])
        better = ok2 & (~ok[suspect] | ((res2**2).sum(1) < (res[suspect] ** 2).sum(1)))
        sel = np.flatnonzero(suspect)[better]
        x[sel], res[sel], ok[sel], J[sel] = x2[better], res2[better], True, J2[better]
        it += it2
    if not ok.all():
        raise RopeInverseError(
            f"rope inverse did not converge in {MAX_ITERATIONS} iterations "
            f"({int((~ok).sum())} of {B} configurations)"
        )
    return InverseSolution(
        alpha=x[..., 0].reshape(*batch, n_j),
        theta=x[..., 1].reshape(*batch, n_j),
        residual=res.reshape(*batch, geom.n_ropes),
        iterations=it,
        jacobian=J.reshape(*batch, geom.n_ropes, 2 * n_j),
    )


def load_fallback_solver() -> None:
    """Import what the robust path of :func:`solve_angles` needs (``scipy.optimize``,
    0.2 s on this machine) now, not at its first use.

    A thread that solves on a schedule (the simulated box's tension board, a session's
    estimator) calls this before it starts: an import at the first near miss holds the
    import lock and most of the interpreter for 0.2-0.5 s, longer than every watchdog
    of a running box.

    >>> load_fallback_solver()
    >>> import sys; "scipy.optimize" in sys.modules
    True
    """
    import scipy.optimize  # noqa: F401


def _polish(
    geom: RopeGeometry, L: np.ndarray, x0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``scipy.optimize.least_squares`` (Levenberg-Marquardt, analytic Jacobian) on every
    rope equation of one configuration from ``x0`` (12, 2): angles (12, 2), residual
    ``L - L(angles)`` (n,) and Jacobian (n, 24) there, or ``None`` if it fails.

    Unlike the joint-by-joint fit it uses every rope crossing a joint, also those of
    the joints further out, which is what tells a fold's two sides apart.
    """
    from scipy.optimize import least_squares  # 0.2 s to import: see load_fallback_solver

    memo: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def evaluate(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = z.tobytes()
        if key not in memo:
            memo.clear()
            s, J, _ = lengths_and_jacobian(geom, z[None, 0::2], z[None, 1::2])
            memo[key] = (s[0] - L, J[0])
        return memo[key]

    try:
        sol = least_squares(
            lambda z: evaluate(z)[0],
            x0.ravel(),
            jac=lambda z: evaluate(z)[1],
            method="lm",
            xtol=STEP_TOL * 1e-2,
            ftol=1e-14,
            gtol=1e-14,
            max_nfev=POLISH_MAX_NFEV,
        )
    except (ValueError, np.linalg.LinAlgError):  # pragma: no cover - defensive
        return None
    if not np.all(np.isfinite(sol.x)):  # pragma: no cover - defensive
        return None
    r, J = evaluate(sol.x)
    return sol.x.reshape(-1, 2), -r, J


def _as_batch(v: np.ndarray, batch: tuple[int, ...], B: int, n_j: int) -> np.ndarray:
    """A warm-start array as (B, 12): same batch shape, or broadcast to it."""
    v = np.asarray(v, dtype=float)
    if v.shape == (*batch, n_j):
        return v.reshape(B, n_j)
    return np.broadcast_to(v, (*batch, n_j)).reshape(B, n_j)


def _joint_rms(residual: np.ndarray, joint_of_rope: np.ndarray, n_j: int) -> np.ndarray:
    """RMS residual of each joint's own ropes, (B, 12) from (B, n)."""
    onehot = (joint_of_rope[:, None] == np.arange(n_j)[None, :]).astype(float)  # (n, 12)
    return np.sqrt((residual**2) @ onehot / onehot.sum(axis=0))


def standardized_residual(
    geom: RopeGeometry,
    joint_of_rope: np.ndarray,
    alpha: np.ndarray,
    theta: np.ndarray,
    residual: np.ndarray,
    *,
    jacobian: np.ndarray | None = None,
    pad: np.ndarray | None = None,
) -> np.ndarray:
    """Each rope's residual divided by ``sqrt(N_mm)``, N the projector onto the part of
    its joint's rope lengths that the joint's two angles cannot explain (mm), shape (n,).

    For a single faulty rope i (offset e) the standardized residual is largest
    (``|e| sqrt(N_ii)``) on rope i whenever the fault is identifiable
    (Cauchy-Schwarz); with three ropes per joint all three are equal, so the
    fault is located to the joint.  Ropes with ``N_mm = 0`` (two ropes per
    joint: no redundancy) get 0.  ``jacobian`` (n, 24) at the solution saves
    recomputing it.
    """
    if jacobian is None:
        _, J, _ = lengths_and_jacobian(geom, np.asarray(alpha)[None], np.asarray(theta)[None])
        jacobian = J[0]
    own = np.asarray(joint_of_rope)
    cols = np.stack([2 * own, 2 * own + 1], axis=1)
    Jo = np.take_along_axis(jacobian, cols, axis=1)  # (n, 2): each rope's own-joint block row
    if pad is None:
        pad = padded_index(own, geom.n_joints)
    Jp = np.concatenate([Jo, np.zeros((1, 2))])[pad]  # (12, n_max, 2), zero rows padded
    Ainv = np.linalg.inv(np.einsum("kic,kid->kcd", Jp, Jp))
    lev = np.einsum("kic,kcd,kid->ki", Jp, Ainv, Jp)  # leverage of each rope in its joint
    d = np.zeros(geom.n_ropes + 1)
    d[pad.ravel()] = (1.0 - lev).ravel()
    d = np.clip(d[:-1], 0.0, None)
    ok = d > 1e-12
    return np.where(ok, np.asarray(residual) / np.sqrt(np.where(ok, d, 1.0)), 0.0)
