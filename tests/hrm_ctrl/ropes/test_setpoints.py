"""The one plan -> motor-counts path: control-rate table, return legs, travel checks,
messages naming plan steps, and the same counts for ``hrm ropes`` and ``hrm run``."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.cli import main
from hrm_ctrl.errors import RopeError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, RopeLimitError
from hrm_ctrl.ropes.setpoints import interpolate_rows, plan_setpoints


def bend(n: int = 5, alpha_deg: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, theta) (n, 12): every joint bends a little more each step."""
    a = np.deg2rad(alpha_deg) * np.arange(n)[:, None] / (n - 1) * np.ones((1, 12))
    return a, -a / 2


def test_plan_table_at_the_control_rate(act: Actuation) -> None:
    alpha, theta = bend()
    sp = plan_setpoints(act, 10.0 * np.arange(5), alpha, theta, period_s=0.01, speed_mm_per_s=40.0)
    # 40 mm at up to 40 mm/s: at least 1 s, plus the ramps from and to rest
    assert 1.0 <= sp.duration_s <= 1.3 and sp.counts.shape == (sp.n_cycles, act.n_motors)
    assert sp.duration_s == pytest.approx((sp.n_cycles - 1) * 0.01)
    np.testing.assert_array_equal(sp.counts[0], act.counts_from_angles(alpha[0], theta[0]))
    np.testing.assert_array_equal(sp.counts[-1], act.counts_from_angles(alpha[-1], theta[-1]))
    np.testing.assert_array_equal(sp.step_counts, act.counts_from_angles(alpha, theta))
    act.check_counts(sp.counts, dt_s=0.01)  # speed and acceleration between rows
    # the travel rate never above the cap; every step is passed, in order
    assert np.diff(sp.sigma_mm).max() / 0.01 <= 40.0 * (1 + 1e-9)
    assert np.all(np.diff(sp.step_time_s) > 0) and sp.step_time_s[-1] == sp.duration_s
    # each row names the step it approaches; a row on a step is that step's
    assert np.all(np.diff(sp.step_of_row) >= 0) and sp.step_of_row[[0, -1]].tolist() == [0, 4]
    r = int(np.flatnonzero(sp.step_of_row == 2)[0])
    assert sp.label(r) == "plan step 2 (travel 20.0 mm)" and sp.sigma_mm[r] > 10.0
    a_rows, t_rows = sp.row_angles()
    np.testing.assert_allclose(a_rows[0], alpha[0], atol=1e-15)
    np.testing.assert_array_equal(act.counts_from_angles(a_rows, t_rows), sp.counts)
    assert not sp.counts.flags.writeable


def test_a_return_leg_goes_out_and_comes_back(act: Actuation) -> None:
    alpha, theta = bend(n=5, alpha_deg=20.0)
    back = np.arange(3, -1, -1)
    travel = np.concatenate([10.0 * np.arange(5), 10.0 * back])  # 0..40 then 30..0
    phase = ["in"] * 5 + ["return"] * 4
    sp = plan_setpoints(
        act,
        travel,
        np.vstack([alpha, alpha[back]]),
        np.vstack([theta, theta[back]]),
        period_s=0.01,
        speed_mm_per_s=40.0,
        phase=phase,
    )
    assert 2.0 <= sp.duration_s <= 2.6  # 40 mm in, 40 back, each leg from and to rest
    straight = act.counts_from_angles(alpha[0], theta[0])
    bent = act.counts_from_angles(alpha[-1], theta[-1])
    np.testing.assert_array_equal(sp.counts[0], straight)
    far = np.flatnonzero(sp.sigma_mm == 40.0)  # the far end: one row, at rest
    assert far.size == 1
    np.testing.assert_array_equal(sp.counts[far[0]], bent)
    np.testing.assert_array_equal(sp.counts[-1], straight)  # and back
    # the way back retraces the way in: the same configurations at the mirrored positions
    back_rows = np.arange(far[0], sp.n_cycles)
    a_back, t_back = sp.path.angles_at(sp.sigma_mm[back_rows])
    a_in, t_in = sp.path.angles_at(80.0 - sp.sigma_mm[back_rows])
    np.testing.assert_allclose(a_back, a_in, atol=1e-12)
    np.testing.assert_allclose(t_back, t_in, atol=1e-12)
    assert abs(sp.n_cycles - 1 - 2 * far[0]) <= 4  # and takes as long, within a few cycles
    moved = np.abs(sp.counts - straight).max(axis=1)
    assert int(moved.argmax()) == far[0] and moved[far[0]] > 1000
    assert np.all(np.diff(sp.step_of_row) >= 0) and sp.step_of_row[-1] == 8
    r = int(np.flatnonzero(sp.step_of_row == 7)[0])  # the first row past step 6
    assert sp.label(r - 1) == "plan step 6 (travel 20.0 mm)"
    assert sp.label(r) == "plan step 7 (travel 10.0 mm)"


