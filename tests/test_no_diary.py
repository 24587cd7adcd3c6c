"""Docs, docstrings and comments describe the code as it is: no commit ids and no dates (a
session's diary).  The one place for dates is the date column of ``BENCHMARKS.md``'s tables;
history stays in git."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("hrm_ctrl", "drivers", "sim_bus", "calibration", "benchmarks", "tests")
BENCHMARKS = REPO / "BENCHMARKS.md"

#: a commit id as written in prose: 7-40 lowercase hex digits with a letter and a digit
#: among them, standing alone -- not after ``0x`` or ``\x`` (CAN ids, EMCY codes, bytes),
#: not inside quotes (hex strings of frames in doctests)
COMMIT_ID = re.compile(
    r"(?<![0-9A-Za-z_'\"\\])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![0-9A-Za-z_'\"])"
)
DATE = re.compile(r"\b(?:19|20)\d\d-[01]\d-[0-3]\d\b")
DATE_CELL = re.compile(r"\|\s*(?:19|20)\d\d-[01]\d-[0-3]\d\s*\|")


def findings(line: str) -> list[str]:
    """The commit ids and dates in one line of prose."""
    return COMMIT_ID.findall(line) + DATE.findall(line)


@pytest.mark.parametrize(
    ("line", "found"),
    [
        ("the CI run of ``03390e1`` stopped a test", ["03390e1"]),
        ("the code of commit bd9359f, measured", ["bd9359f"]),
        ("measured on 2026-12-05 on the VM", ["2026-12-05"]),
        ("a drive's EMCY 0x8130 and COB-ID 0x181", []),
        ("bytes.fromhex('0f00feffffff') and \"3702fbffffff\"", []),
        ("(30000 + 30)^2 / 3e7 = 30.06", []),
        ("bitrate = 1000000, CRC 0x29b1, a\\x1b", []),
        ("every 10 ms, 2000 counts, deadbeef", []),  # no digit: a word, not an id
    ],
)
def test_the_detector_finds_commit_ids_and_dates_only(line: str, found: list[str]) -> None:
    assert findings(line) == found


def prose_of_python(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, text) of every docstring and other string statement, and every comment."""
    src = path.read_text()
    for node in ast.walk(ast.parse(src)):
        if (
            isinstance(node, ast.Expr)
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            for k, line in enumerate(node.value.value.splitlines()):
                yield node.lineno + k, line
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string


def prose_files() -> Iterator[tuple[Path, Iterator[tuple[int, str]]]]:
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            yield path, prose_of_python(path)
    for path in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]:
        yield path, enumerate(path.read_text().splitlines(), 1)
    toml = (REPO / "pyproject.toml").read_text().splitlines()
    yield (
        REPO / "pyproject.toml",
        ((i, x[x.index("#") :]) for i, x in enumerate(toml, 1) if "#" in x),
    )


def test_no_commit_id_or_date_in_docs_docstrings_or_comments() -> None:
    bad = [
        f"{path.relative_to(REPO)}:{n}: {', '.join(found)}"
        for path, lines in prose_files()
        for n, line in lines
        if (found := findings(line))
    ]
    assert not bad, "commit ids or dates (history belongs in git):\n" + "\n".join(bad)


def test_benchmarks_has_dates_only_in_its_date_column() -> None:
    bad = []
    for n, line in enumerate(BENCHMARKS.read_text().splitlines(), 1):
        found = findings(DATE_CELL.sub("||", line))
        if found:
            bad.append(f"BENCHMARKS.md:{n}: {', '.join(found)}")
    assert not bad, "BENCHMARKS.md: dates belong in the date column only:\n" + "\n".join(bad)
