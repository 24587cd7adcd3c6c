"""The URDF export checked by an independent URDF library (yourdfpy).

yourdfpy parses the file and computes forward kinematics with its own scene
graph; its joint centres and frames must equal ``kinematics.frames``.
"""

from __future__ import annotations

import io
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl import kinematics
from hrm_ctrl.cli import main
from hrm_ctrl.formats.urdf import joint_names, link_names, robot_urdf, rotation_rpy, rpy_rotation
from hrm_ctrl.model import RobotModel, default_robot, load_robot

yourdfpy = pytest.importorskip("yourdfpy")

TOL_MM = 1e-6
MOUNTED_TOML = """
name = "mounted"
links_mm = [150, 160, 170, 179, 179, 179, 179, 179, 179, 130, 120, 101.5]
outer_diameter_mm = [40, 40, 36, 36, 30, 30, 30, 30, 30, 26, 26, 20]
[joint_limits]
alpha_deg = 45.0
theta_deg = 70.0
[base]
position_mm = [120.5, -80.0, 310.25]
yaw_deg = {yaw}
pitch_deg = {pitch}
"""


def load_urdf(model: RobotModel) -> yourdfpy.URDF:
    return yourdfpy.URDF.load(
        io.StringIO(robot_urdf(model)), load_meshes=False, build_collision_scene_graph=False
    )


def mounted_robot(tmp_path: Path, yaw: float, pitch: float) -> RobotModel:
    path = tmp_path / f"mounted_{yaw}_{pitch}.toml"
    path.write_text(MOUNTED_TOML.format(yaw=yaw, pitch=pitch))
    return load_robot(path)


def urdf_frames(urdf: yourdfpy.URDF, model: RobotModel, alpha, theta):
    """(R (12,3,3), O (13,3) in mm) of the paper's frames, computed by yourdfpy.

    trimesh's scene graph keeps a joint's old transform when the new one differs by
    less than 1e-8 (``EnforcedForest.add_edge``), so an angle of 1e-9 rad after 0
    would be ignored: go through a configuration 0.5 rad away first.
    """
    cfg = {}
    for i in range(model.n_joints):
        cfg[f"j{i + 1}_alpha"] = float(alpha[i])
        cfg[f"j{i + 1}_theta"] = float(theta[i])
    urdf.update_cfg({name: q + 0.5 for name, q in cfg.items()})
    urdf.update_cfg(cfg)
    T = np.array([urdf.get_transform(name, "world") for name in link_names(model)])
    return T[:-1, :3, :3], T[:, :3, 3] * 1000.0


def not_tiny(q: float) -> bool:
    """trimesh's ``SceneGraph.get`` drops every joint transform within 1e-8 of the
    identity, so yourdfpy reads an angle of, say, 1e-9 rad as 0: keep such angles out."""
    return q == 0.0 or abs(q) > 1e-7


def angles(model: RobotModel, n: int = 12):
    """Random angles strictly inside the joint limits."""
    a = st.floats(-0.999 * model.limit_alpha, 0.999 * model.limit_alpha).filter(not_tiny)
    t = st.floats(-0.999 * model.limit_theta, 0.999 * model.limit_theta).filter(not_tiny)
    return st.tuples(st.lists(a, min_size=n, max_size=n), st.lists(t, min_size=n, max_size=n))


DEFAULT = default_robot()
DEFAULT_URDF = load_urdf(DEFAULT)


@settings(max_examples=40, deadline=None)
@given(angles(DEFAULT))
def test_yourdfpy_fk_equals_kinematics(at) -> None:
    alpha, theta = np.array(at[0]), np.array(at[1])
    R_urdf, O_urdf = urdf_frames(DEFAULT_URDF, DEFAULT, alpha, theta)
    R, O = kinematics.frames(DEFAULT, alpha, theta)
    assert np.abs(O_urdf - O).max() < TOL_MM  # every joint centre and the end point
    assert np.abs(R_urdf - R).max() < 1e-12


def test_zero_configuration_lies_along_x0_with_x_up() -> None:
    R, O = urdf_frames(DEFAULT_URDF, DEFAULT, np.zeros(12), np.zeros(12))
    assert np.allclose(O[-1], [2007.0, 0.0, 0.0], atol=1e-9)
    assert np.allclose(R[0][:, 0], [0.0, 0.0, 1.0], atol=1e-15)  # frame 1's x points up


