"""Collecting poses (calibration/collect.py) with a stand-in session and instrument: every
move within the motor limits and rest to rest, the instrument read once per pose, and the
pose data in the fit's convention (the rope geometry's angles of the commanded counts)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.collect import collect_poses, move_table
from calibration.kinematic import spread_configurations
from hrm_ctrl.errors import CalibrationDataError
from hrm_ctrl.kinematics import frames
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import RopeLimitError, load_actuation

PERIOD_S = 0.01


class FakeSession:
    """Plays each source's table at once; the arm is where the last row put it."""

    def __init__(self, actuation, start_counts):
        self.act = actuation
        self.actual = np.asarray(start_counts, dtype=np.int64)
        self.tables: list[np.ndarray] = []

    def stream(self, source):
        source.start(self.actual, PERIOD_S)
        self.tables.append(source.table)
        self.actual = source.table[-1].copy()


class FakeTracker:
    """The end point of the arm at the session's counts, through a true arm whose joints
    sit at commanded + offset (the rope layer ``truth`` maps counts to commanded angles)."""

    def __init__(self, session, commanded, model, offsets):
        self.session, self.commanded, self.model, self.offsets = session, commanded, model, offsets
        self.calls: list[int] = []

    def measure(self, n):
        self.calls.append(n)
        a, t, _ = self.commanded.angles_from_counts(self.session.actual)
        q = (a + self.offsets[0])[None], (t + self.offsets[1])[None]
        return frames(self.model, *q)[1][0, -1]


@pytest.fixture(scope="module")
def model():
    return default_robot()


def test_collect_writes_commanded_angles_and_moves_within_limits(model):
    rng = np.random.default_rng(4)
    da, dt = np.radians(rng.uniform(-1, 1, 12)), np.radians(rng.uniform(-1, 1, 12))
    act = load_actuation(model, alpha_offset_rad=da, theta_offset_rad=dt)  # the active ones
    nominal = load_actuation(model)
    session = FakeSession(act, act.counts_from_angles(da, dt))  # parked commanded-straight
    tracker = FakeTracker(session, nominal, model, (da, dt))
    alpha, theta = spread_configurations(model, 5, rng)
    data = collect_poses(session, act, tracker, alpha, theta, period_s=PERIOD_S, samples=7)
    assert tracker.calls == [7] * 5 and len(data) == 5
    # commanded = the rope geometry's angles: the targets less the active offsets
    np.testing.assert_allclose(data.alpha_rad, alpha - da, atol=1e-4)
    np.testing.assert_allclose(data.theta_rad, theta - dt, atol=1e-4)
    # with the true offsets (here the active ones) the points are the targets' end points
    expected = frames(model, alpha, theta)[1][:, -1, :]
    np.testing.assert_allclose(data.points_mm, expected, atol=0.05)
    for table in session.tables:
        act.check_counts(table, dt_s=PERIOD_S)  # speed and acceleration within the limits
        assert np.array_equal(table[-1], table[-2])  # ends at rest (the hold)


def test_move_table_is_rest_to_rest_and_bounded(model):
    act = load_actuation(model)
    z = np.zeros(12)
    table = move_table(act, (z, z), (z + 0.5, z - 0.4), PERIOD_S)
    v = np.diff(table.astype(float), axis=0) / PERIOD_S
    assert np.all(np.abs(v) <= 0.55 * act.max_rate_counts_per_s)  # half the limit, + curvature
    assert np.all(np.abs(v[0]) < 0.01 * act.max_rate_counts_per_s)  # starts and ends at rest
    assert np.all(np.abs(v[-1]) < 0.01 * act.max_rate_counts_per_s)
    np.testing.assert_array_equal(table[0], act.counts_from_angles(z, z))
    np.testing.assert_array_equal(table[-1], act.counts_from_angles(z + 0.5, z - 0.4))


