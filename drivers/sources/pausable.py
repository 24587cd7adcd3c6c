"""Pause, resume and abort: a table source played at a variable rate along its own path
(:class:`PausableSource`), so that the operator can stop it on the path and go on."""

from __future__ import annotations

import math
from enum import Enum
from typing import Any

import numpy as np

from drivers.rope_model import MotorLimits
from drivers.safety.limits import SetpointError, accel_limits, jerk_limits, jerk_limits_of
from drivers.sources.moves import cubic_at, slowed_table
from drivers.sources.table import TabledSource

PAUSE_RAMP_S = 0.5  # a pause or a resume changes the playback rate by 1 in about this long
MAX_PAUSE_S = 600.0  # a run paused longer in all than this is aborted (at rest: at once)
MAX_PLAYED_ROWS = 360_000  # setpoints a pausable source keeps for a way back (1 h at 100 Hz)
MAX_OFF_PATH_COUNTS = 2.0  # a setpoint may leave the interpolated path by this much (rounding)
# the share of a motor's jerk a change of the playback rate's own change may take (the
# fastest row of the table times the change of the rate per cycle, per cycle)
JERK_RATE_SHARE = 0.5


class PlayState(Enum):
    """Where a :class:`PausableSource` is (its operator's view)."""

    PLAYING = "playing"
    PAUSING = "pausing"
    PAUSED = "paused"
    RESUMING = "resuming"
    ABORTING = "aborting"
    ABORTED = "aborted"
    DONE = "done"


