"""The console's ``calibrate zero`` / ``stiffness`` over the live session on the simulated
box: enabled drives only, the simulated arm in its fixture for the routine, the version
saved in the console's store, used from the next ``connect`` on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.store import CalibrationStore
from hrm_ctrl.cli._console.shell import run_script
from hrm_ctrl.cli._console.table import ConsoleError
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT


def run(ctx: object, *lines: str) -> None:
    run_script(ctx, list(lines), "test")


def test_bad_options_and_states_are_refused_before_anything_moves(make_ctx) -> None:
    ctx = make_ctx()
    for line, match in [
        ("calibrate zero --target-N -3", r"--target-N must be > 0, got -3.0"),
        ("calibrate zero --speed 3", r"calibrate zero: unrecognized arguments: --speed 3"),
        ("calibrate stiffness --steps 1", r"--steps must be at least 2, got 1"),
        ("calibrate stiffness --steps x", r"calibrate stiffness: argument --steps: invalid int"),
        ("calibrate zero", r"calibrate zero: enable the drives first"),
    ]:
        with pytest.raises(ConsoleError, match=match):
            run(ctx, line)
    run(ctx, "connect")
    before = ctx.sim.box.counts().copy()
    with pytest.raises(ConsoleError, match=r"enable the drives first"):
        run(ctx, "calibrate stiffness")
    run(ctx, "enable")
    sim, ctx.sim = ctx.sim, None  # as on a real box: the operator must confirm the fixture
    try:
        with pytest.raises(ConsoleError, match=r"the arm must lie in its zero fixture: say so "
                                               r"with --fixture"):  # fmt: skip
            run(ctx, "calibrate zero")
    finally:
        ctx.sim = sim
    assert np.array_equal(ctx.sim.box.counts(), before)
    assert ctx.session.results == []  # nothing was streamed


@STALL_TOLERANT
def test_zero_saves_a_version_that_the_next_connect_drives_with(make_ctx, tmp_path: Path) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable", "calibrate zero --json")
    summary = json.loads(next(line for line in ctx.lines if line.startswith("{")))
    assert summary["motors"] == 36 and summary["version"] == 1
    assert summary["max_abs_tension_error_N"] <= summary["tol_N"]
    assert any("lies in its zero fixture" in line for line in ctx.lines)
    assert not ctx.sim.box.arm.fixture  # taken out again
    assert ctx.watches is not None  # the watches run again on the enabled drives
    store = CalibrationStore(tmp_path / "calibrations")
    assert store.active() == 1
    saved = store.load(1)
    assert {m: int(v) for m, v in saved.motor_zero_counts.items()} == summary["zero_counts"]
    with pytest.raises(ConsoleError, match=r"v0001 was saved in this session: disconnect"):
        run(ctx, "calibrate stiffness")
    assert ctx.active is None  # the session still drives with what it connected with
    run(ctx, "disconnect", "connect")
    assert "calibration: v0001" in ctx.lines
    assert ctx.active is not None and ctx.active.version == 1
    assert ctx.session.calibration is not None and ctx.session.calibration.version == 1
    zeros = np.asarray(ctx.actuation.motors.zero_offsets_counts)
    ids = ctx.actuation.motor_ids
    assert [int(zeros[ids.index(m)]) for m in summary["zero_counts"]] == list(
        summary["zero_counts"].values()
    )
