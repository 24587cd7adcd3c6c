"""The tip camera's frame, rendered on the host: a pinhole camera at the end effector
looking along the tip's axis (:func:`hrm_ctrl.view.geometry.tip_camera_pose`), ray-cast
in NumPy against the known environment's own geometry, one ray a pixel.

What it shows is the environment model the planner measures clearance against, not a
picture: a pipe is its inner wall (a tube of the pipe's radius around its axis, the axis
simplified to within :data:`AXIS_TOLERANCE_MM` and the tube mitred at its vertices) with
a ring marked every :data:`RING_SPACING_MM` along the axis and one line along it (the
roll of the view), its end faces drawn as a ring one bore radius wide (the model's
material beyond is not drawn); a wall is its face towards the camera (a thick wall's
bore through an opening is not drawn) with a grid every :data:`WALL_GRID_MM`; a box is
solid; the trail the tip has drawn is orange dots (hidden behind a nearer surface).
Surfaces are lit by a lamp at the camera (:func:`shade`: the cosine of the incidence,
fading with the distance), so depth reads as brightness; what no ray meets within
:data:`MAX_RANGE_MM` is the background colour (nothing known there).  The arm itself is
not drawn (it is behind the camera).  A yellow cross marks the tip's axis.

The cost is a few NumPy operations on (pixels x pipe segments) arrays and one small
slab test per box in view over the pixels of its outline (``benchmarks/bench_tip_camera.py``).

>>> from hrm_ctrl.planning.scenarios import scenario
>>> sc = scenario("bent-pipe")
>>> scene = TipScene.of(sc.environment)
>>> cam = TipCamera(64, 48, math.radians(70.0))
>>> R = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # looks along +x (z axis -> +x)
>>> img, depth = render(scene, cam, sc.path.points[0] + [10.0, 0, 0], R)
>>> img.shape, img.dtype.name
((48, 64, 3), 'uint8')
>>> bool(np.isfinite(depth).all())  # inside the pipe every ray meets its wall
True
>>> x, y = (0.5 - 32) / cam.fy, 0.5 / cam.fy  # pixel (24, 0): its ray, z = 1
>>> round(float(depth[24, 0]), 1), round(35.0 * math.sqrt(x * x + y * y + 1) / math.hypot(x, y), 1)
(51.7, 51.7)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from functools import cached_property

import numpy as np

from hrm_ctrl.planning.environment import Box, Environment, Pipe, RectOpening, Wall
from hrm_ctrl.view.geometry import perpendicular

AXIS_TOLERANCE_MM = 0.25  # a pipe's axis is simplified to within this (Douglas-Peucker)
MAX_RANGE_MM = 3000.0  # rays end here: beyond, the background
NEAR_MM = 0.5  # nothing nearer the camera is drawn
LAMP_FALLOFF_MM = 250.0  # the lamp's light is halved this far from the camera
AMBIENT = 0.12  # light a surface gets whatever its angle
RING_SPACING_MM = 50.0  # pipe: a ring every this along the axis
WALL_GRID_MM = 100.0  # wall: grid lines this far apart
MARK_WIDTH_MM = 1.5  # rings, grid lines and the pipe's line along its axis
MARK_DARKEN = 0.45  # a mark is this bright against its surface
PIECES_A_BATCH = 2  # pipe pieces cast together (nearest first)
MAX_BOXES = 256  # the nearest boxes in view drawn at most
PIPE_RGB = (175, 170, 160)
PIPE_LINE_RGB = (60, 120, 200)  # the line along the pipe (its "top" by parallel transport)
WALL_RGB = (165, 175, 190)
BOX_RGB = (190, 150, 110)
TRAIL_RGB = (255, 140, 20)
CROSS_RGB = (250, 210, 40)
BACKGROUND_RGB = (18, 22, 30)
CROSS_PX = 6  # half length of the cross's arms


@dataclass(frozen=True, eq=False)
class TipCamera:
    """A pinhole camera of ``width`` x ``height`` pixels and vertical field of view
    ``fov_rad``, OpenCV's convention (+z forward, +x right, +y down): its rays, unit, in
    the camera's frame, one a pixel in row-major order.

    >>> cam = TipCamera(4, 3, math.radians(90.0))
    >>> cam.rays.shape, round(cam.fy, 9)
    ((12, 3), 1.5)
    """

    width: int
    height: int
    fov_rad: float
    rays: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        x = (u.ravel() + 0.5 - self.cx) / self.fy
        y = (v.ravel() + 0.5 - self.cy) / self.fy
        d = np.stack([x, y, np.ones_like(x)], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d.astype(np.float32)
        d.setflags(write=False)
        object.__setattr__(self, "rays", d)

    @property
    def fy(self) -> float:
        """Focal length in pixels (square pixels: also the horizontal one)."""
        return 0.5 * self.height / math.tan(0.5 * self.fov_rad)

    @property
    def cx(self) -> float:
        return 0.5 * self.width

    @property
    def cy(self) -> float:
        return 0.5 * self.height


def simplify_polyline(points: np.ndarray, tol_mm: float) -> np.ndarray:
    """The points of a polyline (P, 3) kept by Douglas-Peucker: every dropped point within
    ``tol_mm`` of the polyline kept, both ends kept.

    >>> a = np.linspace(0.0, np.pi / 2, 91)
    >>> arc = 100.0 * np.stack([np.cos(a), np.sin(a), 0 * a], 1)  # 1 deg steps, R 100
    >>> len(simplify_polyline(arc, 0.25))  # halved until within: 16 segments of 5.6 deg
    17
    """
    p = np.asarray(points, dtype=float)
    keep = np.zeros(len(p), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(p) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        seg = p[j] - p[i]
        n2 = float(seg @ seg)
        rel = p[i + 1 : j] - p[i]
        t = np.clip(rel @ seg / n2, 0.0, 1.0) if n2 > 0.0 else np.zeros(len(rel))
        d = np.linalg.norm(rel - t[:, None] * seg, axis=1)
        k = int(np.argmax(d))
        if d[k] > tol_mm:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return p[keep]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass(frozen=True, eq=False)
class PipePieces:
    """Every pipe of a scene as mitred tube pieces, one a segment of its simplified
    axis: start ``a`` and end ``b`` (S, 3), unit direction ``u``, the mitre planes'
    normals at start and end ``n0``, ``n1`` (pointing along the axis), the arc length
    at the start ``s0`` (S,), a frame across the axis ``e1``, ``e2`` carried along it
    by parallel transport, the radius (S,) and the pipe's index (S,); the end faces:
    centre, normal (into the pipe), bore radius (E,).  The ``*32`` properties: the same
    in float32, what the per-pixel work uses."""

    a: np.ndarray
    b: np.ndarray
    u: np.ndarray
    n0: np.ndarray
    n1: np.ndarray
    s0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    radius: np.ndarray
    pipe: np.ndarray
    end_centre: np.ndarray
    end_normal: np.ndarray
    end_radius: np.ndarray

    @classmethod
    def of(cls, pipes: list[Pipe]) -> PipePieces:
        parts: list[list[np.ndarray]] = [[] for _ in range(13)]
        for i, p in enumerate(pipes):
            v = simplify_polyline(p.axis.points, AXIS_TOLERANCE_MM)
            u = _unit(np.diff(v, axis=0))
            mid = u[:-1] + u[1:]
            ok = np.linalg.norm(mid, axis=1) > 1e-6  # a U-turn at a vertex: no mitre
            mitre = np.where(ok[:, None], mid, u[1:])
            mitre = _unit(mitre)
            n0 = np.vstack([u[:1], mitre])
            n1 = np.vstack([mitre, u[-1:]])
            s0 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(v, axis=0), axis=1))])
            e1 = np.empty_like(u)
            e1[0] = perpendicular(u[0])
            for k in range(1, len(u)):  # parallel transport: the least turn onto u[k]
                f = e1[k - 1] - (e1[k - 1] @ u[k]) * u[k]
                e1[k] = _unit(f) if np.linalg.norm(f) > 1e-9 else perpendicular(u[k])
            r = np.full(len(u), p.inner_radius)
            for lst, x in zip(
                parts[:10],
                (v[:-1], v[1:], u, n0, n1, s0[:-1], e1, np.cross(u, e1), r, np.full(len(u), i)),
                strict=True,
            ):
                lst.append(x)
            parts[10].append(np.stack([v[0], v[-1]]))
            parts[11].append(np.stack([u[0], -u[-1]]))
            parts[12].append(np.full(2, p.inner_radius))
        shapes = [(0, 3)] * 5 + [(0,)] + [(0, 3)] * 2 + [(0,), (0,)] + [(0, 3)] * 2 + [(0,)]
        arrays = [
            np.concatenate(lst) if lst else np.zeros(shape)
            for lst, shape in zip(parts, shapes, strict=True)
        ]
        return cls(*arrays)

    def __len__(self) -> int:
        return len(self.a)

    @cached_property
    def u32(self) -> np.ndarray:
        return self.u.astype(np.float32)

    @cached_property
    def n0_32(self) -> np.ndarray:
        return self.n0.astype(np.float32)

    @cached_property
    def n1_32(self) -> np.ndarray:
        return self.n1.astype(np.float32)

    @cached_property
    def ab32(self) -> np.ndarray:
        return (self.b - self.a).astype(np.float32)

    @cached_property
    def s0_32(self) -> np.ndarray:
        return self.s0.astype(np.float32)

    @cached_property
    def e1_32(self) -> np.ndarray:
        return self.e1.astype(np.float32)

    @cached_property
    def e2_32(self) -> np.ndarray:
        return self.e2.astype(np.float32)

    @cached_property
    def radius32(self) -> np.ndarray:
        return self.radius.astype(np.float32)


@dataclass(frozen=True, eq=False)
class TipScene:
    """What the tip camera sees of an environment, prepared once: the pipes as mitred
    tube pieces, the walls, the boxes (centres, world-from-box rotations, half sizes)."""

    pipes: PipePieces
    walls: tuple[Wall, ...]
    box_centre: np.ndarray
    box_rotation: np.ndarray
    box_half: np.ndarray

    @classmethod
    def of(cls, environment: Environment | None) -> TipScene:
        obstacles = () if environment is None else tuple(environment.obstacles)
        boxes = [o for o in obstacles if isinstance(o, Box)]
        return cls(
            pipes=PipePieces.of([o for o in obstacles if isinstance(o, Pipe)]),
            walls=tuple(o for o in obstacles if isinstance(o, Wall)),
            box_centre=np.array([b.centre for b in boxes]).reshape(-1, 3),
            box_rotation=np.array([b.rotation for b in boxes]).reshape(-1, 3, 3),
            box_half=np.array([0.5 * b.size for b in boxes]).reshape(-1, 3),
        )


class Material(IntEnum):
    """What a pixel shows: its colour is :data:`PALETTE`'s, lit by :func:`light`."""

    BACKGROUND = 0
    PIPE = 1
    PIPE_LINE = 2
    WALL = 3
    BOX = 4


