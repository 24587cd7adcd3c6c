"""What the live view draws, as plain arrays (no viewer library): link cylinders, the
clearance colour of every link, the environment as triangle meshes and lines, the
trail the tip has drawn, the pose of the camera at the tip.

Lengths here are mm (the stack's unit); :mod:`hrm_ctrl.view.server` scales them to the
viewer's metres.

>>> c, q, h = link_cylinders(np.array([[0.0, 0, 0], [0, 0, 100], [100, 0, 100]]))
>>> c.tolist(), h.tolist()
([[0.0, 0.0, 50.0], [50.0, 0.0, 100.0]], [100.0, 100.0])
>>> clearance_colours(np.array([-1.0, 2.0, 30.0, np.inf])).tolist()
[[220, 40, 40], [245, 165, 0], [40, 170, 80], [90, 130, 190]]
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np

from hrm_ctrl.planning.environment import Box, Environment, Pipe, RoundOpening, Wall

# Clearance bands (mm): below 0 a link meets an obstacle; below WARN_CLEARANCE_MM it is
# close (the clearance fit of the bent pipe keeps 5.6 mm; an estimate off by a few mm of
# rope stretch shows there first).
WARN_CLEARANCE_MM = 5.0


class ClearanceBand(StrEnum):
    """How a link stands against the environment, as the view colours it."""

    COLLISION = "collision"  # clearance < 0
    CLOSE = "close"  # 0 <= clearance < WARN_CLEARANCE_MM
    CLEAR = "clear"  # clearance >= WARN_CLEARANCE_MM
    FREE = "free"  # no obstacle known (clearance +inf)


BAND_RGB: dict[ClearanceBand, tuple[int, int, int]] = {
    ClearanceBand.COLLISION: (220, 40, 40),
    ClearanceBand.CLOSE: (245, 165, 0),
    ClearanceBand.CLEAR: (40, 170, 80),
    ClearanceBand.FREE: (90, 130, 190),
}
ENV_RGB = (120, 120, 130)
PATH_RGB = (200, 30, 60)
BACKBONE_RGB = (30, 90, 200)
PLANNED_ARM_RGB = (100, 100, 120)
PIPE_RING_SPACING_MM = 20.0
PIPE_SEGMENTS = 32
MAX_PIPE_RINGS = 2000  # a pipe's mesh stays bounded whatever its length
TRAIL_RGB = (230, 120, 20)
MAX_TRAIL_POINTS = 2000  # a trail drawn is thinned to this many points
TIP_CAMERA_AHEAD_MM = 1.0  # the tip camera sits this far out of the last link's end face


def clearance_band(clearance_mm: float) -> ClearanceBand:
    """The band of one clearance value (mm; +inf: free space, NaN: as a collision).

    >>> clearance_band(4.9), clearance_band(5.0), clearance_band(float("inf"))
    (<ClearanceBand.CLOSE: 'close'>, <ClearanceBand.CLEAR: 'clear'>, <ClearanceBand.FREE: 'free'>)
    """
    c = float(clearance_mm)
    if c == np.inf:
        return ClearanceBand.FREE
    if not c >= 0.0:  # negative or NaN
        return ClearanceBand.COLLISION
    return ClearanceBand.CLOSE if c < WARN_CLEARANCE_MM else ClearanceBand.CLEAR


def clearance_colours(clearance_mm: np.ndarray) -> np.ndarray:
    """(L,) link clearances (mm) -> (L, 3) uint8 RGB colours of their bands."""
    c = np.asarray(clearance_mm, dtype=float).reshape(-1)
    return np.array([BAND_RGB[clearance_band(v)] for v in c], dtype=np.uint8).reshape(-1, 3)


def quaternion_z_to(d: np.ndarray) -> np.ndarray:
    """(..., 3) directions -> (..., 4) unit quaternions ``wxyz`` turning +z onto them.

    >>> q = quaternion_z_to(np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]))
    >>> (q.round(6) + 0.0).tolist()
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.707107, 0.0, 0.707107, 0.0]]
    """
    d = np.asarray(d, dtype=float)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.where(n > 0.0, d / np.where(n > 0.0, n, 1.0), np.array([0.0, 0.0, 1.0]))
    w = 1.0 + u[..., 2]
    xyz = np.stack([-u[..., 1], u[..., 0], np.zeros_like(w)], axis=-1)  # z x u
    q = np.concatenate([w[..., None], xyz], axis=-1)
    flip = w < 1e-9  # u = -z: half a turn about x
    q = np.where(flip[..., None], np.array([0.0, 1.0, 0.0, 0.0]), q)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def link_cylinders(O: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint centres and end point (L + 1, 3) -> each link's centre (L, 3), orientation
    ``wxyz`` (L, 4, +z along the link) and length (L,)."""
    O = np.asarray(O, dtype=float)
    d = O[1:] - O[:-1]
    return 0.5 * (O[1:] + O[:-1]), quaternion_z_to(d), np.linalg.norm(d, axis=-1)


