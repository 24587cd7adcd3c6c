"""The simulated box's commands beside two CPU burners (issue 34, item 5).

Each test starts two busy loops (``sh``, in this test's session: they compete with the
command as any other work of its user would), runs one command as a user does and
checks that it completed with no stop: ``hrm demo`` (in one box process the stages of
``hrm calibrate zero``, ``hrm calibrate kinematic --collect`` and ``hrm run --sim`` of the
bent pipe with its return, which the suite's time does not allow on their own as well) and
the console running the cabins plan (its command thread beside the session's, which starved
first).  The burners end with the test whatever ends it
(the fixture kills them), and end by themselves once this process is gone (each loops
only while this process exists).  Marked ``load``: CI runs them once, in the normal
suite; ``pytest -m load`` runs only these.  What starved and the runs measured:
``docs/sim.md`` ("A busy machine").
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

# alone: the burners would starve another worker's test beside it (tests/conftest.py)
pytestmark = [pytest.mark.load, pytest.mark.exclusive]

PYTHON = sys.executable
BURNERS = 2
COMMAND_TIMEOUT_S = 280.0  # below the suite's 300 s per test (the demo's: twice that)


@pytest.fixture
def burners() -> Iterator[list[subprocess.Popen[bytes]]]:
    """Two CPU burners beside the test, killed on any exit of the test."""
    loop = f"while kill -0 {os.getpid()} 2>/dev/null; do :; done"  # ends with this process
    procs = [subprocess.Popen(["sh", "-c", loop]) for _ in range(BURNERS)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=10)


def hrm(
    tmp_path: Path, *args: str, stdin: str | None = None, timeout_s: float = COMMAND_TIMEOUT_S
) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HRM_CALIBRATIONS": str(tmp_path / "calibrations")}
    return subprocess.run(
        [PYTHON, "-m", "hrm_ctrl.cli", *args],
        input=stdin, capture_output=True, text=True, timeout=timeout_s,
        cwd=tmp_path, env=env,
    )  # fmt: skip


def completed(p: subprocess.CompletedProcess[str]) -> None:
    """Exit 0 and no stop said on stderr or stdout."""
    said = p.stdout + p.stderr
    assert p.returncode == 0, said[-2000:]
    assert "stopped" not in said and "Traceback" not in said, said[-2000:]


@pytest.fixture(scope="module")
def cabins_plan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The cabins plan with its return leg, made once and before the burners (the planner
    is not a command of the box)."""
    folder = tmp_path_factory.mktemp("plans")
    out = folder / "cabins.json"
    p = hrm(folder, "plan", "--scenario", "cabins", "--return", "--out", str(out))
    assert p.returncode == 0, p.stderr
    return out


@pytest.mark.timeout(600)  # its two plans and two calibrations take their time beside burners
def test_demo(tmp_path: Path, burners: list) -> None:
    """Fewer poses (14: the fewest the kinematic fit takes with a margin) and a coarser step
    than the defaults, for the suite's time; the same stages."""
    p = hrm(tmp_path, "demo", "--poses", "14", "--step", "10", "--out", "demo", timeout_s=580)
    completed(p)
    assert "end point vs path (with the calibration)" in p.stdout


def test_console_sim_runs_a_plan_and_returns(
    tmp_path: Path, cabins_plan: Path, burners: list
) -> None:
    script = f"connect\nenable\nrun {cabins_plan}\nquit\n"
    p = hrm(tmp_path, "console", "--sim", "--log-dir", "runs", stdin=script)
    completed(p)
