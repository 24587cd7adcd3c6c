"""Point cloud files: PLY (ASCII, binary), CSV and NPY round trips, and every bad file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import plyfile
import pytest

from hrm_ctrl.errors import HrmError, PlanningError
from hrm_ctrl.formats import pointcloud
from hrm_ctrl.formats.pointcloud import PointCloudError, read_point_cloud

PTS = np.random.default_rng(3).uniform(-500.0, 1500.0, (257, 3))


def write_ply(path: Path, pts: np.ndarray, *, text: bool, dtype: str = "f8", extra: bool = False):
    fields = [("x", dtype), ("y", dtype), ("z", dtype)]
    if extra:
        fields.append(("intensity", "u1"))
    v = np.zeros(len(pts), dtype=fields)
    v["x"], v["y"], v["z"] = pts.T
    elements = [plyfile.PlyElement.describe(v, "vertex")]
    if extra:
        faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
        elements.append(plyfile.PlyElement.describe(faces, "face"))
    plyfile.PlyData(elements, text=text).write(str(path))
    return path


def one_line_error(path: Path, match: str) -> str:
    with pytest.raises(PointCloudError, match=match) as err:
        read_point_cloud(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    return msg


@pytest.mark.parametrize("text", [True, False])
def test_ply_round_trip(tmp_path: Path, text: bool) -> None:
    p = write_ply(tmp_path / "c.ply", PTS, text=text, extra=True)
    got = read_point_cloud(p)
    assert got.dtype == np.float64 and got.shape == PTS.shape
    np.testing.assert_allclose(got, PTS, rtol=0, atol=1e-9 if not text else 1e-3)


def test_ply_of_float32_and_int_vertices(tmp_path: Path) -> None:
    p = write_ply(tmp_path / "f.PLY", PTS, text=False, dtype="f4")
    np.testing.assert_allclose(read_point_cloud(p), PTS.astype(np.float32), rtol=0, atol=0)
    q = write_ply(tmp_path / "i.ply", np.round(PTS), text=False, dtype="i4")
    np.testing.assert_array_equal(read_point_cloud(q), np.round(PTS))


def test_csv_with_a_header_in_any_order_and_extra_columns(tmp_path: Path) -> None:
    rows = "\n".join(f"7,{z!r},{x!r},{y!r}" for x, y, z in PTS.tolist())
    p = tmp_path / "c.csv"
    p.write_text(f"intensity, Z ,X,y\n{rows}\n\n")
    np.testing.assert_array_equal(read_point_cloud(p), PTS)


def test_csv_without_a_header(tmp_path: Path) -> None:
    p = tmp_path / "c.csv"
    np.savetxt(p, PTS, delimiter=",", fmt="%.17g")
    np.testing.assert_array_equal(read_point_cloud(p), PTS)


def test_npy_round_trip(tmp_path: Path) -> None:
    p = tmp_path / "c.npy"
    np.save(p, PTS)
    np.testing.assert_array_equal(read_point_cloud(p), PTS)
    np.save(p, PTS.astype(np.float32))
    assert read_point_cloud(p).dtype == np.float64


def test_the_error_is_a_planning_error() -> None:
    assert issubclass(PointCloudError, PlanningError) and issubclass(PointCloudError, HrmError)


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        ("a.csv", "x,y,z\n1,2,3\n1,2\n", r"a\.csv:3: expected 3 columns, got 2"),
        ("b.csv", "x,y,z\n1,2,3\n1,abc,3\n", r"b\.csv:3: y is not a number: 'abc'"),
        ("c.csv", "1,2,3\n\n4,5,inf\n", r"c\.csv:3: z is not finite: 'inf'"),
        (
            "d.csv",
            "x,y,w\n1,2,3\n",
            r"d\.csv:1: the header must name columns x, y and z, missing z",
        ),
        ("e.csv", "1,2,3,4\n", r"e\.csv:1: expected 3 columns x,y,z"),
        ("f.csv", "x,y,z\n", r"f\.csv: point cloud has a header but no points"),
        ("g.csv", "\n\n", r"g\.csv: point cloud is empty"),
        ("h.csv", "1,2,3\n1,2,3e9\n", r"h\.csv:2: z = 3e\+09 mm is farther than 1e\+06 mm"),
        ("i.txt", "1,2,3\n", r"i\.txt: unknown point cloud format '\.txt'"),
        ("j.csv", "x,y,z\n1,2,3\n\xff\n", r"j\.csv: cannot read point cloud"),
    ],
)
def test_bad_csv_files_are_one_line_errors(tmp_path: Path, name: str, text: str, match: str):
    p = tmp_path / name
    p.write_bytes(text.encode("latin-1"))
    one_line_error(p, match)


def test_a_missing_file_and_a_directory(tmp_path: Path) -> None:
    one_line_error(tmp_path / "none.ply", "point cloud not found")
    d = tmp_path / "dir.npy"
    d.mkdir()
    one_line_error(d, "not a regular file")


def test_bad_npy_files(tmp_path: Path) -> None:
    p = tmp_path / "c.npy"
    np.save(p, PTS[:, :2])
    one_line_error(p, r"shape \(n, 3\), got \(257, 2\)")
    np.save(p, PTS.astype(complex))
    one_line_error(p, "real numbers")
    np.save(p, np.zeros((0, 3)))
    one_line_error(p, "no points")
    bad = PTS.copy()
    bad[41, 1] = np.nan
    np.save(p, bad)
    one_line_error(p, r"row 42: y is not finite")
    np.save(p, PTS)
    p.write_bytes(p.read_bytes()[:-100])  # truncated
    one_line_error(p, "cut short")
    p.write_bytes(b"not numpy at all")
    one_line_error(p, "not an NPY file")
    np.save(p, np.array([{"a": 1}], dtype=object))
    one_line_error(p, "real numbers")


def test_bad_ply_files(tmp_path: Path) -> None:
    p = tmp_path / "c.ply"
    bad = PTS.copy()
    bad[9, 2] = np.inf
    write_ply(p, bad, text=False)
    one_line_error(p, r"vertex 10: z is not finite")
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n")
    one_line_error(p, "has no y, z")
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n1 2 3\n"
    )
    one_line_error(p, "states elements of at least 18 bytes, but the file has 6 bytes")
    p.write_text("hello")
    one_line_error(p, "not a PLY file")
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n")
    one_line_error(p, "no end_header")
    p.write_text("ply\nformat ascii 1.0\nelement face 1\nproperty float a\nend_header\n1\n")
    one_line_error(p, "no vertex element")
    write_ply(p, PTS, text=False)
    raw = p.read_bytes()
    p.write_bytes(raw[: len(raw) // 2])  # truncated binary
    one_line_error(p, "cut short")


def test_a_count_beyond_the_bound_is_refused_before_reading(tmp_path: Path) -> None:
    p = tmp_path / "huge.ply"
    p.write_text(
        "ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    one_line_error(p, r"vertex has 99999999999 items, more than the 20000000")
    q = tmp_path / "huge.npy"
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**9, 3)}
    with open(q, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
    one_line_error(q, "1000000000 points, more than the 20000000")


def test_a_file_beyond_the_size_bound_is_refused_unread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    p = tmp_path / "c.csv"
    np.savetxt(p, PTS, delimiter=",")
    monkeypatch.setattr(pointcloud, "MAX_POINT_CLOUD_BYTES", 100)
    one_line_error(p, "larger than the 100 bytes")


# ---- red team (issue 10) ------------------------------------------------------------------

PLY_XYZ = "property float x\nproperty float y\nproperty float z\n"


def test_end_header_in_a_comment_does_not_end_the_header(tmp_path: Path) -> None:
    """Found: the count check stopped at the first 'end_header' bytes, a comment's, so the
    vertex count after it (1e11) went unchecked to plyfile (an allocation of 1.09 TiB)."""
    p = tmp_path / "c.ply"
    p.write_text(
        "ply\nformat ascii 1.0\ncomment end_header\nelement vertex 99999999999\n"
        f"{PLY_XYZ}end_header\n1 2 3\n"
    )
    one_line_error(p, r"vertex has 99999999999 items, more than the 20000000")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("stated", [2, 1000, 19_000_000])
def test_a_header_stating_more_points_than_the_file_holds_is_refused_unread(
    tmp_path: Path, fmt: str, stated: int
) -> None:
    """A lying header (within the bound) is refused from the file's size, before plyfile
    allocates its rows (19 M rows: 228 MB for a 12-byte body)."""
    p = tmp_path / "c.ply"
    p.write_bytes(
        f"ply\nformat {fmt} 1.0\nelement vertex {stated}\n{PLY_XYZ}end_header\n".encode()
        + (b"1 2 3\n" if fmt == "ascii" else b"\0" * 12)
    )
    one_line_error(p, r"states elements of at least \d+ bytes, but the file has \d+ bytes")


@pytest.mark.parametrize("text", [True, False])
def test_the_size_check_passes_every_well_formed_ply(tmp_path: Path, text: bool) -> None:
    p = write_ply(tmp_path / "c.ply", PTS[:5], text=text, extra=True)  # a face list too
    assert read_point_cloud(p).shape == (5, 3)
    p.write_text(  # the last line without its newline
        f"ply\nformat ascii 1.0\nelement vertex 2\n{PLY_XYZ}end_header\n1 2 3\n4 5 6"
    )
    assert read_point_cloud(p).tolist() == [[1, 2, 3], [4, 5, 6]]


def test_a_csv_of_too_many_columns_is_refused_before_it_is_split(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Found: a line of 10^7 columns (20 MB) was split into 10^7 strings (a 1 GiB one:
    5 x 10^8, tens of GB) before its width was looked at."""
    p = tmp_path / "c.csv"
    p.write_text("0," * 10**6 + "0\n")
    one_line_error(p, r"c.csv:1: 1000001 columns, more than the 1000")
    p.write_text("x,y,z\n1,2,3\n" + "4," * 10**6 + "4\n")  # a ragged data line
    one_line_error(p, r"c.csv:3: expected 3 columns, got 1000001")


