"""A run as it went over the wire: the run record (``hrm-run/1``, written by the drive
session beside its CAN logs) and the logs themselves (``.blf`` / ``.asc``, read with
python-can's :class:`can.LogReader`) as typed arrays.

Per SYNC (one control cycle) of the first bus: its wire time, the target every motor
was commanded (the last RPDO1 before that SYNC: controlword + target position, applied at
the SYNC) and the position it reported (its TPDO1 after that SYNC: statusword + position
actual value), each in the record's motor order.  Streams are told apart by gaps in the
SYNCs (:data:`STREAM_GAP_S`).  The CANopen layouts are the ones ``drivers.protocol``
defines (RPDO1 0x200 + node, TPDO1 0x180 + node, SYNC 0x080); they are restated here
because this layer does not import the drivers.

:func:`joint_angles` maps counts to joint angles with the rope layer's inverse
(:meth:`hrm_ctrl.ropes.actuation.Actuation.angles_from_counts`); :func:`tension_csv`
reads the run's tension side file (``<run>_tension.csv``, written by ``hrm run`` when a
tension board is read) and :func:`write_tension_csv` writes it.

>>> split_streams(np.array([0.0, 0.01, 0.02, 5.0, 5.01]), 0.5)
[(0, 3), (3, 5)]
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.errors import HrmError
from hrm_ctrl.files import write_atomic

RUN_RECORD_FORMAT = "hrm-run/1"
MAX_RECORD_BYTES = 64 * 1024 * 1024  # a run record larger than this is refused
MAX_LOG_FRAMES = 60_000_000  # frames read from one CAN log at most (a 1 h run: ~27 M)
MAX_CYCLES = 400_000  # SYNCs kept at most (1 h at 100 Hz: 360 000)
MAX_TENSION_ROWS = 100_000
STREAM_GAP_S = 0.5  # SYNCs further apart than this belong to different streams
COB_SYNC = 0x080
COB_TPDO1 = 0x180
COB_RPDO1 = 0x200
_PDO = struct.Struct("<Hi")  # controlword/statusword (UNSIGNED16), position (INTEGER32)


class RunLogError(HrmError):
    """A run record or CAN log that cannot be read (one line naming file and problem)."""


@dataclass(frozen=True)
class RunLog:
    """A run's wire traffic as arrays: ``t_s`` (cycles,) SYNC wire times from the first
    SYNC, ``t0_unix`` that SYNC's timestamp; ``target`` / ``actual`` (cycles, motors)
    counts (``actual`` NaN where a TPDO is missing, ``target`` NaN before the first RPDO);
    ``streams`` (start, end) index ranges of the streams; ``frames`` per log."""

    record_path: Path
    record: dict[str, Any]
    motor_ids: tuple[str, ...]
    period_s: float
    t0_unix: float
    t_s: np.ndarray
    target: np.ndarray
    actual: np.ndarray
    streams: list[tuple[int, int]]
    frames: list[int]

    @property
    def n_cycles(self) -> int:
        return int(self.t_s.shape[0])

    def stream(self, index: int) -> slice:
        """The cycles of stream ``index`` (negative: from the end)."""
        if not self.streams:
            raise RunLogError(f"{self.record_path}: no stream in the CAN log")
        try:
            a, b = self.streams[index]
        except IndexError:
            raise RunLogError(
                f"{self.record_path}: stream {index}: the log has {len(self.streams)}"
            ) from None
        return slice(a, b)

    def sync_lateness_s(self) -> np.ndarray:
        """Each SYNC's interval from the one before less the control period (s); 0 first."""
        if self.n_cycles == 0:
            return np.zeros(0)
        d = np.diff(self.t_s, prepend=self.t_s[0]) - self.period_s
        d[0] = 0.0
        for a, _b in self.streams:  # the first SYNC of each stream has no predecessor
            d[a] = 0.0
        return d


def split_streams(t_s: np.ndarray, gap_s: float = STREAM_GAP_S) -> list[tuple[int, int]]:
    """(start, end) index ranges of runs of SYNC times without a gap over ``gap_s``."""
    n = len(t_s)
    if n == 0:
        return []
    cuts = [0, *(int(i) + 1 for i in np.flatnonzero(np.diff(t_s) > gap_s)), n]
    return [(cuts[i], cuts[i + 1]) for i in range(len(cuts) - 1)]