@settings(max_examples=20, deadline=None)
@given(
    yaw=st.sampled_from([0.0, 30.0, -135.0, 180.0]),
    pitch=st.sampled_from([0.0, -20.0, 45.0, 89.9999999, 90.0, -90.0]),
    data=st.data(),
)
def test_base_mounting_and_custom_links(tmp_path_factory, yaw, pitch, data) -> None:
    model = mounted_robot(tmp_path_factory.mktemp("robot"), yaw, pitch)
    at = data.draw(angles(model))
    alpha, theta = np.array(at[0]), np.array(at[1])
    R_urdf, O_urdf = urdf_frames(load_urdf(model), model, alpha, theta)
    R, O = kinematics.frames(model, alpha, theta)
    assert np.abs(O_urdf - O).max() < TOL_MM
    assert np.abs(R_urdf - R).max() < 1e-12


def test_joints_limits_and_geometry_match_the_model(tmp_path: Path) -> None:
    model = mounted_robot(tmp_path, 10.0, 5.0)
    urdf = load_urdf(model)
    assert urdf.validate(), urdf.errors
    assert urdf.base_link == "world"
    assert urdf.actuated_joint_names == joint_names(model)
    for i in range(model.n_joints):
        ja, jt = urdf.joint_map[f"j{i + 1}_alpha"], urdf.joint_map[f"j{i + 1}_theta"]
        assert ja.type == jt.type == "revolute"
        assert np.array_equal(ja.axis, [0, 1, 0]) and np.array_equal(jt.axis, [1, 0, 0])
        assert ja.child == jt.parent == f"cross{i + 1}"
        assert (ja.limit.lower, ja.limit.upper) == (-model.limit_alpha, model.limit_alpha)
        assert (jt.limit.lower, jt.limit.upper) == (-model.limit_theta, model.limit_theta)
        link = urdf.link_map[f"link{i + 1}"]
        cyl = link.visuals[0].geometry.cylinder
        assert math.isclose(cyl.length * 1000.0, model.links[i], rel_tol=1e-15)
        assert math.isclose(cyl.radius * 2000.0, model.outer_diameter[i], rel_tol=1e-15)
        assert link.inertial is not None and link.inertial.mass > 0.0
        assert urdf.link_map[f"cross{i + 1}"].inertial is not None


@settings(max_examples=200, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-math.pi / 2, math.pi / 2), st.floats(-3.1, 3.1))
def test_rotation_rpy_round_trips(roll, pitch, yaw) -> None:
    R = rpy_rotation(roll, pitch, yaw)
    assert np.abs(rpy_rotation(*rotation_rpy(R)) - R).max() < 1e-14


# --- the command ----------------------------------------------------------------------------


def test_cli_writes_the_urdf_file(tmp_path: Path, capsys) -> None:
    out = tmp_path / "arm.urdf"
    out.write_text("old contents")  # replaced, not appended to
    assert main(["urdf", "--out", str(out)]) == 0
    assert out.read_text() == robot_urdf(DEFAULT)
    ET.fromstring(out.read_text().encode())  # well-formed XML
    assert capsys.readouterr().out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm.urdf"]  # no temp file left


def test_cli_writes_stdout_without_out(capsys) -> None:
    assert main(["urdf"]) == 0
    assert capsys.readouterr().out == robot_urdf(DEFAULT)


def test_cli_uses_the_robot_file(tmp_path: Path) -> None:
    robot = tmp_path / "r.toml"
    robot.write_text(MOUNTED_TOML.format(yaw=0.0, pitch=0.0))
    out = tmp_path / "r.urdf"
    assert main(["urdf", "--robot", str(robot), "--out", str(out)]) == 0
    assert '<robot name="mounted">' in out.read_text()


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("this is = not [toml", "not valid TOML"),
        ('name = "x"\nlinks_mm = [1, 2, 3]\n', "links_mm"),
        (MOUNTED_TOML.format(yaw=0, pitch=0).replace("150,", "-150,"), "links_mm[0]"),
        (MOUNTED_TOML.format(yaw=0, pitch=0).replace("120.5", '"a"'), "position_mm[0]"),
        # a name XML cannot carry (before: written, a file no XML parser reads)
        (MOUNTED_TOML.format(yaw=0, pitch=0).replace('"mounted"', '"a\\u0000b"'), "U+0000"),
    ],
)
def test_cli_bad_robot_file(tmp_path: Path, capsys, content: str, needle: str) -> None:
    robot = tmp_path / "bad.toml"
    robot.write_text(content)
    out = tmp_path / "arm.urdf"
    assert main(["urdf", "--robot", str(robot), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hrm urdf: error: ")
    assert str(robot) in err and needle in err
    assert "Traceback" not in err
    assert not out.exists()


def test_cli_missing_robot_file_and_unwritable_out(tmp_path: Path, capsys) -> None:
    assert main(["urdf", "--robot", str(tmp_path / "nope.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not found" in err
    out = tmp_path / "no_such_dir" / "arm.urdf"
    assert main(["urdf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(out) in err
    assert not out.parent.exists()
