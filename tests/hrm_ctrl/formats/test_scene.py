"""The scene file reader, and the environment a plan file keeps."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import PlanFileError, PlanningError
from hrm_ctrl.formats.planfile import PlanDoc, read_plan, write_plan
from hrm_ctrl.formats.scene import SceneFileError, read_scene, rotation_zyx, scene_from_dict
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.environment import Box, Pipe, RectOpening, RoundOpening, Wall
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.report import plan_file_clearance
from hrm_ctrl.planning.scenarios import scenario

SCENE = """\
description = "one of each"

[[pipe]]
axis_mm = [[0, 0, 0], [100, 0, 0], [200, 50, 0]]
inner_diameter_mm = 70

[[wall]]
point_mm = [300, 0, 0]
normal = [2, 0, 0]
thickness_mm = 4

  [[wall.opening]]
  shape = "round"
  centre_mm = [300, 0, 0]
  diameter_mm = 80

  [[wall.opening]]
  shape = "rect"
  centre_mm = [300, 0, 200]
  width_mm = 120
  height_mm = 60
  u = [0, 1, 0]

  [[wall.bound]]
  point_mm = [0, 0, -300]
  normal = [0, 0, 1]

[[box]]
centre_mm = [500, 0, 0]
size_mm = [100, 50, 20]
yaw_deg = 30
"""


@pytest.fixture
def scene_file(tmp_path: Path) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(SCENE)
    return p


def test_read_scene_builds_every_kind(scene_file: Path) -> None:
    env = read_scene(scene_file)
    pipe, wall, box = env.obstacles
    assert isinstance(pipe, Pipe) and pipe.inner_diameter == 70.0
    assert pipe.axis.points.shape == (3, 3)
    assert isinstance(wall, Wall) and wall.normal.tolist() == [1.0, 0.0, 0.0]
    assert wall.thickness == 4.0
    assert isinstance(wall.openings[0], RoundOpening) and wall.openings[0].diameter == 80.0
    rect = wall.openings[1]
    assert isinstance(rect, RectOpening) and (rect.width, rect.height) == (120.0, 60.0)
    assert len(wall.bounds) == 1
    assert isinstance(box, Box)
    np.testing.assert_allclose(box.rotation, rotation_zyx(30.0, 0.0, 0.0))
    # a point 10 mm along the box's own x beyond its +x face
    p = box.centre + box.rotation @ np.array([60.0, 0.0, 0.0])
    assert env.free_distance(p) == pytest.approx(10.0)


def test_scene_round_trips_through_its_data(scene_file: Path) -> None:
    env = read_scene(scene_file)
    again = scene_from_dict(json.loads(json.dumps(env.to_dict())))
    q = np.random.default_rng(3).uniform(-100, 700, size=(500, 3))
    np.testing.assert_allclose(again.free_distance(q), env.free_distance(q), atol=1e-9)
    assert again.to_dict() == env.to_dict()


def test_box_rotation_matrix_is_accepted(tmp_path: Path) -> None:
    p = tmp_path / "s.toml"
    p.write_text(
        "[[box]]\ncentre_mm = [0, 0, 0]\nsize_mm = [10, 20, 30]\n"
        "rotation = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]\n"
    )
    (box,) = read_scene(p).obstacles
    assert box.free_distance(np.array([[0.0, 8.0, 0.0]]))[0] == pytest.approx(3.0)


def test_empty_scene_is_free_space(tmp_path: Path) -> None:
    p = tmp_path / "s.toml"
    p.write_text('description = "nothing"\n')
    assert read_scene(p).obstacles == ()


@pytest.mark.parametrize(
    ("text", "place", "what"),
    [
        ("[[tube]]\n", "s.toml", "unknown key 'tube'"),
        ("[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1,1,1]\ncolour = 1\n", "box[0]", "'colour'"),
        (
            '[[wall]]\npoint_mm = [0,0,0]\nnormal = [1,0,0]\n[[wall.opening]]\nshape = "oval"\n',
            "wall[0].opening[0].shape",
            "'oval'",
        ),
        (
            '[[wall]]\npoint_mm = [0,0,0]\nnormal = [1,0,0]\n[[wall.opening]]\nshape = "round"\n'
            "centre_mm = [0,0,0]\ndiameter_mm = -80\n",
            "wall[0].opening[0].diameter_mm",
            "> 0",
        ),
        (
            '[[wall]]\npoint_mm = [0,0,0]\nnormal = [1,0,0]\n[[wall.opening]]\nshape = "rect"\n'
            "centre_mm = [0,0,0]\nwidth_mm = 1\nheight_mm = 1\nu = [1,0,0]\n",
            "wall[0].opening[0].u",
            "normal to its wall",
        ),
        (
            "[[pipe]]\naxis_mm = [[0,0,0],[1,0,0]]\ninner_diameter_mm = nan\n",
            "pipe[0].inner_diameter_mm",
            "finite",
        ),
        (
            "[[pipe]]\naxis_mm = [[0,0,0],[1,0,inf]]\ninner_diameter_mm = 70\n",
            "pipe[0].axis_mm[1][2]",
            "finite",
        ),
        ("[[pipe]]\naxis_mm = [[0,0,0]]\ninner_diameter_mm = 70\n", "pipe[0].axis_mm", "2 points"),
        ("[[pipe]]\naxis_mm = [[0,0],[1,0]]\ninner_diameter_mm = 70\n", "axis_mm[0]", "3 numbers"),
        ("[[pipe]]\naxis_mm = [[0,0,0],[0,0,0]]\ninner_diameter_mm = 7\n", "axis_mm", "distinct"),
        ("[[pipe]]\ninner_diameter_mm = 70\n", "pipe[0]", "missing key 'axis_mm'"),
        ("[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1,0,1]\n", "box[0].size_mm[1]", "> 0"),
        ("[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1,1,1,1]\n", "box[0].size_mm", "3 numbers"),
        ("[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1e308,1,1]\n", "size_mm[0]", "at most 2e+06"),
        ("[[pipe]]\naxis_mm = [[0,0,0],[1,0,0]]\ninner_diameter_mm = 1e308\n", "diameter", "most"),
        ("[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1,1,1]\nyaw_deg = 1e300\n", "yaw_deg", "360"),
        (
            "[[wall]]\npoint_mm = [0,0,0]\nnormal = [1,0,0]\nthickness_mm = 3e6\n",
            "thickness",
            "most",
        ),
        (
            "[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1,1,1]\nyaw_deg = 1\n"
            "rotation = [[1,0,0],[0,1,0],[0,0,1]]\n",
            "box[0]",
            "not both",
        ),
        (
            "[[box]]\ncentre_mm = [0,0,0]\nsize_mm = [1,1,1]\n"
            "rotation = [[2,0,0],[0,1,0],[0,0,1]]\n",
            "box[0]",
            "rotation matrix",
        ),
        ("[[wall]]\npoint_mm = [0,0,0]\nnormal = [0,0,0]\n", "wall[0].normal", "zero vector"),
        ("[[wall]]\npoint_mm = [0,0,0]\nnormal = [1,0,0]\nthickness_mm = -1\n", "thickness", ">="),
        ("[[wall]]\npoint_mm = [0,0,true]\nnormal = [1,0,0]\n", "point_mm[2]", "a number"),
        ("box = 3\n", "box", "array of tables"),
        ("description = 3\n", "description", "a string"),
        ("[[box]\n", "s.toml", "not valid TOML"),
    ],
)
def test_bad_scene_is_one_line_naming_file_table_and_key(tmp_path, text, place, what) -> None:
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(SceneFileError) as err:
        read_scene(p)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(str(p)), msg
    assert place in msg and what in msg, msg
    assert isinstance(err.value, PlanningError)


def test_missing_scene_file(tmp_path: Path) -> None:
    with pytest.raises(SceneFileError, match="scene file not found"):
        read_scene(tmp_path / "none.toml")


# ---- the environment in a plan file --------------------------------------------------


@pytest.fixture(scope="module")
def cabins_doc() -> dict:
    sc = scenario("cabins")
    plan = plan_path(default_robot(), sc.path, PlanOptions(step=20.0), scenario=sc)
    return plan.to_dict()


def test_plan_file_keeps_environment_and_clearance(tmp_path: Path, cabins_doc: dict) -> None:
    p = tmp_path / "plan.json"
    write_plan(p, cabins_doc)
    doc = read_plan(p)
    assert doc.to_dict() == json.loads(json.dumps(cabins_doc))
    env = doc.environment
    assert env is not None and len(env.obstacles) == 2
    c = doc.clearance
    assert c is not None and set(c) >= {"min", "step", "link"}
    # the clearance of the arm recomputed from the file is the stored one
    again = plan_file_clearance(doc)
    assert again is not None and again.shape == (doc.n_steps, 12)
    assert float(again.min()) == pytest.approx(c["min"], abs=1e-9)
    i, j = np.unravel_index(int(np.argmin(again)), again.shape)
    assert (int(i), int(j) + 1) == (c["step"], c["link"])


def test_old_plan_without_environment_is_readable(cabins_doc: dict) -> None:
    old = json.loads(json.dumps(cabins_doc))
    old["scenario"] = {"name": "cabins", "obstacles": []}
    old["report"].pop("clearance_mm")
    doc = PlanDoc.from_dict(old, "old.json")
    assert doc.environment is None and doc.clearance is None
    assert plan_file_clearance(doc) is None


def test_plan_file_with_broken_environment_is_refused(cabins_doc: dict) -> None:
    bad = json.loads(json.dumps(cabins_doc))
    bad["scenario"]["environment"]["wall"][1]["opening"][0]["diameter_mm"] = -1
    with pytest.raises(PlanFileError) as err:
        PlanDoc.from_dict(bad, "p.json")
    assert str(err.value).startswith("p.json: scenario.environment: wall[1].opening[0]")


def test_plan_file_clearance_summary_is_checked_by_the_schema(cabins_doc: dict) -> None:
    bad = json.loads(json.dumps(cabins_doc))
    bad["report"]["clearance_mm"]["min"] = "low"
    with pytest.raises(PlanFileError, match=r"report\.clearance_mm\.min"):
        PlanDoc.from_dict(bad, "p.json")
    bad["report"]["clearance_mm"] = {"min": None, "step": -1, "link": 0}
    assert PlanDoc.from_dict(bad, "p.json").clearance["min"] is None
    assert math.isfinite(cabins_doc["report"]["clearance_mm"]["min"])


# ---- red team (issue 10) ------------------------------------------------------------------


def test_the_pipes_of_a_scene_have_a_bounded_total_length(tmp_path: Path) -> None:
    """Found: 10 pipes of 100 m (650 bytes of TOML) took 106 MB at the first distance query
    (each axis resampled every 0.5 mm), so 1000 of them (65 kB) about 10 GB."""
    p = tmp_path / "s.toml"
    pipe = "[[pipe]]\naxis_mm = [[-50000, {i}, 0], [49999, {i}, 0]]\ninner_diameter_mm = 70\n"
    p.write_text(pipe.format(i=0))
    assert len(read_scene(p).obstacles) == 1  # one pipe of the longest a path may be: fine
    p.write_text(pipe.format(i=0) + pipe.format(i=1))
    with pytest.raises(SceneFileError, match=r"pipe\[1\]\.axis_mm: the pipes' axes are 199998 mm"):
        read_scene(p)
    axis = [[0.001 * k, 0, 0] for k in range(60_000)]  # 60 mm each, 60,000 points
    doc = {"pipe": [{"axis_mm": axis, "inner_diameter_mm": 70}] * 2}
    with pytest.raises(SceneFileError, match=r"pipe\[1\]\.axis_mm: .* 120000 points in all"):
        scene_from_dict(doc, "plan.json: scenario.environment")


@settings(max_examples=40, deadline=None)
@given(
    v=st.lists(
        st.one_of(st.just(0.0), st.floats(1e-300, 1e308), st.floats(-1e308, -1e-300)),
        min_size=3,
        max_size=3,
    ).filter(any)
)
@example(v=[1e308, 1e308, 0.0])  # found: the norm overflowed, the wall's normal became 0
@example(v=[1e-10, 0.0, 0.0])  # found: refused as "the zero vector" (any length > 0 is valid)
def test_a_wall_normal_of_any_length_is_a_unit_normal(v: list[float]) -> None:
    env = scene_from_dict({"wall": [{"point_mm": [0, 0, 0], "normal": v}]}, "s")
    n = env.obstacles[0].normal
    assert abs(float(np.linalg.norm(n)) - 1.0) < 1e-12
    u = np.array(v) / np.abs(v).max()
    assert np.allclose(n, u / np.linalg.norm(u))
    d = env.free_distance(np.array([[0.0, 0, 0], *(10.0 * n)[None]]))
    assert d.tolist() == pytest.approx([0.0, 10.0])


def test_the_openings_of_a_scene_are_bounded_in_all() -> None:
    """Found: 1000 walls of 100 openings each were accepted (as a plan file's environment);
    one distance query of 4000 points then took 16 s, a plan's clearance over an hour."""
    opening = {"shape": "round", "centre_mm": [0, 0, 0], "diameter_mm": 1}
    wall = {"point_mm": [0, 0, 0], "normal": [0, 0, 1], "opening": [opening] * 100}
    assert len(scene_from_dict({"wall": [wall] * 10}).obstacles) == 10  # 1000: fine
    with pytest.raises(SceneFileError, match=r"s: wall\[10\]: 1100 wall openings and bounds"):
        scene_from_dict({"wall": [wall] * 11}, "s")


def test_the_scene_example_of_the_planner_docs_loads(tmp_path: Path) -> None:
    """docs/planner.md's scene file, as printed (its wall bound once lay across the wall:
    refused as 'normal to the wall')."""
    doc = (Path(__file__).resolve().parents[3] / "docs" / "planner.md").read_text()
    start = doc.index("```toml\ndescription = ")
    text = doc[start + len("```toml\n") : doc.index("```", start + 7)]
    path = tmp_path / "scene.toml"
    path.write_text(text)
    env = read_scene(path)
    assert sorted(type(o).__name__ for o in env.obstacles) == ["Box", "Pipe", "Wall"]
