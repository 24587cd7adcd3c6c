"""The console's commands on the in-process simulated box, driven by script lines as an
operator types them: connect, status, enable, jogs within and beyond the limits, a stop
while streaming, reset-fault after an injected drive fault, quit."""

from __future__ import annotations

import io
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.protocol.cia402 import State402, decode_state
from hrm_ctrl.cli._console.commands_session import close_session
from hrm_ctrl.cli._console.shell import run_console, run_script
from hrm_ctrl.cli._console.table import ConsoleError
from hrm_ctrl.errors import SignalInterrupt
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT

ENABLED = State402.OPERATION_ENABLED


def states(ctx: object) -> set[State402]:
    """The CiA 402 states of every simulated drive (the box's own view)."""
    return {State402(decode_state(sw)) for sw in ctx.sim.box.statuswords().values()}


def run(ctx: object, *lines: str) -> None:
    run_script(ctx, list(lines), "test")


def test_nothing_is_sent_before_connect_and_nothing_moves_before_enable(make_ctx) -> None:
    ctx = make_ctx()
    before = {m: d.position_counts for m, d in ctx.sim.box.drives.items()}
    with pytest.raises(ConsoleError, match=r"test:1: status: not connected"):
        run(ctx, "status")
    run(ctx, "connect")
    assert ctx.session.state.name == "READY"
    assert ENABLED not in states(ctx)
    with pytest.raises(ConsoleError, match=r"test:1: jog: the drives are not enabled"):
        run(ctx, "jog 5 theta +2")
    with pytest.raises(ConsoleError, match=r"home: the drives are not enabled"):
        run(ctx, "home")
    assert {m: d.position_counts for m, d in ctx.sim.box.drives.items()} == before
    assert ctx.session.results == []  # no stream was started


def test_status_shows_every_drive_and_bus(make_ctx) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable", "status")
    motors = ctx.actuation.motor_ids
    rows = [line for line in ctx.lines if line.split()[:1] and line.split()[0] in motors]
    assert [r.split()[0] for r in rows] == list(motors)
    first = rows[0].split()
    assert first[3:5] == ["OPERATIONAL", "OPERATION_ENABLED"]
    assert first[-1] == "-"  # no EMCY
    buses = [line for line in ctx.lines if line.startswith("bus ")]
    assert len(buses) == len(ctx.config.buses)
    assert all("load " in b and "error frames 0" in b for b in buses)
    st = ctx.session.status_snapshot()
    assert st.state == "ENABLED" and st.by_sdo
    assert all(n.following_error_counts == 0 for n in st.nodes)  # holding, not moving
    assert all(n.heartbeat_age_s is not None and n.heartbeat_age_s < 1.0 for n in st.nodes)


def test_home_where_the_arm_is_at_zero_moves_nothing_and_is_not_an_error(make_ctx) -> None:
    """A script's ``home`` on the straight arm (red-team: it was an error, exit 2 ended the
    script); after a jog it moves back."""
    ctx = make_ctx()
    run(ctx, "connect", "enable", "home")
    assert "at its zero configuration already" in ctx.lines[-1]
    assert ctx.session.results == []  # nothing streamed
    run(ctx, "jog 2 alpha +3", "home 50")
    assert ctx.lines[-1].startswith("home: done")
    assert int(np.abs(ctx.session.supervisor.targets).max()) <= 2


def test_joint_jog_within_the_limits_turns_the_joint(make_ctx) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable")
    held0 = ctx.session.supervisor.targets.copy()
    run(ctx, "jog 5 theta +2")
    held = ctx.session.supervisor.targets.copy()
    moved = np.flatnonzero(held != held0)
    # the ropes of joints 5..12 move (3 per joint), those of joints 1..4 do not
    assert set(ctx.actuation.joint_of_motor[moved]) == set(range(4, 12))
    st = ctx.session.status_snapshot()
    actual = np.array([n.position_counts for n in st.nodes])
    alpha, theta, _ = ctx.actuation.angles_from_counts(actual)
    assert math.degrees(theta[4]) == pytest.approx(2.0, abs=0.05)
    assert np.degrees(np.abs(np.delete(theta, 4))).max() < 0.05
    assert np.degrees(np.abs(alpha)).max() < 0.05
    assert "joint 5 theta 0.00 -> 2.00 deg" in ctx.lines[-1]


