"""Pause, resume and abort: a table source played at a variable rate along its own path
(:class:`PausableSource`), so that the operator can stop it on the path and go on."""

from __future__ import annotations

import math
from enum import Enum
from typing import Any

import numpy as np

from drivers.rope_model import MotorLimits
from drivers.safety.limits import SetpointError, accel_limits, jerk_limits, jerk_limits_of
from drivers.safety.ramps import jerk_window
from drivers.sources.moves import cubic_at, slowed_table
from drivers.sources.table import TabledSource

PAUSE_RAMP_S = 0.5  # a pause or a resume changes the playback rate by 1 in about this long
MAX_PAUSE_S = 600.0  # a run paused longer in all than this is aborted (at rest: at once)
MAX_PLAYED_ROWS = 360_000  # setpoints a pausable source keeps for a way back (1 h at 100 Hz)
MAX_OFF_PATH_COUNTS = 2.0  # a setpoint may leave the interpolated path by this much (rounding)
# a third difference of rounded setpoints is off the path's by at most this (counts)
ROUNDING_JERK_COUNTS = 4


def whole_counts(limit: np.ndarray, period_s: float, power: int) -> np.ndarray:
    """A limit in counts per second (squared, cubed: ``power``) as the largest whole
    counts per period (squared, cubed) that, divided back, does not exceed it.

    >>> whole_counts(np.array([4.096e7]), 0.01, 3).tolist()
    [40]
    """
    t = period_s**power
    c = np.floor(np.asarray(limit, np.float64) * t).astype(np.int64)
    return c - (c.astype(np.float64) / t > limit).astype(np.int64)


