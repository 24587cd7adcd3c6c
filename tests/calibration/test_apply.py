"""Applying a calibration (calibration/apply.py) and the rope layer's joint offsets and
per-rope EA (hrm_ctrl/ropes/actuation.py, load_actuation)."""

from __future__ import annotations

import dataclasses
import json
import math
from importlib import resources

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from calibration.apply import (
    UPDATABLE,
    active_for,
    calibrated_actuation,
    calibrated_model,
    check_belongs,
    file_sha256,
    nominal_calibration,
    robot_sha256,
    starting_point,
    updated,
)
from calibration.store import CalibrationStore, Routine
from hrm_ctrl.errors import CalibrationFileError, RopeError
from hrm_ctrl.model import default_robot, load_robot
from hrm_ctrl.ropes.actuation import load_actuation


@pytest.fixture(scope="module")
def model():
    return default_robot()


@pytest.fixture(scope="module")
def nominal(model):
    return load_actuation(model)


def _offsets(seed: int, deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return np.radians(rng.uniform(-deg, deg, 12)), np.radians(rng.uniform(-deg, deg, 12))


# --- the rope layer with joint offsets --------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    q=st.lists(st.floats(-0.9, 0.9), min_size=24, max_size=24),
)
@example(seed=0, q=[0.0] * 24)
def test_offsets_map_true_angles_through_the_nominal_geometry(seed, q):
    model = default_robot()
    nominal = load_actuation(model)
    da, dt = _offsets(seed)
    act = load_actuation(model, alpha_offset_rad=da, theta_offset_rad=dt)
    a, t = np.array(q[:12]), np.array(q[12:])
    np.testing.assert_array_equal(
        act.counts_from_angles(a, t), nominal.counts_from_angles(a - da, t - dt)
    )
    np.testing.assert_array_equal(act.rope_lengths(a, t), nominal.rope_lengths(a - da, t - dt))
    tension = np.full(act.n_motors, 45.0)
    np.testing.assert_array_equal(
        act.counts_from_angles(a, t, tension), nominal.counts_from_angles(a - da, t - dt, tension)
    )
    # round trip: counts -> true angles, to the counts' quantisation (~5e-4 mm of rope)
    a2, t2, _ = act.angles_from_counts(act.counts_from_angles(a, t))
    assert np.abs(a2 - a).max() < 1e-3 and np.abs(t2 - t).max() < 1e-3
    a3, t3, _ = nominal.angles_from_counts(act.counts_from_angles(a, t))
    np.testing.assert_allclose(a2, a3 + da, atol=1e-12)
    np.testing.assert_allclose(t2, t3 + dt, atol=1e-12)
    # a warm start is in true angles too
    a4, t4, _ = act.angles_from_counts(act.counts_from_angles(a, t), None, a + 0.01, t - 0.01)
    assert np.abs(a4 - a).max() < 1e-3 and np.abs(t4 - t).max() < 1e-3


def test_zero_offsets_change_nothing(model, nominal):
    act = load_actuation(model, alpha_offset_rad=np.zeros(12), theta_offset_rad=np.zeros(12))
    q = np.linspace(-0.8, 0.8, 24).reshape(2, 12)
    np.testing.assert_array_equal(
        act.counts_from_angles(q[0], q[1]), nominal.counts_from_angles(q[0], q[1])
    )
    assert not act.alpha_offset_rad.flags.writeable


def test_joint_limits_are_checked_on_the_true_angles(model):
    da = np.zeros(12)
    da[3] = math.radians(2.0)
    act = load_actuation(model, alpha_offset_rad=da)
    a = np.zeros(12)
    a[3] = model.limit_alpha - math.radians(1.0)  # commanded: limit - 3 deg; true: limit - 1
    act.counts_from_angles(a, np.zeros(12))
    a[3] = model.limit_alpha + math.radians(0.5)  # commanded inside, true outside
    with pytest.raises(RopeError, match="joint 4: alpha"):
        act.counts_from_angles(a, np.zeros(12))


def test_per_rope_EA_replaces_the_routing(model, nominal):
    ids = nominal.motor_ids
    ea = {m: 20_000.0 + 100.0 * i for i, m in enumerate(ids)}
    act = load_actuation(model, rope_EA_N=ea)
    np.testing.assert_array_equal(act.routing.stiffness_EA_N, list(ea.values()))
    q = np.full(12, 0.2)
    T = np.full(len(ids), 60.0)
    # a softer rope stretches more: more rope wound in for the same pose at 60 N
    diff = act.counts_from_angles(q, q, T) - nominal.counts_from_angles(q, q, T)
    assert np.all(diff * nominal.motors.direction > 0)
    with pytest.raises(RopeError, match="misses"):
        load_actuation(model, rope_EA_N={ids[0]: 3e4})
    with pytest.raises(RopeError, match=f"rope {ids[2]} is -1.0"):
        load_actuation(model, rope_EA_N=[3e4, 3e4, -1.0] + [3e4] * (len(ids) - 3))
    with pytest.raises(RopeError, match="12 finite angles"):
        load_actuation(model, theta_offset_rad=np.zeros(11))


