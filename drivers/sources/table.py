"""What every setpoint source is (:class:`SetpointSource`), a source playing a
precomputed table (:class:`TableSource`), and the check of a table against the motors'
limits before anything of it is sent (:func:`check_table`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from drivers.rope_model import MotorLimits
from drivers.safety.limits import (
    SetpointError,
    acceleration_text,
    first_too_hard,
    first_too_jerky,
    jerk_text,
)
from hrm_ctrl.errors import HrmError


class SetpointSource(Protocol):
    """A stream of setpoints (counts, the rope layer's motor order), one per control
    slot: checked (:meth:`precheck`) before the drives are asked for anything, started
    from the drives' actual positions, then asked for slot ``k`` = 0, 1, ... until it
    gives ``None``."""

    name: str

    def precheck(self, period_s: float) -> None: ...

    def start(self, actual_counts: np.ndarray, period_s: float) -> None: ...

    def setpoint(self, k: int) -> np.ndarray | None: ...

    @property
    def n_cycles(self) -> int:
        """Control slots the source asks for at most (known once started)."""
        ...

    def describe(self) -> dict[str, Any]: ...


class TabledSource(SetpointSource, Protocol):
    """A source whose whole table is known once it is started (what a pausable playback
    plays at its own rate: :class:`~drivers.sources.pausable.PausableSource`)."""

    table: np.ndarray


class TableSource:
    """Setpoints from a precomputed (cycles, motors) table, after ``start``."""

    name = "table"

    def __init__(self) -> None:
        self.table: np.ndarray = np.zeros((0, 0), dtype=np.int64)

    def precheck(self, period_s: float) -> None:
        """Refuse what can be refused before the actual positions are known."""

    def setpoint(self, k: int) -> np.ndarray | None:
        if k >= self.table.shape[0]:
            return None
        return self.table[k]

    @property
    def n_cycles(self) -> int:
        return int(self.table.shape[0])

    def describe(self) -> dict[str, Any]:
        return {"source": self.name, "cycles": self.n_cycles}


LabelOfRow = Callable[[int], str] | Sequence[str]


def row_name(label: LabelOfRow | None, row: int) -> str:
    """A body row as a message names it: by its label (a plan step), else as the control
    cycle of the table it is.

    >>> row_name(None, 3), row_name(["a", "b"], 1), row_name(lambda r: f"step {7 * r}", 2)
    ('cycle 3', 'b', 'step 14')
    """
    if label is None:
        return f"cycle {row}"
    return label(row) if callable(label) else str(label[row])


def check_table(
    limits: MotorLimits,
    table: np.ndarray,
    period_s: float,
    name_of_row: Callable[[int], str],
    what: str,
    previous: np.ndarray | None = None,
) -> None:
    """``limits.check_counts`` of a (rows, motors) table at the control period, every
    second difference within the motors' acceleration and every third difference within
    their jerk (from rest at ``previous`` when given: the drives hold it), the first
    offending row named by ``name_of_row(row)`` (:class:`SetpointError`, one line).

    >>> class Lim:
    ...     counts_min = np.array([-10]); counts_max = np.array([10])
    ...     max_rate_counts_per_s = np.array([1e9]); motor_ids = ("m0",)
    ...     max_accel_counts_per_s2 = max_jerk_counts_per_s3 = None
    ...     def motor_label(self, i): return self.motor_ids[i]
    ...     def check_counts(self, counts, previous=None, dt_s=None):
    ...         if np.any(np.abs(counts) > 10): raise SetpointError("m0 outside [-10, 10]")
    >>> check_table(Lim(), np.array([[0], [11]]), 0.01, lambda r: f"plan step {7 * r}", "plan")
    Traceback (most recent call last):
    ...
    drivers.safety.limits.SetpointError: plan: plan step 7: m0 outside [-10, 10]
    """
    whole: HrmError | None = None
    try:
        limits.check_counts(table, previous=previous, dt_s=period_s)
    except HrmError as exc:
        whole = exc
    hard = first_too_hard(limits, table, period_s, previous)
    jerky = first_too_jerky(limits, table, period_s, previous)
    if jerky is not None and (hard is None or jerky[0] < hard[0]):
        hard = jerky  # the first row past a limit of the motions' derivatives
        hard_text = jerk_text(limits, jerky[1], jerky[2])
    elif hard is not None:
        hard_text = acceleration_text(limits, hard[1], hard[2])
    if whole is None and hard is None:
        return
    n = table.shape[0]
    lo = np.asarray(limits.counts_min)
    hi = np.asarray(limits.counts_max)
    out = np.flatnonzero(((table < lo) | (table > hi)).any(axis=1))
    seq = table if previous is None else np.vstack([np.asarray(previous)[None, :], table])
    rate = np.abs(np.diff(seq.astype(np.float64), axis=0)) / period_s
    fast = np.flatnonzero((rate > np.asarray(limits.max_rate_counts_per_s)).any(axis=1))
    first_fast = int(fast[0]) + (1 if previous is None else 0) if fast.size else n
    first_out = int(out[0]) if out.size else n
    first_hard = hard[0] if hard is not None else n
    r = min(first_out, first_fast, first_hard)
    if r >= n:  # the checker refused for another reason: say so as it did
        raise SetpointError(f"{what}: {whole}") from None
    if r not in (first_out, first_fast) and hard is not None:
        raise SetpointError(f"{what}: {name_of_row(r)}: {hard_text}")
    try:
        if r == first_out:
            limits.check_counts(table[r])
        else:
            prev = seq[r - 1] if previous is None else seq[r]
            limits.check_counts(table[r], previous=prev, dt_s=period_s)
    except HrmError as exc:
        raise SetpointError(f"{what}: {name_of_row(r)}: {exc}") from None
    raise SetpointError(f"{what}: {name_of_row(r)}: {whole}")
