"""Path conditioning: can the arm follow a path with its joints on it, and rounding corners.

**What a joint can bend.**  A universal joint turns the next link by Eq. (1)'s
``Rot_y(α) Rot_x(θ)``: the link's direction ``z`` becomes
``(cos θ sin α, −sin θ, cos α cos θ)``, so the *combined bend* between the two links is
``φ = arccos(cos α cos θ)``.  With ``|α| < α_max`` and ``|θ| < θ_max`` a bend of any
direction is possible as long as ``φ < φ_max = min(α_max, θ_max)``: ``cos φ = cos α cos θ``
with ``cos θ <= 1`` gives ``cos α >= cos φ``, so ``|α| <= φ`` (and the same for θ).  A larger
bend fits only in some directions (up to ``arccos(cos α_max cos θ_max)``, 75.5° for 60°
limits, towards the diagonal), and the arm has no roll joint to choose the direction of its
bends: the path does.  So φ_max is what a joint can be relied on to bend, 60° for Table 1.

**Joints on the path.**  The planner puts the joint centres on the path (Sec. 3.3), so the
links are chords of it: the joint at travel ``s`` with link ``l_b`` behind and ``l_a``
ahead bends by the angle between the chord to the path point ``l_b`` behind (straight
back along the start tangent before the path's start, where the modal curve joins it
tangentially) and the chord to the path point ``l_a`` ahead.  On a circle of radius R this
bend is ``asin(l_b / 2R) + asin(l_a / 2R)``, so equal links ``l`` follow a circle of
radius ``R >= l / (2 sin(φ_max / 2))``: :func:`smallest_bend_radius`, 179 mm for Table 1.
A *shorter* bend may be tighter (even a corner, radius 0) as long as no joint has to bend
more than φ_max: a corner of β < φ_max is passable, the bent pipe's 45° bends of radius
100 mm are (its joints bend at most 45°), the cabins' 107° corner is not, and rounded to
150 mm it is (52.6° at most).  :func:`check_path` measures exactly that, for every
place a joint can reach: joint k can sit at travel s only if the links beyond it fit on the
rest of the path, ``s + l_k + ... + l_12 <= L_path`` (a chord is no longer than its arc).

**Rounding.**  :func:`round_corners` replaces each corner by a circular arc of radius R
tangent to both segments, the tangent points ``R tan(β / 2)`` from the corner
(``rounded_corner_path`` of the cabins scenario, for any number of corners).

>>> from hrm_ctrl.model import default_robot
>>> round(smallest_bend_radius(default_robot()), 6)
179.0
>>> P = KnownPath.from_points(np.array([[0, 0, 0], [300, 0, 0], [300, 300, 0]], float))
>>> c = check_path(default_robot(), P)
>>> c.ok, round(c.corner_travel, 3), c.local_radius
(False, 300.0, 0.0)
>>> check_path(default_robot(), round_corners(P, 150.0)).ok
True
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.known_path import MAX_PATH_POINTS, KnownPath, drop_consecutive_duplicates

BEND_STEP_RAD = math.radians(1.0)  # arcs sampled every 1 deg, as the scenarios sample them
CHECK_SPACING = 0.5  # mm: the places along the path where a joint's bend is measured
CORNER_TURN_RAD = math.radians(10.0)  # a vertex turning more is a corner (radius 0), see below
TURN_TOL_RAD = 1e-9  # a vertex turning less is straight: nothing to round


def joint_bend(alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Combined bend φ of a universal joint, ``arccos(cos α cos θ)`` (Eq. 1), in radians.

    >>> round(float(np.degrees(joint_bend(np.radians(60.0), np.radians(60.0)))), 3)
    75.522
    """
    # the angle of z' = (cos th sin a, -sin th, cos a cos th) from z, accurate near 0
    ct = np.cos(theta)
    side = np.hypot(ct * np.sin(alpha), np.sin(theta))
    return np.arctan2(side, np.cos(alpha) * ct)


def bend_limit(model: RobotModel) -> float:
    """φ_max: the bend a joint can make in any direction, ``min(α_max, θ_max)`` (rad)."""
    return float(min(model.limit_alpha, model.limit_theta))


