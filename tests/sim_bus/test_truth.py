"""The simulated arm's truth: perturbation ranges, the truth file reader and writer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from hrm_ctrl.errors import SimError
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from sim_bus.truth import (
    PERTURB_EA_FRACTION,
    PERTURB_LINK_MM,
    PERTURB_OFFSET_RAD,
    PERTURB_ZERO_COUNTS,
    TRUTH_FORMAT,
    TrueArm,
    TruthFileError,
    read_truth,
    truth_from_dict,
    truth_to_toml,
    write_truth,
)

ACT: Actuation = load_actuation(default_robot())
EA = np.asarray(ACT.routing.stiffness_EA_N, dtype=float)


def _rotation_ok(R: np.ndarray) -> bool:
    return bool(np.allclose(R.T @ R, np.eye(3), atol=1e-12) and abs(np.linalg.det(R) - 1) < 1e-12)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(0)
def test_perturbation_stays_within_the_issue_ranges(seed: int) -> None:
    t = TrueArm.perturbed(ACT, seed)
    assert np.abs(t.links_mm - ACT.robot.links).max() <= PERTURB_LINK_MM
    assert np.abs(t.alpha_offset_rad).max() <= PERTURB_OFFSET_RAD
    assert np.abs(t.theta_offset_rad).max() <= PERTURB_OFFSET_RAD
    assert np.abs(t.rope_EA_N / EA - 1.0).max() <= PERTURB_EA_FRACTION + 1e-12
    assert np.abs(t.motor_zero_counts).max() <= PERTURB_ZERO_COUNTS
    assert t.motor_zero_counts.dtype == np.int64
    assert not t.slack_mm.any()  # no slack unless asked
    assert _rotation_ok(t.tracker_rotation)
    # the tracker stands 2-3 m (horizontally) from the arm's middle, +-0.5 m in height
    origin = -t.tracker_rotation.T @ t.tracker_translation_mm
    middle = np.array([0.5 * ACT.robot.length, 0.0, 0.0])
    assert 2000.0 - 1e-6 <= np.hypot(*(origin - middle)[:2]) <= 3000.0 + 1e-6
    assert abs(origin[2]) <= 500.0
    assert not t.is_nominal(ACT)


def test_perturbation_uses_the_whole_range_and_is_repeatable() -> None:
    draws = [TrueArm.perturbed(ACT, s) for s in range(20)]
    zeros = np.concatenate([t.motor_zero_counts for t in draws])
    links = np.concatenate([t.links_mm - ACT.robot.links for t in draws])
    assert zeros.max() > 0.9 * PERTURB_ZERO_COUNTS and zeros.min() < -0.9 * PERTURB_ZERO_COUNTS
    assert links.max() > 0.9 * PERTURB_LINK_MM and links.min() < -0.9 * PERTURB_LINK_MM
    again = TrueArm.perturbed(ACT, 3)
    assert np.array_equal(again.motor_zero_counts, draws[3].motor_zero_counts)
    assert np.array_equal(again.tracker_rotation, draws[3].tracker_rotation)
    assert not np.array_equal(draws[4].links_mm, draws[3].links_mm)


def test_slack_only_when_asked_and_bad_seeds_refused() -> None:
    t = TrueArm.perturbed(ACT, 1, max_slack_mm=3.0)
    assert 0.0 <= t.slack_mm.min() and t.slack_mm.max() <= 3.0 and t.slack_mm.max() > 1.0
    for bad in (-1, 1.5, True):
        with pytest.raises(SimError, match="seed"):
            TrueArm.perturbed(ACT, bad)  # type: ignore[arg-type]
    with pytest.raises(SimError, match="max_slack_mm"):
        TrueArm.perturbed(ACT, 1, max_slack_mm=math.nan)


def test_nominal_is_the_description() -> None:
    t = TrueArm.nominal(ACT)
    assert t.is_nominal(ACT) and t.motor_ids == ACT.motor_ids
    assert np.array_equal(t.links_mm, ACT.robot.links)
    assert _rotation_ok(t.tracker_rotation)
    assert 2000.0 < np.linalg.norm(t.to_tracker(np.zeros(3))) < 3000.0
    # arrays are read-only
    with pytest.raises(ValueError):
        t.links_mm[0] = 1.0


def test_to_tracker_is_a_rigid_transform() -> None:
    t = TrueArm.perturbed(ACT, 11)
    p = np.array([[0.0, 0.0, 0.0], [2007.0, 0.0, 0.0], [1000.0, 300.0, -200.0]])
    q = t.to_tracker(p)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    assert np.allclose(np.linalg.norm(q[:, None] - q[None], axis=-1), d)
    assert np.allclose(q, (t.tracker_rotation @ p.T).T + t.tracker_translation_mm)


@pytest.mark.parametrize("seed", [0, 5])
def test_truth_file_round_trip_bit_for_bit(tmp_path: Path, seed: int) -> None:
    t = TrueArm.perturbed(ACT, seed, max_slack_mm=2.0)
    path = tmp_path / "truth.toml"
    write_truth(path, t)
    back = read_truth(path, ACT)
    assert back.source == str(path)
    assert back.to_dict() == t.to_dict()  # floats read back exactly
    for key in ("links_mm", "rope_EA_N", "motor_zero_counts", "slack_mm", "tracker_rotation"):
        assert np.array_equal(getattr(back, key), getattr(t, key)), key


def test_a_partial_truth_file_takes_the_description_for_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "t.toml"
    path.write_text(
        f'format = "{TRUTH_FORMAT}"\n'
        "[motor_zero_counts]\nj01r1 = 1234\n"
        "[rope_EA_N]\nj12r2 = 25000.0\n"
        "[slack_mm]\nj05r2 = 3\n"
        "[tracker]\nnoise_mm = 0.0\n"
    )
    t = read_truth(path, ACT)
    i = ACT.motor_ids.index
    assert t.motor_zero_counts[i("j01r1")] == 1234 and t.motor_zero_counts.sum() == 1234
    assert t.rope_EA_N[i("j12r2")] == 25000.0 and t.rope_EA_N[i("j01r0")] == EA[0]
    assert t.slack_mm[i("j05r2")] == 3.0
    assert t.tracker_noise_mm == 0.0
    assert np.array_equal(t.links_mm, ACT.robot.links) and not t.alpha_offset_rad.any()
    nominal = TrueArm.nominal(ACT)
    assert np.array_equal(t.tracker_rotation, nominal.tracker_rotation)


@pytest.mark.parametrize(
    ("text", "key", "why"),
    [
        ("colour = 1", "colour", "unknown key"),
        ('format = "hrm-sim-truth/2"', "format", "expected"),
        ("links_mm = [1.0, 2.0]", "links_mm", "list of 12"),
        ("links_mm = [" + ", ".join(["179.0"] * 11) + ", nan]", "links_mm[11]", "finite"),
        ("links_mm = [" + ", ".join(["179.0"] * 11) + ', "x"]', "links_mm[11]", "a number"),
        ("links_mm = [" + ", ".join(["100.0"] * 12) + "]", "links_mm[0]", "more than"),
        ("alpha_offset_rad = [" + ", ".join(["0.2"] * 12) + "]", "alpha_offset_rad[0]", "beyond"),
        ("[motor_zero_counts]\nj99r0 = 1", "motor_zero_counts.j99r0", "unknown rope motor"),
        ("[motor_zero_counts]\nj01r0 = 1.5", "motor_zero_counts.j01r0", "integer"),
        ("[motor_zero_counts]\nj01r0 = 60000", "motor_zero_counts.j01r0", "beyond"),
        ("motor_zero_counts = 3", "motor_zero_counts", "table"),
        ("[rope_EA_N]\nj01r0 = 1000.0", "rope_EA_N.j01r0", "outside"),
        ("[rope_EA_N]\nj01r0 = inf", "rope_EA_N.j01r0", "finite"),
        ("[slack_mm]\nj01r0 = -1.0", "slack_mm.j01r0", "outside"),
        ("[tracker]\nrotation = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]", "tracker.rotation", "det"),
        ("[tracker]\nrotation = [[1, 0, 0], [0, 1, 0]]", "tracker.rotation", "3 rows"),
        ("[tracker]\ntranslation_mm = [1e6, 0, 0]", "tracker.translation_mm", "beyond"),
        ("[tracker]\nnoise_mm = 5.0", "tracker.noise_mm", "outside"),
        ("[tracker]\nwhere = 1", "tracker.where", "unknown key"),
    ],
)
def test_bad_truth_files_are_one_line_errors_naming_file_and_key(
    tmp_path: Path, text: str, key: str, why: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text + "\n")
    with pytest.raises(TruthFileError) as info:
        read_truth(path, ACT)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{path}: {key}: ") and why in msg, msg


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(TruthFileError, match="not found"):
        read_truth(tmp_path / "none.toml", ACT)
    (tmp_path / "x.toml").write_text("links_mm = [\n")
    with pytest.raises(TruthFileError, match="not valid TOML"):
        read_truth(tmp_path / "x.toml", ACT)
    with pytest.raises(TruthFileError, match="must be a TOML table"):
        truth_from_dict([], ACT, "doc")  # type: ignore[arg-type]


def test_written_file_is_commented_toml_and_writing_fails_cleanly(tmp_path: Path) -> None:
    text = truth_to_toml(TrueArm.perturbed(ACT, 2))
    assert text.startswith("# simulated arm truth") and "[motor_zero_counts]" in text
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(TruthFileError, match="cannot write"):
        write_truth(blocker / "t.toml", TrueArm.nominal(ACT))  # its folder is a file


def test_host_zero_counts_are_the_truths_with_the_slack_taken_up() -> None:
    t = TrueArm.perturbed(ACT, 4)
    rope = load_actuation(t.model(ACT.robot))
    # the truth's zeros are at the rope geometry's zero, the host's convention: joint
    # offsets do not move them
    assert t.alpha_offset_rad.any()
    assert np.array_equal(t.host_zero_counts(rope), t.motor_zero_counts)
    slack = t.replace(slack_mm=np.full(36, 0.5))
    d = slack.host_zero_counts(rope) - t.motor_zero_counts
    assert np.array_equal(d, np.rint(rope.motors.direction * rope.motors.counts_per_mm * 0.5))


def test_a_truth_read_from_a_path_with_a_line_break_is_written_back_readable(
    tmp_path: Path,
) -> None:
    """The source path goes into the file's first comment, escaped: a newline in it made
    the written file's next line TOML (``links_mm = 5``: unreadable)."""
    odd = tmp_path / "t\nlinks_mm = 5\n.toml"
    write_truth(odd, TrueArm.perturbed(ACT, 1, max_slack_mm=2.0))
    first = read_truth(odd, ACT)
    again = tmp_path / "again.toml"
    write_truth(again, first)
    assert again.read_text().splitlines()[0].startswith("# simulated arm truth (")
    assert read_truth(again, ACT).to_dict() == first.to_dict()
