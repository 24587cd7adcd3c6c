"""The plan file, ``hrm-plan/1``: a contract other tools read.

``{"format": "hrm-plan/1", "robot": {"links_mm": [...12], ...}, "path_mm": [[x, y, z], ...],
"steps": [{"travel_mm": d, "alpha_rad": [...12], "theta_rad": [...12],
"joints_mm": [[x, y, z] x 13]}, ...], "report": {...}}``.  ``alpha`` is the first
rotation (about y), ``theta`` the second (about x); ``joints_mm`` lists O1..O12 then
the end point.  Extra keys are allowed everywhere.

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "p.json"
>>> plan = {"format": PLAN_FORMAT, "robot": {"links_mm": [1.0] * 12},
...         "path_mm": [[0, 0, 0], [1, 0, 0]], "report": {},
...         "steps": [{"travel_mm": 0.0, "alpha_rad": [0.0] * 12, "theta_rad": [0.0] * 12,
...                    "joints_mm": [[float(i), 0.0, 0.0] for i in range(13)]}]}
>>> write_plan(p, plan)
>>> read_plan(p)["steps"][0]["joints_mm"][12]
[12.0, 0.0, 0.0]
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from hrm_ctrl.errors import PlanFileError
from hrm_ctrl.files import read_text_file, write_atomic

PLAN_FORMAT = "hrm-plan/1"
N_JOINTS = 12


def _vector(value: Any, n: int, where: str) -> None:
    if not isinstance(value, list) or len(value) != n:
        raise PlanFileError(f"{where}: expected a list of {n} numbers")
    for k, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise PlanFileError(f"{where}[{k}]: expected a finite number, got {v!r}")


def validate_plan(plan: Any, where: str = "plan") -> dict[str, Any]:
    """Check the structure of an ``hrm-plan/1`` document; return it unchanged.

    Raises :class:`PlanFileError` naming the first problem and where it is.
    """
    if not isinstance(plan, dict):
        raise PlanFileError(f"{where}: not a JSON object")
    fmt = plan.get("format")
    if fmt != PLAN_FORMAT:
        raise PlanFileError(f"{where}: format is {fmt!r}, expected {PLAN_FORMAT!r}")
    for key in ("robot", "path_mm", "steps", "report"):
        if key not in plan:
            raise PlanFileError(f"{where}: missing key '{key}'")
    robot = plan["robot"]
    if not isinstance(robot, dict) or "links_mm" not in robot:
        raise PlanFileError(f"{where}: robot.links_mm missing")
    _vector(robot["links_mm"], N_JOINTS, f"{where}: robot.links_mm")
    path = plan["path_mm"]
    if not isinstance(path, list) or len(path) < 2:
        raise PlanFileError(f"{where}: path_mm must list at least 2 points")
    for j, p in enumerate(path):
        _vector(p, 3, f"{where}: path_mm[{j}]")
    steps = plan["steps"]
    if not isinstance(steps, list) or not steps:
        raise PlanFileError(f"{where}: steps must be a non-empty list")
    for i, st in enumerate(steps):
        w = f"{where}: steps[{i}]"
        if not isinstance(st, dict):
            raise PlanFileError(f"{w}: not an object")
        for key in ("travel_mm", "alpha_rad", "theta_rad", "joints_mm"):
            if key not in st:
                raise PlanFileError(f"{w}: missing key '{key}'")
        t = st["travel_mm"]
        if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
            raise PlanFileError(f"{w}.travel_mm: expected a finite number, got {t!r}")
        _vector(st["alpha_rad"], N_JOINTS, f"{w}.alpha_rad")
        _vector(st["theta_rad"], N_JOINTS, f"{w}.theta_rad")
        joints = st["joints_mm"]
        if not isinstance(joints, list) or len(joints) != N_JOINTS + 1:
            raise PlanFileError(f"{w}.joints_mm: expected {N_JOINTS + 1} points")
        for k, p in enumerate(joints):
            _vector(p, 3, f"{w}.joints_mm[{k}]")
    if not isinstance(plan["report"], dict):
        raise PlanFileError(f"{where}: report must be an object")
    return plan


def read_plan(path: str | Path) -> dict[str, Any]:
    """Read and validate a plan file; one-line :class:`PlanFileError` on any problem."""
    p = Path(path)
    text = read_text_file(p, PlanFileError, "plan file")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PlanFileError(f"{p}: not JSON (line {exc.lineno}: {exc.msg})") from None
    return validate_plan(doc, str(p))


def write_plan(path: str | Path, plan: dict[str, Any]) -> None:
    """Validate and write a plan file atomically."""
    validate_plan(plan, str(path))
    try:
        write_atomic(path, json.dumps(plan, allow_nan=False, separators=(",", ":")) + "\n")
    except OSError as exc:
        raise PlanFileError(f"{path}: cannot write plan file ({exc.strerror or exc})") from None