def rate_limits(table: np.ndarray, jerk_counts: np.ndarray, dr: float) -> tuple[float, float]:
    """How fast the playback rate ``r`` of ``table`` (rows per period) may change (``dr``
    at most, a period) and its change change (the second return, a period) so that the
    third difference of the played setpoints keeps each motor's jerk ``jerk_counts``
    (whole counts per period cubed).  Played at ``s(t)``, a motor's third difference is
    about ``q3 r^3 + 3 q2 r dr + q1 ddr`` (``q1, q2, q3`` the table's first, second, third
    differences): the table's own (``r <= 1``) and the rounding's take their share, the
    rest is split evenly between the rate's change and its change's change.

    >>> t = np.cumsum(np.cumsum(np.r_[0, 0, 2, 2, 0, -2, -2, 0, 0])).reshape(-1, 1) * 10
    >>> dr, ddr = rate_limits(t, np.array([40]), 0.05)
    >>> round(dr, 4), round(ddr, 5)
    (0.05, 0.2)
    """
    rows = np.asarray(table, dtype=np.int64)
    d1 = np.abs(np.diff(rows, axis=0)).max(axis=0)
    d2 = np.abs(np.diff(rows, n=2, axis=0)).max(axis=0)
    d3 = np.abs(np.diff(rows, n=3, axis=0)).max(axis=0)
    share = np.maximum(np.asarray(jerk_counts) - d3 - ROUNDING_JERK_COUNTS, 1) / 2.0
    dr = min(dr, float(np.min(share / (3.0 * np.maximum(d2, 1)))))
    return dr, float(np.min(share / np.maximum(d1, 1)))


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
    With jerk limits the window also keeps every motor's third difference and a speed
    from which its acceleration can be eased off in time
    (:func:`~drivers.safety.ramps.jerk_window`), the path between rows is a cubic
    (:func:`~drivers.sources.moves.cubic_at`, no kink at a row), the rate is not capped
    below 1 off whole rows, and the rate's change and its change's change are bounded by
    what the table's own differences leave of the jerk (:func:`rate_limits`; the change
    braked in time to reach its target): a pause of a fast table takes longer than
    ``ramp_s`` (:attr:`ramp_cycles`).  Where no rate keeps both the path and the jerk
    window (a table at the motors' acceleration limit and near their jerk limit), the
    setpoint keeps the path within speed and acceleration, with the least jerk, and the
    cycle is counted (:attr:`jerk_relaxed_cycles`): at a tenth of the motors' speed, and
    along the bent pipe at up to 500 mm/s, every third difference keeps the limit; at
    90 % of their speed, at their acceleration limit and 80 % of their jerk, it reached
    1.32 times it.

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
        self.jerk_relaxed_cycles = 0  # cycles sent within speed and acceleration alone
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
        self._drate = 0.0
        # the window's limits in whole counts per period (squared, cubed), each within the
        # supervisor's check in its own terms (counts/s, counts/s^2, counts/s^3)
        self._vc = whole_counts(self._v, period_s, 1)
        self._ac = None if self._a is None else whole_counts(self._a, period_s, 2)
        self._jc = None
        if self._j is not None:
            self._jc = whole_counts(self._j, period_s, 3)
            if self._ac is None:
                self._ac = whole_counts(np.asarray(accel_limits(self.limits)), period_s, 2)
        if self._jc is not None and self._table.shape[0] > 3:
            self._dr, ddr = rate_limits(self._table, self._jc, self._dr)
            self._ddr = ddr if ddr < 2.0 * self._dr else math.inf
        self._cmin = np.asarray(self.limits.counts_min, dtype=np.int64)
        self._cmax = np.asarray(self.limits.counts_max, dtype=np.int64)
        self.position, self.rate, self._k, self._out = 0.0, 1.0, -1, None
        self._prev = self._before = self._before2 = self._actual
        self.held_cycles = self.jerk_relaxed_cycles = 0
        self._played = [self._actual.astype(np.int32)]
        self.played_complete = True

    @property
    def n_cycles(self) -> int:
        """Cycles at most: at full rate, plus the longest pause and two ramps (what the
        session's wait for the stream's end allows for)."""
        rows = int(self._table.shape[0]) if self._table.size else self.inner.n_cycles
        period_s = self._period_s if math.isfinite(self._period_s) else 0.01  # not started
        return rows + math.ceil(self.max_pause_s / period_s) + 2 * self.ramp_cycles

    @property
    def ramp_cycles(self) -> int:
        """Cycles a pause or a resume takes from full rate to rest (or back), on a table
        that lets the rate change all along: ``ramp_s`` unless the table's own speed,
        acceleration and jerk leave the rate less room (:func:`rate_limits`)."""
        if not math.isfinite(self._period_s):  # not started
            return math.ceil(self.ramp_s / 0.01)
        ease = self._dr / self._ddr if math.isfinite(self._ddr) else 0.0
        return math.ceil(1.0 / self._dr + ease) + 1

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
            self._before2, self._before, self._prev = self._before, self._prev, out
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
        rest = rest[(rest >= 0.0) & (rest <= cap)]
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
            if not ((x >= lo) & (x <= hi)).all():
                # the last setpoints are not the table's rows (a pause left the path by a
                # count or two): the row is a candidate like any other
                rates, x, c = self._search(target, end, n)
        else:
            rates, x, c = self._search(target, end, n)
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

    def _search(self, target: float, end: float, n: int) -> tuple[np.ndarray, np.ndarray, int]:
        """The rates tried this cycle, the setpoint chosen and its index: the first choices
        alone first (most cycles: one row of the table), then every candidate, within the
        jerk window; where none of them stays on the path within it (a table at the
        motors' acceleration limit that a rate change cannot follow in jerk), within the
        supervisor's window of speed and acceleration alone (counted in
        :attr:`jerk_relaxed_cycles`)."""
        n_first, rates = self._candidates(target)
        xs, over = self._try(rates[:n_first], end, n)
        ok = np.flatnonzero(over <= 0.0)
        if ok.size:
            return rates, xs[int(ok[0])], int(ok[0])
        xs, over = self._try(rates, end, n)
        if self._jc is not None and not (over <= 0.0).any():
            xs_free, over_free = self._try(rates, end, n, jerk=False)
            ok = np.flatnonzero(over_free <= 0.0)
            if ok.size:  # of those on the path, the one with the least jerk
                self.jerk_relaxed_cycles += 1
                d3 = xs_free[ok] - 3 * self._prev + 3 * self._before - self._before2
                c = int(ok[np.argmin(np.max(np.abs(d3) / self._jc, axis=1))])
                return rates, xs_free[c], c
        c = self._choose(rates, over, n_first)
        return rates, xs[c], c

    @staticmethod
    def _choose(rates: np.ndarray, over: np.ndarray, n_first: int) -> int:
        """The feasible rate (``over <= 0``) nearest to the nominal step (the last first
        choice); none feasible: the one that leaves the path least."""
        ok = np.flatnonzero(over <= 0.0)
        if ok.size == 0:
            return int(np.argmin(over))
        return int(ok[np.argmin(np.abs(rates[ok] - rates[n_first - 1]))])

    def _try(
        self, rates: np.ndarray, end: float, n: int, jerk: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
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
        lo, hi = self._window(jerk)
        xs = np.clip(np.rint(path).astype(np.int64), lo, hi)
        over = np.max(np.abs(xs - path), axis=1) - MAX_OFF_PATH_COUNTS
        if not (lo <= hi).all():  # no setpoint within the limits at all (not for a table)
            over[:] = np.inf
        return xs, over

    def _window(self, jerk: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The integer setpoints of each motor the supervisor accepts next: the speed from
        the last setpoint and the second difference within the motors' limits (checked in
        the supervisor's own terms, counts/s and counts/s^2); with jerk limits also the
        third difference, the speed kept where the acceleration can still be eased off
        before the speed limit (:func:`~drivers.safety.ramps.jerk_window`)."""
        prev, before = self._prev, self._before
        if jerk and self._jc is not None and self._ac is not None:
            lo, hi = jerk_window(prev, before, self._before2, self._vc, self._ac, self._jc)
        else:
            lo, hi = prev - self._vc, prev + self._vc
            if self._ac is not None:
                mid = 2 * prev - before
                lo, hi = np.maximum(lo, mid - self._ac), np.minimum(hi, mid + self._ac)
        lo = np.maximum(lo, self._cmin)
        hi = np.minimum(hi, self._cmax)
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
