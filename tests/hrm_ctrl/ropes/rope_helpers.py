"""Helpers shared by the rope-layer tests (imported by name; not a conftest)."""

from __future__ import annotations

import copy
import tomllib
from importlib import resources
from typing import Any

import numpy as np

from hrm_ctrl.model import RobotModel, robot_from_dict


def default_doc() -> dict[str, Any]:
    text = resources.files("hrm_ctrl.data").joinpath("robot.toml").read_text()
    return tomllib.loads(text)


def robot_with(
    ropes: dict[str, Any] | None = None, motors: dict[str, Any] | None = None
) -> RobotModel:
    """The default robot with some [ropes] / [motors] keys replaced (None value: key removed)."""
    doc = copy.deepcopy(default_doc())
    for name, upd in (("ropes", ropes), ("motors", motors)):
        for k, v in (upd or {}).items():
            if v is None:
                doc[name].pop(k, None)
            else:
                doc[name][k] = v
    return robot_from_dict(doc, "<test>")


def random_config(
    rng: np.random.Generator, lim: float, shape: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(-lim, lim, (*shape, 12)), rng.uniform(-lim, lim, (*shape, 12))
