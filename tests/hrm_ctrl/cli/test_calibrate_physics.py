"""``hrm calibrate physics``: bad arguments refused in one line before anything opens;
on the simulated box (its own process, the default physics' constants, gravity and
capstan friction) a short routine saves a version whose ``physics`` ``show`` prints and
the feed-forward of the calibrated rope layer takes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.apply import calibrated_actuation
from calibration.store import CalibrationStore, Routine
from hrm_ctrl.cli import main
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.feedforward import Feedforward
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT


def test_bad_arguments_are_one_line(
    store_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    box = tmp_path / "box.toml"
    for argv, message in [
        (["calibrate", "physics"], "give --sim or --config BOX.toml"),
        (["calibrate", "physics", "--sim", "--config", str(box)], "give --sim or --config"),
        (["calibrate", "physics", "--config", str(box), "--perturb", "1"],
         "--perturb goes with --sim"),
        (["calibrate", "physics", "--config", str(box), "--physics", "all"],
         "--physics goes with --sim"),
        (["calibrate", "physics", "--sim", "--holds", "3"], "--holds must be 8..500"),
        (["calibrate", "physics", "--sim", "--payload-kg", "-1"], "--payload-kg must be"),
        (["calibrate", "physics", "--sim", "--physics", "gravity,frition"],
         "unknown effect 'frition'"),
    ]:  # fmt: skip
        assert main(argv) == 2, argv
        captured = capsys.readouterr()
        assert message in captured.err and captured.err.count("\n") == 1, (argv, captured.err)
        assert captured.out == ""
    assert not store_dir.exists()  # nothing written


@STALL_TOLERANT
def test_on_the_simulated_box_saves_the_physics(
    store_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """8 holds (the fewest the fit takes) on the arm of the description with the default
    constants (link masses 20 g, payload 20 g, friction 0.10): found within 10 %."""
    argv = ["calibrate", "physics", "--sim", "--holds", "8", "--log-dir", str(tmp_path / "r")]
    assert main([*argv, "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    summary = json.loads(out[-1])
    assert summary["version"] == 1 and summary["active"] and summary["holds"] == 8
    mu = np.array(summary["mu_kinetic"])
    mass = np.array(summary["link_mass_kg"])
    assert np.abs(mu / 0.10 - 1.0).max() < 0.10, mu
    assert np.abs(mass / 0.020 - 1.0).max() < 0.10, mass
    cal = CalibrationStore(store_dir).load(1)
    assert cal.routine is Routine.PHYSICS and cal.physics is not None
    assert cal.physics.mu_kinetic.tolist() == mu.tolist() and cal.physics.payload_kg == 0.02
    assert main(["calibrate", "show"]) == 0
    shown = capsys.readouterr().out
    assert "physics: payload 20.00 g (given)" in shown and "mu kinetic" in shown
    ff = Feedforward.of(calibrated_actuation(default_robot(), cal))
    assert ff.physics.mu_kinetic.tolist() == mu.tolist()
