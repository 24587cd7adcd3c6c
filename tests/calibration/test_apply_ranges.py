"""Calibrated values far from the robot description are refused when applied.

A version file with ``links_mm[0] = 1e300`` and a recomputed checksum used to pass the
store's check: ``hrm calibrate show`` showed it and ``hrm plan --calibrations`` printed
about ten NumPy overflow warnings before its error.  Now every command that applies a
calibration refuses it with one line naming the version file and the key (exit 2), and
nothing warns on the way (RuntimeWarnings are errors here).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calibration.apply import check_belongs, nominal_calibration, updated
from calibration.store import CalibrationStore, checksum
from hrm_ctrl.errors import CalibrationFileError
from hrm_ctrl.model import default_robot
from tests.hrm_ctrl.cli.test_bad_input import refused

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

MODEL = default_robot()


def _store(tmp_path: Path, edit: Callable[[dict[str, Any]], None] | None = None) -> Path:
    """A store with one version (a plausible kinematic result), ``edit`` applied to its
    file by hand and the checksum recomputed (so only the range check can refuse it)."""
    folder = tmp_path / "cal"
    cal = updated(
        nominal_calibration(MODEL), routine="kinematic", residuals={}, links_mm=MODEL.links + 1.5
    )
    CalibrationStore(folder).save(cal)
    if edit is not None:
        path = folder / "v0001.json"
        doc = json.loads(path.read_text())
        edit(doc)
        doc["sha256"] = checksum(doc)
        path.write_text(json.dumps(doc, indent=2))
    return folder


def _put(key: str, sub: Any, value: Any) -> Callable[[dict[str, Any]], None]:
    return lambda doc: doc[key].__setitem__(sub, value)


# (key, index or id, value, the text the one line holds)
ABSURD = [
    ("links_mm", 0, 1e300, "links_mm[0] is 1e+300 mm, more than 20 mm from the description's"),
    ("links_mm", 11, 136.0 + 25.0, "links_mm[11] is 161 mm, more than 20 mm"),
    ("links_mm", 3, -5.0, "links_mm[3] is -5.0, not > 0"),
    ("alpha_offset_rad", 4, 1e300, "alpha_offset_rad[4] is 1e+300 rad"),
    ("theta_offset_rad", 0, math.radians(-11.0), "theta_offset_rad[0] is -0.191986 rad (-11 deg)"),
    ("rope_EA_N", "j02r1", 1e300, "rope_EA_N.j02r1 is 1e+300 N, not within 0.25 .. 4 times"),
    ("rope_EA_N", "j02r1", 5000.0, "rope_EA_N.j02r1 is 5000 N"),
    ("motor_zero_counts", "j05r2", 2**30, "motor_zero_counts.j05r2 is 1073741824 counts"),
    ("motor_zero_counts", "j05r2", -200_000, "motor_zero_counts.j05r2 is -200000 counts"),
]


@pytest.mark.parametrize(("key", "sub", "value", "text"), ABSURD)
@pytest.mark.parametrize("command", ["plan", "show"])
def test_an_absurd_calibrated_value_is_one_line_naming_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch,
    command: str, key: str, sub: Any, value: Any, text: str,
) -> None:  # fmt: skip
    monkeypatch.chdir(tmp_path)
    folder = _store(tmp_path, _put(key, sub, value))
    argv = (
        ["plan", "--scenario", "bent-pipe", "--calibrations", str(folder), "--out", "p.json"]
        if command == "plan"
        else ["calibrate", "show", "--calibrations", str(folder)]
    )
    refused(capsys, tmp_path, argv, f"{folder / 'v0001.json'}: {text}")


def test_use_refuses_such_a_version_too(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    folder = _store(tmp_path, _put("links_mm", 0, 1e300))
    argv = ["calibrate", "use", "1", "--calibrations", str(folder)]
    refused(capsys, tmp_path, argv, "v0001.json: links_mm[0] is 1e+300 mm")


def test_values_inside_the_ranges_apply() -> None:
    """Well beyond the simulated arm's perturbations (links 2 mm, offsets 1 deg, EA 20 %,
    zeros 5000 counts) and its truth files' limits (10 mm, 5 deg, 0.5 .. 2, 50 000)."""
    base = nominal_calibration(MODEL)
    ids = base.motor_ids
    cal = updated(
        base,
        routine="manual",
        residuals={},
        links_mm=MODEL.links + np.where(np.arange(12) % 2 == 0, 19.9, -19.9),
        alpha_offset_rad=np.full(12, math.radians(9.9)),
        theta_offset_rad=np.full(12, math.radians(-9.9)),
        rope_EA_N={m: (3.9 if k % 2 else 0.26) * 30000.0 for k, m in enumerate(ids)},
        motor_zero_counts={m: (-1) ** k * 100_000 for k, m in enumerate(ids)},
    )
    check_belongs(MODEL, cal, "v.json")


def test_the_check_is_one_line_in_process() -> None:
    cal = updated(
        nominal_calibration(MODEL), routine="manual", residuals={}, links_mm=MODEL.links * 1e6
    )
    with pytest.raises(CalibrationFileError) as err:
        check_belongs(MODEL, cal, "v0007.json")
    assert str(err.value).startswith("v0007.json: links_mm[0] is 1.79e+08 mm")
    assert "\n" not in str(err.value)
