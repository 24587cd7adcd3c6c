"""Reading text and TOML description files with one-line errors that name the file.

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "x.toml"
>>> _ = p.write_text("a = 1")
>>> doc, source = read_toml(p, ValueError, "test file")
>>> doc, source.endswith("x.toml")
({'a': 1}, True)
>>> read_toml(p.with_name("none.toml"), ValueError, "test file")
Traceback (most recent call last):
ValueError: ...none.toml: test file not found
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any


def read_text_file(
    path: str | Path, error: type[Exception], what: str, source: str | None = None
) -> str:
    """The UTF-8 text of ``path``; a missing or unreadable file raises ``error`` with one
    line naming ``source`` (default: the path), e.g. ``p.csv: path file not found``."""
    name = str(path) if source is None else source
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{name}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{name}: cannot read {what} ({exc})") from None


def read_toml(
    path: str | Path, error: type[Exception], what: str, source: str | None = None
) -> tuple[dict[str, Any], str]:
    """Parse the TOML file at ``path``; return ``(document, source)``.

    ``source`` names the file in messages (default: the path).  A missing,
    unreadable or malformed file raises ``error`` with one line, e.g.
    ``robot.toml: robot file not found`` or ``box.toml: not valid TOML (...)``.
    """
    name = str(path) if source is None else source
    text = read_text_file(path, error, what, name)
    try:
        return tomllib.loads(text), name
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{name}: not valid TOML ({exc})") from None
