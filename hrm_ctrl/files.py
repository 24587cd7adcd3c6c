"""The only shared I/O helpers: reading text, TOML and JSON with one-line errors that
name the file, and atomic writes (a reader sees the old file or the new one, never half).

Every reader is bounded and guarded, whatever the input: a file is read up to a size
(:data:`MAX_TEXT_BYTES` by default, :data:`MAX_TOML_BYTES` for TOML) and refused past it
without reading further (``/dev/zero`` included); a TOML integer must fit TOML's 64 bits
and a JSON integer a 64-bit float (Python would otherwise stop at 4300 digits with a
``ValueError``, or raise ``OverflowError`` later where the number becomes a float); a
document nested too deeply for the parser is refused.  Every refusal is one line of the
caller's error class naming the file.

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "x.toml"
>>> _ = p.write_text("a = 1")
>>> doc, source = read_toml(p, ValueError, "test file")
>>> doc, source.endswith("x.toml")
({'a': 1}, True)
>>> read_toml(p.with_name("none.toml"), ValueError, "test file")
Traceback (most recent call last):
ValueError: ...none.toml: test file not found
>>> _ = p.write_text("[motors]\\nn = [1, 99999999999999999999]")
>>> read_toml(p, ValueError, "test file")
Traceback (most recent call last):
ValueError: ...x.toml: motors.n[1]: integer 99999999999999999999 is outside TOML's 64-bit range
>>> parse_json('{"a": [1, 2.5]}', ValueError, "p.json")
{'a': [1, 2.5]}
>>> parse_json('{"a": 1' + "0" * 400 + '}', ValueError, "p.json")  # doctest: +ELLIPSIS
Traceback (most recent call last):
ValueError: p.json: line 1: integer 100000000000...(401 digits) is too large for a number ...
>>> write_atomic(p.with_name("y.txt"), "hello")
>>> p.with_name("y.txt").read_text()
'hello'
"""

from __future__ import annotations

import errno
import json
import os
import re
import stat
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import Any

MAX_TEXT_BYTES = 64 * 2**20  # a text file larger than this is refused (default bound)
MAX_TOML_BYTES = 2**20  # robot and bus descriptions are a few kB; 1 MiB is far beyond
TOML_INT_MIN, TOML_INT_MAX = -(2**63), 2**63 - 1  # TOML 1.0: integers are 64-bit
# The most digits an integer within a 64-bit float's range has (1.8e308); longer ones are
# refused before Python converts them (its limit is 4300 digits, then ValueError).
_FLOAT_INT_DIGITS = len(str(int(sys.float_info.max)))


