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
    batch = alpha.shape[:-1]
    if not batch:
        return _frames_one(model, alpha, theta)
    Rj = joint_rotation(alpha, theta)  # (..., 12, 3, 3)
    R = np.empty((*batch, n, 3, 3))
    O = np.empty((*batch, n + 1, 3))
    prev = np.broadcast_to(model.base_rotation @ R_BASE_PAPER, (*batch, 3, 3))
    O[..., 0, :] = model.base_position
    for i in range(n):  # in place: no array allocated per joint
        np.matmul(prev, Rj[..., i, :, :], out=R[..., i, :, :])
        prev = R[..., i, :, :]
        np.add(O[..., i, :], prev[..., :, 2] * model.links[i], out=O[..., i + 1, :])
    return R, O


Rows9 = tuple[float, float, float, float, float, float, float, float, float]


def turned_by_joint(r: Rows9, c_a: float, s_a: float, c_t: float, s_t: float) -> Rows9:
    """``R Rot_y(alpha) Rot_x(theta)`` (:func:`joint_rotation`) for a rotation ``R`` given
    as its 9 entries row by row and the cosines and sines of the angles, on floats: one
    link of the chain for a single configuration, cheaper than a NumPy call.

    >>> R = turned_by_joint((1.0, 0, 0, 0, 1, 0, 0, 0, 1), np.cos(0.3), np.sin(0.3), 1.0, 0.0)
    >>> bool(np.allclose(np.reshape(R, (3, 3)), joint_rotation(np.array(0.3), np.array(0.0))))
    True
    """
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    sst, sct, cst, cct = s_a * s_t, s_a * c_t, c_a * s_t, c_a * c_t
    return (
        r00 * c_a - r02 * s_a,
        r00 * sst + r01 * c_t + r02 * cst,
        r00 * sct - r01 * s_t + r02 * cct,
        r10 * c_a - r12 * s_a,
        r10 * sst + r11 * c_t + r12 * cst,
        r10 * sct - r11 * s_t + r12 * cct,
        r20 * c_a - r22 * s_a,
        r20 * sst + r21 * c_t + r22 * cst,
        r20 * sct - r21 * s_t + r22 * cct,
    )


def base_rows(model: RobotModel) -> Rows9:
    """The rotation before joint 1's (the base mounting, then Eq. 2's fixed part) as
    :func:`turned_by_joint`'s 9 floats."""
    r = (model.base_rotation @ R_BASE_PAPER).ravel().tolist()
    return (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8])


def _frames_one(
    model: RobotModel, alpha: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`frames` of one configuration: the chain of Eq. (3) on floats
    (:func:`turned_by_joint`), as the online step evaluates a configuration a few times
    each control cycle."""
    ca, sa = np.cos(alpha).tolist(), np.sin(alpha).tolist()
    ct, st = np.cos(theta).tolist(), np.sin(theta).tolist()
    r = base_rows(model)
    ox, oy, oz = model.base_position.tolist()
    R: list[Rows9] = []
    O = [(ox, oy, oz)]
    for c_a, s_a, c_t, s_t, length in zip(ca, sa, ct, st, model.links.tolist(), strict=True):
        r = turned_by_joint(r, c_a, s_a, c_t, s_t)
        R.append(r)
        ox, oy, oz = ox + r[2] * length, oy + r[5] * length, oz + r[8] * length
        O.append((ox, oy, oz))
    return np.array(R).reshape(-1, 3, 3), np.array(O)


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
