"""Fixtures of the hrm_ctrl tests: the rope layer, shared by the rope and CLI tests."""

from __future__ import annotations

import pytest

from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from tests.hrm_ctrl.ropes.rope_helpers import robot_with


@pytest.fixture(scope="session")
def act() -> Actuation:
    return load_actuation(default_robot())


@pytest.fixture(scope="session")
def act4() -> Actuation:
    return load_actuation(robot_with({"per_joint": 4, "joint_step_deg": None}))
