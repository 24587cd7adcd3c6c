"""Both reference scenarios end to end (NOTES.md), and random reachable paths."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hrm_ctrl.formats.planfile import validate_plan
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.environment import Environment, worst_clearance
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.planner import PlanOptions, plan_path
from hrm_ctrl.planning.scenarios import scenario

MODEL = default_robot()
MAX_STEP_CHANGE_DEG = 3.0  # per 5 mm of travel: no jumps


@pytest.fixture(scope="module", params=["bent-pipe", "cabins"])
def planned(request: pytest.FixtureRequest):
    sc = scenario(request.param)
    return sc, plan_path(MODEL, sc.path, PlanOptions(return_to_start=True), scenario=sc)


def test_tip_follows_the_path_at_every_step_and_ends_on_it(planned) -> None:
    sc, plan = planned
    for d, tip in zip(plan.travel, plan.joints[:, -1], strict=True):
        assert np.linalg.norm(tip - sc.path.point_at(d)) < 0.01
    fwd_end = plan.phase.index("return") - 1
    assert plan.travel[fwd_end] == pytest.approx(sc.path.length)
    assert np.linalg.norm(plan.joints[fwd_end, -1] - sc.path.points[-1]) < 0.01
    assert plan.report["tip_error_mm"] < 0.01


def test_steps_are_lambda_apart_and_the_last_lands_on_the_end(planned) -> None:
    _sc, plan = planned
    fwd = plan.travel[: plan.phase.index("return")]
    np.testing.assert_allclose(np.diff(fwd)[:-1], 5.0)
    assert 0.0 < fwd[-1] - fwd[-2] <= 5.0


def test_joint_limits_are_respected(planned) -> None:
    _, plan = planned
    assert np.abs(plan.alpha).max() < MODEL.limit_alpha
    assert np.abs(plan.theta).max() < MODEL.limit_theta
    assert plan.report["first_violation"] is None


def test_joint_trajectories_have_no_jumps(planned) -> None:
    _, plan = planned
    change = np.degrees(np.abs(np.diff(np.stack((plan.alpha, plan.theta)), axis=1)))
    assert change.max() < MAX_STEP_CHANGE_DEG


def test_joints_in_the_path_lie_on_it(planned) -> None:
    _, plan = planned
    assert plan.report["joints_off_path_mm"] < 1e-6


def test_return_backs_out_to_the_start_configuration(planned) -> None:
    _, plan = planned
    assert plan.phase[-1] == "return"
    np.testing.assert_allclose(plan.alpha[-1], plan.alpha[0])
    np.testing.assert_allclose(plan.joints[-1], plan.joints[0])
    assert plan.travel[-1] == 0.0


def test_plan_document_is_hrm_plan_1_and_fk_consistent(planned) -> None:
    _, plan = planned
    doc = validate_plan(plan.to_dict())
    st0 = doc["steps"][7]
    from hrm_ctrl.kinematics import joint_centres

    O = joint_centres(MODEL, np.array(st0["alpha_rad"]), np.array(st0["theta_rad"]))
    np.testing.assert_allclose(O, np.array(st0["joints_mm"]), atol=1e-9)
    assert len(st0["joints_mm"]) == 13


def test_cabins_clearance_is_the_links_footprint_in_the_openings() -> None:
    """The paper plan passes the entrance (along its normal) with room to spare; the end
    link crosses the partition obliquely (the corner is rounded), so its footprint in the
    opening is wider than its diameter: the report measures the link, not its axis point."""
    sc = scenario("cabins")
    plan = plan_path(MODEL, sc.path, scenario=sc)
    c = plan.report["clearance_mm"]
    entrance, partition = sc.environment.obstacles
    r = 0.5 * MODEL.outer_diameter
    assert worst_clearance(Environment((entrance,)), plan.joints, r)[0] > 5.0
    at_partition = worst_clearance(Environment((partition,)), plan.joints, r)
    assert (c["min"], c["step"], c["link"]) == pytest.approx(at_partition)
    # a dense search along that link agrees
    O = plan.joints[c["step"], c["link"] - 1 : c["link"] + 1]
    t = np.linspace(0.0, 1.0, 20_001)[:, None]
    dense = sc.environment.free_distance(O[0] + t * (O[1] - O[0])).min() - r[c["link"] - 1]
    assert c["min"] == pytest.approx(dense, abs=0.01)
    assert len(c["per_step"]) == len(plan.travel) and min(
        v for v in c["per_step"] if v is not None
    ) == pytest.approx(c["min"])


def test_bent_pipe_reports_the_link_that_cuts_the_corner() -> None:
    """NOTES.md: chords cut corners; the report measures it instead of hiding it."""
    sc = scenario("bent-pipe")
    plan = plan_path(MODEL, sc.path, scenario=sc)
    assert plan.report["links_off_path_mm"] > 20.0
    c = plan.report["clearance_mm"]
    assert c["min"] == pytest.approx(20.0 - plan.report["links_off_path_mm"], abs=0.5)


@st.composite
def reachable_paths(draw) -> KnownPath:
    """Paths the arm can enter: a start in front of the base, 2-4 legs each within
    25 deg of +x, turns of at most 20 deg, 60-450 mm long in all."""
    A = np.array(
        [
            draw(st.floats(1000.0, 1400.0)),
            draw(st.floats(-150.0, 150.0)),
            draw(st.floats(-150.0, 150.0)),
        ]
    )
    n_legs = draw(st.integers(1, 3))
    pts = [A]
    yaw, pitch = draw(st.floats(-0.2, 0.2)), draw(st.floats(-0.2, 0.2))
    for _ in range(n_legs):
        yaw = float(np.clip(yaw + draw(st.floats(-0.3, 0.3)), -0.43, 0.43))
        pitch = float(np.clip(pitch + draw(st.floats(-0.3, 0.3)), -0.43, 0.43))
        d = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
        pts.append(pts[-1] + draw(st.floats(30.0, 150.0)) * d)
    return KnownPath.from_points(np.array(pts))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(reachable_paths())
def test_random_reachable_paths_are_followed(path: KnownPath) -> None:
    plan = plan_path(MODEL, path, PlanOptions(step=10.0))
    r = plan.report
    assert r["tip_error_mm"] < 0.01
    assert r["end_error_mm"] < 0.01
    assert r["joints_off_path_mm"] < 1e-6
    np.testing.assert_allclose(
        np.linalg.norm(np.diff(plan.joints, axis=1), axis=-1),
        np.broadcast_to(MODEL.links, (*plan.joints.shape[:1], 12)),
    )
    change = np.degrees(np.abs(np.diff(np.stack((plan.alpha, plan.theta)), axis=1)))
    assert change.max() < 2 * MAX_STEP_CHANGE_DEG  # 10 mm steps
