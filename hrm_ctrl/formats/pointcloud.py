"""Point clouds (scans of a pipe's inner wall): one reader for PLY, CSV and NPY.

The format comes from the file's suffix (``.ply``, ``.csv``, ``.npy``, any case):

- **PLY** (ASCII or binary, read with ``plyfile``): the ``vertex`` element's ``x``, ``y``,
  ``z`` properties (any numeric type); other elements and properties are ignored.
- **CSV**: either a header naming the columns, which must include ``x``, ``y`` and ``z``
  (any order, any case; other columns such as normals or intensity are ignored), or no
  header and exactly three numeric columns ``x,y,z``.  A first line that is not all
  numbers is the header.  Blank lines are skipped.
- **NPY** (``np.load`` with ``allow_pickle=False``): one array of shape (n, 3) of real
  numbers (float or integer).

Units are mm.  Every problem is one :class:`PointCloudError` line naming the file and the
row (CSV line, PLY vertex, NPY row): NaN or infinite values, coordinates farther than
1e6 mm from the origin, missing columns, wrong shapes.  A file larger than
:data:`MAX_POINT_CLOUD_BYTES` is refused unread and one of more than
:data:`MAX_POINT_CLOUD_POINTS` points before its points are read (a PLY header or an NPY
header states the count).

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = (d / "c.csv").write_text("x,y,z,intensity\\n0,0,1,7\\n1,2,3,7\\n")
>>> read_point_cloud(d / "c.csv").tolist()
[[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]]
>>> _ = (d / "bad.csv").write_text("0,0,1\\n1,nan,3\\n")
>>> read_point_cloud(d / "bad.csv")
Traceback (most recent call last):
...
hrm_ctrl.formats.pointcloud.PointCloudError: ...bad.csv:2: y is not finite: 'nan'
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.files import read_text_file

MAX_POINT_CLOUD_POINTS = 20_000_000  # 20 M points: 480 MB as float64 (n, 3)
MAX_POINT_CLOUD_BYTES = 2**30  # 1 GiB: an ASCII cloud of 20 M points is about 600 MB
MAX_PLY_HEADER_BYTES = 2**16  # a PLY header is a few hundred bytes
MAX_COORDINATE_MM = 1e6  # as for path files: 1 km from the world origin
SUFFIXES = (".ply", ".csv", ".npy")


class PointCloudError(PlanningError):
    """A point cloud file (PLY, CSV or NPY) is missing, malformed or out of bounds."""


def read_point_cloud(path: str | Path) -> np.ndarray:
    """The points of a cloud file, shape (n, 3), float64, mm (module docstring)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in SUFFIXES:
        raise PointCloudError(
            f"{p}: unknown point cloud format {p.suffix or '(no suffix)'!r} "
            f"(expected {', '.join(SUFFIXES)})"
        )
    try:
        size = os.stat(p).st_size
    except FileNotFoundError:
        raise PointCloudError(f"{p}: point cloud not found") from None
    except OSError as exc:
        raise PointCloudError(f"{p}: cannot read point cloud ({exc})") from None
    if not p.is_file():
        raise PointCloudError(f"{p}: point cloud is not a regular file")
    if size > MAX_POINT_CLOUD_BYTES:
        raise PointCloudError(
            f"{p}: point cloud is larger than the {MAX_POINT_CLOUD_BYTES} bytes it may have"
        )
    if suffix == ".csv":
        pts = _read_csv(p)
    elif suffix == ".npy":
        pts = _read_npy(p)
    else:
        pts = _read_ply(p)
    return pts


def _check_points(pts: np.ndarray, p: Path, row: str, first_row: int = 1) -> np.ndarray:
    """(n, 3) float64, every value finite and within bounds; errors name ``row`` k."""
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    if len(pts) == 0:
        raise PointCloudError(f"{p}: point cloud has no points")
    if len(pts) > MAX_POINT_CLOUD_POINTS:
        raise PointCloudError(
            f"{p}: point cloud has {len(pts)} points, more than the {MAX_POINT_CLOUD_POINTS} "
            "it may have"
        )
    bad = ~np.isfinite(pts)
    if bad.any():
        k, c = (int(v) for v in np.argwhere(bad)[0])
        raise PointCloudError(f"{p}: {row} {k + first_row}: {'xyz'[c]} is not finite ({pts[k, c]})")
    far = np.abs(pts) > MAX_COORDINATE_MM
    if far.any():
        k, c = (int(v) for v in np.argwhere(far)[0])
        raise PointCloudError(
            f"{p}: {row} {k + first_row}: {'xyz'[c]} = {pts[k, c]:.6g} mm is farther than "
            f"{MAX_COORDINATE_MM:g} mm from the origin"
        )
    return pts


