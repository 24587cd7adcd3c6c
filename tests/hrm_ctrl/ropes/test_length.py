"""Exact rope lengths: straight arm, independent check through the FK frames, coupling."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.kinematics import R_BASE_PAPER, frames, homogeneous_chain
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.length import crossing_length, small_angle_crossing_length

LIM = float(np.deg2rad(59.9))
angles = st.lists(st.floats(-LIM, LIM), min_size=24, max_size=24).map(np.array)


def lengths_through_frames(act: Actuation, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Each rope's length from hole points carried by the planner's FK frames (world frame)."""
    model = act.robot
    R, O = frames(model, alpha, theta)
    rt = act.routing
    out = np.zeros(act.n_motors)
    for m in range(act.n_motors):
        r, phi = rt.hole_radius[m], rt.hole_angle[m]
        for j in range(int(rt.joint_of_rope[m]) + 1):
            before = model.base_rotation @ R_BASE_PAPER if j == 0 else R[j - 1]
            p = O[j] + before @ np.array([r * np.cos(phi), r * np.sin(phi), -rt.proximal_disk[j]])
            q = O[j] + R[j] @ np.array([r * np.cos(phi), r * np.sin(phi), rt.distal_disk[j]])
            out[m] += np.linalg.norm(q - p)
            if j < rt.joint_of_rope[m]:  # inside link j: distal disk of j to proximal of j+1
                nxt = O[j + 1] + R[j] @ np.array(
                    [r * np.cos(phi), r * np.sin(phi), -rt.proximal_disk[j + 1]]
                )
                out[m] += np.linalg.norm(nxt - q)
    return out


