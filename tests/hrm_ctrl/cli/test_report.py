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