# --- robot identity -----------------------------------------------------------------------


def test_robot_sha256_is_the_descriptions_content(model, tmp_path):
    sha = robot_sha256(model)
    assert len(sha) == 64 and sha == sha.lower()
    # the same content elsewhere, with other comments and layout: the same robot
    shipped = resources.files("hrm_ctrl.data").joinpath("robot.toml").read_text()
    copy = tmp_path / "copy.toml"
    copy.write_text("# a copy\n\n" + shipped.replace(" = ", "=") + "\n# end\n")
    assert robot_sha256(load_robot(copy)) == sha
    # one value changed: another robot
    changed = tmp_path / "changed.toml"
    changed.write_text(shipped.replace("pretension_N = 30.0", "pretension_N = 31.0"))
    assert robot_sha256(load_robot(changed)) != sha
    links = model.links.copy()
    links[5] += 1e-9
    assert robot_sha256(dataclasses.replace(model, links=links)) != sha


# --- calibrated model, actuation, a new version ------------------------------------------------


def test_calibrated_model_and_actuation(model, nominal):
    base = nominal_calibration(model)
    assert base.robot_sha256 == robot_sha256(model)
    assert np.array_equal(
        calibrated_actuation(model, base).counts_from_angles(np.full(12, 0.1), np.zeros(12)),
        nominal.counts_from_angles(np.full(12, 0.1), np.zeros(12)),
    )
    da, dt = _offsets(3)
    zero = {m: 100 * i for i, m in enumerate(nominal.motor_ids)}
    ea = {m: 25_000.0 for m in nominal.motor_ids}
    cal = updated(
        base,
        routine=Routine.KINEMATIC,
        residuals={"rms_after_mm": 0.05},
        links_mm=model.links + 0.25,
        alpha_offset_rad=da,
        theta_offset_rad=dt,
        motor_zero_counts=zero,
        rope_EA_N=ea,
    )
    m2 = calibrated_model(model, cal)
    np.testing.assert_array_equal(m2.links, model.links + 0.25)
    assert m2.name == model.name and m2.tables == model.tables
    act = calibrated_actuation(model, cal)
    np.testing.assert_array_equal(act.alpha_offset_rad, da)
    np.testing.assert_array_equal(act.motors.zero_offsets_counts, list(zero.values()))
    np.testing.assert_array_equal(act.routing.stiffness_EA_N, list(ea.values()))
    # the straight commanded pose (true angle = offset) is at the zero counts
    np.testing.assert_array_equal(act.counts_from_angles(da, dt), list(zero.values()))
    assert act.robot.links[0] == model.links[0] + 0.25


def test_updated_carries_the_other_fields(model):
    base = nominal_calibration(model)
    zero = {m: 7 for m in base.motor_ids}
    a = updated(base, routine="zero", residuals={"r": 1.0}, motor_zero_counts=zero)
    b = updated(
        a, routine=Routine.KINEMATIC, residuals={"rms_after_mm": 0.1}, links_mm=model.links + 1.0
    )
    assert dict(b.motor_zero_counts) == zero and b.routine is Routine.KINEMATIC
    assert dict(b.residuals) == {"rms_after_mm": 0.1}
    assert b.robot_sha256 == base.robot_sha256 and b.created_utc >= a.created_utc
    np.testing.assert_array_equal(b.links_mm, model.links + 1.0)
    assert set(UPDATABLE) == {
        "links_mm",
        "alpha_offset_rad",
        "theta_offset_rad",
        "motor_zero_counts",
        "rope_EA_N",
        "box",  # the box a routine ran on (issue 34)
        "physics",  # link masses, payload, friction (issue 38)
    }
    with pytest.raises(TypeError, match="robot_sha256"):
        updated(a, routine="manual", residuals={}, robot_sha256="0" * 64)
    with pytest.raises(CalibrationFileError, match=r"links_mm\[0\]"):
        updated(a, routine="manual", residuals={}, links_mm=[-1.0] + [1.0] * 11)


# --- the store, for one robot ---------------------------------------------------------------


