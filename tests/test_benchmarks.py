"""Every benchmark still imports: the helpers it takes from the others and from the stack
exist (``bench_watches.py`` imported two that ``bench_drivers.py`` had dropped, and went
unnoticed for a whole issue).  Importing runs no benchmark (``__main__`` guard)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parents[1] / "benchmarks"
BENCHMARKS = sorted(HERE.glob("bench_*.py"))


def test_there_are_benchmarks() -> None:
    assert len(BENCHMARKS) >= 10


@pytest.mark.parametrize("path", BENCHMARKS, ids=[p.stem for p in BENCHMARKS])
def test_a_benchmark_imports(path: Path) -> None:
    code = f"import sys; sys.path.insert(0, {str(HERE)!r}); import {path.stem}"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout == ""  # nothing ran
