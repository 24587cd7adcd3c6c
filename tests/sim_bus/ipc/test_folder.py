"""``sim_bus.ipc.folder``: bad channel names and folders that are not private, or whose
socket paths would be too long, are refused in one line."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from sim_bus.ipc import (
    IpcBus,
)


@pytest.mark.parametrize(
    ("channel", "words"),
    [("", "channel"), ("a/b", "channel"), ("x" * 65, "channel")],
)
def test_bad_channel_is_refused(folder: str, channel: str, words: str) -> None:
    with pytest.raises(can.CanInitializationError, match=words):
        IpcBus(channel, directory=folder)


def test_unsafe_or_long_folder_is_refused(folder: str) -> None:
    open_dir = Path(folder, "hrm-ipc-pub")
    open_dir.mkdir(mode=0o755)
    open_dir.chmod(0o755)
    private = r"private folder of this user \(mode 0700; it is uid \d+'s, mode 0755\)"
    with pytest.raises(can.CanInitializationError, match=private):
        IpcBus("pub", directory=folder)
    Path(folder, "hrm-ipc-file").write_text("")
    with pytest.raises(can.CanInitializationError, match="not a directory"):
        IpcBus("file", directory=folder)
    deep = Path(folder, "d" * 90)
    with pytest.raises(can.CanInitializationError, match="107"):
        IpcBus("long", directory=deep)
    assert not deep.exists()  # refused before any folder was made
    with pytest.raises(can.CanInitializationError, match="rx_queue_size"):
        IpcBus("q", directory=folder, rx_queue_size=0)
    with pytest.raises(can.CanInitializationError, match="unknown option diretory"):
        can.Bus(interface="hrm_ipc", channel="q", diretory=folder)
    with pytest.raises(can.CanInitializationError, match="FD"):
        can.Bus(interface="hrm_ipc", channel="q", directory=folder, fd=True)
    assert list(Path(folder).glob("*/*.sock")) == []  # nothing left by the refused opens
