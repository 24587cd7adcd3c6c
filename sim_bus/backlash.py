"""Backlash: play in each axis of the universal joints.

A joint axis with total play ``b`` may stand anywhere within ``+-b/2`` of where its
ropes hold it.  A gravity moment on the axis above ``torque_Nmm`` takes the play up on
its side; an axis without such a load keeps its place in the play while the ropes turn
it, until the play's end drags it along (the play operator: the link lags the motion).

>>> h = np.array([0.01, 0.01])
>>> backlash_update(np.zeros(2), np.array([0.05, 0.0]), np.array([0.0, -50.0]), h, 2.0).tolist()
[-0.005, -0.005]
"""

from __future__ import annotations

import numpy as np


def backlash_update(
    play_rad: np.ndarray,
    turned_rad: np.ndarray,
    gravity_Nmm: np.ndarray,
    backlash_rad: np.ndarray,
    torque_Nmm: float,
) -> np.ndarray:
    """Where each of the 24 axes (alpha_1, theta_1, ...) stands in its play (rad, physical
    minus rope-held angle) after the ropes turned them by ``turned_rad`` under the gravity
    moments ``gravity_Nmm``; ``backlash_rad`` (24,) the total play of each axis."""
    half = 0.5 * backlash_rad
    dragged = np.clip(play_rad - turned_rad, -half, half)
    loaded = np.abs(gravity_Nmm) > torque_Nmm
    return np.where(loaded, np.sign(gravity_Nmm) * half, dragged)
