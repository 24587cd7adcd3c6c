"""Removing what killed processes left: the folders of channels whose ends are all gone.

An end that is shut down unlinks its socket (the last one takes the folder along); a
process killed before that leaves its socket file behind.  Peers unlink such a file when
its connection is refused (:mod:`sim_bus.ipc.discovery`); a channel nobody opens again
keeps its folder until :func:`remove_stale_channels` removes it.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

from sim_bus.ipc.folder import FOLDER_PREFIX, SOCKET_NAME, default_directory, is_private


def pid_alive(pid: int) -> bool:
    """Whether a process of this pid runs here (a zombie does not; another user's does,
    as far as this end can judge).

    >>> pid_alive(os.getpid()), pid_alive(2**40)
    (True, False)
    """
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # gone, or no pid at all
        return False
    except OSError:  # EPERM (another user's: not ours to judge) and the like
        return True
    try:  # a zombie (killed, not yet reaped) is gone too
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rpartition(b")")[2].split()[:1] != [b"Z"]
    except OSError:
        return True


def nobody_listens(path: Path) -> bool:
    """Whether the socket file ``path`` is stale: a connection to it is refused (what
    :class:`sim_bus.ipc.discovery.Peers` takes for a crashed end).  Anything else
    (accepted, a full backlog, another error): not known to be stale."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_NONBLOCK)
    try:
        sock.connect(os.fspath(path))
    except ConnectionRefusedError:
        return True
    except OSError:
        return False
    finally:
        sock.close()
    return False


def remove_stale_channels(
    prefix: str, directory: str | os.PathLike[str] | None = None
) -> list[Path]:
    """Remove the folders of channels named ``prefix...`` whose ends are all gone (left by
    processes killed before their :meth:`IpcBus.shutdown`): this user's private folder,
    every entry a ``<pid>-<n>.sock`` of no process here whose connection is refused.  The
    pid alone does not decide (a process of another PID namespace sharing the folder has
    a pid that means nothing here); a folder with any other entry (a socket being bound),
    with none, or with a socket that accepts is left alone.  The folders removed.

    >>> import tempfile
    >>> from sim_bus.ipc import open_ends
    >>> with tempfile.TemporaryDirectory() as d:
    ...     dead = Path(d, "hrm-ipc-x-dead"); dead.mkdir(mode=0o700)
    ...     s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ...     s.bind(str(dead / "999999999-0.sock")); s.close()   # bound, never listened
    ...     live = open_ends("x-live", 1, d)[0]
    ...     [p.name for p in remove_stale_channels("x-", d)], live.path.exists()
    ...     live.shutdown()
    (['hrm-ipc-x-dead'], True)
    """
    base = Path(directory) if directory is not None else default_directory()
    removed: list[Path] = []
    try:
        folders = [e for e in os.scandir(base) if e.name.startswith(FOLDER_PREFIX + prefix)]
    except OSError:
        return removed
    for entry in folders:
        folder = Path(entry.path)
        try:
            st = os.lstat(folder)
            names = os.listdir(folder)
        except OSError:
            continue
        if not is_private(st) or not names:  # not a folder IpcBus made: not ours to judge
            continue
        matches = [SOCKET_NAME.fullmatch(n) for n in names]
        if any(m is None for m in matches):
            continue
        if any(m is not None and pid_alive(int(m.group(1))) for m in matches):
            continue
        if not all(nobody_listens(folder / n) for n in names):
            continue
        try:
            for name in names:
                os.unlink(folder / name)
            folder.rmdir()
        except OSError:
            continue
        removed.append(folder)
    return removed
