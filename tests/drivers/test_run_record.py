"""drivers/run_record.py: the run record names the calibration; it is written atomically
or refused in one line with the OS error as its cause."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from drivers.run_record import (
    UNCALIBRATED,
    CalibrationRef,
    calibration_entry,
    jsonable,
    write_run_record,
)
from drivers.sources import HoldSource
from hrm_ctrl.errors import DriverError
from tests.drivers.driver_rig import Rig


def test_the_run_record_names_the_calibration(
    rig_factory: Callable[..., Rig], tmp_path: Path
) -> None:
    rig = rig_factory()
    box = rig.open_box(log_dir=tmp_path / "a", allow_uncalibrated=True)
    box.bring_up()  # (the rig's box: a calibration of it names its drives)
    ref = CalibrationRef(7, "ab" * 32, "/store/v0007.json", box=box.box_identity)
    box.finish()
    box.close()
    rig.box = None
    box = rig.open_box(log_dir=tmp_path / "a", calibration=ref, allow_uncalibrated=False)
    box.bring_up()
    assert box.stream(HoldSource(n_cycles=3)).completed
    box.finish()
    record = json.loads(box.close().read_text())  # type: ignore[union-attr]
    assert record["calibration"] == {"version": 7, "sha256": "ab" * 32, "source": ref.source}
    assert record["box"] == ref.box.to_dict() and record["box"]["simulated"] is True
    rig.box = None
    box = rig.open_box(log_dir=tmp_path / "b")  # the rig's explicit override
    box.bring_up()
    box.finish()
    record = json.loads(box.close().read_text())  # type: ignore[union-attr]
    rig.box = None
    assert record["calibration"] == UNCALIBRATED == "uncalibrated (override)"
    with pytest.raises(TypeError, match="CalibrationRef"):
        rig.open_box(calibration={"version": 1})


def test_without_a_calibration_the_record_says_why() -> None:
    assert calibration_entry(None, True) == UNCALIBRATED
    assert calibration_entry(None, False) == "none (enable refused)"


def test_the_record_is_json_without_non_finite_numbers(tmp_path: Path) -> None:
    path = tmp_path / "run.json"
    write_run_record(path, {"a": [1.5, float("inf")], "b": np.float64("nan"), "c": np.int64(2)})
    assert json.loads(path.read_text()) == {"a": [1.5, None], "b": None, "c": 2}
    assert jsonable((np.float32(0.5),)) == [0.5]


def test_a_record_that_cannot_be_written_is_one_line_with_its_cause(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    path = tmp_path / "a-file" / "run.json"  # its directory is a file
    with pytest.raises(DriverError) as info:
        write_run_record(path, {"run": "x"})
    assert str(info.value).startswith(f"run record {path}: cannot write it (")
    assert "\n" not in str(info.value)
    assert isinstance(info.value.__cause__, OSError)  # what the OS said, for a log reader
