"""``sim_bus.ipc.cleanup``: the folders of channels whose ends were all killed are
removed; a listening end is kept."""

from __future__ import annotations

import socket
from pathlib import Path

from sim_bus.ipc import (
    IpcBus,
    remove_stale_channels,
)
from tests.sim_bus.ipc.ipc_rig import child


def test_the_folder_of_a_channel_whose_ends_were_killed_is_removed(folder: str) -> None:
    """A process killed before its shutdown leaves the channel folder with its socket;
    a live end's folder is kept, and so is a folder of another prefix."""
    p = child(folder, "idle")
    live = IpcBus("kid-live", directory=folder)
    other = Path(folder, "hrm-ipc-other")
    other.mkdir()
    Path(other, "999999999-0.sock").touch()  # stale, but not ours to remove
    try:
        p.kill()
        p.wait(30.0)
        stale = Path(folder, "hrm-ipc-kid")
        assert [f.name for f in stale.iterdir()] == [f"{p.pid}-0.sock"]  # left behind
        assert remove_stale_channels("kid", folder) == [stale]
        assert not stale.exists()
        assert live.path.exists() and other.exists()
        assert remove_stale_channels("kid", folder) == []
    finally:
        live.shutdown()


def test_a_listening_end_under_a_pid_unknown_here_is_kept(folder: str) -> None:
    """An end of another PID namespace (its pid names no process here) still listens: its
    channel stays.  A pid too large for a pid, a stale socket: removed, no error.  A
    folder that is not private (not one IpcBus made): left alone."""
    ns = Path(folder, "hrm-ipc-ns")
    ns.mkdir(mode=0o700)
    listening = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listening.bind(str(ns / "999999999-0.sock"))
    listening.listen(1)
    huge = Path(folder, "hrm-ipc-ns-huge")
    huge.mkdir(mode=0o700)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(huge / "9999999999-0.sock"))
    stale.close()
    public = Path(folder, "hrm-ipc-ns-public")
    public.mkdir(mode=0o755)
    public.chmod(0o755)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stale.bind(str(public / "999999999-0.sock"))
    stale.close()
    try:
        assert remove_stale_channels("ns", folder) == [huge]
        assert (ns / "999999999-0.sock").exists() and public.exists()
    finally:
        listening.close()