def test_motor_jog_moves_one_motor_by_its_counts(make_ctx) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable", "jog j05r1 -800")
    i = ctx.actuation.motor_ids.index("j05r1")
    held = ctx.session.supervisor.targets
    assert int(held[i]) == -800
    assert int(np.count_nonzero(held)) == 1
    assert ctx.sim.box.drives["j05r1"].position_counts == pytest.approx(-800, abs=5)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("jog 5 theta +12", r"larger than a jog's 10 deg"),
        ("jog 13 alpha 1", r"joint must be 1\.\.12"),
        ("jog 5 beta 1", r"axis 'beta': alpha or theta"),
        ("jog j05r1 9000", r"larger than a jog's 5000 counts"),
        ("jog j99r1 10", r"unknown rope motor"),
        # one rope paid out 2.3 mm alone: slack by the rope model (the simulated board
        # read 0.0 N and stopped the box when this was played)
        ("jog j01r0 -5000", r"rope j01r0: the rope model's tension [0-9.]+ N, below 10 N"),
        ("jog 5 theta", r"usage: jog MOTOR COUNTS|usage: jog JOINT"),
    ],
)
def test_jog_beyond_its_limits_is_refused_and_sends_nothing(make_ctx, line, message) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable")
    held = ctx.session.supervisor.targets.copy()
    with pytest.raises(ConsoleError, match=rf"^test:1: jog: .*{message}"):
        run(ctx, line)
    assert np.array_equal(ctx.session.supervisor.targets, held)
    assert ctx.session.results == []
    assert ctx.session.state.name == "ENABLED"


def test_jog_past_a_joint_limit_is_refused(make_ctx, tmp_path: Path) -> None:
    from importlib import resources

    text = resources.files("hrm_ctrl.data").joinpath("robot.toml").read_text()
    lines = text.splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip() == "[joint_limits]")
    for j in range(k + 1, len(lines)):
        if lines[j].startswith("["):
            break
        if "=" in lines[j] and not lines[j].lstrip().startswith("#"):
            key = lines[j].split("=")[0].strip()
            lines[j] = f"{key} = 3.0"
    robot = tmp_path / "robot.toml"
    robot.write_text("\n".join(lines) + "\n")
    ctx = make_ctx("--robot", str(robot))
    assert math.degrees(ctx.actuation.robot.limit_theta) == pytest.approx(3.0)
    run(ctx, "connect", "enable", "jog 5 theta +2")
    held = ctx.session.supervisor.targets.copy()
    with pytest.raises(ConsoleError, match=r"jog 5 theta \+2 deg: joint 5: theta .* outside "
                       r"the joint limit"):  # fmt: skip
        run(ctx, "jog 5 theta +2")
    assert np.array_equal(ctx.session.supervisor.targets, held)
    assert len(ctx.session.results) == 1  # only the first jog was streamed


@pytest.mark.slow  # ~11 s on the loaded 2-core machine (two homes planned)
def test_stop_while_streaming_quick_stops_and_the_console_goes_on(make_ctx) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable", "jog 3 alpha +2")

    def stop_once_streaming() -> None:  # as a progress display's `stop` would
        deadline = time.monotonic() + 30.0
        while ctx.session.supervisor.mode.name != "STREAMING" and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(0.3)
        ctx.stop_requested.set()

    timer = threading.Thread(target=stop_once_streaming)
    timer.start()
    t0 = time.monotonic()
    with pytest.raises(ConsoleError, match=r"home: stopped: .*stop requested"):
        run(ctx, "home 2")  # ~50 mm of tip travel at 2 mm/s: still moving at 0.3 s
    timer.join()
    assert time.monotonic() - t0 < 10.0
    assert ctx.session.state.name == "STOPPED"
    assert ENABLED not in states(ctx)  # quick stop active on every drive
    run(ctx, "reset-fault")
    assert ctx.session.state.name == "READY"
    assert "reset: no drive was in FAULT" in ctx.lines[-1]
    run(ctx, "enable", "jog 3 alpha -1")  # the console goes on: the next move plays
    assert ctx.session.results[-1].completed


