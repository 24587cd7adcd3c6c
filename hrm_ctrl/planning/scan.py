"""A pipe's centre line and inner diameter from a scan of its inner wall.

The paper's introduction suggests taking the principal axes of slices along the pipe;
this module slices the cloud normal to the pipe's local axis and fits a circle to each
slice, robustly (noise and outliers expected):

1. **Seed.**  The slab through the cloud's median along its principal axis (PCA of the
   99 % of points nearest the median: a few stray points far away turn no axis): a
   RANSAC circle (3-point circles, the one most points lie near) refined as below, then
   the local axis from two slices one radius either side, three times.  If that fails
   (a slab across a bend), slabs at other quantiles along the principal axis are tried.
2. **March** both ways in steps ``h`` (default 0.15 r; 0.05 r to 0.5 r): slice normal to
   the current direction at the predicted centre, keep the points of the slab (width
   ``max(h, 0.15 r)``) within 1.6 r of it, fit a circle (an algebraic fit on the points
   near the expected wall, then Gauss-Newton on the geometric residual ``|q - c| - r``
   with Tukey weights, scale from the median absolute deviation, iterated); the new
   direction is the tangent of the least-squares quadratic through the centres of the
   last 0.3 r.  It stops where a slab holds few wall points (the scan's end), the radius
   jumps by more than 20 %, the centre jumps by more than r/2, or it comes back to where it
   has been (a closed ring).  The march runs on a random subset of at most 30,000 points.
3. **Refine.**  Every slice is fitted again, on every fitted point (the points nearest its
   centre), normal to the central-difference tangent of the centre line (the march's
   direction lags in bends); the centres are smoothed by a quadratic Savitzky-Golay filter
   over 7 slices.  Each end is placed where the wall points stop: from the third slice in,
   the wall points past it divided by the wall's density along the axis behind it (for
   noise blurring the end: where the density halves; an outlier near the wall moves it
   by 1/density), done twice, the second time from just before the end found.
4. **Diameter and residuals.**  The inner diameter is twice the median slice radius; the
   residual of every point is its distance to the fitted wall (its distance to the axis
   less the radius).  Inliers are within ``max(3 sigma, 0.05 mm)`` of the wall, sigma
   estimated as 1.4826 times the median absolute deviation of the residuals.  A band
   wider than half the radius (points not on a wall: a solid, a box of noise) or a
   diameter below 1 mm (a scan in metres) is refused.

Clouds of more than ``max_fit_points`` (default 500,000) are fitted on a random subset of
that many points (seeded: the same cloud gives the same fit); the residuals are measured on
every point.

>>> from hrm_ctrl.planning.scenarios import scenario
>>> axis = scenario("bent-pipe").path
>>> cloud = synthetic_pipe_scan(axis, 70.0, 20_000, 0.5, 0.02, np.random.default_rng(1))
>>> fit = pipe_from_scan(cloud)
>>> abs(fit.inner_diameter - 70.0) < 0.5, fit.inlier_fraction > 0.95
(True, True)
>>> bool(axis.distance_to(fit.axis).max() < 1.0)
True
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.planning.known_path import MAX_PATH_LENGTH_MM, KnownPath

MIN_SCAN_POINTS = 100  # fewer cannot show a pipe
MAX_FIT_POINTS = 500_000  # the fit uses a random subset of this many points at most
MAX_MARCH_POINTS = 30_000  # the march (step 2) a random subset of these
MAX_SYNTHETIC_POINTS = 20_000_000  # as many as a point cloud file may hold
MIN_SLICE_POINTS = 12  # wall points a slice needs for its circle
STEP_PER_RADIUS = 0.15  # default slice step, in pipe radii
MIN_STEP_PER_RADIUS = 0.05  # smallest slice step, in pipe radii
MAX_STEP_PER_RADIUS = 0.5  # largest slice step, in pipe radii
TANGENT_SPAN_PER_RADIUS = 0.3  # the march's direction: from the centres of this many radii
GATE_PER_RADIUS = 1.6  # a slice keeps the points within this many radii of its centre
RANSAC_HYPOTHESES = 256
RANSAC_MAX_POINTS = 2_000  # a seed slab's points scored (a random subset of them)
MAX_SLICES = 40_000  # slices of a march each way (a path has at most 100,000 points)
SEED_QUANTILES = (50.0, 40.0, 60.0, 30.0, 70.0, 20.0, 80.0)  # where seeds are tried
TUKEY_C = 4.685  # Tukey biweight constant (95 % efficiency for Gaussian noise)
IRLS_ITERATIONS = 12
SMOOTH_WINDOW = 7  # slices of the Savitzky-Golay smoothing of the centre line
INLIER_SIGMAS = 3.0
MIN_INLIER_BAND_MM = 0.05
MAX_BAND_PER_RADIUS = 0.5  # a wider 3-sigma band about the wall: no wall (noise 5 mm: 0.44 r)
MIN_INNER_DIAMETER_MM = 1.0  # a narrower fit is a scan in other units
CORE_PERCENTILE = 99.0  # the seed's principal axis: the points this near the median
STATS_CHUNK = 1_000_000  # residuals are measured this many points at a time


class ScanFitError(PlanningError):
    """A scan does not show a pipe the fit can follow (too few points, no circle, ...)."""


@dataclass(frozen=True, eq=False)
class ScanFit:
    """A pipe fitted to a scan of its inner wall (mm).

    Attributes:
        axis: the centre line, (k, 3), from one end of the scan to the other.
        inner_diameter: twice the median radius of the slices.
        rms: root mean square of the inliers' distance to the fitted wall.
        p95: 95th percentile of the inliers' |distance to the fitted wall|.
        inlier_fraction: the share of the points within ``inlier_band`` of the wall.
        inlier_band: the band (mm) that decides an inlier.
        n_points: the points of the scan.
        n_outliers: the points rejected (outside the band).
        n_slices: the slices fitted.
        diameter_spread: 1.4826 x the median absolute deviation of the slice diameters.
        timings_s: seconds taken by each stage of the fit.
    """

    axis: np.ndarray
    inner_diameter: float
    rms: float
    p95: float
    inlier_fraction: float
    inlier_band: float
    n_points: int
    n_outliers: int
    n_slices: int
    diameter_spread: float
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def axis_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.axis, axis=0), axis=1).sum())

    def path(self, start_near: np.ndarray | None = None, source: str = "scan") -> KnownPath:
        """The centre line as a path, starting at the end nearest ``start_near`` (the
        robot's base; by default the world origin)."""
        q = np.zeros(3) if start_near is None else np.asarray(start_near, dtype=float)
        pts = self.axis
        if np.linalg.norm(pts[-1] - q) < np.linalg.norm(pts[0] - q):
            pts = pts[::-1]
        return KnownPath.from_points(pts, source=source)

    def to_dict(self) -> dict[str, Any]:
        return {
            "inner_diameter_mm": self.inner_diameter,
            "diameter_spread_mm": self.diameter_spread,
            "axis_length_mm": self.axis_length,
            "axis_points": len(self.axis),
            "slices": self.n_slices,
            "points": self.n_points,
            "outliers": self.n_outliers,
            "inlier_fraction": self.inlier_fraction,
            "inlier_band_mm": self.inlier_band,
            "rms_mm": self.rms,
            "p95_mm": self.p95,
            "timings_s": dict(self.timings_s),
        }


def _basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing unit d to a right-handed orthonormal frame."""
    a = np.eye(3)[int(np.argmin(np.abs(d)))]
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def _mad_scale(e: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(e - np.median(e)))) if len(e) else 0.0


@dataclass(frozen=True)
class _Circle:
    centre: np.ndarray  # (3,), in the slice's mid-plane
    radius: float
    inliers: int
    scale: float  # robust scale of the residuals (mm)


def _kasa(q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Weighted algebraic circle fit (Kasa): ``u^2 + v^2 = a u + b v + c``."""
    A = np.column_stack((q, np.ones(len(q))))
    sw = np.sqrt(w)
    sol, *_ = np.linalg.lstsq(A * sw[:, None], (q * q).sum(axis=1) * sw, rcond=None)
    c = sol[:2] / 2.0
    r2 = sol[2] + c @ c
    if not (np.all(np.isfinite(c)) and r2 > 0.0):
        return None
    return c, math.sqrt(r2)


def _irls(
    q: np.ndarray, c: np.ndarray, r: float, w0: np.ndarray
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Geometric circle fit by Gauss-Newton with Tukey weights; returns the centre, the
    radius, the final weights and the residual scale.  The start radius is the median
    distance of the starting points from ``c``: a start radius off by more than a few
    robust scales (an algebraic fit pulled by a stray point, on a noise-free wall) would
    weigh every point out."""
    w = w0.astype(float)
    rho0 = np.linalg.norm(q - c, axis=1)[w > 0]
    if len(rho0):
        r = float(np.median(rho0))
    floor = 1e-6 * r + 1e-9
    s = max(_mad_scale(rho0 - r), floor)
    for _ in range(IRLS_ITERATIONS):
        dq = q - c
        rho = np.linalg.norm(dq, axis=1)
        rho = np.where(rho > 0, rho, 1e-12)
        e = rho - r
        z = e / (TUKEY_C * s)
        w = np.where(np.abs(z) < 1.0, (1.0 - z * z) ** 2, 0.0)
        if np.count_nonzero(w) < 3:
            break
        J = np.column_stack((-dq / rho[:, None], -np.ones(len(q))))
        JW = J * w[:, None]
        H = JW.T @ J
        g = JW.T @ e
        try:
            delta = np.linalg.solve(H, -g)
        except np.linalg.LinAlgError:
            break
        c = c + delta[:2]
        r = r + float(delta[2])
        s_new = max(_mad_scale(e[w > 0]), floor)
        s = s_new
        if np.abs(delta).max() < 1e-7 * max(r, 1.0):
            break
    e = np.linalg.norm(q - c, axis=1) - r
    w = (np.abs(e) < TUKEY_C * s).astype(float)
    return c, float(r), w, s


def _ransac(
    q: np.ndarray, rng: np.random.Generator, r_max: float
) -> tuple[np.ndarray, float] | None:
    """The 3-point circle most points of q (m, 2) lie near."""
    if len(q) > RANSAC_MAX_POINTS:  # hypotheses x points distances: bounded
        q = q[rng.choice(len(q), RANSAC_MAX_POINTS, replace=False)]
    m = len(q)
    if m < 3:
        return None
    idx = rng.integers(0, m, size=(RANSAC_HYPOTHESES, 3))
    a, b, c = q[idx[:, 0]], q[idx[:, 1]], q[idx[:, 2]]
    d = 2.0 * (
        a[:, 0] * (b[:, 1] - c[:, 1])
        + b[:, 0] * (c[:, 1] - a[:, 1])
        + c[:, 0] * (a[:, 1] - b[:, 1])
    )
    ok = np.abs(d) > 1e-12
    a2, b2, c2 = (a * a).sum(1), (b * b).sum(1), (c * c).sum(1)
    dd = np.where(ok, d, 1.0)
    ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / dd
    uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / dd
    centres = np.column_stack((ux, uy))
    radii = np.linalg.norm(a - centres, axis=1)
    r_max = min(r_max, 0.6 * float(np.ptp(q, axis=0).max()))  # the circle spans the slab
    ok &= (radii > 0) & (radii < r_max)
    if not ok.any():
        return None
    centres, radii = centres[ok], radii[ok]
    dist = np.linalg.norm(q[None, :, :] - centres[:, None, :], axis=2)
    score = (np.abs(dist - radii[:, None]) < 0.03 * radii[:, None]).sum(axis=1)
    k = int(np.argmax(score))
    return centres[k], float(radii[k])


def _fit_slice(
    X: np.ndarray,
    centre: np.ndarray,
    d: np.ndarray,
    width: float,
    r_ref: float | None,
    gate: float,
    rng: np.random.Generator,
) -> _Circle | None:
    """The circle of the candidate points X (m, 3) in the slab of ``width`` about
    ``centre`` normal to unit ``d`` and within ``gate`` of it; None if it holds too few
    wall points.  Without ``r_ref`` (no expected radius) the circle is found by RANSAC."""
    X = X - centre
    tau = X @ d
    X = X[np.abs(tau) <= width / 2.0]
    u, v = _basis(d)
    q = np.column_stack((X @ u, X @ v))
    q = q[np.einsum("ij,ij->i", q, q) <= gate * gate]
    if len(q) < MIN_SLICE_POINTS:
        return None
    if r_ref is None:
        found = _ransac(q, rng, gate)
        if found is None:
            return None
        c0, r0 = found
        near = np.abs(np.linalg.norm(q - c0, axis=1) - r0) < 0.1 * r0
    else:
        near = np.abs(np.linalg.norm(q, axis=1) - r_ref) < 0.25 * r_ref
        if near.sum() < MIN_SLICE_POINTS:
            return None
        kasa = _kasa(q[near], np.ones(int(near.sum())))
        if kasa is None:
            return None
        c0, r0 = kasa
    if near.sum() < MIN_SLICE_POINTS:
        return None
    c, r, w, s = _irls(q, c0, r0, near)
    n_in = int(w.sum())
    if n_in < MIN_SLICE_POINTS or not (0.0 < r < gate):
        return None
    return _Circle(centre + c[0] * u + c[1] * v, r, n_in, s)


class _Slicer:
    """Slices of a cloud (through a KD-tree of it) normal to a direction, and their circles."""

    def __init__(self, Q: np.ndarray, rng: np.random.Generator) -> None:
        self.Q = Q
        self.tree = cKDTree(Q)
        self.rng = rng

    def fit(
        self,
        centre: np.ndarray,
        d: np.ndarray,
        width: float,
        r_ref: float | None,
        gate: float,
    ) -> _Circle | None:
        """:func:`_fit_slice` of the points within reach of the slab."""
        idx = self.tree.query_ball_point(centre, math.hypot(width / 2.0, gate))
        if len(idx) < MIN_SLICE_POINTS:
            return None
        return _fit_slice(self.Q[np.asarray(idx)], centre, d, width, r_ref, gate, self.rng)


def _tangents(C: np.ndarray) -> np.ndarray:
    """Unit central-difference tangents of a polyline (one-sided at its ends)."""
    T = np.gradient(C, axis=0)
    return T / np.linalg.norm(T, axis=1, keepdims=True)


def _end_tangent(centres: list[np.ndarray], span: float, h: float) -> np.ndarray:
    """Unit tangent at the last centre: of the quadratic through the centres of the last
    ``span`` mm (at least three), fitted by least squares."""
    m = min(len(centres), max(3, math.ceil(span / h) + 1))
    if m < 3:
        t = centres[-1] - centres[-2]
    else:
        Y = np.array(centres[-m:])
        x = np.arange(m, dtype=float) - (m - 1)
        V = np.column_stack((np.ones(m), x, x * x))
        coef, *_ = np.linalg.lstsq(V, Y, rcond=None)
        t = coef[1]  # the derivative at x = 0, the last centre
    return t / np.linalg.norm(t)


def _end_point(C: np.ndarray, length: float, m: int = 7) -> np.ndarray:
    """The point ``length`` mm before ``C[0]`` (away from ``C[1]``) on the quadratic through
    ``C[0]`` fitted to the centres ``C[:m]`` by chord length: an end placed along the
    tangent alone would leave a bend's curve by ``length**2 / (2 R)`` (0.4 mm for an
    11 mm end on a radius of 150 mm).

    >>> t = np.linspace(0.0, 0.3, 7)                          # centres 5 mm apart
    >>> C = np.c_[100 * np.sin(t), 100 * (1 - np.cos(t)), 0 * t]      # a circle, R 100
    >>> off = lambda p: abs(float(np.linalg.norm(p - [0, 100, 0])) - 100.0)
    >>> off(_end_point(C, 10.0)) < 0.05, round(off(C[0] - [10.0, 0, 0]), 2)  # vs the tangent
    (True, 0.5)
    """
    m = min(m, len(C))
    Y = C[1:m] - C[0]
    if m < 3:
        return C[0] - length * Y[0] / np.linalg.norm(Y[0])
    s = np.cumsum(np.linalg.norm(np.diff(C[:m], axis=0), axis=1))
    coef, *_ = np.linalg.lstsq(np.column_stack((s, s * s)), Y, rcond=None)
    b, c = coef
    u = -length / float(np.linalg.norm(b))  # the parameter 'length' of arc before C[0]
    return C[0] + b * u + c * u * u


def _march(
    sl: _Slicer,
    c0: np.ndarray,
    d0: np.ndarray,
    r0: float,
    h: float,
    width: float,
    n0: float,
) -> tuple[list[np.ndarray], list[float]]:
    """Centres and radii from c0 (excluded) along d0 until the pipe ends, slices of
    ``width`` every ``h``."""
    centres, radii, counts = [c0], [r0], [float(n0)]
    d = d0
    max_slices = min(int(MAX_PATH_LENGTH_MM / h) + 1, MAX_SLICES)
    for _ in range(max_slices):
        r_ref = float(np.median(radii[-9:]))
        pred = centres[-1] + h * d
        circ = sl.fit(pred, d, width, r_ref, GATE_PER_RADIUS * r_ref)
        if circ is None:
            break
        typical = float(np.median(counts[-9:]))
        if circ.inliers < max(MIN_SLICE_POINTS, 0.2 * typical):
            break
        if abs(circ.radius - r_ref) > 0.2 * r_ref:
            break
        if np.linalg.norm(circ.centre - pred) > 0.5 * r_ref:
            break
        if len(centres) > 8:  # back where it has been: a ring, or the march turned round
            old = np.array(centres[: -math.ceil(4.0 * r_ref / h)])
            if len(old) and np.linalg.norm(old - circ.centre, axis=1).min() < r_ref:
                break
        centres.append(circ.centre)
        radii.append(circ.radius)
        counts.append(circ.inliers)
        d = _end_tangent(centres, TANGENT_SPAN_PER_RADIUS * r_ref, h)
    return centres[1:], radii[1:]


def _end_extension(
    X: np.ndarray, c: np.ndarray, d: np.ndarray, r: float, band: float, behind: float
) -> float:
    """How far past the centre c (along outward unit d, where the wall is whole for
    ``behind`` mm behind c) the wall of the points X goes.

    The wall points (within ``band`` of the radius) past a place where the wall is still
    whole, up to the first gap of a tenth of a radius, divided by the wall's density
    along the axis behind it, give the length they cover: for noise blurring the end, where
    the density halves, and barely moved by an outlier near the wall.  Done twice, the
    second time from just before the end found, so that the density's own error matters
    over a few mm only.
    """
    Y = X - c
    tau = Y @ d
    rho = np.linalg.norm(Y - tau[:, None] * d, axis=1)
    tau = np.sort(tau[(np.abs(rho - r) < band) & (tau >= -behind)])
    past = tau[tau >= 0.0]
    if len(past) == 0:
        return 0.0
    gaps = np.flatnonzero(np.diff(np.concatenate(([0.0], past))) > 0.1 * r)
    stop = (
        float(past[gaps[0] - 1])
        if len(gaps) and gaps[0] > 0
        else (0.0 if len(gaps) else float(past[-1]))
    )
    tau = tau[tau <= stop]
    tau0 = 0.0
    end = 0.0
    for _ in range(2):
        n_before = np.count_nonzero(tau < tau0)
        if n_before == 0:
            return end
        density = n_before / (behind + tau0)
        end = tau0 + np.count_nonzero(tau >= tau0) / density
        tau0 = max(0.0, end - band)
    return float(end)


def _distance_to_polyline(V: np.ndarray, tree: cKDTree, X: np.ndarray) -> np.ndarray:
    """Distance from each point of X (n, 3) to the polyline of vertices V (k, 3), measured
    exactly on the segments next to the two nearest vertices (``tree`` is a KD-tree of V).
    The centre line's vertices are a fraction of a radius apart and the points about a
    radius from it, so the nearest segment is among them."""
    _, v = tree.query(X, k=min(2, len(V)))
    v = v.reshape(len(X), -1)
    segs = np.clip(np.concatenate((v - 1, v), axis=1), 0, len(V) - 2)  # (n, 4)
    A = V[segs]
    AB = V[segs + 1] - A
    L2 = np.einsum("nkj,nkj->nk", AB, AB)
    rel = X[:, None, :] - A
    s = np.clip(np.einsum("nkj,nkj->nk", rel, AB) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    return np.linalg.norm(rel - s[..., None] * AB, axis=-1).min(axis=1)


def _seed(
    sl: _Slicer, where: np.ndarray, e1: np.ndarray, width: float, gate: float
) -> tuple[np.ndarray, np.ndarray, _Circle] | None:
    """A centre, the local axis and the circle there, from the slab through ``where``
    normal to e1; the axis from two slices one radius either side, three times."""
    circ = sl.fit(where, e1, width, None, gate)
    if circ is None:
        return None
    c, d, r = circ.centre, e1, circ.radius
    for _ in range(3):
        ahead = sl.fit(c + r * d, d, width, r, GATE_PER_RADIUS * r)
        behind = sl.fit(c - r * d, d, width, r, GATE_PER_RADIUS * r)
        if ahead is None or behind is None:
            return None
        dn = ahead.centre - behind.centre
        d = dn / np.linalg.norm(dn)
        circ = sl.fit(0.5 * (ahead.centre + behind.centre), d, width, r, GATE_PER_RADIUS * r)
        if circ is None:
            return None
        c, r = circ.centre, circ.radius
    return c, d, circ


def pipe_from_scan(
    points: np.ndarray,
    *,
    slice_step: float | None = None,
    max_fit_points: int = MAX_FIT_POINTS,
    seed: int = 0,
) -> ScanFit:
    """Fit the centre line and inner diameter of a pipe to a scan of its inner wall
    (module docstring).  ``slice_step`` (mm) defaults to 0.15 radii (0.05 to 0.5 radii).

    Raises :class:`ScanFitError` (one line) when the points show no pipe to follow.
    """
    times: dict[str, float] = {}
    t_start = time.perf_counter()
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ScanFitError(f"scan points must have shape (n, 3), got {P.shape}")
    if len(P) < MIN_SCAN_POINTS:
        raise ScanFitError(f"a scan needs at least {MIN_SCAN_POINTS} points, got {len(P)}")
    if not np.all(np.isfinite(P)):
        raise ScanFitError("scan points contain NaN or inf")
    if slice_step is not None and not (math.isfinite(slice_step) and slice_step > 0.0):
        raise ScanFitError(f"slice step must be a finite number > 0 mm, got {slice_step}")
    rng = np.random.default_rng(seed)
    Q = (
        P
        if len(P) <= max_fit_points
        else P[np.sort(rng.choice(len(P), max_fit_points, replace=False))]
    )
    M = Q if len(Q) <= MAX_MARCH_POINTS else Q[rng.choice(len(Q), MAX_MARCH_POINTS, replace=False)]
    sl = _Slicer(M, rng)
    now = time.perf_counter()
    times["index"], t0 = now - t_start, now

    # 1. seed: the middle slab across the principal axis (or one nearby, if that fails)
    mu = np.median(M, axis=0)
    r_mu = np.linalg.norm(M - mu, axis=1)
    core = M[r_mu <= np.percentile(r_mu, CORE_PERCENTILE)]  # a stray point turns no axis
    _, _, Vt = np.linalg.svd(np.cov((core - core.mean(axis=0)).T))
    e1 = Vt[0]
    t = (M - mu) @ e1
    lo, hi = np.percentile(t, [1.0, 99.0])
    extent = float(hi - lo)
    if not extent > 0.0:
        raise ScanFitError("the scan points do not extend along any direction")
    cross_extent = float(np.ptp((core - mu) @ Vt[1:].T, axis=0).max())
    width0 = max(extent / 50.0, 1e-6)
    seeded = None
    for f in SEED_QUANTILES:
        where = mu + float(np.percentile(t, f)) * e1
        seeded = _seed(sl, where, e1, width0, max(cross_extent, width0))
        if seeded is not None:
            break
    if seeded is None:
        raise ScanFitError(
            "no pipe found in the middle of the scan (is it a scan of a pipe's inner wall?)"
        )
    c, d, seed_circ = seeded
    r = seed_circ.radius
    now = time.perf_counter()
    times["seed"], t0 = now - t0, now

    # 2. march both ways (on at most MAX_MARCH_POINTS points)
    h = slice_step if slice_step is not None else STEP_PER_RADIUS * r
    if h > MAX_STEP_PER_RADIUS * r:
        raise ScanFitError(
            f"slice step {h:.3g} mm is above {MAX_STEP_PER_RADIUS:g} of the pipe's radius "
            f"({r:.3g} mm): its chords would cut the bends"
        )
    if h < MIN_STEP_PER_RADIUS * r:
        raise ScanFitError(
            f"slice step {h:.3g} mm is below {MIN_STEP_PER_RADIUS:g} of the pipe's radius "
            f"({r:.3g} mm): its slices would hold too few points"
        )
    width = max(h, STEP_PER_RADIUS * r)  # slices overlap when the step is smaller
    n0 = seed_circ.inliers * width / width0  # the wall points a slice holds there
    fwd, r_fwd = _march(sl, c, d, r, h, width, n0)
    bwd, r_bwd = _march(sl, c, -d, r, h, width, n0)
    C = np.array([*bwd[::-1], c, *fwd])
    if len(C) < 3:
        raise ScanFitError(
            f"the pipe could be followed over {len(C)} slice(s) only (step {h:.3g} mm)"
        )
    now = time.perf_counter()
    times["march"], t0 = now - t0, now

    # 3. refine on every fitted point: each slice is the points nearest its centre, fitted
    # normal to the centre line's tangent; smooth; extend the ends
    T = _tangents(C)
    r_med = float(np.median([*r_bwd, r, *r_fwd]))
    gate = GATE_PER_RADIUS * r_med
    label = cKDTree(C).query(Q)[1]
    order = np.argsort(label, kind="stable")
    bounds = np.searchsorted(label[order], np.arange(len(C) + 1))
    C2, R2, S2 = [], [], []
    a = max(0, math.ceil(width / (2.0 * h) - 0.5))  # neighbouring cells the slice reaches
    for i in range(len(C)):
        X = Q[order[bounds[max(0, i - a)] : bounds[min(len(C), i + a + 1)]]]
        circ2 = _fit_slice(X, C[i], T[i], width, r_med, gate, rng)
        if circ2 is not None and abs(circ2.radius - r_med) <= 0.2 * r_med:
            C2.append(circ2.centre)
            R2.append(circ2.radius)
            S2.append(circ2.scale)
    if len(C2) < 3:
        raise ScanFitError(
            f"only {len(C2)} of {len(C)} slices hold a circle when fitted again "
            "(is it a scan of a pipe's inner wall?)"
        )
    C = np.array(C2)
    if len(C) >= SMOOTH_WINDOW:
        from scipy.signal import savgol_filter  # here: scipy.signal takes 0.7 s to import

        C = savgol_filter(C, SMOOTH_WINDOW, 2, axis=0, mode="interp")
    radii = np.array(R2)
    r_fit = float(np.median(radii))
    band = max(INLIER_SIGMAS * float(np.median(S2)), MIN_INLIER_BAND_MM)
    T = _tangents(C)
    # each end measured from the third slice in (its slab and the one before are whole: the
    # march went two slices further); the slices past the end found are dropped
    if len(C) >= 12:  # the points nearest the first and last six slices
        k = 2
        ends = cKDTree(C[[0, 1, 2, 3, 4, 5, -6, -5, -4, -3, -2, -1]]).query(Q)[1]
        head_pts, tail_pts = Q[ends < 6], Q[ends >= 6]
        behind = 2.5 * h
    else:
        k, head_pts, tail_pts, behind = 0, Q, Q, 0.5 * h
    wide = max(band, 0.05 * r_fit)  # the same points counted behind and past the end
    head = _end_extension(head_pts, C[k], -T[k], r_fit, wide, behind)
    tail = _end_extension(tail_pts, C[-1 - k], T[-1 - k], r_fit, wide, behind)
    reach = (k + 1) * h + width + 3.0 * wide  # as far as a stop at the scan's end leaves it
    for name, ext, c_end in (("first", head, C[0]), ("last", tail, C[-1])):
        if ext > reach:
            x, y, z = (f"{v:.1f}" for v in c_end)
            raise ScanFitError(
                f"the pipe could not be followed past its {name} slice at ({x}, {y}, {z}): "
                f"the wall goes on for {ext:.0f} mm (a scan too sparse or noisy there, or a "
                "slice step too small)"
            )
    keep = np.ones(len(C), dtype=bool)
    keep[:k] = (C[:k] - C[k]) @ -T[k] < head - 1e-9
    if k:
        keep[-k:] = (C[-k:] - C[-1 - k]) @ T[-1 - k] < tail - 1e-9
    start = _end_point(C[k:], head)  # along the centre line's curve, not its tangent
    end = _end_point(C[len(C) - 1 - k :: -1], tail)
    parts = [C[keep]]
    if np.linalg.norm(start - parts[0][0]) > 1e-9:
        parts.insert(0, start[None])
    if np.linalg.norm(end - parts[-1][-1]) > 1e-9:
        parts.append(end[None])
    axis = np.vstack(parts)
    now = time.perf_counter()
    times["refine"], t0 = now - t0, now

    # 4. residuals of every point
    try:
        path = KnownPath.from_points(axis, source="scan axis")
    except PlanningError as exc:
        raise ScanFitError(f"the fitted centre line is not a path: {exc}") from None
    tree = cKDTree(path.points)
    e = np.concatenate(
        [
            _distance_to_polyline(path.points, tree, P[j : j + STATS_CHUNK]) - r_fit
            for j in range(0, len(P), STATS_CHUNK)
        ]
    )
    band = max(INLIER_SIGMAS * _mad_scale(e), MIN_INLIER_BAND_MM)
    if 2.0 * r_fit < MIN_INNER_DIAMETER_MM:
        raise ScanFitError(
            f"the fitted inner diameter is {2.0 * r_fit:.3g} mm, below "
            f"{MIN_INNER_DIAMETER_MM:g} mm (is the scan in metres? mm are expected)"
        )
    if band > MAX_BAND_PER_RADIUS * r_fit:
        raise ScanFitError(
            f"the points spread {band:.3g} mm (3 sigma) about the fitted wall, more than "
            f"{MAX_BAND_PER_RADIUS:g} of its radius ({r_fit:.3g} mm): not a scan of a pipe's "
            "inner wall"
        )
    inl = np.abs(e) <= band
    n_in = int(inl.sum())
    ei = e[inl]
    times["residuals"] = time.perf_counter() - t0
    times["total"] = time.perf_counter() - t_start
    axis = np.array(path.points)
    axis.setflags(write=False)
    return ScanFit(
        axis=axis,
        inner_diameter=2.0 * r_fit,
        rms=float(np.sqrt(np.mean(ei * ei))) if n_in else math.nan,
        p95=float(np.percentile(np.abs(ei), 95.0)) if n_in else math.nan,
        inlier_fraction=n_in / len(P),
        inlier_band=band,
        n_points=len(P),
        n_outliers=len(P) - n_in,
        n_slices=len(radii),
        diameter_spread=2.0 * _mad_scale(radii),
        timings_s=times,
    )


def read_scan(path: str | Path, **kwargs: Any) -> ScanFit:
    """:func:`pipe_from_scan` of a point cloud file (PLY, CSV or NPY)."""
    from hrm_ctrl.formats.pointcloud import read_point_cloud

    points = read_point_cloud(path)
    try:
        return pipe_from_scan(points, **kwargs)
    except ScanFitError as exc:
        raise ScanFitError(f"{path}: {exc}") from None


def path_and_pipe_from_scan(
    path: str | Path, start_near: np.ndarray | None = None
) -> tuple[KnownPath, KnownPath, float]:
    """The path to plan along a scanned pipe, the pipe's axis and its inner diameter (mm).

    The path is the fitted centre line from the end nearest ``start_near`` (the robot's
    base position; by default the world origin); the axis is the same line, for the pipe
    environment (``Pipe(axis, inner_diameter)``).
    """
    fit = read_scan(path)
    line = fit.path(start_near, source=f"scan {path}")
    return line, line, fit.inner_diameter


def synthetic_pipe_scan(
    axis: KnownPath,
    inner_diameter: float,
    n_points: int,
    noise_mm: float,
    outlier_fraction: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """A scan of the inner wall of the pipe of ``axis`` and ``inner_diameter`` (mm):
    ``n_points`` points, of which ``round(outlier_fraction n_points)`` outliers uniform in
    the axis's bounding box grown by the diameter, the rest on the wall (uniform in arc
    length and angle) with isotropic Gaussian noise of standard deviation ``noise_mm``;
    shuffled.  The tangent is interpolated between the vertices' mean tangents, so a
    finely sampled arc gives a smooth tube.
    """
    n = int(n_points)
    if not 0 < n <= MAX_SYNTHETIC_POINTS:
        raise PlanningError(f"n_points must be in 1..{MAX_SYNTHETIC_POINTS}, got {n_points}")
    if not (0.0 <= outlier_fraction <= 1.0) or not (noise_mm >= 0.0) or not inner_diameter > 0:
        raise PlanningError("noise must be >= 0, outlier fraction in [0, 1], diameter > 0")
    r = inner_diameter / 2.0
    n_out = round(outlier_fraction * n)
    n_wall = n - n_out
    s = rng.uniform(0.0, axis.length, n_wall)
    seg = np.diff(axis.points, axis=0)
    dseg = seg / np.linalg.norm(seg, axis=1, keepdims=True)
    Tv = np.vstack((dseg[:1], dseg[:-1] + dseg[1:], dseg[-1:]))
    Tv /= np.linalg.norm(Tv, axis=1, keepdims=True)
    j = np.clip(np.searchsorted(axis.s, s, side="right") - 1, 0, len(axis.s) - 2)
    f = ((s - axis.s[j]) / (axis.s[j + 1] - axis.s[j]))[:, None]
    t = (1.0 - f) * Tv[j] + f * Tv[j + 1]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    a = np.eye(3)[np.argmin(np.abs(t), axis=1)]
    n1 = np.cross(t, a)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 = np.cross(t, n1)
    psi = rng.uniform(0.0, 2.0 * math.pi, n_wall)[:, None]
    wall = axis.points_at(s) + r * (np.cos(psi) * n1 + np.sin(psi) * n2)
    wall += rng.normal(0.0, noise_mm, wall.shape) if noise_mm > 0 else 0.0
    lo = axis.points.min(axis=0) - inner_diameter
    hi = axis.points.max(axis=0) + inner_diameter
    out = rng.uniform(lo, hi, (n_out, 3))
    cloud = np.vstack((wall, out))
    return cloud[rng.permutation(n)]
