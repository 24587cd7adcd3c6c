"""``hrm-plan/1`` and :class:`PlanDoc`: round trips, schema errors as one line naming the
place, bounded input, and the robot check."""

from __future__ import annotations

import copy
import dataclasses
import json
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hrm_ctrl.errors import PlanFileError
from hrm_ctrl.formats import planfile
from hrm_ctrl.formats.planfile import (
    LINK_TOLERANCE_MM,
    Phase,
    PlanDoc,
    plan_schema,
    read_plan,
    validate_plan,
    write_plan,
)
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario


def hand_plan(n: int = 4) -> dict[str, Any]:
    """A minimal hand-written plan: no phase, ints where floats are usual."""
    robot = default_robot()
    a = np.linspace(0.0, 0.2, n)[:, None] * np.ones((1, 12))
    O = joint_centres(robot, a, -a)
    return {
        "format": "hrm-plan/1",
        "robot": {"links_mm": [int(v) for v in robot.links]},
        "path_mm": [[0, 0, 0], [1, 0, 0]],
        "steps": [
            {
                "travel_mm": 5 * k,
                "alpha_rad": a[k].tolist(),
                "theta_rad": (-a[k]).tolist(),
                "joints_mm": O[k].tolist(),
                "note": f"step {k}",
            }
            for k in range(n)
        ],
        "report": {"by": "hand"},
        "x-tool": {"version": 3},
    }


@pytest.fixture(scope="module")
def planned() -> dict[str, Any]:
    """A planner-made plan with a return leg, as ``hrm plan --return`` writes it."""
    sc = scenario("bent-pipe")
    plan = plan_path(default_robot(), sc.path, PlanOptions(step=20.0, return_to_start=True), sc)
    return json.loads(json.dumps(plan.to_dict()))  # as read back from a file


def test_round_trip_of_a_planner_plan(planned: dict[str, Any], tmp_path: Path) -> None:
    doc = PlanDoc.from_dict(planned, "bp.json")
    assert doc.to_dict() == planned
    assert PlanDoc.from_dict(doc.to_dict()) == doc
    assert doc.phase[0] is Phase.IN and doc.phase[-1] is Phase.RETURN and doc.explicit_phase
    s = doc.n_steps
    assert doc.alpha_rad.shape == doc.theta_rad.shape == (s, 12)
    assert doc.joints_mm.shape == (s, 13, 3) and doc.travel_mm.shape == (s,)
    assert doc.links_mm.shape == (12,) and doc.path_mm.shape[1] == 3
    assert doc.title == "bent-pipe" and doc.report == planned["report"]
    assert doc.distance_mm[-1] == pytest.approx(2 * doc.travel_mm.max())  # in and back
    p = tmp_path / "bp.json"
    write_plan(p, doc)
    again = read_plan(p)
    assert again == doc and again.source == str(p)
    assert json.loads(p.read_text()) == planned


def test_round_trip_keeps_extra_keys_and_no_phase(tmp_path: Path) -> None:
    plan = hand_plan()
    doc = PlanDoc.from_dict(plan)
    assert doc.to_dict() == plan  # ints compare equal to the floats read
    assert not doc.explicit_phase and doc.phase == (Phase.IN,) * 4
    assert doc.step_extra[2] == {"note": "step 2"} and doc.extra == {"x-tool": {"version": 3}}
    p = tmp_path / "hand.json"
    write_plan(p, plan)
    assert json.loads(p.read_text()) == plan and "phase" not in p.read_text()