def _cell(cell: str) -> str:
    text = repr(cell.strip())
    return text if len(text) <= 40 else f"{text[:30]}...' ({len(cell.strip())} characters)"


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _read_csv(p: Path) -> np.ndarray:
    text = read_text_file(p, PointCloudError, "point cloud", max_bytes=MAX_POINT_CLOUD_BYTES)
    lines = text.split("\n")
    numbered = [n for n, line in enumerate(lines, start=1) if line.strip()]
    if not numbered:
        raise PointCloudError(f"{p}: point cloud is empty")
    n0 = numbered[0]
    first = [c.strip() for c in lines[n0 - 1].split(",")]
    if all(_is_number(c) for c in first):
        cols, width, rows = [0, 1, 2], 3, numbered
        if len(first) != 3:
            raise PointCloudError(
                f"{p}:{n0}: expected 3 columns x,y,z (or a header naming them), got {len(first)}"
            )
    else:
        names = [c.lower() for c in first]
        missing = [c for c in "xyz" if c not in names]
        if missing:
            raise PointCloudError(
                f"{p}:{n0}: the header must name columns x, y and z, missing "
                f"{', '.join(missing)} (got {','.join(first)[:60]!r})"
            )
        cols, width, rows = [names.index(c) for c in "xyz"], len(names), numbered[1:]
    if not rows:
        raise PointCloudError(f"{p}: point cloud has a header but no points")
    if len(rows) > MAX_POINT_CLOUD_POINTS:
        raise PointCloudError(
            f"{p}: point cloud has {len(rows)} points, more than the "
            f"{MAX_POINT_CLOUD_POINTS} it may have"
        )
    body = [lines[n - 1] for n in rows]
    try:
        pts = np.loadtxt(body, delimiter=",", usecols=cols, ndmin=2, dtype=np.float64)
        ragged = any(line.count(",") != width - 1 for line in body)
    except ValueError:
        pts, ragged = None, True
    if ragged or pts is None:
        _first_bad_row(p, lines, rows, cols, width)  # raises
    pts = np.asarray(pts)
    bad = ~np.isfinite(pts) | (np.abs(pts) > MAX_COORDINATE_MM)
    if bad.any():
        k, c = (int(v) for v in np.argwhere(bad)[0])
        n = rows[k]
        cell = lines[n - 1].split(",")[cols[c]]
        v = float(cell)
        if not math.isfinite(v):
            raise PointCloudError(f"{p}:{n}: {'xyz'[c]} is not finite: {_cell(cell)}")
        raise PointCloudError(
            f"{p}:{n}: {'xyz'[c]} = {v:.6g} mm is farther than {MAX_COORDINATE_MM:g} mm "
            "from the origin"
        )
    return _check_points(pts, p, "row")


def _first_bad_row(p: Path, lines: list[str], rows: list[int], cols: list[int], width: int) -> None:
    """Raise the error of the first line the fast reader refused."""
    for n in rows:
        cells = lines[n - 1].split(",")
        if len(cells) != width:
            raise PointCloudError(f"{p}:{n}: expected {width} columns, got {len(cells)}")
        for name, c in zip("xyz", cols, strict=True):
            try:
                float(cells[c])
            except ValueError:
                raise PointCloudError(
                    f"{p}:{n}: {name} is not a number: {_cell(cells[c])}"
                ) from None
    raise PointCloudError(f"{p}: not a CSV point cloud")  # pragma: no cover


def _read_npy(p: Path) -> np.ndarray:
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    except OSError as exc:
        raise PointCloudError(f"{p}: cannot read point cloud ({exc})") from None
    except ValueError as exc:
        raise PointCloudError(f"{p}: not an NPY file ({str(exc).splitlines()[0]})") from None
    if dtype.kind not in "fiu" or dtype.fields is not None:
        raise PointCloudError(f"{p}: expected an array of real numbers, got dtype {dtype}")
    if len(shape) != 2 or shape[1] != 3:
        raise PointCloudError(f"{p}: expected an array of shape (n, 3), got {tuple(shape)}")
    if shape[0] > MAX_POINT_CLOUD_POINTS:
        raise PointCloudError(
            f"{p}: point cloud has {shape[0]} points, more than the {MAX_POINT_CLOUD_POINTS} "
            "it may have"
        )
    try:
        pts = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise PointCloudError(f"{p}: cannot read NPY array ({str(exc).splitlines()[0]})") from None
    return _check_points(pts, p, "row")


def _ply_counts(p: Path) -> None:
    """Refuse, from the header alone, a PLY whose elements hold more than the bound."""
    with open(p, "rb") as f:
        head = f.read(MAX_PLY_HEADER_BYTES)
    if not head.startswith(b"ply"):
        raise PointCloudError(f"{p}: not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise PointCloudError(
            f"{p}: PLY header has no end_header within {MAX_PLY_HEADER_BYTES} bytes"
        )
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element":
            try:
                count = int(words[2])
            except ValueError:
                raise PointCloudError(
                    f"{p}: PLY header: element {words[1]} has count {words[2]!r}"
                ) from None
            if count > MAX_POINT_CLOUD_POINTS:
                raise PointCloudError(
                    f"{p}: PLY element {words[1]} has {count} items, more than the "
                    f"{MAX_POINT_CLOUD_POINTS} a point cloud may have"
                )


def _read_ply(p: Path) -> np.ndarray:
    import plyfile  # the only PLY reader: imported where it is needed

    try:
        _ply_counts(p)
    except OSError as exc:
        raise PointCloudError(f"{p}: cannot read point cloud ({exc})") from None
    try:
        ply = plyfile.PlyData.read(str(p))
        if "vertex" not in ply:
            raise PointCloudError(f"{p}: PLY file has no vertex element")
        v = ply["vertex"]
        names = [prop.name for prop in v.properties]
        missing = [c for c in "xyz" if c not in names]
        if missing:
            raise PointCloudError(
                f"{p}: PLY vertex element has no {', '.join(missing)} "
                f"(properties: {', '.join(names)[:60]})"
            )
        data = v.data
        kinds = {c: data.dtype[c].kind for c in "xyz"}
        wrong = [c for c, k in kinds.items() if k not in "fiu"]
        if wrong:
            raise PointCloudError(f"{p}: PLY vertex property {wrong[0]} is not a number")
        pts = np.column_stack([np.asarray(data[c], dtype=np.float64) for c in "xyz"])
    except PointCloudError:
        raise
    except (
        plyfile.PlyParseError,
        ValueError,
        EOFError,
        OSError,
        IndexError,
        KeyError,
        TypeError,
        UnicodeDecodeError,
        OverflowError,
        MemoryError,
    ) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PointCloudError(f"{p}: not a readable PLY file ({msg[:120]})") from None
    return _check_points(pts, p, "vertex")