def read_record(path: str | Path) -> dict[str, Any]:
    """The run record at ``path`` (``hrm-run/1``), checked for what this module uses."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_RECORD_BYTES:
            raise RunLogError(f"{p}: run record of {size} bytes (at most {MAX_RECORD_BYTES})")
        doc = json.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise RunLogError(f"{p}: cannot read run record ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RunLogError(f"{p}: not a run record (JSON: {exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != RUN_RECORD_FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise RunLogError(f"{p}: not a run record (format {got!r}, expected {RUN_RECORD_FORMAT})")
    for key, kind in (("motor_ids", list), ("config", dict), ("can_logs", list)):
        if not isinstance(doc.get(key), kind):
            raise RunLogError(f"{p}: run record without {key!r}")
    return doc


def _node_maps(doc: dict[str, Any], where: Path) -> list[dict[int, int]]:
    """Per bus (record order): node id -> motor index."""
    order = {m: i for i, m in enumerate(doc["motor_ids"])}
    buses = doc["config"].get("buses")
    if not isinstance(buses, dict) or not buses:
        raise RunLogError(f"{where}: run record without buses in its config")
    maps = []
    for name, bus in buses.items():
        nodes = bus.get("nodes") if isinstance(bus, dict) else None
        if not isinstance(nodes, dict):
            raise RunLogError(f"{where}: bus {name}: no nodes in the record's config")
        try:
            maps.append({int(nid): order[m] for m, nid in nodes.items()})
        except (KeyError, TypeError, ValueError):
            raise RunLogError(
                f"{where}: bus {name}: nodes that are not the record's motors"
            ) from None
    return maps


def _log_path(record_path: Path, logged: str) -> Path:
    """A CAN log named in the record: as written, or beside the record (moved runs)."""
    p = Path(logged)
    if p.exists():
        return p
    return record_path.parent / p.name


def read_run(path: str | Path, *, max_frames: int = MAX_LOG_FRAMES) -> RunLog:
    """The run record at ``path`` and its CAN logs as a :class:`RunLog`."""
    import can

    rp = Path(path)
    doc = read_record(rp)
    maps = _node_maps(doc, rp)
    logs = [str(x) for x in doc["can_logs"]]
    if len(logs) != len(maps):
        raise RunLogError(f"{rp}: {len(logs)} CAN logs for {len(maps)} buses")
    n = len(doc["motor_ids"])
    try:
        period_s = 1.0 / float(doc["config"]["control"]["rate_hz"])
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        raise RunLogError(f"{rp}: run record without a control rate") from None
    sync_t: list[float] = []
    target_rows: list[np.ndarray] = []
    actual_rows: list[np.ndarray] = []
    frames: list[int] = []
    for b, (logged, nodes) in enumerate(zip(logs, maps, strict=True)):
        lp = _log_path(rp, logged)
        held = np.full(n, np.nan)
        k = -1  # SYNCs of this bus so far
        count = 0
        try:
            reader = can.LogReader(str(lp))
        except (OSError, ValueError, can.CanError) as exc:
            raise RunLogError(f"{lp}: cannot open CAN log ({exc})") from None
        try:
            for msg in reader:
                count += 1
                if count > max_frames:
                    raise RunLogError(f"{lp}: more than {max_frames} frames")
                if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                    continue
                cid = msg.arbitration_id
                if cid == COB_SYNC and len(msg.data) == 0:
                    k += 1
                    if k >= MAX_CYCLES:
                        raise RunLogError(f"{lp}: more than {MAX_CYCLES} SYNCs")
                    if b == 0:
                        sync_t.append(float(msg.timestamp))
                        target_rows.append(held.copy())
                        actual_rows.append(np.full(n, np.nan))
                    elif k < len(target_rows):
                        target_rows[k] = np.where(np.isnan(held), target_rows[k], held)
                    continue
                base, nid = cid & 0x780, cid & 0x07F
                if len(msg.data) != _PDO.size or nid not in nodes:
                    continue
                if base == COB_RPDO1:
                    held[nodes[nid]] = _PDO.unpack(bytes(msg.data))[1]
                elif base == COB_TPDO1 and 0 <= k < len(actual_rows):
                    actual_rows[k][nodes[nid]] = _PDO.unpack(bytes(msg.data))[1]
        except RunLogError:
            raise
        except (OSError, ValueError, struct.error, can.CanError) as exc:
            raise RunLogError(f"{lp}: cannot read CAN log ({exc})") from None
        finally:
            stop = getattr(reader, "stop", None)
            if callable(stop):
                stop()
        frames.append(count)
    t = np.asarray(sync_t, dtype=np.float64)
    t0 = float(t[0]) if t.size else math.nan
    return RunLog(
        record_path=rp,
        record=doc,
        motor_ids=tuple(str(m) for m in doc["motor_ids"]),
        period_s=period_s,
        t0_unix=t0,
        t_s=t - t0 if t.size else t,
        target=np.array(target_rows).reshape(-1, n),
        actual=np.array(actual_rows).reshape(-1, n),
        streams=split_streams(t - t0 if t.size else t),
        frames=frames,
    )


def joint_angles(actuation: Any, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, theta) (rows, 12) rad from counts (rows, motors); rows with a missing
    value come out NaN."""
    c = np.asarray(counts, dtype=np.float64)
    nj = int(actuation.robot.n_joints)
    alpha = np.full((c.shape[0], nj), np.nan)
    theta = np.full((c.shape[0], nj), np.nan)
    ok = np.isfinite(c).all(axis=1)
    if ok.any():
        a, t, _res = actuation.angles_from_counts(c[ok], robust=False)
        alpha[ok], theta[ok] = a, t
    return alpha, theta


