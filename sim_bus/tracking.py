"""How closely the simulated arm followed a plan: true joint centres against planned ones.

The simulated box records every drive's actual position after each SYNC
(:meth:`sim_bus.box.SimBox.trace`).  The drives reach cycle j's setpoint at the SYNC
after it (one cycle of drive lag), but a slot the host skipped when late, or a frame
a loaded transport lost, shifts the SYNC count of one bus.  So each bus's drives are
matched to the nearest setpoint row of the streamed table (moving forward only), and a
trace row is compared with the plan when every bus sat on the same setpoint row.
The lag (SYNCs between a setpoint and the trace row that sat on it) is reported, so
a matching that had to reach far ahead shows.

>>> import numpy as np
>>> table = np.arange(10)[:, None] * np.array([[1, 1]])        # two motors, one per bus
>>> counts = np.vstack(([0, 0], table[:-1]))                  # one cycle of lag
>>> rows, mixed = match_trace_to_table(table, counts, [np.array([0]), np.array([1])])
>>> rows[:4].tolist(), mixed
([[0, 0], [1, 0], [2, 1], [3, 2]], 0)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.ropes.actuation import Actuation

MATCH_WINDOW = 6  # setpoint rows a bus may move forward between two SYNCs


def match_trace_to_table(
    table: np.ndarray, counts: np.ndarray, bus_columns: Sequence[np.ndarray]
) -> tuple[np.ndarray, int]:
    """For each trace row i (actual counts after SYNC i), the setpoint row j every
    bus sat on; returns ``(rows (m, 2) of (i, j), number of rows where buses differed)``."""
    js = [0] * len(bus_columns)
    rows: list[tuple[int, int]] = []
    mixed = 0
    for i in range(counts.shape[0]):
        for b, c in enumerate(bus_columns):
            window = table[js[b] : js[b] + MATCH_WINDOW][:, c]
            if len(window) == 0:
                continue
            js[b] += int(np.argmin(np.abs(window - counts[i, c]).max(axis=1)))
        if len(set(js)) > 1:
            mixed += 1
        else:
            rows.append((i, js[0]))
    return np.array(rows, dtype=np.int64).reshape(-1, 2), mixed


@dataclass(frozen=True)
class Tracking:
    """Result of :func:`tracking_error` (mm, cycles)."""

    compared_cycles: int
    body_cycles: int
    mixed_cycles: int
    max_error_mm: float
    p99_error_mm: float
    median_lag_cycles: float
    p95_lag_cycles: float
    max_lag_cycles: int
    worst_joint: int  # 1-based joint centre (13 = end point)

    def to_dict(self) -> dict[str, float | int]:
        return {
            "compared_cycles": self.compared_cycles,
            "body_cycles": self.body_cycles,
            "mixed_cycles": self.mixed_cycles,
            "max_error_mm": self.max_error_mm,
            "p99_error_mm": self.p99_error_mm,
            "median_lag_cycles": self.median_lag_cycles,
            "p95_lag_cycles": self.p95_lag_cycles,
            "max_lag_cycles": self.max_lag_cycles,
            "worst_joint": self.worst_joint,
        }


def tracking_error(
    actuation: Actuation,
    table: np.ndarray,
    n_lead_in: int,
    planned_angles: tuple[np.ndarray, np.ndarray],
    counts: np.ndarray,
    bus_columns: Sequence[np.ndarray],
    settle_cycles: int = 5,
) -> Tracking:
    """Compare the true joint centres (the rope layer's inverse of the traced counts,
    then FK) with the planned ones (FK of ``planned_angles``, one row per cycle of the
    plan's body, which starts after ``n_lead_in`` rows of ``table``), skipping the
    first ``settle_cycles`` of drive lag."""
    alpha_p, theta_p = planned_angles
    n_body = alpha_p.shape[0]
    rows, mixed = match_trace_to_table(table, counts, bus_columns)
    keep = (rows[:, 1] >= n_lead_in + settle_cycles) & (rows[:, 1] < n_lead_in + n_body)
    rows = rows[keep]
    if len(rows) == 0:
        nan = float("nan")
        return Tracking(0, n_body, mixed, nan, nan, nan, nan, 0, 0)
    ti, tj = rows[:, 0], rows[:, 1]
    a, th, _res = actuation.angles_from_counts(counts[ti])
    true = joint_centres(actuation.robot, a, th)
    planned = joint_centres(actuation.robot, alpha_p[tj - n_lead_in], theta_p[tj - n_lead_in])
    err = np.linalg.norm(true - planned, axis=-1)  # (m, 13)
    worst = int(np.unravel_index(int(np.argmax(err)), err.shape)[1]) + 1
    lag = ti - tj  # SYNCs between a setpoint row and the trace row that sat on it
    return Tracking(
        compared_cycles=len(rows),
        body_cycles=n_body,
        mixed_cycles=mixed,
        max_error_mm=float(err.max()),
        p99_error_mm=float(np.percentile(err.max(axis=1), 99)),
        median_lag_cycles=float(np.median(lag)),
        p95_lag_cycles=float(np.percentile(lag, 95)),
        max_lag_cycles=int(lag.max()),
        worst_joint=worst,
    )