def chord_bend_on_circle(l_b: float, l_a: float, R: float) -> float:
    """Bend of a joint on a circle of radius R between chords l_b and l_a (rad).

    >>> round(math.degrees(chord_bend_on_circle(130.0, 136.0, 150.0)), 2)
    52.64
    """
    return math.asin(min(1.0, l_b / (2.0 * R))) + math.asin(min(1.0, l_a / (2.0 * R)))


def smallest_bend_radius(model: RobotModel) -> float:
    """The tightest circle the chain can follow with its joints on it (mm).

    For every pair of neighbouring links (l_b, l_a) the radius R where
    ``asin(l_b / 2R) + asin(l_a / 2R) = φ_max`` (module docstring; ``l / (2 sin(φ_max/2))``
    for equal links), and the largest of them.  Links 1 to 12 meet at joints 2 to 12.
    When even folded chords (R = max(l_b, l_a) / 2) stay within φ_max, that is R.
    """
    phi = bend_limit(model)
    radii = []
    links = np.asarray(model.links, dtype=float)
    for l_b, l_a in itertools.pairwise(links):
        lo = max(l_b, l_a) / 2.0  # R below this: a chord longer than the diameter
        if chord_bend_on_circle(l_b, l_a, lo) <= phi:
            radii.append(lo)
            continue
        hi = max(l_b, l_a) / (2.0 * math.sin(phi / 2.0)) + 1.0  # bend there < phi
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if chord_bend_on_circle(l_b, l_a, mid) > phi:
                lo = mid
            else:
                hi = mid
            if hi - lo < 1e-12 * hi:
                break
        radii.append(hi)
    return float(max(radii)) if radii else 0.0


@dataclass(frozen=True, eq=False)
class PathCheck:
    """Whether the arm can follow a path with its joints on it (:func:`check_path`).

    Attributes:
        ok: no joint has to bend more than ``bend_available`` anywhere it can reach.
        max_bend: the largest bend any joint needs along the path (rad); 0 when no joint
            reaches the path (a path shorter than the tip link).
        max_bend_travel: where (travel along the path, mm) that joint sits.
        bend_available: φ_max (rad).
        radius_available: :func:`smallest_bend_radius` (mm), for reference.
        travel: the first place (travel, mm) a joint cannot bend enough, or None.
        point: that place on the path, (3,), or None.
        joint: the joint (2..12) that first cannot, or None.
        bend_required: its bend there (rad), or None.
        local_radius: the path's tightest radius within that joint's two links (mm):
            0 at a corner (a vertex turning more than 10°), otherwise the radius of the
            circle through the vertex and its neighbours; None when ``ok``.
        corner_travel: the travel of that tightest vertex (the corner), or None.
    """

    ok: bool
    max_bend: float
    max_bend_travel: float
    bend_available: float
    radius_available: float
    travel: float | None = None
    point: np.ndarray | None = None
    joint: int | None = None
    bend_required: float | None = None
    local_radius: float | None = None
    corner_travel: float | None = None

    def message(self) -> str:
        """One line a person reads."""
        avail = math.degrees(self.bend_available)
        if self.ok:
            return (
                f"the arm can follow the path: its joints bend at most "
                f"{math.degrees(self.max_bend):.1f} deg of {avail:.1f} deg "
                f"(at travel {self.max_bend_travel:.1f} mm)"
            )
        p = self.point if self.point is not None else np.zeros(3)
        radius = (
            "a sharp corner" if self.local_radius == 0.0 else f"radius {self.local_radius:.1f} mm"
        )
        return (
            f"the arm cannot follow the path from travel {self.travel:.1f} mm "
            f"({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}): joint {self.joint} would bend "
            f"{math.degrees(self.bend_required or 0.0):.1f} deg, more than the {avail:.1f} deg "
            f"it can; the path there has {radius} (at travel {self.corner_travel:.1f} mm; "
            f"a long bend needs radius >= {self.radius_available:.1f} mm); rounding the "
            "corners may help"
        )


