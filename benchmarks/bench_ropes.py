"""Rope-layer speed: forward map, batch forward map, inverse, estimator update.

Run ``python benchmarks/bench_ropes.py``; prints one JSON object.  Targets
(issue 3): forward 1 config -> 36 counts <= 50 us; 10,000 configs <= 50 ms;
inverse of one config <= 1 ms; estimator update with 36 measurements <= 2 ms.
Times are medians (and 99th percentiles) of wall-clock repetitions.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable

import numpy as np

from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.ropes.estimator import RopeStateEstimator


def timings_us(fn: Callable[[int], object], n: int) -> np.ndarray:
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out[i] = time.perf_counter() - t0
    return out * 1e6


def summary(t: np.ndarray, target: float, unit: str = "us") -> dict[str, float | bool | str]:
    med = float(np.median(t))
    return {
        "median": round(med, 1),
        "min": round(float(t.min()), 1),
        "p99": round(float(np.percentile(t, 99)), 1),
        "unit": unit,
        "target": target,
        "meets_target": med <= target,
    }


def main() -> None:
    load = round(os.getloadavg()[0], 2)
    act = load_actuation(default_robot())
    rng = np.random.default_rng(0)
    lim = np.deg2rad(59.9)
    n = 2000
    A, T = rng.uniform(-lim, lim, (n, 12)), rng.uniform(-lim, lim, (n, 12))
    for i in range(50):  # warm up
        act.counts_from_angles(A[i], T[i])

    fwd = timings_us(lambda i: act.counts_from_angles(A[i], T[i]), n)
    lengths = timings_us(lambda i: act.rope_lengths(A[i], T[i]), n)
    A10, T10 = rng.uniform(-lim, lim, (10_000, 12)), rng.uniform(-lim, lim, (10_000, 12))
    batch = timings_us(lambda i: act.counts_from_angles(A10, T10), 20) / 1e3

    C = act.counts_from_angles(A, T)
    ni = 400
    inv_cold = timings_us(lambda i: act.angles_from_counts(C[i]), ni)
    inv_warm = timings_us(
        lambda i: act.angles_from_counts(C[i], None, A[i] + 0.01, T[i] - 0.01), ni
    )
    # moderate configurations (|angle| <= 30 deg), cold start
    Am, Tm = A / 2, T / 2
    Cm = act.counts_from_angles(Am, Tm)
    inv_mod = timings_us(lambda i: act.angles_from_counts(Cm[i]), ni)
    a_err = max(float(np.abs(act.angles_from_counts(C[i])[0] - A[i]).max()) for i in range(100))

    est = RopeStateEstimator(act, rate_hz=100.0)
    dt = 0.01
    ph = np.arange(12)

    def counts_at(k: int) -> np.ndarray:
        a = 0.5 * np.sin(0.5 * k * dt + 0.3 * ph)
        t = 0.4 * np.cos(0.4 * k * dt + 0.2 * ph)
        return act.counts_from_angles(a, t) + rng.normal(0, 3, 36).round().astype(np.int64)

    feed = [counts_at(k) for k in range(1100)]
    est.initialise(feed[0])
    for k in range(1, 100):
        est.update(feed[k])
    upd = timings_us(lambda i: est.update(feed[100 + i]), 1000)

    print(
        json.dumps(
            {
                "benchmark": "ropes",
                "machine": f"{platform.machine()} {platform.python_implementation()} "
                f"{platform.python_version()} numpy {np.__version__}",
                "load_average_1min_at_start": load,
                "motors": act.n_motors,
                "forward_1_config_to_counts": summary(fwd, 50.0),
                "rope_lengths_1_config": summary(lengths, 50.0),
                "forward_10000_configs_to_counts": summary(batch, 50.0, "ms"),
                "inverse_1_config_cold_start_full_range": summary(inv_cold, 1000.0),
                "inverse_1_config_cold_start_within_30deg": summary(inv_mod, 1000.0),
                "inverse_1_config_warm_start_0.01rad": summary(inv_warm, 1000.0),
                "inverse_max_angle_error_rad_counts_quantised": a_err,
                "estimator_update_36_measurements": summary(upd, 2000.0),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