def perpendicular(n: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to unit ``n`` (from the axis ``n`` is least along).

    >>> perpendicular(np.array([0.0, 0.0, 1.0]))
    array([1., 0., 0.])
    """
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = e - (e @ n) * n
    return u / np.linalg.norm(u)


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    u = perpendicular(n)
    return u, np.cross(n, u)


def circle(c: np.ndarray, n: np.ndarray, r: float, k: int = 48) -> np.ndarray:
    """(k + 1, 3) closed circle of radius ``r`` around ``c`` in the plane of unit ``n``."""
    u, v = _basis(n)
    a = np.linspace(0.0, 2.0 * np.pi, k + 1)
    return c + r * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)


def pipe_mesh(p: Pipe) -> tuple[np.ndarray, np.ndarray]:
    """The pipe's inner wall as a triangle mesh: vertices (V, 3) mm, faces (F, 3)."""
    axis = p.axis
    k = int(min(MAX_PIPE_RINGS, max(2, np.ceil(axis.length / PIPE_RING_SPACING_MM) + 1)))
    m = PIPE_SEGMENTS
    rings = [
        circle(axis.point_at(d), axis.tangent_at(d), p.inner_radius, m)[:-1]
        for d in np.linspace(0.0, axis.length, k)
    ]
    verts = np.concatenate(rings)
    i, j = np.meshgrid(np.arange(k - 1), np.arange(m), indexing="ij")
    a, b = i * m + j, i * m + (j + 1) % m
    c, d = a + m, b + m
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([b, d, c], -1)]).reshape(-1, 3)
    return verts, faces.astype(np.uint32)


def _clip(poly: np.ndarray, q: np.ndarray, m: np.ndarray) -> np.ndarray:
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        da, db = (a - q) @ m, (b - q) @ m
        if da >= 0.0:
            out.append(a)
        if da * db < 0.0:
            out.append(a + da / (da - db) * (b - a))
    return np.array(out).reshape(-1, 3)