def test_a_planner_return_plan_plays(act: Actuation) -> None:
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.scenarios import scenario

    sc = scenario("bent-pipe")
    plan = plan_path(act.robot, sc.path, PlanOptions(step=10.0, return_to_start=True), sc)
    sp = plan_setpoints(
        act,
        plan.travel,
        plan.alpha,
        plan.theta,
        phase=plan.phase,
        period_s=0.01,
        speed_mm_per_s=50.0,
    )
    at_cap = 2 * sc.path.length / 50.0
    assert at_cap <= sp.duration_s <= at_cap + 1.0  # the cap binds; ramps at both ends
    assert abs(int(sp.counts[-1].astype(np.int64).max() - sp.counts[0].max())) <= 1


@pytest.mark.parametrize(
    ("travel", "phase", "message"),
    [
        (
            [0.0, 10.0, 5.0, 20.0],
            None,
            "plan step 2 (travel 5.0 mm): travel goes back from 10.0 mm (plan step 1) "
            "within the 'in' phase",
        ),
        (
            [0.0, 10.0, 10.0, 20.0],
            None,
            "plan step 2 (travel 10.0 mm): travel repeats 10.0 mm (plan step 1) within the "
            "'in' phase",
        ),
        (
            [0.0, 10.0, 5.0, 8.0],
            ["in", "in", "return", "return"],
            "plan step 3 (travel 8.0 mm): travel goes up from 5.0 mm (plan step 2) within the "
            "'return' phase",
        ),
        (
            [0.0, 10.0, 12.0, 8.0],
            ["in", "in", "return", "return"],
            "plan step 2 (travel 12.0 mm): travel goes up from 10.0 mm (plan step 1) within "
            "the 'return' phase",
        ),
    ],
    ids=["back", "repeat", "return-up", "return-starts-up"],
)
def test_travel_the_wrong_way_within_a_phase_is_refused(
    act: Actuation, travel: list[float], phase: list[str] | None, message: str
) -> None:
    alpha, theta = bend(n=4)
    with pytest.raises(RopeError) as info:
        plan_setpoints(
            act,
            travel,
            alpha,
            theta,
            phase=phase,
            period_s=0.01,
            speed_mm_per_s=20.0,
            where="p.json",
        )
    assert str(info.value) == f"p.json: {message}"


