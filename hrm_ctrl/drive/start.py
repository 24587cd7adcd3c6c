"""Where a drive starts and what it knows: the one way ``hrm drive`` and the console's
``drive`` build their :class:`~hrm_ctrl.drive.driver.Driver`.

A drive starts at a scenario's entry (its environment known) or on a path file (the
trail so far); a scene file gives or replaces the environment.  :func:`start_driver`
builds the trail, the online planner and the driver for the control period.

>>> from hrm_ctrl.model import default_robot
>>> drv = start_driver(default_robot(), DriveStart(scenario="bent-pipe"), SteerLimits(), 0.01)
>>> drv.planner.trail.length, drv.planner.env is not None
(0.0, True)
>>> DriveStart()
Traceback (most recent call last):
...
hrm_ctrl.drive.command.DriveError: a drive starts at a scenario's entry or on a path file
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hrm_ctrl.drive.command import DriveError, SteerLimits
from hrm_ctrl.drive.driver import Driver
from hrm_ctrl.drive.online import OnlinePlanner
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.model import RobotModel


@dataclass(frozen=True)
class DriveStart:
    """A scenario's name (``bent-pipe``, ``cabins``) or a path file (one of them), and a
    scene file (the environment; for a scenario it replaces the scenario's)."""

    scenario: str | None = None
    path: Path | None = None
    scene: Path | None = None

    def __post_init__(self) -> None:
        if (self.scenario is None) == (self.path is None):
            raise DriveError("a drive starts at a scenario's entry or on a path file")


def start_driver(
    robot: RobotModel, start: DriveStart, limits: SteerLimits, period_s: float
) -> Driver:
    """The driver of a drive from ``start`` (trail, environment, online planner) at the
    control period ``period_s``."""
    from hrm_ctrl.formats.scene import read_scene
    from hrm_ctrl.planning.known_path import load_path_csv
    from hrm_ctrl.planning.scenarios import scenario

    env = read_scene(start.scene) if start.scene is not None else None
    if start.scenario is not None:
        sc = scenario(start.scenario)
        env = env if env is not None else sc.environment
        P = sc.path.points
        trail = Trail.starting_at(P[0], P[1] - P[0])
    else:
        assert start.path is not None
        trail = Trail.from_path(load_path_csv(start.path))
    return Driver(OnlinePlanner(robot, trail, env), limits, period_s)
