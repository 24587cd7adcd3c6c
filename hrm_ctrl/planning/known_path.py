"""Known paths (Sec. 3.2, Eqs. 10-12): a polyline of points the tip follows.

Arc length is the trapezoidal integral of Eq. (10), which for a polyline is the
sum of its chord lengths.  The point at a travelled distance ``d`` is Eq. (12)
with the erratum of ``NOTES.md``: between the bracketing points C and D,
``E' = C + (d - L_AC) / |CD| (D - C)``.

>>> P = KnownPath.from_points(np.array([[0, 0, 0], [3, 0, 0], [3, 4, 0]], float))
>>> P.length
7.0
>>> P.point_at(5.0).tolist(), P.tangent_at(5.0).tolist()
([3.0, 2.0, 0.0], [0.0, 1.0, 0.0])
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from hrm_ctrl.errors import PathFileError
from hrm_ctrl.files import read_text_file
from hrm_ctrl.planning.point_tree import PointTree

DENSE_SPACING = 0.5  # mm, resampling of the path for distance queries
# Bounds on what a path may size (memory and time of everything planned along it): the
# arm is 2 m long and its scenarios have a few hundred points.
MAX_PATH_POINTS = 100_000  # points of a path (a path file has one a line)
MAX_PATH_BYTES = 16 * 2**20  # a path file larger than this is refused unread
MAX_COORDINATE_MM = 1e6  # |x|, |y|, |z| of a point: 1 km from the world origin
MAX_PATH_LENGTH_MM = 1e5  # 100 m: the dense resampling then has at most 200,000 points


class DuplicatePointsWarning(UserWarning):
    """Consecutive duplicate points were dropped from a path."""


def drop_consecutive_duplicates(points: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, int]:
    """Remove points equal (within ``tol`` mm) to their predecessor.

    >>> p, n = drop_consecutive_duplicates(np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]], float))
    >>> p.shape, n
    ((2, 3), 1)
    """
    if len(points) < 2:
        return points, 0
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate(([True], step > tol))
    return points[keep], int((~keep).sum())


@dataclass(frozen=True, eq=False)
class KnownPath:
    """A polyline path with its cumulative arc length.

    Attributes:
        points: (M, 3) distinct consecutive points, mm.
        s: (M,) arc length at each point (Eq. 10), ``s[0] = 0``.
        source: where the path came from (file or scenario name).
    """

    points: np.ndarray
    s: np.ndarray
    source: str = "<points>"

    @classmethod
    def from_points(cls, points: np.ndarray, source: str = "<points>") -> KnownPath:
        pts = np.array(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise PathFileError(f"{source}: path points must have 3 columns (x, y, z)")
        if not np.all(np.isfinite(pts)):
            raise PathFileError(f"{source}: path contains NaN or inf")
        if len(pts) > MAX_PATH_POINTS:
            raise PathFileError(
                f"{source}: path has {len(pts)} points, more than the {MAX_PATH_POINTS} "
                "a path may have"
            )
        far = np.abs(pts) > MAX_COORDINATE_MM
        if far.any():
            k, c = (int(v) for v in np.argwhere(far)[0])
            raise PathFileError(
                f"{source}: point {k + 1}: {'xyz'[c]} = {pts[k, c]:.6g} mm is farther than "
                f"{MAX_COORDINATE_MM:g} mm from the origin"
            )
        pts, dropped = drop_consecutive_duplicates(pts)
        if dropped:
            warnings.warn(
                f"{source}: dropped {dropped} consecutive duplicate point(s)",
                DuplicatePointsWarning,
                stacklevel=2,
            )
        if len(pts) < 2:
            raise PathFileError(f"{source}: a path needs at least 2 distinct points")
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        s = np.concatenate(([0.0], np.cumsum(seg)))
        if s[-1] > MAX_PATH_LENGTH_MM:
            raise PathFileError(
                f"{source}: path is {s[-1]:.6g} mm long, longer than the "
                f"{MAX_PATH_LENGTH_MM:g} mm a path may be"
            )
        pts.setflags(write=False)
        s.setflags(write=False)
        return cls(points=pts, s=s, source=source)

    @property
    def length(self) -> float:
        """Total arc length L_path (Eq. 10)."""
        return float(self.s[-1])

    def _segment(self, d: float) -> int:
        """Index j of the segment [P_j, P_j+1] holding travelled distance d."""
        j = int(np.searchsorted(self.s, d, side="right")) - 1
        return min(max(j, 0), len(self.s) - 2)

    def point_at(self, d: float) -> np.ndarray:
        """Eq. (12): the point at travelled distance d (clamped to the path)."""
        d = min(max(float(d), 0.0), self.length)
        j = self._segment(d)
        C, D = self.points[j], self.points[j + 1]
        return C + (d - self.s[j]) / (self.s[j + 1] - self.s[j]) * (D - C)

    def points_at(self, d: np.ndarray) -> np.ndarray:
        """:meth:`point_at` for many distances at once, shape (N, 3).

        >>> P = KnownPath.from_points(np.array([[0, 0, 0], [3, 0, 0], [3, 4, 0]], float))
        >>> P.points_at(np.array([0.0, 5.0, 9.0])).tolist()
        [[0.0, 0.0, 0.0], [3.0, 2.0, 0.0], [3.0, 4.0, 0.0]]
        """
        d = np.clip(np.asarray(d, dtype=float), 0.0, self.length)
        j = np.clip(np.searchsorted(self.s, d, side="right") - 1, 0, len(self.s) - 2)
        C, D = self.points[j], self.points[j + 1]
        frac = (d - self.s[j]) / (self.s[j + 1] - self.s[j])
        return C + frac[:, None] * (D - C)

    def tangent_at(self, d: float) -> np.ndarray:
        """Unit tangent of the segment holding d (the first at 0, the last at the end)."""
        d = min(max(float(d), 0.0), self.length)
        j = self._segment(d)
        t = self.points[j + 1] - self.points[j]
        return t / np.linalg.norm(t)

    @cached_property
    def _dense(self) -> tuple[np.ndarray, PointTree]:
        """The same polyline resampled every <= DENSE_SPACING mm, and a KD-tree of it."""
        seg = np.diff(self.s)
        k = np.maximum(np.ceil(seg / DENSE_SPACING).astype(np.int64), 1)
        t = np.concatenate([np.arange(kk) / kk for kk in k])
        j = np.repeat(np.arange(len(seg)), k)
        pts = self.points[j] + t[:, None] * (self.points[j + 1] - self.points[j])
        pts = np.vstack((pts, self.points[-1]))
        return pts, PointTree(pts)

    def distance_to(self, q: np.ndarray) -> np.ndarray:
        """Shortest distance from each point of ``q`` (..., 3) to the polyline.

        The path is resampled every <= 0.5 mm (the same polyline); the segments
        next to the two nearest samples are measured exactly, which finds the
        true nearest segment unless another part of the path comes within the
        sample spacing of it.

        >>> P = KnownPath.from_points(np.array([[0, 0, 0], [100, 0, 0], [100, 50, 0]], float))
        >>> P.distance_to(np.array([[50.0, 3.0, 4.0], [120.0, 60.0, 0.0]])).round(9).tolist()
        [5.0, 22.360679775]
        """
        q = np.asarray(q, dtype=float)
        shape = q.shape[:-1]
        flat = q.reshape(-1, 3)
        if len(flat) == 0:
            return np.zeros(shape)
        pts, tree = self._dense
        _, v = tree.query(flat, k=min(2, len(pts)))
        v = np.atleast_2d(v).reshape(len(flat), -1)
        segs = np.clip(np.concatenate((v - 1, v), axis=1), 0, len(pts) - 2)  # (P, 4)
        A = pts[segs]
        AB = pts[segs + 1] - A
        L2 = np.einsum("pkj,pkj->pk", AB, AB)
        rel = flat[:, None, :] - A
        t = np.clip(np.einsum("pkj,pkj->pk", rel, AB) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
        d = np.linalg.norm(rel - t[..., None] * AB, axis=-1).min(axis=1)
        return d.reshape(shape)


def tangent_angles(u: np.ndarray) -> tuple[float, float]:
    """(K, T) of a unit tangent per Eq. (6): ``u = (sinK cosT, cosK cosT, sinT)``.

    >>> K, T = tangent_angles(np.array([1.0, 0.0, 0.0]))
    >>> round(K, 12), round(T, 12)
    (1.570796326795, 0.0)
    """
    u = np.asarray(u, dtype=float)
    u = u / np.linalg.norm(u)
    T = math.asin(max(-1.0, min(1.0, float(u[2]))))
    K = math.atan2(float(u[0]), float(u[1]))
    return K, T


def _cell(cell: str) -> str:
    """A cell for a message, at most about 40 characters."""
    text = repr(cell.strip())
    return text if len(text) <= 40 else f"{text[:30]}...' ({len(cell.strip())} characters)"


def load_path_csv(path: str | Path) -> KnownPath:
    """Read a path file: header ``x,y,z`` then one point per line (mm).

    Raises :class:`PathFileError` naming the file, line and value on any problem; a
    file larger than :data:`MAX_PATH_BYTES` is refused unread, one of more than
    :data:`MAX_PATH_POINTS` points before its numbers are read.
    """
    p = Path(path)
    text = read_text_file(p, PathFileError, "path file", max_bytes=MAX_PATH_BYTES)
    lines = text.splitlines()
    if len(lines) > MAX_PATH_POINTS + 1 and sum(bool(x.strip()) for x in lines) > (
        MAX_PATH_POINTS + 1
    ):
        raise PathFileError(
            f"{p}: path file has more than the {MAX_PATH_POINTS} points a path may have"
        )
    reader = csv.reader(lines)
    rows: list[list[str]] = []
    try:
        rows.extend(reader)
    except csv.Error as exc:  # e.g. a field longer than csv's limit
        raise PathFileError(f"{p}:{reader.line_num}: not a CSV line ({exc})") from None
    rows_numbered = [(n, r) for n, r in enumerate(rows, start=1) if any(c.strip() for c in r)]
    if not rows_numbered:
        raise PathFileError(f"{p}: path file is empty")
    n0, header = rows_numbered[0]
    if [c.strip().lower() for c in header] != ["x", "y", "z"]:
        raise PathFileError(f"{p}:{n0}: header must be 'x,y,z', got {','.join(header)!r}")
    if len(rows_numbered) == 1:
        raise PathFileError(f"{p}: path file has a header but no points")
    pts = []
    for n, row in rows_numbered[1:]:
        if len(row) != 3:
            raise PathFileError(f"{p}:{n}: expected 3 columns (x,y,z), got {len(row)}")
        vals = []
        for name, cell in zip("xyz", row, strict=True):
            try:
                v = float(cell)
            except ValueError:
                raise PathFileError(f"{p}:{n}: {name} is not a number: {_cell(cell)}") from None
            if not math.isfinite(v):
                raise PathFileError(f"{p}:{n}: {name} is not finite: {_cell(cell)}")
            if abs(v) > MAX_COORDINATE_MM:
                raise PathFileError(
                    f"{p}:{n}: {name} = {v:.6g} mm is farther than {MAX_COORDINATE_MM:g} mm "
                    "from the origin"
                )
            vals.append(v)
        pts.append(vals)
    return KnownPath.from_points(np.array(pts), source=str(p))


def path_csv(path: KnownPath) -> str:
    """A path file (``x,y,z`` header, one point a line, mm) that :func:`load_path_csv` reads.

    >>> print(path_csv(KnownPath.from_points(np.array([[0, 0, 0], [1.5, 0, 2]], float))), end="")
    x,y,z
    0,0,0
    1.5,0,2
    """
    rows = ["x,y,z", *(",".join(f"{v:.10g}" for v in p) for p in path.points)]
    return "\n".join(rows) + "\n"
