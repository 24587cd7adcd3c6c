"""The plan file, ``hrm-plan/1``: a contract other tools read, and :class:`PlanDoc`, the only
reader of it.

``{"format": "hrm-plan/1", "robot": {"links_mm": [...12], ...}, "path_mm": [[x, y, z], ...],
"steps": [{"travel_mm": d, "phase": "in", "alpha_rad": [...12], "theta_rad": [...12],
"joints_mm": [[x, y, z] x 13]}, ...], "report": {...}}``.  ``alpha`` is the first
rotation (about y), ``theta`` the second (about x); ``joints_mm`` lists O1..O12 then
the end point; ``phase`` is ``in`` or ``return`` (on every step or on none: then all
``in``).  Extra keys are allowed everywhere and kept: ``to_dict()`` gives back what
``from_dict()`` read.  The JSON Schema ``hrm-plan-1.schema.json`` next to this module is
the format's definition; documents are validated against it (``jsonschema``, Draft
2020-12) and, since JSON Schema cannot say so, every number read into an array must be
finite and in range: lengths, coordinates and travels within +-:data:`MAX_LENGTH_MM` (100 m),
step angles within a half turn, the robot's joint limits within 180 deg; at most
:data:`MAX_PLAN_STEPS` steps and :data:`MAX_PATH_POINTS` path points (counted before the
schema walks them: the 256 MiB a file may have hold a million steps).  Every problem is
one :class:`~hrm_ctrl.errors.PlanFileError` line naming the file and the place, e.g.
``plan.json: steps[3].alpha_rad[2]: expected a finite number``.
A plan made in an environment keeps it as ``scenario.environment`` (the data of a scene
file, :mod:`hrm_ctrl.formats.scene`, checked on reading: :attr:`PlanDoc.environment`) and its
clearance in ``report.clearance_mm`` (``min``, ``step``, ``link``: :attr:`PlanDoc.clearance`);
both are optional (older plans have neither).

>>> import tempfile, pathlib
>>> p = pathlib.Path(tempfile.mkdtemp()) / "p.json"
>>> plan = {"format": PLAN_FORMAT, "robot": {"links_mm": [1.0] * 12},
...         "path_mm": [[0, 0, 0], [1, 0, 0]], "report": {},
...         "steps": [{"travel_mm": 0.0, "alpha_rad": [0.0] * 12, "theta_rad": [0.0] * 12,
...                    "joints_mm": [[float(i), 0.0, 0.0] for i in range(13)]}]}
>>> write_plan(p, plan)
>>> doc = read_plan(p)
>>> doc.joints_mm[0, 12].tolist(), doc.phase, doc.to_dict() == plan
([12.0, 0.0, 0.0], (<Phase.IN: 'in'>,), True)
>>> plan["steps"][0]["alpha_rad"][2] = float("nan")
>>> PlanDoc.from_dict(plan, "plan.json")
Traceback (most recent call last):
...
hrm_ctrl.errors.PlanFileError: plan.json: steps[0].alpha_rad[2]: expected a finite number, got nan
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from functools import cache, cached_property
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from hrm_ctrl.errors import PlanFileError
from hrm_ctrl.files import parse_json, read_text_file, write_atomic
from hrm_ctrl.model import MAX_LENGTH_MM
from hrm_ctrl.planning.known_path import MAX_PATH_POINTS

if TYPE_CHECKING:
    from hrm_ctrl.model import RobotModel
    from hrm_ctrl.planning.environment import Environment

PLAN_FORMAT = "hrm-plan/1"
SCHEMA_FILE = "hrm-plan-1.schema.json"
N_JOINTS = 12
LINK_TOLERANCE_MM = 1e-6  # a plan fits a robot when every link length agrees this closely
# Every length, coordinate and travel of a plan is within +-MAX_LENGTH_MM (100 m, the robot
# description's bound: anything larger is a typo, not an arm), every angle within a half turn
# (the joint limits are below 90 deg), the robot's joint limits in degrees within a half turn
# too: an extreme number (1e300) would overflow the time parameterisation's sums and splines.
MAX_ANGLE_RAD = math.pi
# Two consecutive steps' travels differ by 0 or by at least this much (1 nm, a 500th of an
# encoder count of the shipped motors): the playback's splines divide by the difference.
MIN_TRAVEL_STEP_MM = 1e-6
MAX_LIMIT_DEG = 180.0
MAX_PLAN_BYTES = 256 * 2**20  # a plan file larger than this is refused unread
MAX_PLAN_STEPS = 20_000  # steps of a plan (the planner makes no more; a file has no more)

_TOP_KEYS = ("format", "robot", "path_mm", "steps", "report")
_STEP_KEYS = ("travel_mm", "phase", "alpha_rad", "theta_rad", "joints_mm", "backbone_mm")


class Phase(StrEnum):
    """Which way a plan step moves along the path."""

    IN = "in"
    RETURN = "return"


# ---- the schema ---------------------------------------------------------------------------


def _numbers_ok(items: Any) -> bool:
    return all(isinstance(x, int | float) and not isinstance(x, bool) for x in items)


def _points_ok(items: Any) -> bool:
    return all(isinstance(p, list) and len(p) == 3 and _numbers_ok(p) for p in items)


# Arrays of numbers and of points are most of a plan; checking them element by element
# through jsonschema takes ~10x longer than the rest.  For ``items`` that refer to these
# definitions an array that passes the quick check (which is what the definition says, as
# checked when the schema is loaded) is valid; anything else is checked by jsonschema's own
# ``items``, so the errors and their places are jsonschema's.
_POINT = {"type": "array", "minItems": 3, "maxItems": 3, "items": {"$ref": "#/$defs/number"}}
_QUICK_DEFS = {"number": ({"type": "number"}, _numbers_ok), "point": (_POINT, _points_ok)}


def _keywords(schema: Mapping[str, Any]) -> dict[str, Any]:
    """A schema's validation keywords (without annotations)."""
    return {
        k: v
        for k, v in schema.items()
        if not k.startswith("x-") and k not in ("description", "$comment", "title")
    }