def test_plan_doc_is_read_only(planned: dict[str, Any]) -> None:
    doc = PlanDoc.from_dict(planned)
    with pytest.raises(ValueError, match="read-only"):
        doc.alpha_rad[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        doc.source = "other"  # type: ignore[misc]
    with pytest.raises(TypeError):
        doc.report["steps"] = 0  # type: ignore[index]
    changed = copy.deepcopy(planned)
    changed["steps"][3]["alpha_rad"][0] += 1e-3
    assert PlanDoc.from_dict(changed) != doc


Mutation = Callable[[dict[str, Any]], Any]

BAD: list[tuple[Mutation, str]] = [
    (lambda p: p.pop("steps"), "plan.json: missing key 'steps'"),
    (lambda p: p.update(format="hrm-plan/0"), "plan.json: format is 'hrm-plan/0', expected"),
    (lambda p: p["robot"].pop("links_mm"), "plan.json: robot: missing key 'links_mm'"),
    (
        lambda p: p["robot"]["links_mm"].append(1.0),
        "plan.json: robot.links_mm: expected an array of 12 numbers, got 13 items",
    ),
    (
        lambda p: p["steps"][3]["alpha_rad"].__setitem__(2, float("nan")),
        "plan.json: steps[3].alpha_rad[2]: expected a finite number, got nan",
    ),
    (
        lambda p: p["steps"][3]["alpha_rad"].__setitem__(2, "0.1"),
        "plan.json: steps[3].alpha_rad[2]: expected a number, got '0.1'",
    ),
    (
        lambda p: p["steps"][1]["joints_mm"][4].__setitem__(2, float("-inf")),
        "plan.json: steps[1].joints_mm[4][2]: expected a finite number, got -inf",
    ),
    (
        lambda p: p["steps"][2]["joints_mm"].pop(),
        "plan.json: steps[2].joints_mm: expected an array of 13 points [x, y, z], got 12 items",
    ),
    (
        lambda p: p["steps"][2].update(travel_mm=True),
        "plan.json: steps[2].travel_mm: expected a number, got True",
    ),
    (
        lambda p: p["steps"][2].update(phase="out"),
        "plan.json: steps[2].phase: expected one of 'in', 'return', got 'out'",
    ),
    (
        lambda p: p["steps"][1].pop("phase"),
        "plan.json: steps[1]: missing key 'phase' (give it on every step or on none)",
    ),
    (lambda p: p.update(path_mm=[[0, 0, 0]]), "plan.json: path_mm: expected an array of at least"),
    (lambda p: p.update(report=None), "plan.json: report: expected an object, got None"),
    (
        lambda p: p["robot"].update(joint_limits_deg={"alpha": 0}),
        "plan.json: robot.joint_limits_deg.alpha: expected a number > 0, got 0",
    ),
    (
        lambda p: p["steps"][0].update(backbone_mm=[[1.0, 2.0, float("nan")]]),
        "plan.json: steps[0].backbone_mm[0][2]: expected a finite number, got nan",
    ),
]


@pytest.mark.parametrize(("mutate", "message"), BAD, ids=[m for _, m in BAD])
def test_schema_errors_are_one_line_naming_the_place(
    planned: dict[str, Any], mutate: Mutation, message: str
) -> None:
    bad = copy.deepcopy(planned)
    mutate(bad)
    with pytest.raises(PlanFileError) as info:
        PlanDoc.from_dict(bad, "plan.json")
    assert str(info.value).startswith(message) and "\n" not in str(info.value)
    with pytest.raises(PlanFileError):
        validate_plan(bad, "plan.json")
    assert validate_plan(planned) is planned


def test_not_an_object() -> None:
    with pytest.raises(PlanFileError, match=r"^p\.json: expected a JSON object, got \[1, 2\]$"):
        PlanDoc.from_dict([1, 2], "p.json")


@pytest.mark.parametrize("mutate", [m for m, _ in BAD])
def test_the_quick_array_check_agrees_with_jsonschema(
    planned: dict[str, Any], mutate: Mutation
) -> None:
    """The reader's shortcut for arrays of numbers finds what plain jsonschema finds."""
    bad = copy.deepcopy(planned)
    mutate(bad)
    plain = jsonschema.Draft202012Validator(plan_schema())
    want = [list(e.absolute_path) for e in plain.iter_errors(bad)]
    got = [list(e.absolute_path) for e in planfile._validator().iter_errors(bad)]
    assert got == want


def test_the_schema_is_package_data_and_valid() -> None:
    text = resources.files("hrm_ctrl.formats").joinpath("hrm-plan-1.schema.json").read_text()
    schema = json.loads(text)
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema == plan_schema()
    assert schema["properties"]["format"] == {"const": "hrm-plan/1"}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[" * 100_000, "not a plan (JSON nested too deeply)"),
        ('{"format": "hrm-plan/1", "report": ' + "[" * 100_000, "nested too deeply"),
        ('{"n": 1' + "0" * 5000 + "}", "line 1: integer 100000000000...(5001 digits) is too"),
        ("{not json", "not JSON (line 1"),
        ("", "not JSON"),
    ],
    ids=["deep", "deep-inside", "huge-int", "syntax", "empty"],
)
def test_bad_files_are_one_line(tmp_path: Path, text: str, message: str) -> None:
    p = tmp_path / "plan.json"
    p.write_text(text)
    with pytest.raises(PlanFileError) as info:
        read_plan(p)
    assert str(info.value).startswith(f"{p}: ") and message in str(info.value)
    assert "\n" not in str(info.value)


