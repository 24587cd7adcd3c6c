"""What several commands share: the bus configuration and the calibration store they
read, and the one check that an output is not an input (their options:
:mod:`hrm_ctrl.cli._options`).

Every command that writes calls :func:`refuse_overwriting_inputs` first, before it
reads or writes anything else: an output path (a file, or a directory and the files
the command writes into it) that names one of the files the command reads (plan, path
file, robot description, bus configuration, the shipped files it reads by default) is
refused with one line naming both.  Two paths name the same file when they resolve to
the same path (symbolic links followed) or, when both exist, are the same file
(:func:`os.path.samefile`: hard links too).

The calibration store is an input of every command, whether it reads it or not: no output
is written into the default store (``$HRM_CALIBRATIONS``, else the one under the home
folder) nor into any folder that holds a store's files (an ``active`` pointer or a
version file ``v0001.json``); only ``hrm calibrate`` writes there, through the store.

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = (d / "plan.json").write_text("{}")
>>> (d / "link.json").symlink_to(d / "plan.json")
>>> refuse_overwriting_inputs([Output("--out", d / "link.json")],
...                           [Input("plan file", d / "plan.json")])
... # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.errors.OverwriteInputError: --out .../link.json would overwrite ...: the same file
>>> refuse_overwriting_inputs([Output("--out", d / "new.json")],
...                           [Input("plan file", d / "plan.json"), Input("robot", None)])
"""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from hrm_ctrl.errors import OverwriteInputError

# the arm and the calibration store's folder: hrm_ctrl.runtime.arm (re-exported here)
from hrm_ctrl.runtime.arm import (
    CALIBRATIONS_ENV as CALIBRATIONS_ENV,
)
from hrm_ctrl.runtime.arm import (
    DEFAULT_CALIBRATIONS as DEFAULT_CALIBRATIONS,
)
from hrm_ctrl.runtime.arm import (
    Arm,
    calibrations_folder,
)

if TYPE_CHECKING:
    from hrm_ctrl.model import RobotModel


_STORE_FILE = re.compile(r"v\d{4,6}\.json")  # a version file (calibration.store)


class Input(NamedTuple):
    """A file a command reads: what it is (``plan file``) and its path (None: not read);
    with ``folder``, a folder whose every file is read (the calibration store): no
    output may be written anywhere in it."""

    what: str
    path: Path | str | None
    folder: bool = False


class Output(NamedTuple):
    """Where a command writes: its option (``--out``), the path, and for a directory the
    files (relative paths) the command writes into it."""

    option: str
    path: Path | str | None
    members: Sequence[str] = ()
    folder: bool = False  # the path is a folder (``--log-dir``; one with members is too)


def _same_file(a: Path, b: Path) -> bool:
    try:
        if os.path.samefile(a, b):
            return True
    except OSError:  # one of them does not exist (yet)
        pass
    try:
        return a.resolve() == b.resolve()
    except (OSError, RuntimeError):  # a symbolic link loop
        return os.path.abspath(a) == os.path.abspath(b)


def _special(path: Path) -> bool:
    """``path`` exists and is neither a regular file nor a folder (links followed)."""
    return os.path.lexists(path) and not (os.path.isfile(path) or os.path.isdir(path))


def _inside(path: Path, folder: Path) -> bool:
    """``path`` is ``folder`` or lies under it (links followed where they exist)."""
    try:
        p, f = path.resolve(), folder.resolve()
    except (OSError, RuntimeError):  # a symbolic link loop
        p, f = Path(os.path.abspath(path)), Path(os.path.abspath(folder))
    return p == f or f in p.parents


def _store_folder(path: Path) -> Path | None:
    """The calibration store ``path`` would be written into, else None: the default store
    (:func:`calibrations_folder`) or a folder on the way holding a store's files."""
    default = calibrations_folder(None)
    if _inside(path, default):
        return default
    for folder in (path, *path.parents)[:2]:  # the output itself, or the folder it is in
        try:
            names = os.listdir(folder) if os.path.isdir(folder) else []
        except OSError:
            continue
        if any(n == "active" or _STORE_FILE.fullmatch(n) for n in names):
            return folder
    return None


