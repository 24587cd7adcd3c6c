"""HIL: the bent-pipe plan of ``test_plan.py`` on the 36-motor box in its own process, at the
watchdog tolerance this 2-core machine carries today: 10 cycles without a TPDO and a 1 s
heartbeat timeout and tension samples stale after 500 ms, the tolerance ``hrm run --sim``
uses for a box in the host's interpreter.

Issue 13 asks for the production watchdogs (3 cycles, 350 ms) across processes; that run
(``test_plan.py``, marker ``production_timing``, not in the default run: ``pytest -m
production_timing tests/hil``) passes alone on a quiet machine but stops spuriously on a box
stall under load (BENCHMARKS.md, "CAN drivers"): not met yet.  Until it is, the default run
checks the tracking (true joint centres within 1 mm of the plan) here.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.hil.test_plan import test_bent_pipe_plan_true_joint_centres_within_1mm as _plan_run

pytestmark = pytest.mark.hrm_buses("ipc", "socketcan")

TOLERANT_CONTROL = {"missing_tpdo_cycles": 10, "heartbeat_timeout_ms": 1000}


TOLERANT_TENSION_STALE_S = 0.5


@pytest.fixture(scope="module")
def hrm_control() -> dict[str, Any]:
    return dict(TOLERANT_CONTROL)


@pytest.fixture
def hrm_host(hrm_box: Any, tmp_path: Path, hrm_process_settings: None) -> Iterator[Any]:
    """The plugin's host, with the tension samples stale after 500 ms."""
    from hrm_ctrl.hil.rig import HilHost, fault

    fault(hrm_box, "reset")
    host = HilHost(hrm_box, tmp_path, tension_stale_s=TOLERANT_TENSION_STALE_S)
    try:
        yield host
    finally:
        host.close()


def test_bent_pipe_plan_at_a_tolerant_watchdog(
    hrm_box: Any, hrm_host: Any, hrm_box_config: Any, bent_pipe_plan: Any, actuation: Any
) -> None:
    """The same run and assertions as ``test_plan.py``'s, at this module's watchdogs."""
    _plan_run(hrm_box, hrm_host, hrm_box_config, bent_pipe_plan, actuation)
