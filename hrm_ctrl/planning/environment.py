"""Environment models and the arm's clearance against them (issue 10).

An :class:`Environment` is a tuple of obstacles, each of which answers the signed
distance from a point to its *material* (mm, negative inside material) and the
gradient of that distance:

- :class:`Pipe`: the inner wall of a pipe, a circle of inner diameter ``D`` swept
  along an axis polyline.  Between the two end planes (normal to the axis at its
  ends, the *inside*), the free distance is ``D/2 - (distance to the axis)``,
  negative beyond the wall (the pipe is taken as embedded in solid material, so
  a link that leaves the bore sideways collides).  Outside the end planes the
  space is open: only the rim, the circle of radius ``D/2`` where the bore meets
  the end plane, is material there, and the free distance is the distance to the
  nearest rim circle.  This is continuous across an end plane inside the bore.
  "Outside an end plane" is beyond it with that end the nearest sample of the axis:
  where a folded axis (a U-bend of unequal legs) runs behind an end plane, the
  points about that leg are the pipe's, not open space (to the sample spacing,
  :data:`AXIS_SPACING`, about where the two are equally near).
- :class:`Wall`: an infinite plane slab (mid-plane through ``point``, unit
  ``normal``, ``thickness`` >= 0, 0 = a sheet) with openings cut through it
  (:class:`RoundOpening`, :class:`RectOpening`: prisms along the normal) and
  optional ``bounds``: half-planes ``(q, m)`` where the wall exists only on the
  side ``(p - q) . m >= 0`` (``m`` is projected onto the wall's plane).  The wall
  is the product of the slab and an in-plane region, so its distance is exact
  (``sqrt(max(|s| - t/2, 0)^2 + max(e, 0)^2)`` with ``s`` the offset from the
  mid-plane and ``e`` the in-plane signed distance); near an opening it is the
  distance to the opening's rim.  Where two in-plane limits meet (an opening
  crossing a bound, two overlapping openings) ``e`` is their maximum, a lower
  bound of the true distance (conservative).
- :class:`Box`: a solid box (centre, edge lengths, rotation); exact signed distance.

The clearance of a link (Sec. 4: a cylinder of the link's outer diameter from
joint centre to joint centre) is the minimum over the link's segment of the free
distance minus the link's radius (the link taken as a capsule, which at the joint
centres is where the next link continues anyway).  :func:`link_clearance` samples
every segment densely and refines the two lowest sampled minima by golden-section
search to better than 0.001 mm.

A link lying along a pipe's wall, 20 mm off the axis of a 70 mm pipe, with a
radius of 15 mm clears it by 35 - 20 - 15 = 0 mm:

>>> axis = KnownPath.from_points(np.array([[0, 0, 0], [500, 0, 0]], float))
>>> env = Environment((Pipe(axis, 70.0),))
>>> O = np.zeros((1, 13, 3)); O[0, :, 0] = np.linspace(10, 490, 13); O[0, :, 1] = 20.0
>>> bool(abs(link_clearance(env, O, np.full(12, 15.0))).max() < 1e-9)
True

A sheet wall x = 0 with a round opening of 80 mm at the origin: a point on the
axis of the opening 30 mm in front of it is 50 mm from the rim
(``sqrt(30^2 + 40^2)``), one 5 mm in front of the wall and 10 mm outside the rim
is 5 mm from it (a sheet of thickness 0 has no inside: its distance is never negative,
and a link crossing it has the clearance ``-radius``):

>>> wall = Wall(np.zeros(3), np.array([1.0, 0, 0]), openings=(RoundOpening(np.zeros(3), 80.0),))
>>> Environment((wall,)).free_distance(np.array([[30.0, 0, 0], [5, 50.0, 0]])).round(9).tolist()
[50.0, 5.0]
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from functools import cached_property
from typing import Any, TypeAlias

import numpy as np

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.point_tree import PointTree

AXIS_SPACING = 0.5  # mm, resampling of a pipe's axis for nearest-point queries
SAMPLES_PER_SEGMENT = 33  # samples of a link for its minimum (every <= 5.6 mm of 179 mm)
REFINED_MINIMA = 2  # lowest sampled local minima of a link refined by golden section
GOLDEN_ITERATIONS = 20  # the bracket (2 sample spacings, <= 11.2 mm) shrinks to < 0.0011 mm
DISPLAY_GOLDEN_ITERATIONS = 8  # to < 0.25 mm: a clearance shown, not one planned with
_EPS = 1e-12


def _vec3(v: object, what: str) -> np.ndarray:
    a = np.array(v, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise PlanningError(f"{what} must be 3 finite numbers, got {v!r}")
    a.setflags(write=False)
    return a


def _unit(v: object, what: str) -> np.ndarray:
    a = np.array(_vec3(v, what))
    if not np.any(a):
        raise PlanningError(f"{what} must not be the zero vector")
    a /= np.abs(a).max()  # first: the norm of [1e308, 1e308, 0] is no overflow
    a /= np.linalg.norm(a)
    a.setflags(write=False)
    return a


def _positive(v: float, what: str, zero_ok: bool = False) -> float:
    x = float(v)
    if not math.isfinite(x) or x < 0.0 or (x == 0.0 and not zero_ok):
        raise PlanningError(f"{what} must be a finite number > {'=' if zero_ok else ''}0, got {v}")
    return x


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...j,...j->...", v, v))


def _safe_unit(v: np.ndarray) -> np.ndarray:
    n = _norm(v)
    return v / np.where(n > _EPS, n, 1.0)[..., None]


@dataclass(frozen=True, eq=False)
class Pipe:
    """The inner wall of a pipe of ``inner_diameter`` (mm) around ``axis``.

    >>> axis = KnownPath.from_points(np.array([[0, 0, 0], [100, 0, 0]], float))
    >>> p = Pipe(axis, 70.0)
    >>> p.free_distance(np.array([[50, 10, 0], [50, 0, 40], [-30, 0, 0]], float)).round(9).tolist()
    [25.0, -5.0, 46.097722286]
    """

    axis: KnownPath
    inner_diameter: float

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "inner_diameter", _positive(self.inner_diameter, "pipe inner diameter")
        )

    @property
    def inner_radius(self) -> float:
        return 0.5 * self.inner_diameter

    @cached_property
    def _dense(self) -> tuple[np.ndarray, PointTree]:
        s, pts = self.axis.s, self.axis.points
        k = np.maximum(np.ceil(np.diff(s) / AXIS_SPACING).astype(np.int64), 1)
        t = np.concatenate([np.arange(kk) / kk for kk in k])
        j = np.repeat(np.arange(len(k)), k)
        dense = np.vstack((pts[j] + t[:, None] * (pts[j + 1] - pts[j]), pts[-1]))
        return dense, PointTree(dense)

    @cached_property
    def _ends(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """(point, unit normal into the pipe) of the start and end planes."""
        a = self.axis
        return (a.points[0], a.tangent_at(0.0)), (a.points[-1], -a.tangent_at(a.length))

    @cached_property
    def _open_radii(self) -> tuple[float, float]:
        """Per end: the distance (mm) from the end's axis line (through the end, along its
        normal) within which a point beyond the end's plane has that end as its nearest
        axis sample X (not nearer when ``w . (X - E) <= |X - E|^2 / 2``, w the point's
        offset from the line); 0 where the axis runs behind the plane (always looked up)."""
        dense = self._dense[0]
        radii = []
        for P, n in self._ends:
            rel = dense - P
            h = rel @ n
            if np.any(h < -1e-9):
                radii.append(0.0)
                continue
            lateral = _norm(rel - h[:, None] * n)
            far = lateral > 1e-9
            ratio = np.einsum("ij,ij->i", rel[far], rel[far]) / (2.0 * lateral[far])
            radii.append(float(ratio.min()) if far.any() else math.inf)
        return radii[0], radii[1]

    @cached_property
    def _segments(self) -> np.ndarray:
        """The segments of the resampled axis as the rows (7, S) of their constants for
        :meth:`_nearest`: each segment's start A (rows 0-2), A -> B (3-5) and |AB|^2 (6, 1
        where 0), component by component, so that one indexing gathers every constant of
        the points' segments in contiguous (7, P, 4) blocks."""
        dense = self._dense[0]
        if len(dense) < 2:  # segs are clipped to -1 then: the one sample, a point
            table = np.hstack((dense, np.zeros_like(dense), np.ones((len(dense), 1))))
        else:
            A = dense[:-1]
            AB = dense[1:] - A
            L2 = np.einsum("sj,sj->s", AB, AB)
            table = np.hstack((A, AB, np.where(L2 > 0, L2, 1.0)[:, None]))
        table = np.ascontiguousarray(table.T)
        table.setflags(write=False)
        return table

    def _samples(self, q: np.ndarray) -> np.ndarray:
        """(P, 3) points -> (P, k) indices of their nearest (k = 2) axis samples, nearest first."""
        dense, tree = self._dense
        _, v = tree.query(q, k=min(2, len(dense)))
        return np.asarray(v).reshape(len(q), -1)

    def _nearest(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points and their nearest samples ``v`` (:meth:`_samples`) -> q - C (P, 3)
        and |q - C| (P,), C the nearest axis points: the segments on either side of the
        samples (four per point) projected in one batch, component by component (each
        operation on a contiguous (P, 4) block: a fraction of the cost of (P, 4, 3)
        arrays' sums over their last axis).

        >>> axis = KnownPath.from_points(np.array([[0, 0, 0], [100, 0, 0]], float))
        >>> p = Pipe(axis, 70.0)
        >>> q = np.array([[50.0, 3, 4], [120, 0, 0]])
        >>> rel, dist = p._nearest(q, p._samples(q))
        >>> rel.tolist(), dist.tolist()
        ([[0.0, 3.0, 4.0], [20.0, 0.0, 0.0]], [5.0, 20.0])
        """
        table = self._segments
        segs = np.concatenate((v - 1, v), axis=1)  # (P, 4)
        np.minimum(np.maximum(segs, 0, out=segs), table.shape[1] - 1, out=segs)
        seg = table[:, segs]  # (7, P, 4)
        AB = seg[3:6]
        rel = q.T[:, :, None] - seg[:3]  # (3, P, 4): from each segment's start ...
        t = rel[0] * AB[0]  # the sums in einsum's order over (..., 3): 0 + 2, then 1
        t += rel[2] * AB[2]
        t += rel[1] * AB[1]
        t /= seg[6]
        np.minimum(np.maximum(t, 0.0, out=t), 1.0, out=t)
        AB *= t
        rel -= AB  # ... then from its nearest point
        d2 = rel[0] * rel[0]
        d2 += rel[2] * rel[2]
        d2 += rel[1] * rel[1]
        dist = np.sqrt(d2, out=d2)
        best = np.argmin(dist, axis=1)
        i = np.arange(len(q))
        return rel[:, i, best].T, dist[i, best]

    def _inside_distance_and_gradient(
        self, q: np.ndarray, v: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points of the pipe, their nearest samples -> ``r - |q - C|``, its gradient."""
        rel, dist = self._nearest(q, v)
        g = rel / np.where(dist > _EPS, -dist, -1.0)[:, None]  # = -(q - C) / |q - C|
        return self.inner_radius - dist, g

    def _rim_distance_and_gradient(
        self, rel: np.ndarray, h: np.ndarray, n: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Points ``rel`` (M, 3) from an end's centre, ``h`` (M,) along its normal ``n`` ->
        their distance to the end's rim circle and its gradient."""
        radial = rel - h[:, None] * n
        nr = _norm(radial)
        flat = nr <= _EPS  # on the axis line: any rim point
        u = radial / np.where(flat, 1.0, nr)[:, None]
        if flat.any():
            e = np.eye(3)[int(np.argmin(np.abs(n)))]
            u[flat] = _safe_unit(e - (e @ n) * n)
        w = rel - self.inner_radius * u  # from the nearest rim point
        dw = _norm(w)
        return dw, w / np.where(dw > _EPS, dw, 1.0)[:, None]

    def free_distance_and_gradient(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points -> distance (P,) to the pipe's material and its gradient (P, 3)."""
        r = self.inner_radius
        if not len(q):
            return np.empty(0), np.zeros_like(q)
        (A, nA), (B, nB) = self._ends
        relA, relB = q - A, q - B
        hA = relA @ nA  # > 0: past the start plane
        hB = relB @ nB  # > 0: before the end plane
        beyond_A, beyond_B = hA < 0.0, hB < 0.0
        if not (beyond_A.any() or beyond_B.any()):  # all inside: no masks
            return self._inside_distance_and_gradient(q, self._samples(q))
        # beyond a plane: open space only where that end is the nearest axis sample (a
        # folded axis's other leg may run behind the plane); surely so within _open_radii
        # of the end's axis line, else looked up (with the samples of the inside points)
        rA, rB = self._open_radii
        out = beyond_A & (np.einsum("ij,ij->i", relA, relA) - hA * hA < rA * rA)
        if beyond_B.any():
            out |= beyond_B & (np.einsum("ij,ij->i", relB, relB) - hB * hB < rB * rB)
        d = np.empty(len(q))
        g = np.empty_like(q)
        cand = np.flatnonzero(~out)  # inside, or beyond a plane and looked up
        if len(cand):
            v = self._samples(q[cand])
            at_end = (v[:, 0] == 0) & beyond_A[cand]
            if beyond_B.any():
                at_end |= (v[:, 0] == len(self._dense[0]) - 1) & beyond_B[cand]
            if at_end.any():
                out[cand[at_end]] = True
                keep = ~at_end
                cand, v = cand[keep], v[keep]
            d[cand], g[cand] = self._inside_distance_and_gradient(q[cand], v)
        if len(cand) < len(q):  # to the start's rim, then the end's where nearer
            best, bg = self._rim_distance_and_gradient(relA[out], hA[out], nA)
            seen = best < math.inf
            if not seen.all():  # a point at infinity (or NaN): no gradient
                best = np.where(seen, best, math.inf)
                bg = np.where(seen[:, None], bg, 0.0)
            relB = relB[out]
            # |q - B| - r is a lower bound of the distance to the end's rim: skip it where
            # that is surely no nearer (the margin covers rounding; NaN compares false)
            if not np.all(_norm(relB) - (r + 1e-6) >= best):
                dw, gw = self._rim_distance_and_gradient(relB, hB[out], nB)
                better = dw < best
                best = np.where(better, dw, best)
                bg = np.where(better[:, None], gw, bg)
            d[out], g[out] = best, bg
        return d, g

    def free_distance(self, q: np.ndarray) -> np.ndarray:
        return self.free_distance_and_gradient(q)[0]


@dataclass(frozen=True, eq=False)
class RoundOpening:
    """A round hole of ``diameter`` (mm) centred at ``centre`` (projected onto the wall)."""

    centre: np.ndarray
    diameter: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vec3(self.centre, "opening centre"))
        object.__setattr__(self, "diameter", _positive(self.diameter, "opening diameter"))


@dataclass(frozen=True, eq=False)
class RectOpening:
    """A rectangular hole ``width`` x ``height`` (mm) centred at ``centre``; ``u`` is the
    in-plane direction of the width (projected onto the wall, normalised), the height runs
    along ``normal x u``."""

    centre: np.ndarray
    width: float
    height: float
    u: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vec3(self.centre, "opening centre"))
        object.__setattr__(self, "width", _positive(self.width, "opening width"))
        object.__setattr__(self, "height", _positive(self.height, "opening height"))
        object.__setattr__(self, "u", _unit(self.u, "opening width direction u"))


Opening: TypeAlias = RoundOpening | RectOpening


class OpeningShape(StrEnum):
    """The shape of a wall opening, as a scene file names it."""

    ROUND = "round"
    RECT = "rect"


def _sd_box2(x: np.ndarray, y: np.ndarray, hx: float, hy: float):
    """Signed distance to the rectangle |x| <= hx, |y| <= hy and its gradient (gx, gy)."""
    ax, ay = np.abs(x) - hx, np.abs(y) - hy
    ox, oy = np.maximum(ax, 0.0), np.maximum(ay, 0.0)
    on = np.hypot(ox, oy)
    outside = on > 0.0
    sx, sy = np.where(x < 0, -1.0, 1.0), np.where(y < 0, -1.0, 1.0)
    xk = ax >= ay
    d = np.where(outside, on, np.maximum(ax, ay))
    safe = np.where(outside, on, 1.0)
    gx = np.where(outside, ox / safe * sx, np.where(xk, sx, 0.0))
    gy = np.where(outside, oy / safe * sy, np.where(xk, 0.0, sy))
    return d, gx, gy


@dataclass(frozen=True, eq=False)
class Wall:
    """A plane slab with openings (see the module docstring).

    ``bounds``: pairs ``(q, m)``; the wall exists only where ``(p - q) . m >= 0``.

    >>> w = Wall(np.zeros(3), np.array([0, 0, 2.0]), thickness=10.0)
    >>> w.normal.tolist(), w.free_distance(np.array([[0, 0, 8.0], [3, 4, 2.0]])).tolist()
    ([0.0, 0.0, 1.0], [3.0, -3.0])
    """

    point: np.ndarray
    normal: np.ndarray
    thickness: float = 0.0
    openings: tuple[Opening, ...] = ()
    bounds: tuple[tuple[np.ndarray, np.ndarray], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "point", _vec3(self.point, "wall point"))
        n = _unit(self.normal, "wall normal")
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "thickness", _positive(self.thickness, "wall thickness", True))
        object.__setattr__(self, "openings", tuple(self.openings))
        for o in self.openings:
            if not isinstance(o, RoundOpening | RectOpening):
                raise PlanningError(f"a wall opening must be round or rect, got {o!r}")
            if isinstance(o, RectOpening) and abs(float(o.u @ n)) > 1.0 - 1e-9:
                raise PlanningError("a rect opening's width direction u is normal to its wall")
        bounds = []
        for q, m in self.bounds:
            m = np.array(_unit(m, "wall bound normal"))
            m -= (m @ n) * n
            if np.linalg.norm(m) < 1e-9:
                raise PlanningError("a wall bound's normal must not be normal to the wall")
            bounds.append((_vec3(q, "wall bound point"), _unit(m, "wall bound normal")))
        object.__setattr__(self, "bounds", tuple(bounds))

    def free_distance_and_gradient(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points -> distance (P,) to the wall's material and its gradient (P, 3)."""
        n = self.normal
        s = (q - self.point) @ n
        ds = np.abs(s) - 0.5 * self.thickness
        gs = np.where(s < 0, -1.0, 1.0)[:, None] * n
        # in-plane signed distance e to the wall's region: max over the limits
        e = np.full(len(q), -math.inf)
        ge = np.zeros_like(q)
        for o in self.openings:
            rel = q - o.centre
            rel = rel - (rel @ n)[:, None] * n
            if isinstance(o, RoundOpening):
                rho = _norm(rel)
                ek = 0.5 * o.diameter - rho  # minus the opening's signed distance
                gk = -_safe_unit(rel)
            else:
                v = np.cross(n, o.u)
                v /= np.linalg.norm(v)
                u = np.cross(v, n)
                sd, gx, gy = _sd_box2(rel @ u, rel @ v, 0.5 * o.width, 0.5 * o.height)
                ek = -sd
                gk = -(gx[:, None] * u + gy[:, None] * v)
            take = ek > e
            e = np.where(take, ek, e)
            ge = np.where(take[:, None], gk, ge)
        for bq, m in self.bounds:
            ek = -((q - bq) @ m)
            take = ek > e
            e = np.where(take, ek, e)
            ge = np.where(take[:, None], -m, ge)
        # the slab times the region (exact signed distance of a product of sets)
        os_, oe = np.maximum(ds, 0.0), np.maximum(e, 0.0)
        on = np.hypot(os_, oe)
        outside = on > 0.0
        safe = np.where(outside, on, 1.0)[:, None]
        g_out = (os_[:, None] * gs + oe[:, None] * ge) / safe
        g_in = np.where((ds >= e)[:, None], gs, ge)
        d = np.where(outside, on, np.maximum(ds, e))
        return d, np.where(outside[:, None], g_out, g_in)

    def free_distance(self, q: np.ndarray) -> np.ndarray:
        return self.free_distance_and_gradient(q)[0]


def _box_distance_and_gradient(x: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``x`` (P, 3) in a box's coordinates, its half edge lengths ``half`` (3,) or
    (P, 3) -> signed distance (P,) to the box and its gradient (P, 3), box coordinates."""
    a = np.abs(x) - half
    o = np.maximum(a, 0.0)
    on = _norm(o)
    outside = on > 0.0
    sgn = np.where(x < 0, -1.0, 1.0)
    k = np.argmax(a, axis=1)
    g_in = np.zeros_like(x)
    g_in[np.arange(len(x)), k] = sgn[np.arange(len(x)), k]
    g_out = o * sgn / np.where(outside, on, 1.0)[:, None]
    d = np.where(outside, on, a.max(axis=1))
    return d, np.where(outside[:, None], g_out, g_in)


@dataclass(frozen=True, eq=False)
class Box:
    """A solid box: ``centre`` (3,), edge lengths ``size`` (3,), world-from-box ``rotation``.

    >>> b = Box(np.zeros(3), np.array([20.0, 20.0, 20.0]))
    >>> b.free_distance(np.array([[13, 0, 0], [13, 14, 0], [5, 0, 0]], float)).tolist()
    [3.0, 5.0, -5.0]
    """

    centre: np.ndarray
    size: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", _vec3(self.centre, "box centre"))
        size = _vec3(self.size, "box size")
        if np.any(size <= 0.0):
            raise PlanningError(f"box size must be > 0 on every axis, got {size.tolist()}")
        object.__setattr__(self, "size", size)
        R = np.array(self.rotation, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise PlanningError("box rotation must be a finite 3 x 3 matrix")
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0.0:
            raise PlanningError("box rotation must be a rotation matrix (orthonormal, det +1)")
        R.setflags(write=False)
        object.__setattr__(self, "rotation", R)

    def free_distance_and_gradient(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3) points -> signed distance (P,) to the box and its gradient (P, 3)."""
        R = self.rotation
        d, g = _box_distance_and_gradient((q - self.centre) @ R, 0.5 * self.size)
        return d, g @ R.T

    def free_distance(self, q: np.ndarray) -> np.ndarray:
        return self.free_distance_and_gradient(q)[0]


Obstacle: TypeAlias = Pipe | Wall | Box

#: an environment with at least this many boxes finds each point's boxes in a spatial
#: index (:class:`BoxIndex`); fewer are each evaluated at every point
BROAD_PHASE_MIN_BOXES = 4
BROAD_PHASE_NEIGHBOURS = 4  # box centres looked up per point first (more where needed)


class BoxIndex:
    """Boxes of one size class (bounding-sphere radii within a factor of 2) in a k-d tree of
    their centres: the broad phase of :meth:`Environment.free_distance_and_gradient`.

    A box lies inside the sphere of radius ``rho`` (half its diagonal) about its centre,
    so its signed distance from a point ``q`` is at least ``|q - c| - rho`` (inside the box
    too).  A point whose nearest centre is farther than its distance so far plus the
    largest ``rho`` is done; for the others, their nearest box centres are looked up
    (:data:`BROAD_PHASE_NEIGHBOURS`) and only those boxes evaluated;
    every other box is at least the k-th centre's distance minus the largest ``rho``
    away: where that is no nearer than the distance found, the point is done, else it is
    looked up again with four times as many centres.  The result is exact; its cost
    grows with the boxes near the points, not with the boxes in the scene.

    >>> boxes = [Box(np.array([100.0 * k, 0, 0]), np.full(3, 10.0)) for k in range(50)]
    >>> idx = BoxIndex(boxes)
    >>> d, g = np.full(2, math.inf), np.zeros((2, 3))
    >>> idx.lower(np.array([[300.0, 30, 0], [-40.0, 0, 0]]), d, g)
    >>> d.tolist(), g.tolist()
    ([25.0, 35.0], [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    """

    def __init__(self, boxes: list[Box]) -> None:
        self.centre = np.array([b.centre for b in boxes], dtype=float).reshape(-1, 3)
        self.half = 0.5 * np.array([b.size for b in boxes], dtype=float).reshape(-1, 3)
        self.rotation = np.array([b.rotation for b in boxes], dtype=float).reshape(-1, 3, 3)
        self.rho_max = float(_norm(self.half).max())
        self.tree = PointTree(self.centre)

    def __len__(self) -> int:
        return len(self.centre)

    def _pairs(self, q: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (M, 3) and a box index each (M,) -> signed distance (M,), gradient (M, 3)."""
        R = self.rotation[box]
        x = np.einsum("mj,mjk->mk", q - self.centre[box], R)
        d, gl = _box_distance_and_gradient(x, self.half[box])
        return d, np.einsum("mk,mjk->mj", gl, R)

    def _lower_pairs(
        self, q: np.ndarray, d: np.ndarray, g: np.ndarray, pts: np.ndarray, box: np.ndarray
    ) -> None:
        """Evaluate box ``box[m]`` at point ``pts[m]`` (a point may come more than once) and
        lower ``d``, ``g`` to each point's nearest of them where nearer (in place)."""
        if not len(pts):
            return
        db, gb = self._pairs(q[pts], box)
        order = np.lexsort((db, pts))  # by point, nearest box first
        ps = pts[order]
        sel = order[np.concatenate(([True], ps[1:] != ps[:-1]))]  # each point's nearest
        p, best = pts[sel], db[sel]
        take = best < d[p]
        d[p[take]] = best[take]
        g[p[take]] = gb[sel[take]]

    def lower(self, q: np.ndarray, d: np.ndarray, g: np.ndarray) -> None:
        """Lower ``d`` (P,) and ``g`` (P, 3), the distance and gradient of points ``q``
        (P, 3) so far, to these boxes' where one is nearer (in place)."""
        n, rho = len(self), self.rho_max
        if not len(q):
            return
        # the nearest centre first: most points (inside a pipe, beside a wall) are nearer
        # to something else than any of these boxes can be, and are done; the others
        # take their nearest centre's box (most often the nearest box)
        dist, box = self.tree.query(q, k=1, distance_upper_bound=float(d.max()) + rho)
        todo = np.flatnonzero(dist - rho < d)
        self._lower_pairs(q, d, g, todo, box[todo])
        seen, k = 1, min(BROAD_PHASE_NEIGHBOURS, n)
        while len(todo) and seen < n:
            qq = q[todo]
            reach = float(d[todo].max()) + rho
            dist, box = self.tree.query(qq, k=k, distance_upper_bound=reach)
            dist, box = dist.reshape(len(qq), k), box.reshape(len(qq), k)
            near = (box < n) & (dist - rho < d[todo][:, None])
            near[:, :seen] = False  # evaluated in an earlier round
            rows, cols = np.nonzero(near)
            self._lower_pairs(q, d, g, todo[rows], box[rows, cols])
            # done: fewer than k centres within reach, or the k-th one's sphere no nearer
            done = (box[:, -1] == n) | (dist[:, -1] - rho >= d[todo])
            todo = todo[~done]
            seen, k = k, min(4 * k, n)


def _box_indices(boxes: list[Box]) -> tuple[BoxIndex, ...]:
    """The boxes in one :class:`BoxIndex` per size class (half diagonals in [2^i, 2^(i+1)))."""
    rho = np.array([0.5 * float(np.linalg.norm(b.size)) for b in boxes])
    cls = np.floor(np.log2(rho)).astype(np.int64)
    return tuple(
        BoxIndex([b for b, c in zip(boxes, cls, strict=True) if c == k]) for k in np.unique(cls)
    )


@dataclass(frozen=True, eq=False)
class Environment:
    """The obstacles the arm moves among; empty = free space (distance +inf).

    >>> box = Box(np.array([100.0, 0, 0]), np.array([10.0, 10, 10]))
    >>> d, g = Environment((box,)).free_distance_and_gradient(np.array([0.0, 0, 0]))
    >>> float(d), g.tolist()
    (95.0, [-1.0, 0.0, 0.0])
    >>> Environment().free_distance(np.zeros((2, 3))).tolist()
    [inf, inf]
    """

    obstacles: tuple[Obstacle, ...] = ()

    def __post_init__(self) -> None:
        obs = tuple(self.obstacles)
        for o in obs:
            if not isinstance(o, Pipe | Wall | Box):
                raise PlanningError(f"an obstacle must be a Pipe, Wall or Box, got {o!r}")
        object.__setattr__(self, "obstacles", obs)

    def to_dict(self) -> dict[str, Any]:
        """The environment as scene data (the tables of a scene file,
        :mod:`hrm_ctrl.formats.scene`): lists ``pipe``, ``wall``, ``box``, the empty ones left out.

        >>> Environment((Box(np.zeros(3), np.ones(3)),)).to_dict()["box"][0]["size_mm"]
        [1.0, 1.0, 1.0]
        """
        out: dict[str, list[dict[str, Any]]] = {"pipe": [], "wall": [], "box": []}
        for o in self.obstacles:
            if isinstance(o, Pipe):
                out["pipe"].append(
                    {"axis_mm": o.axis.points.tolist(), "inner_diameter_mm": o.inner_diameter}
                )
            elif isinstance(o, Wall):
                w: dict[str, Any] = {
                    "point_mm": o.point.tolist(),
                    "normal": o.normal.tolist(),
                    "thickness_mm": o.thickness,
                }
                ops = []
                for op in o.openings:
                    if isinstance(op, RoundOpening):
                        ops.append(
                            {
                                "shape": OpeningShape.ROUND.value,
                                "centre_mm": op.centre.tolist(),
                                "diameter_mm": op.diameter,
                            }
                        )
                    else:
                        ops.append(
                            {
                                "shape": OpeningShape.RECT.value,
                                "centre_mm": op.centre.tolist(),
                                "width_mm": op.width,
                                "height_mm": op.height,
                                "u": op.u.tolist(),
                            }
                        )
                if ops:
                    w["opening"] = ops
                if o.bounds:
                    w["bound"] = [
                        {"point_mm": q.tolist(), "normal": m.tolist()} for q, m in o.bounds
                    ]
                out["wall"].append(w)
            else:
                out["box"].append(
                    {
                        "centre_mm": o.centre.tolist(),
                        "size_mm": o.size.tolist(),
                        "rotation": o.rotation.tolist(),
                    }
                )
        return {k: v for k, v in out.items() if v}

    @cached_property
    def _broad_phase(self) -> tuple[tuple[Obstacle, ...], tuple[BoxIndex, ...]]:
        """(the obstacles evaluated at every point, the boxes' spatial indices): with
        fewer than :data:`BROAD_PHASE_MIN_BOXES` boxes, every obstacle and no index."""
        boxes = [o for o in self.obstacles if isinstance(o, Box)]
        if len(boxes) < BROAD_PHASE_MIN_BOXES:
            return self.obstacles, ()
        rest = tuple(o for o in self.obstacles if not isinstance(o, Box))
        return rest, _box_indices(boxes)

    def free_distance_and_gradient(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) points -> distance (...) to the nearest material (mm, negative inside)
        and its gradient (..., 3) (of the nearest obstacle; zero in free space).

        Pipes and walls (unbounded: a pipe is embedded in material, a wall is a plane)
        are evaluated at every point; many boxes are found through spatial indices
        (:class:`BoxIndex`), so boxes far from the points cost next to nothing."""
        p = np.asarray(p, dtype=float)
        if p.shape[-1:] != (3,):
            raise PlanningError(f"points must have shape (..., 3), got {p.shape}")
        shape = p.shape[:-1]
        q = p.reshape(-1, 3)
        d = np.full(len(q), math.inf)
        g = np.zeros_like(q)
        if len(q):
            everywhere, indices = self._broad_phase
            for o in everywhere:
                dk, gk = o.free_distance_and_gradient(q)
                take = dk < d
                if take.all():  # the first obstacle (or one nearer everywhere): no blend
                    d, g = dk, gk
                    continue
                d = np.where(take, dk, d)
                g = np.where(take[:, None], gk, g)
            if indices:
                d, g = np.array(d), np.array(g)  # written in place: never an obstacle's own
                for index in indices:
                    index.lower(q, d, g)
        return d.reshape(shape), g.reshape(*shape, 3)

    def free_distance(self, p: np.ndarray) -> np.ndarray:
        """(..., 3) points -> (...) distance to the nearest obstacle material (mm),
        negative inside material."""
        return self.free_distance_and_gradient(p)[0]


def link_clearance(
    env: Environment,
    O: np.ndarray,
    radius: np.ndarray,
    *,
    iterations: int = GOLDEN_ITERATIONS,
) -> np.ndarray:
    """O (N, 13, 3) joint centres and end point, radius (12,) link outer radii ->
    (N, 12) clearance: the minimum over each link's segment of the free distance
    minus the link's radius (negative = collision; +inf in free space).

    Each segment is sampled at :data:`SAMPLES_PER_SEGMENT` points; around its
    :data:`REFINED_MINIMA` lowest sampled local minima, a golden-section search over
    the two neighbouring sample intervals finds the minimum to < 0.001 mm
    (``iterations`` steps: each shrinks the bracket by 0.618, and a display needs
    fewer, :data:`DISPLAY_GOLDEN_ITERATIONS`).

    >>> env = Environment((Box(np.zeros(3), np.array([10.0, 10, 10])),))
    >>> O = np.zeros((1, 3, 3)); O[0, :, 0] = [-50, 50, 150]; O[0, :, 1] = 20.0
    >>> link_clearance(env, O, np.array([5.0, 5.0])).round(9).tolist()  # 20 - 5 - 5, |(45, 15)| - 5
    [[10.0, 42.434164903]]
    """
    O = np.asarray(O, dtype=float)
    if O.ndim == 2:
        O = O[None]
    if O.ndim != 3 or O.shape[-1] != 3 or O.shape[1] < 2:
        raise PlanningError(f"joint centres must have shape (N, links + 1, 3), got {O.shape}")
    radius = np.broadcast_to(np.asarray(radius, dtype=float), (O.shape[1] - 1,))
    N, L = O.shape[0], O.shape[1] - 1
    if not env.obstacles or N == 0:
        return np.full((N, L), math.inf)
    P0, D = O[:, :-1], O[:, 1:] - O[:, :-1]  # (N, L, 3)
    S = SAMPLES_PER_SEGMENT
    t = np.linspace(0.0, 1.0, S)
    f = env.free_distance(P0[:, :, None, :] + t[None, None, :, None] * D[:, :, None, :])
    best = f.min(axis=2)
    # local minima of the samples (plateaus count once per sample: harmless)
    left = np.concatenate((np.full((N, L, 1), math.inf), f[:, :, :-1]), axis=2)
    right = np.concatenate((f[:, :, 1:], np.full((N, L, 1), math.inf)), axis=2)
    cand = np.where((f <= left) & (f <= right), f, math.inf)
    k = min(REFINED_MINIMA, S)
    idx = np.argsort(cand, axis=2)[:, :, :k]  # (N, L, k)
    finite = np.isfinite(np.take_along_axis(cand, idx, axis=2))
    h = 1.0 / (S - 1)
    lo = np.clip(idx * h - h, 0.0, 1.0)
    hi = np.clip(idx * h + h, 0.0, 1.0)
    P0k, Dk = P0[:, :, None, :], D[:, :, None, :]

    def at(u: np.ndarray) -> np.ndarray:
        return env.free_distance(P0k + u[..., None] * Dk)

    phi = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - phi * (b - a), a + phi * (b - a)
    fc, fd = at(c), at(d)
    for _ in range(iterations):
        left_better = fc < fd
        b = np.where(left_better, d, b)
        a = np.where(left_better, a, c)
        c_new = b - phi * (b - a)
        d_new = a + phi * (b - a)
        # the kept interior point is reused; one new evaluation per iteration
        c2 = np.where(left_better, c_new, d)
        d2 = np.where(left_better, c, d_new)
        fnew = at(np.where(left_better, c_new, d_new))
        fc2 = np.where(left_better, fnew, fd)
        fd2 = np.where(left_better, fc, fnew)
        c, d, fc, fd = c2, d2, fc2, fd2
    refined = np.where(finite, np.minimum(fc, fd), math.inf).min(axis=2)
    return np.minimum(best, refined) - radius[None, :]


def worst_clearance(env: Environment, O: np.ndarray, radius: np.ndarray) -> tuple[float, int, int]:
    """The smallest clearance (mm) over all steps and links of ``O`` (N, 13, 3), with its
    0-based step and 1-based link; ``(inf, -1, 0)`` when nothing is near (no obstacles).

    >>> env = Environment((Box(np.zeros(3), np.array([10.0, 10, 10])),))
    >>> O = np.zeros((2, 3, 3)); O[:, :, 0] = [-50, 50, 150]; O[:, :, 1] = [[20.0], [8.0]]
    >>> v, step, link = worst_clearance(env, O, np.array([5.0, 5.0]))
    >>> round(v, 9), step, link
    (-2.0, 1, 1)
    """
    c = link_clearance(env, O, radius)
    if c.size == 0 or not np.isfinite(c).any():
        return math.inf, -1, 0
    i, j = np.unravel_index(int(np.argmin(c)), c.shape)
    return float(c[i, j]), int(i), int(j) + 1
