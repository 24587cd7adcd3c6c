"""Fitting the arm's joint centres onto the backbone, Sec. 3.3.

From the tip towards the base, each joint centre ``O_i`` is the point of the
backbone polyline at distance ``l_i`` from ``O_{i+1}`` (Steps 1-3): the last
polyline point (towards the tip) still at least ``l_i`` from ``O_{i+1}`` brackets the
crossing between two neighbouring points P_{j-1}, P_j, and the exact intersection of
the sphere of radius l_i with segment P_{j-1}P_j is taken (Fig. 7).  Joint 2 (Step 4)
lies on the circle where the spheres about O_1 (radius l_1) and O_3 (radius l_2) meet;
of its points we take the one nearest the backbone point at arc length l_1, which keeps
joints 1-3 close to the backbone and moves continuously from step to step.

The bracket is what the paper's bisection finds where the distance from O_{i+1} grows
monotonically towards the base, and the nearest crossing along the curve where the
polyline folds back (it never does on the reference scenarios).  It is searched
backwards from the last point at least ``l_i`` before O_{i+1} along the curve (a chord
is no longer than its arc, so no point after it can be ``l_i`` away): a few points per
joint, however long the curve (a trail drawn at 0.2 mm a step has thousands).

>>> import numpy as np
>>> line = np.array([[0.0, 0, 0], [10.0, 0, 0]])
>>> O = fit_joint_centres(line, np.array([5.0, 5.0]))
>>> O.round(9).tolist()
[[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 0.0, 0.0]]
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from hrm_ctrl.errors import PlanningError


def sphere_segment_intersection(C: np.ndarray, P: np.ndarray, Q: np.ndarray, r: float) -> float:
    """Parameter t in [0, 1] of the point ``P + t (Q - P)`` at distance r from C,
    where |P - C| >= r > |Q - C| (the crossing nearest P).

    >>> sphere_segment_intersection(np.zeros(3), np.array([2.0, 0, 0]), np.zeros(3), 1.0)
    0.5
    """
    D = (Q - P).tolist()
    E = (P - C).tolist()
    return _crossing(E, D, r)


def _crossing(E: list[float], D: list[float], r: float) -> float:
    """:func:`sphere_segment_intersection` of E = P - C and D = Q - P (3 floats each)."""
    a = D[0] * D[0] + D[1] * D[1] + D[2] * D[2]
    b = E[0] * D[0] + E[1] * D[1] + E[2] * D[2]
    c = E[0] * E[0] + E[1] * E[1] + E[2] * E[2] - r * r
    disc = max(b * b - a * c, 0.0)
    t = (-b - math.sqrt(disc)) / a
    return min(max(t, 0.0), 1.0)


def _last_at_least(
    curve: np.ndarray, cum: np.ndarray, P: list[float], r: float, k: int, slack: float
) -> int:
    """Largest k' <= k with ``|curve[k'] - P| >= r``; -1 if none or the first point is
    within r of P (the bisection's bracket needs it at least r away).

    Walked backwards by arc length: a point ``delta`` before one at distance d along the
    curve is at most ``d + delta`` from P, so the points less than ``r - d`` before it are
    skipped (``cum``: the arc length at each point, searched in place: a few of its
    entries are read, never all)."""
    if math.dist(curve[0].tolist(), P) < r:
        return -1
    while k >= 0:
        d = math.dist(curve[k].tolist(), P)
        if d >= r:
            return k
        k = min(bisect.bisect_right(cum, float(cum[k]) - (r - d) + slack) - 1, k - 1)
    return -1


def circle_point_nearest(
    O1: np.ndarray, O3: np.ndarray, l1: float, l2: float, ref: np.ndarray
) -> np.ndarray:
    """Step 4: the point O2 with |O2 - O1| = l1 and |O3 - O2| = l2 nearest ``ref``.

    >>> O3, ref = np.array([6.0, 0, 0]), np.array([3.0, 0, 9])
    >>> circle_point_nearest(np.zeros(3), O3, 5.0, 5.0, ref).round(9).tolist()
    [3.0, 0.0, 4.0]
    """
    (x1, y1, z1), (x3, y3, z3) = O1.tolist(), O3.tolist()
    vx, vy, vz = x3 - x1, y3 - y1, z3 - z1
    D = math.sqrt(vx * vx + vy * vy + vz * vz)
    if D > l1 + l2 or D < abs(l1 - l2) or D == 0.0:
        raise PlanningError(
            f"joint 2 has no place: O1-O3 is {D:.3f} mm, links 1 and 2 span "
            f"{abs(l1 - l2):.3f} to {l1 + l2:.3f} mm (backbone too long for the arm)"
        )
    # on floats (3-vectors: a NumPy call costs more than its arithmetic)
    nx, ny, nz = vx / D, vy / D, vz / D
    a = (D * D + l1 * l1 - l2 * l2) / (2.0 * D)
    r = math.sqrt(max(l1 * l1 - a * a, 0.0))
    cx, cy, cz = x1 + a * nx, y1 + a * ny, z1 + a * nz
    rx, ry, rz = ref.tolist()
    wx, wy, wz = rx - cx, ry - cy, rz - cz
    wn = wx * nx + wy * ny + wz * nz
    wx, wy, wz = wx - wn * nx, wy - wn * ny, wz - wn * nz
    nw = math.sqrt(wx * wx + wy * wy + wz * wz)
    if nw < 1e-12:  # ref on the axis: any point; take one perpendicular to n
        n = np.array([nx, ny, nz])
        w = np.cross(n, [0.0, 0.0, 1.0])
        if np.linalg.norm(w) < 1e-9:
            w = np.cross(n, [0.0, 1.0, 0.0])
        wx, wy, wz = w.tolist()
        nw = math.sqrt(wx * wx + wy * wy + wz * wz)
    return np.array([cx + r * wx / nw, cy + r * wy / nw, cz + r * wz / nw])


def point_at_arc(curve: np.ndarray, s: float) -> np.ndarray:
    """Point of a polyline at arc length s from its first point (clamped)."""
    return _point_at_arc(curve, _arc_lengths(curve), s)


def _arc_lengths(curve: np.ndarray) -> np.ndarray:
    """Arc length (m,) of a polyline (m, 3) at each of its points.

    >>> _arc_lengths(np.array([[0.0, 0, 0], [3, 4, 0], [3, 4, 12]])).tolist()
    [0.0, 5.0, 17.0]
    """
    D = curve[1:] - curve[:-1]
    D *= D
    cum = np.empty(len(curve))
    cum[:1] = 0.0
    np.cumsum(np.sqrt(np.add.reduce(D, axis=1)), out=cum[1:])  # np.linalg.norm's sum
    return cum


def _point_at_arc(curve: np.ndarray, cum: np.ndarray, s: float) -> np.ndarray:
    s = min(max(s, 0.0), float(cum[-1]))
    j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(cum) - 2)
    (ax, ay, az), (bx, by, bz) = curve[j].tolist(), curve[j + 1].tolist()
    dx, dy, dz = bx - ax, by - ay, bz - az
    seg = math.sqrt(dx * dx + dy * dy + dz * dz)
    t = (s - float(cum[j])) / seg if seg > 0 else 0.0
    return np.array([ax + t * dx, ay + t * dy, az + t * dz])


def fit_joint_centres(curve: np.ndarray, links: np.ndarray) -> np.ndarray:
    """Joint centres O_1..O_n and the end point O_{n+1} fitted onto ``curve``
    (see :func:`fit_joint_centres_on_segments`)."""
    return fit_joint_centres_on_segments(curve, links)[0]


def fit_joint_centres_on_segments(
    curve: np.ndarray, links: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Joint centres O_1..O_n and the end point O_{n+1} fitted onto ``curve``, and
    for each the index k of the curve segment [curve[k], curve[k+1]] it lies on
    (-1 for O_2, which lies on the circle of Step 4, not on the curve).

    ``curve`` (m, 3) runs from the base (O_1 = curve[0]) to the tip
    (O_{n+1} = curve[-1]); ``links`` are l_1..l_n.  Joints n..3 by the bracket (the
    module's) and the exact sphere-segment intersection, joint 2 on the circle of Step 4.

    Raises :class:`PlanningError` when the curve is too short for the arm or
    too long for joint 2 to close the chain.
    """
    n = len(links)
    O = np.empty((n + 1, 3))
    seg = np.zeros(n + 1, dtype=np.int64)
    seg[n] = len(curve) - 2
    O[n] = curve[-1]
    O[0] = curve[0]
    cum = _arc_lengths(curve)  # searched in place (bisect): a few entries read per joint
    # a point nearer P along the curve than r is nearer than r (chord <= arc): the
    # crossing is searched backwards from the last point at least r before P
    s_P = float(cum[-1])
    slack = 1e-9 * (1.0 + s_P)
    P = curve[-1].tolist()
    j = len(curve) - 2  # P lies on segment [curve[j], curve[j + 1]]
    for i in range(n - 1, 1, -1):  # O_{i+1} (0-based index i) from O_{i+2}
        r = float(links[i])
        k0 = min(bisect.bisect_right(cum, s_P - r + slack) - 1, j)
        k = _last_at_least(curve, cum, P, r, k0, slack)
        if k < 0:
            raise PlanningError(
                f"backbone too short: no place for joint {i + 1} at {r:.1f} mm from joint {i + 2}"
            )
        A = curve[k].tolist()
        B = curve[k + 1].tolist() if k + 1 <= j else P
        D = [B[0] - A[0], B[1] - A[1], B[2] - A[2]]
        t = _crossing([A[0] - P[0], A[1] - P[1], A[2] - P[2]], D, r)
        P = [A[0] + t * D[0], A[1] + t * D[1], A[2] + t * D[2]]
        s_P = float(cum[k]) + t * math.hypot(*D)
        O[i] = P
        seg[i] = k
        j = k
    if n >= 2:
        ref = _point_at_arc(curve, cum, float(links[0]))
        O[1] = circle_point_nearest(O[0], O[2], float(links[0]), float(links[1]), ref)
        seg[1] = -1
    return O, seg


def circle_points_nearest(
    O1: np.ndarray, O3: np.ndarray, l1: float, l2: float, ref: np.ndarray
) -> np.ndarray:
    """:func:`circle_point_nearest` for many steps at once; arrays of shape (N, 3).

    Returns NaN rows where no circle exists (the caller reports them)."""
    v = O3 - O1
    D = np.linalg.norm(v, axis=1)
    n = v / D[:, None]
    a = (D * D + l1 * l1 - l2 * l2) / (2.0 * D)
    r = np.sqrt(np.maximum(l1 * l1 - a * a, 0.0))
    c = O1 + a[:, None] * n
    w = ref - c
    w = w - np.einsum("ij,ij->i", w, n)[:, None] * n
    nw = np.linalg.norm(w, axis=1)
    flat = nw < 1e-12
    if flat.any():
        alt = np.cross(n[flat], [0.0, 0.0, 1.0])
        w[flat] = alt
        nw[flat] = np.linalg.norm(alt, axis=1)
    out = c + (r / nw)[:, None] * w
    bad = (D > l1 + l2) | (D < abs(l1 - l2)) | (D == 0.0)
    out[bad] = np.nan
    return out


def fit_joint_centres_batch(
    curves: np.ndarray, links: np.ndarray, ref2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sec. 3.3 for N backbones at once.

    ``curves`` (N, m, 3): each from the base (index 0) to the tip (index m - 1);
    a shorter curve is padded at its end with copies of its tip.  ``ref2`` (N, 3):
    the reference point that picks joint 2 on its circle (Step 4).  Each joint's
    bracket is the last curve point, towards the tip, still at distance >= l_i
    from the joint after it: the bracket bisection finds on a monotone distance
    (compare :func:`fit_joint_centres`, which bisects, on one curve).

    Returns the joint centres (N, n + 1, 3) and segment indices (N, n + 1).
    Raises :class:`PlanningError` naming the first step that cannot be fitted.
    """
    N, m, _ = curves.shape
    n = len(links)
    rows = np.arange(N)
    idx = np.arange(m)
    O = np.empty((N, n + 1, 3))
    seg = np.zeros((N, n + 1), dtype=np.int64)
    P = curves[:, -1].copy()
    j = np.full(N, m - 2)
    O[:, n] = P
    O[:, 0] = curves[:, 0]
    seg[:, n] = m - 2
    C2 = np.einsum("nmk,nmk->nm", curves, curves)  # |C|^2, once for every joint
    for i in range(n - 1, 1, -1):
        r = float(links[i])
        # |C - P|^2 = |C|^2 - 2 C.P + |P|^2: the bracket test only (the intersection
        # below uses the points themselves)
        d2 = C2 - 2.0 * np.einsum("nmk,nk->nm", curves, P)
        d2 += np.einsum("nk,nk->n", P, P)[:, None]
        ok = (d2 >= r * r) & (idx[None, :] <= j[:, None])
        found = ok.any(axis=1)
        if not found.all():
            bad = int(np.flatnonzero(~found)[0])
            raise PlanningError(
                f"step {bad}: backbone too short, no place for joint {i + 1} "
                f"at {r:.1f} mm from joint {i + 2}"
            )
        k = m - 1 - np.argmax(ok[:, ::-1], axis=1)
        Ck = curves[rows, k]
        nxt = np.where((k + 1 <= j)[:, None], curves[rows, np.minimum(k + 1, m - 1)], P)
        D = nxt - Ck
        E = Ck - P
        qa = np.einsum("ij,ij->i", D, D)
        qb = np.einsum("ij,ij->i", E, D)
        qc = np.einsum("ij,ij->i", E, E) - r * r
        t = (-qb - np.sqrt(np.maximum(qb * qb - qa * qc, 0.0))) / np.where(qa > 0, qa, 1.0)
        t = np.clip(t, 0.0, 1.0)
        P = Ck + t[:, None] * D
        O[:, i] = P
        seg[:, i] = k
        j = k
    if n >= 2:
        O[:, 1] = circle_points_nearest(O[:, 0], O[:, 2], float(links[0]), float(links[1]), ref2)
        seg[:, 1] = -1
        bad_rows = np.flatnonzero(np.isnan(O[:, 1, 0]))
        if len(bad_rows):
            b = int(bad_rows[0])
            D = float(np.linalg.norm(O[b, 2] - O[b, 0]))
            raise PlanningError(
                f"step {b}: joint 2 has no place: O1-O3 is {D:.3f} mm, links 1 and 2 span "
                f"up to {links[0] + links[1]:.3f} mm (backbone too long for the arm)"
            )
    return O, seg
