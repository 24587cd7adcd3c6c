"""The simulated box's commands beside two CPU burners (issue 34, item 5).

Each test starts two busy loops (``sh``, in this test's session: they compete with the
command as any other work of its user would), runs one command as a user does and
checks that it completed with no stop.  The burners end with the test whatever ends it
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
def plans(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The scenarios' plans with their return legs, made once and before the burners (the
    planner is not a command of the box): the module's tests play them."""
    folder = tmp_path_factory.mktemp("plans")
    made = {}
    for scenario in ("bent-pipe", "cabins"):
        out = folder / f"{scenario}.json"
        p = hrm(folder, "plan", "--scenario", scenario, "--return", "--out", str(out))
        assert p.returncode == 0, p.stderr
        made[scenario] = out
    return made


@pytest.mark.parametrize("scenario", ["bent-pipe", "cabins"])
def test_run_sim_of_a_scenario_with_return(
    tmp_path: Path, plans: dict[str, Path], burners: list, scenario: str
) -> None:
    p = hrm(tmp_path, "run", "--sim", str(plans[scenario]), "--log-dir", "runs")
    completed(p)
    assert "cycles:" in p.stdout


def test_calibrate_zero_then_kinematic_sim(tmp_path: Path, burners: list) -> None:
    """The zero calibration first: the perturbed arm's motors stand up to 5,000 counts off
    their zeros, some of its ropes slack until ``calibrate zero`` has set them."""
    # 14 poses: the fewest the kinematic fit takes with a margin (the demo's, for the time)
    for routine in (["zero"], ["kinematic", "--collect", "14"]):
        p = hrm(tmp_path, "calibrate", *routine, "--sim", "--perturb", "2", "--log-dir", "runs")
        completed(p)
    assert "calibration saved as v0002" in p.stdout + p.stderr


@pytest.mark.timeout(600)  # its two plans and two calibrations take their time beside burners
def test_demo(tmp_path: Path, burners: list) -> None:
    """Fewer poses (14: the fewest the kinematic fit takes with a margin) and a coarser step
    than the defaults, for the suite's time; the same stages."""
    p = hrm(tmp_path, "demo", "--poses", "14", "--step", "10", "--out", "demo", timeout_s=580)
    completed(p)
    assert "end point vs path (with the calibration)" in p.stdout


def test_console_sim_runs_a_plan_and_returns(
    tmp_path: Path, plans: dict[str, Path], burners: list
) -> None:
    script = f"connect\nenable\nrun {plans['cabins']}\nquit\n"
    p = hrm(tmp_path, "console", "--sim", "--log-dir", "runs", stdin=script)
    completed(p)