@STALL_TOLERANT
def test_reset_fault_after_an_injected_drive_fault(make_ctx) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable", "sim fault drive-fault:j05r1")
    deadline = time.monotonic() + 5.0
    while ctx.session.state.name != "STOPPED" and time.monotonic() < deadline:
        time.sleep(0.01)
    assert ctx.session.state.name == "STOPPED"
    with pytest.raises(ConsoleError, match=r"jog: .*EMCY node 14: error code 0x8611"):
        run(ctx, "jog j05r1 100")
    with pytest.raises(ConsoleError, match=r"enable: session STOPPED after a stop"):
        run(ctx, "enable")
    n_lines = len(ctx.lines)
    run(ctx, "reset-fault")
    shown = ctx.lines[n_lines:]
    assert any(s.startswith("cause: j05r1") and "EMCY node 14: error code 0x8611" in s
               for s in shown), shown  # fmt: skip
    assert "reset: j05r1 (bus can0 node 14)" in shown[-1]
    assert ctx.session.state.name == "READY"
    assert State402.FAULT not in states(ctx)
    run(ctx, "enable", "jog j05r1 100")
    assert ctx.sim.box.drives["j05r1"].position_counts == pytest.approx(100, abs=5)


def test_quit_leaves_every_drive_disabled_and_writes_the_run_record(make_ctx) -> None:
    import json

    ctx = make_ctx()
    run(ctx, "connect", "enable", "jog j01r0 300", "quit", "jog j01r0 300")  # quit ends it
    assert ctx.quit_requested
    assert ENABLED in states(ctx)  # the script stopped at quit: the shell finishes next
    close_session(ctx)
    assert states(ctx) <= {State402.READY_TO_SWITCH_ON, State402.SWITCH_ON_DISABLED}
    record = json.loads(Path(ctx.last_run).read_text())
    assert record["session_state"] == "closed"
    assert len(record["streams"]) == 1
    assert record["console"] is True


def test_idle_stop_watch_view_and_a_second_connect(make_ctx) -> None:
    import urllib.request

    ctx = make_ctx()
    run(ctx, "connect", "stop")
    assert "nothing to stop: the drives are not enabled (session READY)" in ctx.lines[-1]
    run(ctx, "enable", "stop")
    assert ctx.session.state.name == "STOPPED"
    assert ENABLED not in states(ctx)
    run(ctx, "disable", "enable")  # no drive in FAULT: disable clears the stop
    assert ctx.session.state.name == "ENABLED"
    n = len(ctx.lines)
    run(ctx, "status watch 0.2 2")
    assert sum(line.startswith("session ENABLED") for line in ctx.lines[n:]) == 2
    with pytest.raises(ConsoleError, match="in a script, give the number of refreshes"):
        run(ctx, "status watch 0.5")
    run(ctx, "view")
    url = ctx.lines[-1].split()[1]
    with urllib.request.urlopen(url, timeout=10) as page:
        assert page.status == 200
    first = ctx.session
    run(ctx, "disconnect")
    assert ctx.session is None and ctx.extra.get("live_view") is None
    assert states(ctx) <= {State402.READY_TO_SWITCH_ON, State402.SWITCH_ON_DISABLED}
    assert Path(ctx.last_run).is_file()
    run(ctx, "connect")  # a new session, a second bring-up of the same box
    assert ctx.session is not first and ctx.session.state.name == "READY"
    with pytest.raises(ConsoleError, match="connect: connected already"):
        run(ctx, "connect")


def test_calibrate_show_and_history_read_the_console_store(make_ctx, tmp_path, capsys) -> None:
    ctx = make_ctx()
    with pytest.raises(ConsoleError, match=r"calibrate: .*calibrations: no active calibration"):
        run(ctx, "calibrate show")
    run(ctx, "calibrate history")
    assert f"{tmp_path / 'calibrations'}: no calibration yet" in capsys.readouterr().out
    with pytest.raises(ConsoleError, match=r"calibrate zero: enable the drives first"):
        run(ctx, "calibrate zero")
    with pytest.raises(ConsoleError, match=r"usage: calibrate show\|history"):
        run(ctx, "calibrate kinematic")
    assert ctx.session is None  # nothing was connected


