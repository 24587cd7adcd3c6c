"""Fixtures of the console tests: a console context on the in-process simulated box."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import pytest

from hrm_ctrl.cli._console.context import ConsoleContext


@pytest.fixture
def isolated_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """HOME and the calibration store in the test's folder (no calibration: the simulated
    arm runs with the description's values)."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("HRM_CALIBRATIONS", str(tmp_path / "calibrations"))
    return home


def console_args(tmp_path: Path, *extra: str) -> argparse.Namespace:
    """The parsed arguments of ``hrm console --sim --wire virtual --log-dir TMP/runs
    EXTRA...``: the box in this interpreter, whose drives the tests look into
    (``ctx.sim.box``; ``hrm console --sim`` runs it in its own process by default)."""
    from hrm_ctrl.cli import console

    p = argparse.ArgumentParser()
    console.register(p)
    argv = ["--sim", "--wire", "virtual", "--log-dir", str(tmp_path / "runs"), *extra]
    return p.parse_args(argv)


@pytest.fixture
def make_ctx(tmp_path: Path, isolated_home: Path) -> Iterator[object]:
    """``make_ctx(*extra_args)``: a console context on a fresh in-process simulated box
    whose lines are collected in ``ctx.lines`` (out) and ``ctx.errors`` (err); finished
    (drives disabled, session closed, box stopped) at the end of the test.  The process
    runs with the switch interval ``hrm console --sim`` runs with (``hrm_ctrl.cli.main``
    sets it; these tests build the context without it)."""
    from drivers.realtime import process_settings
    from hrm_ctrl.cli._console.shell import build_context, finish_context
    from sim_bus.in_process import IN_PROCESS_SWITCH_INTERVAL_S

    made: list[ConsoleContext] = []

    def make(*extra: str) -> ConsoleContext:
        ctx = build_context(console_args(tmp_path, *extra), "hrm console")
        lines: list[str] = []
        errors: list[str] = []
        ctx.out = lines.append
        ctx.err = errors.append
        ctx.lines = lines  # type: ignore[attr-defined]
        ctx.errors = errors  # type: ignore[attr-defined]
        made.append(ctx)
        return ctx

    with process_settings(switch_interval_s=IN_PROCESS_SWITCH_INTERVAL_S):
        yield make
        for ctx in made:
            finish_context(ctx)
