"""Fixtures of the CLI tests (helpers live in ``cli_helpers``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest


@pytest.fixture
def no_bus(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Record (and refuse) every attempt to open a CAN bus."""
    opened: list[dict[str, Any]] = []

    def refuse(*args: Any, **kwargs: Any) -> None:
        opened.append(kwargs)
        raise AssertionError(f"a bus was opened: {kwargs}")

    monkeypatch.setattr(can, "Bus", refuse)
    return opened


@pytest.fixture
def store_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A temporary store as the default (``$HRM_CALIBRATIONS``), HOME elsewhere."""
    folder = tmp_path / "calibrations"
    monkeypatch.setenv("HRM_CALIBRATIONS", str(folder))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    return folder
