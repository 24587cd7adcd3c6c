"""Every exception the packages define derives from HrmError and is drawn in hrm_ctrl.errors.

The drawing in the docstring of :mod:`hrm_ctrl.errors` is compared with the classes
themselves (name, parent, defining module), so it cannot fall behind the code: a new
exception fails here until it has its line in the tree.
"""

from __future__ import annotations

import builtins
import importlib
import inspect
import pkgutil

import pytest

import hrm_ctrl.errors
from hrm_ctrl.errors import HrmError

PACKAGES = ("hrm_ctrl", "drivers", "sim_bus", "calibration")
# Not errors of the stack, drawn outside HrmError (the errors.py docstring says why).
OUTSIDE_HRM_ERROR = {"SdoAbort", "SignalInterrupt"}


def _module_names() -> tuple[list[str], list[str]]:
    names: list[str] = []
    failed: list[str] = []
    for pkg in PACKAGES:
        names.append(pkg)
        root = importlib.import_module(pkg)
        for info in pkgutil.walk_packages(root.__path__, f"{pkg}.", onerror=failed.append):
            if info.name.rsplit(".", 1)[-1] != "__main__":  # running it is the console
                names.append(info.name)
    return names, failed


@pytest.fixture(scope="module")
def defined() -> tuple[dict[str, list[type[BaseException]]], list[str]]:
    """Every exception class defined in a package module, by name; and modules that failed."""
    names, failed = _module_names()
    found: dict[str, list[type[BaseException]]] = {}
    for name in names:
        try:
            module = importlib.import_module(name)
        except Exception as exc:
            failed.append(f"{name}: {exc!r}")
            continue
        for obj in vars(module).values():
            if (
                inspect.isclass(obj)
                and issubclass(obj, BaseException)
                and obj.__module__ == module.__name__
            ):
                found.setdefault(obj.__name__, []).append(obj)
    return found, failed


def drawn_tree(doc: str) -> dict[str, tuple[str, str]]:
    """The drawing's classes: name -> (parent's name, module).

    >>> drawn_tree('''
    ...     Exception (Python standard library)
    ...      +-- AError          a
    ...      |    +-- BError     a.b
    ...      +-- CError          c
    ... ''')
    {'AError': ('Exception', 'a'), 'BError': ('AError', 'a.b'), 'CError': ('Exception', 'c')}
    """
    tree: dict[str, tuple[str, str]] = {}
    stack: list[tuple[int, str]] = []  # (column of "+--", name) from the root down
    for line in doc.splitlines():
        if line.rstrip().endswith("(Python standard library)"):
            stack = [(-1, line.split()[0])]
        elif "+-- " in line and stack:
            col = line.index("+-- ")
            name, *_, module = line[col + 4 :].split()
            while stack[-1][0] >= col:
                stack.pop()
            assert name not in tree, f"{name} is drawn twice"
            tree[name] = (stack[-1][1], module)
            stack.append((col, name))
    return tree


def test_every_package_module_imports(defined):
    _, failed = defined
    assert not failed, "cannot collect the exceptions of: " + "; ".join(failed)


def test_exception_names_are_unique(defined):
    found, _ = defined
    twice = {n: [c.__module__ for c in cs] for n, cs in found.items() if len(cs) > 1}
    assert not twice, f"exception names defined more than once: {twice}"


def test_every_exception_derives_from_hrm_error(defined):
    found, _ = defined
    stray = sorted(
        f"{c.__module__}.{c.__name__}"
        for cs in found.values()
        for c in cs
        if not issubclass(c, HrmError | Warning) and c.__name__ not in OUTSIDE_HRM_ERROR
    )
    assert not stray, f"derive these from HrmError (hrm_ctrl.errors): {stray}"
    assert OUTSIDE_HRM_ERROR <= found.keys(), "OUTSIDE_HRM_ERROR names a class nobody defines"


def test_the_docstring_draws_every_exception(defined):
    found, _ = defined
    tree = drawn_tree(hrm_ctrl.errors.__doc__ or "")
    wrong = []
    for name, classes in sorted(found.items()):
        cls = classes[0]
        actual = (cls.__bases__[0].__name__, cls.__module__)
        if name not in tree:
            wrong.append(f"{name} ({cls.__module__}) is not drawn")
        elif tree[name] != actual:
            wrong.append(f"{name}: drawn under {tree[name]}, is under {actual}")
    wrong += [
        f"{name} is drawn but not found (defined nowhere, or its module does not import)"
        for name in sorted(tree.keys() - found.keys())
    ]
    assert not wrong, "hrm_ctrl/errors.py docstring: " + "; ".join(wrong)


def test_the_drawing_roots_are_builtin():
    tree = drawn_tree(hrm_ctrl.errors.__doc__ or "")
    roots = {parent for parent, _ in tree.values()} - tree.keys()
    assert roots and all(isinstance(getattr(builtins, r, None), type) for r in roots), roots
