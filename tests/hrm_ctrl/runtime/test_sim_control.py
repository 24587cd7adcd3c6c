"""A running simulated box's controls (``hrm_ctrl.runtime.simulated.SimControl``), the same
whichever process the box runs in: the box in its own process (``hrm_ipc``, what ``--sim``,
``hrm demo`` and ``hrm console --sim`` start by default) answers them over its control
commands as the box in this interpreter does."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.config import load_box_config
from hrm_ctrl.errors import HrmError
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.runtime.process_box import BoxProcess
from hrm_ctrl.runtime.simulated import (
    PROCESS_WIRE,
    InProcessSim,
    SimulatedArm,
    SimulatedBox,
    running_box,
    start_simulated_box,
)


@pytest.mark.parametrize("wire", [PROCESS_WIRE, "virtual"])
def test_the_controls_answer_alike_in_either_process(wire: str) -> None:
    actuation = load_actuation(default_robot())
    box = SimulatedBox(SimulatedArm(actuation), wire, fixture=True)
    with running_box(load_box_config(None), box, prog="test") as running:
        sim = running.sim
        assert isinstance(sim, BoxProcess if wire == PROCESS_WIRE else InProcessSim)
        assert {b.interface for b in running.config.buses} == {wire}
        assert running.config.tension is not None  # the box's board, a port
        sim.set_straight_fixture(False)
        sim.record_trace(True)
        times, counts = sim.trace()  # no host: no SYNC, nothing recorded
        assert times.shape == (0,) and counts.shape == (0, actuation.n_motors)
        assert counts.dtype == np.int64
        assert sim.fault("rope-snap:j06r2") == "rope-snap:j06r2"
        with pytest.raises(HrmError, match="j99r9"):
            sim.fault("rope-snap:j99r9")


def test_a_box_process_started_to_outlive_a_block_stops_when_told() -> None:
    box = SimulatedBox(SimulatedArm(load_actuation(default_robot())))
    running = start_simulated_box(load_box_config(None), box, prog="test")
    process = running.sim
    assert isinstance(process, BoxProcess) and process.proc.poll() is None
    running.sim.stop()
    assert process.proc.poll() is not None  # exited