def _dense(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The polyline resampled every <= spacing, its vertices kept; and the arc length."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    k = np.maximum(np.ceil(seg / spacing).astype(np.int64), 1)
    t = np.concatenate([np.arange(kk) / kk for kk in k])
    j = np.repeat(np.arange(len(seg)), k)
    X = points[j] + t[:, None] * (points[j + 1] - points[j])
    X = np.vstack((X, points[-1]))
    s = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))))
    return X, s


def _chord_ends(X: np.ndarray, s: np.ndarray, i: np.ndarray, length: float) -> np.ndarray:
    """For each start sample i, the point on the polyline X (arc s) ahead of it at straight
    distance ``length`` (NaN where the polyline ends first).

    The crossing lies at arc >= s_i + length (a chord is no longer than its arc); from there
    a galloping search and a bisection bracket it between two samples, where the sphere
    meets the segment exactly.  Where the path comes back within ``length`` of X_i after
    leaving it, a later crossing may be found (paths curling back within a link length).
    """
    n = len(X)
    out = np.full((len(i), 3), np.nan)
    if len(i) == 0:
        return out
    lo = np.searchsorted(s, s[i] + length, side="left") - 1
    lo = np.clip(np.maximum(lo, i), 0, n - 1)
    L2 = length * length

    def d2(j: np.ndarray, rows: np.ndarray) -> np.ndarray:
        v = X[j] - X[i[rows]]
        return np.einsum("ij,ij->i", v, v)

    rows = np.arange(len(i))
    step = np.ones(len(i), dtype=np.int64)
    hi = np.full(len(i), -1, dtype=np.int64)
    active = rows.copy()
    while len(active):  # gallop: lo stays inside the sphere
        cand = lo[active] + step[active]
        past = cand >= n - 1
        cand = np.minimum(cand, n - 1)
        inside = d2(cand, active) < L2
        done = ~inside
        hi[active[done]] = cand[done]
        grow = inside & ~past  # inside & past: the polyline ends inside: no crossing
        lo[active[grow]] = cand[grow]
        step[active[grow]] *= 2
        active = active[grow]
    found = hi >= 0
    active = rows[found & (hi - lo > 1)]
    while len(active):  # bisect to neighbouring samples
        mid = (lo[active] + hi[active]) // 2
        inside = d2(mid, active) < L2
        lo[active[inside]] = mid[inside]
        hi[active[~inside]] = mid[~inside]
        active = active[hi[active] - lo[active] > 1]
    r = rows[found]
    A, B, C = X[lo[r]], X[hi[r]], X[i[r]]
    AB = B - A
    a = np.einsum("ij,ij->i", AB, AB)
    b = 2.0 * np.einsum("ij,ij->i", AB, A - C)
    c = np.einsum("ij,ij->i", A - C, A - C) - L2  # < 0: A is inside
    disc = np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))
    t = np.clip((-b + disc) / np.where(a > 0, 2.0 * a, 1.0), 0.0, 1.0)
    out[r] = A + t[:, None] * AB
    return out