def refuse_overwriting_inputs(outputs: Iterable[Output], inputs: Iterable[Input]) -> None:
    """Raise :class:`OverwriteInputError` (one line naming both) when an output, or a file
    a directory output is written with, is one of the ``inputs`` or inside an input
    folder, or exists and is not a regular file (a device or a FIFO would be replaced by
    the atomic write), or when two outputs name the same file (``--plot DIR --out
    DIR/angles.png``); entries with no path are skipped.  Reads nothing but the paths'
    metadata."""
    outputs = [o for o in outputs if o.path is not None]
    written = [
        (o.option, t)
        for o in outputs
        for t in (Path(o.path), *(Path(o.path) / m for m in o.members))
    ]
    for k, (option, target) in enumerate(written):  # two outputs, one file: one would be lost
        for other, there in written[k + 1 :]:
            if other != option and _same_file(target, there):
                raise OverwriteInputError(
                    f"{option} {target} and {other} {there} are the same file"
                )
    read = [(i.what, Path(i.path)) for i in inputs if i.path is not None and not i.folder]
    folders = [(i.what, Path(i.path)) for i in inputs if i.path is not None and i.folder]
    for out in outputs:
        if out.path is None:
            continue
        base = Path(out.path)
        if out.members or out.folder:  # a member may be a folder, not a device or FIFO
            odd = [t for t in (base / m for m in out.members) if _special(t)]
        else:
            odd = [base] if os.path.lexists(base) and not os.path.isfile(base) else []
        if odd:
            raise OverwriteInputError(
                f"{out.option} {base}: {odd[0]} exists and is not a regular file"
            )
        for what, folder in folders:
            if _inside(base, folder):
                raise OverwriteInputError(
                    f"{out.option} {base} is inside the {what} being read ({folder})"
                )
        store = _store_folder(base)
        if store is not None:
            raise OverwriteInputError(
                f"{out.option} {base} is inside the calibration store ({store}): only hrm "
                "calibrate writes there"
            )
        for target in (base, *(base / m for m in out.members)):
            for what, src in read:
                if not _same_file(target, src):
                    continue
                where = f"{out.option} {base}"
                if target != base:
                    where += f": {target}"
                how = "" if os.path.abspath(target) == os.path.abspath(src) else ": the same file"
                raise OverwriteInputError(
                    f"{where} would overwrite the {what} being read ({src}){how}"
                )


def robot_input(robot: Path | None) -> Input:
    """The robot description a command reads: ``--robot`` or the shipped one."""
    if robot is not None:
        return Input("robot description", robot)
    from importlib import resources

    from hrm_ctrl.model import DEFAULT_ROBOT_RESOURCE

    shipped = resources.files("hrm_ctrl.data").joinpath(DEFAULT_ROBOT_RESOURCE)
    return Input("robot description", Path(str(shipped)))


def config_input(config: Path | None) -> Input:
    """The bus configuration a command reads: ``--config`` or the shipped one."""
    from drivers import default_box_path

    return Input("bus configuration", default_box_path() if config is None else config)


def load_box(args: argparse.Namespace) -> Any:
    """The bus configuration of ``--config`` with the ``--bus`` overrides applied
    (:class:`drivers.config.BoxConfig`; a bad file or override: one-line
    :class:`drivers.config.BusConfigError`)."""
    from drivers.config import load_box_config

    config = load_box_config(args.config)
    return config.with_bus_overrides(getattr(args, "bus", None) or [])


def calibrations_input(args: argparse.Namespace) -> Input:
    """The calibration store a command reads (``--calibrations``), as an input folder;
    none with ``--uncalibrated``."""
    if getattr(args, "uncalibrated", False):
        return Input("calibration store", None, folder=True)
    return Input(
        "calibration store", calibrations_folder(getattr(args, "calibrations", None)), True
    )


def arm_from_args(
    args: argparse.Namespace, description: RobotModel, *, prog: str, simulated: bool = False
) -> Arm:
    """:func:`hrm_ctrl.runtime.arm.load_arm` with the command's ``--calibrations`` and
    ``--uncalibrated`` (when it has them)."""
    from hrm_ctrl.runtime.arm import load_arm

    return load_arm(
        description,
        calibrations=getattr(args, "calibrations", None),
        uncalibrated=bool(getattr(args, "uncalibrated", False)),
        simulated=simulated,
        perturb=getattr(args, "perturb", None) if simulated else None,
        truth_file=getattr(args, "truth", None) if simulated else None,
        prog=prog,
    )


def shipped_inputs(*, plan_schema: bool = False, eds: bool = False) -> list[Input]:
    """Other shipped files a command reads: the plan schema, the drives' EDS."""
    found: list[Input] = []
    if plan_schema:
        from importlib import resources

        from hrm_ctrl.formats.planfile import SCHEMA_FILE

        schema = resources.files("hrm_ctrl.formats").joinpath(SCHEMA_FILE)
        found.append(Input("plan schema", Path(str(schema))))
    if eds:
        from drivers import eds_path

        found.append(Input("drive EDS", eds_path()))
    return found
