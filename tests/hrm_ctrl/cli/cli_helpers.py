"""Helpers shared by the CLI tests (imported by name; fixtures live in conftest.py)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hrm_ctrl.model import default_robot
from sim_bus.in_process import IN_PROCESS_MISSING_TPDO_CYCLES
from tests.vcan_guest import GUEST_RATE_HZ, in_vcan_guest


def small_plan() -> dict[str, Any]:
    """A four-step ``hrm-plan/1`` for the default robot: every alpha from 0 to 3 deg over
    15 mm of travel (as ``hrm plan`` writes them)."""
    steps = []
    for k in range(4):
        a = float(np.deg2rad(3.0) * k / 3)
        steps.append(
            {
                "travel_mm": 5.0 * k,
                "alpha_rad": [a] * 12,
                "theta_rad": [0.0] * 12,
                "joints_mm": [[0.0, 0.0, 0.0]] * 13,
            }
        )
    return {
        "format": "hrm-plan/1",
        "robot": {"links_mm": [float(v) for v in default_robot().links]},
        "path_mm": [[0.0, 0.0, 0.0], [15.0, 0.0, 0.0]],
        "steps": steps,
        "report": {},
    }


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``hrm ARGV`` in this process: its exit status (argparse's exits too), stdout, stderr."""
    from hrm_ctrl.cli import main

    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse errors
        rc = int(exc.code or 0)
    out, err = capsys.readouterr()
    return rc, out, err


#: A long run on the in-process simulated box (``--sim``, the in-process HIL box) ends on a
#: watchdog when the machine holds the process's CPU through the shortest watchdog window
#: of that box: its TPDO tolerance (sim_bus.in_process), 10 ms cycles (box.toml's 100 Hz).
#: Such a test is rerun only when the stall probe saw a stall that long during the failed
#: call (hrm_ctrl.hil.stall_reruns), never because of what failed.
IN_PROCESS_WINDOW_S = IN_PROCESS_MISSING_TPDO_CYCLES * 0.01
STALL_TOLERANT = pytest.mark.stall_tolerant(
    window_s=IN_PROCESS_WINDOW_S,
    watchdog=f"{IN_PROCESS_MISSING_TPDO_CYCLES} cycles without a TPDO (in-process box)",
)
#: The production watchdogs (box.toml: 3 cycles of 10 ms without a TPDO), the box in a
#: process of its own; in the vcan guest, where the HIL rigs run at 25 Hz, 3 cycles of 40 ms.
PRODUCTION_WINDOW_S = 3 / (GUEST_RATE_HZ if in_vcan_guest() else 100)
STALL_TOLERANT_PRODUCTION = pytest.mark.stall_tolerant(
    window_s=PRODUCTION_WINDOW_S, watchdog="3 cycles without a TPDO (box.toml)"
)
