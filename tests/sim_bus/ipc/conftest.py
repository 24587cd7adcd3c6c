"""Fixtures of the hrm_ipc tests: a short private folder, three ends of one channel."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator

import pytest

from sim_bus.ipc import (
    IpcBus,
    open_ends,
)


@pytest.fixture
def folder() -> Iterator[str]:
    # short: a Unix socket path is at most 107 bytes (pytest's tmp_path can be longer)
    with tempfile.TemporaryDirectory(prefix="hrm-ipc-t") as d:
        yield d


@pytest.fixture
def three(folder: str) -> Iterator[list[IpcBus]]:
    ends = open_ends("t3", 3, folder)
    yield ends
    for e in ends:
        e.shutdown()