def read_text_file(
    path: str | Path,
    error: type[Exception],
    what: str,
    source: str | None = None,
    *,
    max_bytes: int = MAX_TEXT_BYTES,
    follow_symlinks: bool = True,
) -> str:
    """The UTF-8 text of ``path`` (newlines as ``\\n``); a missing or unreadable file, one
    that is not a regular file (a FIFO would block the reader until some writer came, a
    device may never end) or one of more than ``max_bytes`` bytes (not read past the
    bound) raises ``error`` with one line naming ``source`` (default: the path), e.g.
    ``p.csv: path file not found``.  ``follow_symlinks=False``: a symbolic link is refused
    too (a store's own files must be its own, not links to files elsewhere)."""
    name = str(path) if source is None else source
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC
    if not follow_symlinks:
        flags |= os.O_NOFOLLOW
    try:
        # non-blocking: opening a FIFO for reading would wait for a writer
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise error(f"{name}: {what} not found") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP and not follow_symlinks:
            raise error(f"{name}: {what} is a symbolic link, not a file of its own") from None
        raise error(f"{name}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        regular = stat.S_ISREG(os.fstat(fd).st_mode)  # a folder opens, but fdopen refuses it
    except OSError as exc:
        os.close(fd)
        raise error(f"{name}: cannot read {what} ({exc.strerror or exc})") from None
    if not regular:
        os.close(fd)
        raise error(f"{name}: {what} is not a regular file")
    try:
        with os.fdopen(fd, "rb") as f:
            raw = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{name}: cannot read {what} ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:
        raise error(f"{name}: {what} is larger than the {max_bytes} bytes it may have")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{name}: cannot read {what} ({exc})") from None
    return text.replace("\r\n", "\n").replace("\r", "\n")  # as text mode reads it


def _abbrev(digits: str) -> str:
    return digits if len(digits) <= 24 else f"{digits[:12]}...({len(digits.lstrip('-'))} digits)"


def _first_wide_int(doc: Any) -> tuple[str, int] | None:
    """The place and value of the first integer outside TOML's 64-bit range, if any."""
    stack: list[tuple[str, Any]] = [("", doc)]
    while stack:
        place, value = stack.pop()
        if isinstance(value, dict):
            items = [(f"{place}.{k}" if place else str(k), v) for k, v in value.items()]
        elif isinstance(value, list):
            items = [(f"{place}[{i}]", v) for i, v in enumerate(value)]
        else:
            if isinstance(value, int) and not isinstance(value, bool):
                if not TOML_INT_MIN <= value <= TOML_INT_MAX:
                    return place, value
            continue
        stack.extend(reversed(items))  # document order
    return None


def read_toml(
    path: str | Path, error: type[Exception], what: str, source: str | None = None
) -> tuple[dict[str, Any], str]:
    """Parse the TOML file at ``path``; return ``(document, source)``.

    ``source`` names the file in messages (default: the path).  A missing,
    unreadable, malformed or too large (:data:`MAX_TOML_BYTES`) file, an integer
    outside TOML's 64-bit range or nesting too deep for the parser raises ``error``
    with one line, e.g. ``robot.toml: robot file not found`` or ``box.toml: not valid
    TOML (...)``.
    """
    name = str(path) if source is None else source
    text = read_text_file(path, error, what, name, max_bytes=MAX_TOML_BYTES)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{name}: not valid TOML ({exc})") from None
    except RecursionError:
        raise error(f"{name}: not valid TOML (nested too deeply)") from None
    except ValueError as exc:  # an integer of more digits than Python converts
        reason = str(exc).split(";")[0]
        raise error(f"{name}: not valid TOML (a number that cannot be read: {reason})") from None
    wide = _first_wide_int(doc)
    if wide is not None:
        place, value = wide
        raise error(
            f"{name}: {place}: integer {_abbrev(str(value))} is outside TOML's 64-bit range"
        )
    return doc, name


_TOO_LARGE = object()  # first argument of the ValueError _json_int raises


def _json_int(text: str) -> int:
    """``parse_int`` of :func:`json.loads`: an integer a 64-bit float can hold."""
    if len(text.lstrip("-")) > _FLOAT_INT_DIGITS:
        raise ValueError(_TOO_LARGE, text)
    value = int(text)
    try:
        float(value)
    except OverflowError:
        raise ValueError(_TOO_LARGE, text) from None
    return value


def _line_of(text: str, digits: str) -> str:
    """``line N: `` of the number token ``digits`` in ``text`` (empty if not found)."""
    m = re.search(rf"(?<![\w.+-]){re.escape(digits)}(?![\w.])", text)
    return "" if m is None else f"line {text.count(chr(10), 0, m.start()) + 1}: "


def parse_json(text: str, error: type[Exception], name: str, what: str = "JSON document") -> Any:
    """Parse JSON ``text``; every problem raises ``error`` with one line naming ``name``:
    bad syntax (``not JSON (line 3: ...)``), nesting too deep for the parser (``not a
    {what} (JSON nested too deeply)``) or an integer beyond a 64-bit float's range (which
    no reader could use as a number)."""
    try:
        return json.loads(text, parse_int=_json_int)
    except json.JSONDecodeError as exc:
        raise error(f"{name}: not JSON (line {exc.lineno}: {exc.msg})") from None
    except RecursionError:
        raise error(f"{name}: not a {what} (JSON nested too deeply)") from None
    except ValueError as exc:
        if len(exc.args) == 2 and exc.args[0] is _TOO_LARGE:
            digits = str(exc.args[1])
            raise error(
                f"{name}: {_line_of(text, digits)}integer {_abbrev(digits)} is too large "
                "for a number (beyond a 64-bit float)"
            ) from None
        raise error(f"{name}: not JSON ({str(exc).splitlines()[0]})") from None


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Read once at import: os.umask can only be read by setting it, which would race with
# files other threads create.
_UMASK = _read_umask()


def _file_in(folder: Path) -> Path:
    """The first part of ``folder`` that exists and is not a folder (else ``folder``).

    >>> _file_in(Path("/dev/null/a/b"))
    PosixPath('/dev/null')
    """
    for part in (*reversed(folder.parents), folder):
        if part.exists() and not part.is_dir():
            return part
    return folder


def write_atomic(path: str | Path, data: str | bytes, *, make_parents: bool = True) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and
    ``os.replace``; flushed and fsynced, with the usual file mode (0666 less the
    umask).  The folder is created if missing unless ``make_parents`` is false.
    Raises ``OSError`` (no partial file is left behind), also when ``path`` exists and
    is not a regular file (a device, a FIFO, a socket, a folder: never replaced).  A
    symbolic link is written through: its target is replaced, the link stays (so
    ``/dev/stdout`` redirected to a file writes that file, and is never itself replaced)."""
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        mode = None
    except OSError:
        mode = None  # (a dangling link, a folder we cannot look into): the write says why
    if mode is not None and not stat.S_ISREG(mode):
        raise OSError(errno.EEXIST, "exists and is not a regular file", str(p))
    if p.is_symlink():
        p = Path(os.path.realpath(p))
    if make_parents:
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):  # a part of the folder is a file
            raise OSError(errno.ENOTDIR, f"{_file_in(p.parent)} is not a folder") from None
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
