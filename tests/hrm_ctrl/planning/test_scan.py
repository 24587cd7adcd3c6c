"""Centre line and diameter of a pipe from synthetic scans of its inner wall."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import Phase, example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hrm_ctrl.planning.environment import Pipe
from hrm_ctrl.planning.known_path import KnownPath
from hrm_ctrl.planning.scan import (
    ScanFitError,
    path_and_pipe_from_scan,
    pipe_from_scan,
    synthetic_pipe_scan,
)
from hrm_ctrl.planning.scenarios import scenario

BENT = scenario("bent-pipe").path


def axis_error(true: KnownPath, fitted: np.ndarray) -> tuple[float, float, float]:
    """Largest distance from the fitted axis to the true one, from the true one (sampled
    every 0.5 mm) to the fitted one, and how far the fitted ends are from the true ends."""
    fit = KnownPath.from_points(fitted)
    if np.linalg.norm(fitted[0] - true.points[0]) > np.linalg.norm(fitted[-1] - true.points[0]):
        fit = KnownPath.from_points(fitted[::-1])
    dense = true.points_at(np.linspace(0.0, true.length, int(true.length / 0.5) + 1))
    to_true = float(true.distance_to(fit.points_at(np.linspace(0, fit.length, 2000))).max())
    to_fit = float(fit.distance_to(dense).max())
    ends = max(
        float(np.linalg.norm(fit.points[0] - true.points[0])),
        float(np.linalg.norm(fit.points[-1] - true.points[-1])),
    )
    return to_true, to_fit, ends


def test_bent_pipe_half_mm_noise_two_percent_outliers() -> None:
    rng = np.random.default_rng(10)
    cloud = synthetic_pipe_scan(BENT, 70.0, 200_000, 0.5, 0.02, rng)
    fit = pipe_from_scan(cloud)
    to_true, to_fit, ends = axis_error(BENT, fit.axis)
    assert to_true < 1.0 and to_fit < 1.0, (to_true, to_fit)
    assert ends < 1.0
    assert abs(fit.inner_diameter - 70.0) < 1.0
    # the residuals are the noise (sigma 0.5 mm along the wall's normal), the outliers rejected
    assert 0.4 < fit.rms < 0.6
    assert 0.8 < fit.p95 < 1.2
    assert 0.96 < fit.inlier_fraction < 0.985
    assert fit.n_outliers == fit.n_points - round(fit.inlier_fraction * fit.n_points)
    assert fit.n_outliers >= 0.9 * 0.02 * len(cloud)
    assert fit.axis_length == pytest.approx(BENT.length, abs=2.0)


def test_straight_pipe_of_another_size_and_direction() -> None:
    rng = np.random.default_rng(11)
    d = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    start = np.array([-400.0, 250.0, 30.0])
    axis = KnownPath.from_points(np.array([start, start + 900.0 * d]))
    cloud = synthetic_pipe_scan(axis, 150.0, 60_000, 0.3, 0.05, rng)
    fit = pipe_from_scan(cloud)
    to_true, to_fit, ends = axis_error(axis, fit.axis)
    assert max(to_true, to_fit, ends) < 1.0
    assert abs(fit.inner_diameter - 150.0) < 0.5


def test_a_noise_free_scan_fits_almost_exactly() -> None:
    cloud = synthetic_pipe_scan(BENT, 70.0, 50_000, 0.0, 0.0, np.random.default_rng(12))
    fit = pipe_from_scan(cloud)
    to_true, to_fit, ends = axis_error(BENT, fit.axis)
    assert max(to_true, to_fit, ends) < 0.5  # the ends: a count of wall points (Poisson)
    assert fit.inner_diameter == pytest.approx(70.0, abs=0.02)
    assert fit.rms < 0.02 and fit.inlier_fraction > 0.98  # within 0.05 mm of the wall


def random_rotation(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


# a fit takes ~0.3 s: no shrinking (a failure is pinned with @example as found)
@settings(max_examples=8, deadline=None, phases=(Phase.explicit, Phase.reuse, Phase.generate))
@given(
    rot=st.integers(0, 2**31 - 1),
    noise=st.floats(0.0, 0.8),
    outliers=st.floats(0.0, 0.05),
    shift=st.tuples(*[st.floats(-2000, 2000)] * 3),
)
@example(rot=0, noise=0.5, outliers=0.02, shift=(0.0, 0.0, 0.0))
@example(rot=7, noise=0.0, outliers=0.0, shift=(-1200.0, -100.0, -300.0))
@example(rot=197, noise=0.0, outliers=0.0, shift=(0.0, 0.0, 0.0))  # found: an end 1.4 mm long
@example(  # found: a noise-free wall, a stray point pulled a slice's start circle 0.07 mm
    rot=0,  # off its radius and the robust fit weighed every point out: the march stopped
    noise=7.234012791278788e-106,
    outliers=0.036121760392193565,
    shift=(-1965.176539483597, 1999.0, 1103.089261323767),
)
def test_the_fit_does_not_depend_on_orientation_or_position(
    rot: int, noise: float, outliers: float, shift: tuple[float, float, float]
) -> None:
    Rm = random_rotation(rot)
    axis = KnownPath.from_points(BENT.points @ Rm.T + np.array(shift))
    rng = np.random.default_rng(rot % 1000)
    cloud = synthetic_pipe_scan(axis, 70.0, 40_000, noise, outliers, rng)
    fit = pipe_from_scan(cloud)
    to_true, to_fit, ends = axis_error(axis, fit.axis)
    assert to_true < 1.0 and to_fit < 1.0, (to_true, to_fit)
    assert ends < 2.0
    assert abs(fit.inner_diameter - 70.0) < 1.0


def test_the_path_starts_at_the_end_nearest_the_base() -> None:
    cloud = synthetic_pipe_scan(BENT, 70.0, 20_000, 0.3, 0.0, np.random.default_rng(13))
    fit = pipe_from_scan(cloud)
    near_A = fit.path(np.array([1000.0, 100.0, 300.0]))
    near_B = fit.path(np.array([2000.0, 100.0, 100.0]))
    assert np.linalg.norm(near_A.points[0] - BENT.points[0]) < 2.0
    assert np.linalg.norm(near_B.points[0] - BENT.points[-1]) < 2.0
    np.testing.assert_allclose(near_A.points, near_B.points[::-1])


def test_path_and_pipe_from_a_scan_file(tmp_path) -> None:
    cloud = synthetic_pipe_scan(BENT, 70.0, 30_000, 0.5, 0.02, np.random.default_rng(14))
    f = tmp_path / "pipe.npy"
    np.save(f, cloud)
    path, axis, diameter = path_and_pipe_from_scan(f)
    assert np.linalg.norm(path.points[0] - BENT.points[0]) < 2.0  # nearest the origin
    assert abs(diameter - 70.0) < 1.0 and str(f) in path.source
    pipe = Pipe(axis, diameter)
    # the true axis lies well inside the fitted pipe
    assert pipe.free_distance(BENT.points).min() > 34.0


def test_the_fit_is_the_same_for_the_same_cloud() -> None:
    cloud = synthetic_pipe_scan(BENT, 70.0, 20_000, 0.5, 0.02, np.random.default_rng(15))
    a, b = pipe_from_scan(cloud), pipe_from_scan(cloud)
    np.testing.assert_array_equal(a.axis, b.axis)
    assert a.inner_diameter == b.inner_diameter


def test_a_large_cloud_is_fitted_on_a_subset_and_measured_on_every_point() -> None:
    cloud = synthetic_pipe_scan(BENT, 70.0, 60_000, 0.5, 0.02, np.random.default_rng(16))
    fit = pipe_from_scan(cloud, max_fit_points=20_000)
    assert fit.n_points == 60_000
    assert max(axis_error(BENT, fit.axis)[:2]) < 1.0


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((50, 3)), "at least 100 points"),
        (np.zeros((200, 2)), "shape"),
        (np.full((200, 3), np.nan), "NaN"),
        (np.zeros((500, 3)), "do not extend"),
    ],
)
def test_what_is_no_scan_is_refused_in_one_line(points: np.ndarray, message: str) -> None:
    with pytest.raises(ScanFitError, match=message) as err:
        pipe_from_scan(points)
    assert "\n" not in str(err.value)


def test_a_blob_is_not_a_pipe() -> None:
    blob = np.random.default_rng(17).normal(0.0, 100.0, (20_000, 3))
    with pytest.raises(ScanFitError) as err:
        pipe_from_scan(blob)
    assert "\n" not in str(err.value)


def test_a_bad_slice_step_is_refused() -> None:
    cloud = synthetic_pipe_scan(BENT, 70.0, 5000, 0.5, 0.0, np.random.default_rng(18))
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ScanFitError, match="slice step must be"):
            pipe_from_scan(cloud, slice_step=bad)
    with pytest.raises(ScanFitError, match=r"slice step 1 mm is below 0\.05 of the pipe.s radius"):
        pipe_from_scan(cloud, slice_step=1.0)
    with pytest.raises(ScanFitError, match=r"above 0\.5 of the pipe.s radius"):
        pipe_from_scan(cloud, slice_step=20.0)


def test_a_u_bend_whose_middle_slab_cuts_both_legs() -> None:
    psi = np.radians(np.arange(0, 181))
    arc = np.column_stack((300 + 100 * np.sin(psi), 100 - 100 * np.cos(psi), 0 * psi))
    U = KnownPath.from_points(np.vstack(([0, 0, 0], arc, [0, 200, 0])))
    cloud = synthetic_pipe_scan(U, 70.0, 60_000, 0.5, 0.02, np.random.default_rng(19))
    fit = pipe_from_scan(cloud, slice_step=3.0)
    to_true, to_fit, ends = axis_error(U, fit.axis)
    assert max(to_true, to_fit, ends) < 1.0
    assert abs(fit.inner_diameter - 70.0) < 0.5


# ---- red team (issue 10) ------------------------------------------------------------------

STRAIGHT = KnownPath.from_points(np.array([[0.0, 0, 0], [500, 0, 0]]))


@settings(max_examples=8, deadline=None, phases=[Phase.explicit, Phase.generate])
@given(far=st.floats(1e3, 1e6), k=st.integers(1, 20), seed=st.integers(0, 3))
@example(far=1e6, k=1, seed=0)  # found: one stray point at 1 km turned the seed's axis
def test_a_few_stray_points_far_away_do_not_break_the_fit(far: float, k: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    cloud = synthetic_pipe_scan(STRAIGHT, 70.0, 20_000, 0.3, 0.0, rng)
    stray = np.tile([far, far, -far], (k, 1))
    fit = pipe_from_scan(np.vstack((cloud, stray)))
    assert abs(fit.inner_diameter - 70.0) < 0.5
    assert max(axis_error(STRAIGHT, fit.axis)) < 1.5


@settings(max_examples=10, deadline=None, phases=[Phase.explicit, Phase.generate])
@given(seed=st.integers(0, 1000), shape=st.sampled_from(["cube", "long box"]))
@example(seed=21, shape="cube")  # found: fitted as a pipe of 69.5 mm, band 66 mm, 100 % inliers
@example(seed=1, shape="long box")  # found: a pipe of 74.9 mm over 240 mm
@example(seed=24, shape="long box")  # found: a pipe of 83.7 mm
def test_points_filling_a_volume_are_not_a_pipe(seed: int, shape: str) -> None:
    rng = np.random.default_rng(seed)
    size = [100.0, 100, 100] if shape == "cube" else [400.0, 100, 100]
    with pytest.raises(ScanFitError) as err:
        pipe_from_scan(rng.uniform(0.0, 1.0, (20_000, 3)) * size)
    assert "\n" not in str(err.value)


def test_a_noisy_wall_is_still_a_pipe_and_a_scan_in_metres_is_refused() -> None:
    rng = np.random.default_rng(5)
    cloud = synthetic_pipe_scan(STRAIGHT, 70.0, 20_000, 4.0, 0.02, rng)  # sigma 4 mm
    assert abs(pipe_from_scan(cloud).inner_diameter - 70.0) < 2.0
    metres = synthetic_pipe_scan(STRAIGHT, 70.0, 20_000, 0.3, 0.0, rng) / 1000.0
    with pytest.raises(ScanFitError, match=r"0\.07 mm, below 1 mm \(is the scan in metres"):
        pipe_from_scan(metres)


def test_a_plan_along_a_scanned_helix_tracks_the_true_axis() -> None:
    """Issue 39: the round trip scan -> centre line -> plan keeps the tip within 0.1 mm of
    the true axis (each end of the centre line placed along its curve, not its tangent,
    which left a bend's end 0.4 mm off)."""
    from hrm_ctrl.model import default_robot
    from hrm_ctrl.planning.environment import Environment
    from hrm_ctrl.planning.planner import PlanOptions, plan_path

    t = np.linspace(0.0, math.pi, 300)  # half a turn of radius 150 mm, pitch 300 mm
    true = KnownPath.from_points(
        np.c_[
            1200.0 + 300.0 * t / (2 * math.pi),
            100.0 + 150 * np.sin(t),
            300.0 + 150 * (1 - np.cos(t)),
        ]
    )
    cloud = synthetic_pipe_scan(true, 70.0, 60_000, 0.0, 0.0, np.random.default_rng(3))
    fit = pipe_from_scan(cloud)
    model = default_robot()
    path = fit.path(model.base_position)
    assert float(true.distance_to(path.points).max()) < 0.05  # the ends too
    assert float(np.linalg.norm(path.points[0] - true.points[0])) < 0.1
    env = Environment((Pipe(path, fit.inner_diameter),))
    plan = plan_path(model, path, PlanOptions(step=10.0), environment=env)
    assert float(true.distance_to(plan.joints[:, -1]).max()) < 0.1
