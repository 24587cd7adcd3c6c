"""Pretension and zero (``calibration.zero``) on the simulated box (in its own process, as
``--sim`` runs it) with its arm in the straight fixture: a seeded perturbed arm's motor
zeros recovered within 50 counts, final tensions within the tolerance, refusals naming the
rope (slack beyond the travel limit, a snapped rope, invalid or saturated sensor channels,
a tension over its limit), the drives left where the routine says and disabled cleanly by
the session's finish.

Why 50 counts holds (``calibration.zero``'s docstring): one count is at least 0.0047 N of
tension (joint 12's 2395 mm ropes, EA 20 % below the description); the mean of 10 frames
of sigma 0.05 N has at most 0.035 N (the simulated board repeats a sample for up to 50 ms,
so only about every fifth frame is independent: 0.05 / sqrt(2)), i.e. about 8 counts, and
the residual inside ``tol_N`` = 0.2 N is extrapolated away on the fitted slope.

The module fixture zeroes joints 1 and 12, not all twelve (about 1 s a group): joint 12's
ropes are that budget's worst case (the fewest newtons a count), joint 1's the other end
(the stiffest, the largest tension step a count); joint 1 is on can0, joint 12 on can1.
The other groups run the same code on ropes in between; every tension in the fixture
depends on its own rope's motor only.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from calibration.zero import (
    BOARD_FLAG_SATURATED,
    DEFAULT_TOL_N,
    RopeTensionError,
    TensionGuard,
    move_table,
    pretension_and_zero,
    read_tensions,
    search_step_counts,
    tension_slope_N_per_count,
)
from drivers.config import load_box_config
from drivers.protocol import cia402
from drivers.session import DriveSession, SessionState
from drivers.tension_sensor import TensionSample, TensionSensorReader
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.runtime.box import NO_WATCHES, SessionOptions, open_box
from hrm_ctrl.runtime.process_box import BoxProcess
from hrm_ctrl.runtime.simulated import SimulatedArm, SimulatedBox
from sim_bus.truth import TrueArm
from tests.drivers.driver_rig import BoxView
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT

SEED = 11
ZERO_TOLERANCE_COUNTS = 50
ZEROED_JOINTS = (0, 11)  # 0-based: the shortest and the longest ropes (module docstring)


@dataclass
class Rig:
    sim: BoxView
    session: DriveSession
    reader: TensionSensorReader
    actuation: Actuation
    truth: TrueArm


@contextmanager
def fixture_rig(
    seed: int = SEED, host: Actuation | None = None, **truth_changes: Any
) -> Iterator[Rig]:
    """The simulated box (36 drives, its tension board) in its own process, as ``--sim``
    starts it (``open_box``), with a perturbed arm lying in its straight fixture, and a
    drive session brought up on it with the rope layer ``host`` (default the
    description's)."""
    act = load_actuation(default_robot())
    truth = TrueArm.perturbed(act, seed)
    if truth_changes:
        truth = truth.replace(**truth_changes)
    # the simulated box's tolerances and hrm_ipc buses of fresh channels, as hrm --sim runs
    # it; the production watches themselves: tests/drivers/safety/test_supervisor_stops.py,
    # tests/hil
    box = SimulatedBox(SimulatedArm(act, truth), fixture=True)
    options = SessionOptions(allow_uncalibrated=True)
    with open_box(
        load_box_config(None), host or act, options, sim=box, watches=NO_WATCHES, bring_up=False
    ) as b:
        assert isinstance(b.sim, BoxProcess) and b.config.tension is not None
        t = b.config.tension
        # the board read from before the bring-up, by a thread of the session's scheduling
        # (SCHED_FIFO where permitted), as hrm calibrate zero does
        with b.session.thread_scheduling():
            opened = TensionSensorReader(t.port, act.n_motors, stale_after_s=t.stale_s).open()
        with closing(opened) as reader:
            b.bring_up()
            yield Rig(BoxView(b.sim), b.session, reader, host or act, truth)


def assert_disabled_after_finish(rig: Rig) -> None:
    """The session's finish leaves no drive enabled (power stage off, nothing moving)."""
    rig.session.finish()
    assert rig.session.state is SessionState.CONNECTED
    states = {cia402.decode_state(sw) for sw in rig.sim.statuswords().values()}
    assert cia402.State402.OPERATION_ENABLED not in states, states
    before = rig.sim.counts()
    time.sleep(0.05)
    assert np.array_equal(rig.sim.counts(), before)


# ---- the whole arm -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def zeroed() -> Iterator[tuple[Rig, Any, np.ndarray]]:
    """The rig, the result and the zeroed motors' indices."""
    with fixture_rig() as rig:
        result = pretension_and_zero(
            rig.session, rig.reader, rig.actuation, joints=list(ZEROED_JOINTS)
        )
        g = np.flatnonzero(np.isin(rig.actuation.joint_of_motor, ZEROED_JOINTS))
        assert len(g) == 3 * len(ZEROED_JOINTS)
        yield rig, result, g


def test_every_zero_recovered_within_50_counts(zeroed: tuple[Rig, Any, np.ndarray]) -> None:
    rig, result, g = zeroed
    error = result.zero_counts[g] - rig.truth.motor_zero_counts[g]
    worst = int(np.argmax(np.abs(error)))
    assert abs(int(error[worst])) <= ZERO_TOLERANCE_COUNTS, (result.motor_ids[g[worst]], error)
    # the perturbation is thousands of counts: the routine did move the zeros that far
    assert np.abs(result.zero_shift_counts[g]).max() > 1000


def test_final_tensions_within_tol(zeroed: tuple[Rig, Any, np.ndarray]) -> None:
    rig, result, g = zeroed
    assert np.all(np.abs(result.tension_error_N[g]) < DEFAULT_TOL_N), result.tension_error_N
    # an independent reading now, every rope at once (mean of 20 frames, sigma < 0.03 N)
    again = read_tensions(rig.reader, rig.actuation.motor_ids, n_samples=20)
    assert np.all(np.abs(again.tensions_N[g] - result.target_N) < DEFAULT_TOL_N + 0.1)


def test_few_moves_per_group_and_the_drives_hold_where_reported(
    zeroed: tuple[Rig, Any, np.ndarray],
) -> None:
    rig, result, g = zeroed
    assert result.iterations[g].max() <= 6, result.iterations
    assert result.moves == sum(int(result.iterations[3 * j]) for j in ZEROED_JOINTS)
    assert rig.session.state is SessionState.ENABLED
    assert np.array_equal(rig.sim.counts(), result.final_counts)
    assert np.abs(result.final_counts - result.zero_counts).max() <= 60  # within tol of it


def expected_zeros(rig: Rig, slack_mm: np.ndarray) -> np.ndarray:
    """Where each rope reaches its pretension: the truth's zero plus its slack wound in."""
    m = rig.actuation.motors
    return np.rint(rig.truth.motor_zero_counts + m.direction * m.counts_per_mm * slack_mm)


@STALL_TOLERANT
def test_slack_within_the_travel_is_taken_up() -> None:
    """1.5 mm of slack on j08r0 (3200 counts): its zero is where the rope reaches the
    pretension, the truth's zero plus the slack wound in; other joints keep theirs."""
    act = load_actuation(default_robot())
    slack = np.zeros(act.n_motors)
    slack[act.motor_ids.index("j08r0")] = 1.5
    g = np.flatnonzero(act.joint_of_motor == 7)
    with fixture_rig(slack_mm=slack) as rig:
        result = pretension_and_zero(rig.session, rig.reader, rig.actuation, joints=[7])
        error = result.zero_counts[g] - expected_zeros(rig, slack)[g]
        assert np.abs(error).max() <= ZERO_TOLERANCE_COUNTS, error
        others = np.setdiff1d(np.arange(act.n_motors), g)
        assert np.array_equal(result.zero_counts[others], result.before_counts[others])


@STALL_TOLERANT
def test_ropes_half_and_twice_as_stiff_as_described() -> None:
    """The widest arm a truth file may describe (EA 0.5x .. 2x), zeros 5000 counts off
    either way, on the shortest and the longest ropes: still within 50 counts, in at most 8
    moves a group (the rope twice as stiff starts at ~300 N and is only loosened)."""
    act = load_actuation(default_robot())
    ea = np.asarray(act.routing.stiffness_EA_N, dtype=float).copy()
    zero = np.zeros(act.n_motors, dtype=np.int64)
    ea[[0, 1, 33, 34]] *= [0.5, 2.0, 2.0, 0.5]
    zero[[0, 1, 33, 34]] = [5000, -5000, -5000, 5000]
    with fixture_rig(rope_EA_N=ea, motor_zero_counts=zero) as rig:
        result = pretension_and_zero(rig.session, rig.reader, rig.actuation, joints=[0, 11])
        g = np.flatnonzero(np.isin(act.joint_of_motor, [0, 11]))
        error = result.zero_counts[g] - zero[g]
        assert np.abs(error).max() <= ZERO_TOLERANCE_COUNTS, error
        assert result.iterations[g].max() <= 8, result.iterations[g]


@STALL_TOLERANT
def test_zeros_do_not_depend_on_the_joint_offsets() -> None:
    """With the true links, joint offsets and EAs in the host's rope layer (as after the
    kinematic and stiffness calibrations), the fixture (rope geometry straight) gives the
    truth's zeros as they are: the joint offsets do not enter; a target other than the
    pretension is converted on the rope layer's model."""
    act = load_actuation(default_robot())
    truth = TrueArm.perturbed(act, SEED)
    host = truth.ideal_actuation(act.robot)
    assert np.abs(host.alpha_offset_rad).max() > np.radians(0.5)  # offsets that matter
    ideal = np.asarray(host.motors.zero_offsets_counts)
    g = np.flatnonzero(np.isin(act.joint_of_motor, [8, 11]))
    with fixture_rig(host=host) as rig:
        result = pretension_and_zero(rig.session, rig.reader, host, joints=[8, 11])
        assert np.array_equal(result.fixture_counts[g], result.zero_counts[g])
        assert np.abs(result.zero_counts[g] - truth.motor_zero_counts[g]).max() <= 50
        assert np.abs(result.zero_counts[g] - ideal[g]).max() <= ZERO_TOLERANCE_COUNTS
        other = pretension_and_zero(rig.session, rig.reader, host, target_N=25.0, joints=[11])
        g12 = g[3:]
        assert np.abs(other.zero_counts[g12] - ideal[g12]).max() <= ZERO_TOLERANCE_COUNTS
        assert np.all(np.abs(other.tension_error_N[g12]) < DEFAULT_TOL_N)
        assert np.abs(other.fixture_counts[g12] - other.zero_counts[g12]).min() > 100


# ---- refusals ------------------------------------------------------------------------------


def _refused(rig: Rig, joint: int, **kw: Any) -> str:
    start = rig.sim.counts()
    with pytest.raises(RopeTensionError) as err:
        pretension_and_zero(rig.session, rig.reader, rig.actuation, joints=[joint], **kw)
    text = str(err.value)
    assert "\n" not in text
    assert rig.session.state is SessionState.ENABLED
    assert np.array_equal(rig.sim.counts(), start), "the group was not moved back"
    assert_disabled_after_finish(rig)
    return text


@STALL_TOLERANT
def test_slack_rope_beyond_the_travel_limit_is_refused_naming_it() -> None:
    act = load_actuation(default_robot())
    slack = np.zeros(act.n_motors)
    i = act.motor_ids.index("j04r1")
    slack[i] = 8.0  # mm: 17 000 counts of rope to take up, beyond 6000 counts of travel
    with fixture_rig(slack_mm=slack) as rig:
        text = _refused(rig, 3, max_travel_counts=6000)
    assert "j04r1" in text and "slack or snapped" in text, text


@STALL_TOLERANT
def test_snapped_rope_is_refused_naming_it() -> None:
    with fixture_rig() as rig:
        rig.sim.snap_rope("j06r2")
        text = _refused(rig, 5, max_travel_counts=8000)
    assert "j06r2" in text and "slack or snapped" in text, text


# ---- the sensor: unit tests on a scripted reader -------------------------------------------


class ScriptedReader:
    """A tension board of fixed frames (one new frame per call)."""

    port = "scripted"

    def __init__(self, tensions: np.ndarray, flags: int = 0) -> None:
        self.tensions = np.asarray(tensions, dtype=float)
        self.flags = flags
        self.seq = 0

    def latest(self, now_s: float | None = None) -> TensionSample:
        self.seq += 1
        return TensionSample(self.seq, 0, self.flags, self.tensions.copy(), time.monotonic())


IDS = ("j01r0", "j01r1", "j01r2")


def test_reading_averages_distinct_frames() -> None:
    r = read_tensions(ScriptedReader(np.array([30.0, 29.0, 31.0])), IDS, n_samples=4)
    assert r.n_samples == 4 and r.tensions_N.tolist() == [30.0, 29.0, 31.0]


def test_invalid_channel_is_refused_naming_the_rope() -> None:
    with pytest.raises(RopeTensionError, match=r"rope j01r1: tension channel invalid"):
        read_tensions(ScriptedReader(np.array([30.0, np.nan, 31.0])), IDS, n_samples=2)
    # a channel not asked for does not refuse
    r = read_tensions(ScriptedReader(np.array([30.0, np.nan, 31.0])), IDS, n_samples=2, ropes=[0])
    assert r.tensions_N[0] == 30.0


def test_saturated_channel_is_refused_naming_the_rope() -> None:
    reader = ScriptedReader(np.array([30.0, 30.0, 655.34]), flags=BOARD_FLAG_SATURATED)
    with pytest.raises(RopeTensionError, match=r"rope j01r2: tension sensor saturated"):
        read_tensions(reader, IDS, n_samples=2)


def test_missing_frames_are_refused_within_the_timeout() -> None:
    class Silent(ScriptedReader):
        def latest(self, now_s: float | None = None) -> TensionSample:
            return TensionSample(1, 0, 0, self.tensions.copy(), time.monotonic() - 10.0)

    with pytest.raises(RopeTensionError, match=r"0 of 3 frames in 0.1 s"):
        read_tensions(Silent(np.array([30.0, 30.0, 30.0])), IDS, n_samples=3, timeout_s=0.1)


def test_guard_names_the_rope_over_its_limit() -> None:
    class Session:
        actuation = type("A", (), {"motor_ids": IDS})()

    reader = ScriptedReader(np.array([30.0, 45.0, 80.0]))
    guard = TensionGuard(Session(), reader, np.array([60.0, 60.0, 90.0]))  # type: ignore[arg-type]
    assert guard.check() is None
    reader.tensions[1] = 61.0
    assert guard.check() == "rope j01r1: tension 61.0 N above 60.0 N"


# ---- the model and the moves ---------------------------------------------------------------


def test_search_step_keeps_a_stiffer_rope_below_the_midpoint() -> None:
    act = load_actuation(default_robot())
    step = search_step_counts(act, 30.0, 60.0)
    k0 = np.abs(tension_slope_N_per_count(act, 0.0))
    assert np.all(1.5 * k0 * step <= 45.0 + 1e-9)
    assert np.all(1.5 * k0 * (step + 1) > 45.0)  # the longest such step


@settings(max_examples=60, deadline=None)
@given(
    start=st.integers(-100_000, 100_000),
    delta=st.integers(-20_000, 20_000),
    speed=st.floats(1_000.0, 200_000.0),
)
@example(start=0, delta=1, speed=1_000.0)
@example(start=0, delta=-20_000, speed=200_000.0)
def test_move_table_stays_within_the_motor_limits(start: int, delta: int, speed: float) -> None:
    act = load_actuation(default_robot())
    n = act.n_motors
    a = np.full(n, start, dtype=np.int64)
    b = a.copy()
    b[::3] += delta
    rate = np.full(n, speed)
    accel = 0.5 * np.asarray(act.max_accel_counts_per_s2)
    table = move_table(a, b, rate, accel, 0.01)
    assert np.array_equal(table[-1], b)
    # every limit the supervisor checks, from rest (the first row too)
    act.check_counts(np.vstack([a, a, table]), dt_s=0.01)
    v = np.abs(np.diff(np.vstack([a, table]), axis=0)) / 0.01
    assert np.all(v <= speed * 1.0 + 100.0 + 1e-9)  # 1 count of rounding per period


# ---- the console ---------------------------------------------------------------------------


@STALL_TOLERANT
def test_console_refusal_is_one_line_and_saves_nothing(
    tmp_path: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """``hrm calibrate zero --sim --perturb 3`` with 200 counts of travel: joint 1's ropes
    are 1000-2900 counts off their zeros, so the first group is refused, exit 2, one line
    naming the rope; no calibration saved, no ``--out`` written."""
    from hrm_ctrl.cli import main

    store, out = tmp_path / "cal", tmp_path / "zero.json"
    argv = ["calibrate", "zero", "--sim", "--perturb", "3", "--max-travel-counts", "200"]
    argv += ["--calibrations", str(store), "--log-dir", str(tmp_path / "runs")]
    rc = main([*argv, "--out", str(out)])
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if "error" in x]
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith("hrm calibrate: error: zero: rope j01r"), lines[0]
    assert "counts of travel" in lines[0]
    assert not out.exists() and not store.exists()