def test_too_large_a_file_is_refused_unread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    p = tmp_path / "plan.json"
    write_plan(p, hand_plan())
    monkeypatch.setattr(planfile, "MAX_PLAN_BYTES", 100)
    with pytest.raises(PlanFileError, match=r"plan file is \d+ bytes, more than the 100"):
        read_plan(p)
    with pytest.raises(PlanFileError, match="plan file not found"):
        read_plan(tmp_path / "none.json")


def test_too_many_steps_or_path_points_refused_before_the_schema(tmp_path: Path) -> None:
    """A plan within the file size but with more steps than a plan may have (400 000 small
    steps took 79 s and 5.4 GB in ``hrm ropes``) or more path points than a path: one line,
    counted before the schema or the arrays see them (the steps here are not even valid)."""
    from hrm_ctrl.planning.known_path import MAX_PATH_POINTS

    doc = hand_plan()
    doc["steps"] = [0] * (planfile.MAX_PLAN_STEPS + 1)
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(PlanFileError, match=r"plan\.json: steps: 20001 items, more than 20000$"):
        read_plan(p)
    doc = hand_plan()
    doc["path_mm"] = [[0, 0, 0]] * (MAX_PATH_POINTS + 1)
    p.write_text(json.dumps(doc))
    with pytest.raises(PlanFileError, match=rf"path_mm: {MAX_PATH_POINTS + 1} items, more than"):
        read_plan(p)


def test_write_refuses_what_json_cannot_hold(tmp_path: Path) -> None:
    plan = hand_plan()
    plan["report"]["error"] = float("nan")
    with pytest.raises(PlanFileError, match="cannot write plan file"):
        write_plan(tmp_path / "p.json", plan)
    assert not (tmp_path / "p.json").exists()
    plan["report"]["error"] = 0.0
    plan["steps"][0]["alpha_rad"][0] = float("inf")
    with pytest.raises(PlanFileError, match=r"steps\[0\]\.alpha_rad\[0\]: expected a finite"):
        write_plan(tmp_path / "p.json", plan)


def test_check_robot_within_the_tolerance() -> None:
    robot = default_robot()
    plan = hand_plan()
    plan["robot"]["links_mm"] = [float(v) for v in robot.links + 0.5 * LINK_TOLERANCE_MM]
    PlanDoc.from_dict(plan, "p.json").check_robot(robot)
    plan["robot"]["links_mm"][4] += 2 * LINK_TOLERANCE_MM
    with pytest.raises(PlanFileError) as info:
        PlanDoc.from_dict(plan, "p.json").check_robot(robot)
    msg = str(info.value)
    assert msg.startswith("p.json: plan was made for links [") and robot.source in msg
    assert "\n" not in msg


@given(
    length=st.floats(min_value=1e-9, max_value=2000.0),
    step=st.floats(min_value=1e-5, max_value=50.0),
)
@example(length=10.0000001, step=5.0)  # a remainder of 1e-7 mm made an unwritable plan
@example(length=9.7e-8, step=5.0)  # a path shorter than a plan's smallest step
@example(length=1e-3, step=1e-5)
@example(length=1.00000199, step=1e-5)  # a remainder of 1.99e-6 mm, rounded
def test_every_travel_schedule_is_a_plan_files(length: float, step: float) -> None:
    """The planner's travels start at 0 (or are the one end point), end at the path's end,
    never go back, and two consecutive ones differ by 0 or by at least
    MIN_TRAVEL_STEP_MM, as a plan file requires (checked by the file's own check)."""
    from hrm_ctrl.errors import PlanningError
    from hrm_ctrl.planning.planner import travel_schedule

    try:
        d = travel_schedule(length, step)
    except PlanningError as exc:
        assert "more than the" in str(exc)
        return
    assert d[-1] == length and (d[0] == 0.0 or len(d) == 1) and (np.diff(d) >= 0).all()
    planfile._check_travel_steps(d, "plan")


def test_the_schema_states_the_phase_rule() -> None:
    """'phase' on every step or on none: a plan with it on half its steps is refused by the
    schema itself (any JSON Schema validator, as another tool checks a plan), and by the
    reader in one line naming the first step without it."""
    plain = jsonschema.Draft202012Validator(plan_schema())
    none, every, half = hand_plan(), hand_plan(), hand_plan()
    for k, step in enumerate(every["steps"]):
        step["phase"] = "in"
        if k % 2 == 0:
            half["steps"][k]["phase"] = "in"
    assert plain.is_valid(none) and plain.is_valid(every)
    assert not plain.is_valid(half)
    with pytest.raises(PlanFileError) as info:
        PlanDoc.from_dict(half, "plan.json")
    assert str(info.value) == (
        "plan.json: steps[1]: missing key 'phase' (give it on every step or on none)"
    )