def test_connect_refuses_a_box_another_master_operates(make_ctx, tmp_path) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable")  # this console operates the box
    import dataclasses

    from hrm_ctrl.cli._console.context import ConsoleContext

    lines: list[str] = []
    # another host on the same buses (not on this host's tension-board port)
    elsewhere = dataclasses.replace(ctx.config, tension=None)
    other = ConsoleContext(
        config=elsewhere,
        description=ctx.description,
        model=ctx.model,
        actuation=ctx.actuation,
        out=lines.append,
        err=lines.append,
        allow_uncalibrated=True,
        runs_dir=tmp_path / "other",
    )  # a second console on the same buses: a real box's listen time
    try:
        with pytest.raises(ConsoleError, match=r"connect: another master is active: bus"):
            run(other, "connect")
        assert other.session is None
    finally:
        close_session(other)
    assert ctx.session.state.name == "ENABLED", ctx.session.idle_causes  # not reset
    assert states(ctx) == {ENABLED}


@pytest.mark.parametrize("line", ["jog 5 theta 1e-300", "jog 5 alpha -1e-7"])
def test_a_jog_of_less_than_a_count_moves_nothing_and_says_so(make_ctx, line: str) -> None:
    """A jog that rounds to no encoder count on any rope (before: a ValueError traceback
    from the joint check of an empty table, ending the console)."""
    ctx = make_ctx()
    run(ctx, "connect", "enable")
    held = ctx.session.supervisor.targets.copy()
    run(ctx, line)
    assert np.array_equal(ctx.session.supervisor.targets, held)
    assert ctx.session.state.name == "ENABLED"
    assert "nothing to move" in ctx.lines[-1], ctx.lines[-1]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_jog_of_no_number_is_refused(make_ctx, value: str) -> None:
    ctx = make_ctx()
    run(ctx, "connect", "enable")
    with pytest.raises(ConsoleError, match=r"^test:1: jog: "):
        run(ctx, f"jog 5 theta {value}")
    assert ctx.session.results == [] and ctx.session.state.name == "ENABLED"


class SignalledScript(io.StringIO):
    """A script whose reading is cut by SIGTERM after its lines (the operator's shell
    sends it while the console holds the enabled drives)."""

    def readline(self, size: int | None = -1) -> str:
        line = super().readline(size)
        if not line:
            raise SignalInterrupt("SIGTERM", 15)
        return line


def test_a_signal_while_enabled_quick_stops_with_its_cause_then_disables(make_ctx) -> None:
    import json

    ctx = make_ctx()
    sim = ctx.sim.box  # the finish stops it
    with pytest.raises(SignalInterrupt):
        run_console(ctx, SignalledScript("connect\nenable\n"))
    assert {State402(decode_state(sw)) for sw in sim.statuswords().values()} <= {
        State402.READY_TO_SWITCH_ON,
        State402.SWITCH_ON_DISABLED,
    }
    record = json.loads(Path(ctx.last_run).read_text())
    causes = [(e["cause"], e["text"]) for e in record["events"] if e["kind"] == "stop_cause"]
    assert causes == [("signal", "SIGTERM: stop requested (console)")]
    kinds = [e["kind"] for e in record["events"]]
    assert kinds.index("quick_stop") < kinds.index("disable")


def test_a_move_longer_than_the_wait_before_it_starts_is_not_cut_short(
    make_ctx, monkeypatch
) -> None:
    """The console's wait for a stream's end counted from a source's length before the
    session had started it (0 cycles for a table source): every console move longer than
    the margins (40 s: a 46 s ``home 5`` in the docs) was quick-stopped as 'no end'.  With
    the margins cut to 0.5 s each, a home of about 1.5 s now plays to its end."""
    import drivers.session
    import hrm_ctrl.cli._console.streaming as streaming

    ctx = make_ctx()
    run(ctx, "connect", "enable", "jog 12 alpha +3")
    monkeypatch.setattr(drivers.session, "STREAM_TIMEOUT_MARGIN_S", 0.5)
    monkeypatch.setattr(streaming, "EXTRA_WAIT_S", 0.5)
    run(ctx, "home 5")
    assert ctx.lines[-1].startswith("home: done"), ctx.lines[-3:]
    cycles = int(ctx.lines[-1].split(" cycles")[0].split()[-1])
    assert cycles * ctx.config.control.period_s > 1.0  # longer than the old wait