@cache
def plan_schema() -> dict[str, Any]:
    """The JSON Schema of ``hrm-plan/1`` shipped with the package."""
    text = resources.files("hrm_ctrl.formats").joinpath(SCHEMA_FILE).read_text(encoding="utf-8")
    return json.loads(text)


@cache
def _validator() -> Any:
    import jsonschema  # here, not at import: the planner imports this module too

    schema = plan_schema()
    base = jsonschema.Draft202012Validator
    base.check_schema(schema)
    defs = schema.get("$defs", {})
    quick = {
        f"#/$defs/{name}": ok
        for name, (want, ok) in _QUICK_DEFS.items()
        if _keywords(defs.get(name, {})) == want
    }
    std_items = base.VALIDATORS["items"]

    def items(validator: Any, sub: Any, instance: Any, schema: Any) -> Iterator[Any]:
        ok = quick.get(sub.get("$ref")) if isinstance(sub, dict) and len(sub) == 1 else None
        if ok is not None and isinstance(instance, list) and ok(instance):
            return
        yield from std_items(validator, sub, instance, schema)

    cls = jsonschema.validators.extend(base, {"items": items})
    return cls(schema)


def _place(path: Any) -> str:
    """``["steps", 3, "alpha_rad", 2]`` -> ``steps[3].alpha_rad[2]``."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


_NOUNS = {"number": "a number", "array": "an array", "object": "an object", "string": "a string"}


def _message(error: Any, where: str) -> str:
    """One line for a jsonschema error: the file, the place, what was expected."""
    place = _place(error.absolute_path)
    head = f"{where}: {place}" if place else where
    kw, value, inst = error.validator, error.validator_value, error.instance
    schema = error.schema if isinstance(error.schema, Mapping) else {}
    expected = schema.get("x-expected")
    if kw == "required":
        missing = next((k for k in value if k not in inst), value[0])
        return f"{head}: missing key '{missing}'"
    if kw == "const":
        return f"{head} is {_short(inst)}, expected {value!r}"
    if kw == "enum":
        return f"{head}: expected one of {', '.join(map(repr, value))}, got {_short(inst)}"
    if kw == "type":
        return f"{head}: expected {expected or _NOUNS.get(value, value)}, got {_short(inst)}"
    if kw in ("minItems", "maxItems") and isinstance(inst, list):
        want = expected or f"{'at least' if kw == 'minItems' else 'at most'} {value} items"
        return f"{head}: expected {want}, got {len(inst)} item{'s' if len(inst) != 1 else ''}"
    if kw == "anyOf" and schema.get("x-rule") and error.context:
        # a rule between alternatives (phase on every step or on none): the first
        # alternative's first failure, and the rule
        first = min(error.context, key=lambda e: (e.relative_schema_path[0], list(e.path)))
        return f"{_message(first, where)} ({schema['x-rule']})"
    if kw == "exclusiveMinimum":
        return f"{head}: expected a number > {value}, got {_short(inst)}"
    return f"{head}: {error.message}"


def validate_plan(plan: Any, where: str = "plan") -> Any:
    """Check that ``plan`` is an ``hrm-plan/1`` document (schema and finite numbers);
    return it unchanged.  Raises :class:`PlanFileError` naming ``where`` and the place of the
    first problem."""
    PlanDoc.from_dict(plan, where)
    return plan


def _first_huge(value: Any, sub: str = "") -> tuple[str, int] | None:
    """The place and value of the first integer in nested lists a float cannot hold."""
    if isinstance(value, list):
        for i, v in enumerate(value):
            found = _first_huge(v, f"{sub}[{i}]")
            if found is not None:
                return found
        return None
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            float(value)
        except OverflowError:
            return sub, value
    return None


def _floats(value: Any, place: str, where: str) -> np.ndarray:
    """``value`` as a float64 array; an integer too large for a float (a document built in
    Python: the file reader refuses those) is one line naming its place."""
    try:
        return np.array(value, dtype=np.float64)
    except OverflowError:
        sub, _ = _first_huge(value) or ("", 0)
        if place.startswith("steps[]."):  # [k] of the stacked steps names the step
            k, _, rest = sub[1:].partition("]")
            place, sub = f"steps[{k}].{place[8:]}", rest
        raise PlanFileError(
            f"{where}: {place}{sub}: expected a finite number, got an integer too large for a float"
        ) from None


_MM = (MAX_LENGTH_MM, "mm")
_RAD = (MAX_ANGLE_RAD, "rad")
_DEG = (MAX_LIMIT_DEG, "deg")


def _refuse_bad(arr: np.ndarray, bound: tuple[float, str], where: str, name: Any) -> None:
    """Refuse the first non-finite number of ``arr``, or the first beyond ``bound`` (the
    largest size, its unit); ``name(index)`` is its place."""
    limit, unit = bound
    bad = ~(np.abs(arr) <= limit)  # nan included
    if not bad.any():
        return
    idx = tuple(int(i) for i in np.argwhere(bad)[0])
    got = float(arr[idx])
    if not math.isfinite(got):
        raise PlanFileError(f"{where}: {name(idx)}: expected a finite number, got {got!r}")
    raise PlanFileError(
        f"{where}: {name(idx)}: {got:.6g} is out of range (|value| <= {limit:.6g} {unit})"
    )


def _array(value: Any, place: str, where: str, bound: tuple[float, str] = _MM) -> np.ndarray:
    """A schema-checked numeric list as a float array; non-finite numbers and numbers
    beyond ``bound`` in size are refused."""
    arr = _floats(value, place, where)
    _refuse_bad(arr, bound, where, lambda idx: place + "".join(f"[{i}]" for i in idx))
    arr.setflags(write=False)
    return arr


def _step_array(
    steps: list[Any], key: str, where: str, bound: tuple[float, str] = _MM
) -> np.ndarray:
    """``key`` of every (schema-checked) step stacked, (S, ...); non-finite numbers and
    numbers beyond ``bound`` in size are refused naming the step."""
    arr = _floats([st[key] for st in steps], f"steps[].{key}", where)

    def name(idx: tuple[int, ...]) -> str:
        i, *rest = idx
        return f"steps[{i}].{key}" + "".join(f"[{v}]" for v in rest)

    _refuse_bad(arr, bound, where, name)
    arr.setflags(write=False)
    return arr


def _check_travel_steps(travel: np.ndarray, where: str) -> None:
    """Refuse two consecutive travels closer than :data:`MIN_TRAVEL_STEP_MM` but not equal
    (equal ones are the time parameterisation's to judge, by phase)."""
    step = np.abs(np.diff(travel))
    tiny = (step > 0.0) & (step < MIN_TRAVEL_STEP_MM)
    if tiny.any():
        k = int(np.argmax(tiny)) + 1
        raise PlanFileError(
            f"{where}: steps[{k}].travel_mm: {float(travel[k])!r} is {float(step[k - 1]):.3g} mm "
            f"from steps[{k - 1}]'s; travels of consecutive steps differ by 0 or by at least "
            f"{MIN_TRAVEL_STEP_MM:g} mm"
        )


# ---- the document -------------------------------------------------------------------------


def _frozen(d: Mapping[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(dict(d))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and np.array_equal(a, b)
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return bool(a == b)


@dataclass(frozen=True, eq=False)
class PlanDoc:
    """An ``hrm-plan/1`` document, checked, as read-only arrays (mm, rad).

    ``S`` steps, ``P`` path points.  ``robot_extra``, ``step_extra`` (one mapping per
    step) and ``extra`` hold the keys the format does not define, ``backbones_mm`` the
    optional per-step backbone curves; ``explicit_phase`` is False when the file gave no
    ``phase`` (all steps are then ``in`` and ``to_dict`` writes none).  ``source`` names
    the document in messages (not part of its value).
    """

    links_mm: np.ndarray  # (12,)
    path_mm: np.ndarray  # (P, 3)
    travel_mm: np.ndarray  # (S,)
    alpha_rad: np.ndarray  # (S, 12)
    theta_rad: np.ndarray  # (S, 12)
    joints_mm: np.ndarray  # (S, 13, 3)
    phase: tuple[Phase, ...]  # (S,)
    report: Mapping[str, Any]
    backbones_mm: Mapping[int, np.ndarray] = field(default_factory=lambda: MappingProxyType({}))
    robot_extra: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    step_extra: tuple[Mapping[str, Any], ...] = ()
    extra: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    explicit_phase: bool = True
    source: str = "plan"

    @property
    def n_steps(self) -> int:
        return int(self.travel_mm.shape[0])

    @property
    def distance_mm(self) -> np.ndarray:
        """(S,) distance travelled along the sequence of steps: ``travel_mm[0]`` plus the
        sum of ``|travel change|`` so far (grows on a return leg too)."""
        steps = np.abs(np.diff(self.travel_mm))
        return self.travel_mm[0] + np.concatenate(([0.0], np.cumsum(steps)))

    @property
    def joint_limits_deg(self) -> tuple[float | None, float | None]:
        """(alpha, theta) joint limits the plan's robot states, None where it states none."""
        lim = self.robot_extra.get("joint_limits_deg")
        if not isinstance(lim, Mapping):
            return None, None
        a, t = lim.get("alpha"), lim.get("theta")
        return (None if a is None else float(a)), (None if t is None else float(t))

    @cached_property
    def environment(self) -> Environment | None:
        """The environment the plan was made in (``scenario.environment``, scene data of
        :mod:`hrm_ctrl.formats.scene`), None for a plan that stores none (older files)."""
        from hrm_ctrl.formats.scene import scene_from_dict

        sc = self.extra.get("scenario")
        data = sc.get("environment") if isinstance(sc, Mapping) else None
        if data is None:
            return None
        return scene_from_dict(data, f"{self.source}: scenario.environment", PlanFileError)

    @property
    def clearance(self) -> Mapping[str, Any] | None:
        """The report's clearance summary (``min`` mm or None, 0-based ``step``, 1-based
        ``link``), None when the plan states none."""
        c = self.report.get("clearance_mm")
        return c if isinstance(c, Mapping) else None

    @property
    def title(self) -> str:
        """The scenario's name, else the robot's, else ``plan``."""
        sc = self.extra.get("scenario")
        name = sc.get("name") if isinstance(sc, Mapping) else None
        robot_name = self.robot_extra.get("name")
        return str(name) if name else (str(robot_name) if robot_name else "plan")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PlanDoc):
            return NotImplemented
        names = [f for f in self.__dataclass_fields__ if f != "source"]
        return all(_same(getattr(self, f), getattr(other, f)) for f in names)

    __hash__ = None  # type: ignore[assignment]

    @classmethod
    def from_dict(cls, doc: Any, where: str = "plan") -> PlanDoc:
        """Check ``doc`` against the schema (and every array number finite) and read it.

        >>> PlanDoc.from_dict({"format": "hrm-plan/1", "robot": {}, "steps": []}, "p.json")
        Traceback (most recent call last):
        ...
        hrm_ctrl.errors.PlanFileError: p.json: missing key 'path_mm'
        """
        if isinstance(doc, dict):  # before the schema walks them: sizes are bounded
            for key, most in (("steps", MAX_PLAN_STEPS), ("path_mm", MAX_PATH_POINTS)):
                items = doc.get(key)
                if isinstance(items, list) and len(items) > most:
                    raise PlanFileError(f"{where}: {key}: {len(items)} items, more than {most}")
        error = next(iter(_validator().iter_errors(doc)), None)
        if error is not None:
            raise PlanFileError(_message(error, where))
        steps = doc["steps"]
        given = ["phase" in st for st in steps]  # on every step or on none: the schema's rule
        robot = doc["robot"]
        links = _array(robot["links_mm"], "robot.links_mm", where)
        lim = robot.get("joint_limits_deg", {})
        for name in ("alpha", "theta"):
            if name in lim:
                _array(lim[name], f"robot.joint_limits_deg.{name}", where, _DEG)
        path = _array(doc["path_mm"], "path_mm", where)
        travel = _step_array(steps, "travel_mm", where)
        _check_travel_steps(travel, where)
        alpha = _step_array(steps, "alpha_rad", where, _RAD)
        theta = _step_array(steps, "theta_rad", where, _RAD)
        joints = _step_array(steps, "joints_mm", where)
        backbones = {
            k: _array(st["backbone_mm"], f"steps[{k}].backbone_mm", where)
            for k, st in enumerate(steps)
            if "backbone_mm" in st
        }
        plan = cls(
            links_mm=links,
            path_mm=path,
            travel_mm=travel,
            alpha_rad=alpha,
            theta_rad=theta,
            joints_mm=joints,
            phase=tuple(Phase(st.get("phase", "in")) for st in steps),
            report=_frozen(doc["report"]),
            backbones_mm=MappingProxyType(backbones),
            robot_extra=_frozen({k: v for k, v in robot.items() if k != "links_mm"}),
            step_extra=tuple(
                _frozen({k: v for k, v in st.items() if k not in _STEP_KEYS}) for st in steps
            ),
            extra=_frozen({k: v for k, v in doc.items() if k not in _TOP_KEYS}),
            explicit_phase=all(given),
            source=where,
        )
        _ = plan.environment  # checked now: a broken environment is refused on reading
        return plan

    def to_dict(self) -> dict[str, Any]:
        """The document as JSON-ready values (what :meth:`from_dict` read)."""
        travel = self.travel_mm.tolist()
        alpha, theta, joints = (
            a.tolist() for a in (self.alpha_rad, self.theta_rad, self.joints_mm)
        )
        extras = self.step_extra or tuple({} for _ in travel)
        steps = []
        for k, t in enumerate(travel):
            st: dict[str, Any] = {"travel_mm": t}
            if self.explicit_phase:
                st["phase"] = str(self.phase[k])
            st.update(alpha_rad=alpha[k], theta_rad=theta[k], joints_mm=joints[k])
            st.update(extras[k])
            if k in self.backbones_mm:
                st["backbone_mm"] = self.backbones_mm[k].tolist()
            steps.append(st)
        return {
            "format": PLAN_FORMAT,
            "robot": {**self.robot_extra, "links_mm": self.links_mm.tolist()},
            "path_mm": self.path_mm.tolist(),
            **self.extra,
            "steps": steps,
            "report": dict(self.report),
        }

    def check_robot(self, model: RobotModel) -> None:
        """Refuse (one line naming the plan) a plan made for other link lengths than
        ``model``'s (within :data:`LINK_TOLERANCE_MM`)."""
        links = np.asarray(model.links, dtype=np.float64)
        if links.shape != self.links_mm.shape or not np.allclose(
            self.links_mm, links, rtol=0.0, atol=LINK_TOLERANCE_MM
        ):
            raise PlanFileError(
                f"{self.source}: plan was made for links {self.links_mm.tolist()} mm, the robot "
                f"description ({model.source}) has {links.tolist()} mm"
            )


# ---- files --------------------------------------------------------------------------------


def read_plan(path: str | Path) -> PlanDoc:
    """Read and check a plan file; one-line :class:`PlanFileError` on any problem
    (missing, unreadable, larger than :data:`MAX_PLAN_BYTES`, not JSON, nested too deeply,
    an integer beyond a 64-bit float, not ``hrm-plan/1``)."""
    p = Path(path)
    try:
        size = p.stat().st_size
    except OSError:
        size = 0  # read_text_file names the problem
    if size > MAX_PLAN_BYTES:
        raise PlanFileError(
            f"{p}: plan file is {size} bytes, more than the {MAX_PLAN_BYTES} a plan may have"
        )
    text = read_text_file(p, PlanFileError, "plan file", max_bytes=MAX_PLAN_BYTES)
    doc = parse_json(text, PlanFileError, str(p), "plan")
    try:
        return PlanDoc.from_dict(doc, str(p))
    except RecursionError:
        raise PlanFileError(f"{p}: not a plan (JSON nested too deeply)") from None


def write_plan(path: str | Path, plan: PlanDoc | Mapping[str, Any]) -> None:
    """Check (a mapping) and write a plan file atomically."""
    doc = plan if isinstance(plan, PlanDoc) else PlanDoc.from_dict(plan, str(path))
    try:
        text = json.dumps(doc.to_dict(), allow_nan=False, separators=(",", ":")) + "\n"
    except (ValueError, TypeError, RecursionError) as exc:
        raise PlanFileError(f"{path}: cannot write plan file ({exc})") from None
    try:
        write_atomic(path, text)
    except OSError as exc:
        raise PlanFileError(f"{path}: cannot write plan file ({exc.strerror or exc})") from None


__all__ = [
    "LINK_TOLERANCE_MM",
    "MAX_ANGLE_RAD",
    "MAX_LIMIT_DEG",
    "MAX_PLAN_BYTES",
    "MAX_PLAN_STEPS",
    "MIN_TRAVEL_STEP_MM",
    "PLAN_FORMAT",
    "Phase",
    "PlanDoc",
    "plan_schema",
    "read_plan",
    "validate_plan",
    "write_plan",
]
