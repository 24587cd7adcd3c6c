"""The console's command table and completer, without a box (nothing opens a bus)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import (
    COMMANDS,
    MAX_LINE_CHARS,
    ConsoleError,
    Need,
    command,
    complete_paths,
    find,
    load_commands,
    run_words,
    split_line,
)
from hrm_ctrl.errors import HrmError


@pytest.fixture
def ctx(act) -> ConsoleContext:
    lines: list[str] = []
    c = ConsoleContext(config=None, description=None, model=act.robot, actuation=act,
                       out=lines.append, err=lines.append)  # fmt: skip
    c.lines = lines  # type: ignore[attr-defined]
    load_commands()
    return c


def test_the_console_commands_are_registered() -> None:
    table = load_commands()
    for name in ("help", "connect", "disconnect", "status", "enable", "disable", "stop",
                 "reset-fault", "jog", "home", "view", "sim", "quit"):  # fmt: skip
        assert name in table, name
        assert table[name].summary and table[name].usage.startswith(name)
    assert table["jog"].needs is Need.ENABLED and table["status"].needs is Need.CONNECTED
    assert issubclass(ConsoleError, HrmError)


def test_register_twice_is_refused_and_prefixes_resolve() -> None:
    @command("zz-test-cmd", "s", "zz-test-cmd")
    def _handler(ctx: ConsoleContext, args: list[str]) -> None: ...

    try:
        with pytest.raises(ValueError, match="registered twice"):
            command("zz-test-cmd", "s", "zz-test-cmd")(_handler)
        assert find("zz-test").name == "zz-test-cmd"
    finally:
        del COMMANDS["zz-test-cmd"]
    load_commands()
    assert find("sta").name == "status"
    with pytest.raises(ConsoleError, match=r"st: ambiguous command \(.*status.*stop"):
        find("st")
    with pytest.raises(ConsoleError, match="unknown command"):
        find("frobnicate")


def test_needs_refuse_before_the_handler_runs(ctx) -> None:
    with pytest.raises(ConsoleError, match=r"^jog: not connected \(connect first\)$"):
        run_words(ctx, ["jog", "5", "theta", "2"])
    with pytest.raises(ConsoleError, match=r"^status: not connected"):
        run_words(ctx, ["status"])
    with pytest.raises(ConsoleError, match=r"^sim: only with --sim"):
        run_words(ctx, ["sim", "fault", "reset"])
    run_words(ctx, ["help", "jog"])
    assert ctx.lines[0].startswith("jog JOINT alpha|theta DEG")


def test_lines_are_bounded_and_quoted() -> None:
    assert split_line("  ") == [] and split_line("# only a comment") == []
    assert split_line("sim fault 'drive-fault:j05r1'") == ["sim", "fault", "drive-fault:j05r1"]
    with pytest.raises(ConsoleError, match="longer than 4096"):
        split_line("x" * (MAX_LINE_CHARS + 1))
    with pytest.raises(ConsoleError, match="No closing quotation"):
        split_line('jog "5')


def completions(ctx: ConsoleContext, text: str) -> list[str]:
    from prompt_toolkit.document import Document

    from hrm_ctrl.cli._console.shell import _completer

    return [c.text for c in _completer(ctx).get_completions(Document(text), None)]


def test_completion_of_commands_joints_axes_motors(ctx) -> None:
    got = completions(ctx, "re")
    assert "reset-fault" in got and all(c.startswith("re") for c in got)
    assert completions(ctx, "dis") == ["disable", "disconnect"]
    assert completions(ctx, "jog 1") == ["1", "10", "11", "12"]
    assert completions(ctx, "jog j05r") == ["j05r0", "j05r1", "j05r2"]
    assert completions(ctx, "jog 5 t") == ["theta"]
    assert completions(ctx, "jog 5 theta ") == []
    assert completions(ctx, "status w") == ["watch"]
    assert "drive-fault:j05r1" in completions(ctx, "sim fault drive-fault:j05")


def test_plan_files_complete(tmp_path: Path) -> None:
    (tmp_path / "bent.json").write_text("{}")
    (tmp_path / "notes.txt").write_text("")
    assert complete_paths(str(tmp_path / "b")) == [str(tmp_path / "bent.json")]
    assert complete_paths(str(tmp_path / "n")) == []