def test_active_for_and_starting_point(model, tmp_path):
    store = CalibrationStore(tmp_path / "store")
    assert active_for(store, model) is None
    base, active, note = starting_point(store, model)
    assert active is None and "no active calibration" in note
    np.testing.assert_array_equal(base.links_mm, model.links)
    assert not base.alpha_offset_rad.any() and not any(base.motor_zero_counts.values())
    cal = updated(
        nominal_calibration(model), routine="manual", residuals={}, links_mm=model.links + 0.5
    )
    v = store.save(cal)
    act = active_for(store, model)
    assert act is not None and act.version == v and act.calibration == cal
    assert act.sha256 == json.loads(store.path_of(v).read_text())["sha256"]
    assert act.sha256 == file_sha256(cal, v)
    base, active, note = starting_point(store, model)
    assert note is None and base == cal and active.version == v
    # a calibration of another robot: refused for use, a fresh start for a routine
    other = dataclasses.replace(model, name="another arm")
    with pytest.raises(CalibrationFileError, match="belongs to robot description") as exc:
        active_for(store, other)
    assert "\n" not in str(exc.value) and "v0001.json" in str(exc.value)
    base, active, note = starting_point(store, other)
    assert active is None and "belongs to robot description" in note
    assert base.robot_sha256 == robot_sha256(other)
    # a damaged active file is refused by both
    store.path_of(v).write_text(store.path_of(v).read_text().replace("179.5", "179.6", 1))
    for fn in (active_for, starting_point):
        with pytest.raises(CalibrationFileError, match="checksum mismatch"):
            fn(store, model)


def test_check_belongs_names_ropes_the_description_does_not_have(model):
    cal = nominal_calibration(model)
    ids = list(cal.motor_ids)
    wrong = dataclasses.replace(cal, motor_zero_counts={**{m: 0 for m in ids[1:]}, "j99r0": 0})
    with pytest.raises(CalibrationFileError, match=r"motor_zero_counts .*unknown \['j99r0'\]"):
        check_belongs(model, wrong, "x.json")


def test_the_estimator_works_in_true_angles_with_offsets(model):
    """The consistency check's filter runs in the rope geometry's angles and reports true
    ones: with joint offsets, consistent feedback is not flagged and the estimate is the
    true configuration."""
    from hrm_ctrl.ropes.estimator import RopeConsistencyCheck

    da, dt = _offsets(8, deg=2.0)
    act = load_actuation(model, alpha_offset_rad=da, theta_offset_rad=dt)
    check = RopeConsistencyCheck(act, rate_hz=20.0)
    q = np.linspace(-0.6, 0.6, 24).reshape(2, 12)
    c = act.counts_from_angles(q[0], q[1])
    assert [check(c, c) for _ in range(5)] == [None] * 5
    assert check.max_figure < 2.0
    np.testing.assert_allclose(check.last.alpha, q[0], atol=1e-3)
    np.testing.assert_allclose(check.last.theta, q[1], atol=1e-3)


def test_a_calibration_lends_nothing_to_another_box(model, tmp_path):
    """``starting_point`` with the box at hand (a simulated one, known before it starts)
    and ``for_box`` (the zero routine's base, once the box is read): a calibration of
    another box, or of an unknown one, gives way to the description's values."""
    from calibration.apply import for_box, starting_point
    from drivers.identity import BoxIdentity, DriveIdentity

    def box(vendor, serial0):
        return BoxIdentity.of(
            {m: DriveIdentity(vendor, 0x402, 1, serial0 + k) for k, m in enumerate(MOTORS)}
        )

    MOTORS = nominal_calibration(model).motor_ids
    mine, other, real = box(0, 100), box(0, 900), box(0x9A, 100)
    cal = updated(
        nominal_calibration(model), routine="kinematic", residuals={},
        links_mm=model.links + 0.5, box=mine,
    )  # fmt: skip
    store = CalibrationStore(tmp_path)
    store.save(cal)
    base, active, note = starting_point(store, model, mine)
    assert base == cal and active is not None and note is None
    for at in (other, real):
        base, active, note = starting_point(store, model, at)
        assert active is None and base.box is None and "starting from the description" in note
        np.testing.assert_array_equal(base.links_mm, model.links)
    # the zero routine: a replaced drive keeps the rest; another box lends nothing
    replaced = BoxIdentity.of({**mine.drives, MOTORS[0]: other.drives[MOTORS[0]]})
    assert for_box(cal, replaced, model) == (cal, None)
    base, note = for_box(cal, other, model)
    np.testing.assert_array_equal(base.links_mm, model.links)
    assert "made on another simulated arm" in note
    nominal = nominal_calibration(model)
    assert for_box(nominal, real, model) == (nominal, None)  # nothing to lend