def test_limit_messages_name_the_plan_step(act: Actuation) -> None:
    alpha, theta = bend(n=5)
    alpha[3, 0] = np.deg2rad(80.0)
    with pytest.raises(RopeLimitError) as info:
        plan_setpoints(act, 5.0 * np.arange(5), alpha, theta, period_s=0.01, speed_mm_per_s=20)
    assert str(info.value).startswith("plan step 3 (travel 15.0 mm): joint 1: alpha = 1.396")
    # drum travel: a rope layer whose drums are short for this bend
    alpha, theta = bend(n=5, alpha_deg=20.0)
    full = act.counts_from_angles(alpha, theta)
    i = int(np.abs(full[-1]).argmax())
    cmax, cmin = act.counts_max.copy(), act.counts_min.copy()
    cmax[i] = cmin[i] = 0
    cmax[i] = np.abs(full[2:4, i]).max() + 1
    cmin[i] = -cmax[i]
    short = dataclasses.replace(act, counts_min=cmin, counts_max=cmax)
    with pytest.raises(RopeLimitError) as info:
        plan_setpoints(short, 5.0 * np.arange(5), alpha, theta, period_s=0.01, speed_mm_per_s=20)
    assert str(info.value).startswith(f"plan step 4 (travel 20.0 mm): motor {act.motor_ids[i]}")
    assert "outside" in str(info.value)
    # motor speed: a cap the motors cannot follow slows the playback down instead
    sp = plan_setpoints(act, 5.0 * np.arange(5), alpha, theta, period_s=0.01, speed_mm_per_s=400)
    assert sp.duration_s > 20.0 / 400 * 1.5
    act.check_counts(sp.counts, dt_s=0.01)
    # a path that leaves the joint limits between two steps (the spline overshoots)
    zig = np.zeros((4, 12))
    zig[:, 0] = np.deg2rad([0.0, 59.0, 59.0, 0.0])
    with pytest.raises(RopeLimitError) as info:
        plan_setpoints(act, 5.0 * np.arange(4), zig, zig * 0, period_s=0.01, speed_mm_per_s=20)
    msg = str(info.value)
    assert msg.startswith("plan step 2 (travel 10.0 mm): on the way from plan step 1: joint 1")
    assert "\n" not in msg


def test_bad_arguments_are_refused(act: Actuation) -> None:
    alpha, theta = bend(n=3)
    travel = [0.0, 1.0, 2.0]
    kw: dict[str, Any] = {"period_s": 0.01, "speed_mm_per_s": 10.0}
    with pytest.raises(RopeError, match="speed must be > 0 mm/s"):
        plan_setpoints(act, travel, alpha, theta, period_s=0.01, speed_mm_per_s=0.0)
    with pytest.raises(RopeError, match="control period must be > 0 s"):
        plan_setpoints(act, travel, alpha, theta, period_s=float("nan"), speed_mm_per_s=1.0)
    with pytest.raises(RopeError, match=r"angles \(S, 12\)"):
        plan_setpoints(act, travel, alpha[:, :11], theta, **kw)
    with pytest.raises(RopeError, match="phase must be 3 of"):
        plan_setpoints(act, travel, alpha, theta, phase=["in", "out", "in"], **kw)
    with pytest.raises(RopeError, match="finite"):
        plan_setpoints(act, [0.0, np.nan, 2.0], alpha, theta, **kw)
    with pytest.raises(RopeError, match=r"^p: 2e\+09 s at 1e-09 mm/s exceeds the longest run"):
        plan_setpoints(act, travel, alpha, theta, period_s=0.01, speed_mm_per_s=1e-9, where="p")


def test_one_step_is_one_row(act: Actuation) -> None:
    alpha, theta = bend(n=3)
    sp = plan_setpoints(act, [7.0], alpha[2:], theta[2:], period_s=0.01, speed_mm_per_s=10.0)
    assert sp.n_cycles == 1 and sp.duration_s == 0.0 and sp.label(0).startswith("plan step 0")
    np.testing.assert_array_equal(sp.counts, sp.step_counts)


@settings(max_examples=50, deadline=None)
@given(
    knots=st.lists(st.floats(0, 10), min_size=2, max_size=6, unique=True),
    q=st.lists(st.floats(-1, 11), min_size=1, max_size=8),
)
def test_interpolate_rows_matches_numpy(knots: list[float], q: list[float]) -> None:
    t = np.sort(np.asarray(knots))
    rows = np.stack([np.sin(t), t**2], axis=1)
    got = interpolate_rows(np.asarray(q), t, rows)
    for j in range(2):
        assert np.allclose(got[:, j], np.interp(q, t, rows[:, j]))


