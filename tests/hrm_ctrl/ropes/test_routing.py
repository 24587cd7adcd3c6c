"""Routing in the robot description: defaults, 4 ropes, and every bad input."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hrm_ctrl.errors import HrmError, RopeError
from hrm_ctrl.model import robot_from_dict
from hrm_ctrl.ropes.actuation import load_actuation
from hrm_ctrl.ropes.routing import RoutingError, routing_from_model
from tests.hrm_ctrl.ropes.rope_helpers import default_doc, robot_with


def test_default_routing_36_ropes_spread_10_degrees() -> None:
    rt = routing_from_model(robot_with())
    assert rt.n_ropes == 36
    deg = np.sort(np.rad2deg(rt.hole_angle))
    np.testing.assert_allclose(np.diff(deg), 10.0, atol=1e-9)
    assert rt.rope_ids[3] == "j02r0" and rt.joint_of_rope.tolist() == sorted(rt.joint_of_rope)


def test_missing_tables_fall_back_to_the_documented_defaults() -> None:
    doc = default_doc()
    doc.pop("ropes")
    doc.pop("motors")
    a = load_actuation(robot_from_dict(doc, "<no rope tables>"))
    b = load_actuation(robot_with())
    np.testing.assert_array_equal(a.routing.hole_angle, b.routing.hole_angle)
    np.testing.assert_array_equal(a.counts_max, b.counts_max)


def test_four_ropes_per_joint_work() -> None:
    a = load_actuation(robot_with({"per_joint": 4, "joint_step_deg": None}))
    assert a.n_motors == 48 and a.motor_ids[-1] == "j12r3"
    deg = np.sort(np.rad2deg(a.routing.hole_angle))
    np.testing.assert_allclose(np.diff(deg), 7.5, atol=1e-9)


def test_mixed_rope_counts_per_joint() -> None:
    per = [3] * 6 + [4] * 6
    a = load_actuation(robot_with({"per_joint": per, "joint_step_deg": None}))
    assert a.n_motors == 42
    assert np.bincount(a.joint_of_motor).tolist() == per


def _explicit(angles: list[list[float]]) -> dict[str, Any]:
    return {"angles_deg": angles}


@pytest.mark.parametrize(
    ("ropes", "match"),
    [
        (
            _explicit(
                [[0.0, 120.0, 240.0]]
                + [[10.0 * k, 10.0 * k + 120, 10.0 * k + 240] for k in range(1, 12)]
            ),
            None,
        ),
        (_explicit([[0.0, 120.0, 240.0]] * 12), "j01r0 and j02r0 share a hole"),
        (
            _explicit(
                [[0.0, 120.0, 240.0], [3.0, 123.0, 243.0]]
                + [[10.0 * k, 10.0 * k + 120, 10.0 * k + 240] for k in range(2, 12)]
            ),
            "share a hole",
        ),
        ({"hole_radius_mm": 14.8}, "outside the 30 mm disk"),
        ({"joint_step_deg": 0.0}, "share a hole"),
        ({"per_joint": 1}, "per_joint"),
        ({"per_joint": [3] * 11}, "per_joint"),
        ({"per_joint": 3.0}, "per_joint"),
        ({"hole_radius_mm": float("nan")}, "hole_radius_mm"),
        ({"proximal_disk_mm": -1.0}, "proximal_disk_mm"),
        ({"distal_disk_mm": [12.0] * 5}, "distal_disk_mm"),
        ({"stiffness_EA_N": "stiff"}, "stiffness_EA_N"),
        ({"colour": "red"}, "unknown key 'colour'"),
        ({"proximal_disk_mm": 150.0}, r"link 10 \(130 mm\) is shorter than the disks"),
        ({"angles_deg": [[0.0, 120.0]] * 12}, r"angles_deg\[0\]"),
        # absurd magnitudes: refused at load (before: 1e300 reached the rope model)
        ({"stiffness_EA_N": 1e300}, r"stiffness_EA_N: must be <= 1e\+09"),
        # a rope softer than 1e3 N: all-zero setpoints and an overflow warning before
        ({"stiffness_EA_N": 1e-300}, r"stiffness_EA_N: must be >= 1000"),
        ({"stiffness_EA_N": 999.0}, r"stiffness_EA_N: must be >= 1000"),
        ({"stiffness_EA_N": 1000.0}, None),
        ({"pretension_N": 1e300}, r"pretension_N: must be <= 100000"),
        ({"box_length_mm": 1e300}, r"box_length_mm: must be <= 10000"),
        ({"proximal_disk_mm": 1e300}, r"proximal_disk_mm: must be <= 10000"),
        # the modelled tension a lead-in, jog or stop may give: holds the pretension
        ({"command_tension_N": [10.0, 100.0]}, None),
        ({"command_tension_N": [5.0, 20.0]}, r"\[5, 20\] N must hold the pretension of 30 N"),
        ({"command_tension_N": 100.0}, r"command_tension_N: must be \[low, high\]"),
        ({"command_tension_N": [10.0, 700.0]}, r"command_tension_N\[1\]: must be <= 650"),
        ({"command_tension_N": [-1.0, 100.0]}, r"command_tension_N\[0\]: must be >= 0"),
        ({"command_tension_N": [10.0, float("nan")]}, r"command_tension_N\[1\]: expected a fin"),
        ({"pretension_N": 1000.0}, None),  # its own top (the board reads 655 N at most)
        ({"command_tension_N": [10.0, 650.0]}, None),
    ],
)
def test_bad_routing_is_one_line_rope_error(ropes: dict[str, Any], match: str | None) -> None:
    robot = robot_with(ropes)
    if match is None:
        assert load_actuation(robot).n_motors == 36
        return
    with pytest.raises(RoutingError, match=match) as info:
        load_actuation(robot)
    assert isinstance(info.value, RopeError) and isinstance(info.value, HrmError)
    assert "\n" not in str(info.value) and "<test>" in str(info.value)


def test_thinner_link_rejects_holes_of_the_ropes_passing_it() -> None:
    doc = default_doc()
    doc["outer_diameter_mm"] = [30.0] * 11 + [24.0]
    with pytest.raises(RoutingError, match=r"j12r0.*24 mm disk"):
        load_actuation(robot_from_dict(doc, "<thin>"))


def test_command_tension_defaults_follow_the_pretension() -> None:
    assert routing_from_model(robot_with()).command_tension_N == (10.0, 120.0)
    assert routing_from_model(robot_with({"pretension_N": 3.0})).command_tension_N == (1.0, 23.0)
    band = routing_from_model(robot_with({"command_tension_N": [12, 90]})).command_tension_N
    assert band == (12.0, 90.0) and all(isinstance(v, float) for v in band)
    high = routing_from_model(robot_with({"pretension_N": 700.0})).command_tension_N
    assert high == (pytest.approx(233.333, abs=1e-3), 700.0)
