"""Forward kinematics of the 12-universal-joint arm, Eqs. (1)-(4).

Conventions (``NOTES.md``): alpha_i is the first rotation, about the joint's
y axis; theta_i the second, about the new x axis.  Eq. (1) is
``Trans(0, 0, l_{i-1}) Rot_y(alpha_i) Rot_x(theta_i)``; Eq. (2) is
``Rot_y(-pi/2) Rot_x(pi) Rot_y(alpha_1) Rot_x(theta_1)``.  Joint centre
``O_{i+1} = T_0^i (0, 0, l_i, 1)``; ``O_13`` is the end point (Eq. 4).

All functions accept a batch: ``alpha`` and ``theta`` of shape (..., 12).

>>> from hrm_ctrl.model import default_robot
>>> m = default_robot()
>>> O = joint_centres(m, np.zeros(12), np.zeros(12))
>>> O[-1].round(9).tolist()       # straight arm: the end point is L_sum along +x0
[2007.0, 0.0, 0.0]
"""

from __future__ import annotations

import numpy as np

from hrm_ctrl.model import RobotModel

# Rot_y(-pi/2) Rot_x(pi): the fixed part of Eq. (2).
R_BASE_PAPER = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def joint_rotation(alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Rotation part of Eq. (1): ``Rot_y(alpha) Rot_x(theta)``, shape (..., 3, 3).

    >>> R = joint_rotation(np.array(0.3), np.array(-0.2))
    >>> ca, sa, ct, st = np.cos(0.3), np.sin(0.3), np.cos(-0.2), np.sin(-0.2)
    >>> bool(np.allclose(R, [[ca, sa*st, sa*ct], [0, ct, -st], [-sa, ca*st, ca*ct]]))
    True
    """
    alpha = np.asarray(alpha, dtype=float)
    theta = np.asarray(theta, dtype=float)
    ca, sa = np.cos(alpha), np.sin(alpha)
    ct, st = np.cos(theta), np.sin(theta)
    R = np.empty((*np.broadcast(alpha, theta).shape, 3, 3))
    R[..., 0, 0] = ca
    R[..., 0, 1] = sa * st
    R[..., 0, 2] = sa * ct
    R[..., 1, 0] = 0.0
    R[..., 1, 1] = ct
    R[..., 1, 2] = -st
    R[..., 2, 0] = -sa
    R[..., 2, 1] = ca * st
    R[..., 2, 2] = ca * ct
    return R


def joint_transform(alpha: float, theta: float, l_prev: float) -> np.ndarray:
    """Eq. (1): ``T_{i-1}^i`` as a 4x4 homogeneous matrix.

    >>> T = joint_transform(0.0, 0.0, 179.0)
    >>> T[:3, 3].tolist()
    [0.0, 0.0, 179.0]
    """
    T = np.eye(4)
    T[:3, :3] = joint_rotation(np.asarray(alpha), np.asarray(theta))
    T[2, 3] = l_prev
    return T


def base_transform(alpha1: float, theta1: float) -> np.ndarray:
    """Eq. (2): ``T_0^1`` for a base at the origin along +x0.

    >>> T = base_transform(0.0, 0.0)
    >>> T[:3, 2].tolist(), T[:3, 0].tolist()     # z1 along +x0, x1 up
    ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    """
    T = np.eye(4)
    T[:3, :3] = R_BASE_PAPER @ joint_rotation(np.asarray(alpha1), np.asarray(theta1))
    return T


def frames(
    model: RobotModel, alpha: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World rotations and origins of the joint frames 1..12 (Eq. 3).

    Returns ``(R, O)``: ``R[..., i, :, :]`` is the rotation of frame i+1 and
    ``O[..., i, :]`` its origin (joint centre ``O_{i+1}``), plus the end point
    as ``O[..., 12, :]``.  Shapes (..., 12, 3, 3) and (..., 13, 3).  The base
    mounting (``model.base_rotation``, ``model.base_position``) is applied
    before Eq. (2); for the default description it is the identity.
    """
    alpha = np.asarray(alpha, dtype=float)
    theta = np.asarray(theta, dtype=float)
    n = model.n_joints
    if alpha.shape[-1:] != (n,) or theta.shape != alpha.shape:
        raise ValueError(
            f"alpha and theta must have shape (..., {n}), got {alpha.shape}, {theta.shape}"
        )
    Rj = joint_rotation(alpha, theta)  # (..., 12, 3, 3)
    batch = alpha.shape[:-1]
    if not batch:
        return _frames_one(model, Rj)
    R = np.empty((*batch, n, 3, 3))
    O = np.empty((*batch, n + 1, 3))
    prev = np.broadcast_to(model.base_rotation @ R_BASE_PAPER, (*batch, 3, 3))
    O[..., 0, :] = model.base_position
    for i in range(n):  # in place: no array allocated per joint
        np.matmul(prev, Rj[..., i, :, :], out=R[..., i, :, :])
        prev = R[..., i, :, :]
        np.add(O[..., i, :], prev[..., :, 2] * model.links[i], out=O[..., i + 1, :])
    return R, O


def _frames_one(model: RobotModel, Rj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`frames` of one configuration from its joint rotations (n, 3, 3): the
    products ``B Rj_1 ... Rj_i`` as a prefix product (Hillis-Steele: log2(n) batched
    products instead of n single ones; the same rotations to rounding), the origins as the
    cumulative sum of the links along each frame's z axis."""
    n = model.n_joints
    R = Rj
    R[0] = (model.base_rotation @ R_BASE_PAPER) @ Rj[0]
    s = 1
    while s < n:
        nxt = R.copy()
        np.matmul(R[:-s], R[s:], out=nxt[s:])
        R, s = nxt, 2 * s
    O = np.empty((n + 1, 3))
    O[0] = model.base_position
    np.cumsum(R[:, :, 2] * model.links[:, None], axis=0, out=O[1:])
    O[1:] += model.base_position
    return R, O


def joint_centres(model: RobotModel, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Joint centres O_1..O_12 and the end point O_13 (Eq. 4), shape (..., 13, 3).

    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> a = np.zeros(12); a[0] = np.pi / 2 * 0.5            # alpha_1 = 45 deg
    >>> O = joint_centres(m, a, np.zeros(12))
    >>> np.round(O[1], 3).tolist()                           # bends up (+z)
    [126.572, 0.0, 126.572]
    """
    return frames(model, alpha, theta)[1]


def end_point(model: RobotModel, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """End-effector point (Eq. 4), shape (..., 3)."""
    return joint_centres(model, alpha, theta)[..., -1, :]


def homogeneous_chain(model: RobotModel, alpha: np.ndarray, theta: np.ndarray) -> list[np.ndarray]:
    """``T_0^1 .. T_0^12`` as 4x4 matrices for one configuration, by the literal
    product of Eqs. (1)-(3) (slow; an independent check for tests and tools)."""
    T0 = np.eye(4)
    T0[:3, :3] = model.base_rotation
    T0[:3, 3] = model.base_position
    T = T0 @ base_transform(float(alpha[0]), float(theta[0]))
    out = [T]
    for i in range(1, model.n_joints):
        T = T @ joint_transform(float(alpha[i]), float(theta[i]), float(model.links[i - 1]))
        out.append(T)
    return out
