"""Bad input, tried from outside (issue 9, items 13 and 14).

Every case is one ``hrm CMD: error: ...`` line on stderr and exit status 2, never a
traceback, and nothing is written: no output file appears, no input changes.  A closed
stdout (``hrm ... | head``) ends a command quietly with status 141.

The classes: an output naming an input (by path, symbolic link, hard link, another
spelling; a file a directory output would be written with), integers too large for a
float (JSON plans, TOML descriptions), nesting too deep for a parser, inputs that would
size a huge allocation (plan steps, playback rows, path points, file sizes, durations,
motor counts beyond the drives' 32 bits) and a closed stdout.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from drivers import default_box_path
from hrm_ctrl.cli import EXIT_CLOSED_PIPE, main
from hrm_ctrl.formats.planfile import write_plan
from tests.hrm_ctrl.cli.cli_helpers import small_plan

ROOT = Path(__file__).resolve().parents[3]
SHIPPED_ROBOT = ROOT / "hrm_ctrl" / "data" / "robot.toml"
ROBOT_TEXT = SHIPPED_ROBOT.read_text()
BOX_TEXT = default_box_path().read_text()
VIRTUAL_BOX_TEXT = BOX_TEXT.replace('interface = "socketcan"', 'interface = "virtual"')
PATH_CSV = "x,y,z\n1200,100,300\n1300,100,300\n1400,100,300\n"
FAST = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def snapshot(root: Path) -> dict[str, tuple[bool, bytes | str]]:
    """Every entry under ``root``: a link's target, a file's bytes (nothing followed)."""
    found: dict[str, tuple[bool, bytes | str]] = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink():
            found[str(p)] = (True, os.readlink(p))
        elif p.is_file():
            found[str(p)] = (False, p.read_bytes())
        else:
            found[str(p)] = (False, "dir")
    return found


def one_error(capsys: pytest.CaptureFixture, command: str, rc: int) -> str:
    """The one stderr line of a refused command (exit 2, no traceback, nothing on stdout)."""
    out, err = capsys.readouterr()
    assert rc == 2, (out, err)
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"hrm {command}: error: "), err
    assert out == "", out
    return lines[0]


def refused(capsys: pytest.CaptureFixture, root: Path, argv: list[str], *wanted: str) -> str:
    """Run ``hrm argv``: one error line holding every ``wanted`` text, and nothing under
    ``root`` written, changed or removed."""
    before = snapshot(root)
    line = one_error(capsys, argv[0], main(argv))
    for text in wanted:
        assert text in line, line
    assert snapshot(root) == before
    return line


# ---- 13. an output never overwrites an input ---------------------------------------------


def alias(path: Path, how: str) -> Path:
    """Another name for the file ``path``: itself, a symbolic or hard link, a spelling."""
    if how == "same":
        return path
    if how == "symlink":
        link = path.with_name(f"symlink-{path.name}")
        link.symlink_to(path.name)
        return link
    if how == "hardlink":
        link = path.with_name(f"hardlink-{path.name}")
        os.link(path, link)
        return link
    assert how == "spelled"
    (path.parent / "sub").mkdir(exist_ok=True)
    return path.parent / "sub" / ".." / "." / path.name


def _inputs(tmp: Path) -> dict[str, Path]:
    files = {
        "plan": tmp / "plan.json",
        "path": tmp / "path.csv",
        "robot": tmp / "robot.toml",
        "box": tmp / "box.toml",
    }
    write_plan(files["plan"], small_plan())
    files["path"].write_text(PATH_CSV)
    files["robot"].write_text(ROBOT_TEXT)
    files["box"].write_text(VIRTUAL_BOX_TEXT)
    return files


# (command line given the inputs and the output path, the input the output names)
OVERWRITES: dict[str, tuple[Callable[[dict[str, Path], Path], list[str]], str, str]] = {
    "plan --out PATH": (
        lambda f, o: ["plan", "--path", str(f["path"]), "--out", str(o)],
        "path",
        "path file",
    ),
    "plan --out ROBOT": (
        lambda f, o: [
            "plan",
            "--path",
            str(f["path"]),
            "--robot",
            str(f["robot"]),
            "--out",
            str(o),
        ],
        "robot",
        "robot description",
    ),
    "ropes --out PLAN": (
        lambda f, o: ["ropes", str(f["plan"]), "--out", str(o)],
        "plan",
        "plan file",
    ),
    "ropes --out BOX": (
        lambda f, o: ["ropes", str(f["plan"]), "--config", str(f["box"]), "--out", str(o)],
        "box",
        "bus configuration",
    ),
    "urdf --out ROBOT": (
        lambda f, o: ["urdf", "--robot", str(f["robot"]), "--out", str(o)],
        "robot",
        "robot description",
    ),
    "run --log-dir PLAN": (
        lambda f, o: [
            "run",
            str(f["plan"]),
            "--sim",
            "--config",
            str(f["box"]),
            "--log-dir",
            str(o),
        ],
        "plan",
        "plan file",
    ),
    "run --log-dir BOX": (
        lambda f, o: [
            "run",
            "--hold",
            "1",
            "--sim",
            "--config",
            str(f["box"]),
            "--log-dir",
            str(o),
        ],
        "box",
        "bus configuration",
    ),
}


@pytest.mark.parametrize("how", ["same", "symlink", "hardlink", "spelled"])
@pytest.mark.parametrize("case", sorted(OVERWRITES))
def test_an_output_naming_an_input_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture, case: str, how: str
) -> None:
    build, key, what = OVERWRITES[case]
    files = _inputs(tmp_path)
    out = alias(files[key], how)
    argv = build(files, out)
    line = refused(capsys, tmp_path, argv, f"would overwrite the {what} being read")
    assert str(out) in line and str(files[key]) in line
    assert line.endswith(": the same file") == (how in ("symlink", "hardlink"))


def test_the_refusal_comes_before_any_input_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    plan = tmp_path / "plan.json"
    plan.write_text("{not json")  # reading it first would give another error
    refused(capsys, tmp_path, ["ropes", str(plan), "--out", str(plan)], "would overwrite")


@pytest.mark.parametrize(
    ("argv", "member", "what"),
    [
        (lambda d, f: ["plan", "--scenario", "bent-pipe", "--robot", str(f), "--plot", str(d)],
         "arm.png", "robot description"),
        (lambda d, f: ["demo", "--config", str(f), "--out", str(d)], "demo.json",
         "bus configuration"),
        (lambda d, f: ["demo", "--config", str(f), "--out", str(d)], "figures/angles.png",
         "bus configuration"),
        (lambda d, f: ["demo", "--robot", str(f), "--out", str(d)], "plan.json",
         "robot description"),
    ],
    ids=["plan-plot", "demo-summary", "demo-figure", "demo-plan"],
)  # fmt: skip
def test_a_file_a_directory_output_would_write_is_no_input(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: Any, member: str, what: str
) -> None:
    out_dir = tmp_path / "out"
    target = out_dir / member
    target.parent.mkdir(parents=True)
    source = tmp_path / "input.toml"
    source.write_text(ROBOT_TEXT if "robot" in what else VIRTUAL_BOX_TEXT)
    os.link(source, target)  # the file the command would write is the input
    command = argv(out_dir, source)
    line = refused(capsys, tmp_path, command, f"the {what} being read")
    option = "--plot" if command[0] == "plan" else "--out"
    assert f"{option} {out_dir}: {target} would overwrite" in line


def test_the_shipped_files_read_by_default_are_inputs_too(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # Through a symbolic link: a replace would replace the link, never the shipped file.
    link = tmp_path / "robot-link.toml"
    link.symlink_to(SHIPPED_ROBOT)
    refused(capsys, tmp_path, ["urdf", "--out", str(link)], "robot description being read")
    box = tmp_path / "box-link.toml"
    box.symlink_to(default_box_path())
    refused(capsys, tmp_path, ["ropes", "p.json", "--out", str(box)], "bus configuration")
    assert SHIPPED_ROBOT.read_text() == ROBOT_TEXT


_SEGMENTS = st.sampled_from([".", "sub/..", "sub/./..", "sub/sub2/../.."])


@FAST
@given(prefix=st.lists(_SEGMENTS, max_size=4), relative=st.booleans())
@example(prefix=["sub/.."], relative=True)
def test_any_spelling_of_the_input_is_the_input(prefix: list[str], relative: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "sub" / "sub2").mkdir(parents=True)
        files = _inputs(tmp)
        spelled = Path(*prefix, "plan.json") if prefix else Path("plan.json")
        out = spelled if relative else tmp / spelled
        here = os.getcwd()
        os.chdir(tmp)
        try:
            before = snapshot(tmp)
            line = _one_error_run(["ropes", str(files["plan"]), "--out", str(out)])
            assert f"--out {out} would overwrite the plan file being read" in line
            assert snapshot(tmp) == before
        finally:
            os.chdir(here)


# ---- 14. numbers: integers too large for a float -----------------------------------------


def digits(lead: int, n: int, negative: bool) -> str:
    return ("-" if negative else "") + str(lead) + "7" * (n - 1)


BIG_INTS = st.builds(digits, st.integers(1, 9), st.integers(310, 6000), st.booleans())
WIDE_INTS = st.builds(digits, st.integers(1, 9), st.integers(20, 6000), st.booleans())


@FAST
@given(number=BIG_INTS, place=st.sampled_from(["travel", "links", "report", "limit"]))
@example(number="9" * 400, place="travel")
@example(number="1" + "0" * 5000, place="links")
def test_a_json_integer_too_large_for_a_float_is_one_line(number: str, place: str) -> None:
    plan = small_plan()
    marker = 12345.678
    if place == "travel":
        plan["steps"][1]["travel_mm"] = marker
    elif place == "links":
        plan["robot"]["links_mm"][3] = marker
    elif place == "report":
        plan["report"]["n"] = marker
    else:
        plan["robot"]["joint_limits_deg"] = {"alpha": marker, "theta": 60.0}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        path = tmp / "plan.json"
        path.write_text(json.dumps(plan).replace(str(marker), number))
        out = tmp / "setpoints.csv"
        for argv in (
            ["ropes", str(path), "--out", str(out)],
            ["run", str(path), "--sim", "--log-dir", str(tmp / "runs")],
        ):
            line = _one_error_run(argv)
            assert f"{path}: line 1: integer " in line and "too large for a number" in line
            assert len(line) < 300
        assert sorted(p.name for p in tmp.iterdir()) == ["plan.json"]


def _one_error_run(argv: list[str]) -> str:
    """``main(argv)`` with stderr captured by hand (Hypothesis tests take no capsys)."""
    import contextlib
    import io

    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        rc = main(argv)
    lines = err.getvalue().splitlines()
    assert rc == 2 and out.getvalue() == "", (out.getvalue(), err.getvalue())
    assert len(lines) == 1 and lines[0].startswith(f"hrm {argv[0]}: error: "), lines
    return lines[0]


@FAST
@given(number=WIDE_INTS, where=st.sampled_from(["robot", "box"]))
@example(number="9" * 400, where="robot")
@example(number="9" * 5000, where="robot")
@example(number="9223372036854775808", where="box")
def test_a_toml_integer_beyond_64_bits_is_one_line(number: str, where: str) -> None:
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        if where == "robot":
            path = tmp / "robot.toml"
            path.write_text(
                ROBOT_TEXT.replace("outer_diameter_mm = 30.0", f"outer_diameter_mm = {number}")
            )
            argv = ["urdf", "--robot", str(path), "--out", str(tmp / "arm.urdf")]
        else:
            path = tmp / "box.toml"
            path.write_text(BOX_TEXT.replace("rate_hz = 100", f"rate_hz = {number}", 1))
            argv = ["busload", "--config", str(path)]
        line = _one_error_run(argv)
        assert line.startswith(f"hrm {argv[0]}: error: {path}: ")
        n = len(number.lstrip("-"))
        if n > 4300:  # more digits than Python converts: the TOML reader refuses it
            assert "not valid TOML (a number that cannot be read" in line
        else:
            assert "outside TOML's 64-bit range" in line
        assert len(line) < 300
        assert sorted(p.name for p in tmp.iterdir()) == [path.name]


def test_counts_beyond_the_drives_32_bits_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    robot = tmp_path / "robot.toml"
    robot.write_text(ROBOT_TEXT.replace("drum_radius_mm = 10.0", "drum_radius_mm = 1e-300"))
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    out = tmp_path / "sp.csv"
    refused(
        capsys, tmp_path, ["ropes", str(plan), "--robot", str(robot), "--out", str(out)],
        "beyond the drives' 32-bit position",
    )  # fmt: skip


# ---- 14. nesting too deep for a parser ---------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "text"),
    [
        ("plan", "[" * 100_000 + "]" * 100_000),
        ("plan", '{"format": "hrm-plan/1", "report": ' + '{"a": ' * 100_000),
        ("robot", ROBOT_TEXT + "\nzz = " + "[" * 100_000 + "]" * 100_000 + "\n"),
        ("box", "zz = " + "[" * 100_000 + "]" * 100_000 + "\n" + BOX_TEXT),
    ],
    ids=["plan-array", "plan-report", "robot-toml", "box-toml"],
)
def test_nesting_100000_deep_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, kind: str, text: str
) -> None:
    path = tmp_path / f"{kind}.input"
    path.write_text(text)
    argv = {
        "plan": ["ropes", str(path), "--out", str(tmp_path / "sp.csv")],
        "robot": ["urdf", "--robot", str(path), "--out", str(tmp_path / "arm.urdf")],
        "box": ["busload", "--config", str(path)],
    }[kind]
    refused(capsys, tmp_path, argv, f"{path}: ", "nested too deeply")
    if kind == "plan":
        run = ["run", str(path), "--sim", "--log-dir", str(tmp_path / "runs")]
        refused(capsys, tmp_path, run, "nested too deeply")


# ---- 14. inputs that would size a huge allocation ----------------------------------------


@FAST
@given(step=st.floats(min_value=5e-324, max_value=0.03))
@example(step=1e-300)
@example(step=5e-324)
@example(step=1e-4)
def test_a_step_that_would_need_gigabytes_is_refused_before_planning(step: float) -> None:
    with tempfile.TemporaryDirectory() as tmp_name:
        out = Path(tmp_name) / "plan.json"
        line = _one_error_run(
            ["plan", "--scenario", "bent-pipe", "--step", repr(step), "--out", str(out)]
        )
        assert (
            "more than the 20000 a plan may have" in line
            or "backbone samples" in line
            or (step < 1e-5 and "step must be at least 1e-05 mm" in line)
        ), line
        assert not out.exists()


def test_demo_refuses_such_a_step_too(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "demo"
    refused(capsys, tmp_path, ["demo", "--step", "1e-4", "--out", str(out)], "a plan may have")
    refused(capsys, tmp_path, ["demo", "--step", "1e-300", "--out", str(out)], "at least 1e-05")


@FAST
@given(hold=st.floats(min_value=3600.5, allow_infinity=True, allow_nan=False))
@example(hold=1e308)
@example(hold=float("inf"))
def test_a_hold_too_long_is_one_line(hold: float) -> None:
    with tempfile.TemporaryDirectory() as tmp_name:
        logs = Path(tmp_name) / "runs"
        line = _one_error_run(["run", "--hold", repr(hold), "--sim", "--log-dir", str(logs)])
        assert "--hold must be > 0 s and at most 3600 s" in line
        assert not logs.exists()


@pytest.mark.parametrize(
    ("rate", "speed", "wanted"),
    [
        # 200 Hz: above about 215 Hz a whole count of motion is over the motors' jerk limit,
        # which is refused first
        ("200", "0.19", "more than the 400000 a playback may have"),
        ("100", "1e-300", "exceeds the longest run of 3600 s"),
        # (a cap faster than the motors, 1e308 mm/s, plays at their limits since issue 10:
        # tests/hrm_ctrl/cli/test_ropes.py)
    ],
    ids=["rows", "duration"],
)
def test_a_speed_that_would_size_a_huge_table_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, rate: str, speed: str, wanted: str
) -> None:
    box = tmp_path / "box.toml"
    box.write_text(VIRTUAL_BOX_TEXT.replace("rate_hz = 100", f"rate_hz = {rate}", 1))
    plan = tmp_path / "plan.json"
    doc = small_plan()
    for k, st_ in enumerate(doc["steps"]):
        st_["travel_mm"] = 200.0 * k  # 600 mm: at 0.19 mm/s, 3158 s
    write_plan(plan, doc)
    argv = ["ropes", str(plan), "--config", str(box), "--speed", speed]
    refused(capsys, tmp_path, [*argv, "--out", str(tmp_path / "sp.csv")], wanted)


def _zigzag(n: int, far: float) -> str:
    rows = [f"{far if k % 2 else -far},0,0" for k in range(n)]
    return "x,y,z\n" + "\n".join(rows) + "\n"


@pytest.mark.parametrize(
    ("text", "wanted"),
    [
        ("x,y,z\n" + "1,2,3\n4,5,6\n" * 50_001, "more than the 100000 points a path may have"),
        ('x,y,z\n"' + "1" * 200_000 + '",0,0\n1,0,0\n', ":2: not a CSV line (field larger"),
        ("x,y,z\n1200,100,300\n1e308,100,300\n", ":3: x = 1e+308 mm is farther than"),
        (_zigzag(60, 9e5), "longer than the 100000 mm a path may be"),
        ("x,y,z\n" + "9" * 5000 + ",0,0\n1,0,0\n", "x is not finite: '999"),
    ],
    ids=["points", "csv-field", "far", "long", "digits"],
)
def test_a_path_file_that_would_size_a_huge_plan_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, text: str, wanted: str
) -> None:
    path = tmp_path / "path.csv"
    path.write_text(text)
    out = tmp_path / "plan.json"
    line = refused(capsys, tmp_path, ["plan", "--path", str(path), "--out", str(out)], wanted)
    assert len(line) < 300


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero")
@pytest.mark.parametrize(
    "argv",
    [
        ["plan", "--path", "/dev/zero"],
        ["urdf", "--robot", "/dev/zero"],
        ["busload", "--config", "/dev/zero"],
        ["ropes", "/dev/zero"],
    ],
    ids=["path", "robot", "box", "plan"],
)
def test_an_endless_input_is_refused_unread(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: list[str]
) -> None:
    refused(capsys, tmp_path, argv, "/dev/zero: ", "is not a regular file")


@pytest.mark.parametrize(
    "argv",
    [
        ["plan", "--path", "FIFO"],
        ["urdf", "--robot", "FIFO"],
        ["busload", "--config", "FIFO"],
        ["ropes", "FIFO"],
        ["calibrate", "kinematic", "FIFO"],
    ],
    ids=["path", "robot", "box", "plan", "poses"],
)
def test_a_fifo_as_input_is_refused_without_waiting_for_a_writer(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: list[str]
) -> None:
    """Opening a FIFO for reading waits for a writer: the command would hang (in the
    console, with the drives enabled); it is refused as not a regular file instead."""
    fifo = tmp_path / "in.fifo"
    os.mkfifo(fifo)
    argv = [str(fifo) if a == "FIFO" else a for a in argv]
    refused(capsys, tmp_path, argv, f"{fifo}: ", "is not a regular file")
    folder = tmp_path / "in.d"  # a folder opens for reading; it is refused the same way
    folder.mkdir()
    argv = [str(folder) if a == str(fifo) else a for a in argv]
    refused(capsys, tmp_path, argv, f"{folder}: ", "is not a regular file")


@pytest.mark.parametrize("kind", ["fifo", "folder"])
@pytest.mark.parametrize(
    "argv",
    [["plan", "--path", "PATH", "--out", "OUT"], ["urdf", "--out", "OUT"]],
    ids=["plan", "urdf"],
)
def test_an_output_that_is_no_regular_file_is_never_replaced(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: list[str], kind: str
) -> None:
    """``--out`` naming a FIFO or a device (``/dev/null``): the atomic write would replace
    it by a regular file; refused before anything is read."""
    out = tmp_path / "out"
    if kind == "fifo":
        os.mkfifo(out)
    else:
        out.mkdir()
    (tmp_path / "path.csv").write_text(PATH_CSV)
    subs = {"PATH": str(tmp_path / "path.csv"), "OUT": str(out)}
    argv = [subs.get(a, a) for a in argv]
    refused(capsys, tmp_path, argv, "exists and is not a regular file")


@pytest.mark.parametrize("argv", [["urdf", "--out", "OUT"], ["plan", "--path", "PATH", "--out",
                                  "OUT"]], ids=["urdf", "plan"])  # fmt: skip
def test_an_output_that_is_a_link_is_written_through(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: list[str]
) -> None:
    """``--out`` naming a symbolic link (``/dev/stdout`` redirected to a file is one):
    the link's target gets the output, the link stays a link (the atomic write once
    replaced ``/dev/stdout`` itself by a regular file)."""
    target = tmp_path / "real" / "target.out"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "link.out"
    link.symlink_to(target)
    (tmp_path / "path.csv").write_text(PATH_CSV)
    subs = {"PATH": str(tmp_path / "path.csv"), "OUT": str(link)}
    assert main([subs.get(a, a) for a in argv]) == 0, capsys.readouterr().err
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_text() != "old" and target.stat().st_size > 100
    assert sorted(x.name for x in target.parent.iterdir()) == ["target.out"]  # no temp left


@pytest.mark.parametrize(
    ("plot", "out"), [("figs", "figs/angles.png"), ("o.json", "o.json")], ids=["member", "same"]
)
def test_two_outputs_naming_one_file_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture, plot: str, out: str
) -> None:
    """``--plot DIR --out DIR/angles.png`` (the plan would replace a figure) and ``--out X
    --plot X``: refused before anything is planned or made (the plot folder too)."""
    (tmp_path / "path.csv").write_text(PATH_CSV)
    argv = ["plan", "--path", str(tmp_path / "path.csv"), "--plot", str(tmp_path / plot)]
    refused(capsys, tmp_path, [*argv, "--out", str(tmp_path / out)], "are the same file")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["path.csv"]


@pytest.mark.skipif(not Path("/dev/null").is_char_device(), reason="no /dev/null")
def test_dev_null_as_output_stays_a_device(capsys: pytest.CaptureFixture) -> None:
    one_error(capsys, "urdf", main(["urdf", "--out", "/dev/null"]))
    assert Path("/dev/null").is_char_device()


def test_an_output_inside_the_calibration_store_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """The store's files are read by ``plan`` and ``ropes``: ``--out`` may not name one of
    them (nor any other path in the store: only ``hrm calibrate`` writes there)."""
    store = tmp_path / "cal"
    store.mkdir()
    (store / "active").write_text("v0001\n")
    empty = tmp_path / "cal-empty"  # (calibrate reads the store's pointer first)
    empty.mkdir()
    (tmp_path / "path.csv").write_text(PATH_CSV)
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    for argv in (
        ["plan", "--path", str(tmp_path / "path.csv"), "--calibrations", str(store),
         "--out", str(store / "active")],
        ["ropes", str(plan), "--calibrations", str(store), "--out", str(store / "x.csv")],
        ["calibrate", "kinematic", str(tmp_path / "poses.csv"), "--calibrations", str(empty),
         "--out", str(empty / "v0005.json")],  # a version the store did not write
        ["calibrate", "zero", "--sim", "--calibrations", str(empty),
         "--out", str(empty / "v0005.json")],
    ):  # fmt: skip
        refused(capsys, tmp_path, argv, "inside the calibration store being read")


def test_a_tension_rate_whose_period_no_wait_takes_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    refused(capsys, tmp_path, ["sim", "--tension-rate", "1e-300"], "--tension-rate must be in [1,")


@pytest.mark.parametrize("value", ["50", "-3"])
def test_a_box_priority_outside_the_safe_range_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, value: str
) -> None:
    refused(capsys, tmp_path, ["sim", "--rt-priority", value], "--rt-priority must be in 0..49")


# ---- 14. a closed stdout -----------------------------------------------------------------


def _closed_stdout_run(argv: list[str], cwd: Path, buffered: bool) -> subprocess.CompletedProcess:
    """``python -m hrm_ctrl.cli argv`` writing into a pipe nobody reads any more."""
    env = dict(os.environ)
    env.pop("PYTHONUNBUFFERED", None)
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run(
            [sys.executable, "-m", "hrm_ctrl.cli", *argv],
            stdout=write_end, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env, timeout=120,
        )  # fmt: skip
    finally:
        os.close(write_end)


@pytest.mark.parametrize("buffered", [True, False], ids=["buffered", "unbuffered"])
@pytest.mark.parametrize(
    "argv",
    [
        ["plan", "--scenario", "bent-pipe", "--step", "50", "--allow-collision"],
        ["ropes", "plan.json", "--json"],
        ["urdf"],
        ["busload"],
        ["sim", "--config", "box.toml", "--duration", "0.2"],
    ],
    ids=["plan", "ropes", "urdf", "busload", "sim"],
)
def test_a_closed_stdout_is_a_quiet_exit(tmp_path: Path, argv: list[str], buffered: bool) -> None:
    write_plan(tmp_path / "plan.json", small_plan())
    (tmp_path / "box.toml").write_text(VIRTUAL_BOX_TEXT)
    done = _closed_stdout_run(argv, tmp_path, buffered)
    assert done.returncode == EXIT_CLOSED_PIPE == 141, done.stderr
    assert "Traceback" not in done.stderr and "Error" not in done.stderr, done.stderr
    assert all(line.startswith(f"hrm {argv[0]}: warning: ") for line in done.stderr.splitlines())


def test_a_broken_pipe_that_is_not_stdout_stays_an_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    import hrm_ctrl.cli.urdf as urdf

    def broken(_args: Any) -> int:
        raise BrokenPipeError(32, "Broken pipe (a socket, not stdout)")

    monkeypatch.setattr(urdf, "run", broken)
    with pytest.raises(BrokenPipeError):
        main(["urdf"])


# ---- paths the file system refuses, log folders in the calibration store -----------------

TOO_LONG = "x" * 300  # over NAME_MAX (255): the file system raises ENAMETOOLONG


@pytest.mark.parametrize(
    "argv",
    [
        ["report", TOO_LONG, "--uncalibrated"],
        ["report", TOO_LONG + ".json", "--uncalibrated"],
        ["report", "somerun", "--log-dir", TOO_LONG, "--uncalibrated"],
        ["calibrate", "show", "--calibrations", TOO_LONG],
        ["run", "--sim", "--hold", "0.2", "--uncalibrated", "--log-dir", TOO_LONG],
    ],
    ids=["report-run", "report-json", "report-log-dir", "calibrate-store", "run-log-dir"],
)
def test_a_path_too_long_for_the_file_system_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch,
    argv: list[str],
) -> None:  # fmt: skip
    """Found by a red-team helper: ``OSError: [Errno 36] File name too long`` tracebacks."""
    monkeypatch.chdir(tmp_path)
    line = refused(capsys, tmp_path, argv)
    assert "xxxx" in line


@pytest.mark.parametrize("command", ["run", "status"])
def test_logs_are_never_written_into_the_calibration_store(
    tmp_path: Path, capsys: pytest.CaptureFixture, command: str
) -> None:
    """Only the store writes in the store (``calibrate`` refused it; ``status`` wrote its
    run record and CAN logs there)."""
    store = tmp_path / "store"
    store.mkdir()
    argv = [command, "--sim", "--calibrations", str(store), "--log-dir", str(store / "runs")]
    if command == "run":
        argv += ["--hold", "0.2"]
    refused(capsys, tmp_path, argv, "is inside the calibration store being read")


def test_an_error_naming_a_path_with_a_line_break_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    refused(capsys, tmp_path, ["sim", "--truth", str(tmp_path / "t\nx.toml")], "t\\nx.toml")