def _vertex_radii(points: np.ndarray) -> np.ndarray:
    """The path's radius at each interior vertex (mm): 0 at a corner (turn > 10°), else
    the circumradius of the vertex and its neighbours (inf where straight).

    A polyline has no curvature but at its vertices; a vertex of a small turn is taken as
    a sample of a smooth curve (the scenarios sample arcs every 1°, scans every few mm),
    one of a large turn as a corner.
    """
    a, b, c = points[:-2], points[1:-1], points[2:]
    u, v = b - a, c - b
    cross = np.linalg.norm(np.cross(u, v), axis=1)
    turn = np.arctan2(cross, np.einsum("ij,ij->i", u, v))
    ab = np.linalg.norm(u, axis=1)
    bc = np.linalg.norm(v, axis=1)
    ac = np.linalg.norm(c - a, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        R = np.where(cross > 1e-12 * ab * bc, ab * bc * ac / (2.0 * cross), np.inf)
    return np.where(turn > CORNER_TURN_RAD, 0.0, R)


def check_path(model: RobotModel, path: KnownPath) -> PathCheck:
    """Measure the bend every joint needs wherever it can sit on ``path`` (module docstring).

    Bends are measured every <= 0.5 mm of travel (and at every vertex); the first place
    a joint would bend more than φ_max is reported with the path's tightest radius
    within that joint's links.
    """
    phi_max = bend_limit(model)
    R_avail = smallest_bend_radius(model)
    links = np.asarray(model.links, dtype=float)
    L = path.length
    X, s = _dense(path.points, CHECK_SPACING)
    t0 = path.tangent_at(0.0)
    ext = float(links.max()) + 1.0
    Xb = np.vstack((X[::-1], X[0] - ext * t0))  # backwards, then straight on before the start
    sb = np.concatenate((s[::-1][0] - s[::-1], [L + ext]))
    # distal[k]: length of the links from joint k (1-based, 2..12) to the tip
    distal = np.cumsum(links[::-1])[::-1]
    pairs: dict[tuple[float, float], tuple[float, int]] = {}
    for k in range(2, len(links) + 1):  # joint k: links k-1 (behind) and k (ahead)
        key = (float(links[k - 2]), float(links[k - 1]))
        reach = L - float(distal[k - 1])
        if reach >= 0.0 and (key not in pairs or reach > pairs[key][0]):
            pairs[key] = (reach, k)
    best_bend, best_s = 0.0, 0.0
    first: tuple[float, int, float, int] | None = None  # (travel, sample, bend, joint)
    for (l_b, l_a), (reach, k) in pairs.items():
        i = np.flatnonzero(s <= reach + 1e-9)
        F = _chord_ends(X, s, i, l_a)
        B = _chord_ends(Xb, sb, len(X) - 1 - i, l_b)
        v1, v2 = X[i] - B, F - X[i]
        bend = np.arctan2(np.linalg.norm(np.cross(v1, v2), axis=1), np.einsum("ij,ij->i", v1, v2))
        ok = np.isfinite(bend)
        if not ok.any():
            continue
        m = int(np.argmax(np.where(ok, bend, -1.0)))
        if bend[m] > best_bend:
            best_bend, best_s = float(bend[m]), float(s[i[m]])
        bad = np.flatnonzero(ok & (bend > phi_max))
        if len(bad):
            j = int(bad[0])
            if first is None or s[i[j]] < first[0]:
                first = (float(s[i[j]]), int(i[j]), float(bend[j]), k)
    if first is None:
        return PathCheck(True, best_bend, best_s, phi_max, R_avail)
    travel, _, bend_req, k = first
    l_b, l_a = float(links[k - 2]), float(links[k - 1])
    radii = _vertex_radii(path.points)
    sv = path.s[1:-1]
    near = np.flatnonzero((sv >= travel - l_b - 1e-9) & (sv <= travel + l_a + 1e-9))
    if len(near):
        v = int(near[np.argmin(radii[near])])
        local, corner_s = float(radii[v]), float(sv[v])
    else:  # only the straight extension before the start bends (the start tangent)
        local, corner_s = math.inf, 0.0
    point = path.point_at(travel)
    point.setflags(write=False)
    return PathCheck(
        False,
        best_bend,
        best_s,
        phi_max,
        R_avail,
        travel=travel,
        point=point,
        joint=k,
        bend_required=bend_req,
        local_radius=local,
        corner_travel=corner_s,
    )


def _arc(T1: np.ndarray, d1: np.ndarray, n: np.ndarray, R: float, phi: float) -> np.ndarray:
    """Arc leaving T1 along d1, turning towards n with radius R through phi, sampled every
    <= 1 deg (first point excluded), as the scenarios sample their bends."""
    k = max(2, math.ceil(phi / BEND_STEP_RAD))
    psi = np.linspace(0.0, phi, k + 1)[1:]
    centre = T1 + R * n
    return centre - R * np.cos(psi)[:, None] * n + R * np.sin(psi)[:, None] * d1


def round_corners(path: KnownPath, radius_mm: float) -> KnownPath:
    """``path`` with every corner replaced by a circular arc of radius ``radius_mm``,
    tangent to both segments at ``R tan(β/2)`` from the corner (β the turn there).

    Raises :class:`PlanningError` (one line naming the corner) when a segment is too
    short for the tangent lengths of its corners, or the path turns back on itself; and,
    before any arc is made, when the arcs would give more than ``MAX_PATH_POINTS`` points.

    >>> P = KnownPath.from_points(np.array([[0, 0, 0], [100, 0, 0], [100, 100, 0]], float))
    >>> Q = round_corners(P, 50.0)
    >>> round(Q.length, 3), round(100 - 50 + 50 * math.pi / 2 + 50, 3)
    (178.539, 178.54)
    >>> round_corners(P, 150.0)
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.PlanningError: <points>: corner 1 (point 2 at (100, 0, 0), turn 90.0 deg): \
a 150 mm radius needs 150.0 mm of the 100.0 mm segment from point 1 to point 2
    """
    R = float(radius_mm)
    if not (math.isfinite(R) and R > 0.0):
        raise PlanningError(f"corner radius must be a finite number > 0 mm, got {radius_mm}")
    P = path.points
    n_pts = len(P)
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    d = np.diff(P, axis=0) / seg[:, None]
    phi = np.zeros(n_pts)
    for j in range(1, n_pts - 1):
        phi[j] = math.acos(max(-1.0, min(1.0, float(d[j - 1] @ d[j]))))
    corner = phi > TURN_TOL_RAD
    number = np.cumsum(corner)  # corner j is number[j] (1-based)

    def where(j: int) -> str:
        x, y, z = (f"{v:.6g}" for v in P[j])
        return (
            f"{path.source}: corner {number[j]} (point {j + 1} at ({x}, {y}, {z}), "
            f"turn {math.degrees(phi[j]):.1f} deg)"
        )

    for j in np.flatnonzero(corner):
        if phi[j] >= math.pi - 1e-9:
            raise PlanningError(f"{where(j)}: the path turns back on itself there")
    t = np.where(corner, R * np.tan(phi / 2.0), 0.0)
    for k in range(n_pts - 1):  # segment k runs from point k to point k+1
        need = t[k] + t[k + 1]
        if need > seg[k] * (1.0 + 1e-12) + 1e-9:
            j = k + 1 if t[k + 1] >= t[k] else k
            other = k if j == k + 1 else k + 1
            also = (
                f" (and corner {number[other]} at point {other + 1} needs {t[other]:.1f} mm of it)"
                if corner[other]
                else ""
            )
            raise PlanningError(
                f"{where(j)}: a {R:g} mm radius needs {t[j]:.1f} mm of the {seg[k]:.1f} mm "
                f"segment from point {k + 1} to point {k + 2}{also}"
            )
    arcs = np.where(corner, np.maximum(2, np.ceil(phi / BEND_STEP_RAD)) + 1, 0.0)
    n_out = int(n_pts + arcs.sum())  # at most: each corner its arc and tangent point
    if n_out > MAX_PATH_POINTS:
        raise PlanningError(
            f"{path.source}: rounding its {int(corner.sum())} corners (one point every "
            f"{math.degrees(BEND_STEP_RAD):g} deg of turn) would give {n_out} points, more "
            f"than the {MAX_PATH_POINTS} a path may have"
        )
    out: list[np.ndarray] = [P[0]]
    for j in range(1, n_pts - 1):
        if not corner[j]:
            out.append(P[j])
            continue
        d1, d2 = d[j - 1], d[j]
        n = d2 - (d2 @ d1) * d1
        n /= np.linalg.norm(n)
        T1 = P[j] - t[j] * d1
        if np.linalg.norm(T1 - out[-1]) > 1e-9:
            out.append(T1)
        out.extend(_arc(T1, d1, n, R, float(phi[j])))
    if np.linalg.norm(P[-1] - out[-1]) > 1e-9:
        out.append(P[-1])
    pts, _ = drop_consecutive_duplicates(np.array(out))  # the arc of a tiny turn: no warning
    return KnownPath.from_points(pts, source=path.source)
