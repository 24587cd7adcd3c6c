"""Console conventions (issue 11): ``hrm --version``, help text on every option, one
metavar spelling per unit, one default tip speed, and ``--bus`` / ``--log-format`` end to
end on the simulated box."""

from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict
from collections.abc import Iterator
from importlib.metadata import version
from pathlib import Path

import can
import pytest

from hrm_ctrl.cli import build_parser
from hrm_ctrl.formats.planfile import write_plan
from hrm_ctrl.ropes.setpoints import DEFAULT_TIP_SPEED_MM_PER_S
from tests.hrm_ctrl.cli.cli_helpers import run_cli, small_plan


def options(
    parser: argparse.ArgumentParser, prog: str = "hrm"
) -> Iterator[tuple[str, argparse.Action]]:
    """(command, action) of every argument of every command and sub-command."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from options(sub, f"{prog} {name}")
        elif not isinstance(action, argparse._HelpAction):
            yield prog, action


def name(action: argparse.Action) -> str:
    return "/".join(action.option_strings) or action.dest


def test_version_is_the_installed_packages(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run_cli(["--version"], capsys)
    assert rc == 0 and err == ""
    assert out == f"hrm {version('hrm')}\n"


def test_every_option_of_every_command_has_help_text() -> None:
    missing = [
        f"{prog} {name(a)}" for prog, a in options(build_parser(every_command=True)) if not a.help
    ]
    assert missing == []
    assert (
        len(list(options(build_parser(every_command=True)))) > 100
    )  # the walk reached every sub-command


# What a value's unit is spelt as, wherever it appears.
UNIT_METAVARS = {
    "mm": "MM",
    "mm/s": "MM_S",
    "s": "S",
    "Hz": "HZ",
    "N": "NEWTON",  # a tension (--target-N); a plain count is "N"
    "counts": "COUNTS",
}
# Options that take a file of one kind: one spelling each.
FILE_METAVARS = {"config": "BOX.toml", "truth": "TRUTH.toml", "write_truth": "TRUTH.toml"}


def test_one_metavar_spelling_per_unit() -> None:
    spellings: dict[str, set[str]] = defaultdict(set)
    types: dict[str, set[str]] = defaultdict(set)
    for prog, a in options(build_parser(every_command=True)):
        if a.metavar is None or not isinstance(a.metavar, str):
            continue
        kind = getattr(a.type, "__name__", str(a.type))
        types[a.metavar].add(kind)
        # the unit a help text gives its default in: "(default 5 mm)", "(default 0.2 N)"
        m = re.search(r"\(default [-+0-9.e]+ ([A-Za-z/]+)", a.help or "")
        if m is not None and m.group(1) in UNIT_METAVARS:
            spellings[m.group(1)].add(a.metavar)
        if a.dest.endswith("_N"):
            spellings["N"].add(a.metavar)
        if a.dest == "speed":
            spellings["mm/s"].add(a.metavar)
        if a.dest in FILE_METAVARS:
            assert a.metavar == FILE_METAVARS[a.dest], f"{prog} {name(a)}: {a.metavar}"
    assert {u: s for u, s in spellings.items() if s != {UNIT_METAVARS[u]}} == {}
    assert set(spellings) >= {"mm", "mm/s", "N"}  # the help texts were read
    for metavar in ("MM", "MM_S", "S", "HZ", "NEWTON"):  # never a count of things
        assert "int" not in types[metavar], (metavar, types[metavar])
    assert types["N"] == {"int"}  # counts of things only
    assert not set(types) & {"MM_PER_S", "K", "SECONDS", "MMPS", "FILE.toml"}


def test_one_default_tip_speed_for_ropes_run_and_demo() -> None:
    parser = build_parser(every_command=True)
    speeds = {
        cmd: parser.parse_args(argv).speed
        for cmd, argv in {
            "ropes": ["ropes", "p.json"],
            "run": ["run", "p.json"],
            "demo": ["demo"],
        }.items()
    }
    assert speeds == dict.fromkeys(("ropes", "run", "demo"), DEFAULT_TIP_SPEED_MM_PER_S)
    speed_options = [a for prog, a in options(parser) if a.dest == "speed"]
    assert len(speed_options) >= 3  # ropes, run, demo, and any other command playing a plan
    assert {a.default for a in speed_options} == {DEFAULT_TIP_SPEED_MM_PER_S}
    for a in speed_options:
        assert f"(default {DEFAULT_TIP_SPEED_MM_PER_S:g} mm/s" in (a.help or ""), a.help


@pytest.fixture
def plan(tmp_path: Path) -> Path:
    path = tmp_path / "plan.json"
    write_plan(path, small_plan())
    return path


def test_run_sim_with_a_bus_override_and_asc_logs(
    tmp_path: Path, plan: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--bus can1=...@800000``: the run's bus budget counts can1 at 800 kbit/s (the
    simulated box replaces the interface, not the bitrate); ``--log-format asc`` writes
    ASC logs that python-can reads back as channel 0 (can0) and 1 (can1)."""
    logs = tmp_path / "runs"
    argv = ["run", str(plan), "--sim", "--log-dir", str(logs), "--json"]
    argv += ["--bus", "can1=socketcan:vcan7@800000", "--log-format", "asc"]
    rc, out, err = run_cli(argv, capsys)
    assert rc == 0, err
    summary = json.loads(out)
    assert summary["completed"] is True and summary["can_log_errors"] == []
    record = json.loads(Path(summary["run_record"]).read_text())
    assert [b["bitrate"] for b in record["bus_loads"]] == [1_000_000, 800_000]
    assert record["bus_loads"][1]["load"] == pytest.approx(
        record["bus_loads"][0]["load"] * 1.25, rel=1e-9
    )
    paths = [Path(p) for p in summary["can_logs"]]
    assert [p.name.rsplit("_", 1)[1] for p in paths] == ["can0.asc", "can1.asc"]
    for bus, path in enumerate(paths):
        back = list(can.LogReader(path))
        assert any(m.arbitration_id == 0x80 for m in back)  # SYNC
        assert {m.channel for m in back} == {bus}


