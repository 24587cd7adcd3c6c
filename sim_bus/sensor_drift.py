"""Tension-sensor offset drift: each load cell's zero wanders as a random walk.

The offset of every sensor starts at 0 (the board tared at power-on) and takes, over a
step of ``dt`` seconds, an independent normal step of ``sigma sqrt(dt)`` (``sigma`` in
N per square-root second): after an hour its spread is ``60 sigma``.  The white noise
of each reading is the arm's ``noise_N`` (``sim_bus.arm``), on with or without it.

>>> rng = np.random.default_rng(0)
>>> d = np.zeros(10000)
>>> for _ in range(36):
...     d = drift_update(d, 0.2 / 60.0, 100.0, rng)
>>> round(float(d.std()), 2)                          # 3600 s: 0.2 N
0.2
"""

from __future__ import annotations

import math

import numpy as np


def drift_update(
    offset_N: np.ndarray, sigma_N_per_sqrt_s: float, dt_s: float, rng: np.random.Generator
) -> np.ndarray:
    """The sensors' offsets (n,) N after ``dt_s`` seconds of drift."""
    if dt_s <= 0.0 or sigma_N_per_sqrt_s <= 0.0:
        return offset_N
    return offset_N + rng.normal(0.0, sigma_N_per_sqrt_s * math.sqrt(dt_s), offset_N.shape)
