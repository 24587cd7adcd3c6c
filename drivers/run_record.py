"""The run record: one JSON file per drive session, beside its CAN logs.

It names the configuration, the calibration the rope layer was built with
(:class:`CalibrationRef`, or :data:`UNCALIBRATED` when the operator overrode), the bus
loads, the bring-up time and the actual positions at the enable, every stream's result,
the events and emergencies, and each CAN log with its frames and losses.  Written
atomically (:func:`write_run_record`); non-finite numbers become ``null``.

>>> cal = CalibrationRef(3, "ab" * 32, "cal.toml")
>>> calibration_text(cal, False), calibration_text(None, True)
('version 3', 'uncalibrated (override)')
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.busload import BusLoad
from drivers.canlog import TrafficLog
from drivers.config import BoxConfig
from drivers.cycle import EventLog, StreamResult
from drivers.identity import BoxIdentity
from drivers.receive import BusReceiver
from drivers.safety.causes import StopCause
from drivers.safety.monitor import NodeMonitor
from hrm_ctrl.errors import DriverError
from hrm_ctrl.files import write_atomic

RUN_RECORD_FORMAT = "hrm-run/1"
UNCALIBRATED = "uncalibrated (override)"  # what the run record says without a calibration
NO_CALIBRATION = "none (enable refused)"  # neither a calibration nor the override


@dataclass(frozen=True)
class CalibrationRef:
    """Which calibration the session's rope layer was built with: its version in the
    store, the file's SHA-256 checksum, where it came from (a path) and the box it was
    made on (``box``; None: unknown).  With ``check_box`` the session refuses it at the
    bring-up unless that box is the one at hand (:func:`drivers.identity.check_box`);
    a routine that makes every motor zero anew (``calibrate zero``) does not check it."""

    version: int
    sha256: str
    source: str
    box: BoxIdentity | None = None
    check_box: bool = True

    def to_dict(self) -> dict[str, Any]:
        return {"version": self.version, "sha256": self.sha256, "source": self.source}


def calibration_entry(
    calibration: CalibrationRef | None, allow_uncalibrated: bool
) -> dict[str, Any] | str:
    """The record's ``calibration``: the reference, or why there is none."""
    if calibration is not None:
        return calibration.to_dict()
    return UNCALIBRATED if allow_uncalibrated else NO_CALIBRATION


def calibration_text(calibration: CalibrationRef | None, allow_uncalibrated: bool) -> str:
    """The calibration in a read-out: its version, or why there is none."""
    if calibration is not None:
        return f"version {calibration.version}"
    return UNCALIBRATED if allow_uncalibrated else NO_CALIBRATION


def run_record(
    *,
    run_name: str,
    config: BoxConfig,
    motor_ids: Sequence[str],
    calibration: CalibrationRef | None,
    allow_uncalibrated: bool,
    loads: Sequence[BusLoad],
    bringup_s: float | None,
    actual: np.ndarray | None,
    results: Sequence[StreamResult],
    state: str,
    receivers: Sequence[BusReceiver],
    idle_causes: Sequence[StopCause],
    events: EventLog,
    monitor: NodeMonitor,
    logs: Sequence[TrafficLog],
    extra: Mapping[str, Any],
) -> dict[str, Any]:
    """The run record: configuration, sources, events, timing statistics, logs."""
    return {
        "format": RUN_RECORD_FORMAT,
        "run": run_name,
        "written_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "config_source": config.source,
        "config": config.to_dict(),
        "motor_ids": list(motor_ids),
        "calibration": calibration_entry(calibration, allow_uncalibrated),
        "bus_loads": [bl.to_dict() for bl in loads],
        "bringup_s": bringup_s,
        "actual_counts_at_enable": None if actual is None else actual.tolist(),
        "streams": [r.to_dict() for r in results],
        "session_state": state,
        "bus_traffic": [r.traffic.to_dict() for r in receivers],
        "idle_stop_causes": [x.to_dict() for x in idle_causes],
        "events": events.to_list(),
        "emergencies": [e.describe() for e in monitor.emergencies],
        "emergencies_dropped": monitor.emergencies_dropped,
        "can_logs": [str(log.path) for log in logs],
        "can_log_frames": [log.n_frames for log in logs],
        "can_log_lost": [log.n_lost for log in logs],
        "can_log_errors": [log.first_error for log in logs if log.write_errors],
        **extra,
    }


def write_run_record(path: Path, record: Mapping[str, Any]) -> None:
    """Write ``record`` as JSON to ``path`` atomically; :class:`DriverError` (one line,
    the OS error chained) if it cannot be written."""
    text = json.dumps(jsonable(dict(record)), indent=1, allow_nan=False) + "\n"
    try:
        write_atomic(path, text)
    except OSError as exc:
        why = exc.strerror or exc
        raise DriverError(f"run record {path}: cannot write it ({why})") from exc


def jsonable(value: Any) -> Any:
    """Replace non-finite floats (not JSON) by None, recursively.

    >>> jsonable({"a": [1.0, float("nan")], "b": np.int64(3)})
    {'a': [1.0, None], 'b': 3}
    """
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return jsonable(value.item())
    return value