def tension_path(record_path: str | Path) -> Path:
    """Where a run's tension side file goes: ``<run>_tension.csv`` beside the record."""
    p = Path(record_path)
    return p.with_name(p.stem + "_tension.csv")


def write_tension_csv(
    path: str | Path, t_unix: Sequence[float], tensions_N: np.ndarray, motor_ids: Sequence[str]
) -> Path:
    """Write tension samples (wire-clock times, N per motor) atomically, at most
    :data:`MAX_TENSION_ROWS` rows (the newest kept)."""
    tn = np.asarray(tensions_N, dtype=np.float64).reshape(len(t_unix), len(motor_ids))
    t = np.asarray(t_unix, dtype=np.float64)[-MAX_TENSION_ROWS:]
    tn = tn[-MAX_TENSION_ROWS:]
    lines = ["t_unix_s," + ",".join(f"{m}_N" for m in motor_ids)]
    for ti, row in zip(t, tn, strict=True):
        lines.append(f"{ti:.6f}," + ",".join("" if not np.isfinite(v) else f"{v:.3f}" for v in row))
    p = Path(path)
    write_atomic(p, "\n".join(lines) + "\n")
    return p


def tension_csv(path: str | Path, motor_ids: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(t_unix (rows,), tensions_N (rows, motors)) of a tension side file."""
    p = Path(path)
    try:
        with p.open(encoding="utf-8") as fh:
            header = fh.readline().strip().split(",")
            want = ["t_unix_s", *(f"{m}_N" for m in motor_ids)]
            if header != want:
                raise RunLogError(f"{p}: not this run's tension file (header {header[:3]}...)")
            rows = []
            for i, line in enumerate(fh, start=2):
                if i > MAX_TENSION_ROWS + 1:
                    raise RunLogError(f"{p}: more than {MAX_TENSION_ROWS} rows")
                cells = line.rstrip("\n").split(",")
                if len(cells) != len(want):
                    raise RunLogError(f"{p}:{i}: {len(cells)} fields, expected {len(want)}")
                rows.append([float(c) if c else math.nan for c in cells])
    except OSError as exc:
        raise RunLogError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise RunLogError(f"{p}: not a number ({exc})") from None
    a = np.array(rows, dtype=np.float64).reshape(-1, len(motor_ids) + 1)
    return a[:, 0], a[:, 1:]
