"""The way back of a run in the cabins (hrm_ctrl.runtime.wayback): joined where the arm
stands, along the path to its first step, checked against the cabins' walls."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.errors import CollisionError


@pytest.fixture(scope="module")
def cabins(tmp_path_factory: pytest.TempPathFactory):
    from hrm_ctrl.cli import main
    from hrm_ctrl.formats.planfile import read_plan
    from hrm_ctrl.model import default_robot
    from hrm_ctrl.ropes.actuation import load_actuation
    from hrm_ctrl.runtime.playback import setpoints_of_plan
    from hrm_ctrl.runtime.wayback import surroundings_of_plan

    out: Path = tmp_path_factory.mktemp("plans") / "cabins.json"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        main(["plan", "--scenario", "cabins", "--out", str(out)])
    doc = read_plan(out)
    act = load_actuation(default_robot())
    sp = setpoints_of_plan(doc, act, period_s=0.01, speed_mm_per_s=50.0)
    return act, sp, surroundings_of_plan(doc, act.robot)


def test_from_between_two_rows_along_the_path_to_its_first_step(cabins) -> None:
    """Stopped between two rows (an abort stops at a fractional row): the way back joins
    the path where the arm is (no join to speak of), its setpoints start there and end at
    the plan's first step, every row within the motors' limits, clear of the walls."""
    from hrm_ctrl.ropes.trajectory import finite_differences
    from hrm_ctrl.runtime.wayback import return_setpoints, way_back

    act, sp, env = cabins
    row = 500
    held = np.rint((sp.counts[row] + sp.counts[row + 1]) / 2).astype(np.int64)
    back = way_back(act, sp, held, row, env, start_counts=sp.counts[0])
    assert back.join_mm < 0.05 and back.row in (row, row + 1)
    assert 0.0 < back.clearance_mm and back.join_clearance_mm > 0.0
    rs = return_setpoints(act, back, period_s=0.01, speed_mm_per_s=50.0, where="return")
    assert np.abs(rs.counts[0] - held).max() <= 5  # a chord between rows vs the curved path
    assert np.array_equal(rs.counts[-1], sp.counts[0])
    v, a = finite_differences(rs.counts, 0.01)
    assert (v <= act.max_rate_counts_per_s).all() and (a <= act.max_accel_counts_per_s2).all()
    # the path back is the run's path: every row of it near one the run played
    played = sp.counts[: row + 2].astype(np.float64)
    gaps = [np.abs(played - r).max(axis=1).min() for r in rs.counts[::25]]
    assert max(gaps) < 200  # counts (0.1 mm of rope): the same path, another timing


def test_a_quick_stop_past_the_last_setpoint_joins_the_nearest_point(cabins) -> None:
    """A quick stop carries the arm past the last setpoint it was sent: the nearest point
    is searched beyond where the playback stood, and the join is short."""
    from hrm_ctrl.runtime.wayback import way_back

    act, sp, env = cabins
    sent = 400
    held = sp.counts[sent + 30] + 3  # 30 cycles on, a few counts off the path
    back = way_back(act, sp, held, sent, env, start_counts=sp.counts[0])
    assert abs(back.row - (sent + 30)) <= 1 and back.join_mm < 0.5


def test_a_join_through_a_wall_is_refused(cabins) -> None:
    """An arm that is not near the path (here the straight arm, which reaches through the
    cabins' entrance wall) is not joined to it through the wall: refused, naming it."""
    from hrm_ctrl.runtime.wayback import straight_home_clearance, way_back

    act, sp, env = cabins
    straight = act.counts_from_angles(np.zeros(12), np.zeros(12))
    with pytest.raises(CollisionError, match=r"way back: the straight move from where the arm"):
        way_back(act, sp, straight, 600, env, start_counts=sp.counts[0])
    # and home from deep inside refuses where the straight move in joint space would hit
    c, at = straight_home_clearance(act, env, sp.counts[700])
    assert c.least_mm < 0.0 and 0.0 < at <= 1.0
