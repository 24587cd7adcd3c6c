"""Known paths (Eqs. 10-12) and path files."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hrm_ctrl.errors import PathFileError
from hrm_ctrl.planning.known_path import DuplicatePointsWarning, KnownPath, load_path_csv


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "path.csv"
    p.write_text(text)
    return p


def test_reads_a_path_file(tmp_path: Path) -> None:
    p = load_path_csv(write(tmp_path, "x,y,z\n0,0,0\n3,0,0\n3,4,0\n"))
    assert p.length == pytest.approx(7.0)
    np.testing.assert_allclose(p.point_at(5.0), [3.0, 2.0, 0.0])


@given(st.floats(0.0, 7.0))
def test_eq12_interpolates_between_the_bracketing_points(d: float) -> None:
    p = KnownPath.from_points(np.array([[0, 0, 0], [3, 0, 0], [3, 4, 0]], float))
    q = p.point_at(d)
    # the point lies on the path at arc length d (Eq. 12 with the erratum)
    expected = [d, 0, 0] if d <= 3 else [3, d - 3, 0]
    np.testing.assert_allclose(q, expected, atol=1e-12)
    assert p.distance_to(q) == pytest.approx(0.0, abs=1e-9)


def test_consecutive_duplicates_are_dropped_with_a_warning(tmp_path: Path) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        p = load_path_csv(write(tmp_path, "x,y,z\n0,0,0\n0,0,0\n1,0,0\n1,0,0\n2,0,0\n"))
    assert len(p.points) == 3
    assert any(issubclass(w.category, DuplicatePointsWarning) for w in caught)
    assert "dropped 2" in str(caught[0].message)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty"),
        ("x,y,z\n", "header but no points"),
        ("a,b,c\n0,0,0\n1,0,0\n", "header must be 'x,y,z'"),
        ("x,y,z\n0,0,0\n1,zero,0\n", ":3: y is not a number: 'zero'"),
        ("x,y,z\n0,0,0\n1,nan,0\n", ":3: y is not finite"),
        ("x,y,z\n0,0,0\ninf,0,0\n", ":3: x is not finite"),
        ("x,y,z\n0,0,0\n1,0\n", ":3: expected 3 columns"),
        ("x,y,z\n0,0,0,0\n1,0,0\n", ":2: expected 3 columns"),
        ("x,y,z\n1,1,1\n1,1,1\n", "at least 2 distinct points"),
        ("x,y,z\n1,1,1\n", "at least 2 distinct points"),
    ],
)
def test_bad_path_files_name_the_problem(tmp_path: Path, text: str, message: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(PathFileError, match=message.replace("(", r"\(")) as exc:
            load_path_csv(write(tmp_path, text))
    assert "\n" not in str(exc.value)
    assert "path.csv" in str(exc.value)


def test_missing_path_file(tmp_path: Path) -> None:
    with pytest.raises(PathFileError, match="not found"):
        load_path_csv(tmp_path / "nope.csv")