class PausableSource:
    """A table source (e.g. :class:`~drivers.sources.counts.CountsSource`) played at a
    variable rate along its own path, so that the operator can pause, resume and abort
    it: :meth:`pause` slows the playback down to rest (the arm stops *on the path*,
    every rope consistent), :meth:`resume` speeds it up again, :meth:`abort` stops it on
    the path and then ends the stream.  Thread-safe: the requests come from another
    thread than the control loop's (keyboard, console); each is one assignment the loop
    reads.

    Every cycle the playback position ``s`` (a fractional row of the inner table)
    advances by the rate ``r`` (rows per cycle, about 0..1) and the setpoint is the table
    linearly interpolated at ``s``, rounded, and kept within the window of setpoints the
    supervisor accepts (speed from the last setpoint, second difference against the
    acceleration limit, in its own terms) by at most :data:`MAX_OFF_PATH_COUNTS` (the
    rounding of a table that brakes at a motor's limit).  The rate moves toward its target
    by at most ``period_s / ramp_s`` a cycle, by less (or not at all that cycle) where
    that would leave the path further, so a pause waits for a point of the table that
    lets it slow down.  At rate 1 on whole rows the setpoints are the inner table's rows.
    With jerk limits, on a table fast enough to need it, the rate's own change also
    changes by at most ``JERK_RATE_SHARE`` of the smallest jerk limit over the table's
    largest row step a cycle (braked in time to reach its target), the path between rows
    is a cubic (:func:`~drivers.sources.moves.cubic_at`, no kink at a row) and the rate is
    not capped below 1 off whole rows; this eases the jerk without a window of its own
    (at a tenth of the motors' speed every third difference keeps the limit; at 90 % of
    their speed and acceleration it can reach about 1.5 times it).

    >>> from drivers.safety.subset import ActuationSubset
    >>> from drivers.sources.counts import CountsSource
    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> class Lim:
    ...     motor_ids = ("m0",); max_rate_counts_per_s = np.array([1e4])
    ...     max_accel_counts_per_s2 = np.array([1e6]); counts_min = np.array([-10**6])
    ...     counts_max = np.array([10**6]); max_jerk_counts_per_s3 = None
    ...     def motor_label(self, i): return self.motor_ids[i]
    ...     def check_counts(self, counts, previous=None, dt_s=None): pass
    >>> j01r0 = ActuationSubset(load_actuation(default_robot()), ("j01r0",))
    >>> body = np.arange(0, 2001, 20).reshape(-1, 1)  # 20 counts a cycle
    >>> src = PausableSource(CountsSource(j01r0, body, 0.01, hold_s=0.0), Lim(), ramp_s=0.1)
    >>> src.start(np.array([0]), 0.01)
    >>> out = [src.setpoint(k) for k in range(30)]
    >>> src.pause()
    >>> out += [src.setpoint(k) for k in range(30, 80)]
    >>> src.state.value, int(out[-1][0]) == int(out[-2][0])
    ('paused', True)
    >>> src.resume()
    >>> k = 80
    >>> while (p := src.setpoint(k)) is not None: out.append(p); k += 1
    >>> src.state.value, int(out[-1][0])
    ('done', 2000)
    >>> d2 = np.diff(np.array([[0], [0]] + out)[:, 0], 2)
    >>> bool((np.abs(d2) <= 1e6 * 0.01**2).all())
    True
    """

    name = "pausable"

    def __init__(
        self,
        inner: TabledSource,
        limits: MotorLimits,
        *,
        ramp_s: float = PAUSE_RAMP_S,
        max_pause_s: float = MAX_PAUSE_S,
    ) -> None:
        if not (math.isfinite(ramp_s) and ramp_s > 0):
            raise SetpointError(f"pause ramp must be > 0 s, got {ramp_s}")
        if not (math.isfinite(max_pause_s) and max_pause_s >= 0):
            raise SetpointError(f"longest pause must be >= 0 s, got {max_pause_s}")
        self.max_pause_s = float(max_pause_s)
        self._period_s = math.nan  # the control period (set by start)
        self.paused_cycles = 0
        self.abort_reason: str | None = None
        self.inner = inner
        self.name = inner.name
        self.limits = limits
        self.ramp_s = float(ramp_s)
        self._target = 1.0
        self._abort = False
        self.state = PlayState.PLAYING
        self.position = 0.0  # fractional row of the inner table (read by the console)
        self.rate = 1.0
        self.held_cycles = 0  # cycles the rate could not move toward its target
        self._table = np.zeros((0, 0), dtype=np.int64)
        self._k = -1
        self._out: np.ndarray | None = None
        self._played: list[np.ndarray] = []
        self.played_complete = True  # False: more than MAX_PLAYED_ROWS, no way back kept

    # the operator's requests (any thread)
    # The requests only set the target rate (and the abort flag, set before the target:
    # the loop never sees a target of 0 from an abort without the flag); the loop's thread
    # alone writes ``state``, from the target and where the playback is.
    def pause(self) -> None:
        """Slow down to rest on the path (no-op once aborting or done)."""
        if not self._abort and self.state is not PlayState.DONE:
            self._target = 0.0

    def resume(self) -> None:
        """Speed up again after :meth:`pause` (no-op once aborting)."""
        if not self._abort:
            self._target = 1.0

    def abort(self, reason: str = "aborted by the operator") -> None:
        """Stop on the path, then end the stream (the rest of the table is not played)."""
        if not self._abort and self.state not in (PlayState.ABORTED, PlayState.DONE):
            self.abort_reason = reason
            self._abort = True
            self._target = 0.0

    @property
    def requested(self) -> str:
        """What was asked last: ``play``, ``pause`` or ``abort`` (the keys' toggle)."""
        return "abort" if self._abort else "pause" if self._target == 0.0 else "play"

    # the source protocol (the control loop's thread)
    def precheck(self, period_s: float) -> None:
        self.inner.precheck(period_s)

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.inner.start(actual_counts, period_s)
        self._table = np.asarray(self.inner.table, dtype=np.int64)
        self._period_s = float(period_s)
        self._actual = np.asarray(actual_counts, dtype=np.int64)
        self._v = np.asarray(self.limits.max_rate_counts_per_s, np.float64)
        acc = accel_limits(self.limits, fallback=False)
        self._a = None if acc is None else np.asarray(acc, np.float64)
        self._dr = period_s / self.ramp_s
        # the highest rate off whole rows (see _candidates): 6 counts of room below the
        # smallest acceleration limit's second difference
        a_min = math.inf if self._a is None else float(np.min(self._a)) * period_s**2
        self._cap = 1.0 if not math.isfinite(a_min) else max(0.5, 1.0 - 6.0 / a_min)
        # the jerk: a window of third differences, and the rate's change changing by at
        # most _ddr a cycle (none where the table is slow enough not to need it)
        jerk = jerk_limits_of(self.limits)
        self._j = None if jerk is None else np.asarray(jerk, np.float64)
        self._ddr = math.inf
        if self._j is not None and self._table.shape[0] > 1:
            step = float(np.max(np.abs(np.diff(self._table, axis=0))))
            ddr = JERK_RATE_SHARE * float(np.min(self._j)) * period_s**3 / max(step, 1.0)
            self._ddr = ddr if ddr < 2.0 * self._dr else math.inf
        self._drate = 0.0
        self.position, self.rate, self._k, self._out = 0.0, 1.0, -1, None
        self._prev = self._before = self._actual
        self._played = [self._actual.astype(np.int32)]
        self.played_complete = True

    @property
    def n_cycles(self) -> int:
        """Cycles at most: at full rate, plus the longest pause and two ramps (what the
        session's wait for the stream's end allows for)."""
        rows = int(self._table.shape[0]) if self._table.size else self.inner.n_cycles
        period_s = self._period_s if math.isfinite(self._period_s) else 0.01  # not started
        extra = (self.max_pause_s + 2 * self.ramp_s) / period_s
        return rows + math.ceil(extra)

    @property
    def paused_s(self) -> float:
        """How long the playback stood paused, in all (s)."""
        return round(self.paused_cycles * self._period_s, 3) if self.paused_cycles else 0.0

    @property
    def n_rows(self) -> int:
        return int(self._table.shape[0])

    def _at(self, s: float) -> np.ndarray:
        i = min(math.floor(s), self._table.shape[0] - 1)
        f = s - i
        if f <= 0.0 or i + 1 >= self._table.shape[0]:
            return self._table[i]
        a, b = self._table[i], self._table[i + 1]
        return np.rint(a + f * (b - a).astype(np.float64)).astype(np.int64)

    def setpoint(self, k: int) -> np.ndarray | None:
        if k == self._k:
            return self._out
        n = self._table.shape[0]
        if n == 0:
            return None
        if k == 0:
            out: np.ndarray | None = self._table[0]
        elif self.state in (PlayState.ABORTED, PlayState.DONE):
            out = None
        else:
            out = self._advance(n)
        if out is not None:
            self._before, self._prev = self._prev, out
            if len(self._played) < MAX_PLAYED_ROWS:
                self._played.append(np.asarray(out, dtype=np.int32))
            else:
                self.played_complete = False
        self._k, self._out = k, out
        return out

    def way_back(self) -> np.ndarray:
        """The setpoints played so far, backwards (from where the arm stands, at rest, to
        where it started), with every stretch at rest shortened to two rows: the table of
        a return along the same path (a speed, second or third difference reversed is the
        same size).  Where what was played breaks a motor's jerk limit (a pause's rate
        ramp is limited in speed and acceleration only), the way back is played slower,
        at one uniform rate, until it keeps the motors' speed, acceleration and jerk
        (:func:`~drivers.sources.moves.slowed_table`).  Empty when nothing was played or
        more than :data:`MAX_PLAYED_ROWS` were (no way back kept)."""
        if not self.played_complete or len(self._played) < 2:
            return np.zeros((0, self._table.shape[1] if self._table.ndim == 2 else 0), np.int64)
        rows = np.array(self._played, dtype=np.int64)
        same = np.all(rows[1:] == rows[:-1], axis=1)
        keep = np.ones(len(rows), dtype=bool)
        keep[2:] = ~(same[1:] & same[:-1])  # a row equal to the two before it goes
        back = rows[keep][::-1].copy()
        acc = accel_limits(self.limits)
        assert acc is not None  # with the fallback there always is one
        return slowed_table(back, self._period_s, np.asarray(self.limits.max_rate_counts_per_s),
                            acc, jerk_limits(self.limits), f"{self.name}: way back")  # fmt: skip

    def _candidates(self, target: float) -> tuple[int, np.ndarray]:
        """Rates to try this cycle: first choices (the rate a nominal step toward the
        target gives; near full rate the one that lands on a whole row, the table itself
        from then on), then rates around the current one, finer and finer.  Off whole rows
        the rate stays at most ``_cap`` (a little below 1): there the table's own second
        difference, interpolated, is at most the rate times the motor's limit, and the
        room left takes the rounding."""
        r0, dr, s = self.rate, self._dr, self.position
        whole = s == math.floor(s)
        cap = self._cap
        gap = target - r0
        eased = math.isfinite(self._ddr)
        if eased:  # the rate's change eased, braking toward the target
            ddr = self._ddr
            brake = ddr * (math.sqrt(2.0 * abs(gap) / ddr + 0.25) - 0.5)  # stops in time
            d = math.copysign(min(dr, abs(gap), brake), gap)
            lo_d, hi_d = self._drate - ddr, self._drate + ddr
            want = r0 + max(lo_d, min(hi_d, d))
            # no step down to the cap and back: the window alone keeps the acceleration
            # (a first choice it does not take falls back to the rates below); near full
            # rate off whole rows a hair below it, so that a whole row comes (the snap)
            cap = 1.0 if whole else 1.0 - 0.5 * ddr
            up = whole and target == 1.0 and r0 >= 1.0 - 1.5 * ddr
        else:
            want = r0 + max(-dr, min(dr, gap))
            up = whole and target == 1.0 and want > cap and r0 >= 1.0 - dr
        first = [1.0 if up else min(cap, max(0.0, want))]
        if target == 1.0 and not whole and r0 >= cap - dr:
            snap = math.ceil(s) - s
            if eased:
                if lo_d <= snap - r0 <= hi_d and r0 >= 1.0 - 2.0 * ddr:
                    first.insert(0, snap)
            elif r0 - dr <= snap <= min(1.0, r0 + dr):
                first.insert(0, snap)
        rest = np.concatenate([r0 + np.linspace(-w, w, 33) for w in (dr, dr / 16, dr / 256)])
        rest = rest[(rest >= 0.0) & (rest <= self._cap)]
        if whole and r0 == 1.0:
            rest = np.concatenate([[1.0], rest])
        return len(first), np.concatenate([np.array(first), rest])

    def _advance(self, n: int) -> np.ndarray | None:
        end = float(n - 1)
        if self.position >= end and self._target == 1.0:
            self.state = PlayState.DONE
            return None
        target = self._target
        pos = self.position
        if target == self.rate == 0.0 and self.state is PlayState.PAUSED and not self._abort:
            x = self._prev  # at rest on the path: nothing to compute
            rates, c = np.array([0.0]), 0
        elif target == self.rate == 1.0 and pos == math.floor(pos):
            # playing the table as it is: its next row (checked against the window)
            x = self._table[min(int(pos) + 1, n - 1)]
            lo, hi = self._window()
            rates, c = np.array([1.0]), 0
            if not ((x >= lo) & (x <= hi)).all():  # cannot happen for a checked table
                raise SetpointError(f"{self.name}: row {int(pos) + 1} outside the limits")
        else:
            n_first, rates = self._candidates(target)
            # the first choices alone first (most cycles: one row of the table)
            xs, over = self._try(rates[:n_first], end, n)
            ok = np.flatnonzero(over <= 0.0)
            if ok.size:
                c = int(ok[0])
            else:
                xs, over = self._try(rates, end, n)
                ok = np.flatnonzero(over <= 0.0)
                if ok.size == 0:
                    c = int(np.argmin(over))
                else:  # the feasible rate nearest to the nominal step
                    c = int(ok[np.argmin(np.abs(rates[ok] - rates[n_first - 1]))])
            x = xs[c]
        r = float(rates[c])
        if r == self.rate and r != target:
            self.held_cycles += 1
        self._drate = r - self.rate
        self.rate = r
        self.position = min(end, self.position + r)
        aborting = self._abort
        if r == 0.0 and target == 0.0 and np.array_equal(x, self._prev):
            self.paused_cycles += 1
            if self.paused_cycles * self._period_s > self.max_pause_s and not aborting:
                self.abort(f"paused longer than {self.max_pause_s:g} s")
                aborting = True
            self.state = PlayState.ABORTED if aborting else PlayState.PAUSED
        elif target == 0.0:
            self.state = PlayState.ABORTING if aborting else PlayState.PAUSING
        elif r >= 1.0:
            self.state = PlayState.PLAYING
        else:
            self.state = PlayState.RESUMING
        return x

    def _try(self, rates: np.ndarray, end: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Candidate setpoints at ``rates`` (the path interpolated, rounded, kept within
        the supervisor's window) and how far each had to leave the path beyond
        :data:`MAX_OFF_PATH_COUNTS` (<= 0: acceptable)."""
        s_new = np.minimum(end, self.position + rates)
        i = np.minimum(np.floor(s_new).astype(np.int64), n - 1)
        j = np.minimum(i + 1, n - 1)
        t = self._table
        if self._j is None:  # a straight line between rows
            f = (s_new - i)[:, None]
            path = t[i] + f * (t[j] - t[i]).astype(np.float64)
        else:  # a cubic: no kink at a row for a third difference to see
            path = cubic_at(t, s_new)
        lo, hi = self._window()
        xs = np.clip(np.rint(path).astype(np.int64), lo, hi)
        over = np.max(np.abs(xs - path), axis=1) - MAX_OFF_PATH_COUNTS
        if not (lo <= hi).all():  # no setpoint within the limits at all (not for a table)
            over[:] = np.inf
        return xs, over

    def _window(self) -> tuple[np.ndarray, np.ndarray]:
        """The integer setpoints of each motor the supervisor accepts next: the speed from
        the last setpoint and the second difference within the motors' limits (checked in
        the supervisor's own terms, counts/s and counts/s^2)."""
        T = self._period_s
        prev, before = self._prev, self._before
        v = np.floor(self._v * T).astype(np.int64)
        v -= (v.astype(np.float64) / T > self._v).astype(np.int64)
        lo, hi = prev - v, prev + v
        if self._a is not None:
            A = np.floor(self._a * T**2).astype(np.int64)
            A -= (A.astype(np.float64) / T**2 > self._a).astype(np.int64)
            mid = 2 * prev - before
            lo, hi = np.maximum(lo, mid - A), np.minimum(hi, mid + A)
        lo = np.maximum(lo, np.asarray(self.limits.counts_min, dtype=np.int64))
        hi = np.minimum(hi, np.asarray(self.limits.counts_max, dtype=np.int64))
        return lo, hi

    def describe(self) -> dict[str, Any]:
        d = dict(self.inner.describe())
        d.update(
            pausable=True,
            play_state=self.state.value,
            stopped_at_row=round(self.position, 3),
            paused_s=self.paused_s,
            abort_reason=self.abort_reason,
            rows=self.n_rows,
        )
        return d
