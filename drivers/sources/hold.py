"""Hold: the actual positions (or given counts) for a number of control cycles."""

from __future__ import annotations

import numpy as np

from drivers.safety.limits import MAX_SOURCE_DURATION_S, SetpointError, check_duration
from drivers.sources.table import TableSource


class HoldSource(TableSource):
    """Hold the actual positions (or given counts) for ``n_cycles`` (None: 1 h).

    >>> src = HoldSource(n_cycles=2)
    >>> src.start(np.array([5, -5]), 0.01)
    >>> [src.setpoint(k) for k in range(3)], src.n_cycles
    ([array([ 5, -5]), array([ 5, -5]), None], 2)
    """

    name = "hold"

    def __init__(self, n_cycles: int | None = None, counts: np.ndarray | None = None) -> None:
        super().__init__()
        self.n_cycles_wanted = n_cycles
        self.counts = None if counts is None else np.asarray(counts, dtype=np.int64)
        self._hold = np.zeros(0, dtype=np.int64)
        self._n = 0  # cycles to hold (set by start)

    def precheck(self, period_s: float) -> None:
        if self.counts is not None and self.counts.ndim != 1:
            raise SetpointError("hold: counts must be one value per motor")
        if self.n_cycles_wanted is not None:
            check_duration("hold", self.n_cycles_wanted * period_s, period_s)

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.precheck(period_s)
        hold = np.asarray(actual_counts if self.counts is None else self.counts, dtype=np.int64)
        n = (
            self.n_cycles_wanted
            if self.n_cycles_wanted is not None
            else int(MAX_SOURCE_DURATION_S / period_s)
        )
        self._hold = hold
        self._n = int(n)

    def setpoint(self, k: int) -> np.ndarray | None:
        return self._hold if k < self._n else None

    @property
    def n_cycles(self) -> int:
        return self._n