def test_a_csv_of_too_many_lines_is_refused_before_it_is_split(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Found: 1 GiB of newlines became a list of 10^9 lines (8 GB) before any check."""
    monkeypatch.setattr(pointcloud, "MAX_CSV_LINES", 1000)
    p = tmp_path / "c.csv"
    p.write_text("1,2,3\n" + "\n" * 1000)
    one_line_error(p, r"1001 lines, more than the 1000")
    p.write_text("x,y,z\n" + "1,2,3\n" * 999)  # the bound itself, its last newline too
    assert read_point_cloud(p).shape == (999, 3)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("x,y,x,z\n1,2,3,4\n", r":1: the header names column x more than once"),
        ("0,0,0\n1_000,2,3\n", r":2: x is not a number: '1_000'"),  # was: no line named
        ("0,0,0\n1,\u0661,3\n", r":2: y is not a number"),  # an Arabic-Indic digit
    ],
)
def test_csv_cells_loadtxt_refuses_are_named(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "c.csv"
    p.write_text(text)
    one_line_error(p, match)


def test_an_npy_header_stating_more_points_than_the_file_holds_is_refused_unread(
    tmp_path: Path,
) -> None:
    """A 128-byte file whose header states 10^6 points had np.load allocate 24 MB (up to
    480 MB within the bound) before it found the data missing."""
    q = tmp_path / "lie.npy"
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**6, 3)}
    with open(q, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.write(b"\0" * 48)
    one_line_error(q, r"states 1000000 points \(24000000 bytes\), but the file has 48 bytes")


def test_a_ply_whose_x_is_a_list_is_refused_from_its_header(tmp_path: Path) -> None:
    """Found by a red-team helper: the whole body was parsed first (about 5 s a million
    vertices) to find x was a list."""
    p = tmp_path / "l.ply"
    p.write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty list uchar float x\n"
        b"property float y\nproperty float z\nend_header\n1 1 2 3\n1 4 5 6\n"
    )
    with pytest.raises(PointCloudError, match=r"l\.ply: PLY vertex property x is a list"):
        read_point_cloud(p)
