"""The calibration store (calibration/store.py): round trip, integrity, robots, versions,
and a writer killed with SIGKILL at random moments."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from calibration.store import (
    MAX_FILE_BYTES,
    MAX_MOTORS,
    Calibration,
    CalibrationStore,
    Routine,
    checksum,
    from_json,
    to_json,
)
from hrm_ctrl.errors import CalibrationError, CalibrationFileError

ROOT = Path(__file__).resolve().parents[2]
ROBOT = "ab" * 32
OTHER_ROBOT = "cd" * 32
MOTORS = [f"j{j:02d}r{r}" for j in range(1, 13) for r in range(1, 4)]  # 36, as robot.toml


def make_cal(seed: int = 0, robot: str = ROBOT) -> Calibration:
    rng = np.random.default_rng(seed)
    return Calibration(
        links_mm=60.0 + rng.uniform(-2, 2, 12),
        alpha_offset_rad=rng.uniform(-0.02, 0.02, 12),
        theta_offset_rad=rng.uniform(-0.02, 0.02, 12),
        motor_zero_counts={m: int(rng.integers(-5000, 5000)) for m in MOTORS},
        rope_EA_N={m: float(rng.uniform(24e3, 36e3)) for m in MOTORS},
        created_utc=datetime(2026, 12, 1, 21, 24, 33, 123456, tzinfo=UTC),
        routine=Routine.KINEMATIC,
        residuals={"rms_before_mm": 1.5, "rms_after_mm": 0.05},
        robot_sha256=robot,
    )


def _one_line_naming(exc: pytest.ExceptionInfo, path: Path) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def _rewrite(path: Path, change) -> None:
    """Edit the document at ``path`` and recompute its checksum (a deliberate writer)."""
    doc = json.loads(path.read_text())
    change(doc)
    doc["sha256"] = checksum(doc)
    path.write_text(json.dumps(doc))


def test_error_class_is_a_calibration_error():
    assert issubclass(CalibrationFileError, CalibrationError)


def test_round_trip(tmp_path):
    store = CalibrationStore(tmp_path / "cal")
    cal = make_cal(1)
    assert store.save(cal) == 1
    back = store.load(1)
    assert back == cal and back is not cal
    assert back.links_mm.tobytes() == cal.links_mm.tobytes()
    assert back.motor_ids == tuple(MOTORS) and back.rope_ids == tuple(MOTORS)
    assert back.created_utc == cal.created_utc and back.routine is Routine.KINEMATIC
    assert dict(back.residuals) == {"rms_before_mm": 1.5, "rms_after_mm": 0.05}
    assert not back.links_mm.flags.writeable
    with pytest.raises(AttributeError):
        back.links_mm = back.links_mm  # type: ignore[misc]
    doc = json.loads((tmp_path / "cal" / "v0001.json").read_text())
    assert doc["format"] == "hrm-calibration/3" and doc["version"] == 1
    assert doc["sha256"] == checksum(doc)
    assert store.load_for(ROBOT) == cal


def test_checksum_catches_an_edited_value(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal())
    path = tmp_path / "v0001.json"
    text = path.read_text()
    doc = json.loads(text)
    old = json.dumps(doc["links_mm"][3])
    edited = text.replace(old, json.dumps(doc["links_mm"][3] + 0.5), 1)
    assert edited != text
    path.write_text(edited)
    with pytest.raises(CalibrationFileError, match="checksum mismatch") as exc:
        store.load(1)
    _one_line_naming(exc, path)
    # an id renamed, a count changed: the same
    for a, b in [('"j05r2"', '"j05r9"'), ('"routine": "kinematic"', '"routine": "manual"')]:
        path.write_text(text.replace(a, b, 1))
        with pytest.raises(CalibrationFileError, match="checksum mismatch"):
            store.load(1)


def test_checksum_or_parser_catches_every_truncation(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal())
    path = tmp_path / "v0001.json"
    raw = path.read_bytes()
    text = raw.decode()
    for n in range(len(text) - 1):  # the last bytes are "}\n": cut at least the brace
        with pytest.raises(CalibrationFileError, match=r"^p\.json: "):
            from_json(text[:n], "p.json", 1)
    for n in (0, 1, len(raw) // 2, len(raw) - 2):  # and through the store, a few
        path.write_bytes(raw[:n])
        with pytest.raises(CalibrationFileError) as exc:
            store.load(1)
        _one_line_naming(exc, path)
    path.write_bytes(raw)
    assert store.load(1) == make_cal()


def test_another_robot_is_refused(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal(robot=OTHER_ROBOT))
    with pytest.raises(CalibrationFileError, match="belongs to robot description cdcd") as exc:
        store.load_for(ROBOT)
    _one_line_naming(exc, tmp_path / "v0001.json")
    assert store.load_for(OTHER_ROBOT) == make_cal(robot=OTHER_ROBOT)
    store.save(make_cal(robot=ROBOT))
    with pytest.raises(CalibrationFileError, match="belongs to robot"):
        store.use(1, robot_sha256=ROBOT)
    assert store.active() == 2


def test_history_use_active(tmp_path):
    store = CalibrationStore(tmp_path / "store")
    assert store.versions() == [] and store.history() == [] and store.active() is None
    with pytest.raises(CalibrationFileError, match="no active calibration"):
        store.load_for(ROBOT)
    assert [store.save(make_cal(i)) for i in range(3)] == [1, 2, 3]
    assert store.active() == 3
    store.use(1)
    assert store.active() == 1 and store.load_for(ROBOT) == make_cal(0)
    assert store.save(make_cal(9), activate=False) == 4 and store.active() == 1
    hist = store.history()
    assert [(h.version, h.active, h.problem) for h in hist] == [
        (1, True, None),
        (2, False, None),
        (3, False, None),
        (4, False, None),
    ]
    assert hist[1].calibration == make_cal(1) and hist[3].path.name == "v0004.json"
    # a damaged version shows in the history and cannot be made active
    (tmp_path / "store" / "v0002.json").write_text("{")
    assert "v0002.json" in (store.history()[1].problem or "")
    with pytest.raises(CalibrationFileError, match=r"v0002\.json"):
        store.use(2)
    assert store.active() == 1
    with pytest.raises(CalibrationFileError, match="not found"):
        store.use(7)
    # the active pointer names a file that is gone, or garbage
    pointer = tmp_path / "store" / "active"
    pointer.write_text("v0009.json\n")
    with pytest.raises(CalibrationFileError, match="not in the store") as exc:
        store.active()
    _one_line_naming(exc, pointer)
    pointer.write_text("../../etc/passwd\n")
    with pytest.raises(CalibrationFileError, match="does not name a version file"):
        store.load_for(ROBOT)
    pointer.write_text("x" * 10_000)
    with pytest.raises(CalibrationFileError, match="larger than"):
        store.active()


def test_a_copied_or_renamed_file_is_refused(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal())
    (tmp_path / "v0002.json").write_bytes((tmp_path / "v0001.json").read_bytes())
    with pytest.raises(CalibrationFileError, match="records version 1, not 2"):
        store.load(2)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.update(format="hrm-calibration/4"), "format is .hrm-calibration/4."),
        (lambda d: d["links_mm"].pop(), "links_mm has 11 values, not 12"),
        (lambda d: d["theta_offset_rad"].append(0.0), "theta_offset_rad has 13 values"),
        (lambda d: d["alpha_offset_rad"].__setitem__(2, float("nan")), r"alpha_offset_rad\[2\]"),
        (lambda d: d["links_mm"].__setitem__(0, float("inf")), "NaN and infinity"),
        (lambda d: d["links_mm"].__setitem__(0, -1.0), r"links_mm\[0\] is -1.0, not > 0"),
        (lambda d: d["rope_EA_N"].update(j01r1=float("nan")), "rope_EA_N.j01r1 is nan"),
        (lambda d: d["rope_EA_N"].update(j01r1=0.0), "rope_EA_N.j01r1 is 0.0, not > 0"),
        (lambda d: d["motor_zero_counts"].update(j01r1=1.5), "not an integer count"),
        (lambda d: d["motor_zero_counts"].update(j01r1=2**40), "32-bit position"),
        (lambda d: d["motor_zero_counts"].update({"a b": 1}), "id 'a b'"),
        (lambda d: d.update(motor_zero_counts={}), "motor_zero_counts is empty"),
        (
            lambda d: d.update(motor_zero_counts={f"m{i}": 0 for i in range(MAX_MOTORS + 1)}),
            "more than the 128 allowed",
        ),
        (lambda d: d["residuals"].update(rms_mm=float("nan")), "residuals.rms_mm"),
        (lambda d: d.update(routine="guess"), "routine 'guess' is not one of"),
        (lambda d: d.update(created_utc="2026-12-01T10:00:00"), "created_utc must be a UTC"),
        (lambda d: d.update(created_utc="yesterday"), "not an ISO 8601 time"),
        (lambda d: d.update(robot_sha256="ABC"), "robot_sha256 is not 64"),
        (lambda d: d.pop("rope_EA_N"), r"members missing \['rope_EA_N'\]"),
        (lambda d: d.update(extra=1), r"unknown \['extra'\]"),
        (lambda d: d.update(version=True), "version True is not an integer"),
    ],
)
def test_a_wrong_file_is_refused_naming_it(tmp_path, change, message):
    store = CalibrationStore(tmp_path)
    store.save(make_cal())
    path = tmp_path / "v0001.json"
    _rewrite(path, change)
    with pytest.raises(CalibrationFileError, match=message) as exc:
        store.load(1)
    _one_line_naming(exc, path)


def test_bounded_sizes(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal())
    path = tmp_path / "v0001.json"
    path.write_text(" " * (MAX_FILE_BYTES + 1))
    with pytest.raises(CalibrationFileError, match="larger than"):
        store.load(1)
    for text, message in [
        ("[1, 2]", "not a JSON object"),
        ("1" * 400, "too large"),
        ("", "truncated or damaged"),
    ]:
        path.write_text(text)
        with pytest.raises(CalibrationFileError, match=message):
            store.load(1)
    with pytest.raises(CalibrationFileError, match="more than the 128 allowed"):
        Calibration.nominal(
            links_mm=[60.0] * 12,
            motor_ids=[f"m{i}" for i in range(MAX_MOTORS + 1)],
            rope_EA_N={"m": 3e4},
            robot_sha256=ROBOT,
        )
    with pytest.raises(CalibrationFileError, match="version 0 is not"):
        store.load(0)


def test_a_calibration_is_checked_when_made():
    with pytest.raises(CalibrationFileError, match=r"calibration: links_mm\[5\] is nan"):
        Calibration.nominal(
            links_mm=[60.0] * 5 + [float("nan")] + [60.0] * 6,
            motor_ids=["m"],
            rope_EA_N={"m": 3e4},
            robot_sha256=ROBOT,
        )
    with pytest.raises(CalibrationFileError, match="created_utc must be a UTC"):
        Calibration(**{**_fields(make_cal()), "created_utc": datetime(2026, 1, 1)})
    cal = Calibration(**{**_fields(make_cal()), "routine": "zero"})
    assert cal.routine is Routine.ZERO


def _fields(cal: Calibration) -> dict:
    return {k: getattr(cal, k) for k in Calibration.__dataclass_fields__}


def test_a_failed_write_leaves_the_store_as_it_was(tmp_path, monkeypatch):
    store = CalibrationStore(tmp_path)
    store.save(make_cal(0))

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "link", broken)
    with pytest.raises(CalibrationFileError, match=r"v0002\.json: cannot write"):
        store.save(make_cal(1))
    monkeypatch.undo()
    monkeypatch.setattr(os, "replace", broken)
    with pytest.raises(CalibrationFileError, match="active: cannot write"):
        store.save(make_cal(2))  # the version is written, the pointer is not moved
    monkeypatch.undo()
    assert store.versions() == [1, 2] and store.active() == 1
    assert store.load(2) == make_cal(2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["active", "v0001.json", "v0002.json"]


def test_stale_temporary_files_are_not_versions_and_are_removed(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal())
    stale = tmp_path / ".v0002.json.abc123.tmp"
    stale.write_text('{"format": "hrm-calibration/1"')
    fresh = tmp_path / ".v0002.json.def456.tmp"
    fresh.write_text("{")
    old = time.time() - 7200
    os.utime(stale, (old, old))
    other = tmp_path / ".notes.tmp"  # not the store's: left alone
    other.write_text("")
    os.utime(other, (old, old))
    (tmp_path / "v00001.json").write_text("{")  # not a version's name (v0001.json is)
    assert store.versions() == [1]
    assert store.save(make_cal(1)) == 2
    assert not stale.exists() and fresh.exists()  # a fresh one may be another writer's
    assert other.exists()


CHILD = textwrap.dedent(
    """
    import sys
    from datetime import UTC, datetime
    from calibration.store import Calibration, CalibrationStore, Routine

    store = CalibrationStore(sys.argv[1])
    ids = [f"j{j:02d}r{r}" for j in range(1, 13) for r in range(1, 4)]
    i = 0
    while True:
        i += 1
        cal = Calibration(
            links_mm=[60.0 + i * 1e-3] * 12,
            alpha_offset_rad=[1e-4 * i] * 12,
            theta_offset_rad=[-1e-4 * i] * 12,
            motor_zero_counts={m: i for m in ids},
            rope_EA_N={m: 3e4 + i for m in ids},
            created_utc=datetime.now(UTC),
            routine=Routine.ZERO,
            residuals={"seq": float(i)},
            robot_sha256="ab" * 32,
        )
        print(store.save(cal), flush=True)
    """
)


def test_sigkill_during_writes_leaves_every_version_and_the_pointer_loadable(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(CHILD)
    folder = tmp_path / "store"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    rng = random.Random(12)
    last_reported = 0
    mid_write = 0  # kills that left a new temporary file behind (for the report below)
    seen_tmp: set[str] = set()
    for kill in range(10):
        proc = subprocess.Popen(
            [sys.executable, str(script), str(folder)],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            first = proc.stdout.readline()  # type: ignore[union-attr]
            assert first.strip().isdigit(), proc.stderr.read()  # type: ignore[union-attr]
            time.sleep(rng.uniform(0.0, 0.05))
        finally:
            proc.send_signal(signal.SIGKILL)
            out, _ = proc.communicate(timeout=30)
        assert proc.returncode == -signal.SIGKILL
        reported = [int(line) for line in [first, *out.splitlines()] if line.strip().isdigit()]
        assert reported[0] == last_reported + 1 or reported[0] > last_reported
        last_reported = reported[-1]

        tmp = {p.name for p in folder.iterdir() if p.name.endswith(".tmp")}
        mid_write += bool(tmp - seen_tmp)
        seen_tmp |= tmp
        store = CalibrationStore(folder)
        versions = store.versions()
        # every version the child reported is there, and every file named as a version
        # is whole: no partial file is ever taken for a version
        assert versions == list(range(1, len(versions) + 1)), versions
        assert len(versions) >= last_reported
        hist = store.history()
        assert all(h.problem is None for h in hist), [h.problem for h in hist if h.problem]
        for h in hist:
            assert h.calibration is not None
            seq = h.calibration.residuals["seq"]
            assert h.calibration.motor_zero_counts["j01r1"] == int(seq), kill
        active = store.active()
        assert active is not None and active >= last_reported, (active, last_reported)
        assert store.load_for("ab" * 32) == store.load(active)
        assert {h.version for h in hist if h.active} == {active}
    print(f"{mid_write} of 10 kills left a temporary file (killed mid-write)")


finite = st.floats(allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=0.0, exclude_min=True, allow_infinity=False)
twelve = st.lists(finite, min_size=12, max_size=12)
ids = st.lists(
    st.from_regex(r"[A-Za-z0-9_.-]{1,32}", fullmatch=True), min_size=1, max_size=8, unique=True
)
PINNED = [-0.0, 5e-324, 1.7976931348623157e308, 0.1 + 0.2, -2.2250738585072014e-308] + [1.0] * 7


@settings(max_examples=200, deadline=None)
@given(
    links=st.lists(positive, min_size=12, max_size=12),
    alpha=twelve,
    theta=twelve,
    motors=ids,
    counts=st.data(),
    ea=positive,
    residual=finite,
)
@example(
    links=[5e-324, 1.7976931348623157e308, 0.30000000000000004, *[60.0] * 9],
    alpha=PINNED,
    theta=list(reversed(PINNED)),
    motors=["j01r1"],
    counts=None,
    ea=5e-324,
    residual=-0.0,
)
def test_arbitrary_floats_round_trip_exactly(links, alpha, theta, motors, counts, ea, residual):
    zeros = (
        [0] * len(motors)
        if counts is None
        else counts.draw(
            st.lists(st.integers(-(2**31), 2**31 - 1), min_size=len(motors), max_size=len(motors))
        )
    )
    cal = Calibration(
        links_mm=links,
        alpha_offset_rad=np.array(alpha),
        theta_offset_rad=theta,
        motor_zero_counts=dict(zip(motors, zeros, strict=True)),
        rope_EA_N=dict.fromkeys(motors, ea),
        created_utc=datetime.now(UTC),
        routine=Routine.STIFFNESS,
        residuals={"r": residual},
        robot_sha256=ROBOT,
    )
    back = from_json(to_json(cal, 7), "p.json", 7)
    given_arrays = {"links_mm": links, "alpha_offset_rad": alpha, "theta_offset_rad": theta}
    for key, values in given_arrays.items():
        assert getattr(back, key).tobytes() == np.array(values, dtype=float).tobytes(), key
    assert np.array(list(back.rope_EA_N.values())).tobytes() == np.full(len(motors), ea).tobytes()
    assert list(back.motor_zero_counts.values()) == zeros
    assert np.float64(back.residuals["r"]).tobytes() == np.float64(residual).tobytes()
    assert back == cal and back.created_utc == cal.created_utc


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("v0009.json\n", "names v0009.json, which is not in the store"),
        ("v0000.json\n", "names version 0, not 1..999999"),
        ("garbage\n", "does not name a version file"),
        ("", "does not name a version file"),
        ("fifo", "not a regular file"),
        ("folder", "not a regular file"),
        ("link", "symbolic link"),
    ],
)
def test_history_lists_the_versions_beside_a_damaged_pointer(tmp_path, damage, message):
    """A damaged ``active`` marks no version active and is its own problem (one line naming
    it); every version is still listed, and ``active()`` still refuses it."""
    store = CalibrationStore(tmp_path)
    assert [store.save(make_cal(i)) for i in range(2)] == [1, 2]
    pointer = tmp_path / "active"
    pointer.unlink()
    if damage == "fifo":
        os.mkfifo(pointer)
    elif damage == "folder":
        pointer.mkdir()
    elif damage == "link":  # names a sound version, but is not the store's own file
        (tmp_path.parent / "elsewhere").write_text("v0001.json\n")
        pointer.symlink_to(tmp_path.parent / "elsewhere")
    else:
        pointer.write_text(damage)
    assert [(h.version, h.active, h.problem) for h in store.history()] == [
        (1, False, None),
        (2, False, None),
    ]
    problem = store.active_problem() or ""
    assert message in problem and str(pointer) in problem and "\n" not in problem
    with pytest.raises(CalibrationFileError, match=message) as exc:
        store.active()
    _one_line_naming(exc, pointer)


def test_a_sound_pointer_has_no_problem(tmp_path):
    store = CalibrationStore(tmp_path)
    assert store.active_problem() is None  # no store yet
    store.save(make_cal())
    assert store.active_problem() is None and store.active() == 1


def test_a_folder_in_the_pointers_place_is_refused_before_anything_is_written(tmp_path):
    store = CalibrationStore(tmp_path)
    store.save(make_cal(0))
    pointer = tmp_path / "active"
    pointer.unlink()
    pointer.mkdir()
    (pointer / "keep").write_text("the user's")
    for act in (lambda: store.save(make_cal(1)), lambda: store.use(1)):
        with pytest.raises(CalibrationFileError, match="active pointer is a folder") as exc:
            act()
        _one_line_naming(exc, pointer)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["active", "v0001.json"]
    assert (pointer / "keep").read_text() == "the user's"  # not removed
    assert store.save(make_cal(1), activate=False) == 2  # not touching the pointer: allowed


@pytest.mark.parametrize("kind", ["outside", "inside", "dangling", "folder"])
def test_a_version_file_that_is_not_a_regular_file_is_refused(tmp_path, kind):
    """A version must be the store's own regular file: a symbolic link (to a sound
    calibration outside the store or to another version), a dangling one or a folder is
    refused naming it, by load, use and history alike."""
    store = CalibrationStore(tmp_path / "store")
    assert [store.save(make_cal(i)) for i in range(2)] == [1, 2]
    path = store.path_of(2)
    if kind == "outside":
        path.rename(tmp_path / "elsewhere.json")
        path.symlink_to(tmp_path / "elsewhere.json")
        assert from_json((tmp_path / "elsewhere.json").read_text(), "x", 2) == make_cal(1)
    elif kind == "inside":
        path.unlink()
        path.symlink_to("v0001.json")
    elif kind == "dangling":
        path.unlink()
        path.symlink_to(tmp_path / "gone.json")
    else:
        path.unlink()
        path.mkdir()
    message = "not a regular file" if kind == "folder" else "symbolic link"
    with pytest.raises(CalibrationFileError, match=message) as exc:
        store.load(2)
    _one_line_naming(exc, path)
    store.use(1)
    with pytest.raises(CalibrationFileError, match=message):
        store.use(2)
    assert (tmp_path / "store" / "active").read_text() == "v0001.json\n"  # not moved
    hist = store.history()
    assert [h.version for h in hist] == [1, 2] and hist[0].problem is None
    assert hist[1].calibration is None and message in (hist[1].problem or "")
    (tmp_path / "store" / "active").write_text("v0002.json\n")
    with pytest.raises(CalibrationFileError, match=message):
        store.load_for(ROBOT)


def test_a_store_that_is_a_file_is_refused_not_taken_for_an_empty_one(tmp_path):
    """``--calibrations /etc/passwd``: not "no calibration yet" (which would run with the
    description's values), but one line naming it."""
    path = tmp_path / "store"
    path.write_text("root:x:0:0\n")
    store = CalibrationStore(path)
    for act in (store.active, store.load_active, lambda: store.load_for(ROBOT)):
        with pytest.raises(CalibrationFileError, match="calibration store is not a folder") as exc:
            act()
        _one_line_naming(exc, path)
    assert CalibrationStore(tmp_path / "none-yet").active() is None  # missing: none yet