def test_collect_refuses_bad_targets_before_moving(model):
    act = load_actuation(model)
    session = FakeSession(act, np.zeros(act.n_motors))
    tracker = FakeTracker(session, act, model, (np.zeros(12), np.zeros(12)))
    a = np.zeros((2, 12))
    with pytest.raises(CalibrationDataError, match=r"targets must be \(N, 12\)"):
        collect_poses(session, act, tracker, a[:, :5], a[:, :5], period_s=PERIOD_S)
    a[1, 4] = 1.2  # beyond the 60 deg limit
    with pytest.raises(RopeLimitError, match="joint 5: alpha"):
        collect_poses(session, act, tracker, a, np.zeros((2, 12)), period_s=PERIOD_S)
    with pytest.raises(CalibrationDataError, match="samples must be"):
        collect_poses(session, act, tracker, a * 0, a * 0, period_s=PERIOD_S, samples=0)
    assert session.tables == [] and tracker.calls == []
    session.actual = None
    with pytest.raises(CalibrationDataError, match="not brought up"):
        collect_poses(session, act, tracker, a * 0, a * 0, period_s=PERIOD_S)


def test_a_measurement_that_is_not_a_point_is_refused(model):
    act = load_actuation(model)
    session = FakeSession(act, np.zeros(act.n_motors, dtype=np.int64))

    class Broken:
        def measure(self, n):
            return np.array([1.0, np.nan, 2.0])

    with pytest.raises(CalibrationDataError, match="not one finite point"):
        collect_poses(session, act, Broken(), np.zeros((1, 12)), np.zeros((1, 12)), period_s=0.01)


def test_a_stopped_collection_keeps_its_poses_and_resumes_from_them(model, tmp_path):
    """Every pose is written down as it is measured (PoseJournal, one atomic file): a
    collection that stops at pose 3 of 5 keeps 2; resumed on the 3 missing targets it ends
    with the same 5 poses as a collection that never stopped; a journal of another
    collection is refused, not overwritten."""
    from calibration.collect import PoseJournal, journal_key
    from hrm_ctrl.errors import DriverError

    act = load_actuation(model)
    zero = (np.zeros(12), np.zeros(12))
    alpha, theta = spread_configurations(model, 5, np.random.default_rng(9))
    key = journal_key(alpha, theta, "test arm")
    path = tmp_path / f"collect-{key}.json"

    session = FakeSession(act, act.counts_from_angles(*zero))
    whole = collect_poses(session, act, FakeTracker(session, act, model, zero), alpha, theta,
                          period_s=PERIOD_S)  # fmt: skip

    class Failing(FakeTracker):
        def measure(self, n):
            if len(self.calls) == 2:
                raise DriverError("tracker: no answer (simulated failure)")
            return super().measure(n)

    journal = PoseJournal(path, key, 5)
    session = FakeSession(act, act.counts_from_angles(*zero))
    keep = lambda _k, a, t, p: journal.add(a, t, p)  # noqa: E731
    with pytest.raises(DriverError):
        collect_poses(session, act, Failing(session, act, model, zero), alpha, theta,
                      period_s=PERIOD_S, on_pose=keep)  # fmt: skip
    again = PoseJournal(path, key, 5)  # what the next command reads
    assert len(again) == 2
    session = FakeSession(act, act.counts_from_angles(*zero))
    keep = lambda _k, a, t, p: again.add(a, t, p)  # noqa: E731
    collect_poses(session, act, FakeTracker(session, act, model, zero), alpha[2:], theta[2:],
                  period_s=PERIOD_S, on_pose=keep)  # fmt: skip
    kept = again.kept
    np.testing.assert_allclose(kept.points_mm, whole.points_mm, atol=1e-9)
    np.testing.assert_allclose(kept.alpha_rad, whole.alpha_rad, atol=1e-9)
    np.testing.assert_allclose(kept.theta_rad, whole.theta_rad, atol=1e-9)
    text = path.read_text()
    with pytest.raises(CalibrationDataError, match="the poses of another collection"):
        PoseJournal(path, journal_key(alpha, theta, "another arm"), 5)
    assert path.read_text() == text
    path.write_text("{not json")
    with pytest.raises(CalibrationDataError, match="not a pose journal"):
        PoseJournal(path, key, 5)
