"""The reference scenarios of Sec. 4, as reconstructed in ``NOTES.md``.

``bent-pipe`` (Sec. 4.1): an S-bend pipe of inner diameter 70 mm from
A = (1200, 100, 300) to B = (1800, 100, 100), bends of radius 100 mm.
``cabins`` (Sec. 4.2): A -> B -> C with the 107 deg corner at B rounded to a
radius of 150 mm, through round openings of 80 mm in the walls x = 1200 and y = 70.

Each scenario carries its path (bends sampled every 1 deg: the chord sagitta is
below 0.004 mm at radius 150) and its :class:`~hrm_ctrl.planning.environment.Environment`
(bent-pipe: the pipe along the whole path; cabins: the two sheet walls with their
openings); :func:`~hrm_ctrl.planning.environment.link_clearance` measures the arm
against it.

>>> sc = scenario("bent-pipe")
>>> abs(sc.path.length - 674.237) < 0.01, sc.path.points[-1].round(6).tolist()
(True, [1800.0, 100.0, 100.0])
>>> abs(scenario("cabins").path.length - 419.44) < 0.01
True
>>> [type(o).__name__ for o in scenario("cabins").environment.obstacles]
['Wall', 'Wall']
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.planning.environment import Environment, Pipe, RoundOpening, Wall
from hrm_ctrl.planning.known_path import KnownPath

BEND_STEP_RAD = math.radians(1.0)
SAMPLES_PER_LINK = 17  # every <= 11.2 mm along a 179 mm link (the report's links-off-path)
PIPE_INNER_DIAMETER = 70.0  # mm, bent-pipe
OPENING_DIAMETER = 80.0  # mm, both walls of cabins


def arc_points(
    start: np.ndarray, d1: np.ndarray, n: np.ndarray, R: float, phi: float
) -> np.ndarray:
    """Points of a circular arc leaving ``start`` along unit ``d1``, turning towards
    unit ``n`` (perpendicular to d1) with radius R through angle phi (first point excluded).
    """
    k = max(2, math.ceil(phi / BEND_STEP_RAD))
    psi = np.linspace(0.0, phi, k + 1)[1:]
    centre = start + R * n
    return centre - R * np.cos(psi)[:, None] * n + R * np.sin(psi)[:, None] * d1


@dataclass(frozen=True, eq=False)
class Scenario:
    """A known path with the environment it runs through."""

    name: str
    path: KnownPath
    environment: Environment = field(default_factory=Environment)
    alpha_step: float = 1.0
    description: str = ""

    def to_dict(self) -> dict[str, Any]:
        """Name, description and the environment as scene data
        (:meth:`Environment.to_dict`, the tables of a scene file)."""
        return {
            "name": self.name,
            "description": self.description,
            "environment": self.environment.to_dict(),
        }

    def with_environment(self, environment: Environment) -> Scenario:
        """The same path through another environment (``hrm plan --scene``)."""
        return replace(self, environment=environment)


def bent_pipe() -> Scenario:
    """Sec. 4.1 as fixed by ``NOTES.md``: straight 158.579 mm along +x, a 45 deg bend
    down (R 100), 200 mm at 45 deg down, a 45 deg bend back to +x, 158.579 mm to B."""
    R = 100.0
    A = np.array([1200.0, 100.0, 300.0])
    ex, ez = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    phi = math.radians(45.0)
    straight = (600.0 - 2.0 * R * math.sin(phi) - 200.0 * math.cos(phi)) / 2.0  # 158.579
    pts = [A, A + straight * ex]
    bend1 = arc_points(pts[-1], ex, -ez, R, phi)
    pts.extend(bend1)
    d45 = np.array([math.cos(phi), 0.0, -math.sin(phi)])
    n45 = np.array([math.sin(phi), 0.0, math.cos(phi)])  # towards the inside of bend 2
    pts.append(pts[-1] + 200.0 * d45)
    pts.extend(arc_points(pts[-1], d45, n45, R, phi))
    pts.append(pts[-1] + straight * ex)
    path = KnownPath.from_points(np.array(pts), source="scenario bent-pipe")
    return Scenario(
        name="bent-pipe",
        path=path,
        environment=Environment((Pipe(path, PIPE_INNER_DIAMETER),)),
        description="S-bend pipe, inner diameter 70 mm, bend radius 100 mm, A to B",
    )


def rounded_corner_path(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, R: float
) -> tuple[np.ndarray, float]:
    """Polyline A -> B -> C with the corner at B replaced by an arc of radius R;
    returns the points and the tangent length R tan(phi / 2)."""
    d1 = (B - A) / np.linalg.norm(B - A)
    d2 = (C - B) / np.linalg.norm(C - B)
    phi = math.acos(max(-1.0, min(1.0, float(d1 @ d2))))
    t = R * math.tan(phi / 2.0)
    if t >= np.linalg.norm(B - A) or t >= np.linalg.norm(C - B):
        raise PlanningError(f"corner radius {R} mm too large for the legs of the path")
    n = d2 - (d2 @ d1) * d1
    n /= np.linalg.norm(n)
    T1 = B - t * d1
    pts = [A, T1, *arc_points(T1, d1, n, R, phi), C]
    return np.array(pts), t


def cabins() -> Scenario:
    """Sec. 4.2 as fixed by ``NOTES.md``: A -> B -> C, corner at B rounded to R 150,
    entrance wall x = 1200 (opening of 80 mm at A) and partition y = 70 (opening of
    80 mm where the rounded path crosses it)."""
    A = np.array([1200.0, 100.0, 300.0])
    B = np.array([1470.0, 190.0, 300.0])
    C = np.array([1470.0, -50.0, 200.0])
    pts, _ = rounded_corner_path(A, B, C, 150.0)
    path = KnownPath.from_points(pts, source="scenario cabins")
    y = path.points[:, 1] - 70.0
    k = int(np.flatnonzero(y[:-1] * y[1:] <= 0.0)[0])
    s = y[k] / (y[k] - y[k + 1])
    cross = path.points[k] + s * (path.points[k + 1] - path.points[k])
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    entrance = Wall(A, ex, openings=(RoundOpening(A, OPENING_DIAMETER),))
    # the partition stands inside the first cabin only (x >= 1200)
    partition = Wall(
        cross, ey, openings=(RoundOpening(cross, OPENING_DIAMETER),), bounds=((A, ex),)
    )
    return Scenario(
        name="cabins",
        path=path,
        environment=Environment((entrance, partition)),
        description="two cabins: entrance x = 1200 and partition y = 70, openings 80 mm",
    )


SCENARIOS = {"bent-pipe": bent_pipe, "cabins": cabins}


def scenario(name: str) -> Scenario:
    """A reference scenario by name (``bent-pipe`` or ``cabins``)."""
    try:
        return SCENARIOS[name]()
    except KeyError:
        raise PlanningError(
            f"unknown scenario {name!r} (known: {', '.join(sorted(SCENARIOS))})"
        ) from None
