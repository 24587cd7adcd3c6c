"""The trail: it grows at the tip as steered, is cut for a new branch, and round-trips as a
path file: saved, planned by ``hrm plan --path``, played through the plan -> counts path
of ``hrm run`` (``hrm ropes``: the same checked setpoints)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.drive.command import DriveError
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.planning.known_path import load_path_csv
from tests.hrm_ctrl.cli.cli_helpers import run_cli

ENTRY = np.array([1200.0, 100.0, 300.0])


@settings(max_examples=30, deadline=None, derandomize=True)
@given(
    st.lists(
        st.tuples(
            st.floats(0.1, 40.0),
            st.floats(-0.02, 0.02),
            st.floats(-0.02, 0.02),
        ),
        min_size=1,
        max_size=8,
    )
)
def test_the_trail_grows_by_what_the_tip_advances(moves: list[tuple[float, float, float]]) -> None:
    t = Trail.starting_at(ENTRY, np.array([1.0, 0.0, 0.0]))
    total = 0.0
    for ds, yaw, pitch in moves:
        t.extend(ds, yaw, pitch)
        total += ds
        assert abs(float(np.linalg.norm(t.heading)) - 1.0) < 1e-12
        assert abs(float(t.heading @ t.up)) < 1e-12
    # the polyline is the arcs' chords (at most 1 mm of arc each): never longer, short by
    # at most kappa^2 / 24 a mm
    assert t.length <= total + 1e-9
    assert t.length >= total * (1.0 - 2 * 0.02**2 / 24.0) - 1e-9
    assert np.array_equal(t.point_at(t.length), t.end)


def test_a_turn_draws_a_circle_of_its_radius() -> None:
    t = Trail.starting_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    t.extend(math.pi * 100.0, 1.0 / 100.0, 0.0)  # half a circle to the left, radius 100
    assert np.allclose(t.end, [0.0, 200.0, 0.0], atol=1e-6)
    r = np.linalg.norm(t.points - [0.0, 100.0, 0.0], axis=1)
    assert np.allclose(r, 100.0, atol=1e-9)
    assert np.allclose(t.heading, [-1.0, 0.0, 0.0], atol=1e-9)


def test_cut_starts_a_new_branch_at_the_tip() -> None:
    t = Trail.starting_at(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    t.extend(50.0, 0.0, 0.0)
    t.extend(30.0, 0.0, 0.01)
    t.cut(40.0)
    assert t.length == pytest.approx(40.0) and np.allclose(t.end, [40.0, 0.0, 0.0])
    assert np.allclose(t.heading, [1.0, 0.0, 0.0])
    t.extend(10.0, 0.0, 0.0)
    assert np.allclose(t.end, [50.0, 0.0, 0.0])


def test_a_trail_of_one_point_is_not_saved(tmp_path: Path) -> None:
    with pytest.raises(DriveError, match="nothing drawn yet"):
        Trail.starting_at(ENTRY, np.array([1.0, 0.0, 0.0])).save(tmp_path / "t.csv")
    assert not (tmp_path / "t.csv").exists()


def test_the_trail_round_trips_save_plan_play(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    t = Trail.starting_at(ENTRY, np.array([1.0, 0.0, 0.0]))
    t.extend(20.0, 0.0, 0.0)
    t.extend(20.0, 0.0, -0.01)
    t.extend(10.0, 0.005, 0.0)
    f = tmp_path / "trail.csv"
    t.save(f)
    path = load_path_csv(f)
    assert np.allclose(path.points, t.points, atol=1e-6)
    plan = tmp_path / "plan.json"
    rc, out, err = run_cli(["plan", "--path", str(f), "--out", str(plan), "--json"], capsys)
    assert rc == 0, err
    report = json.JSONDecoder().raw_decode(out)[0]  # then "plan written to ..."
    doc = json.loads(plan.read_text())
    assert np.allclose(doc["path_mm"], path.points)
    assert report["tip_error_mm"] < 1e-3
    rc, out, err = run_cli(["ropes", str(plan), "--speed", "20", "--json"], capsys)
    assert rc == 0, err
    summary = json.loads(out)
    assert summary["steps"] == len(doc["steps"]) and summary["playback"]["cycles"] > 0


def test_a_reader_on_another_thread_always_sees_the_trail_with_its_end() -> None:
    """The shape watch copies :attr:`Trail.points` on its own thread while the control
    thread advances: a straight advance lengthens the last segment in place, and a copy
    taken while it did once lacked that segment (the tip read as 71.6 mm off the trail
    in a whole run).  With the interpreter switching threads every microsecond, every
    copy's end is as far along as the one before."""
    import sys
    import threading

    t = Trail.starting_at(ENTRY, np.array([1.0, 0.0, 0.0]))
    t.extend(1.0, 0.0, 0.0)
    done = threading.Event()
    went_back: list[float] = []
    copies = 0

    def read() -> None:
        nonlocal copies
        last = 0.0
        while not done.is_set():
            end = float(np.array(t.points)[-1, 0] - ENTRY[0])
            if end < last:
                went_back.append(last - end)
            last = end
            copies += 1

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    reader = threading.Thread(target=read, daemon=True)
    try:
        reader.start()
        for _ in range(20_000):
            t.extend(0.05, 0.0, 0.0)
    finally:
        done.set()
        reader.join(5.0)
        sys.setswitchinterval(interval)
    assert copies > 100
    assert went_back == []
    assert t.n_points == 2 and t.length == pytest.approx(1001.0)
