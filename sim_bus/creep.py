"""Rope creep: a rope under tension lengthens slowly, so its pretension creeps away.

Each rope's creep ``c`` (mm of unstretched length added) relaxes towards
``fraction (T / T0) u T0 / EA``, a share of the rope's pretension stretch scaled by its
tension, with time constant ``tau`` (first order, integrated exactly over each step):

    c(t + dt) = c_inf + (c(t) - c_inf) e^(-dt / tau)

Held at a fixed length, a rope so loses ``fraction / (1 + fraction)`` of its pretension in
the long run, ``1 - e^(-(1 + fraction) t / tau)`` of that by time t (to first order in the
stretch).

>>> c = creep_update(np.zeros(1), np.array([30.0]), 30.0, np.array([1000.0]),
...                  np.array([30000.0]), 0.1, 1200.0, 1.0e9)
>>> round(float(c[0]), 6)                              # 10 % of the 1 mm pretension stretch
0.1
"""

from __future__ import annotations

import math

import numpy as np


def creep_update(
    creep_mm: np.ndarray,
    tension_N: np.ndarray,
    pretension_N: float,
    unstretched_mm: np.ndarray,
    EA_N: np.ndarray,
    fraction: float,
    time_s: float,
    dt_s: float,
) -> np.ndarray:
    """The ropes' creep (n,) mm after ``dt_s`` at ``tension_N`` (see the module docstring)."""
    target = fraction * (tension_N / EA_N) * unstretched_mm
    return target + (creep_mm - target) * math.exp(-max(dt_s, 0.0) / time_s)
