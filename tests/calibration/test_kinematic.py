"""Kinematic calibration (issue 12, item 2) against a synthetic true arm.

Truth: links +-2 mm, offsets +-1 deg, and (for the frame case) an instrument frame far from
the base; noise sigma 0.05 mm per coordinate on 150 poses from spread_configurations.
Tolerances, from the noise and the conditioning: at 150 poses the fit's standard deviations
are about 0.009 mm for links and at most about 0.006 deg for offsets (joint 12's, on the
shortest lever arm; the others are smaller), so 0.1 mm is > 10 sigma and 0.02 deg > 3 sigma;
each error must also lie within 4.5 of its own reported std (which checks the stds), and the
residual sigma within 20 % of 0.05 mm (450 residuals: its relative spread is ~3.5 %).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration import kinematic as kin
from calibration.kinematic import (
    ALPHA_NAMES,
    COLUMNS,
    LINK_NAMES,
    THETA_NAMES,
    fit_kinematics,
    read_pose_csv,
    spread_configurations,
)
from hrm_ctrl.errors import CalibrationDataError, CalibrationError, UnobservableError
from hrm_ctrl.kinematics import R_BASE_PAPER, frames
from hrm_ctrl.model import default_robot

SIGMA = 0.05
N_POSES = 150
LINK_TOL_MM = 0.1
OFFSET_TOL_DEG = 0.02


@pytest.fixture(scope="module")
def model():
    return default_robot()


def _truth(model, seed):
    rng = np.random.default_rng(seed)
    dl = rng.uniform(-2.0, 2.0, 12)
    da = np.radians(rng.uniform(-1.0, 1.0, 12))
    dt = np.radians(rng.uniform(-1.0, 1.0, 12))
    links = model.links + dl
    links.setflags(write=False)
    return dataclasses.replace(model, links=links), dl, da, dt, rng


def _measure(true, da, dt, alpha, theta, rng, frame=None):
    p = frames(true, alpha + da, theta + dt)[1][:, -1, :]
    if frame is not None:
        R, t = frame
        p = p @ R.T + t
    return p + rng.normal(0.0, SIGMA, p.shape)


def _check_recovery(fit, dl, da, dt, skip=()):
    truth = dict(zip(LINK_NAMES + ALPHA_NAMES + THETA_NAMES, np.r_[dl, da, dt], strict=True))
    for name, value in truth.items():
        if name in skip:
            continue
        err = fit.params[name] - value
        tol = LINK_TOL_MM if name.startswith("l_") else math.radians(OFFSET_TOL_DEG)
        assert abs(err) < tol, (name, err)
        assert abs(err) < 4.5 * fit.std[name], (name, err, fit.std[name])
    assert 0.8 * SIGMA < fit.sigma_mm < 1.2 * SIGMA
    assert fit.rms_after_mm == pytest.approx(math.sqrt(3) * SIGMA, rel=0.2)
    assert fit.rms_before_mm > 50 * fit.rms_after_mm
    assert fit.max_after_mm < 6 * SIGMA


def test_fit_recovers_links_and_offsets_in_the_base_frame(model):
    true, dl, da, dt, rng = _truth(model, 1)
    alpha, theta = spread_configurations(model, N_POSES, rng)
    pts = _measure(true, da, dt, alpha, theta, rng)
    fit = fit_kinematics(model, alpha, theta, pts)
    _check_recovery(fit, dl, da, dt)
    assert fit.fixed == {} and fit.frame_rotation is None
    assert len(fit.std) == 36
    np.testing.assert_allclose(fit.links_mm, model.links + fit.link_corrections_mm)
    np.testing.assert_allclose(fit.calibrated_model(model).links, fit.links_mm)


def test_fit_with_a_free_instrument_frame(model):
    true, dl, da, dt, rng = _truth(model, 2)
    alpha, theta = spread_configurations(model, N_POSES, rng)
    Rf = Rotation.from_rotvec([0.4, -0.7, 2.2]).as_matrix()
    tf = np.array([3500.0, -1200.0, 650.0])
    pts = _measure(true, da, dt, alpha, theta, rng, (Rf, tf))
    fit = fit_kinematics(model, alpha, theta, pts, estimate_frame=True)
    # alpha_offset_1 is a rigid rotation of the arm about the base's y axis: folded into the
    # frame, which then equals the true frame times that rotation (the base is at the origin)
    assert list(fit.fixed) == ["alpha_offset_1"] and "alpha_offset_1" not in fit.std
    assert fit.params["alpha_offset_1"] == 0.0
    _check_recovery(fit, dl, da, dt, skip={"alpha_offset_1"})
    axis = model.base_rotation @ R_BASE_PAPER[:, 1]
    Q = Rotation.from_rotvec(axis * da[0]).as_matrix()
    ang = Rotation.from_matrix(fit.frame_rotation.T @ Rf @ Q).magnitude()
    assert math.degrees(ang) < OFFSET_TOL_DEG
    np.testing.assert_allclose(fit.frame_translation_mm, tf, atol=0.2)
    assert {"frame_rx", "frame_tz"} <= set(fit.std)


def test_refuses_poses_that_are_all_the_same_configuration(model):
    true, _, da, dt, rng = _truth(model, 3)
    alpha, theta = spread_configurations(model, 1, rng)
    alpha, theta = np.repeat(alpha, 60, axis=0), np.repeat(theta, 60, axis=0)
    pts = _measure(true, da, dt, alpha, theta, rng)
    with pytest.raises(UnobservableError, match=r"not observable .*l_1-12") as exc:
        fit_kinematics(model, alpha, theta, pts)
    assert "\n" not in str(exc.value)
    assert isinstance(exc.value, CalibrationError)


def test_refuses_too_few_poses_naming_parameters(model):
    true, _, da, dt, rng = _truth(model, 4)
    alpha, theta = spread_configurations(model, 10, rng)
    pts = _measure(true, da, dt, alpha, theta, rng)
    with pytest.raises(
        UnobservableError, match=r"too few poses \(10 give 30 equations for 36.*_offset_"
    ):
        fit_kinematics(model, alpha, theta, pts)


def test_refuses_poses_too_alike_and_names_the_weak_parameters(model):
    """Every angle within +-1 deg: nothing is exactly lost, but far too little is determined."""
    true, _, da, dt, rng = _truth(model, 5)
    alpha, theta = spread_configurations(model, 60, rng)
    alpha, theta = alpha / 60.0, theta / 60.0
    pts = _measure(true, da, dt, alpha, theta, rng)
    with pytest.raises(UnobservableError, match=r"do not determine .*theta_offset_"):
        fit_kinematics(model, alpha, theta, pts)


def test_rejects_bad_arrays(model):
    a = np.zeros((20, 12))
    with pytest.raises(CalibrationDataError, match="points_mm must have shape"):
        fit_kinematics(model, a, a, np.zeros((20, 2)))
    pts = np.zeros((20, 3))
    pts[4, 1] = np.nan
    with pytest.raises(CalibrationDataError, match="pose 5"):
        fit_kinematics(model, a, a, pts)


def test_spread_configurations(model):
    a, t = spread_configurations(model, 60, np.random.default_rng(7))
    a2, _ = spread_configurations(model, 60, np.random.default_rng(7))
    np.testing.assert_array_equal(a, a2)
    assert a.shape == t.shape == (60, 12)
    lim = 0.9 * model.limit_alpha
    assert np.all(np.abs(a) <= lim) and np.all(np.abs(t) <= lim)
    q = np.concatenate([a, t], axis=1)
    assert np.all(q.min(axis=0) < -0.9 * lim) and np.all(q.max(axis=0) > 0.9 * lim)
    for col in q.T:  # a Latin hypercube: one pose in each of the 60 strata of every angle
        strata = np.floor((col + lim) / (2 * lim) * 60).astype(int)
        assert len(set(strata.tolist())) == 60


# --- the pose file -----------------------------------------------------------------------

HEADER = ",".join(COLUMNS)


def _row(k=0):
    vals = [0.01 * (k + i) for i in range(24)] + [1000.0 + k, -2.5, 3.25]
    return ",".join(repr(v) for v in vals)


def test_read_pose_csv_round_trip(tmp_path):
    p = tmp_path / "poses.csv"
    p.write_text("\n".join([HEADER, _row(0), "", _row(1)]) + "\n")
    data = read_pose_csv(p)
    assert len(data) == 2 and data.source == str(p)
    assert data.alpha_rad.shape == data.theta_rad.shape == (2, 12)
    assert data.alpha_rad[1, 0] == pytest.approx(0.01) and data.theta_rad[0, 0] == 0.12
    assert data.points_mm[1].tolist() == [1001.0, -2.5, 3.25]


def _cells(row):
    return row.split(",")


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        ([HEADER, ",".join(_cells(_row())[:26])], r":2: column 27 \(z_mm\) is missing"),
        ([HEADER, _row().replace("1000.0", "nan")], r":2: column 25 \(x_mm\) is not a number"),
        (
            [HEADER, _row(), _row().replace("-2.5", "1" * 400)],
            r":3: column 26 \(y_mm\) = '1111.*\(400 characters\) is out of range",
        ),
        (
            [HEADER, _row().replace("0.03", "1e9", 1)],
            r":2: column 4 \(alpha_4_rad\) = '1e9' is out",
        ),
        (
            [HEADER, _row().replace("0.05", "abc", 1)],
            r":2: column 6 \(alpha_6_rad\) is not a number",
        ),
        (
            [HEADER.replace("theta_3_rad", "theta3_rad"), _row()],
            r":1: header column 15 is 'theta3_rad', expected 'theta_3_rad'",
        ),
        ([HEADER.rsplit(",", 1)[0], _row()], r":1: header column 27 \(z_mm\) is missing"),
        ([HEADER + ",w_mm", _row()], r":1: header column 28 'w_mm' is not part"),
        ([HEADER, _row() + ",7"], r":2: column 28 is one too many"),
        ([HEADER], r"has a header but no poses"),
        (["", " "], r"pose file is empty"),
    ],
)
def test_read_pose_csv_refuses_bad_input_in_one_line(tmp_path, lines, message):
    p = tmp_path / "bad.csv"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationDataError, match=message) as exc:
        read_pose_csv(p)
    text = str(exc.value)
    assert "\n" not in text and text.startswith(str(p))


def test_read_pose_csv_bounds(tmp_path, monkeypatch):
    with pytest.raises(CalibrationDataError, match="pose file not found"):
        read_pose_csv(tmp_path / "none.csv")
    p = tmp_path / "big.csv"
    p.write_text("\n".join([HEADER] + [_row(k) for k in range(5)]) + "\n")
    monkeypatch.setattr(kin, "MAX_POSES", 4)
    with pytest.raises(CalibrationDataError, match="more than the 4 poses"):
        read_pose_csv(p)
    monkeypatch.setattr(kin, "MAX_POSE_BYTES", 100)
    with pytest.raises(CalibrationDataError, match="larger than the 100 bytes"):
        read_pose_csv(p)
