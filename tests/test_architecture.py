"""The import rules of the layout (issue 8), checked by import-linter.

The contracts live in ``pyproject.toml`` (``[tool.importlinter]``); this test runs
``lint-imports`` on the repository and fails with its report when a contract
breaks.  A second test runs the same contracts on a scratch copy of the packages
with one forbidden import added per contract, so a contract that silently checks
nothing (a misspelt module, a wrong kind) fails here too.  Imports that only appear
in docstrings (doctests) are not imports: the scratch copy checks that as well.
"""

from __future__ import annotations

import os
import pkgutil
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import drivers
import hrm_ctrl

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hrm_ctrl", "drivers", "sim_bus", "calibration")
TIMEOUT_S = 120.0

# hrm_ctrl modules the drivers may import; every other one is in contract "drivers".
DRIVERS_MAY_USE = {"errors", "files", "validate"}
# drivers modules the simulator may import; every other one is in contract "sim-bus".
# realtime: the process settings (CPU split, SCHED_FIFO, the GC hold) a box process needs
# as much as the host does.
SIM_MAY_USE = {"protocol", "config", "data", "realtime"}


def _lint_imports(cwd: Path) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.exists() else [shutil.which("lint-imports") or "lint-imports"]
    env = dict(os.environ, PYTHONPATH=str(cwd))  # import the packages under cwd, not another copy
    return subprocess.run(
        [*cmd, "--no-cache", "--no-logo", "--config", str(cwd / "pyproject.toml")],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )


def _contracts() -> dict[str, dict]:
    with open(ROOT / "pyproject.toml", "rb") as f:
        cfg = tomllib.load(f)["tool"]["importlinter"]
    return {c["id"]: c for c in cfg["contracts"]}


def test_import_contracts_are_kept():
    res = _lint_imports(ROOT)
    assert res.returncode == 0, f"import rules broken (lint-imports):\n{res.stdout}{res.stderr}"
    assert "0 broken" in res.stdout


@pytest.mark.parametrize(
    ("contract", "package", "may_use"),
    [("drivers", hrm_ctrl, DRIVERS_MAY_USE), ("sim-bus", drivers, SIM_MAY_USE)],
)
def test_allow_list_contracts_name_every_module(contract, package, may_use):
    """The "nothing but ..." rules are forbidden lists: each new module must join one side."""
    forbidden = set(_contracts()[contract]["forbidden_modules"])
    children = {m.name for m in pkgutil.iter_modules(package.__path__)}
    unlisted = sorted(
        f"{package.__name__}.{name}"
        for name in children - may_use
        if f"{package.__name__}.{name}" not in forbidden
    )
    assert not unlisted, f"contract {contract!r}: forbid or allow {unlisted} in pyproject.toml"


# One forbidden import per contract: (module file, appended line, the import reported, contract).
INJECTED = [
    ("hrm_ctrl/formats/urdf.py", "import drivers.session", "direction"),
    ("hrm_ctrl/model.py", "import hrm_ctrl.planning.backbone", "direction"),
    ("hrm_ctrl/planning/backbone.py", "import hrm_ctrl.ropes.length", "planning"),
    ("hrm_ctrl/ropes/length.py", "import hrm_ctrl.formats.planfile", "ropes"),
    ("drivers/busload.py", "import hrm_ctrl.model", "drivers"),
    ("sim_bus/wire.py", "import drivers.session", "sim-bus"),
    ("hrm_ctrl/runtime/box.py", "import hrm_ctrl.cli", "runtime"),
    ("calibration/workflows.py", "import hrm_ctrl.runtime.box", "direction"),
    ("hrm_ctrl/hil/rig.py", "import hrm_ctrl.cli", "direction"),
]
DOCSTRING_ONLY = ("hrm_ctrl/planning/fitting.py", "import sim_bus.box")


def _module(path: str) -> str:
    return path.removesuffix(".py").removesuffix("/__init__").replace("/", ".")


