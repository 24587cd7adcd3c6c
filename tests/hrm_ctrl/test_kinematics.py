"""Eqs. (1)-(4) against the printed matrices and an independent rotation library."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hrm_ctrl.kinematics import (
    base_transform,
    frames,
    homogeneous_chain,
    joint_centres,
    joint_transform,
)
from hrm_ctrl.model import default_robot

MODEL = default_robot()
angle = st.floats(-np.pi / 3, np.pi / 3, allow_nan=False)
length = st.floats(1.0, 500.0)


def printed_eq1(a: float, t: float, L: float) -> np.ndarray:
    """Eq. (1) exactly as printed in the paper."""
    ca, sa, ct, stt = np.cos(a), np.sin(a), np.cos(t), np.sin(t)
    return np.array(
        [
            [ca, sa * stt, sa * ct, 0],
            [0, ct, -stt, 0],
            [-sa, ca * stt, ca * ct, L],
            [0, 0, 0, 1],
        ]
    )


def printed_eq2(a: float, t: float) -> np.ndarray:
    """Eq. (2) exactly as printed in the paper."""
    ca, sa, ct, stt = np.cos(a), np.sin(a), np.cos(t), np.sin(t)
    return np.array(
        [
            [-sa, ca * stt, ca * ct, 0],
            [0, -ct, stt, 0],
            [ca, sa * stt, sa * ct, 0],
            [0, 0, 0, 1],
        ]
    )


@given(angle, angle, length)
def test_eq1_matches_printed_matrix(a: float, t: float, L: float) -> None:
    np.testing.assert_allclose(joint_transform(a, t, L), printed_eq1(a, t, L), atol=1e-12)


@given(angle, angle)
def test_eq2_matches_printed_matrix(a: float, t: float) -> None:
    np.testing.assert_allclose(base_transform(a, t), printed_eq2(a, t), atol=1e-12)


@given(angle, angle)
def test_eq1_is_rot_y_then_rot_x(a: float, t: float) -> None:
    """NOTES.md: alpha is the first rotation (about y), theta the second (about new x)."""
    R = Rotation.from_euler("YX", [a, t]).as_matrix()  # intrinsic: y, then the new x
    np.testing.assert_allclose(joint_transform(a, t, 0.0)[:3, :3], R, atol=1e-12)


@settings(max_examples=50)
@given(st.lists(angle, min_size=24, max_size=24))
def test_fk_equals_product_of_printed_matrices(angles: list[float]) -> None:
    a = np.array(angles[:12])
    t = np.array(angles[12:])
    T = printed_eq2(a[0], t[0])
    expected = [T[:3, 3].copy()]
    for i in range(1, 12):
        T = T @ printed_eq1(a[i], t[i], MODEL.links[i - 1])
        expected.append(T[:3, 3].copy())
    expected.append((T @ [0, 0, MODEL.links[11], 1])[:3])  # Eq. (4)
    np.testing.assert_allclose(joint_centres(MODEL, a, t), np.array(expected), atol=1e-9)
    chain = homogeneous_chain(MODEL, a, t)
    np.testing.assert_allclose(chain[-1], T, atol=1e-9)


def test_zero_configuration_lies_along_x_with_x_axes_up() -> None:
    R, O = frames(MODEL, np.zeros(12), np.zeros(12))
    np.testing.assert_allclose(O[:, 1:], 0.0, atol=1e-12)
    np.testing.assert_allclose(O[:, 0], np.concatenate(([0.0], np.cumsum(MODEL.links))))
    np.testing.assert_allclose(R[:, :, 0], np.tile([0.0, 0.0, 1.0], (12, 1)), atol=1e-12)


def test_fk_is_vectorised_over_configurations() -> None:
    rng = np.random.default_rng(3)
    a = rng.uniform(-1, 1, (4, 5, 12))
    t = rng.uniform(-1, 1, (4, 5, 12))
    O = joint_centres(MODEL, a, t)
    assert O.shape == (4, 5, 13, 3)
    np.testing.assert_allclose(O[2, 3], joint_centres(MODEL, a[2, 3], t[2, 3]))
    # every link keeps its length
    np.testing.assert_allclose(
        np.linalg.norm(np.diff(O, axis=-2), axis=-1), np.broadcast_to(MODEL.links, (4, 5, 12))
    )
