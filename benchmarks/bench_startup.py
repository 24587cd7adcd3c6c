"""Benchmark: how fast ``hrm`` starts (targets: ``hrm --version`` and ``hrm --help`` at most
0.3 s; ``hrm plan --scenario bent-pipe`` within 0.5 s of its own planning time).

Each command runs as its own process, as an operator types it, ``--repeats`` times (default
5); the figure is the best (least) wall time, beside ``python -c pass`` (the interpreter's
own start), ``python -c "import hrm_ctrl.cli"`` and the libraries a plan cannot do without
(``import numpy``; ``import numpy, pykdtree.kdtree``: the k-d tree of the clearance and
path distance queries, :mod:`hrm_ctrl.planning.point_tree`); with it the least CPU time (user +
system) of the process, which other processes on a loaded machine inflate less.  For the
two plans (the paper's fit and the default, refined for clearance) the plan's own planning
time is read from its JSON report (``plan_time_ms``), and ``overhead_s`` is the least of
wall time minus planning time over the repeats: what start-up, imports, loading and
printing cost around the planning.

The commands run with their bytecode cached, as an installed hrm's are (pip compiles the
modules it installs): ``PYTHONDONTWRITEBYTECODE`` is taken out of their environment, and
each command runs once untimed first, which writes the ``.pyc`` files of a source tree.

Run: ``python benchmarks/bench_startup.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine

TARGET_START_S = 0.3  # hrm --version, hrm --help
TARGET_PLAN_OVERHEAD_S = 0.5  # hrm plan: wall time beyond its own planning time


def hrm_command() -> list[str]:
    """The ``hrm`` console script of this interpreter's environment (else ``python -m``)."""
    script = Path(sys.executable).with_name("hrm")
    if script.exists():
        return [str(script)]
    found = shutil.which("hrm")
    return [found] if found else [sys.executable, "-m", "hrm_ctrl.cli"]


def _env() -> dict[str, str]:
    """This environment, bytecode written (see the module's docstring)."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed(argv: list[str]) -> tuple[float, float, str]:
    """Wall time and CPU time (s) of one process running ``argv`` to its end, and its
    stdout; a failed command ends the benchmark with its stderr."""
    cpu0 = _children_cpu_s()
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, env=_env())
    wall = time.perf_counter() - t0
    cpu = _children_cpu_s() - cpu0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(argv)}: exit {proc.returncode}: {proc.stderr[-2000:]}")
    return wall, cpu, proc.stdout


def best_of(argv: list[str], repeats: int) -> dict[str, Any]:
    timed(argv)  # untimed: the bytecode cached
    runs = [timed(argv) for _ in range(repeats)]
    walls = [r[0] for r in runs]
    return {
        "command": " ".join(argv),
        "best_s": min(walls),
        "best_cpu_s": min(r[1] for r in runs),
        "walls_s": walls,
    }


def plan_figures(argv: list[str], repeats: int) -> dict[str, Any]:
    """Wall and planning time of ``argv`` (an ``hrm plan ... --json``) over the repeats."""
    walls: list[float] = []
    cpus: list[float] = []
    plans: list[float] = []
    timed(argv)  # untimed: the bytecode cached
    for _ in range(repeats):
        wall, cpu, out = timed(argv)
        walls.append(wall)
        cpus.append(cpu)
        plans.append(float(json.loads(out)["plan_time_ms"]) / 1e3)
    overheads = [w - p for w, p in zip(walls, plans, strict=True)]
    return {
        "command": " ".join(argv),
        "best_s": min(walls),
        "best_cpu_s": min(cpus),
        "plan_time_s": min(plans),
        "overhead_s": min(overheads),
        "walls_s": walls,
        "plan_times_s": plans,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    if args.repeats < 1:
        raise SystemExit("--repeats must be >= 1")
    hrm = hrm_command()
    py = sys.executable
    plan = [*hrm, "plan", "--scenario", "bent-pipe", "--json"]
    out = {
        "benchmark": "start-up of hrm (best wall time of each command, own process)",
        "repeats": args.repeats,
        "python_pass": best_of([py, "-c", "pass"], args.repeats),
        "import_hrm_ctrl_cli": best_of([py, "-c", "import hrm_ctrl.cli"], args.repeats),
        "import_numpy": best_of([py, "-c", "import numpy"], args.repeats),
        "import_numpy_pykdtree": best_of([py, "-c", "import numpy, pykdtree.kdtree"], args.repeats),
        "version": best_of([*hrm, "--version"], args.repeats),
        "help": best_of([*hrm, "--help"], args.repeats),
        # the paper's fit meets the pipe wall (-7.3 mm): reported, not refused
        "plan_paper": plan_figures([*plan, "--fit", "paper", "--allow-collision"], args.repeats),
        "plan_refined": plan_figures(plan, args.repeats),
        "bytecode": "cached (PYTHONDONTWRITEBYTECODE unset, one untimed run first)",
        "target_start_s": TARGET_START_S,
        "target_plan_overhead_s": TARGET_PLAN_OVERHEAD_S,
        "machine": machine(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
