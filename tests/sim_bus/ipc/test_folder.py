"""``sim_bus.ipc.folder``: bad channel names and folders that are not private, or whose
socket paths would be too long, are refused in one line."""

from __future__ import annotations

import logging
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
    with pytest.raises(can.CanInitializationError, match="did you mean receive_own_messages"):
        can.Bus(interface="hrm_ipc", channel="q", directory=folder, receive_own_message=True)
    assert list(Path(folder).glob("*/*.sock")) == []  # nothing left by the refused opens


def test_generic_python_can_options_are_accepted_and_named_in_a_log_line(
    folder: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Generic python-can code (its back-to-back tests) passes ``fd`` and ``single_handle``:
    accepted and ignored as python-can's virtual bus does, with one log line; an FD frame
    is still refused at send."""
    with caplog.at_level(logging.WARNING, logger="sim_bus.ipc"):
        bus = can.Bus(
            interface="hrm_ipc",
            channel="gen",
            directory=folder,
            fd=True,
            single_handle=True,
            data_bitrate=2_000_000,
        )
    try:
        lines = [r.getMessage() for r in caplog.records if r.name == "sim_bus.ipc"]
        assert len(lines) == 1
        assert "ignoring option(s) data_bitrate=2000000, fd=True, single_handle=True" in lines[0]
        assert "'gen'" in lines[0] and "FD frame is refused" in lines[0]
        with pytest.raises(can.CanOperationError, match="FD"):
            bus.send(can.Message(arbitration_id=1, data=bytes(12), is_fd=True))
    finally:
        bus.shutdown()
