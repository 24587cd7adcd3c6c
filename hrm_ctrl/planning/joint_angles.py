"""Joint angles from joint centres by the closed-vector method, Sec. 3.4 (Eqs. 13-15).

For joint i, Eq. (15) reads ``(T_0^{i-1})^{-1} X_{i+1} = T_{i-1}^i (0, 0, l_i, 1)``: in
the frame before joint i's rotations, the unit link vector is
``v = Rot_y(alpha_i) Rot_x(theta_i) e_z = (sin a cos t, -sin t, cos a cos t)``, so

    theta_i = -asin(v_y),   alpha_i = atan2(v_x, v_z)

(unique with |theta| < 90 deg).  Joint 1 uses Eq. (13) with ``T_0^1`` of Eq. (2).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.kinematics import joint_centres
>>> m = default_robot()
>>> rng = np.random.default_rng(1)
>>> a, t = rng.uniform(-1, 1, 12), rng.uniform(-1, 1, 12)
>>> a2, t2 = joint_angles_from_centres(m, joint_centres(m, a, t))
>>> bool(np.allclose(a2, a) and np.allclose(t2, t))
True
"""

from __future__ import annotations

import math

import numpy as np

from hrm_ctrl.kinematics import R_BASE_PAPER, base_rows, joint_rotation, turned_by_joint
from hrm_ctrl.model import RobotModel


def joint_angles_from_centres(model: RobotModel, O: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, theta) of every joint from centres O_1..O_{n+1}, shape (..., n + 1, 3);
    returns two arrays of shape (..., n).  Vectorised over the leading axes."""
    O = np.asarray(O, dtype=float)
    n = model.n_joints
    batch = O.shape[:-2]
    if not batch:
        return _angles_one(model, O)
    alpha = np.empty((*batch, n))
    theta = np.empty((*batch, n))
    R = np.broadcast_to(model.base_rotation @ R_BASE_PAPER, (*batch, 3, 3))
    links = O[..., 1:, :] - O[..., :-1, :]
    dirs = links / np.linalg.norm(links, axis=-1, keepdims=True)
    for i in range(n):
        v = np.einsum("...ji,...j->...i", R, dirs[..., i, :])  # R^T d
        t = -np.arcsin(np.clip(v[..., 1], -1.0, 1.0))
        a = np.arctan2(v[..., 0], v[..., 2])
        alpha[..., i] = a
        theta[..., i] = t
        R = R @ joint_rotation(a, t)
    return alpha, theta


def _angles_one(model: RobotModel, O: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`joint_angles_from_centres` of one configuration (n + 1, 3): the same
    recursion on floats (:func:`~hrm_ctrl.kinematics.turned_by_joint`)."""
    links = np.diff(O, axis=0)
    dirs = (links / np.linalg.norm(links, axis=-1, keepdims=True)).tolist()
    r = base_rows(model)
    alpha, theta = [], []
    for dx, dy, dz in dirs:
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
        vx = r00 * dx + r10 * dy + r20 * dz  # R^T d
        vy = r01 * dx + r11 * dy + r21 * dz
        vz = r02 * dx + r12 * dy + r22 * dz
        t = -math.asin(min(max(vy, -1.0), 1.0))
        a = math.atan2(vx, vz)
        alpha.append(a)
        theta.append(t)
        r = turned_by_joint(r, math.cos(a), math.sin(a), math.cos(t), math.sin(t))
    return np.array(alpha), np.array(theta)
