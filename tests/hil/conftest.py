"""Shared fixtures of the project's HIL tests; the box, the host, faults and the true arm
come from the ``hrm_hil`` plugin (``hrm_ctrl/hil/plugin.py``, ``docs/hil.md``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hrm_ctrl.formats.planfile import PlanDoc, read_plan
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from tests.vcan_guest import in_vcan_guest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def actuation() -> Actuation:
    return load_actuation(default_robot())


@pytest.fixture(scope="module")
def bent_pipe_plan(tmp_path_factory: pytest.TempPathFactory) -> PlanDoc:
    out = tmp_path_factory.mktemp("plan") / "bp.json"
    subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.cli", "plan", "--scenario", "bent-pipe", "--out", out],
        check=True,
        capture_output=True,
        # in the vcan guest (page faults 30 times slower) the planner took more than 60 s
        timeout=300 if in_vcan_guest() else 60,
        cwd=REPO,
    )
    return read_plan(out)
