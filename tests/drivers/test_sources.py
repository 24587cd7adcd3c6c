"""Setpoint sources (hold, jog, a precomputed plan table) and a short run of the full
36-drive box.  How a plan becomes counts is the rope layer's (tests/hrm_ctrl/ropes/
test_setpoints.py); here it is played."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.config import load_box_config
from drivers.protocol import cia402 as c
from drivers.safety.limits import MAX_SOURCE_DURATION_S
from drivers.session import DriveSession
from drivers.sources import CountsSource, HoldSource, JogSource, SetpointError, ramp_table
from hrm_ctrl.errors import RopeError
from hrm_ctrl.ropes.actuation import Actuation
from hrm_ctrl.ropes.setpoints import plan_setpoints
from sim_bus.box import SimBox


def small_plan(alpha_deg: float = 5.0, n: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(travel, alpha, theta) of a plan that bends every joint a little, 10 mm a step."""
    a = np.deg2rad(alpha_deg) * np.arange(n)[:, None] / (n - 1) * np.ones((1, 12))
    return 10.0 * np.arange(n), a, -a / 2


def plan_source(actuation: Actuation, speed: float = 40.0, hold_s: float = 0.05) -> CountsSource:
    """The small plan through the rope layer's plan -> counts path, as ``hrm run`` plays it."""
    sp = plan_setpoints(actuation, *small_plan(), period_s=0.01, speed_mm_per_s=speed)
    return CountsSource(actuation, sp.counts, 0.01, name="plan", label=sp.label, hold_s=hold_s)


def test_counts_source_plays_the_body_then_holds(actuation: Actuation) -> None:
    _travel, alpha, theta = small_plan()
    src = plan_source(actuation)
    src.precheck(0.01)
    start = np.zeros(actuation.n_motors, dtype=np.int64)
    src.start(start, 0.01)
    body = src.body
    # 40 mm at 40 mm/s: 1 s, 101 cycles; the first equals the first step already.
    assert body.shape == (101, actuation.n_motors)
    assert src.n_lead_in == 0
    last = actuation.counts_from_angles(alpha[-1], theta[-1])
    assert np.array_equal(body[-1], last)
    assert np.array_equal(src.table[-1], last) and src.n_cycles == 101 + 5
    mid = actuation.counts_from_angles(alpha[2], theta[2])
    assert np.array_equal(body[50], mid)
    actuation.check_counts(src.table, previous=start, dt_s=0.01)
    d = src.describe()
    assert d["source"] == "plan" and d["body_cycles"] == 101 and d["cycles"] == 106


def test_counts_source_lead_in_from_elsewhere(actuation: Actuation) -> None:
    src = plan_source(actuation)
    start = np.full(actuation.n_motors, 20_000, dtype=np.int64)
    src.start(start, 0.01)
    assert src.n_lead_in >= 1
    actuation.check_counts(src.table, previous=start, dt_s=0.01)
    assert np.array_equal(src.table[src.n_lead_in - 1], src.body[0])
    assert np.array_equal(src.table[src.n_lead_in :][: len(src.body)], src.body)


def test_counts_source_names_the_row_by_its_label(actuation: Actuation) -> None:
    """A body that jumps (hand-made, or made for another arm) is refused before any bus,
    the message naming the body row by its label, not a control cycle."""
    body = np.zeros((30, actuation.n_motors), dtype=np.int64)
    body[20:, 5] = 50_000  # one control period: far faster than any motor
    labels = [f"plan step {r // 10} (travel {r:.1f} mm)" for r in range(30)]
    src = CountsSource(actuation, body, 0.01, name="plan.json", label=labels)
    with pytest.raises(SetpointError) as info:
        src.precheck(0.01)
    msg = str(info.value)
    assert msg.startswith("plan.json: plan step 2 (travel 20.0 mm): motor j02r2 (joint 2, rope 2)")
    assert "faster than the motor" in msg and "\n" not in msg
    body[20:, 5] = 10**9  # outside the drum travel
    src = CountsSource(actuation, body, 0.01, name="plan", label=lambda r: f"plan step {r}")
    with pytest.raises(SetpointError, match=r"^plan: plan step 20: motor j02r2 .*outside"):
        src.precheck(0.01)


def test_counts_source_refuses_what_it_cannot_play(actuation: Actuation) -> None:
    n = actuation.n_motors
    with pytest.raises(SetpointError, match="counts must be an integer table"):
        CountsSource(actuation, np.zeros((3, n)), 0.01)
    with pytest.raises(SetpointError, match="counts must be an integer table"):
        CountsSource(actuation, np.zeros((3, n - 1), dtype=np.int64), 0.01)
    with pytest.raises(SetpointError, match="2 row labels for 3 rows"):
        CountsSource(actuation, np.zeros((3, n), dtype=np.int64), 0.01, label=["a", "b"])
    src = CountsSource(actuation, np.zeros((3, n), dtype=np.int64), 0.01)
    with pytest.raises(SetpointError, match=r"made for a 0\.01 s control period, the control"):
        src.precheck(0.008)
    with pytest.raises(SetpointError, match="hold must be >= 0 s"):
        CountsSource(actuation, np.zeros((3, n), dtype=np.int64), 0.01, hold_s=-1.0)


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
    with SimBox(cfg, actuation=actuation) as sim:
        with DriveSession(cfg, actuation, log_dir=tmp_path, run_name="full") as box:
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
    with pytest.raises(RopeError, match="exceeds the longest run of 3600 s"):  # as hrm run asks
        plan_setpoints(
            actuation,
            *small_plan(),
            period_s=0.01,
            speed_mm_per_s=1e-9,
            max_duration_s=MAX_SOURCE_DURATION_S,
        )
    with pytest.raises(SetpointError, match=r"^plan: .*exceeds the longest run of 3600 s"):
        plan_source(actuation, hold_s=7200.0).precheck(0.01)
    with pytest.raises(SetpointError, match=r"^hold: .*exceeds the longest run"):
        HoldSource(n_cycles=10**12).precheck(0.01)
    HoldSource(n_cycles=None).precheck(0.01)  # "until stopped" is one hour
