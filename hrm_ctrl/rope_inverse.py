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

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.rope_routing import routing_from_model
>>> from hrm_ctrl.rope_length import rope_geometry, rope_lengths
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

from hrm_ctrl.errors import RopeError
from hrm_ctrl.rope_length import (
    N_FEATURES,
    RopeGeometry,
    _features_and_derivatives,
    lengths_and_jacobian,
    rope_lengths,
    rotation_features,
)

MAX_ITERATIONS = 30
STEP_TOL = 1e-10
SWITCH_TOL = 1e-6  # rad: from squared-length to plain-length Newton
FALLBACK_RMS_MM = 0.01  # a joint's RMS rope residual above this triggers the robust solve
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


def newton_step(J: np.ndarray, r: np.ndarray, pad: np.ndarray) -> np.ndarray:
    """One block-forward-substitution Newton step, shape (B, 24), from J (B, n, 24), r (B, n)."""
    B, n, n_x = J.shape
    n_j, n_max = pad.shape
    Jr = np.concatenate([J, r[..., None]], axis=2)  # (B, n, 25)
    if n_j * n_max == n and _is_identity(pad):
        Jx = Jr.reshape(B, n_j, n_max, n_x + 1)
    else:
        Jx = np.concatenate([Jr, np.zeros((B, 1, n_x + 1))], axis=1)[:, pad]
    k = np.arange(n_j)
    own = Jx[:, :, :, :n_x].reshape(B, n_j, n_max, n_j, 2)[:, k, :, k, :]  # (12, B, n_max, 2)
    ownT = own.transpose(1, 0, 3, 2)  # (B, 12, 2, n_max)
    A = ownT @ ownT.transpose(0, 1, 3, 2)
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    if not np.all(np.abs(det) > 1e-18):
        raise RopeInverseError("a joint's ropes do not determine its two angles (singular)")
    P = np.linalg.inv(A) @ ownT  # (B, 12, 2, n_max)
    Mr = (P @ Jx).reshape(B, 2 * n_j, n_x + 1)
    return np.linalg.solve(Mr[..., :n_x], Mr[..., n_x:])[..., 0]


def _is_identity(pad: np.ndarray) -> bool:
    return bool(np.array_equal(pad.ravel(), np.arange(pad.size)))


def _coupled_newton(
    geom: RopeGeometry, Lb: np.ndarray, x: np.ndarray, pad: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Newton on the triangular rope equations in mm; returns x, converged (B,), iterations."""
    B, n_j = x.shape[0], geom.n_joints
    step = np.full(B, np.inf)
    it = 0
    for it in range(1, MAX_ITERATIONS + 1):
        s, J, _ = lengths_and_jacobian(geom, x[..., 0], x[..., 1])
        delta = newton_step(J, Lb - s, pad)
        np.clip(delta, -MAX_STEP, MAX_STEP, out=delta)
        x += delta.reshape(B, n_j, 2)
        step = np.abs(delta).max(axis=1)
        if float(step.max()) < STEP_TOL:
            break
    return x, step < 1e-8, it


def _sequential_squared(
    geom: RopeGeometry, joint_of_rope: np.ndarray, Lb: np.ndarray
) -> np.ndarray:
    """Joint-by-joint Gauss-Newton on squared crossing lengths, from the straight arm.

    Slower than :func:`_coupled_newton` (a loop over joints) but free of the
    spurious least-squares minima that plain-length Newton meets near the corners
    of the joint range: the squared crossing ``C0 - 2 W . F(alpha, theta)`` is
    linear in the rotation entries.
    """
    B, n_j = Lb.shape[0], geom.n_joints
    x = np.zeros((B, n_j, 2))
    prior = np.zeros_like(Lb)
    for k in range(n_j):
        idx = np.flatnonzero(joint_of_rope == k)
        Wk = geom.W[k][:, idx]
        C0k = geom.C0[k, idx]
        t2 = (Lb[:, idx] - prior[:, idx]) ** 2
        xk = np.zeros((B, 2))
        for _ in range(MAX_ITERATIONS):
            F3 = _features_and_derivatives(xk[:, 0], xk[:, 1]).reshape(B, 3, N_FEATURES)
            G = F3.transpose(1, 0, 2) @ Wk  # (3, B, n_k)
            g = C0k - 2.0 * G[0] - t2
            ja, jt = -2.0 * G[1], -2.0 * G[2]
            a11, a12, a22 = (ja * ja).sum(1), (ja * jt).sum(1), (jt * jt).sum(1)
            b1, b2 = -(ja * g).sum(1), -(jt * g).sum(1)
            det = a11 * a22 - a12 * a12
            det = np.where(np.abs(det) > 1e-300, det, 1e-300)
            d = np.stack([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det], axis=1)
            np.clip(d, -MAX_STEP, MAX_STEP, out=d)
            xk += d
            if float(np.abs(d).max()) < SWITCH_TOL:
                break
        x[:, k] = xk
        F = rotation_features(xk[:, 0], xk[:, 1])  # (B, 8)
        prior += np.sqrt(np.maximum(geom.C0[k] - 2.0 * (F @ geom.W[k]), 0.0))
    return x


def solve_angles(
    geom: RopeGeometry,
    joint_of_rope: np.ndarray,
    lengths: np.ndarray,
    alpha0: np.ndarray | None = None,
    theta0: np.ndarray | None = None,
    pad: np.ndarray | None = None,
) -> InverseSolution:
    """Joint angles whose geometric rope lengths best match ``lengths`` (..., n) mm.

    Fast path: Newton on all joints at once from ``alpha0``/``theta0`` (default:
    straight arm).  Where it does not converge or leaves a joint's RMS residual
    above ``FALLBACK_RMS_MM`` (a spurious minimum near the joint-range corners,
    or inconsistent data), the configuration is solved again joint by joint on
    squared lengths and polished; the better fit is kept.
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
        x[..., 0] = np.broadcast_to(alpha0, (*batch, n_j)).reshape(B, n_j)
    if theta0 is not None:
        x[..., 1] = np.broadcast_to(theta0, (*batch, n_j)).reshape(B, n_j)
    if pad is None:
        pad = padded_index(joint_of_rope, n_j)
    x, ok, it = _coupled_newton(geom, Lb, x, pad)
    res = Lb - rope_lengths(geom, x[..., 0], x[..., 1])
    rms = _joint_rms(res, joint_of_rope, n_j)
    suspect = ~ok | (rms.max(axis=1) > FALLBACK_RMS_MM)
    if suspect.any():
        x2 = _sequential_squared(geom, joint_of_rope, Lb[suspect])
        x2, ok2, it2 = _coupled_newton(geom, Lb[suspect], x2, pad)
        res2 = Lb[suspect] - rope_lengths(geom, x2[..., 0], x2[..., 1])
        better = ok2 & (~ok[suspect] | ((res2**2).sum(1) < (res[suspect] ** 2).sum(1)))
        sel = np.flatnonzero(suspect)[better]
        x[sel], res[sel], ok[sel] = x2[better], res2[better], True
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
    )


def _joint_rms(residual: np.ndarray, joint_of_rope: np.ndarray, n_j: int) -> np.ndarray:
    """RMS residual of each joint's own ropes, (B, 12) from (B, n)."""
    onehot = (joint_of_rope[:, None] == np.arange(n_j)[None, :]).astype(float)  # (n, 12)
    return np.sqrt((residual**2) @ onehot / onehot.sum(axis=0))
