"""Exact rope length across universal joints, and the coupling sum.

Around joint j the rope's proximal hole is ``p = (r cos phi, r sin phi, -d_p)`` in
the frame before the joint, its distal hole ``q = (r cos phi, r sin phi, +d_d)`` in
the frame after it.  The frame after is the frame before rotated by
``R = Rot_y(alpha) Rot_x(theta)`` (:func:`hrm_ctrl.kinematics.joint_rotation`),
so the straight rope between the two holes has the exact length

    s = |R q - p|,   s^2 = |p|^2 + |q|^2 - 2 p^T R q.

``p^T R q = sum_ab p_a q_b R_ab`` is linear in the eight non-zero entries of R
(``R_10 = 0``), so with ``W_ab = p_a q_b`` precomputed per rope and joint, every
rope across every joint is one small matrix product and a square root.  A rope
anchored past joint k crosses joints 1..k: its length is the sum of its
crossings (the coupling).  ``docs/ropes.md`` has the derivation.

>>> s = crossing_length(np.deg2rad(60.0), 0.0, 0.0, 12.0, 12.0, 12.0)
>>> round(float(s), 4)          # inner rope of a 60 deg bend: 24 mm straight
8.7846
>>> round(float(crossing_length(np.deg2rad(60.0), 0.0, np.pi, 12.0, 12.0, 12.0)), 4)
32.7846
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrm_ctrl.kinematics import joint_rotation
from hrm_ctrl.ropes.routing import RopeRouting

# Rotation entries (row, col) that p^T R q uses, in feature order.
_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2))


def crossing_length(
    alpha: np.ndarray | float,
    theta: np.ndarray | float,
    hole_angle: np.ndarray | float,
    hole_radius: np.ndarray | float,
    proximal_disk: np.ndarray | float,
    distal_disk: np.ndarray | float,
) -> np.ndarray:
    """Exact length (mm) of one rope across one joint, ``|R q - p|`` (broadcasts).

    >>> round(float(crossing_length(0.0, 0.0, 1.0, 12.0, 10.0, 14.0)), 12)
    24.0
    """
    phi = np.asarray(hole_angle, dtype=float)
    r = np.asarray(hole_radius, dtype=float)
    hx, hy = r * np.cos(phi), r * np.sin(phi)
    d_p = np.asarray(proximal_disk, dtype=float)
    d_d = np.asarray(distal_disk, dtype=float)
    shape = np.broadcast_shapes(hx.shape, d_p.shape, d_d.shape)
    p = np.stack(np.broadcast_arrays(hx, hy, -d_p), axis=-1).reshape(*shape, 3)
    q = np.stack(np.broadcast_arrays(hx, hy, d_d), axis=-1).reshape(*shape, 3)
    R = joint_rotation(np.asarray(alpha, dtype=float), np.asarray(theta, dtype=float))
    return np.linalg.norm(np.einsum("...ab,...b->...a", R, q) - p, axis=-1)


def small_angle_crossing_length(
    alpha: np.ndarray | float,
    theta: np.ndarray | float,
    hole_angle: np.ndarray | float,
    hole_radius: np.ndarray | float,
    proximal_disk: np.ndarray | float,
    distal_disk: np.ndarray | float,
) -> np.ndarray:
    """First-order approximation ``d_p + d_d - r (alpha cos phi - theta sin phi)``.

    Only for comparison (``docs/ropes.md``); it is what the exact form replaces.

    >>> round(float(small_angle_crossing_length(0.1, 0.0, 0.0, 12.0, 12.0, 12.0)), 6)
    22.8
    """
    phi = np.asarray(hole_angle, dtype=float)
    return (
        np.asarray(proximal_disk)
        + np.asarray(distal_disk)
        - np.asarray(hole_radius)
        * (np.asarray(alpha) * np.cos(phi) - np.asarray(theta) * np.sin(phi))
    )


@dataclass(frozen=True, eq=False)
class RopeGeometry:
    """Precomputed coefficients of every rope across every joint (read-only).

    A rope's geometric length runs from the proximal disk of joint 1 to its
    anchor on the distal disk of its joint: its crossings plus the constant
    stretches inside the links (``in_link``).

    ``W[j, f, m] = p_a q_b`` for feature f = entry (a, b) of joint j's rotation
    and rope m, zero where rope m does not cross joint j; ``C0[j, m] = |p|^2 + |q|^2``
    (zero where it does not cross).  ``straight[m]`` is each rope's length on
    the straight arm.
    """

    W: np.ndarray  # (12, 8, n)
    C0: np.ndarray  # (12, n)
    crosses: np.ndarray  # (12, n) bool
    straight: np.ndarray  # (n,)
    W9: np.ndarray  # (12, 9, n): s^2 = sum_f W9[j, f, m] * A_f T_f (signs and C0 folded in)
    first_rope: np.ndarray  # (12,) ropes first_rope[j]: cross joint j (ropes ordered by joint)
    in_link: np.ndarray  # (n,) constant length inside the links (mm)

    @property
    def n_ropes(self) -> int:
        return int(self.W.shape[-1])

    @property
    def n_joints(self) -> int:
        return int(self.W.shape[0])


def rope_geometry(routing: RopeRouting) -> RopeGeometry:
    """Build the coefficient tables of a routing.

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.routing import routing_from_model
    >>> g = rope_geometry(routing_from_model(default_robot()))
    >>> g.W.shape, g.straight[[0, 3, 35]].tolist()   # base disk to anchor, straight arm
    ((12, 8, 36), [24.0, 203.0, 1895.0])
    """
    n_j = int(routing.proximal_disk.shape[0])
    n = routing.n_ropes
    joints = np.arange(n_j)
    crosses = joints[:, None] <= routing.joint_of_rope[None, :]  # (12, n)
    r = routing.hole_radius[None, :]
    px = np.broadcast_to(r * np.cos(routing.hole_angle)[None, :], (n_j, n))
    py = np.broadcast_to(r * np.sin(routing.hole_angle)[None, :], (n_j, n))
    pz = np.broadcast_to(-routing.proximal_disk[:, None], (n_j, n))
    qz = np.broadcast_to(routing.distal_disk[:, None], (n_j, n))
    p = (px, py, pz)
    q = (px, py, qz)
    W = np.stack([p[a] * q[b] for a, b in _ENTRIES], axis=1) * crosses[:, None, :]
    C0 = (px**2 + py**2 + pz**2 + px**2 + py**2 + qz**2) * crosses
    straight = ((routing.proximal_disk + routing.distal_disk)[:, None] * crosses).sum(axis=0)
    straight = straight + routing.in_link
    W9 = np.concatenate([-2.0 * _SIGN[None, :, None] * W, C0[:, None, :]], axis=1)
    if np.all(np.diff(routing.joint_of_rope) >= 0):
        first = np.searchsorted(routing.joint_of_rope, joints)
    else:
        first = np.zeros(n_j, dtype=np.int64)
    in_link = np.array(routing.in_link, dtype=float)
    arrays = (W, C0, crosses, straight, W9, first, in_link)
    for arr in arrays:
        arr.setflags(write=False)
    return RopeGeometry(*arrays)


# Each used rotation entry is sign * A * T with A in (1, cos a, sin a), T in (1, cos t, sin t);
# the trig table is (1, cos, sin, -sin, 0) so derivatives are lookups too.  Feature 9 is the
# constant 1 (A = T = 1) that carries C0.
_IA = np.array([1, 2, 2, 0, 0, 2, 1, 1])
_IT = np.array([0, 2, 1, 1, 2, 0, 2, 1])
_SIGN = np.array([1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0])
_D = np.array([4, 3, 1])  # d/dx of (1, cos, sin) as indices into the trig table
_IA9 = np.append(_IA, 0)
_IT9 = np.append(_IT, 0)
_IA27 = np.concatenate([_IA9, _D[_IA9], _IA9])
_IT27 = np.concatenate([_IT9, _IT9, _D[_IT9]])
N9 = 9
BATCH_CHUNK = 1024


def _trig(alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Table (1, cos, sin, -sin, 0) of alpha and theta, shape (2, ..., 5)."""
    alpha = np.asarray(alpha, dtype=float)
    u = np.empty((2, *alpha.shape, 5))
    x = u[..., 4]
    x[0] = alpha
    x[1] = theta
    np.cos(x, out=u[..., 1])
    np.sin(x, out=u[..., 2])
    np.negative(u[..., 2], out=u[..., 3])
    u[..., 0] = 1.0
    u[..., 4] = 0.0
    return u


