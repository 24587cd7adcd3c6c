"""Path conditioning: the bend a joint can make, where a path asks more, rounding corners."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import PlanningError
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.conditioning import (
    bend_limit,
    check_path,
    joint_bend,
    round_corners,
    smallest_bend_radius,
)
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.scenarios import scenario

A = np.array([1200.0, 100.0, 300.0])
B = np.array([1470.0, 190.0, 300.0])
C = np.array([1470.0, -50.0, 200.0])
ROBOT = default_robot()


def turns(points: np.ndarray) -> np.ndarray:
    d = np.diff(points, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("ij,ij->i", d[:-1], d[1:]), -1.0, 1.0))


@given(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5))
def test_the_combined_bend_is_at_least_either_angle(alpha: float, theta: float) -> None:
    # so |alpha|, |theta| < limit whenever the bend is below the smaller limit
    phi = float(joint_bend(np.float64(alpha), np.float64(theta)))
    assert phi >= max(abs(alpha), abs(theta)) - 1e-12
    # the next link's direction, Rot_y(alpha) Rot_x(theta) z (Eq. 1), makes that angle with z
    ca, sa, ct, s_t = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    Ry = np.array([[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]])
    Rx = np.array([[1, 0, 0], [0, ct, -s_t], [0, s_t, ct]])
    z = Ry @ Rx @ np.array([0.0, 0.0, 1.0])
    assert math.atan2(math.hypot(z[0], z[1]), z[2]) == pytest.approx(phi, abs=1e-12)


def test_smallest_bend_radius_of_equal_links_is_l_over_2_sin_half_the_limit() -> None:
    assert smallest_bend_radius(ROBOT) == pytest.approx(179.0 / (2 * math.sin(math.pi / 6)))
    arm = dataclasses.replace(
        ROBOT, links=np.full(12, 100.0), limit_alpha=math.radians(45), limit_theta=1.0
    )
    assert bend_limit(arm) == pytest.approx(math.radians(45))
    assert smallest_bend_radius(arm) == pytest.approx(100.0 / (2 * math.sin(math.radians(22.5))))


def test_the_cabins_corner_is_found_where_it_is() -> None:
    path = KnownPath.from_points(np.array([A, B, C]), source="cabins, sharp")
    c = check_path(ROBOT, path)
    corner = float(np.linalg.norm(B - A))
    assert not c.ok
    assert c.corner_travel == pytest.approx(corner, abs=1e-6)
    assert c.local_radius == 0.0
    assert c.bend_required > c.bend_available == pytest.approx(math.radians(60))
    # the first joint that cannot bend enough sits within its link of the corner
    assert c.joint == 12 and corner - ROBOT.links[11] <= c.travel < corner
    np.testing.assert_allclose(c.point, path.point_at(c.travel))
    assert c.max_bend == pytest.approx(math.radians(107.0), abs=math.radians(0.5))
    assert c.max_bend_travel == pytest.approx(corner, abs=0.5)
    assert "cannot follow" in c.message() and "sharp corner" in c.message()


def test_rounding_the_cabins_corner_reproduces_the_scenario_and_makes_it_passable() -> None:
    sharp = KnownPath.from_points(np.array([A, B, C]))
    rounded = round_corners(sharp, 150.0)
    ref = scenario("cabins").path
    assert rounded.points.shape == ref.points.shape
    np.testing.assert_allclose(rounded.points, ref.points, atol=1e-6, rtol=0)
    c = check_path(ROBOT, rounded)
    assert c.ok and c.travel is None
    # joint 12 on the 150 mm arc between links of 130 and 136 mm: asin(130/300) + asin(136/300)
    expected = math.asin(130 / 300) + math.asin(136 / 300)
    assert c.max_bend == pytest.approx(expected, abs=math.radians(0.05))
    assert "can follow" in c.message()


@pytest.mark.parametrize("name", ["bent-pipe", "cabins"])
def test_the_reference_scenarios_pass(name: str) -> None:
    c = check_path(ROBOT, scenario(name).path)
    assert c.ok and c.max_bend < c.bend_available


def test_a_straight_path_passes_without_bending() -> None:
    c = check_path(ROBOT, KnownPath.from_points(np.array([[0, 0, 0], [500, 200, -100]], float)))
    assert c.ok and c.max_bend == pytest.approx(0.0, abs=1e-9)


def test_a_path_shorter_than_the_tip_link_asks_no_joint_anything() -> None:
    P = KnownPath.from_points(np.array([[0, 0, 0], [50, 0, 0], [50, 50, 0]], float))
    c = check_path(ROBOT, P)
    assert c.ok and c.max_bend == 0.0


def arc_path(R: float, turn_deg: float, lead: float = 300.0) -> tuple[KnownPath, float, float]:
    """Straight ``lead``, an arc of R through turn_deg (1 deg samples), straight ``lead``;
    and the travel where the arc starts and ends."""
    psi = np.radians(np.linspace(0.0, turn_deg, int(turn_deg) + 1))
    arc = np.column_stack((lead + R * np.sin(psi), R - R * np.cos(psi), np.zeros_like(psi)))
    d = np.array([math.cos(psi[-1]), math.sin(psi[-1]), 0.0])
    pts = np.vstack(([0.0, 0.0, 0.0], arc, arc[-1] + lead * d))
    P = KnownPath.from_points(pts, source="arc")
    return P, lead, float(P.s[-2])


def test_a_too_tight_arc_is_reported_with_its_travel() -> None:
    P, start, end = arc_path(60.0, 120.0)
    c = check_path(ROBOT, P)
    assert not c.ok
    assert start - ROBOT.links.max() <= c.travel <= end
    assert start <= c.corner_travel <= end
    assert c.local_radius == pytest.approx(60.0, rel=1e-3)
    assert c.bend_required > math.radians(60)
    # at R 150 joint 10 (links of 179 and 130 mm) reaches the arc: on a whole circle it would
    # bend 62.3 deg; a bend of radius 200 (> 179 mm, the smallest) passes
    c150 = check_path(ROBOT, arc_path(150.0, 120.0)[0])
    assert not c150.ok and c150.joint == 10
    assert math.radians(60) < c150.max_bend <= math.asin(179 / 300) + math.asin(130 / 300)
    assert check_path(ROBOT, arc_path(200.0, 120.0)[0]).ok


@settings(max_examples=30, deadline=None)
@given(
    turn=st.floats(5.0, 170.0),
    R=st.floats(5.0, 150.0),
    tilt=st.floats(-1.0, 1.0),
)
@example(turn=107.0, R=150.0, tilt=0.0)
@example(turn=5.000000000000001, R=5.0, tilt=0.0)  # found: 5 or 6 arc samples
def test_round_corners_puts_an_arc_of_the_radius_tangent_to_both_legs(
    turn: float, R: float, tilt: float
) -> None:
    b = math.radians(turn)
    assume(R * math.tan(b / 2) < 999.0)
    d2 = np.array([math.cos(b), math.sin(b) * math.cos(tilt), math.sin(b) * math.sin(tilt)])
    P0, P1 = np.zeros(3), np.array([1000.0, 0, 0])
    P = KnownPath.from_points(np.array([P0, P1, P1 + 1000.0 * d2]))
    Q = round_corners(P, R)
    assert turns(Q.points).max() <= math.radians(1.0) + 1e-9
    t = R * math.tan(b / 2)
    assert Q.length == pytest.approx(P.length - 2 * t + R * b, rel=1e-4)
    # the arc's midpoint lies R / cos(b/2) - R from the corner, every arc point R from its centre
    n = d2 - (d2 @ [1, 0, 0]) * np.array([1.0, 0, 0])
    centre = P1 - t * np.array([1.0, 0, 0]) + R * n / np.linalg.norm(n)
    on_arc = Q.points[1:-1]
    np.testing.assert_allclose(np.linalg.norm(on_arc - centre, axis=1), R, rtol=1e-9)
    D = R / math.cos(b / 2)  # corner to centre; the arc's samples are <= 1 deg apart
    half_step = b / max(2, math.ceil(turn - 1e-6)) / 2  # the coarsest sampling it may have
    nearest = np.linalg.norm(Q.points - P1, axis=1).min()
    far = math.sqrt(D * D + R * R - 2 * D * R * math.cos(half_step))
    assert D - R - 1e-9 <= nearest <= far + 1e-9


def test_round_corners_refuses_a_segment_too_short_naming_the_corner() -> None:
    P = KnownPath.from_points(
        np.array([[0, 0, 0], [100, 0, 0], [100, 40, 0], [200, 40, 0]], float), source="p.csv"
    )
    with pytest.raises(PlanningError, match=r"^p\.csv: corner 2 \(point 3 at \(100, 40, 0\)"):
        round_corners(P, 30.0)  # 30 + 30 mm of the 40 mm segment
    assert len(round_corners(P, 20.0).points) > 4  # 20 + 20 fit exactly
    with pytest.raises(PlanningError, match="turns back on itself"):
        round_corners(KnownPath.from_points(np.array([[0, 0, 0], [9, 0, 0], [1, 0, 0]], float)), 1)
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(PlanningError, match="corner radius"):
            round_corners(P, bad)


def test_round_corners_keeps_straight_vertices_and_rounds_every_corner() -> None:
    pts = np.array([[0, 0, 0], [100, 0, 0], [200, 0, 0], [200, 200, 0], [400, 200, 0]], float)
    Q = round_corners(KnownPath.from_points(pts), 50.0)
    assert any(np.allclose(q, [100, 0, 0]) for q in Q.points)
    assert turns(Q.points).max() <= math.radians(1.0) + 1e-9
    assert Q.length == pytest.approx(600.0 - 2 * (100.0 - 50.0 * math.pi / 2), rel=1e-4)
    # still too sharp: 90 deg within 79 mm of path, less than a 130 mm link
    c = check_path(ROBOT, Q)
    assert not c.ok and c.local_radius == pytest.approx(50.0, rel=1e-3)


def zigzag(n: int, turn_deg: float, segment_mm: float = 1.0) -> KnownPath:
    """n points, every interior vertex turning by turn_deg, segments of segment_mm."""
    half = math.radians(90.0 - turn_deg / 2.0)
    dx, dy = segment_mm * math.sin(half), segment_mm * math.cos(half)
    k = np.arange(n)
    return KnownPath.from_points(np.column_stack((k * dx, np.where(k % 2, dy, 0.0), 0 * k)))


def test_round_corners_refuses_too_many_points_before_making_them() -> None:
    """Found: a path file of 100,000 points zigzagging by 170 deg with --round-corners 0.01
    built 17 million arc points (3.6 GB, 16 s) before the path refused them."""
    P = zigzag(5_000, 170.0)
    with pytest.raises(PlanningError, match=r"would give \d+ points, more than the 100000"):
        round_corners(P, 0.01)


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(3, 40),
    turn=st.floats(1.0, 175.0),
    radius=st.floats(0.001, 0.02),  # 2 R tan(87.5 deg) < 1 mm: fits every segment
)
@example(n=3, turn=175.0, radius=0.02)
def test_round_corners_makes_no_more_points_than_it_allows(
    n: int, turn: float, radius: float
) -> None:
    P = zigzag(n, turn)
    Q = round_corners(P, radius)
    corners = n - 2
    assert len(Q.points) <= n + corners * (max(2, math.ceil(turn)) + 1)
    assert len(Q.points) > n - 1  # every corner became an arc


@settings(max_examples=30, deadline=None)
@given(offset=st.floats(3e-7, 1e-4), radius=st.floats(1e-3, 10.0))
@example(offset=1e-6, radius=1.0)  # found: a 1e-8 rad turn's arc points 7e-9 mm apart
def test_rounding_a_tiny_turn_warns_nothing(offset: float, radius: float) -> None:
    """Found: the arc of a corner turning 1e-8 rad had points closer than 1e-9 mm; the path
    dropped them with a DuplicatePointsWarning, two lines of Python on hrm plan's stderr."""
    import warnings

    P = KnownPath.from_points(np.array([[1200.0, 0, 0], [1300.0, 0, 0], [1400.0, offset, 0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Q = round_corners(P, radius)
    assert np.allclose(Q.points[[0, -1]], P.points[[0, -1]])
