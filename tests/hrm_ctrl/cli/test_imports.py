"""``hrm`` starts light: importing the console, building its parser, ``hrm --help`` and
``hrm --version`` import none of the heavy libraries (a structural check in a fresh
interpreter, not a timing: ``benchmarks/bench_startup.py`` measures the times), and a plan
imports none it does not use."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# What a command imports where it uses it, never to start: each costs 0.05-0.7 s to import
HEAVY = (
    "numpy", "scipy", "matplotlib", "can", "canopen", "toppra", "ruckig", "viser",
    "jsonschema", "rich", "prompt_toolkit", "plyfile", "filterpy", "serial", "sim_bus",
    "calibration",
)  # fmt: skip

PREAMBLE = "import json, sys\n"
REPORT = (
    "\nprint(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))\n"
    "print(json.dumps(sorted(m for m in sys.modules if m.startswith('scipy.'))))\n"
)


def imported(code: str) -> tuple[set[str], set[str]]:
    """The top-level packages, and the scipy modules, a fresh interpreter has imported
    after running ``code``."""
    proc = subprocess.run(
        [sys.executable, "-c", PREAMBLE + code + REPORT],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    top, scipy = proc.stdout.splitlines()[-2:]
    return set(json.loads(top)), set(json.loads(scipy))


def _quietly(argv: list[str]) -> str:
    return (
        "import contextlib, io\n"
        "from hrm_ctrl.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        f"        main({argv!r})\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, exc.code\n"
    )


@pytest.mark.parametrize(
    "code",
    [
        "import hrm_ctrl.cli",
        "from hrm_ctrl.cli import build_parser; build_parser()",
        _quietly(["--version"]),
        _quietly(["--help"]),
    ],
    ids=["import", "build_parser", "version", "help"],
)
def test_starting_hrm_imports_no_heavy_library(code: str) -> None:
    top, _ = imported(code)
    assert sorted(top & set(HEAVY)) == []
    assert "hrm_ctrl" in top  # the code ran


def test_a_plan_imports_only_what_planning_uses() -> None:
    """The paper's fit of the bent pipe: numpy and the k-d tree (pykdtree), not scipy (0.25-
    0.5 s of imports: the scan's smoothing is scipy's), the plots, the buses, the trajectory
    and the 3D view."""
    argv = ["plan", "--scenario", "bent-pipe", "--fit", "paper", "--allow-collision", "--json"]
    top, scipy = imported(_quietly(argv))
    assert {"numpy", "pykdtree"} <= top  # it planned
    unused = {"matplotlib", "can", "canopen", "toppra", "ruckig", "viser", "sim_bus", "rich"}
    assert sorted(top & (unused | {"scipy"})) == []
    assert scipy == set()