def _features9(alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Unsigned products ``A_f T_f`` and the constant 1, shape (..., 9)."""
    u = _trig(alpha, theta)
    return u[0][..., _IA9] * u[1][..., _IT9]


def _features27(alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """:func:`_features9`, its d/dalpha and d/dtheta side by side: shape (..., 27)."""
    u = _trig(alpha, theta)
    return u[0][..., _IA27] * u[1][..., _IT27]


def rope_lengths(geom: RopeGeometry, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Geometric length (mm) of every rope from the base disk to its anchor, (..., n).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.routing import routing_from_model
    >>> g = rope_geometry(routing_from_model(default_robot()))
    >>> a = np.zeros(12); a[11] = np.deg2rad(60.0)      # bend only joint 12
    >>> L = rope_lengths(g, a, np.zeros(12))
    >>> bool(np.allclose(L[:33], g.straight[:33]))       # ropes of joints 1..11 unchanged
    True
    >>> np.round(L[33:] - g.straight[33:], 3).tolist()   # joint 12's ropes, holes at 110+120m deg
    [0.889, 4.498, -15.033]
    """
    alpha = np.asarray(alpha, dtype=float)
    theta = np.asarray(theta, dtype=float)
    batch = alpha.shape[:-1]
    F = _features9(alpha, theta).reshape(-1, geom.n_joints, N9)
    B = F.shape[0]
    if B < 64:
        G = np.matmul(F.transpose(1, 0, 2), geom.W9)  # (12, B, n)
        np.maximum(G, 0.0, out=G)
        np.sqrt(G, out=G)
        L = G.sum(axis=0)
        L += geom.in_link
        return L.reshape(*batch, geom.n_ropes)
    # Large batches: per joint only the ropes that cross it, in cache-sized chunks.
    out = np.empty((B, geom.n_ropes))
    out[:] = geom.in_link
    for c0 in range(0, B, BATCH_CHUNK):
        Fc = F[c0 : c0 + BATCH_CHUNK]
        oc = out[c0 : c0 + BATCH_CHUNK]
        for j in range(geom.n_joints):
            f = int(geom.first_rope[j])
            G = Fc[:, j, :] @ geom.W9[j][:, f:]
            np.maximum(G, 0.0, out=G)
            np.sqrt(G, out=G)
            oc[:, f:] += G
    return out.reshape(*batch, geom.n_ropes)


def lengths_and_jacobian(
    geom: RopeGeometry, alpha: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rope lengths (B, n), their Jacobian (B, n, 24) and the segments (12, B, n).

    ``alpha``, ``theta`` of shape (B, 12); Jacobian columns (alpha_1, theta_1,
    alpha_2, ...).  It is block lower triangular: the rope of joint k depends on
    joints 1..k only, and column block j holds the derivative of the rope's
    crossing of joint j (``d s / d x = (d s^2 / d x) / 2 s``).
    """
    B = alpha.shape[0]
    n_j, n = geom.n_joints, geom.n_ropes
    F3 = _features27(alpha, theta).reshape(B, n_j, 3, N9)
    G = np.matmul(F3.transpose(1, 2, 0, 3).reshape(n_j, 3 * B, N9), geom.W9)
    G = G.reshape(n_j, 3, B, n)
    s = np.sqrt(np.maximum(G[:, 0], 0.0))  # (12, B, n)
    safe = np.where(s > 0.0, 2.0 * s, 1.0)
    J = (G[:, 1:] / safe[:, None]).transpose(2, 3, 0, 1).reshape(B, n, 2 * n_j)
    return s.sum(axis=0) + geom.in_link, J, s
