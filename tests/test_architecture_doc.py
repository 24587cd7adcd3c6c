"""``docs/architecture.md`` lists every module of the packages, one line each, and no module
that does not exist: its "Modules" section against the tree."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "architecture.md"
PACKAGES = ("hrm_ctrl", "drivers", "sim_bus", "calibration", "benchmarks")
LISTED = re.compile(r"^- `([\w/]+\.py)`: \S")


def modules_in_tree() -> set[str]:
    """Every module file of the packages but the packages' ``__init__.py``."""
    return {
        p.relative_to(REPO).as_posix()
        for package in PACKAGES
        for p in (REPO / package).rglob("*.py")
        if p.name != "__init__.py"
    }


def modules_listed(text: str) -> list[str]:
    """The modules the document's "## Modules" section lists (``- `path.py`: what``)."""
    section = text.split("\n## Modules\n", 1)[1].split("\n## ", 1)[0]
    return [m.group(1) for line in section.splitlines() if (m := LISTED.match(line))]


def test_modules_listed_reads_the_modules_section_only() -> None:
    text = (
        "## Packages\n- `a/x.py`: no\n## Modules\n\n### a\n\n- `a/b.py`: one\n"
        "- `a/c.py`:\n## Next\n- `a/d.py`: no\n"
    )
    assert modules_listed(text) == ["a/b.py"]  # c has no line of its own


def test_architecture_doc_lists_every_module_once_and_nothing_else() -> None:
    listed = modules_listed(DOC.read_text())
    tree = modules_in_tree()
    missing = sorted(tree - set(listed))
    extra = sorted(set(listed) - tree)
    twice = sorted({m for m in listed if listed.count(m) > 1})
    problems = (
        [f"missing (in the tree, not in docs/architecture.md): {m}" for m in missing]
        + [f"extra (in docs/architecture.md, no such module): {m}" for m in extra]
        + [f"listed twice: {m}" for m in twice]
    )
    assert not problems, "docs/architecture.md, section Modules:\n" + "\n".join(problems)
