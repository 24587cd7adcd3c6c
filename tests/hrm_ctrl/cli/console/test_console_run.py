"""The console's ``run`` (pause / resume / abort from its script arguments), ``return``
and ``log`` (list, show, replay) on the in-process simulated box."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import can
import numpy as np
import pytest

from hrm_ctrl.cli._console.shell import run_script
from hrm_ctrl.cli._console.table import ConsoleError
from tests.hrm_ctrl.cli.cli_helpers import small_plan


def _relaxed_box(tmp_path: Path) -> Path:
    """The shipped box with watchdogs that bear a loaded test machine."""
    import drivers

    box = (Path(drivers.__file__).parent / "data" / "box.toml").read_text()
    box = box.replace("heartbeat_timeout_ms = 350", "heartbeat_timeout_ms = 2000")
    box = box.replace("missing_tpdo_cycles = 3 ", "missing_tpdo_cycles = 25 ")
    assert "heartbeat_timeout_ms = 2000" in box and "missing_tpdo_cycles = 25" in box
    p = tmp_path / "box.toml"
    p.write_text(box)
    return p


def run(ctx: object, *lines: str) -> None:
    run_script(ctx, list(lines), "test")


@pytest.fixture
def plan(tmp_path: Path) -> Path:
    p = tmp_path / "small.json"
    p.write_text(json.dumps(small_plan()))
    return p


def _positions(ctx: object) -> np.ndarray:
    return np.array([ctx.sim.box.drives[m].position_counts for m in ctx.actuation.motor_ids])


@pytest.mark.slow
def test_run_pause_resume_then_return_to_the_start(make_ctx, plan: Path, tmp_path: Path) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "enable")
    start = _positions(ctx)
    run(ctx, f"run {plan} --speed 10 --pause-at 30% --resume-after 0.3s")
    done = [x for x in ctx.lines if x.startswith(f"run {plan}: done")]
    assert done and "paused" in done[0] and "paused 0.00 s" not in done[0]
    figs = [x for x in ctx.lines if x.startswith("figures: ")]
    assert figs
    folder = Path(figs[0].split()[1])
    assert {p.name for p in folder.glob("*.png")} == {"angles.png", "tracking.png", "lateness.png"}
    moved = _positions(ctx)
    assert np.abs(moved - start).max() > 1000  # the plan moved the ropes
    run(ctx, "return")
    assert any(x.startswith("return: back at the start") for x in ctx.lines)
    back = _positions(ctx)
    # the drives' own positions: where the run started, within the following error of
    # a position loop at rest (none for the simulated drive: exactly)
    assert np.array_equal(back, start)
    with pytest.raises(ConsoleError, match="no run to return from"):
        run(ctx, "return")


@pytest.mark.slow
def test_run_abort_stops_on_the_path_and_log_lists_it(make_ctx, plan: Path, tmp_path: Path) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "enable", f"run {plan} --speed 10 --abort-at 20% --no-figures")
    aborted = [x for x in ctx.lines if "aborted by the operator: stopped on the path" in x]
    assert aborted and "plan step" in aborted[0]
    run(ctx, "disconnect", "log")
    rows = [x for x in ctx.lines if x.strip().startswith("1 ")]
    assert rows and "small.json" in rows[0] and "aborted" in rows[0]
    run(ctx, "log show 1")
    assert any(x.startswith("play: aborted") for x in ctx.lines)
    with pytest.raises(ConsoleError, match="run 9: the log lists 1 run"):
        run(ctx, "log show 9")


def _frames(path: str) -> list[tuple[int, bytes]]:
    with can.LogReader(path) as reader:
        return [(m.arbitration_id, bytes(m.data)) for m in reader if not m.is_error_frame]


@pytest.mark.slow
def test_log_replay_sends_the_logged_frames_in_order(make_ctx, tmp_path: Path) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "disconnect")  # a short session: bring-up traffic only
    record = json.loads(Path(ctx.last_run).read_text())
    got: dict[str, list[tuple[int, bytes]]] = {"can0": [], "can1": []}
    buses = {name: can.Bus(interface="virtual", channel=f"h7-replay-test-{name}") for name in got}
    stop = threading.Event()

    def listen(name: str) -> None:
        while not stop.is_set():
            m = buses[name].recv(0.05)
            if m is not None:
                got[name].append((m.arbitration_id, bytes(m.data)))

    threads = [threading.Thread(target=listen, args=(n,), daemon=True) for n in got]
    for t in threads:
        t.start()
    try:
        run(ctx, "log replay 1 --bus can0=virtual:h7-replay-test-can0 "
                 "--bus can1=virtual:h7-replay-test-can1")  # fmt: skip
    finally:
        import time

        time.sleep(0.3)
        stop.set()
        for t in threads:
            t.join(2.0)
        for b in buses.values():
            b.shutdown()
    for name, logged in zip(("can0", "can1"), record["can_logs"], strict=True):
        want = _frames(logged)
        assert len(want) > 100  # NMT, SDO configuration, heartbeats
        assert got[name] == want  # the same frames, in the same order
    assert any(x.startswith("replayed ") and "can0" in x for x in ctx.lines)


def test_log_replay_refuses_the_live_sessions_bus(make_ctx, tmp_path: Path) -> None:
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "disconnect", "connect")
    bus0 = ctx.config.buses[0]
    with pytest.raises(ConsoleError, match="a bus of this console's box"):
        run(ctx, f"log replay 1 --bus {bus0.name}={bus0.interface}:{bus0.channel}")
    run(ctx, "disconnect")  # its drives are still on the bus: a replay would bring them up
    with pytest.raises(ConsoleError, match="a bus of this console's box"):
        run(ctx, f"log replay 1 --bus {bus0.name}={bus0.interface}:{bus0.channel}")
    with pytest.raises(ConsoleError, match="the run has no bus 'nope'"):
        run(ctx, "log replay 1 --bus nope=virtual:x")


def test_check_reports_each_limit_and_refuses_a_broken_plan(make_ctx, plan: Path) -> None:
    ctx = make_ctx()
    run(ctx, f"check {plan} 20")  # needs no session
    text = "\n".join(ctx.lines)
    for what in ("joint limits: ok", "rope travel: ok", "motor speed: ok",
                 "motor acceleration: ok", "clearance: no environment"):  # fmt: skip
        assert what in text
    assert ctx.lines[-1] == f"{plan}: ok to run at up to 20 mm/s"
    bad = json.loads(plan.read_text())
    bad["steps"][-1]["alpha_rad"] = [1.2] * 12  # 68.8 deg: beyond the 60 deg limit
    broken = plan.with_name("broken.json")
    broken.write_text(json.dumps(bad))
    with pytest.raises(ConsoleError, match=r"broken.json: \d problem\(s\)"):
        run(ctx, f"check {broken}")
    assert any(x.startswith("joint limits: BROKEN") for x in ctx.lines)
    with pytest.raises(ConsoleError, match="SPEED_MM_S must be > 0"):
        run(ctx, f"check {plan} -3")


@pytest.mark.slow
def test_plan_is_hrm_plan(make_ctx, tmp_path: Path) -> None:
    ctx = make_ctx()
    out = tmp_path / "p.json"
    run(ctx, f"plan --scenario bent-pipe --out {out}")
    assert json.loads(out.read_text())["format"] == "hrm-plan/1"
    assert ctx.lines  # the plan's report
    with pytest.raises(ConsoleError, match=r"plan: .*--scenario"):
        run(ctx, "plan --scenario")


def test_log_replay_refuses_a_hostile_log_before_opening_a_bus(make_ctx, tmp_path: Path) -> None:
    """A BLF python-can would read for ever (an inner object of size 0): one line naming
    it, before any bus is opened or frame sent."""
    import struct

    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "disconnect")
    log = Path(json.loads(Path(ctx.last_run).read_text())["can_logs"][1])
    raw = log.read_bytes()
    header_size = struct.unpack_from("<4sL", raw)[1]
    inner = struct.pack("<4sHHLL", b"LOBJ", 32, 1, 0, 1) + bytes(64)
    body = struct.pack("<H6xL4x", 0, len(inner)) + inner  # stored, not compressed
    obj = struct.pack("<4sHHLL", b"LOBJ", 16, 1, 16 + len(body), 10) + body
    log.write_bytes(raw[:header_size] + obj + raw[header_size:])
    with pytest.raises(ConsoleError, match=rf"{log.name}: CAN log: .* a frame of 0 bytes"):
        run(ctx, "log replay 1 --bus can0=virtual:h7-hostile-0 --bus can1=virtual:h7-hostile-1")


@pytest.mark.parametrize(
    "damage",
    [
        {"streams": {"a": 1}},
        {"streams": 5},
        {"streams": [1, 2]},
        {"streams": [{"stats": None, "cycles": "x"}]},
        {"streams": [{"stats": {"jitter_p99_s": "x", "late_cycles": [1]}}]},
        {"can_log_frames": 5, "idle_stop_causes": "x"},
        {"streams": [{"causes": 7}], "console_runs": [{"pausable": True}], "written_utc": 3},
    ],
)
def test_log_lists_and_shows_a_damaged_record_without_raising(
    make_ctx, tmp_path: Path, damage: dict
) -> None:
    """A run record whose optional parts have the wrong types (the red team found six
    tracebacks in ``log show`` and one in ``log``): both print, nothing raises."""
    ctx = make_ctx()
    ctx.runs_dir.mkdir(parents=True, exist_ok=True)
    rec = {"format": "hrm-run/1", "run": "r", "motor_ids": ["m"], "config": {},
           "can_logs": [], **damage}  # fmt: skip
    (ctx.runs_dir / "r.json").write_text(json.dumps(rec))
    run(ctx, "log", "log show 1", "log show r")
    assert any(line.startswith("  1  ") for line in ctx.lines)
    assert sum(line.startswith("run r  (") for line in ctx.lines) == 2
    with pytest.raises(ConsoleError, match="no such run"):
        run(ctx, "log show " + "x" * 3000)  # a file name too long for the file system


def test_log_replay_refuses_a_cut_log(make_ctx, tmp_path: Path) -> None:
    """A log cut short (python-can reads its first half without a word) is refused before
    any bus opens, and not replayed: where the cut falls in a BLF container's or object's
    header (the log's length depends on the run's timing), that header is named; else its
    frames are counted against the record's."""
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "disconnect")
    log = Path(json.loads(Path(ctx.last_run).read_text())["can_logs"][0])
    raw = log.read_bytes()
    log.write_bytes(raw[: len(raw) // 2 + 7])
    cut = r"CAN log: BLF (container|object) at byte \d+ cut short"
    with pytest.raises(
        ConsoleError, match=rf"{log.name}: (\d+ frames, the run record says \d+|{cut})"
    ):
        run(ctx, "log replay 1 --bus can0=virtual:h7-cut-0 --bus can1=virtual:h7-cut-1")
    assert not any(line.startswith("replayed ") for line in ctx.lines)


def test_ctrl_c_during_status_watch_ends_a_script(make_ctx, monkeypatch) -> None:
    """In a script, Ctrl-C during ``status watch`` ends the script like Ctrl-C anywhere
    else (it was swallowed, and the script's next moves still ran); at the prompt it
    only ends the watch."""
    from hrm_ctrl.cli._console import commands_session

    ctx = make_ctx()
    run(ctx, "connect")

    def interrupted(_s: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(commands_session.time, "sleep", interrupted)
    with pytest.raises(ConsoleError, match=r"t:1: interrupted \(Ctrl-C\)"):
        run_script(ctx, ["status watch 1 5", "help"], "t")
    assert "> help" not in ctx.lines
    ctx.interactive = True
    run_script(ctx, ["status watch 1 5", "help"], "t")  # the prompt's way: the watch ends
    assert "> help" in ctx.lines


def test_a_stopped_run_is_kept_in_the_run_record(make_ctx, plan: Path, tmp_path: Path) -> None:
    """A console ``run`` that a stop ends (here the operator's, as a signal or a fault
    would): the session's run record still keeps it in ``console_runs``, with where it
    stopped (it was noted only after a normal end)."""
    ctx = make_ctx("--config", str(_relaxed_box(tmp_path)))
    run(ctx, "connect", "enable")
    timer = threading.Timer(1.0, ctx.stop_requested.set)
    timer.start()
    try:
        with pytest.raises(ConsoleError, match="stop requested"):
            run(ctx, f"run {plan} --speed 10 --no-figures")
    finally:
        timer.cancel()
    (noted,) = ctx.session.record_extra["console_runs"]
    assert noted["plan"] == str(plan) and noted["where"]


def test_a_script_pause_with_nothing_to_resume_it_is_refused(make_ctx, plan: Path) -> None:
    """In a script the input may end in the middle of a run: a ``--pause-at`` without
    ``--resume-after`` would leave the run paused with nothing to resume it (until the
    longest pause aborts it, 600 s later).  Refused before anything moves."""
    ctx = make_ctx()
    run(ctx, "connect", "enable")
    before = _positions(ctx)
    with pytest.raises(ConsoleError, match="--pause-at without --resume-after in a script"):
        run(ctx, f"run {plan} --pause-at 30%")
    assert np.array_equal(_positions(ctx), before)
    assert not any(x.startswith("run: moving") for x in ctx.lines)
