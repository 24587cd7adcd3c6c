"""The only shared I/O helpers: reading text and TOML files with one-line errors that
name the file, and atomic writes (a reader sees the old file or the new one, never half).

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "x.toml"
>>> _ = p.write_text("a = 1")
>>> doc, source = read_toml(p, ValueError, "test file")
>>> doc, source.endswith("x.toml")
({'a': 1}, True)
>>> read_toml(p.with_name("none.toml"), ValueError, "test file")
Traceback (most recent call last):
ValueError: ...none.toml: test file not found
>>> write_atomic(p.with_name("y.txt"), "hello")
>>> p.with_name("y.txt").read_text()
'hello'
"""

from __future__ import annotations

import os
import tempfile
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


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once at import: os.umask can only be read by setting it, which would race with
# files other threads create.
_UMASK = _read_umask()


def write_atomic(path: str | Path, data: str | bytes, *, make_parents: bool = True) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and
    ``os.replace``; flushed and fsynced, with the usual file mode (0666 less the
    umask).  The folder is created if missing unless ``make_parents`` is false.
    Raises ``OSError`` (no partial file is left behind)."""
    p = Path(path)
    if make_parents:
        p.parent.mkdir(parents=True, exist_ok=True)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
