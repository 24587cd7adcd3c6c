"""Setpoint sources (hold, jog, plan) and a short run of the full 36-drive box."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.config import load_box_config
from drivers.protocol import cia402 as c
from drivers.session import DriveBox
from drivers.sources import (
    HoldSource,
    JogSource,
    PlanSource,
    SetpointError,
    interpolate_rows,
    ramp_table,
)
from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation
from sim_bus.box import SimBox
from sim_bus.config import sim_config_from_dict


def small_plan(alpha_deg: float = 5.0, n: int = 5) -> dict:
    steps = []
    for k in range(n):
        a = np.deg2rad(alpha_deg) * k / (n - 1)
        steps.append(
            {
                "travel_mm": 10.0 * k,
                "alpha_rad": [a] * 12,
                "theta_rad": [-a / 2] * 12,
                "joints_mm": [[0.0, 0.0, 0.0]] * 13,
            }
        )
    return {"format": "hrm-plan/1", "steps": steps}


def test_plan_source_table(actuation: Actuation) -> None:
    plan = small_plan()
    src = PlanSource(actuation, plan, speed_mm_per_s=40.0, hold_s=0.05)
    src.precheck(0.01)
    start = np.zeros(actuation.n_motors, dtype=np.int64)
    src.start(start, 0.01)
    body = src.plan_table(0.01)
    # 40 mm at 40 mm/s: 1 s, 101 cycles; the first equals the first step already.
    assert body.shape == (101, actuation.n_motors)
    assert src.n_lead_in == 0
    last = actuation.counts_from_angles(
        np.asarray(plan["steps"][-1]["alpha_rad"]), np.asarray(plan["steps"][-1]["theta_rad"])
    )
    assert np.array_equal(body[-1], last)
    assert np.array_equal(src.table[-1], last) and src.n_cycles == 101 + 5
    mid = actuation.counts_from_angles(
        np.asarray(plan["steps"][2]["alpha_rad"]), np.asarray(plan["steps"][2]["theta_rad"])
    )
    assert np.array_equal(body[50], mid)
    actuation.check_counts(src.table, previous=start, dt_s=0.01)


def test_plan_source_lead_in_from_elsewhere(actuation: Actuation) -> None:
    src = PlanSource(actuation, small_plan(), speed_mm_per_s=40.0)
    start = np.full(actuation.n_motors, 20_000, dtype=np.int64)
    src.start(start, 0.01)
    assert src.n_lead_in >= 1
    actuation.check_counts(src.table, previous=start, dt_s=0.01)
    assert np.array_equal(src.table[src.n_lead_in - 1], src.plan_table(0.01)[0])


def test_plan_outside_joint_limits_is_refused(actuation: Actuation) -> None:
    src = PlanSource(actuation, small_plan(alpha_deg=80.0), speed_mm_per_s=40.0)
    with pytest.raises(RopeError):
        src.precheck(0.01)


def test_jog_and_hold(actuation: Actuation) -> None:
    start = np.zeros(actuation.n_motors, dtype=np.int64)
    jog = JogSource(actuation, "j02r1", -10_000.0, 0.1, hold_s=0.02)
    jog.precheck(0.01)
    jog.start(start, 0.01)
    i = actuation.motor_ids.index("j02r1")
    assert jog.table[:, i].tolist() == [-100 * k for k in range(1, 11)] + [-1000, -1000]
    assert np.count_nonzero(jog.table[:, np.arange(actuation.n_motors) != i]) == 0
    with pytest.raises(SetpointError, match="unknown rope motor 'nope'"):
        JogSource(actuation, "nope", 1.0, 1.0)
    hold = HoldSource(n_cycles=3)
    hold.start(start + 7, 0.01)
    assert [None if x is None else int(x[0]) for x in map(hold.setpoint, range(4))] == [
        7,
        7,
        7,
        None,
    ]


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


@settings(max_examples=50, deadline=None)
@given(
    delta=st.lists(st.integers(-100_000, 100_000), min_size=3, max_size=3),
    rate=st.floats(1_000, 500_000),
)
def test_ramp_table_respects_the_rate(delta: list[int], rate: float) -> None:
    start = np.array([5, -5, 0])
    end = start + np.array(delta)
    table = ramp_table(start, end, np.full(3, rate), 0.01)
    steps = np.abs(np.diff(np.vstack([start, table]), axis=0))
    assert np.all(steps <= 0.5 * rate * 0.01 + 1)
    assert np.array_equal(table[-1], end)


def test_full_box_36_drives_short_run(actuation: Actuation, tmp_path: Path) -> None:
    """Default configuration (36 drives, 2 buses) on virtual buses against the simulated
    box in this interpreter: bring-up and 50 cycles.  The TPDO tolerance is relaxed
    because the simulated drives share the interpreter (timing is benchmarked, not
    tested)."""
    cfg = load_box_config(None)
    tag = uuid.uuid4().hex[:8]
    cfg = cfg.with_bus_kwargs(
        [{"interface": "virtual", "channel": f"full-{tag}-{b.name}"} for b in cfg.buses]
    ).with_control(missing_tpdo_cycles=25)
    with SimBox(sim_config_from_dict(cfg.to_dict(), "test"), actuation=actuation) as sim:
        with DriveBox(cfg, actuation, log_dir=tmp_path, run_name="full") as box:
            actual = box.bring_up()
            assert actual.shape == (36,)
            assert {c.decode_state(sw) for sw in sim.statuswords().values()} == {
                c.State402.OPERATION_ENABLED
            }
            result = box.stream(JogSource(actuation, "j12r2", 20_000.0, 0.3, hold_s=0.2))
            assert result.completed and result.cycles == 50
        i = actuation.motor_ids.index("j12r2")
        assert abs(int(sim.counts()[i]) - 6000) <= 2
    assert (tmp_path / "full.json").exists()
    assert (tmp_path / "full_can0.blf").stat().st_size > 0


def test_jog_outside_the_joint_limits_is_refused(actuation: Actuation) -> None:
    """Rope range and speed alone let this jog bend joint 1 to about -83 deg."""
    jog = JogSource(actuation, "j01r0", 400_000.0, 0.5)
    with pytest.raises(SetpointError, match=r"^jog j01r0 .*joint limits") as info:
        jog.precheck(0.01)
    assert "\n" not in str(info.value)
    with pytest.raises(SetpointError, match=r"^jog j01r0 .*from the actual positions"):
        jog.start(np.zeros(actuation.n_motors, dtype=np.int64), 0.01)
    assert jog.n_cycles == 0  # no table to play


def test_jog_checked_again_from_the_actual_positions(actuation: Actuation) -> None:
    """Fine from the straight arm, but the arm is already bent near the joint limit."""
    jog = JogSource(actuation, "j01r0", 50_000.0, 0.2)
    jog.precheck(0.01)
    a = np.zeros(12)
    a[0] = np.deg2rad(56.0)
    bent = actuation.counts_from_angles(a, np.zeros(12))
    with pytest.raises(SetpointError, match=r"jog j01r0 .*joint 1: alpha"):
        jog.start(bent, 0.01)
    jog.start(np.zeros(actuation.n_motors, dtype=np.int64), 0.01)  # fine when straight


def test_jog_longer_than_the_motor_range_is_refused_before_any_bus(actuation: Actuation) -> None:
    jog = JogSource(actuation, "j01r0", 400_000.0, 3.0)
    with pytest.raises(SetpointError, match="exceed the motor's whole range"):
        jog.precheck(0.01)


def test_sources_longer_than_an_hour_are_refused(actuation: Actuation) -> None:
    with pytest.raises(SetpointError, match=r"^jog j01r0: 1e\+12 s exceeds the longest run"):
        JogSource(actuation, "j01r0", 0.0, 1e12).precheck(0.01)
    with pytest.raises(SetpointError, match="exceeds the longest run of 3600 s"):
        PlanSource(actuation, small_plan(), speed_mm_per_s=1e-9).precheck(0.01)
    with pytest.raises(SetpointError, match=r"^hold: .*exceeds the longest run"):
        HoldSource(n_cycles=10**12).precheck(0.01)
    HoldSource(n_cycles=None).precheck(0.01)  # "until stopped" is one hour