def test_run_bus_override_over_the_load_budget_is_refused_before_any_frame(
    tmp_path: Path, plan: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "runs"
    argv = ["run", str(plan), "--sim", "--log-dir", str(logs), "--bus", "can0=virtual:x@500000"]
    rc, out, err = run_cli(argv, capsys)
    lines = [x for x in err.splitlines() if ": error: " in x]
    assert rc == 2 and out == "" and len(lines) == 1, err
    assert "bus can0: worst-case load" in lines[0] and "at 500000 bit/s" in lines[0]
    assert not list(logs.glob("*")) if logs.exists() else True  # no log, no run record


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--log-format", "csv"], "argument --log-format: invalid choice: 'csv'"),
        (["--bus", "can0=virtual"], "argument --bus: 'can0=virtual': expected NAME=INTERFACE"),
        (["--bus", "can0=virtual:x@9"], None),  # parses; the load check refuses it
    ],
)
def test_bad_log_format_or_bus_is_one_line_exit_2(
    tmp_path: Path,
    plan: Path,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    expected: str | None,
) -> None:
    logs = tmp_path / "runs"
    rc, out, err = run_cli(["run", str(plan), "--sim", "--log-dir", str(logs), *argv], capsys)
    assert rc == 2 and out == ""
    if expected is not None:
        assert err.count("\n") == 1 and expected in err, err
    assert not logs.exists() or not list(logs.iterdir())


@pytest.mark.parametrize(
    ("argv", "in_process_box"),
    [
        (["run", "plan.json", "--sim", "--wire", "virtual"], True),
        (["run", "plan.json", "--sim"], False),  # the box in its own process (hrm_ipc)
        (["calibrate", "kinematic", "--collect", "5", "--sim"], False),
        (["demo"], False),  # the box in its own process (hrm_ipc)
        (["demo", "--wire", "virtual"], True),
        (["status", "--sim"], False),
        (["console", "--sim", "--wire", "hrm_sim"], True),
        (["run", "plan.json"], False),
        (["sim", "--config", "box.toml"], False),  # the box in its own process
        (["plan", "--scenario", "bent-pipe"], False),
    ],
)
def test_the_switch_interval_is_the_longer_one_only_with_the_box_in_this_interpreter(
    argv: list[str], in_process_box: bool
) -> None:
    from drivers.realtime import SWITCH_INTERVAL_S
    from hrm_ctrl.cli import _switch_interval_s, build_parser
    from hrm_ctrl.cli._simwire import SIM_SWITCH_INTERVAL_S

    args = build_parser().parse_args(argv)
    want = SIM_SWITCH_INTERVAL_S if in_process_box else SWITCH_INTERVAL_S
    assert _switch_interval_s(args) == want and SIM_SWITCH_INTERVAL_S > SWITCH_INTERVAL_S


def test_a_librarys_log_records_do_not_reach_stderr() -> None:
    """canopen logs every aborted SDO transfer at ERROR; without a handler, logging's
    last resort printed 36 such lines beside the console's one error line when a bus went
    off.  After a command has run, they are not printed (hrm's own line says what failed)."""
    import subprocess
    import sys

    code = (
        "import logging\n"
        "from hrm_ctrl.cli import main\n"
        "rc = main(['busload'])\n"
        "logging.getLogger('canopen.sdo.client').error('Transfer aborted by client')\n"
        "logging.getLogger('hrm.other').error('still shown')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "Transfer aborted" not in res.stderr and "still shown" in res.stderr
