"""Extreme numbers in a plan file and a PLY of the wrong byte order: one error line.

A plan whose step travel is 1e300 (or -1e300, or 1e-300 from its neighbour) used to pass
the reader and crash the time parameterisation (a NumPy RuntimeWarning, then a scipy
traceback); a big-endian PLY of little-endian floats printed a RuntimeWarning pair before
its error.  Each is now refused with one ``hrm CMD: error:`` line (exit 2), and with
RuntimeWarnings turned into errors nothing warns on the way.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hrm_ctrl.errors import PlanFileError
from hrm_ctrl.formats.planfile import PlanDoc, write_plan
from tests.hrm_ctrl.cli.cli_helpers import small_plan
from tests.hrm_ctrl.cli.test_bad_input import refused

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def _set(doc: dict[str, Any], place: tuple[Any, ...], value: float) -> dict[str, Any]:
    doc = json.loads(json.dumps(doc))  # small_plan's points are one list 13 times
    node = doc
    for key in place[:-1]:
        node = node[key]
    node[place[-1]] = value
    return doc


# (place in the plan, value, the text the one line holds)
EXTREME = [
    (("steps", -1, "travel_mm"), 1e300, "steps[3].travel_mm: 1e+300 is out of range"),
    (("steps", 0, "travel_mm"), -1e300, "steps[0].travel_mm: -1e+300 is out of range"),
    (("steps", -1, "travel_mm"), 1.0e5 + 1.0, "steps[3].travel_mm: 100001 is out of range"),
    (("steps", 1, "travel_mm"), 1e-300, "steps[1].travel_mm: 1e-300 is 1e-300 mm from steps[0]"),
    (("steps", 2, "alpha_rad", 4), 1e300, "steps[2].alpha_rad[4]: 1e+300 is out of range"),
    (("steps", 2, "theta_rad", 0), -4.0, "steps[2].theta_rad[0]: -4 is out of range"),
    (("steps", 1, "joints_mm", 12, 2), 1e300, "steps[1].joints_mm[12][2]: 1e+300 is out"),
    (("path_mm", 1, 0), -1e300, "path_mm[1][0]: -1e+300 is out of range"),
    (("robot", "links_mm", 3), 1e300, "robot.links_mm[3]: 1e+300 is out of range"),
]
IDS = ["travel-1e300", "travel-minus-1e300", "travel-100001", "travel-step-1e-300",
       "alpha", "theta", "joints", "path", "links"]  # fmt: skip


@pytest.mark.parametrize(("place", "value", "text"), EXTREME, ids=IDS)
def test_an_extreme_plan_number_is_one_line_naming_step_and_key(
    place: tuple[Any, ...], value: float, text: str
) -> None:
    doc = _set(small_plan(), place, value)
    with pytest.raises(PlanFileError) as err:
        PlanDoc.from_dict(doc, "p.json")
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("p.json: ") and text in msg, msg


def test_numbers_in_range_still_read() -> None:
    doc = small_plan()
    doc["steps"][1]["travel_mm"] = 1e-6  # the smallest step of travel
    doc["steps"][3]["travel_mm"] = 1.0e5
    doc["steps"][2]["alpha_rad"][0] = np.pi
    doc["path_mm"][0] = [1.0e5, -1.0e5, 0.0]
    plan = PlanDoc.from_dict(doc, "p.json")
    assert plan.travel_mm[1] - plan.travel_mm[0] == pytest.approx(1e-6)


@pytest.mark.parametrize("value", [1e300, -1e300], ids=["last-1e300", "first-minus-1e300"])
@pytest.mark.parametrize("command", ["ropes", "run"])
def test_hrm_refuses_a_plan_with_an_extreme_travel(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch,
    command: str, value: float,
) -> None:  # fmt: skip
    monkeypatch.chdir(tmp_path)
    doc = small_plan()
    step = -1 if value > 0 else 0
    plan = tmp_path / "plan.json"
    write_plan(plan, doc)  # a valid plan, then the number written by hand
    doc["steps"][step]["travel_mm"] = value
    plan.write_text(json.dumps(doc))
    argv = (
        ["ropes", str(plan), "--out", str(tmp_path / "sp.csv")]
        if command == "ropes"
        else ["run", str(plan), "--sim", "--calibrations", str(tmp_path / "cal")]
    )
    k = len(doc["steps"]) - 1 if value > 0 else 0
    refused(capsys, tmp_path, argv, f"steps[{k}].travel_mm: {value:.6g} is out of range")


def test_a_big_endian_ply_of_little_endian_floats_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    pts = np.column_stack(
        [np.linspace(0.0, 300.0, 400), 20 * np.cos(np.arange(400)), 20 * np.sin(np.arange(400))]
    ).astype("<f4")
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 400\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    ply = tmp_path / "scan.ply"
    ply.write_bytes(header.encode() + pts.tobytes())
    # read big-endian, some of these floats are NaNs whose cast to float64 warns
    assert not np.isfinite(pts.view(">f4")).all()
    line = refused(capsys, tmp_path, ["scan", str(ply), "--out", str(tmp_path / "path.csv")])
    assert "scan.ply: vertex " in line and "is not finite" in line, line


def test_an_npy_of_long_doubles_beyond_float64_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    pts = np.zeros((10, 3), dtype=np.longdouble)
    if np.finfo(np.longdouble).max <= np.finfo(np.float64).max:
        pytest.skip("long double is float64 here")
    pts[2, 0] = np.longdouble(np.finfo(np.float64).max) * 4
    npy = tmp_path / "scan.npy"
    np.save(npy, pts)
    line = refused(capsys, tmp_path, ["scan", str(npy)], "scan.npy: row 3: x is not finite")
    assert line
