"""The reference scenarios of Sec. 4, as reconstructed in ``NOTES.md``.

``bent-pipe`` (Sec. 4.1): an S-bend pipe of inner diameter 70 mm from
A = (1200, 100, 300) to B = (1800, 100, 100), bends of radius 100 mm.
``cabins`` (Sec. 4.2): A -> B -> C with the 107 deg corner at B rounded to a
radius of 150 mm, through round openings of 80 mm in the walls x = 1200 and y = 70.

Each scenario carries its path (bends sampled every 1 deg: the chord sagitta is
below 0.004 mm at radius 150) and its obstacles, and measures a link's
clearance: the arm (outer diameter from the robot model) must stay inside the
pipe, and must pass each wall through its opening.

>>> sc = scenario("bent-pipe")
>>> abs(sc.path.length - 674.237) < 0.01, sc.path.points[-1].round(6).tolist()
(True, [1800.0, 100.0, 100.0])
>>> abs(scenario("cabins").path.length - 419.44) < 0.01
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.planning.known_path import KnownPath

BEND_STEP_RAD = math.radians(1.0)
SAMPLES_PER_LINK = 17  # every <= 11.2 mm along a 179 mm link


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
    """A known path with the obstacles it runs through."""

    name: str
    path: KnownPath
    pipe_radius: float | None = None  # inner radius of a pipe around the whole path
    walls: tuple[dict[str, Any], ...] = field(default_factory=tuple)
    alpha_step: float = 1.0
    description: str = ""

    def to_dict(self) -> dict[str, Any]:
        obstacles: list[dict[str, Any]] = []
        if self.pipe_radius is not None:
            obstacles.append({"kind": "pipe", "inner_radius_mm": self.pipe_radius})
        for w in self.walls:
            obstacles.append(
                {
                    "kind": "wall",
                    "axis": int(w["axis"]),
                    "value_mm": float(w["value"]),
                    "opening_centre_mm": [float(v) for v in w["centre"]],
                    "opening_radius_mm": float(w["radius"]),
                    **(
                        {"beyond": {"axis": w["beyond"][0], "value_mm": w["beyond"][1]}}
                        if "beyond" in w
                        else {}
                    ),
                }
            )
        return {"name": self.name, "description": self.description, "obstacles": obstacles}

    def clearance(self, O: np.ndarray, outer_radius: np.ndarray) -> tuple[float, int, int]:
        """Smallest clearance (mm, negative = collision) of the arm over the steps of
        ``O`` (N, 13, 3) with link outer radii (12,), and the 0-based step and
        1-based link that have it (-1, 0 where no link meets an obstacle).

        Pipe: every link point past the entrance plane (normal to the path at A) and
        before the exit plane must keep ``inner radius - link radius`` from the axis.
        Wall: where a link's axis crosses the wall, the crossing must lie within
        ``opening radius - link radius`` of the opening's centre (a link crossing
        at an angle has a wider footprint; this takes the axis point).
        """
        O = np.asarray(O, dtype=float)
        if O.ndim == 2:
            O = O[None]
        best, where = math.inf, (-1, 0)
        if self.pipe_radius is not None:
            t = np.linspace(0.0, 1.0, SAMPLES_PER_LINK)
            seg = O[:, 1:] - O[:, :-1]
            pts = O[:, :-1, None, :] + t[None, None, :, None] * seg[:, :, None, :]
            start, end = self.path.points[0], self.path.points[-1]
            t0, t1 = self.path.tangent_at(0.0), self.path.tangent_at(self.path.length)
            inside = ((pts - start) @ t0 > 0.0) & ((pts - end) @ t1 < 0.0)  # (N, 12, S)
            if inside.any():
                c = np.full(inside.shape, math.inf)
                c[inside] = (
                    self.pipe_radius
                    - np.broadcast_to(outer_radius[None, :, None], inside.shape)[inside]
                    - self.path.distance_to(pts[inside])
                )
                k = np.unravel_index(int(np.argmin(c)), c.shape)
                if c[k] < best:
                    best, where = float(c[k]), (int(k[0]), int(k[1]) + 1)
        for w in self.walls:
            ax, val = int(w["axis"]), float(w["value"])
            a, b = O[:, :-1, ax] - val, O[:, 1:, ax] - val
            n_idx, l_idx = np.nonzero(a * b <= 0.0)
            if len(n_idx) == 0:
                continue
            aa, bb = a[n_idx, l_idx], b[n_idx, l_idx]
            denom = bb - aa
            sfrac = np.where(denom == 0, 0.5, -aa / np.where(denom == 0, 1.0, denom))
            P0 = O[n_idx, l_idx]
            p = P0 + sfrac[:, None] * (O[n_idx, l_idx + 1] - P0)
            keep = np.ones(len(p), dtype=bool)
            if "beyond" in w:  # the wall does not extend there
                keep = p[:, w["beyond"][0]] >= w["beyond"][1]
            if not keep.any():
                continue
            c = w["radius"] - outer_radius[l_idx] - np.linalg.norm(p - w["centre"], axis=1)
            c = np.where(keep, c, math.inf)
            m = int(np.argmin(c))
            if c[m] < best:
                best, where = float(c[m]), (int(n_idx[m]), int(l_idx[m]) + 1)
        return best, where[0], where[1]


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
        pipe_radius=35.0,
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
    walls = (
        {"axis": 0, "value": 1200.0, "centre": A.copy(), "radius": 40.0},
        # the partition stands inside the first cabin only (x > 1200)
        {"axis": 1, "value": 70.0, "centre": cross, "radius": 40.0, "beyond": (0, 1200.0)},
    )
    return Scenario(
        name="cabins",
        path=path,
        walls=walls,
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