PALETTE = np.array([BACKGROUND_RGB, PIPE_RGB, PIPE_LINE_RGB, WALL_RGB, BOX_RGB], np.float32)


def light(cos_incidence: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """The light (0..1) a surface seen at ``cos_incidence`` from ``t_mm`` away returns
    from the lamp at the camera: an ambient share and the rest by the cosine, halved at
    :data:`LAMP_FALLOFF_MM` (inverse square beyond).

    >>> light(np.array([1.0, 1.0, 0.0]), np.array([0.0, LAMP_FALLOFF_MM, 0.0])).round(3).tolist()
    [1.0, 0.5, 0.12]
    """
    lit = AMBIENT + (1.0 - AMBIENT) * np.abs(cos_incidence)
    return lit / (1.0 + (np.asarray(t_mm) / LAMP_FALLOFF_MM) ** 2)


def _marks(x: np.ndarray, spacing: float) -> np.ndarray:
    """Whether coordinates ``x`` (mm) lie on a mark every ``spacing``."""
    return np.abs(x - spacing * np.round(x / spacing)) < 0.5 * MARK_WIDTH_MM


class _Frame:
    """The per-frame buffers: each pixel's nearest hit so far, the cosine of its
    incidence (times a mark's darkening) and its material."""

    def __init__(self, n: int) -> None:
        self.t = np.full(n, np.inf, dtype=np.float32)
        self.cos = np.zeros(n, dtype=np.float32)
        self.mat = np.zeros(n, dtype=np.uint8)
        self.piece = np.zeros(n, dtype=np.intp)  # a pipe's pixel: the piece it shows

    def take(self, idx: np.ndarray, t: np.ndarray, cos: np.ndarray, mat: Material) -> None:
        """Pixels ``idx`` with hits at ``t``: kept where nearer than what they had."""
        nearer = t < self.t[idx]
        sel = idx[nearer]
        self.t[sel] = t[nearer]
        self.cos[sel] = cos[nearer]
        self.mat[sel] = mat

    def image(self, height: int, width: int) -> np.ndarray:
        """The pixels' colours (H, W, 3) uint8."""
        seen = np.isfinite(self.t)
        lit = np.where(seen, light(self.cos, np.where(seen, self.t, 0.0)), 1.0)
        rgb = PALETTE[self.mat] * lit[:, None].astype(np.float32)
        return np.clip(rgb, 0.0, 255.0).astype(np.uint8).reshape(height, width, 3)


def _cast_pieces(
    pp: PipePieces, k: np.ndarray, w: np.ndarray, DT: np.ndarray, far_only: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The nearest crossing (N,) of rays ``DT`` (3, N) with the walls of pieces ``k``
    (``w``: the camera from every piece's start, (S, 3)), and the piece crossed (inf, and
    any piece, where none is): per piece, the ray's crossings of its cylinder kept if
    between its mitre planes.  A ray from inside a tube leaves it first: only the far
    crossing of the pieces of the pipe the camera is in (``far_only``) can be its wall
    seen.  The arrays are (pieces, rays): a piece's row is contiguous."""
    f32 = np.float32
    u, n0, n1, wk = pp.u32[k], pp.n0_32[k], pp.n1_32[k], w[k]
    wu = np.einsum("ij,ij->i", wk, u)
    wp = wk - wu[:, None] * u  # across the axis
    A = u @ DT  # (S, N)
    A *= A
    np.subtract(f32(1.0), A, out=A)
    B = wp @ DT
    C = (np.einsum("ij,ij->i", wp, wp) - pp.radius32[k] ** 2)[:, None]
    sq = B * B
    sq -= A * C
    np.sqrt(sq, out=sq)  # NaN where the ray misses the cylinder: never good below
    inv = np.divide(f32(1.0), A, out=A)
    D0 = n0 @ DT
    D1 = n1 @ DT
    h0 = np.einsum("ij,ij->i", wk, n0)[:, None]
    h1 = np.einsum("ij,ij->i", wk - pp.ab32[k], n1)[:, None]
    best = np.full(B.shape, np.inf, dtype=f32)
    t = np.empty_like(B)
    good = np.empty(B.shape, dtype=bool)
    tmp = np.empty_like(B)
    signs = (f32(1.0),) if far_only[k].all() else (f32(1.0), f32(-1.0))
    for sign in signs:  # the far crossing first: the near one overwrites
        np.multiply(sq, sign, out=t)
        t -= B
        t *= inv
        np.greater(t, NEAR_MM, out=good)
        np.multiply(t, D0, out=tmp)
        tmp += h0
        good &= tmp >= 0.0
        np.multiply(t, D1, out=tmp)
        tmp += h1
        good &= tmp <= 0.0
        if sign < 0.0:
            good &= ~far_only[k][:, None]
        np.copyto(best, t, where=good)
    t, j = best[0], np.full(best.shape[1], k[0])
    for r in range(1, len(k)):
        nearer = best[r] < t
        t = np.where(nearer, best[r], t)
        j[nearer] = k[r]
    return t, j


def _inside(pp: PipePieces, w: np.ndarray) -> np.ndarray:
    """(S,) whether the camera (``w``: from every piece's start) is inside the pipe of
    each piece (inside one of its pieces)."""
    wu = np.einsum("ij,ij->i", w, pp.u)
    across = np.linalg.norm(w - wu[:, None] * pp.u, axis=1)
    h0 = np.einsum("ij,ij->i", w, pp.n0)
    h1 = np.einsum("ij,ij->i", w - (pp.b - pp.a), pp.n1)
    inside = (across < pp.radius) & (h0 >= 0.0) & (h1 <= 0.0)
    return np.isin(pp.pipe, pp.pipe[inside])


def _cast_pipes(
    f: _Frame, pp: PipePieces, cam: TipCamera, o: np.ndarray, R: np.ndarray, D: np.ndarray
) -> None:
    """The nearest hit of every ray on the pipes' walls (mitred tube pieces) and end
    faces.  The pieces in view are cast nearest first, :data:`PIECES_A_BATCH` at a time;
    a ray whose hit is nearer than any piece left can reach is done."""
    if not len(pp):
        return
    w = o - pp.a
    far_only = _inside(pp, w)
    w32 = w.astype(np.float32)
    mid = 0.5 * (pp.a + pp.b)
    reach = 0.5 * np.linalg.norm(pp.b - pp.a, axis=1) + 2.0 * pp.radius  # mitres included
    seen = np.flatnonzero(_in_view(cam, (mid - o) @ R, reach))
    lower = np.linalg.norm(mid[seen] - o, axis=1) - reach[seen]  # no crossing nearer
    order = np.argsort(lower)
    seen, lower = seen[order], np.append(lower[order], np.inf)
    active = np.arange(len(D))
    DT = np.ascontiguousarray(D.T)
    with np.errstate(invalid="ignore", divide="ignore"):
        for b in range(0, len(seen), PIECES_A_BATCH):
            if not len(active):
                break
            rays = DT if len(active) == len(D) else np.take(DT, active, axis=1)
            t, j = _cast_pieces(pp, seen[b : b + PIECES_A_BATCH], w32, rays, far_only)
            nearer = t < np.minimum(f.t[active], MAX_RANGE_MM)
            sel = active[nearer]
            f.t[sel], f.piece[sel], f.mat[sel] = t[nearer], j[nearer], Material.PIPE
            nxt = lower[min(b + PIECES_A_BATCH, len(seen))]
            active = active[f.t[active] > nxt]
    _shade_pipes(f, pp, w32, DT)
    ends = _in_view(cam, (pp.end_centre - o) @ R, 2.0 * pp.end_radius)
    for c, n, r in zip(pp.end_centre[ends], pp.end_normal[ends], pp.end_radius[ends], strict=True):
        _cast_disc(f, o, D, c, n, r, 2.0 * r)


def _shade_pipes(f: _Frame, pp: PipePieces, w32: np.ndarray, DT: np.ndarray) -> None:
    """The pipe's pixels: the cosine of their incidence, a ring's darkening, the line
    along the pipe.  Computed for every pixel (a pipe's view is mostly pipe), by
    components: (3, N) arrays, each piece's vectors taken by the pixel's piece."""
    pipe = f.mat == Material.PIPE
    j = f.piece
    t = np.where(pipe, f.t, np.float32(0.0))

    def per_pixel(v: np.ndarray) -> np.ndarray:  # (S, 3) -> (3, N)
        return np.take(np.ascontiguousarray(v.T), j, axis=1)

    u = per_pixel(pp.u32)
    rel = per_pixel(w32)
    rel += t * DT  # the hit from its piece's start
    along = (rel * u).sum(axis=0)
    rel -= along * u  # across the axis
    cos = (rel * DT).sum(axis=0) / np.take(pp.radius32, j)
    cos[_marks(np.take(pp.s0_32, j) + along, RING_SPACING_MM)] *= MARK_DARKEN
    np.copyto(f.cos, cos, where=pipe)
    side = (rel * per_pixel(pp.e2_32)).sum(axis=0)
    on_top = (rel * per_pixel(pp.e1_32)).sum(axis=0) > 0.0
    f.mat[pipe & on_top & (np.abs(side) < 0.5 * MARK_WIDTH_MM)] = Material.PIPE_LINE


def _cast_disc(
    f: _Frame, o: np.ndarray, D: np.ndarray, c: np.ndarray, n: np.ndarray, r0: float, r1: float
) -> None:
    """The ring between radii ``r0`` and ``r1`` about ``c`` in the plane of normal ``n``."""
    dn = D @ n.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (float((c - o) @ n) / dn).astype(np.float32)
    idx = np.flatnonzero((t > NEAR_MM) & (t < np.minimum(f.t, MAX_RANGE_MM)))
    if not len(idx):
        return
    t = t[idx]
    rho = np.linalg.norm(o + t[:, None] * D[idx] - c, axis=1)
    ring = (rho >= r0) & (rho <= r1)
    idx, t = idx[ring], t[ring]
    f.take(idx, t, dn[idx], Material.WALL)


def _cast_wall(f: _Frame, w: Wall, o: np.ndarray, D: np.ndarray) -> None:
    """A wall's face towards the camera, but for its openings and beyond its bounds."""
    n = w.normal
    s0 = float((o - w.point) @ n)
    face = math.copysign(0.5 * w.thickness, s0)
    dn = D @ n.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((face - s0) / dn).astype(np.float32)
    idx = np.flatnonzero((t > NEAR_MM) & (t < np.minimum(f.t, MAX_RANGE_MM)))
    if not len(idx):
        return
    t = t[idx]
    p = o + t[:, None] * D[idx]
    material = np.ones(len(idx), dtype=bool)
    for op in w.openings:
        rel = p - op.centre
        rel -= (rel @ n)[:, None] * n
        if isinstance(op, RectOpening):
            v = _unit(np.cross(n, op.u))
            u = np.cross(v, n)
            inside = (np.abs(rel @ u) < 0.5 * op.width) & (np.abs(rel @ v) < 0.5 * op.height)
        else:
            inside = np.einsum("ij,ij->i", rel, rel) < (0.5 * op.diameter) ** 2
        material &= ~inside
    for q, m in w.bounds:
        material &= (p - q) @ m >= 0.0
    idx, t, p = idx[material], t[material], p[material]
    cos = dn[idx]
    e1 = perpendicular(n)
    cos[_marks(p @ e1, WALL_GRID_MM) | _marks(p @ np.cross(n, e1), WALL_GRID_MM)] *= MARK_DARKEN
    f.take(idx, t, cos, Material.WALL)


def _in_view(cam: TipCamera, centres_cam: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Whether spheres (centres in the camera's frame) may be seen: in front of the camera,
    within range, inside the view's pyramid widened by their radius."""
    x, y, z = centres_cam.T
    half_w = 0.5 * cam.width / cam.fy
    half_h = 0.5 * cam.height / cam.fy
    slack_w = radius * math.sqrt(1.0 + half_w**2)
    slack_h = radius * math.sqrt(1.0 + half_h**2)
    return (
        (z > -radius)
        & (np.linalg.norm(centres_cam, axis=1) - radius < MAX_RANGE_MM)
        & (np.abs(x) <= z * half_w + slack_w)
        & (np.abs(y) <= z * half_h + slack_h)
    )


_CORNERS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)


def _cast_boxes(
    f: _Frame, sc: TipScene, cam: TipCamera, o: np.ndarray, R: np.ndarray, D: np.ndarray
) -> None:
    """Each box in view (the :data:`MAX_BOXES` nearest) by the slab test, over the
    pixels of its outline on the image (all pixels where it reaches behind the camera)."""
    if not len(sc.box_centre):
        return
    cc = (sc.box_centre - o) @ R  # centres in the camera's frame
    rad = np.linalg.norm(sc.box_half, axis=1)
    seen = np.flatnonzero(_in_view(cam, cc, rad))
    seen = seen[np.argsort(np.linalg.norm(cc[seen], axis=1))][:MAX_BOXES]
    W, H = cam.width, cam.height
    for k in seen:
        Rb, h, c = sc.box_rotation[k], sc.box_half[k], sc.box_centre[k]
        corners = ((c + (_CORNERS * h) @ Rb.T) - o) @ R  # in the camera's frame
        if (corners[:, 2] > NEAR_MM).all():
            px = cam.cx + cam.fy * corners[:, 0] / corners[:, 2]
            py = cam.cy + cam.fy * corners[:, 1] / corners[:, 2]
            c0, c1 = max(int(px.min()), 0), min(int(px.max()) + 1, W)
            r0, r1 = max(int(py.min()), 0), min(int(py.max()) + 1, H)
            if c0 >= c1 or r0 >= r1:
                continue
            idx = (np.arange(r0, r1)[:, None] * W + np.arange(c0, c1)[None, :]).ravel()
        else:
            idx = np.arange(W * H)
        d = D[idx] @ Rb.astype(np.float32)  # rays in the box's frame
        ob = (o - c) @ Rb
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(1.0) / d
            t1 = (-h - ob).astype(np.float32) * inv
            t2 = (h - ob).astype(np.float32) * inv
        near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
        far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
        tin, tout = near.max(axis=1), far.min(axis=1)
        hit = (tin <= tout) & (tin > NEAR_MM) & (tin < np.minimum(f.t[idx], MAX_RANGE_MM))
        axis = np.argmax(near, axis=1)[hit]
        idx, t = idx[hit], tin[hit]
        cos = d[hit][np.arange(len(idx)), axis]
        f.take(idx, t, cos, Material.BOX)


def _draw_trail(
    img: np.ndarray,
    depth: np.ndarray,
    cam: TipCamera,
    o: np.ndarray,
    R: np.ndarray,
    trail: np.ndarray,
) -> None:
    """The trail's points, every segment cut to 2 mm pieces, as 2 x 2 pixel dots where
    nothing nearer hides them."""
    p = np.asarray(trail, dtype=float)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    k = np.clip(np.ceil(seg / 2.0).astype(int), 1, 64)
    j = np.repeat(np.arange(len(seg)), k)
    frac = (np.arange(len(j)) - np.repeat(np.cumsum(k) - k, k)) / k[j]
    dense = np.vstack([p[j] + frac[:, None] * (p[j + 1] - p[j]), p[-1:]])
    q = (dense - o) @ R
    front = q[:, 2] > NEAR_MM
    q = q[front]
    u = np.floor(cam.cx + cam.fy * q[:, 0] / q[:, 2]).astype(int)
    v = np.floor(cam.cy + cam.fy * q[:, 1] / q[:, 2]).astype(int)
    dist = np.linalg.norm(q, axis=1)
    H, W = depth.shape
    for du in (0, 1):
        for dv in (0, 1):
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
            uu, vv, dd = uu[ok], vv[ok], dist[ok]
            shown = dd <= depth[vv, uu] + 1.0
            img[vv[shown], uu[shown]] = TRAIL_RGB


def _draw_cross(img: np.ndarray) -> None:
    H, W = img.shape[:2]
    cy, cx = H // 2, W // 2
    for a in range(2, CROSS_PX + 1):
        for y, x in ((cy, cx - a), (cy, cx + a - 1), (cy - a, cx), (cy + a - 1, cx)):
            img[y, x] = CROSS_RGB


def render(
    scene: TipScene,
    cam: TipCamera,
    position_mm: np.ndarray,
    R_world_from_cam: np.ndarray,
    trail_mm: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The camera's frame from ``position_mm`` (3,) with orientation ``R_world_from_cam``
    (3, 3; its z axis the view's direction): the image (H, W, 3) uint8 and each pixel's
    distance to what it shows (H, W) mm, inf where nothing is met (module doc)."""
    o = np.asarray(position_mm, dtype=float)
    R = np.asarray(R_world_from_cam, dtype=float)
    D = cam.rays @ R.T.astype(np.float32)  # the rays in the world's frame
    f = _Frame(len(D))
    _cast_pipes(f, scene.pipes, cam, o, R, D)
    for w in scene.walls:
        _cast_wall(f, w, o, D)
    _cast_boxes(f, scene, cam, o, R, D)
    img = f.image(cam.height, cam.width)
    depth = f.t.reshape(cam.height, cam.width)
    if trail_mm is not None and len(trail_mm) >= 2:
        _draw_trail(img, depth, cam, o, R, trail_mm)
    _draw_cross(img)
    return img, depth
