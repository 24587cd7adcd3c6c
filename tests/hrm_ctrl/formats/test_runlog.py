"""hrm_ctrl.formats.runlog: a run record and its CAN logs as arrays (a synthetic BLF
written with python-can, so every value is known), and its bad input."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import can
import numpy as np
import pytest

from hrm_ctrl.formats.runlog import (
    RunLogError,
    read_record,
    read_run,
    tension_csv,
    tension_path,
    write_tension_csv,
)

PDO = struct.Struct("<Hi")


def _write_run(tmp: Path, targets: np.ndarray, actual: np.ndarray, t0: float = 1.7e9) -> Path:
    """Two buses, one motor each (node 1 on a, node 2 on b); per cycle k: the RPDOs, the
    SYNC at t0 + k*T (+ a 5 s gap after cycle 2: a second stream), then the TPDOs."""
    T = 0.01
    logs = []
    for b, (bus, nid) in enumerate((("a", 1), ("b", 2))):
        path = tmp / f"run-x_{bus}.blf"
        with can.BLFWriter(str(path)) as w:

            def put(t: float, cid: int, data: bytes, w: can.BLFWriter = w) -> None:
                w.on_message_received(
                    can.Message(timestamp=t, arbitration_id=cid, is_extended_id=False, data=data)
                )

            for k in range(targets.shape[0]):
                t = t0 + k * T + (5.0 if k >= 3 else 0.0)
                put(t - 0.004, 0x200 + nid, PDO.pack(15, int(targets[k, b])))
                put(t, 0x80, b"")
                if np.isfinite(actual[k, b]):
                    put(t + 0.002, 0x180 + nid, PDO.pack(0x1237, int(actual[k, b])))
        logs.append(str(path))
    rec = {
        "format": "hrm-run/1", "run": "run-x", "motor_ids": ["m0", "m1"],
        "config": {"control": {"rate_hz": 100.0},
                   "buses": {"a": {"nodes": {"m0": 1}}, "b": {"nodes": {"m1": 2}}}},
        "can_logs": logs,
    }  # fmt: skip
    p = tmp / "run-x.json"
    p.write_text(json.dumps(rec))
    return p


def test_arrays_are_the_logged_values(tmp_path: Path) -> None:
    targets = np.array([[0, 0], [10, -5], [30, -15], [40, -20], [45, -22]])
    actual = np.array([[0, 0], [0, 0], [10, np.nan], [30, -15], [40, -20]], dtype=float)
    log = read_run(_write_run(tmp_path, targets, actual))
    assert log.motor_ids == ("m0", "m1") and log.period_s == 0.01
    assert np.array_equal(log.target, targets.astype(float))
    assert np.array_equal(log.actual, actual, equal_nan=True)
    assert log.streams == [(0, 3), (3, 5)]  # the 5 s gap
    assert np.allclose(log.t_s[:3], [0.0, 0.01, 0.02])
    assert log.t0_unix == pytest.approx(1.7e9, abs=1e-3)
    assert log.frames == [5 * 3, 5 * 2 + 4]  # RPDO, SYNC, TPDO per cycle; one TPDO missing
    assert np.allclose(log.sync_lateness_s(), 0.0, atol=1e-6)  # every SYNC on its period


def test_tension_file_round_trip_and_bounds(tmp_path: Path) -> None:
    rec = tmp_path / "run-y.json"
    p = write_tension_csv(tension_path(rec), [1.0, 1.1], np.array([[30.0, np.nan], [31.5, 29.0]]),
                          ["m0", "m1"])  # fmt: skip
    assert p.name == "run-y_tension.csv"
    t, n = tension_csv(p, ["m0", "m1"])
    assert np.allclose(t, [1.0, 1.1]) and np.array_equal(n, [[30.0, np.nan], [31.5, 29.0]],
                                                         equal_nan=True)  # fmt: skip
    with pytest.raises(RunLogError, match="not this run's tension file"):
        tension_csv(p, ["m0", "other"])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{", r"not a run record \(JSON"),
        ('{"format": "hrm-plan/1"}', r"format 'hrm-plan/1', expected hrm-run/1"),
        ('{"format": "hrm-run/1", "motor_ids": [], "config": {}}', "without 'can_logs'"),
    ],
)
def test_bad_records_one_line(tmp_path: Path, text: str, message: str) -> None:
    p = tmp_path / "r.json"
    p.write_text(text)
    with pytest.raises(RunLogError, match=message) as exc:
        read_record(p)
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)


def test_missing_log_named(tmp_path: Path) -> None:
    p = _write_run(tmp_path, np.zeros((2, 2), int), np.zeros((2, 2)))
    (tmp_path / "run-x_b.blf").unlink()
    with pytest.raises(RunLogError, match=r"run-x_b\.blf: cannot open CAN log"):
        read_run(p)
