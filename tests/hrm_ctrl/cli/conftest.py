"""Fixtures of the CLI tests (helpers live in ``cli_helpers``)."""

from __future__ import annotations

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
