"""What a console script may be and what its lines may say: a named SCRIPT that is not a
regular file (a FIFO with no writer) refused without blocking, a byte that is not UTF-8
refused at its line before anything runs (a file) or at its line (a pipe), a line of
exactly MAX_LINE_CHARS characters accepted, move numbers parsed as plain ASCII decimal
only, and ``run``'s announcement the plan's own length (not the pause allowance)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hrm_ctrl.cli._console.shell import script_of, script_path
from hrm_ctrl.cli._console.table import (
    COMMANDS,
    MAX_LINE_CHARS,
    ConsoleError,
    load_commands,
    parse_float,
    parse_int,
    split_line,
)
from tests.hrm_ctrl.cli.cli_helpers import run_cli

PYTHON = sys.executable
WAIT_S = 60.0


def _console(tmp_path: Path, *args: str, stdin: object = subprocess.DEVNULL):
    env = dict(os.environ, HOME=str(tmp_path), HRM_CALIBRATIONS=str(tmp_path / "cal"))
    return subprocess.run(
        [PYTHON, "-m", "hrm_ctrl.cli", "console", "--sim", "--log-dir", "runs", *args],
        stdin=stdin, capture_output=True, text=True, timeout=WAIT_S, cwd=tmp_path, env=env,
    )  # fmt: skip


# ---------------------------------------------------------------- 1. not a regular file
def test_a_fifo_as_script_is_refused_without_waiting_for_a_writer(tmp_path: Path) -> None:
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    started = time.monotonic()
    p = _console(tmp_path, "f")  # no writer ever comes: open() would block for ever
    assert time.monotonic() - started < WAIT_S
    assert p.returncode == 2
    assert p.stderr.splitlines() == [
        "hrm console: error: argument SCRIPT: f: not a regular file (a FIFO)"
    ]
    assert not (tmp_path / "runs").exists()


def test_script_path_refuses_folders_and_devices_and_leaves_missing_files(tmp_path, capsys):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError, match="not a regular file \\(a folder\\)"):
        script_path(str(tmp_path))
    with pytest.raises(argparse.ArgumentTypeError, match="not a regular file \\(a device\\)"):
        script_path(os.devnull)
    assert script_path(str(tmp_path / "none.txt")) == tmp_path / "none.txt"  # opening says it
    rc, _out, err = run_cli(["console", "--sim", os.devnull], capsys)
    assert rc == 2
    assert err.splitlines() == [
        f"hrm console: error: argument SCRIPT: {os.devnull}: not a regular file (a device)"
    ]


# ---------------------------------------------------------------- 2. not UTF-8 text
BAD_UTF8 = b"help\n# moves first\nhelp jog\n# caf\xe9 \xff\nhelp home\n"


def test_a_file_that_is_not_utf8_is_refused_at_its_line_before_the_first_command(
    tmp_path: Path,
) -> None:
    path = tmp_path / "c1.txt"
    path.write_bytes(BAD_UTF8)
    with open(path, encoding="utf-8", errors="strict") as stream:  # as hrm console opens it
        with pytest.raises(ConsoleError, match=r"^c1\.txt:4: not UTF-8 text \(byte 0xe9 at col"):
            script_of(stream, "c1.txt")  # a regular file: read and checked whole, nothing run


def test_a_pipe_that_is_not_utf8_is_refused_at_its_line(tmp_path: Path) -> None:
    r, w = os.pipe()
    os.write(w, BAD_UTF8)
    os.close(w)
    with open(r, encoding="utf-8", errors="strict") as stream:
        lines = iter(script_of(stream, "stdin"))  # a pipe: line by line as they come
        assert [next(lines) for _ in range(3)] == ["help\n", "# moves first\n", "help jog\n"]
        with pytest.raises(ConsoleError, match=r"^stdin:4: not UTF-8 text \(byte 0xe9"):
            next(lines)


def test_the_console_refuses_a_later_undecodable_line_with_nothing_run(tmp_path: Path) -> None:
    """File and stdin give the same line; nothing of the script ran (no connect, no move)."""
    script = tmp_path / "c1.txt"
    script.write_bytes(b"connect\nenable\njog 5 theta +2\n# \xff\n")
    p = _console(tmp_path, "c1.txt")
    assert p.returncode == 2, p.stderr
    assert p.stderr.splitlines()[-1] == (
        "hrm console: error: c1.txt:4: not UTF-8 text (byte 0xff at column 3)"
    )
    assert "Traceback" not in p.stderr and "> connect" not in p.stdout
    assert not (tmp_path / "runs").exists()  # no session was opened
    with script.open("rb") as stdin:
        q = _console(tmp_path, stdin=stdin)
    assert q.returncode == 2
    assert q.stderr.splitlines()[-1] == p.stderr.splitlines()[-1]
    assert "> connect" not in q.stdout


# ---------------------------------------------------------------- 3. MAX_LINE_CHARS
def test_a_line_of_exactly_max_line_chars_is_accepted(tmp_path: Path) -> None:
    line = "# " + "x" * (MAX_LINE_CHARS - 2)
    assert split_line(line + "\n") == [] and split_line(line + "\r\n") == []
    with pytest.raises(ConsoleError, match=f"longer than {MAX_LINE_CHARS}"):
        split_line(line + "x\n")
    for newline in ("\n", "\r\n"):
        path = tmp_path / "long.txt"
        path.write_bytes(f"{line}{newline}help{newline}".encode())
        with open(path, encoding="utf-8") as stream:
            assert len(script_of(stream, "long.txt")) == 2
    path.write_text(f"help\n{line}x\nhelp\n")
    with open(path, encoding="utf-8") as stream:
        with pytest.raises(ConsoleError, match=f"^long.txt:2: line longer than {MAX_LINE_CHARS}"):
            script_of(stream, "long.txt")


# ---------------------------------------------------------------- 4. numbers
@pytest.mark.parametrize("text", ["1_0", "١٠", "٥", "²", "0x10", "1e3", " 5", "5 ", "", "+"])
def test_whole_numbers_are_ascii_decimal_only(text: str) -> None:
    with pytest.raises(ConsoleError, match=r"^COUNTS: .* is not a whole number"):
        parse_int(text, "COUNTS")


@pytest.mark.parametrize(
    "text", ["1_0", "٢", "٢.٥", "nan", "inf", "-Infinity", "0x1p3", "1e", ".", "", "2 "]
)
def test_decimal_numbers_are_ascii_decimal_only(text: str) -> None:
    with pytest.raises(ConsoleError, match=r"^DEG: .* is not a number"):
        parse_float(text, "DEG")


def test_plain_numbers_still_parse() -> None:
    assert [parse_int(t, "N") for t in ("5", "+5", "-800", "007")] == [5, 5, -800, 7]
    values = [parse_float(t, "DEG") for t in ("+2", "-1.5", ".5", "2.", "1e-3", "-2E+1")]
    assert values == [2.0, -1.5, 0.5, 2.0, 0.001, -20.0]
    with pytest.raises(ConsoleError, match=r"^DEG: '1e999' is too large"):
        parse_float("1e999", "DEG")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["jog", "5", "theta", "1_0"], r"DEG: '1_0' is not a number"),
        (["jog", "٥", "theta", "٢"], r"JOINT: '٥' is not a whole number"),
        (["jog", "5", "theta", "٢"], r"DEG: '٢' is not a number"),
        (["jog", "j05r1", "1_000"], r"COUNTS: '1_000' is not a whole number"),
        (["jog", "j05r1", "١٠٠"], r"COUNTS: '١٠٠' is not a whole number"),
        (["home", "2_0"], r"SPEED_MM_S: '2_0' is not a number"),
    ],
)
def test_move_commands_refuse_loose_numbers_before_anything(args, message) -> None:
    """Refused while parsing, before the session is looked at (the stub has none)."""
    load_commands()
    config = SimpleNamespace(control=SimpleNamespace(period_s=0.01))
    ctx = SimpleNamespace(actuation=None, config=config, session=None)
    with pytest.raises(ConsoleError, match=f"^{message}.*; usage: {args[0]}"):
        COMMANDS[args[0]].handler(ctx, args[1:])


# ---------------------------------------------------------------- 5. run's announcement
def test_a_pausable_source_is_announced_with_its_own_length() -> None:
    """``play`` announces what a pausable source plays at full rate (its table), not its
    ``n_cycles`` (which adds the longest pause: the wait for the stream's end)."""
    from drivers.sources import CountsSource, PausableSource
    from hrm_ctrl.cli._console.streaming import play

    class Lim:
        motor_ids = ("m0",)
        max_rate_counts_per_s = np.array([1e4])
        max_accel_counts_per_s2 = np.array([1e6])
        max_jerk_counts_per_s3 = None
        counts_min = np.array([-(10**6)])
        counts_max = np.array([10**6])

        def motor_label(self, i):
            return self.motor_ids[i]

        def check_counts(self, counts, previous=None, dt_s=None):
            pass

    body = np.arange(0, 2001, 20).reshape(-1, 1)
    source = PausableSource(CountsSource(Lim(), body, 0.01, hold_s=0.0), Lim())
    source.start(np.array([0]), 0.01)
    assert source.n_cycles > source.n_rows + 60_000  # the allowance for a 600 s pause

    class Session:
        supervisor = SimpleNamespace(mode=SimpleNamespace(name="STREAMING"))

        def _stream_timeout_s(self, src):
            return 5.0

        def stream(self, src):
            time.sleep(0.3)  # the main thread announces meanwhile
            return SimpleNamespace(cycles=src.n_rows)

    lines: list[str] = []
    config = SimpleNamespace(control=SimpleNamespace(period_s=0.01))
    ctx = SimpleNamespace(
        session=Session(), stop_requested=threading.Event(), out=lines.append, config=config
    )
    play(ctx, source, "run")
    n = source.n_rows
    assert lines == [f"run: moving, {n} cycles ({n * 0.01:.2f} s); Ctrl-C stops"]