def _report_of(stdout: str, contract_name: str) -> str:
    """The part of lint-imports' report about one broken contract."""
    broken = stdout.split("Broken contracts", 1)[-1]
    start = broken.find(f"\n{contract_name}\n")
    assert start >= 0, f"contract {contract_name!r} not reported broken:\n{stdout}"
    rest = broken[start + len(contract_name) + 2 :]
    ends = [rest.find(f"\n{c['name']}\n") for c in _contracts().values()]
    return rest[: min([e for e in ends if e >= 0], default=len(rest))]


def test_contracts_catch_a_forbidden_import(tmp_path):
    for pkg in PACKAGES:
        shutil.copytree(
            ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
        )
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    for path, line, _ in INJECTED:
        with open(tmp_path / path, "a") as f:
            f.write(f"\n{line}  # injected by test_architecture\n")
    path, line = DOCSTRING_ONLY
    with open(tmp_path / path, "a") as f:
        f.write(f'\n\ndef _injected():\n    """\n    >>> {line}\n    """\n')

    res = _lint_imports(tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode != 0, out
    names = {k: c["name"] for k, c in _contracts().items()}
    for path, line, contract in INJECTED:
        imported = line.removeprefix("import ")
        assert f"{_module(path)} -> {imported}" in _report_of(res.stdout, names[contract]), out
    assert f"{_module(DOCSTRING_ONLY[0])} -> " not in out


# The one composition root (issue 33): a drive session is opened by the runtime layer alone
# (hrm_ctrl.runtime.box.open_box), and the benchmarks, which are not a package import-linter
# sees, use the library the way the entry points do, not the CLI.
SESSION_CONSTRUCTED = re.compile(r"\bDriveSession\(")
CLI_IMPORTED = re.compile(r"^\s*(from|import)\s+hrm_ctrl\.cli\b", re.MULTILINE)


def _code_lines(path: Path) -> list[tuple[int, str]]:
    """The lines of ``path`` outside docstrings and comments that construct a session."""
    import ast

    tree = ast.parse(path.read_text(), str(path))
    hits = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name | ast.Attribute)
            and (node.func.id if isinstance(node.func, ast.Name) else node.func.attr)
            == "DriveSession"
        ):
            hits.append((node.lineno, ast.get_source_segment(path.read_text(), node) or ""))
    return hits


def test_only_the_runtime_layer_constructs_a_drive_session():
    production = [
        p
        for pkg in (*PACKAGES, "benchmarks")
        for p in sorted((ROOT / pkg).rglob("*.py"))
        if "__pycache__" not in p.parts
    ]
    found = [
        f"{p.relative_to(ROOT)}:{line}"
        for p in production
        if p.relative_to(ROOT).parts[:2] != ("hrm_ctrl", "runtime")
        for line, _ in _code_lines(p)
    ]
    assert not found, f"DriveSession constructed outside hrm_ctrl/runtime: {found}"
    # the check sees a construction where there is one
    assert _code_lines(ROOT / "hrm_ctrl" / "runtime" / "box.py")
    assert SESSION_CONSTRUCTED.search((ROOT / "hrm_ctrl" / "runtime" / "box.py").read_text())


def test_the_benchmarks_import_nothing_of_the_cli():
    benchmarks = sorted((ROOT / "benchmarks").glob("*.py"))
    assert benchmarks
    found = [
        f"{p.relative_to(ROOT)}: {m.group(0).strip()}"
        for p in benchmarks
        for m in CLI_IMPORTED.finditer(p.read_text())
    ]
    assert not found, f"benchmarks import the CLI: {found}"
    assert CLI_IMPORTED.search("x = 1\nfrom hrm_ctrl.cli._common import Input\n")
    assert CLI_IMPORTED.search("import hrm_ctrl.cli\n")
    assert not CLI_IMPORTED.search("from hrm_ctrl.clinic import x\n")