def wall_shapes(w: Wall, near: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """A wall's drawn patch (convex polygon (k, 3): a square around its openings, or around
    the point of the wall nearest ``near``, cut by its bounds) and its openings' outlines."""
    n = w.normal
    outlines = []
    for o in w.openings:
        c = o.centre - ((o.centre - w.point) @ n) * n
        if isinstance(o, RoundOpening):
            outlines.append(circle(c, n, 0.5 * o.diameter))
        else:
            u = o.u - (o.u @ n) * n
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            hw, hh = 0.5 * o.width, 0.5 * o.height
            corners = [(-hw, -hh), (hw, -hh), (hw, hh), (-hw, hh), (-hw, -hh)]
            outlines.append(np.array([c + a * u + b * v for a, b in corners]))
    if outlines:
        pts = np.concatenate(outlines)
        centre = pts.mean(axis=0)
        half = max(float(np.abs(pts - centre).max()) * 1.6, 60.0)
    else:
        centre = near - ((near - w.point) @ n) * n
        half = 150.0
    u, v = _basis(n)
    patch = np.array(
        [centre + half * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    )
    for q, m in w.bounds:
        patch = _clip(patch, q, m)
    return patch, outlines


def fan(poly: np.ndarray) -> np.ndarray:
    """Faces (k - 2, 3) of a convex polygon's triangle fan."""
    k = len(poly)
    return np.array([[0, i, i + 1] for i in range(1, k - 1)], dtype=np.uint32).reshape(-1, 3)


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """(P, 3) polyline -> (P - 1, 2, 3) segments."""
    p = np.asarray(points, dtype=float)
    return np.stack([p[:-1], p[1:]], axis=1)


def rotation_wxyz(R: np.ndarray) -> np.ndarray:
    """A rotation matrix (3, 3) as a unit quaternion ``wxyz`` (Shepperd's method).

    >>> rotation_wxyz(np.eye(3)).tolist()
    [1.0, 0.0, 0.0, 0.0]
    >>> (rotation_wxyz(np.diag([1.0, -1.0, -1.0])) + 0.0).tolist()  # half a turn about x
    [0.0, 1.0, 0.0, 0.0]
    """
    R = np.asarray(R, dtype=float)
    tr = float(np.trace(R))
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    out = np.array(q, dtype=float)
    return out / np.linalg.norm(out)


def box_wxyz(b: Box) -> np.ndarray:
    """A box's world-from-box rotation as a unit quaternion ``wxyz``.

    >>> box_wxyz(Box(np.zeros(3), np.ones(3))).tolist()
    [1.0, 0.0, 0.0, 0.0]
    """
    return rotation_wxyz(b.rotation)


def tip_camera_pose(
    R_tip: np.ndarray, O_tip: np.ndarray, ahead_mm: float = TIP_CAMERA_AHEAD_MM
) -> tuple[np.ndarray, np.ndarray]:
    """The tip camera's pose from the tip frame: rotation ``R_tip`` (3, 3, world from
    tip; its z axis along the last link, out of the arm) and the end point ``O_tip``
    (3,) mm -> the camera's position (3,) mm, ``ahead_mm`` out along the tip's z (clear of
    the last link's end face), and its orientation ``wxyz``.

    The camera follows the OpenCV convention the viewer's cameras use (+z forward, +x
    right, +y down in the image): it looks along the tip's z axis, the tip's x axis to the
    right of the image and its y axis down.

    >>> from hrm_ctrl.kinematics import frames
    >>> from hrm_ctrl.model import default_robot
    >>> R, O = frames(default_robot(), np.zeros(12), np.zeros(12))
    >>> p, q = tip_camera_pose(R[-1], O[-1], ahead_mm=2.0)
    >>> p.round(9).tolist()  # the straight arm's end point (2007 mm along +x) plus 2 mm
    [2009.0, 0.0, 0.0]
    >>> forward = quaternion_rotate(q, np.array([0.0, 0.0, 1.0]))
    >>> (forward.round(9) + 0.0).tolist()  # the camera looks out along +x, as the tip
    [1.0, 0.0, 0.0]
    """
    R = np.asarray(R_tip, dtype=float)
    return np.asarray(O_tip, dtype=float) + ahead_mm * R[:, 2], rotation_wxyz(R)


def quaternion_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The vector ``v`` (3,) turned by the unit quaternion ``q`` (``wxyz``).

    >>> half_turn_x = np.array([0.0, 1.0, 0.0, 0.0])
    >>> (quaternion_rotate(half_turn_x, np.array([0.0, 1.0, 0.0])) + 0.0).tolist()
    [0.0, -1.0, 0.0]
    """
    w, x, y, z = (float(c) for c in q)
    u = np.array([x, y, z])
    v = np.asarray(v, dtype=float)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def trail_points(points: np.ndarray, max_points: int = MAX_TRAIL_POINTS) -> np.ndarray:
    """A trail (P, 3) thinned to at most ``max_points`` (evenly by index, both ends
    kept): what the view draws of a long trail.

    >>> trail_points(np.arange(30.0).reshape(10, 3), 4)[:, 0].tolist()
    [0.0, 9.0, 18.0, 27.0]
    """
    p = np.asarray(points, dtype=float)
    if len(p) <= max_points:
        return p
    return p[np.unique(np.linspace(0, len(p) - 1, max_points).round().astype(int))]


def obstacles(env: Environment | None) -> tuple[Pipe | Wall | Box, ...]:
    """The obstacles of ``env`` (none for None)."""
    return () if env is None else tuple(env.obstacles)