def lengths_through_homogeneous(act: Actuation, alpha: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The same with the literal 4x4 products of Eqs. (1)-(3)."""
    model = act.robot
    T = homogeneous_chain(model, alpha, theta)
    base = np.eye(4)
    base[:3, :3] = model.base_rotation @ R_BASE_PAPER
    base[:3, 3] = model.base_position
    rt = act.routing
    out = np.zeros(act.n_motors)
    for m in range(act.n_motors):
        r, phi = rt.hole_radius[m], rt.hole_angle[m]
        for j in range(int(rt.joint_of_rope[m]) + 1):
            if j == 0:
                before = base
            else:  # frame j-1 moved along its z axis by l_{j-1}: Trans(0, 0, l) of Eq. (1)
                shift = np.eye(4)
                shift[2, 3] = model.links[j - 1]
                before = T[j - 1] @ shift
            p = before @ np.array([r * np.cos(phi), r * np.sin(phi), -rt.proximal_disk[j], 1.0])
            after = before.copy()
            after[:3, :3] = T[j][:3, :3]
            q = after @ np.array([r * np.cos(phi), r * np.sin(phi), rt.distal_disk[j], 1.0])
            out[m] += np.linalg.norm((q - p)[:3])
            if j < rt.joint_of_rope[m]:
                nxt = T[j] @ np.array(
                    [
                        r * np.cos(phi),
                        r * np.sin(phi),
                        model.links[j] - rt.proximal_disk[j + 1],
                        1.0,
                    ]
                )
                out[m] += np.linalg.norm((nxt - q)[:3])
    return out


def test_straight_arm_gives_straight_lengths(act: Actuation) -> None:
    L = act.rope_lengths(np.zeros(12), np.zeros(12))
    links = act.robot.links
    # base disk (12 mm before joint 1) along the links to the anchor (12 mm past joint k)
    expected = np.array([12.0 + links[:k].sum() + 12.0 for k in act.joint_of_motor])
    np.testing.assert_allclose(L, expected, atol=1e-12)
    np.testing.assert_allclose(L[:3], 24.0)
    np.testing.assert_allclose(L[-3:], 2007.0 - 136.0 + 24.0)


@settings(max_examples=40, deadline=None)
@given(angles)
def test_lengths_match_fk_frames(act: Actuation, x: np.ndarray) -> None:
    a, t = x[:12], x[12:]
    np.testing.assert_allclose(act.rope_lengths(a, t), lengths_through_frames(act, a, t), atol=1e-9)


def test_lengths_match_homogeneous_chain_and_four_ropes(act: Actuation, act4: Actuation) -> None:
    rng = np.random.default_rng(7)
    for A in (act, act4):
        for _ in range(5):
            a, t = rng.uniform(-LIM, LIM, 12), rng.uniform(-LIM, LIM, 12)
            ref = lengths_through_homogeneous(A, a, t)
            np.testing.assert_allclose(A.rope_lengths(a, t), ref, atol=1e-9)
            np.testing.assert_allclose(lengths_through_frames(A, a, t), ref, atol=1e-9)


def test_batch_equals_single(act: Actuation) -> None:
    rng = np.random.default_rng(1)
    a, t = rng.uniform(-LIM, LIM, (4, 5, 12)), rng.uniform(-LIM, LIM, (4, 5, 12))
    L = act.rope_lengths(a, t)
    assert L.shape == (4, 5, 36)
    np.testing.assert_allclose(L[2, 3], act.rope_lengths(a[2, 3], t[2, 3]), atol=1e-12)


def test_coupling_joint1_moves_every_rope_joint12_only_its_own(act: Actuation) -> None:
    z = np.zeros(12)
    L0 = act.rope_lengths(z, z)
    a = z.copy()
    a[0] = 0.3
    t = z.copy()
    t[0] = 0.2
    d1 = act.rope_lengths(a, t) - L0
    assert np.all(np.abs(d1) > 1e-3)  # every rope crosses joint 1
    # every rope at the same hole angle changes by the same amount: only joint 1 bent
    a = z.copy()
    a[11] = 0.3
    t = z.copy()
    t[11] = 0.2
    d12 = act.rope_lengths(a, t) - L0
    assert np.all(np.abs(d12[act.joint_of_motor == 11]) > 1e-3)
    np.testing.assert_array_equal(d12[act.joint_of_motor < 11], 0.0)


def test_crossing_is_independent_of_the_rest_of_the_arm(act: Actuation) -> None:
    """A rope's length is the sum of its crossings; bending joint 5 shifts every rope of
    joints 5..12 by its crossing of joint 5 alone."""
    rt = act.routing
    a = np.zeros(12)
    a[4] = -0.7
    t = np.zeros(12)
    t[4] = 0.4
    d = act.rope_lengths(a, t) - act.geometry.straight
    expected = crossing_length(-0.7, 0.4, rt.hole_angle, rt.hole_radius, 12.0, 12.0) - 24.0
    crosses = act.joint_of_motor >= 4
    np.testing.assert_allclose(d[crosses], expected[crosses], atol=1e-12)
    np.testing.assert_array_equal(d[~crosses], 0.0)


def test_small_angle_approximation_is_far_off_at_60_degrees(act: Actuation) -> None:
    rt = act.routing
    lim = np.deg2rad(60.0) * 0.9999
    a = np.full(12, lim)
    z = np.zeros(12)
    own12 = act.joint_of_motor == 11  # ropes of joint 12 cross all 12 joints
    exact = act.rope_lengths(a, z)[own12] - act.routing.in_link[own12]
    approx = 12 * small_angle_crossing_length(lim, 0.0, rt.hole_angle[own12], 12.0, 12.0, 12.0)
    assert np.abs(exact - approx).max() > 20.0
    np.testing.assert_allclose(
        exact, 12 * crossing_length(lim, 0.0, rt.hole_angle[own12], 12.0, 12.0, 12.0)
    )


@pytest.mark.parametrize("shape", [(11,), (2, 13)])
def test_wrong_shape_is_a_rope_error(act: Actuation, shape: tuple[int, ...]) -> None:
    from hrm_ctrl.errors import RopeError

    with pytest.raises(RopeError, match="shape"):
        act.rope_lengths(np.zeros(shape), np.zeros(shape))
