"""The rope consistency check on a compensated playback (``RopeConsistencyCheck(...,
compensation=...)``): the feed-forward's rows fit no configuration at the pretension, so
without what it added the check skips every one of them; with it, it checks every one,
with feedback that lags the commands, and still catches a rope that is off."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.ropes.estimator import Compensation, RopeConsistencyCheck

EVERY = 5  # the watch checks every 5th control period (drivers.safety.watches)


@dataclass(frozen=True)
class Played:
    act: Actuation
    counts: np.ndarray  # (rows, n) the compensated rows
    added: np.ndarray  # (rows, n) what the feed-forward added
    ramp_rows: int


@pytest.fixture(scope="module")
def bent_pipe() -> Played:
    """The bent pipe there and back at the demo's speed, compensated (``hrm run
    --compensate``'s counts)."""
    from hrm_ctrl.formats.planfile import PlanDoc
    from hrm_ctrl.planning.planner import PlanOptions, plan_path
    from hrm_ctrl.planning.scenarios import scenario
    from hrm_ctrl.runtime.playback import setpoints_of_plan

    robot = default_robot()
    act = load_actuation(robot)
    sc = scenario("bent-pipe")
    plan = plan_path(robot, sc.path, PlanOptions(step=5.0, return_to_start=True), scenario=sc,
                     environment=sc.environment)  # fmt: skip
    doc = PlanDoc.from_dict(plan.to_dict(), sc.name)
    sp = setpoints_of_plan(doc, act, period_s=0.01, speed_mm_per_s=50.0, compensate=True)
    assert sp.compensation_counts is not None
    return Played(act, sp.counts, sp.compensation_counts, sp.ramp_rows)


def lagged(rows: np.ndarray, lag_rows: float) -> np.ndarray:
    """Feedback that follows ``rows`` ``lag_rows`` behind (linearly between rows, rounded)."""
    n = rows.shape[0]
    at = np.clip(np.arange(n) - lag_rows, 0, n - 1)
    i0 = np.floor(at).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    w = (at - i0)[:, None]
    return np.rint(rows[i0] + w * (rows[i1] - rows[i0])).astype(np.int64)


def watch(
    p: Played, feedback: np.ndarray, compensation: Compensation | None
) -> tuple[RopeConsistencyCheck, list[tuple[int, str]]]:
    """The check at 20 Hz over the whole playback (each command with its feedback)."""
    check = RopeConsistencyCheck(p.act, rate_hz=20.0, compensation=compensation)
    faults = []
    for r in range(0, p.counts.shape[0], EVERY):
        text = check(feedback[r], p.counts[r])
        if text is not None:
            faults.append((r, text))
    return check, faults


def test_the_plain_check_skips_every_compensated_sample(bent_pipe: Played) -> None:
    p = bent_pipe
    check, faults = watch(p, p.counts, None)
    samples = len(range(0, p.counts.shape[0], EVERY))
    assert faults == []
    # measured: 561 of 563 gated (the two checked: the ramp-in's first rows, at rest at
    # the pretension's counts); the watch looks at next to nothing
    assert check.gated >= samples - 3 and check.evaluations <= 3, check.summary()


@pytest.mark.parametrize("lag_rows", [0.0, 1.0, 1.5, 3.0, 10.0])
def test_with_what_was_added_every_compensated_sample_is_checked(
    bent_pipe: Played, lag_rows: float
) -> None:
    """The drives lag their targets: taking off what was added at the command's row
    from feedback one row behind read 4.8 (flag 5), two rows behind stopped the run on
    a healthy arm; taken off where the feedback stands, every figure stays below 1."""
    p = bent_pipe
    comp = Compensation.of(p.counts, p.added)
    check, faults = watch(p, lagged(p.counts, lag_rows), comp)
    samples = len(range(0, p.counts.shape[0], EVERY))
    assert faults == []
    s = check.summary()
    assert s["gated"] == 0 and s["evaluations"] == samples, s  # measured: 563 of 563
    assert s["compensated"] == {"samples": samples, "off_path": 0}
    assert s["max_figure"] < 1.0, s  # measured 0.949, as on the plain rows


@pytest.mark.parametrize("motor", ["j05r1", "j02r0", "j11r2"])
def test_a_rope_off_by_half_a_millimetre_is_caught_with_compensation(
    bent_pipe: Played, motor: str
) -> None:
    """A slipped rope or an encoder that is off (the motor's feedback 0.5 mm, 1075 counts,
    off from row 1000 on, the way back in: ``hrm run``'s shifted-encoder test) stops the
    compensated playback at the first check after it, naming the rope's joint."""
    p = bent_pipe
    comp = Compensation.of(p.counts, p.added)
    fb = lagged(p.counts, 1.5)
    i = p.act.motor_ids.index(motor)
    fb[1000:, i] += 1075
    _check, faults = watch(p, fb, comp)
    assert faults, "not caught"
    row, text = faults[0]
    assert 1000 <= row <= 1000 + 3 * EVERY, (row, text)
    joint = int(motor[1:3])
    assert text.startswith(f"rope consistency: joint {joint}, rope"), text
    assert motor in text


def test_the_threshold_is_the_plain_checks(bent_pipe: Played) -> None:
    """The smallest offset caught (a ladder of 100 counts, 0.047 mm) on a rope of every
    joint is the plain check's on the uncompensated rows, or one rung more (measured over
    all 36 ropes at row 700: the same for 33, one rung more for j03r2, j10r0, j12r1; the
    largest 600 counts, 0.28 mm, either way)."""
    p = bent_pipe
    plain = p.counts - p.added
    comp = Compensation.of(p.counts, p.added)
    start = 700

    def caught(rows: np.ndarray, compensation: Compensation | None, i: int, shift: int) -> bool:
        fb = lagged(rows, 1.5)
        fb[start:, i] += shift
        check = RopeConsistencyCheck(p.act, rate_hz=20.0, compensation=compensation)
        for r in range(0, start + 100, EVERY):
            if check(fb[r], rows[r]) is not None:
                return r >= start
        return False

    ladder = range(100, 1100, 100)
    for motor in ("j01r0", "j03r2", "j06r1", "j09r0", "j12r1"):
        i = p.act.motor_ids.index(motor)
        low_plain = next(s for s in ladder if caught(plain, None, i, s))
        low_comp = next(s for s in ladder if caught(p.counts, comp, i, s))
        assert low_plain <= low_comp <= low_plain + 100, (motor, low_plain, low_comp)


def test_a_command_off_the_rows_is_checked_as_it_is() -> None:
    """A lead-in (not on the compensated rows) is checked as without compensation: a
    command that is no configuration is gated; the rows themselves are found again."""
    act = load_actuation(default_robot())
    a = np.linspace(0.0, 0.2, 40)[:, None] * np.ones(12)
    plain = act.counts_from_angles(a, -0.5 * a)
    added = np.zeros_like(plain)
    added[:, ::3] = 400  # what no configuration takes up
    comp = Compensation.of(plain + added, added)
    check = RopeConsistencyCheck(act, rate_hz=20.0, compensation=comp)
    lead_in = (0.5 * (plain[0] + added[0])).astype(np.int64)  # a line in counts
    assert check(lead_in, lead_in) is None
    assert check.off_path == 1 and check.gated == 1
    for r in range(0, 40, 2):
        assert check(plain[r] + added[r], plain[r] + added[r]) is None
    s = check.summary()
    assert s["compensated"] == {"samples": 20, "off_path": 1}
    assert s["evaluations"] == 19 and s["gated"] == 2  # the lead-in and one settling sample
