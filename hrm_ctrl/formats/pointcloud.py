"""Point clouds (scans of a pipe's inner wall): one reader for PLY, CSV and NPY.

The format comes from the file's suffix (``.ply``, ``.csv``, ``.npy``, any case):

- **PLY** (ASCII or binary, read with ``plyfile``): the ``vertex`` element's ``x``, ``y``,
  ``z`` properties (any numeric type); other elements and properties are ignored.
- **CSV**: either a header naming the columns, which must include ``x``, ``y`` and ``z``
  (any order, any case; other columns such as normals or intensity are ignored), or no
  header and exactly three numeric columns ``x,y,z``.  A first line that is not all
  numbers is the header.  Blank lines are skipped.  At most :data:`MAX_CSV_COLUMNS`
  columns and :data:`MAX_CSV_LINES` lines (counted before the text is split).
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
MAX_CSV_COLUMNS = 1_000  # x, y, z and whatever a scanner adds (normals, colour, ...)
MAX_CSV_LINES = MAX_POINT_CLOUD_POINTS + 1  # lines of a CSV (a header, blank lines too)
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
    with np.errstate(invalid="ignore", over="ignore"):  # what the cast makes inf/nan is refused
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
    """A number as the CSV reader (``np.loadtxt``) reads it: ASCII, no ``_`` (which
    ``float`` alone would take)."""
    if not cell.isascii() or "_" in cell:
        return False
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _columns(p: Path, n: int, line: str) -> int:
    """The columns of CSV line n, refused (before the line is split) beyond the bound."""
    k = line.count(",") + 1
    if k > MAX_CSV_COLUMNS:
        raise PointCloudError(
            f"{p}:{n}: {k} columns, more than the {MAX_CSV_COLUMNS} a point cloud may have"
        )
    return k


def _read_csv(p: Path) -> np.ndarray:
    text = read_text_file(p, PointCloudError, "point cloud", max_bytes=MAX_POINT_CLOUD_BYTES)
    n_lines = text.count("\n") + (not text.endswith("\n"))
    if n_lines > MAX_CSV_LINES:  # before the split (8 bytes a line, blank ones too)
        raise PointCloudError(
            f"{p}: {n_lines} lines, more than the {MAX_CSV_LINES} a CSV point cloud may have"
        )
    lines = text.split("\n")
    numbered = [n for n, line in enumerate(lines, start=1) if line.strip()]
    if not numbered:
        raise PointCloudError(f"{p}: point cloud is empty")
    n0 = numbered[0]
    _columns(p, n0, lines[n0 - 1])
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
        twice = [c for c in "xyz" if names.count(c) > 1]
        if twice:
            raise PointCloudError(f"{p}:{n0}: the header names column {twice[0]} more than once")
        cols, width, rows = [names.index(c) for c in "xyz"], len(names), numbered[1:]
    if not rows:
        raise PointCloudError(f"{p}: point cloud has a header but no points")
    if len(rows) > MAX_POINT_CLOUD_POINTS:
        raise PointCloudError(
            f"{p}: point cloud has {len(rows)} points, more than the "
            f"{MAX_POINT_CLOUD_POINTS} it may have"
        )
    body = [lines[n - 1] for n in rows]
    ragged = any(line.count(",") != width - 1 for line in body)  # before any line is parsed
    pts = None
    if not ragged:
        try:
            pts = np.loadtxt(body, delimiter=",", usecols=cols, ndmin=2, dtype=np.float64)
        except ValueError:
            pts = None
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
        k = lines[n - 1].count(",") + 1
        if k != width:
            raise PointCloudError(f"{p}:{n}: expected {width} columns, got {k}")
        cells = lines[n - 1].split(",")
        for name, c in zip("xyz", cols, strict=True):
            if not _is_number(cells[c]):
                raise PointCloudError(f"{p}:{n}: {name} is not a number: {_cell(cells[c])}")
    raise PointCloudError(f"{p}: not a CSV point cloud")  # pragma: no cover


def _read_npy(p: Path) -> np.ndarray:
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(f)
            data_bytes = os.fstat(f.fileno()).st_size - f.tell()
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
    if shape[0] * 3 * dtype.itemsize > data_bytes:  # a lying header: nothing allocated for it
        raise PointCloudError(
            f"{p}: NPY header states {shape[0]} points ({shape[0] * 3 * dtype.itemsize} "
            f"bytes), but the file has {data_bytes} bytes of data (is it cut short?)"
        )
    try:
        pts = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise PointCloudError(f"{p}: cannot read NPY array ({str(exc).splitlines()[0]})") from None
    return _check_points(pts, p, "row")


_PLY_TYPE_BYTES = {
    **dict.fromkeys(("char", "int8", "uchar", "uint8"), 1),
    **dict.fromkeys(("short", "int16", "ushort", "uint16"), 2),
    **dict.fromkeys(("int", "int32", "uint", "uint32", "float", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}


def _ply_counts(p: Path) -> None:
    """Refuse, from the header alone, a PLY whose elements hold more than the bound, or
    more than the file's bytes after its header can hold (a header that lies about its
    counts: nothing is allocated for it).  The header ends at the line ``end_header``
    (not at those words in a comment)."""
    with open(p, "rb") as f:
        head = f.read(MAX_PLY_HEADER_BYTES)
        size = os.fstat(f.fileno()).st_size
    if not head.startswith(b"ply"):
        raise PointCloudError(f"{p}: not a PLY file (it does not start with 'ply')")
    lines = head.split(b"\n")
    end = next((i for i, x in enumerate(lines[:-1]) if x.strip() == b"end_header"), None)
    if end is None:
        raise PointCloudError(
            f"{p}: PLY header has no end_header within {MAX_PLY_HEADER_BYTES} bytes"
        )
    body = size - sum(len(x) + 1 for x in lines[: end + 1])
    ascii_ = True
    need = 0  # the fewest bytes the elements the header states can take
    count, row = 0, 0
    element = ""
    for line in [x.decode("ascii", errors="replace") for x in lines[:end]] + ["element"]:
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            ascii_ = words[1] == "ascii"
        if words[:1] == ["property"] and len(words) > 2:  # ascii: a value and a separator
            kind = words[2] if words[1] == "list" else words[1]
            row += 2 if ascii_ else _PLY_TYPE_BYTES.get(kind, 1)
            if element == "vertex" and words[1] == "list" and words[-1] in ("x", "y", "z"):
                # refused from the header: the body of a list is not parsed to find out
                raise PointCloudError(
                    f"{p}: PLY vertex property {words[-1]} is a list, not a number"
                )
        if words[:1] == ["element"]:
            need += count * row
            count, row = 0, 0
            element = words[1] if len(words) > 1 else ""
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
            count = max(count, 0)
    if need - (1 if ascii_ else 0) > body:  # ascii: the last newline may be missing
        raise PointCloudError(
            f"{p}: PLY header states elements of at least {need} bytes, but the file has "
            f"{body} bytes after its header (is it cut short?)"
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
        # a NaN of another byte order or a long double beyond float64 warns when cast: those
        # values are refused by _check_points, the one line
        with np.errstate(invalid="ignore", over="ignore"):
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
