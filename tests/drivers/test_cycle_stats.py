"""A stream's cycle statistics: bounded memory, quantiles to one bin, exact maxima."""

from __future__ import annotations

import tracemalloc

import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st

from drivers.cycle import HIST_BIN_S, HIST_LO_S, MAX_NOTABLE_CYCLES, CycleStats, TimeHistogram

IN_RANGE = st.floats(min_value=HIST_LO_S, max_value=0.098, allow_nan=False)


@given(st.lists(IN_RANGE, min_size=1, max_size=400), st.sampled_from([1.0, 50.0, 99.0, 100.0]))
@example([0.0001, 0.0002, 0.0003, 0.004], 99.0)
@example([0.0], 50.0)
def test_a_quantile_is_the_true_one_or_at_most_one_bin_above(xs: list[float], q: float) -> None:
    h = TimeHistogram()
    for x in xs:
        h.add(x)
    true = float(np.percentile(np.asarray(xs), q, method="inverted_cdf"))
    got = h.quantile(q)
    assert true - 1e-12 <= got <= true + HIST_BIN_S + 1e-12
    assert h.max == max(xs) and h.min == min(xs) and h.n == len(xs)


def test_values_beyond_the_range_count_in_the_end_bins_and_keep_their_extremes() -> None:
    h = TimeHistogram()
    for x in (-0.5, 0.0, 2.0):
        h.add(x)
    assert h.counts[0] == 1 and h.counts[-1] == 1 and h.max == 2.0 and h.min == -0.5
    assert h.quantile(100) == 2.0 and h.quantile(67) == 2.0  # the end bin: the maximum
    assert -0.5 <= h.quantile(1) <= HIST_LO_S + HIST_BIN_S  # above the truth, as any bin


def test_late_cycles_are_counted_exactly_and_jitter_between_syncs() -> None:
    T = 0.01
    st_ = CycleStats(T, late_threshold_s=0.002)
    lates = [0.0001, 0.0021, 0.0019, 0.0050, 0.0]
    for k, late in enumerate(lates):
        st_.add(k * T, k * T, k * T + late, 0.0003)
    s = st_.summary()
    assert s["late_cycles"] == 2 and s["cycles"] == 5
    assert abs(s["lateness_max_s"] - 0.005) < 1e-12
    assert abs(s["jitter_max_s"] - 0.0050) < 1e-12  # 0.0019 -> 0.0050 and 0.0050 -> 0.0
    assert abs(s["drift_s"] - (0.0 - 0.0001)) < 1e-12
    assert abs(s["cpu_per_cycle_mean_s"] - 0.0003) < 1e-12


def test_a_long_stream_holds_no_more_memory_than_a_short_one() -> None:
    """60 000 cycles (a 10-minute soak at 100 Hz) against 1000: the same few kB."""

    def grown(cycles: int) -> int:
        st_ = CycleStats(0.01)
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        for k in range(cycles):
            st_.add(k * 0.01, k * 0.01 + 1e-4, k * 0.01 + 2e-4, 3e-4)
        used = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.stop()
        return used

    short, long_ = grown(1000), grown(60_000)
    assert long_ < 4096, long_  # the lists it kept before: ~4 x 60 000 floats, > 5 MB
    assert long_ <= short + 1024


def test_late_and_missing_feedback_cycles_are_kept_with_their_deadlines_up_to_a_bound() -> None:
    T = 0.01
    st_ = CycleStats(T, late_threshold_s=0.002)
    missing_total = 5  # what the monitor counted before the stream: not this stream's
    for k in range(3 * MAX_NOTABLE_CYCLES):
        late = 0.003 if k % 2 else 0.0001
        missing_total += 18 if k % 3 == 1 else 0
        woke = k * T + (0.0025 if k % 4 == 3 else 0.0)  # some late cycles woke late
        st_.add(k * T, woke, k * T + late, 0.0003 + k * 1e-6, missing_total)
    notable = st_.summary()["notable_cycles"]
    assert len(notable) == MAX_NOTABLE_CYCLES
    # every cycle that was late (odd k) or found 18 TPDOs missing (k % 3 == 1), in order
    want = [k for k in range(3 * MAX_NOTABLE_CYCLES) if k % 2 or k % 3 == 1]
    assert [round(d / T) for d, *_ in notable] == want[:MAX_NOTABLE_CYCLES]
    assert all(m == (18 if round(d / T) % 3 == 1 else 0) for d, _, m, *_ in notable)
    assert all((lt > 0.002) == (round(d / T) % 2 == 1) for d, lt, *_ in notable)
    # with each its wake lateness and the supervisor's CPU time, to tell waiting from work
    assert all(w == (0.0025 if round(d / T) % 4 == 3 else 0.0) for d, _, _, w, _ in notable)
    assert all(c == round(0.0003 + round(d / T) * 1e-6, 6) for d, _, _, _, c in notable)
