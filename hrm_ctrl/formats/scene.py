"""The scene file: the environment the arm moves among (pipes, walls with openings, boxes).

A TOML file of three kinds of tables, each an array of tables (any number, in any order)::

    description = "a pipe and a wall"      # optional

    [[pipe]]                               # the inner wall of a pipe
    axis_mm = [[1200, 100, 300], [1800, 100, 300]]   # the axis polyline, >= 2 points
    inner_diameter_mm = 70                 # > 0

    [[wall]]                               # a plane slab, infinite unless bounded
    point_mm = [1200, 0, 0]                # a point of its mid-plane
    normal = [1, 0, 0]                     # its normal (any length > 0)
    thickness_mm = 0                       # optional, >= 0 (default 0: a sheet)

      [[wall.opening]]                     # a round hole through the wall
      shape = "round"
      centre_mm = [1200, 100, 300]
      diameter_mm = 80                     # > 0

      [[wall.opening]]                     # a rectangular hole
      shape = "rect"
      centre_mm = [1200, 100, 100]
      width_mm = 120                       # > 0, along u
      height_mm = 60                       # > 0, along normal x u
      u = [0, 1, 0]                        # in the wall's plane

      [[wall.bound]]                       # optional: the wall exists only where
      point_mm = [1200, 0, 0]              #   (p - point_mm) . normal >= 0
      normal = [1, 0, 0]                   #   (normal projected onto the wall's plane)

    [[box]]                                # a solid box
    centre_mm = [1500, 0, 0]
    size_mm = [100, 50, 20]                # edge lengths along its own x, y, z; > 0
    yaw_deg = 30                           # optional: rotation Rz(yaw) Ry(pitch) Rx(roll),
    pitch_deg = 0                          #   or instead `rotation` = a 3 x 3 rotation
    roll_deg = 0                           #   matrix (rows), world from box

Lengths in mm.  What the models mean (distances, what the end of a pipe is, what a wall's
opening is) is in :mod:`hrm_ctrl.planning.environment`.  Every problem (an unknown table,
key or shape, a missing key, a size <= 0 or over :data:`MAX_SIZE_MM`, a coordinate over
:data:`MAX_COORDINATE_MM`, an angle over :data:`MAX_ANGLE_DEG`, NaN or inf, a list of the
wrong length) is one
:class:`SceneFileError` line naming the file, the table and its index (0-based) and the
key, e.g. ``scene.toml: wall[1].opening[0].diameter_mm: expected a number > 0, got -80``.
A scene's pipes may have axes of at most :data:`MAX_PIPE_AXIS_MM` and 100,000 points in
all (each axis is
resampled every 0.5 mm for its distance queries), its walls :data:`MAX_WALL_LIMITS`
openings and bounds in all (each is a term of every distance query, as a table is).
The same data (:meth:`Environment.to_dict`) is what a plan file keeps of its environment.

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "scene.toml"
>>> _ = p.write_text('[[box]]\\ncentre_mm = [0, 0, 0]\\nsize_mm = [20, 20, 20]\\n')
>>> env = read_scene(p)
>>> float(env.free_distance(np.array([15.0, 0, 0])))
5.0
>>> _ = p.write_text('[[wall]]\\npoint_mm = [0, 0, 0]\\nnormal = [1, 0, 0]\\n'
...                  '[[wall.opening]]\\nshape = "oval"\\n')
>>> read_scene(p)  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.formats.scene.SceneFileError: ...scene.toml: wall[0].opening[0].shape: expected one \
of 'round', 'rect', got 'oval'
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.errors import PathFileError, PlanningError
from hrm_ctrl.files import read_toml
from hrm_ctrl.planning.environment import (
    Box,
    Environment,
    OpeningShape,
    Pipe,
    RectOpening,
    RoundOpening,
    Wall,
)
from hrm_ctrl.planning.known_path import (
    MAX_COORDINATE_MM,
    MAX_PATH_LENGTH_MM,
    MAX_PATH_POINTS,
    KnownPath,
)

MAX_SIZE_MM = 2 * MAX_COORDINATE_MM  # a diameter, width, thickness or box edge
MAX_ANGLE_DEG = 360.0  # a box's yaw, pitch or roll, either way
MAX_OBSTACLES = 1000  # tables of a scene (every one costs each clearance query)
MAX_OPENINGS = 100  # openings (and bounds) of one wall
MAX_WALL_LIMITS = 1000  # openings and bounds of all walls (each costs every query, as a table)
MAX_PIPE_AXIS_MM = MAX_PATH_LENGTH_MM  # all pipes' axes: 200,000 points resampled, ~10 MB

_TOP = {"description", "pipe", "wall", "box"}
_PIPE = {"axis_mm", "inner_diameter_mm"}
_WALL = {"point_mm", "normal", "thickness_mm", "opening", "bound"}
_ROUND = {"shape", "centre_mm", "diameter_mm"}
_RECT = {"shape", "centre_mm", "width_mm", "height_mm", "u"}
_BOUND = {"point_mm", "normal"}
_BOX = {"centre_mm", "size_mm", "yaw_deg", "pitch_deg", "roll_deg", "rotation"}


class SceneFileError(PlanningError):
    """A scene file (or a plan file's environment) is not a valid scene."""


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


class _Reader:
    """Checks scene data, raising ``error`` with one line naming ``where`` and the place."""

    def __init__(self, where: str, error: type[Exception]) -> None:
        self.where, self.error = where, error

    def fail(self, place: str, what: str) -> Exception:
        return self.error(f"{self.where}: {place}: {what}" if place else f"{self.where}: {what}")

    def table(self, value: Any, place: str, keys: set[str], required: tuple[str, ...]) -> dict:
        if not isinstance(value, Mapping):
            raise self.fail(place, f"expected a table, got {_short(value)}")
        for k in value:
            if k not in keys:
                raise self.fail(place, f"unknown key {k!r} (known: {', '.join(sorted(keys))})")
        for k in required:
            if k not in value:
                raise self.fail(place, f"missing key {k!r}")
        return dict(value)

    def tables(self, value: Any, place: str, limit: int) -> list[Any]:
        if not isinstance(value, list):
            raise self.fail(
                place, f"expected an array of tables ([[{place}]]), got {_short(value)}"
            )
        if len(value) > limit:
            raise self.fail(place, f"{len(value)} tables, more than the {limit} allowed")
        return value

    def number(
        self,
        value: Any,
        place: str,
        low: float | None = None,
        strict=True,
        high: float | None = None,
    ) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(place, f"expected a number, got {_short(value)}")
        x = float(value)
        if not math.isfinite(x):
            raise self.fail(place, f"expected a finite number, got {value!r}")
        if low is not None and (x <= low if strict else x < low):
            raise self.fail(
                place, f"expected a number {'>' if strict else '>='} {low:g}, got {value!r}"
            )
        if high is not None and abs(x) > high:
            span = f"at most {high:g}" if low is not None else f"within -{high:g}..{high:g}"
            raise self.fail(place, f"expected a number {span}, got {value!r}")
        return x

    def size(self, value: Any, place: str, strict: bool = True) -> float:
        """A size (a diameter, a width, a thickness): > 0 (>= 0 unless ``strict``), at
        most :data:`MAX_SIZE_MM` (a scene's sizes and coordinates stay where a distance
        squared is still a finite float)."""
        return self.number(value, place, 0.0, strict, high=MAX_SIZE_MM)

    def vector(self, value: Any, place: str, n: int = 3, coordinate: bool = False) -> np.ndarray:
        if not isinstance(value, list) or len(value) != n:
            got = f"{len(value)} items" if isinstance(value, list) else _short(value)
            raise self.fail(place, f"expected an array of {n} numbers, got {got}")
        v = np.array([self.number(x, f"{place}[{i}]") for i, x in enumerate(value)])
        if coordinate and np.abs(v).max() > MAX_COORDINATE_MM:
            raise self.fail(place, f"farther than {MAX_COORDINATE_MM:g} mm from the origin")
        return v

    def direction(self, value: Any, place: str) -> np.ndarray:
        """A direction of any length > 0, scaled to a largest component of 1 (its norm
        neither overflows, as of [1e308, 1e308, 0], nor underflows)."""
        v = self.vector(value, place)
        if not np.any(v):
            raise self.fail(place, "expected a direction, got the zero vector")
        return v / np.abs(v).max()

    def points(self, value: Any, place: str) -> np.ndarray:
        if not isinstance(value, list) or len(value) < 2:
            got = f"{len(value)} items" if isinstance(value, list) else _short(value)
            raise self.fail(place, f"expected an array of at least 2 points [x, y, z], got {got}")
        return np.array(
            [self.vector(p, f"{place}[{i}]", coordinate=True) for i, p in enumerate(value)]
        )

    def build(self, place: str, make: Any) -> Any:
        """``make()``, with a model's own refusal named at ``place``."""
        try:
            return make()
        except PlanningError as exc:
            raise self.fail(place, str(exc)) from None


def _pipe(r: _Reader, t: Any, place: str) -> Pipe:
    t = r.table(t, place, _PIPE, ("axis_mm", "inner_diameter_mm"))
    pts = r.points(t["axis_mm"], f"{place}.axis_mm")
    D = r.size(t["inner_diameter_mm"], f"{place}.inner_diameter_mm")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # repeated points: the same polyline
            axis = KnownPath.from_points(pts, source=f"{r.where}: {place}.axis_mm")
    except PathFileError as exc:
        raise r.error(str(exc)) from None
    return r.build(place, lambda: Pipe(axis, D))


def _opening(r: _Reader, t: Any, place: str) -> RoundOpening | RectOpening:
    if not isinstance(t, Mapping):
        raise r.fail(place, f"expected a table, got {_short(t)}")
    if "shape" not in t:
        raise r.fail(place, "missing key 'shape'")
    shapes = [s.value for s in OpeningShape]
    if t["shape"] not in shapes:
        raise r.fail(
            f"{place}.shape",
            f"expected one of {', '.join(map(repr, shapes))}, got {_short(t['shape'])}",
        )
    if t["shape"] == OpeningShape.ROUND:
        t = r.table(t, place, _ROUND, ("centre_mm", "diameter_mm"))
        c = r.vector(t["centre_mm"], f"{place}.centre_mm", coordinate=True)
        D = r.size(t["diameter_mm"], f"{place}.diameter_mm")
        return r.build(place, lambda: RoundOpening(c, D))
    t = r.table(t, place, _RECT, ("centre_mm", "width_mm", "height_mm", "u"))
    c = r.vector(t["centre_mm"], f"{place}.centre_mm", coordinate=True)
    w = r.size(t["width_mm"], f"{place}.width_mm")
    h = r.size(t["height_mm"], f"{place}.height_mm")
    u = r.direction(t["u"], f"{place}.u")
    return r.build(place, lambda: RectOpening(c, w, h, u))


def _wall(r: _Reader, t: Any, place: str) -> Wall:
    t = r.table(t, place, _WALL, ("point_mm", "normal"))
    p = r.vector(t["point_mm"], f"{place}.point_mm", coordinate=True)
    n = r.direction(t["normal"], f"{place}.normal")
    T = r.size(t.get("thickness_mm", 0.0), f"{place}.thickness_mm", strict=False)
    ops = tuple(
        _opening(r, o, f"{place}.opening[{i}]")
        for i, o in enumerate(r.tables(t.get("opening", []), f"{place}.opening", MAX_OPENINGS))
    )
    unit_n = n / np.linalg.norm(n)
    for i, o in enumerate(ops):
        if isinstance(o, RectOpening) and abs(float(o.u @ unit_n)) > 1.0 - 1e-9:
            raise r.fail(f"{place}.opening[{i}].u", "is normal to its wall (u must lie in it)")
    bounds = []
    for i, b in enumerate(r.tables(t.get("bound", []), f"{place}.bound", MAX_OPENINGS)):
        bp = f"{place}.bound[{i}]"
        b = r.table(b, bp, _BOUND, ("point_mm", "normal"))
        bounds.append(
            (
                r.vector(b["point_mm"], f"{bp}.point_mm", coordinate=True),
                r.direction(b["normal"], f"{bp}.normal"),
            )
        )
    return r.build(place, lambda: Wall(p, n, T, ops, tuple(bounds)))


def rotation_zyx(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``, world from body.

    >>> rotation_zyx(90.0, 0.0, 0.0).round(12).tolist()[0]
    [0.0, -1.0, 0.0]
    """
    y, p, r = (math.radians(v) for v in (yaw_deg, pitch_deg, roll_deg))
    cz, sz, cy, sy, cx, sx = (
        math.cos(y),
        math.sin(y),
        math.cos(p),
        math.sin(p),
        math.cos(r),
        math.sin(r),
    )
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return Rz @ Ry @ Rx


def _box(r: _Reader, t: Any, place: str) -> Box:
    t = r.table(t, place, _BOX, ("centre_mm", "size_mm"))
    c = r.vector(t["centre_mm"], f"{place}.centre_mm", coordinate=True)
    size = r.vector(t["size_mm"], f"{place}.size_mm")
    for i, s in enumerate(size):
        r.size(float(s), f"{place}.size_mm[{i}]")
    angles = [k for k in ("yaw_deg", "pitch_deg", "roll_deg") if k in t]
    if "rotation" in t:
        if angles:
            raise r.fail(place, f"give either 'rotation' or {angles[0]!r}, not both")
        rows = t["rotation"]
        if not isinstance(rows, list) or len(rows) != 3:
            raise r.fail(f"{place}.rotation", "expected 3 rows of 3 numbers")
        R = np.array([r.vector(row, f"{place}.rotation[{i}]") for i, row in enumerate(rows)])
    else:
        ypr = [
            r.number(t.get(k, 0.0), f"{place}.{k}", high=MAX_ANGLE_DEG)
            for k in ("yaw_deg", "pitch_deg", "roll_deg")
        ]
        R = rotation_zyx(*ypr)
    return r.build(place, lambda: Box(c, size, R))


def scene_from_dict(
    doc: Any, where: str = "scene", error: type[Exception] = SceneFileError
) -> Environment:
    """Check scene data (a parsed scene file, or a plan file's ``environment``) and build
    its :class:`Environment`; ``error`` (default :class:`SceneFileError`) names ``where``.

    >>> env = scene_from_dict({"pipe": [{"axis_mm": [[0, 0, 0], [100, 0, 0]],
    ...                                  "inner_diameter_mm": 70}]})
    >>> float(env.free_distance(np.array([50.0, 10.0, 0.0])))
    25.0
    >>> scene_from_dict({"pipe": [{"axis_mm": [[0, 0, 0], [1, 0, 0]],
    ...                            "inner_diameter_mm": float("nan")}]}, "s.toml")
    Traceback (most recent call last):
    ...
    hrm_ctrl.formats.scene.SceneFileError: s.toml: pipe[0].inner_diameter_mm: expected a \
finite number, got nan
    """
    r = _Reader(where, error)
    doc = r.table(doc, "", _TOP, ())
    if "description" in doc and not isinstance(doc["description"], str):
        raise r.fail("description", f"expected a string, got {_short(doc['description'])}")
    counts = {k: len(v) for k, v in doc.items() if k != "description" and isinstance(v, list)}
    if sum(counts.values()) > MAX_OBSTACLES:
        raise r.fail("", f"{sum(counts.values())} obstacles, more than the {MAX_OBSTACLES} allowed")
    obstacles: list[Any] = []
    axis_mm, axis_points, limits = 0.0, 0, 0
    for key, make in (("pipe", _pipe), ("wall", _wall), ("box", _box)):
        for i, t in enumerate(r.tables(doc.get(key, []), key, MAX_OBSTACLES)):
            obstacles.append(make(r, t, f"{key}[{i}]"))
            if isinstance(obstacles[-1], Pipe):  # each resampled every 0.5 mm when queried
                axis_mm += obstacles[-1].axis.length
                axis_points += len(obstacles[-1].axis.points)
                if axis_points > MAX_PATH_POINTS:
                    raise r.fail(
                        f"{key}[{i}].axis_mm",
                        f"the pipes' axes have {axis_points} points in all, more than the "
                        f"{MAX_PATH_POINTS} a scene's may have",
                    )
                if axis_mm > MAX_PIPE_AXIS_MM:
                    raise r.fail(
                        f"{key}[{i}].axis_mm",
                        f"the pipes' axes are {axis_mm:.6g} mm long in all, longer than the "
                        f"{MAX_PIPE_AXIS_MM:g} mm a scene's may be",
                    )
            if isinstance(obstacles[-1], Wall):
                limits += len(obstacles[-1].openings) + len(obstacles[-1].bounds)
                if limits > MAX_WALL_LIMITS:
                    raise r.fail(
                        f"{key}[{i}]",
                        f"{limits} wall openings and bounds in all, more than the "
                        f"{MAX_WALL_LIMITS} a scene may have",
                    )
    return Environment(tuple(obstacles))


def read_scene(path: str | Path) -> Environment:
    """Read and check a scene file (the format above); one :class:`SceneFileError` line on
    any problem, naming the file, the table and the key."""
    doc, name = read_toml(path, SceneFileError, "scene file")
    return scene_from_dict(doc, name)


__all__ = ["SceneFileError", "read_scene", "rotation_zyx", "scene_from_dict"]
