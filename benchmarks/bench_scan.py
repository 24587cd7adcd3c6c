"""Benchmark: the centre line of a 200k-point scan of the bent pipe (target: <= 2 s).

A synthetic scan of the bent pipe (inner diameter 70 mm, noise sigma 0.5 mm, 2 % outliers)
is written as NPY, binary PLY and CSV; each is read, and the fit run ``--repeats`` times.
Prints JSON: the read time of each format, the fit's stages (median and best) and the
whole read + fit of the NPY and PLY files, and the fit's accuracy against the true axis
(largest distance both ways) and diameter.

Run: ``python benchmarks/bench_scan.py [--points N] [--repeats N]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import plyfile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine

from hrm_ctrl.formats.pointcloud import read_point_cloud
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.scan import pipe_from_scan, synthetic_pipe_scan
from hrm_ctrl.planning.scenarios import scenario


def timed(f, *args, **kwargs):
    t = time.perf_counter()
    out = f(*args, **kwargs)
    return out, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats must be >= 1")
    axis = scenario("bent-pipe").path
    cloud = synthetic_pipe_scan(axis, 70.0, args.points, 0.5, 0.02, np.random.default_rng(0))
    read_s: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as d:
        files = {"npy": Path(d) / "scan.npy", "ply": Path(d) / "scan.ply", "csv": Path(d) / "s.csv"}
        np.save(files["npy"], cloud)
        v = np.zeros(len(cloud), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
        v["x"], v["y"], v["z"] = cloud.T
        plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(files["ply"]))
        np.savetxt(files["csv"], cloud, delimiter=",", header="x,y,z", comments="", fmt="%.4f")
        for name, f in files.items():
            read_point_cloud(f)  # warm-up
            read_s[name] = min(timed(read_point_cloud, f)[1] for _ in range(3))
    pipe_from_scan(cloud)  # warm-up (imports)
    fits = [pipe_from_scan(cloud) for _ in range(args.repeats)]
    stages = {
        k: {
            "median": statistics.median(f.timings_s[k] for f in fits),
            "best": min(f.timings_s[k] for f in fits),
        }
        for k in fits[0].timings_s
    }
    fit = fits[0]
    fitted = KnownPath.from_points(fit.axis)
    dense = axis.points_at(np.linspace(0.0, axis.length, int(axis.length / 0.5) + 1))
    out = {
        "benchmark": f"scan of the bent pipe, {args.points} points, noise 0.5 mm, 2 % outliers",
        "repeats": args.repeats,
        "read_s": read_s,
        "fit_s": stages,
        "read_and_fit_s": {
            "npy": read_s["npy"] + stages["total"]["median"],
            "ply": read_s["ply"] + stages["total"]["median"],
        },
        "target_s": 2.0,
        "accuracy": {
            "axis_to_true_max_mm": float(axis.distance_to(fitted.points).max()),
            "true_to_axis_max_mm": float(fitted.distance_to(dense).max()),
            "diameter_error_mm": fit.inner_diameter - 70.0,
            "rms_mm": fit.rms,
            "p95_mm": fit.p95,
            "inlier_fraction": fit.inlier_fraction,
            "slices": fit.n_slices,
        },
        "machine": machine(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
