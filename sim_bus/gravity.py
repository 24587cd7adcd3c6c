"""Gravity on the simulated arm: the generalised forces of link masses and a tip payload.

Each link's mass sits at its middle, between joint centres ``O_i`` and ``O_{i+1}``; the
payload at the end point ``O_13``.  With gravity ``g`` (N/kg, base frame), the generalised
force on a joint angle whose axis is the unit vector ``a`` through the joint centre ``O_j``
is the moment of every weight beyond the joint about that axis,

    Q = a . sum_{i >= j} (c_i - O_j) x m_i g        (N mm: masses in kg, positions in mm)

with the alpha axis of joint j the y axis of the frame before the joint and the theta
axis the x axis after alpha (``hrm_ctrl.kinematics``: ``Rot_y(alpha) Rot_x(theta)``).
Columns ordered (alpha_1, theta_1, alpha_2, ...), as the rope layer's Jacobian.

>>> from hrm_ctrl.model import default_robot
>>> m = default_robot()
>>> mass = np.zeros(12); mass[11] = 1.0               # 1 kg on link 12 only
>>> Q = gravity_forces(m, np.zeros(12), np.zeros(12), mass, 0.0, np.array([0, 0, -9.81]))
>>> round(float(Q[22]), 3), round(9.81 * float(m.links[11]) / 2, 3)   # alpha_12 pulled down
(-667.08, 667.08)
>>> bool(np.allclose(Q[1::2], 0.0))                   # no theta moment: the arm lies level
True
"""

from __future__ import annotations

import numpy as np

from hrm_ctrl.kinematics import R_BASE_PAPER, frames
from hrm_ctrl.model import RobotModel


def gravity_forces(
    model: RobotModel,
    alpha: np.ndarray,
    theta: np.ndarray,
    link_mass_kg: np.ndarray,
    payload_kg: float,
    gravity_N_per_kg: np.ndarray,
) -> np.ndarray:
    """Generalised gravity forces (24,) N mm on the physical joint angles (12,) each."""
    R, O = frames(model, alpha, theta)  # (12, 3, 3), (13, 3)
    centres = 0.5 * (O[:-1] + O[1:])  # link middles (12, 3)
    moment = link_mass_kg[:, None] * centres  # (12, 3) kg mm
    moment[-1] += payload_kg * O[-1]
    mass_beyond = np.cumsum(link_mass_kg[::-1])[::-1] + payload_kg  # (12,)
    moment_beyond = np.cumsum(moment[::-1], axis=0)[::-1]  # (12, 3)
    lever = moment_beyond - mass_beyond[:, None] * O[:-1]  # sum m_i (c_i - O_j)
    torque = np.cross(lever, gravity_N_per_kg)  # (12, 3) N mm
    before = np.empty_like(R)
    before[0] = model.base_rotation @ R_BASE_PAPER
    before[1:] = R[:-1]
    ca, sa = np.cos(alpha), np.sin(alpha)
    # the theta axis: x of (frame before) Rot_y(alpha) = before @ (cos a, 0, -sin a)
    axis_theta = before[:, :, 0] * ca[:, None] - before[:, :, 2] * sa[:, None]
    Q = np.empty(2 * len(link_mass_kg))
    Q[0::2] = np.einsum("ja,ja->j", torque, before[:, :, 1])
    Q[1::2] = np.einsum("ja,ja->j", torque, axis_theta)
    return Q