def write_plan_file(path: Path) -> None:
    """Out 40 mm and back, 10 mm a step (a step every 25 control cycles at 40 mm/s)."""
    robot = default_robot()
    alpha, theta = bend(n=5, alpha_deg=10.0)
    back = np.arange(3, -1, -1)
    alpha, theta = np.vstack([alpha, alpha[back]]), np.vstack([theta, theta[back]])
    travel = np.concatenate([10.0 * np.arange(5), 10.0 * back])
    O = joint_centres(robot, alpha, theta)
    steps = [
        {
            "travel_mm": float(travel[k]),
            "phase": "in" if k < 5 else "return",
            "alpha_rad": alpha[k].tolist(),
            "theta_rad": theta[k].tolist(),
            "joints_mm": O[k].tolist(),
        }
        for k in range(len(travel))
    ]
    doc = {
        "format": "hrm-plan/1",
        "robot": {"links_mm": robot.links.tolist()},
        "path_mm": [[0.0, 0.0, 0.0], [40.0, 0.0, 0.0]],
        "steps": steps,
        "report": {},
    }
    path.write_text(json.dumps(doc))


def test_hrm_ropes_and_playback_get_the_same_counts(
    tmp_path: Path, act: Actuation, capsys: pytest.CaptureFixture[str]
) -> None:
    from hrm_ctrl.cli.run import _source

    plan = tmp_path / "plan.json"
    write_plan_file(plan)
    out = tmp_path / "sp.csv"
    assert main(["ropes", str(plan), "--speed", "40", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert 201 <= summary["playback"]["cycles"] <= 260
    header, *rows = list(csv.reader(out.open()))
    assert header[:3] == ["t_s", "step", "travel_mm"]
    per_step = np.array([[int(v) for v in r[3:]] for r in rows])

    from hrm_ctrl.cli import run as run_cli

    parser = argparse.ArgumentParser()
    run_cli.register(parser)
    args = parser.parse_args([str(plan), "--speed", "40"])
    source, _hold, record = _source(args, act, 0.01)
    assert record["plan_steps"] == 9
    source.precheck(0.01)
    source.start(per_step[0], 0.01)  # already at the plan's start: no lead-in
    assert source.n_lead_in == 0
    n = summary["playback"]["cycles"]
    body = source.table[:n]
    travel, alpha, theta, phase = _plan_arrays(plan)
    sp = plan_setpoints(act, travel, alpha, theta, phase=phase, period_s=0.01, speed_mm_per_s=40.0)
    np.testing.assert_array_equal(body, sp.counts)  # what hrm ropes reports is what plays
    t_s = [float(r[0]) for r in list(csv.reader(out.open()))[1:]]
    np.testing.assert_allclose(t_s, sp.step_time_s, atol=1e-6)
    np.testing.assert_array_equal(body[n // 2], per_step[4])  # the far end, half way
    np.testing.assert_array_equal(source.table[n:], np.repeat(per_step[-1:], 20, axis=0))
    d = source.describe()
    assert d["source"] == "plan" and d["steps"] == 9 and d["body_cycles"] == n


def _plan_arrays(path: Path) -> tuple[Any, ...]:
    doc = json.loads(path.read_text())["steps"]
    travel = [st["travel_mm"] for st in doc]
    alpha = np.array([st["alpha_rad"] for st in doc])
    theta = np.array([st["theta_rad"] for st in doc])
    return travel, alpha, theta, [st["phase"] for st in doc]


def test_a_step_that_rounds_over_a_joint_limit_is_refused(act: Actuation) -> None:
    """Every alpha at 59.999999 deg is inside the open limit, but its whole counts decode
    to 60.0014 deg on joint 1 (a red-team plan: 22 such rows went to the drives): refused
    naming the plan step; 59.99 deg plays, every row decoding inside the limits."""
    import math

    a = np.zeros((2, 12))
    a[1] = math.radians(59.999999)
    with pytest.raises(RopeLimitError, match=r"^plan step 1 \(travel 100.0 mm\): rounded to "
                       r"whole counts: joint 1: alpha") as info:  # fmt: skip
        plan_setpoints(act, [0.0, 100.0], a, np.zeros((2, 12)), period_s=0.01,
                       speed_mm_per_s=50.0)  # fmt: skip
    assert "\n" not in str(info.value)
    a[1] = math.radians(59.99)
    sp = plan_setpoints(act, [0.0, 100.0], a, np.zeros((2, 12)), period_s=0.01,
                        speed_mm_per_s=50.0)  # fmt: skip
    back_a, back_t = act.angles_from_counts(sp.counts[-20:])[:2]
    act.check_angles(back_a, back_t)
