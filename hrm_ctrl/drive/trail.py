"""The trail: the path the tip draws as the operator steers, and the body follows.

The trail starts at a point ``A`` with a heading (the arm's current tip along its last
link, a scenario's entry, or a given path file) and grows at its end as the tip
advances beyond it: each advance ``ds`` turns the heading by the steer (yaw about the
trail's "up" normal, pitch about its "side" normal) and adds the chord of that arc.
``A`` is where the paper's modal segment joins the travelled path (Sec. 3.2): the arm is
the modal segment from its base to ``A`` plus the trail from ``A`` up to the tip's
travel.  Retracting only moves the tip's travel back along the trail; advancing again
follows the trail drawn, unless the operator steers there, which cuts the trail at the
tip and draws a new branch from it.

The heading frame is carried without twist (parallel transport): ``up`` turns only with
pitch.  Positive yaw turns left (towards ``up x tangent``), positive pitch turns up.
Straight advances extend the last segment instead of adding points, so the trail's
points are its corners and arc samples only (at most one point per ``ARC_SPACING_MM``
on an arc).

>>> import math
>>> t = Trail.starting_at(np.zeros(3), np.array([1.0, 0, 0]))
>>> t.extend(100.0, 0.0, 0.0); t.extend(math.pi / 2 * 50, 0.0, 1 / 50)  # a quarter circle up
>>> np.round(t.end, 6).tolist(), (np.round(t.heading, 9) + 0.0).tolist()
([150.0, 0.0, 50.0], [0.0, 0.0, 1.0])
>>> round(t.length, 3)          # 100 + 25 pi, less by the chords of 1 mm of arc
178.539
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hrm_ctrl.drive.command import DriveError
from hrm_ctrl.errors import PathFileError
from hrm_ctrl.files import write_atomic
from hrm_ctrl.planning.known_path import (
    MAX_PATH_LENGTH_MM,
    MAX_PATH_POINTS,
    KnownPath,
    path_csv,
)

ARC_SPACING_MM = 1.0  # on an arc, a point at least every this much of the trail


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if not (math.isfinite(n) and n > 0.0):
        raise DriveError(f"trail: a heading must be a finite non-zero vector, got {v.tolist()}")
    return v / n


def _up_for(tangent: np.ndarray) -> np.ndarray:
    """The "up" normal of a heading: world +z made normal to it (+x if the heading is
    vertical)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(tangent[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    return _unit(ref - (ref @ tangent) * tangent)


class Trail:
    """A growing polyline with a heading frame at its end (see the module)."""

    def __init__(
        self, points: np.ndarray, heading: np.ndarray, up: np.ndarray | None = None
    ) -> None:
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 1 or not np.isfinite(pts).all():
            raise DriveError("trail: points must be a finite (n >= 1, 3) array")
        self._cap = max(1024, 2 * len(pts) + 2)
        self._p = np.empty((self._cap, 3))
        self._s = np.empty(self._cap)
        self._n = 0
        for p in pts:
            self._append(p)
        self._heading = _unit(np.asarray(heading, dtype=float))
        u = _up_for(self._heading) if up is None else np.asarray(up, dtype=float)
        self._up = _unit(u - (u @ self._heading) * self._heading)
        self._straight_end = False  # the last segment may be lengthened in place

    @classmethod
    def starting_at(cls, point: np.ndarray, heading: np.ndarray) -> Trail:
        """A trail of one point (the junction A) and the heading the tip has there."""
        return cls(np.asarray(point, dtype=float)[None, :], heading)

    @classmethod
    def from_path(cls, path: KnownPath) -> Trail:
        """The trail of a path (a path file): its points, headed along its last segment."""
        p = path.points
        return cls(p, p[-1] - p[-2])

    # read-outs
    @property
    def points(self) -> np.ndarray:
        """The trail's points (a read-only view, valid until the trail changes)."""
        v = self._p[: self._n]
        v.flags.writeable = False
        return v

    @property
    def s(self) -> np.ndarray:
        """Arc length at each point (a read-only view)."""
        v = self._s[: self._n]
        v.flags.writeable = False
        return v

    @property
    def n_points(self) -> int:
        return self._n

    @property
    def length(self) -> float:
        return float(self._s[self._n - 1])

    @property
    def start(self) -> np.ndarray:
        return self._p[0].copy()

    @property
    def end(self) -> np.ndarray:
        return self._p[self._n - 1].copy()

    @property
    def heading(self) -> np.ndarray:
        """Unit tangent at the trail's end."""
        return self._heading.copy()

    @property
    def up(self) -> np.ndarray:
        return self._up.copy()

    def start_tangent(self) -> np.ndarray:
        """Unit tangent at A (the modal segment's end direction)."""
        if self._n >= 2:
            return _unit(self._p[1] - self._p[0])
        return self._heading.copy()

    def point_at(self, travel_mm: float, out: np.ndarray | None = None) -> np.ndarray:
        """The point at ``travel_mm`` along the trail (clamped), into ``out`` if given."""
        out = np.empty(3) if out is None else out
        n = self._n
        if n == 1:
            out[:] = self._p[0]
            return out
        d = min(max(travel_mm, 0.0), float(self._s[n - 1]))
        j = min(max(int(np.searchsorted(self._s[:n], d, side="right")) - 1, 0), n - 2)
        ds = self._s[j + 1] - self._s[j]
        w = (d - self._s[j]) / ds if ds > 0.0 else 0.0
        np.multiply(self._p[j + 1] - self._p[j], w, out=out)
        out += self._p[j]
        return out

    def count_before(self, travel_mm: float) -> int:
        """How many points lie strictly before ``travel_mm``."""
        return int(np.searchsorted(self._s[: self._n], travel_mm, side="left"))

    # changes
    def _append(self, p: np.ndarray) -> None:
        self._put(self._n, p)

    def _put(self, k: int, p: np.ndarray) -> None:
        """Point ``k`` (at most :attr:`n_points`) set to ``p`` with its arc length, the
        trail ending there (``p`` within 1e-9 mm of point ``k - 1``: ending at that one).
        The point is written before the count changes, so a reader on another thread (the
        shape watch's copy of :attr:`points`) sees a trail with its end, never one cut
        back by the segment a straight advance lengthens in place."""
        if k == self._cap:
            if self._cap >= MAX_PATH_POINTS:
                raise DriveError(
                    f"trail: more than the {MAX_PATH_POINTS} points a path may have; "
                    "save it and start a new drive"
                )
            grow = min(2 * self._cap, MAX_PATH_POINTS)
            p2, s2 = np.empty((grow, 3)), np.empty(grow)
            p2[: self._n], s2[: self._n] = self._p[: self._n], self._s[: self._n]
            self._p, self._s, self._cap = p2, s2, grow
        if k == 0:
            s = 0.0
        else:
            d = float(np.linalg.norm(p - self._p[k - 1]))
            if d <= 1e-9:
                self._n = k
                return
            s = float(self._s[k - 1]) + d
        if s > MAX_PATH_LENGTH_MM:
            raise DriveError(f"trail: longer than the {MAX_PATH_LENGTH_MM:g} mm a path may be")
        self._p[k] = p
        self._s[k] = s
        self._n = k + 1

    def extend(self, ds_mm: float, yaw_per_mm: float, pitch_per_mm: float) -> None:
        """Grow the trail by ``ds_mm`` (> 0) at its end, turning the heading by
        ``yaw_per_mm`` and ``pitch_per_mm`` (rad per mm) along the way (an arc)."""
        if not (math.isfinite(ds_mm) and ds_mm > 0.0):
            return
        h, u = self._heading, self._up
        left = np.cross(u, h)
        w = yaw_per_mm * u - pitch_per_mm * left  # pitch up turns h towards up
        kappa = float(np.linalg.norm(w))
        if not kappa > 1e-12:  # straight (a turn of less than 1e-9 rad a km is none)
            end = self._p[self._n - 1] + ds_mm * h
            if self._straight_end and self._n >= 2:
                self._put(self._n - 1, end)  # lengthen the last straight segment in place
            else:
                self._append(end)
            self._straight_end = True
            return
        # the turn: a rotation by angle phi = |w| ds about the axis w
        axis = w / kappa
        remaining = ds_mm
        while remaining > 1e-12:
            step = min(remaining, ARC_SPACING_MM)
            phi = kappa * step
            # chord of the arc: length 2 sin(phi/2)/kappa along h turned by phi/2
            h_mid = _rotate(h, axis, 0.5 * phi)
            chord = step if phi < 1e-9 else 2.0 * math.sin(0.5 * phi) / kappa
            self._append(self._p[self._n - 1] + chord * h_mid)
            h = _rotate(h, axis, phi)
            u = _rotate(u, axis, phi)
            remaining -= step
        self._heading = _unit(h)
        self._up = _unit(u - (u @ self._heading) * self._heading)
        self._straight_end = False

    def cut(self, travel_mm: float) -> None:
        """End the trail at ``travel_mm`` (a new branch grows from there), the heading
        that of the segment it ends on."""
        if travel_mm >= self.length - 1e-9:
            return
        d = max(travel_mm, 0.0)
        p = self.point_at(d)
        k = self.count_before(d)  # points strictly before d
        if k == 0:
            k = 1
            p = self._p[0].copy()
        h = self._p[k] - self._p[k - 1] if k < self._n else self._heading
        self._put(k, p)
        self._heading = _unit(h)
        self._up = _unit(self._up - (self._up @ self._heading) * self._heading)
        self._straight_end = False

    def set_heading(self, heading: np.ndarray, up: np.ndarray) -> None:
        """Set the heading frame at the end (after :meth:`cut`, to take back a growth)."""
        self._heading = _unit(np.asarray(heading, dtype=float))
        u = np.asarray(up, dtype=float)
        self._up = _unit(u - (u @ self._heading) * self._heading)

    # files
    def known_path(self, source: str = "<trail>") -> KnownPath:
        """The trail as a :class:`KnownPath` (needs two points)."""
        if self._n < 2:
            raise DriveError("trail: nothing drawn yet (one point), no path to save")
        return KnownPath.from_points(self._p[: self._n].copy(), source=source)

    def save(self, path: str | Path) -> None:
        """Write the trail as a path file ``hrm plan --path`` reads (atomically)."""
        text = path_csv(self.known_path(str(path)))
        try:
            write_atomic(path, text)
        except OSError as exc:
            raise PathFileError(f"{path}: cannot write path file ({exc})") from None


def _rotate(v: np.ndarray, axis: np.ndarray, phi: float) -> np.ndarray:
    """Rodrigues' rotation of ``v`` about the unit ``axis`` by ``phi``."""
    c, s = math.cos(phi), math.sin(phi)
    return v * c + np.cross(axis, v) * s + axis * (axis @ v) * (1.0 - c)
