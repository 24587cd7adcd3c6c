"""The calibration store kept safe (issue 34, item 7): a store others can write is not
used; a routine checks the store can keep its result before its first move; no output of
another command is written into a store."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

import pytest

from calibration.apply import nominal_calibration
from calibration.store import MAX_VERSION, CalibrationStore
from hrm_ctrl.cli import main
from hrm_ctrl.errors import CalibrationFileError
from hrm_ctrl.model import default_robot

NOBODY = 65534


@pytest.fixture
def store(tmp_path: Path) -> CalibrationStore:
    s = CalibrationStore(tmp_path / "cal")
    s.save(nominal_calibration(default_robot()))
    return s


def test_a_world_writable_store_is_refused_naming_owner_and_mode(store: CalibrationStore) -> None:
    os.chmod(store.folder, 0o777)
    for use in (store.active, store.history, lambda: store.load(1), store.check_can_save):
        with pytest.raises(CalibrationFileError) as exc:
            use()
        text = str(exc.value)
        assert text.startswith(f"{store.folder}: the calibration store is writable by everyone")
        assert "drwxrwxrwx (0777)" in text and f"chmod o-w {store.folder}" in text
    with pytest.raises(CalibrationFileError, match="writable by everyone"):
        store.save(nominal_calibration(default_robot()))
    assert store.versions.__self__ is store and sorted(os.listdir(store.folder))[-1] == "v0001.json"
    os.chmod(store.folder, 0o755)
    assert store.active() == 1


def test_a_store_of_another_user_is_refused(
    store: CalibrationStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    uid = os.stat(store.folder).st_uid
    monkeypatch.setattr(os, "getuid", lambda: uid + 1 if uid != NOBODY - 1 else uid + 2)
    with pytest.raises(CalibrationFileError) as exc:
        store.active()
    text = str(exc.value)
    assert "the calibration store is owned by" in text and f"(uid {uid})" in text
    assert "mode drwx" in text and "a store others can write is not used" in text


def test_check_before_you_move(store: CalibrationStore, monkeypatch: pytest.MonkeyPatch) -> None:
    store.check_can_save()  # ours, writable, numbers left
    last = store.folder / f"v{MAX_VERSION:06d}.json"
    last.write_text("{}")
    with pytest.raises(CalibrationFileError, match="no version number left"):
        store.check_can_save()
    last.unlink()

    def read_only(*a: object, **k: object) -> tuple[int, str]:
        raise PermissionError(13, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    with pytest.raises(CalibrationFileError, match=r"not writable \(Read-only file system\)"):
        store.check_can_save()
    # a folder in the active pointer's place: refused before anything is measured
    monkeypatch.undo()
    (store.folder / "active").unlink()
    (store.folder / "active").mkdir()
    with pytest.raises(CalibrationFileError, match="the active pointer is a folder"):
        store.check_can_save()


def test_calibrate_zero_refuses_a_full_store_before_the_first_move(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "cal"
    folder.mkdir()
    (folder / f"v{MAX_VERSION:06d}.json").write_text("{}")
    runs = tmp_path / "runs"
    argv = ["calibrate", "zero", "--sim", "--calibrations", str(folder), "--log-dir", str(runs)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "no version number left" in err and err.count("\n") == 1, err
    assert not runs.exists() or not list(runs.glob("*.json"))  # no session was opened
    # a store others can write: refused as well, naming its mode
    (folder / f"v{MAX_VERSION:06d}.json").unlink()
    os.chmod(folder, 0o777)
    assert main(argv) == 2
    assert "writable by everyone" in capsys.readouterr().err
    assert stat.S_IMODE(os.stat(folder).st_mode) == 0o777  # left as it was


@pytest.mark.parametrize("name", ["v0001.json", "active", "v0002.json"])
def test_no_output_is_written_into_a_store(
    name: str,
    store: CalibrationStore,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    before = {p.name: p.read_bytes() for p in store.folder.iterdir()}
    target = store.folder / name
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    scan = tmp_path / "scan.csv"
    scan.write_text("x,y,z\n0,0,0\n")
    commands = [
        ["urdf", "--out", str(target)],
        ["scan", str(scan), "--out", str(target)],
        ["plan", "--scenario", "bent-pipe", "--uncalibrated", "--out", str(target)],
        ["sim", "--write-truth", str(target), "--perturb", "1"],
    ]
    for argv in commands:
        # the store given to the command, the default one, or neither: refused alike
        for env in (str(store.folder), str(tmp_path / "elsewhere")):
            monkeypatch.setenv("HRM_CALIBRATIONS", env)
            assert main(argv) == 2, argv
            err = capsys.readouterr().err
            assert "is inside the calibration store" in err, (argv, err)
            assert str(store.folder) in err, (argv, err)
    assert {p.name: p.read_bytes() for p in store.folder.iterdir()} == before
    assert store.active() == 1
