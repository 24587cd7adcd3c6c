"""A channel's folder and this end's socket in it.

Each end of channel ``NAME`` binds a Unix-domain ``SOCK_SEQPACKET`` socket
``<pid>-<n>.sock`` in the folder ``<directory>/hrm-ipc-NAME/``: mode 0700, owned by this
user (anything else is refused, naming the folder), ``directory`` defaulting to
``$XDG_RUNTIME_DIR`` or ``/tmp``.  A socket is bound and listening under a hidden name
before it is linked to its visible one, so no peer ever sees a socket nobody listens on.

>>> import tempfile
>>> with tempfile.TemporaryDirectory() as d:
...     folder = channel_folder(d, "doc")
...     make_folder(folder)
...     sock, path = bind(folder)
...     mode = oct(folder.stat().st_mode & 0o777)
...     print(folder.name, bool(SOCKET_NAME.fullmatch(path.name)), mode)
...     sock.close()
hrm-ipc-doc True 0o700
"""

from __future__ import annotations

import errno
import itertools
import os
import re
import socket
import stat
import threading
from pathlib import Path

import can

CHANNEL_RE = re.compile(r"[A-Za-z0-9._-]{1,64}")
#: What an end's socket is called: ``<pid>-<n>.sock``
SOCKET_NAME = re.compile(r"([0-9]{1,10})-[0-9]{1,20}\.sock")
FOLDER_PREFIX = "hrm-ipc-"
LISTEN_BACKLOG = 128
MAX_SUN_PATH = 107  # bytes of a socket path (sockaddr_un.sun_path, less its NUL)
_MAX_BIND_TRIES = 1000

_counter = itertools.count()
_counter_lock = threading.Lock()


def default_directory() -> Path:
    """Where channel folders live unless ``directory`` is given: ``$XDG_RUNTIME_DIR`` or
    ``/tmp``.

    >>> isinstance(default_directory(), Path)
    True
    """
    return Path(os.environ.get("XDG_RUNTIME_DIR") or "/tmp")


def channel_folder(directory: str | os.PathLike[str] | None, channel: str) -> Path:
    """The folder of ``channel`` under ``directory`` (default :func:`default_directory`)."""
    base = Path(directory if directory is not None else default_directory())
    return base / f"{FOLDER_PREFIX}{channel}"


def check_path_room(folder: Path) -> None:
    """Refuse a folder whose socket paths would be too long for a Unix socket, before the
    folder is made (a refused end leaves nothing behind): the name :func:`bind` will use,
    with room for a counter of 6 digits."""
    longest = folder / f".{os.getpid()}-{10**6 - 1}.tmp"
    if len(os.fsencode(longest)) > MAX_SUN_PATH:
        raise can.CanInitializationError(
            f"hrm_ipc: socket paths under {folder} would be longer than "
            f"{MAX_SUN_PATH} bytes (pass a shorter directory=)"
        )


def is_private(st: os.stat_result) -> bool:
    """Whether a folder's status is that of a folder :func:`make_folder` made: a directory
    of this user that nobody else may enter."""
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.geteuid() and not st.st_mode & 0o077


def make_folder(folder: Path) -> None:
    """Make the channel folder (mode 0700) unless it exists; refuse one that is not a
    private directory of this user (``can.CanInitializationError`` naming it)."""
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:
            pass
        st = os.lstat(folder)
    except OSError as exc:
        raise can.CanInitializationError(
            f"hrm_ipc: cannot create channel folder {folder} ({exc.strerror})"
        ) from None
    if not stat.S_ISDIR(st.st_mode):
        raise can.CanInitializationError(f"hrm_ipc: {folder} is not a directory")
    if not is_private(st):
        raise can.CanInitializationError(
            f"hrm_ipc: {folder} must be a private folder of this user (mode 0700; it is "
            f"uid {st.st_uid}'s, mode {stat.S_IMODE(st.st_mode):04o}): remove it, or set "
            "XDG_RUNTIME_DIR or pass directory= for a folder of your own"
        )


def bind(folder: Path) -> tuple[socket.socket, Path]:
    """Bind and listen under a hidden name, then link the socket to ``<pid>-<n>.sock``:
    a peer never sees a socket file nobody listens on yet (it would take it for a stale
    one and unlink it), and an existing name is never replaced."""
    pid = os.getpid()
    for _ in range(_MAX_BIND_TRIES):
        with _counter_lock:
            n = next(_counter)
        path = folder / f"{pid}-{n}.sock"
        tmp = folder / f".{pid}-{n}.tmp"
        if len(os.fsencode(tmp)) > MAX_SUN_PATH:
            raise can.CanInitializationError(
                f"hrm_ipc: socket path {tmp} is longer than {MAX_SUN_PATH} bytes "
                "(pass a shorter directory=)"
            )
        sock = socket.socket(
            socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_NONBLOCK | socket.SOCK_CLOEXEC
        )
        try:
            try:
                sock.bind(os.fspath(tmp))
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    sock.close()
                    continue  # left over by an earlier process with this pid: next n
                if exc.errno == errno.ENOENT:  # the last end removed the empty folder
                    sock.close()
                    make_folder(folder)
                    continue
                raise
            try:
                sock.listen(LISTEN_BACKLOG)
                os.link(tmp, path)
            except FileExistsError:
                sock.close()
                continue
            finally:
                tmp.unlink(missing_ok=True)
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError(
                f"hrm_ipc: cannot bind {path} ({exc.strerror})"
            ) from None
        return sock, path
    raise can.CanInitializationError(f"hrm_ipc: no free socket name in {folder}")
