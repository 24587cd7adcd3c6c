"""``hrm run`` paused, resumed and aborted from its arguments on the simulated box, and
``hrm report`` of those runs: figures written, arrays as the CAN log has them."""

from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.formats.runlog import read_run
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from tests.hrm_ctrl.cli.cli_helpers import run_cli, small_plan

SPEED = "10"  # mm/s: the small plan's 15 mm take 1.5 s, long enough to pause in


def _hrm(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    d = tmp_path_factory.mktemp("runs")
    mp = pytest.MonkeyPatch()
    mp.setenv("HRM_CALIBRATIONS", str(d / "calibrations"))  # none: the description's values
    plan = d / "small.json"
    plan.write_text(json.dumps(small_plan()))
    # the shipped box with watchdogs that bear a loaded test machine (a stall of the
    # in-process simulated box is not what these tests are about)
    import drivers

    box = (Path(drivers.__file__).parent / "data" / "box.toml").read_text()
    box = box.replace("heartbeat_timeout_ms = 350", "heartbeat_timeout_ms = 2000")
    box = box.replace("missing_tpdo_cycles = 3 ", "missing_tpdo_cycles = 25 ")
    assert "heartbeat_timeout_ms = 2000" in box and "missing_tpdo_cycles = 25" in box
    config = d / "box.toml"
    config.write_text(box)
    out: dict[str, Any] = {"dir": d, "plan": plan}
    for name, extra in (
        ("paused", ["--pause-at", "30%", "--resume-after", "0.3s"]),
        ("aborted", ["--abort-at", "25%"]),
    ):
        logs = d / name
        rc, text, err = _hrm(
            [
                "run",
                str(plan),
                "--sim",
                "--config",
                str(config),
                "--log-dir",
                str(logs),
                "--speed",
                SPEED,
                "--json",
                *extra,
            ]
        )
        assert rc == 0, err
        summary = json.loads(text)
        out[name] = (summary, json.loads(Path(summary["run_record"]).read_text()))
    yield out
    mp.undo()


def _limits() -> tuple[np.ndarray, np.ndarray]:
    act = load_actuation(default_robot())
    return act.max_rate_counts_per_s * 0.01, act.max_accel_counts_per_s2 * 0.01**2


@pytest.mark.slow
def test_pause_then_resume_holds_on_the_path_within_the_limits(runs: dict[str, Any]) -> None:
    summary, record = runs["paused"]
    assert summary["outcome"] == "completed" and summary["causes"] == []
    sp = record["setpoints"]
    assert sp["pausable"] is True and sp["play_state"] == "done"
    actions = [a["action"] for a in record["run_control"]]
    assert actions == ["pause", "resume"]
    assert record["run_control"][0]["fraction"] >= 0.3
    log = read_run(summary["run_record"])
    tg = log.target[log.stream(-1)]
    tg = tg[np.isfinite(tg).all(axis=1)]
    # while paused the targets stand still: at least the paused time's cycles in a row
    same = np.all(np.diff(tg, axis=0) == 0, axis=1)
    longest = max((len(r) for r in "".join("1" if s else "0" for s in same).split("0")), default=0)
    # (cycles, not wall time: a loaded machine skips slots)
    assert sp["paused_s"] > 0 and longest >= round(sp["paused_s"] / 0.01) - 1
    assert record["run_control"][1]["fraction"] > record["run_control"][0]["fraction"]
    v, a = _limits()
    d1 = np.abs(np.diff(tg, axis=0))
    d2 = np.abs(np.diff(tg, 2, axis=0))
    assert (d1 <= v).all() and (d2 <= a).all()  # as the supervisor checked them
    assert np.array_equal(tg[-1], tg[-2])  # ends at rest


@pytest.mark.slow
def test_abort_stops_on_the_path_before_the_end(runs: dict[str, Any]) -> None:
    summary, record = runs["aborted"]
    assert summary["outcome"] == "aborted"
    assert record["setpoints"]["play_state"] == "aborted"
    assert record["setpoints"]["stopped_at_row"] < record["setpoints"]["rows"] - 1
    log = read_run(summary["run_record"])
    full = read_run(runs["paused"][0]["run_record"])
    end_full = full.target[full.stream(-1)][-1]
    tg = log.target[log.stream(-1)]
    tg = tg[np.isfinite(tg).all(axis=1)]
    assert np.array_equal(tg[-1], tg[-2])  # at rest
    assert not np.array_equal(tg[-1], end_full)  # not where the whole plan ends
    _v, a = _limits()
    assert (np.abs(np.diff(tg, 2, axis=0)) <= a).all()


def _count_syncs(path: str) -> int:
    n = 0
    with can.LogReader(path) as reader:
        for msg in reader:
            n += msg.arbitration_id == 0x080 and not msg.is_extended_id and len(msg.data) == 0
    return n


@pytest.mark.slow
def test_report_writes_figures_matching_the_can_log(
    runs: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    summary, record = runs["paused"]
    out = runs["dir"] / "report"
    rc, text, err = run_cli(["report", summary["run_record"], "--out", str(out), "--json"], capsys)
    assert rc == 0, err
    rep = json.loads(text)
    for name in ("angles.png", "tracking.png", "lateness.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert rep["cycles"] == _count_syncs(record["can_logs"][0])  # every SYNC of the log
    log = read_run(summary["run_record"])
    tg = log.target[log.stream(-1)]
    step = float(np.nanmax(np.abs(np.diff(tg, axis=0))))
    ac = log.actual[log.stream(-1)]
    fed = np.flatnonzero(np.isfinite(ac).all(axis=1))
    # measured follows planned: typically within one cycle's motion (the in-process box
    # lags more while the machine is loaded), never outside what was commanded, and at
    # rest where the last target put it
    assert rep["median_counts_error"] is not None and rep["median_counts_error"] <= step
    lo, hi = np.nanmin(tg, axis=0) - step, np.nanmax(tg, axis=0) + step
    assert ((ac[fed] >= lo) & (ac[fed] <= hi)).all()
    assert np.array_equal(ac[fed[-1]], tg[fed[-1]])
    # the figures' numbers are there (their size depends on how loaded the machine was)
    assert rep["max_angle_error_deg"] is not None and rep["max_tip_error_mm"] is not None
    # the simulated box's tension board was read while it ran: its samples, on the wire's
    # clock, fall within the run and are drawn
    assert summary["tension_file"] is not None and rep["tension_samples"] > 0


def test_report_bad_input_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "run-x.json"
    bad.write_text('{"format": "something/1"}')
    rc, out, err = run_cli(["report", str(bad), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert "not a run record" in err and str(bad) in err
    assert not (tmp_path / "o").exists()
    rc, _, err = run_cli(["report", "no-such-run", "--log-dir", str(tmp_path)], capsys)
    assert rc == 2 and "no such run record" in err


# -- bad input of ``hrm report`` on a small synthetic run of the default robot -------------

PDO = (0x200, 0x080, 0x180)  # RPDO1 base, SYNC, TPDO1 base


def _synthetic_run(folder: Path, cycles: int = 6, fmt: str = "blf") -> dict[str, Path]:
    """A run of the default robot as ``hrm run`` leaves it, without running it: the record
    (with the frames written to each log), one BLF (or ``fmt``) log per bus (every motor
    commanded and reporting 0 counts, one SYNC every 10 ms) and a tension file.
    ``hrm report`` reads it in well under a second."""
    import struct

    from hrm_ctrl.formats.runlog import tension_path, write_tension_csv

    motors = list(load_actuation(default_robot()).motor_ids)
    buses = {"can0": motors[:18], "can1": motors[18:]}
    folder.mkdir(parents=True, exist_ok=True)
    t0 = 1.7e9
    paths: dict[str, Path] = {}
    for bus, ids in buses.items():
        path = folder / f"run-s_{bus}.{fmt}"
        with can.Logger(str(path)) as w:
            for k in range(cycles):
                t = t0 + 0.01 * k
                frames = [(PDO[0] + n, struct.pack("<Hi", 15, 0)) for n in range(1, len(ids) + 1)]
                frames.append((PDO[1], b""))
                frames += [
                    (PDO[2] + n, struct.pack("<Hi", 0x1237, 0)) for n in range(1, len(ids) + 1)
                ]
                for i, (cid, data) in enumerate(frames):
                    w.on_message_received(
                        can.Message(timestamp=t + 1e-5 * i, arbitration_id=cid,
                                    is_extended_id=False, data=data)
                    )  # fmt: skip
        paths[bus] = path
    record = {
        "format": "hrm-run/1", "run": "run-s", "motor_ids": motors,
        "config": {"control": {"rate_hz": 100.0},
                   "buses": {b: {"nodes": {m: i + 1 for i, m in enumerate(ids)}}
                             for b, ids in buses.items()}},
        "can_logs": [str(paths[b]) for b in buses],
        "can_log_frames": [cycles * (2 * len(ids) + 1) for ids in buses.values()],
        "can_log_lost": [0, 0],
    }  # fmt: skip
    paths["record"] = folder / "run-s.json"
    paths["record"].write_text(json.dumps(record))
    paths["tension"] = write_tension_csv(
        tension_path(paths["record"]), [t0, t0 + 0.01], np.full((2, len(motors)), 30.0), motors
    )
    return paths


@pytest.fixture
def synthetic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    monkeypatch.setenv("HRM_CALIBRATIONS", str(tmp_path / "calibrations"))  # none
    return _synthetic_run(tmp_path / "runs")


def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_line_error(rc: int, out: str, err: str, name: str) -> None:
    assert rc == 2 and out == ""
    assert len(err.splitlines()) == 1 and err.startswith("hrm report: error: "), err
    assert name in err and "Traceback" not in err


def test_report_of_the_synthetic_run(
    synthetic: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    out = synthetic["record"].parent / "figs"
    rc, text, err = run_cli(["report", str(synthetic["record"]), "--out", str(out), "--json"],
                            capsys)  # fmt: skip
    assert rc == 0 and err == "", err
    rep = json.loads(text)
    assert rep["cycles"] == 6 and rep["max_counts_error"] == 0.0 and rep["tension_samples"] == 2
    assert sorted(p.name for p in out.iterdir()) == ["angles.png", "lateness.png", "tracking.png"]


def test_a_records_text_is_not_printed_raw(
    synthetic: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """A record whose run name holds a newline and an escape sequence, and whose calibration
    version is text of several lines: the report names the run by its file, the note on
    the calibration is one line with the version escaped."""
    rec = json.loads(synthetic["record"].read_text())
    rec["run"] = "x\n\x1b[31mred"
    rec["calibration"] = {"version": "\n\n\nxxx", "sha256": 5}
    synthetic["record"].write_text(json.dumps(rec))
    out = synthetic["record"].parent / "figs"
    rc, text, err = run_cli(["report", str(synthetic["record"]), "--out", str(out)], capsys)
    assert rc == 0, err
    assert "\x1b" not in text + err and text.startswith("run run-s: 6 cycles")
    (line,) = err.splitlines()
    assert "the run used calibration version '\\n\\n\\nxxx'" in line


@pytest.mark.parametrize(
    "target", ["record", "can0", "can1", "tension", "link-to-record", "file", "under-a-file",
               "sys"],
)  # fmt: skip
def test_report_out_refused_nothing_written(
    synthetic: dict[str, Path],
    target: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An --out naming one of the run's files, an existing file or a path that cannot be
    made: one line naming it, exit 2, no CAN log read, nothing written or replaced."""
    import hrm_ctrl.formats.runlog as runlog

    runs = synthetic["record"].parent
    other = runs / "notes.txt"
    other.write_text("mine")
    (runs / "link.json").symlink_to(synthetic["record"])
    out = {
        "record": synthetic["record"], "can0": synthetic["can0"], "can1": synthetic["can1"],
        "tension": synthetic["tension"], "link-to-record": runs / "link.json", "file": other,
        "under-a-file": other / "figs", "sys": Path("/sys/hrm-report-test/figs"),
    }[target]  # fmt: skip
    before = _files(runs)

    def no_log(*_a: Any, **_k: Any) -> None:
        raise AssertionError("a CAN log was read")

    if target != "sys":  # a path that cannot be made is found on writing, all else before
        monkeypatch.setattr(runlog, "read_run", no_log)
    if target not in ("can0", "can1", "sys"):  # refused before the record is read at all
        monkeypatch.setattr(runlog, "read_record", no_log)
    rc, text, err = run_cli(["report", str(synthetic["record"]), "--out", str(out)], capsys)
    assert not Path("/sys/hrm-report-test").exists()
    _one_line_error(rc, text, err, str(out))
    assert _files(runs) == before  # inputs untouched, no figure anywhere
    assert sorted(runs.iterdir()) == sorted({*before, runs / "link.json"})


def _nested(p: dict[str, Path]) -> Path:
    p["record"].write_text("[" * 100_000 + "]" * 100_000)
    return p["record"]


def _blf(bus: str, data: bytes | None) -> Any:
    def damage(p: dict[str, Path]) -> Path:
        raw = p[bus].read_bytes()
        if data is None:  # a byte changed in each compressed container's data
            b = bytearray(raw)
            for i in range(len(b) // 2, len(b), 97):
                b[i] ^= 0x5A
            raw = bytes(b)
        p[bus].write_bytes(raw if data is None else data)
        return p[bus]

    return damage


def _rate(value: str) -> Any:
    def damage(p: dict[str, Path]) -> Path:
        text = p["record"].read_text().replace('"rate_hz": 100.0', f'"rate_hz": {value}')
        assert value in text
        p["record"].write_text(text)
        return p["record"]

    return damage


def _motors(p: dict[str, Path]) -> Path:
    rec = json.loads(p["record"].read_text())
    rec["motor_ids"] += [f"x{i}" for i in range(2_000_000)]
    p["record"].write_text(json.dumps(rec))
    return p["record"]


def _node(p: dict[str, Path]) -> Path:
    rec = json.loads(p["record"].read_text())
    rec["config"]["buses"]["can1"]["nodes"]["j12r2"] = 1e300
    p["record"].write_text(json.dumps(rec))
    return p["record"]


def _counts(value: Any) -> Any:
    def damage(p: dict[str, Path]) -> Path:
        rec = json.loads(p["record"].read_text())
        rec["can_log_frames"] = value
        p["record"].write_text(json.dumps(rec))
        return p["record"]

    return damage


def _tension(cell: str) -> Any:
    def damage(p: dict[str, Path]) -> Path:
        lines = p["tension"].read_text().splitlines()
        lines[2] = cell + lines[2][lines[2].index(",") :]
        p["tension"].write_text("\n".join(lines) + "\n")
        return p["tension"]

    return damage


@pytest.mark.parametrize(
    "damage",
    [_nested, _blf("can0", b""), _blf("can1", bytes(range(256)) * 16), _blf("can0", None),
     _rate("NaN"), _rate("Infinity"), _rate("-Infinity"), _rate("-100"), _rate("0"),
     _rate("1e300"), _rate("true"), _motors, _node, _tension("nan"), _tension("1e999"),
     _counts("many"), _counts([222]), _counts([222, -1]), _counts([222, 1.5e300])],
    ids=["nested-record", "empty-blf", "random-blf", "damaged-blf", "rate-nan", "rate-inf",
         "rate-minus-inf", "rate-negative", "rate-zero", "rate-huge", "rate-bool",
         "two-million-motors", "node-id-huge", "tension-nan-time", "tension-inf-time",
         "counts-text", "counts-one-log", "counts-negative", "counts-float"],
)  # fmt: skip
def test_report_damaged_input_one_line(
    synthetic: dict[str, Path],
    damage: Any,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A damaged record, CAN log or tension file: one line naming it, exit 2, no figure."""
    bad = damage(synthetic)
    out = synthetic["record"].parent / "figs"
    rc, text, err = run_cli(["report", str(synthetic["record"]), "--out", str(out)], capsys)
    _one_line_error(rc, text, err, bad.name)
    assert not out.exists()
    assert not [r for r in caplog.records if r.name.startswith("can")]  # nothing logged either


# -- CAN logs that miss frames the run record counts -------------------------------------


def _cut_in_half(path: Path) -> None:
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])


def _lines_replaced(path: Path) -> None:
    """40 frame lines in the middle of a text log replaced by 3 lines of garbage (python-can's
    ASC reader skips what it cannot parse, without a word)."""
    lines = path.read_text().splitlines(keepends=True)
    n = len(lines) // 3
    lines[n : n + 40] = ["garbage line here 0x\n"] * 3
    path.write_text("".join(lines))


@pytest.mark.parametrize(
    ("fmt", "damage", "read"),
    [("blf", _cut_in_half, None), ("asc", _lines_replaced, 120 * 37 - 40)],
    ids=["cut-blf", "damaged-asc"],
)
def test_a_log_that_misses_frames_is_refused_and_partial_says_what_is_missing(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    fmt: str,
    damage: Any,
    read: int | None,
) -> None:
    monkeypatch.setenv("HRM_CALIBRATIONS", str(tmp_path / "calibrations"))
    run = _synthetic_run(tmp_path / "runs", cycles=120, fmt=fmt)  # 4,440 frames a bus
    damage(run["can1"])
    out = tmp_path / "figs"
    rc, text, err = run_cli(["report", str(run["record"]), "--out", str(out)], capsys)
    _one_line_error(rc, text, err, str(run["can1"]))
    assert "of the 4,440 frames the run record counts (the log is cut or damaged)" in err
    assert "--partial" in err and not out.exists()
    if read is not None:
        assert f"{read:,} of the 4,440" in err
    # --partial: the figures of what the logs hold, a warning line naming the log
    rc, text, err = run_cli(
        ["report", str(run["record"]), "--out", str(out), "--partial", "--json"], capsys
    )
    assert rc == 0, err
    (line,) = err.splitlines()
    assert line.startswith(f"hrm report: warning: {run['can1']}: ") and "4,440" in line
    rep = json.loads(text)
    assert rep["complete"] is False and len(rep["missing"]) == 1
    assert sorted(p.name for p in out.iterdir()) == ["angles.png", "lateness.png", "tracking.png"]


def _record_edit(path: Path, **changes: Any) -> None:
    rec = json.loads(path.read_text())
    for key, value in changes.items():
        if value is None:
            del rec[key]
        else:
            rec[key] = value
    path.write_text(json.dumps(rec))


def test_every_frame_there_is_complete_and_more_or_lost_frames_are_named(
    synthetic: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    record, out = synthetic["record"], synthetic["record"].parent / "figs"
    rc, text, err = run_cli(["report", str(record), "--out", str(out), "--json"], capsys)
    assert rc == 0 and err == "" and json.loads(text)["complete"] is True
    # more frames than the run wrote: not its log
    _record_edit(record, can_log_frames=[222, 100])
    rc, text, err = run_cli(["report", str(record), "--out", str(tmp := out / "x")], capsys)
    _one_line_error(rc, text, err, str(synthetic["can1"]))
    assert "222 frames, the run record counts 100 (not the log the run wrote)" in err
    assert not tmp.exists()
    # frames the session could not write: missing too
    _record_edit(record, can_log_frames=[222, 222], can_log_lost=[5, 0])
    rc, text, err = run_cli(["report", str(record), "--out", str(tmp)], capsys)
    _one_line_error(rc, text, err, str(synthetic["can0"]))
    assert "5 frame(s) never reached the log" in err
    # a record that keeps no counts: drawn, with a note that the logs are not checked
    _record_edit(record, can_log_frames=None, can_log_lost=None)
    rc, text, err = run_cli(["report", str(record), "--out", str(tmp), "--json"], capsys)
    assert rc == 0 and json.loads(text)["complete"] is None
    (line,) = err.splitlines()
    assert line.startswith("hrm report: note: ") and "a cut log cannot be told" in line
