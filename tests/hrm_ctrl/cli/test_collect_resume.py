"""``hrm calibrate kinematic --collect N`` keeps every pose as it is measured: a collection
that stops (here the tracker fails at the third pose) leaves its poses in the log folder,
and the same command resumes from them, driving only the poses still missing."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from hrm_ctrl.cli import main

pytestmark = pytest.mark.slow


@pytest.fixture
def isolated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("HRM_CALIBRATIONS", str(tmp_path / "calibrations"))
    return tmp_path


def test_a_stopped_collection_keeps_its_poses_and_resumes(isolated, capsys, monkeypatch):
    from drivers.tracker import TrackerReader
    from hrm_ctrl.errors import DriverError

    logs = isolated / "runs"
    argv = ["calibrate", "kinematic", "--collect", "6", "--sim", "--samples", "1",
            "--log-dir", str(logs)]  # fmt: skip
    real_measure = TrackerReader.measure

    def failing(self, n=1, fiducial=0):  # the third pose's reading fails
        kept = list(logs.glob("collect-*.json"))
        if kept and len(json.loads(kept[0].read_text())["measured"]) == 2:
            raise DriverError("tracker /dev/ttyX: no answer in 1 s (simulated failure)")
        return real_measure(self, n, fiducial)

    monkeypatch.setattr(TrackerReader, "measure", failing)
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert len(list(logs.glob("collect-*.json"))) == 1, err
    (journal,) = logs.glob("collect-*.json")
    kept = json.loads(journal.read_text())
    assert kept["poses"] == 6 and len(kept["measured"]) == 2
    assert f"2 of 6 poses kept in {journal}: the same command resumes from them" in err
    assert "no answer in 1 s" in err

    monkeypatch.setattr(TrackerReader, "measure", real_measure)
    rc = main(argv)
    out, err = capsys.readouterr()
    assert f"resuming: 2 of 6 poses kept in {journal}" in err, err
    # only the four missing poses were driven and read
    assert re.findall(r"^pose (\d)/6:", err, re.M) == ["3", "4", "5", "6"], err
    # the collection is complete (6 poses are too few for a fit: refused after the pose
    # file is written, a short test's price)
    assert rc == 2 and "kinematic fit refused: too few poses" in err, err
    assert "poses written to " in out and not journal.exists()  # folded into the pose file
    from calibration.kinematic import read_pose_csv

    (pose_file,) = logs.glob("*-poses.csv")
    data = read_pose_csv(pose_file)
    assert len(data) == 6
    first = np.array([m["point_mm"] for m in kept["measured"]])
    assert np.allclose(data.points_mm[:2], first, atol=1e-6)
    assert np.allclose(data.alpha_rad[:2], [m["alpha_rad"] for m in kept["measured"]])
