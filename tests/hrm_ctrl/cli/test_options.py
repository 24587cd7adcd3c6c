"""The shared options (``hrm_ctrl/cli/_options.py``): each declared once, the same type,
metavar and default in every command and console command that has it, a help text on
every option of every command and console command; a command's arguments registered
when the command is parsed."""

from __future__ import annotations

import argparse
import ast
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import pytest

from hrm_ctrl.cli import build_parser

CLI = Path(__file__).resolve().parents[3] / "hrm_ctrl" / "cli"
OPTIONS_MODULE = CLI / "_options.py"

# The options several commands (or a command and the console) have: declared in _options.py
SHARED = (
    "--json", "--out", "--robot", "--calibrations", "--uncalibrated", "--config", "--bus",
    "--take-over", "--log-dir", "--log-format", "--sim", "--wire", "--perturb", "--truth",
    "--speed", "--pause-at", "--resume-after", "--abort-at", "--allow-collision",
    "--target-N", "--tol-N", "--max-travel-counts", "--sweep-N", "--steps", "--physics",
)  # fmt: skip


# One name, two options: hrm plan's and hrm demo's --step MM (lambda, from _options.py) and
# hrm view's --step I (the plan step shown first; docs/usage.md's command table has both)
HOMONYMS = {"--step": ["_options.py", "view.py"]}


def console_parsers() -> dict[str, argparse.ArgumentParser]:
    """The console commands that parse options with argparse."""
    from hrm_ctrl.cli._console.commands_calibrate import _parser
    from hrm_ctrl.cli._console.commands_run import _run_parser

    return {
        "console run": _run_parser(),
        "console calibrate zero": _parser("zero"),
        "console calibrate stiffness": _parser("stiffness"),
    }


def actions(
    parser: argparse.ArgumentParser, prog: str = "hrm"
) -> Iterator[tuple[str, argparse.Action]]:
    """(command, action) of every argument of every command and sub-command."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from actions(sub, f"{prog} {name}")
        elif not isinstance(action, argparse._HelpAction):
            yield prog, action


def every_action() -> list[tuple[str, argparse.Action]]:
    found = list(actions(build_parser(every_command=True)))
    for prog, parser in console_parsers().items():
        found += list(actions(parser, prog))
    return found


def declarations(path: Path) -> Iterator[tuple[str, int]]:
    """(option, line) of every ``add_argument("--option", ...)`` call in a source file."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "add_argument"
        ):
            for arg in node.args:
                if isinstance(arg, ast.Constant) and str(arg.value).startswith("--"):
                    yield str(arg.value), node.lineno


def test_every_option_of_every_command_and_console_command_has_help_text() -> None:
    found = every_action()
    missing = [f"{prog} {'/'.join(a.option_strings) or a.dest}" for prog, a in found if not a.help]
    assert missing == []
    progs = {prog for prog, _ in found}
    assert {"hrm run", "hrm calibrate zero", "console run", "console calibrate zero"} <= progs


def test_the_shared_options_are_declared_once_in_options_module() -> None:
    where: dict[str, list[str]] = defaultdict(list)
    for path in sorted(CLI.rglob("*.py")):
        for option, line in declarations(path):
            where[option].append(f"{path.relative_to(CLI)}:{line}")
    elsewhere = {
        o: [w for w in where[o] if not w.startswith("_options.py:")] for o in SHARED if where[o]
    }
    assert {o: w for o, w in elsewhere.items() if w} == {}
    assert {o: len(where[o]) for o in SHARED} == dict.fromkeys(SHARED, 1)
    for option, files in HOMONYMS.items():
        assert sorted(w.split(":")[0] for w in where[option]) == files


def test_a_shared_option_has_one_type_metavar_and_kind_wherever_it_is() -> None:
    seen: dict[str, set[tuple[object, ...]]] = defaultdict(set)
    uses: dict[str, set[str]] = defaultdict(set)
    for prog, a in every_action():
        for option in a.option_strings:
            if option in SHARED:
                uses[option].add(prog)
                # --out's metavar names what is written (PLAN.json, DIR, ...)
                metavar = None if option == "--out" else a.metavar
                seen[option].add((type(a).__name__, a.type, metavar, a.nargs))
    assert {o: s for o, s in seen.items() if len(s) != 1} == {}
    # shared indeed: by two commands at least (or a command and the console)
    assert {o: sorted(p) for o, p in uses.items() if len(p) < 2} == {}
    assert set(uses) == set(SHARED)


def test_the_json_option_says_what_it_prints() -> None:
    helps = [a.help or "" for _, a in every_action() if "--json" in a.option_strings]
    assert len(helps) >= 12
    assert all(h.startswith("print ") and h.endswith(" as JSON") for h in helps), helps


def test_options_of_a_sim_go_with_sim_in_their_help() -> None:
    """--wire, --perturb, --truth: "with --sim: ..." where the command has --sim."""
    by_prog: dict[str, dict[str, argparse.Action]] = defaultdict(dict)
    for prog, a in every_action():
        for option in a.option_strings:
            by_prog[prog][option] = a
    checked = 0
    for prog, opts in by_prog.items():
        if "--sim" not in opts:
            continue
        for option in ("--wire", "--perturb", "--truth"):
            if option in opts:
                assert (opts[option].help or "").startswith("with --sim: "), (prog, option)
                checked += 1
    assert checked >= 6


def _same(a: argparse.Action, b: argparse.Action) -> tuple[object, ...]:
    return (a.type, a.default, a.metavar, a.help, a.option_strings) == (
        b.type,
        b.default,
        b.metavar,
        b.help,
        b.option_strings,
    ), (a, b)


@pytest.mark.parametrize(
    ("command", "console"),
    [
        ("hrm run", "console run"),
        ("hrm calibrate zero", "console calibrate zero"),
        ("hrm calibrate stiffness", "console calibrate stiffness"),
    ],
)
def test_a_console_command_takes_the_options_of_its_hrm_command(command: str, console: str) -> None:
    """The console's ``run`` has ``hrm run``'s run controls (and --no-figures), its
    ``calibrate zero`` the routine's settings of ``hrm calibrate zero`` (and --fixture)."""
    found = every_action()
    mine = {o: a for p, a in found if p == console for o in a.option_strings}
    theirs = {o: a for p, a in found if p == command for o in a.option_strings}
    own = {"--no-figures", "--fixture"}
    shared = set(mine) - own
    assert shared and shared <= set(theirs), shared - set(theirs)
    for option in shared - {"--json"}:  # --json prints a summary either way
        ok, pair = _same(mine[option], theirs[option])
        assert ok, pair


def test_a_commands_arguments_are_registered_when_it_is_parsed() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert all(len(p._actions) == 1 for p in sub.choices.values())  # -h only, none registered
    args = parser.parse_args(["busload", "--rate", "200", "--json"])
    assert (args.command, args.rate, args.json) == ("busload", 200.0, True)
    registered = {n for n, p in sub.choices.items() if len(p._actions) > 1}
    assert registered == {"busload"}
    # parsing again registers nothing twice
    assert parser.parse_args(["busload"]).rate is None


def test_a_command_usage_error_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    from tests.hrm_ctrl.cli.cli_helpers import run_cli

    rc, out, err = run_cli(["run", "p.json", "--wire", "can"], capsys)
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and "argument --wire: invalid choice: 'can'" in err, err
    rc, out, err = run_cli(["plan", "--help"], capsys)
    assert rc == 0 and "--scenario {bent-pipe,cabins}" in out and "--fit {paper,clearance}" in out
