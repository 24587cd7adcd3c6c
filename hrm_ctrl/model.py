"""The robot model: an immutable description of the arm, loaded from TOML.

Like pinocchio's ``Model``, a :class:`RobotModel` never changes once loaded;
every function that needs it takes it explicitly (no globals).  Units inside
are mm and radians; the TOML file uses degrees where a person types angles.

Every table and key of the file is known (:data:`PLAIN_KEYS`, :data:`TABLE_KEYS`): an
unknown one is refused when the file loads, naming the key and its table (a typo such
as ``[ropess]`` would otherwise fall back to the default ropes unnoticed).  The keys
of ``[ropes]`` and ``[motors]`` are checked, with their values, by the rope layer
that owns them (``hrm_ctrl.ropes.routing``, ``hrm_ctrl.ropes.motor_map``), the same
way: ``[ropes]: unknown key 'colour'``.

>>> m = default_robot()
>>> m.n_joints, float(m.links.sum())
(12, 2007.0)
>>> round(float(m.limit_alpha), 6) == round(float(np.deg2rad(60.0)), 6)
True
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.errors import RobotDescriptionError
from hrm_ctrl.files import read_toml
from hrm_ctrl.validate import Spec, number, unknown_key

N_JOINTS = 12
MAX_FIDUCIALS = 16
# The base plate's reference nests (base frame, mm): behind and around joint 1, not in one
# plane, so that three or more of them fix an instrument's frame.
DEFAULT_FIDUCIALS_MM = np.array(
    [[-100.0, 120.0, 120.0], [-100.0, -120.0, 120.0], [-100.0, 0.0, -150.0], [-250.0, 0.0, 0.0]]
)
DEFAULT_FIDUCIALS_MM.setflags(write=False)
DEFAULT_ROBOT_RESOURCE = "robot.toml"

PLAIN_KEYS = frozenset({"name", "links_mm", "outer_diameter_mm"})
"""Top-level keys of a robot description that hold a value."""

TABLE_KEYS: Mapping[str, frozenset[str] | None] = {
    "joint_limits": frozenset({"alpha_deg", "theta_deg"}),
    "base": frozenset({"position_mm", "yaw_deg", "pitch_deg", "fiducials_mm"}),
    "ropes": None,  # keys checked by hrm_ctrl.ropes.routing when the rope layer is built
    "motors": None,  # keys checked by hrm_ctrl.ropes.motor_map when the rope layer is built
    # optional, for the feed-forward compensation; values checked by
    # hrm_ctrl.ropes.feedforward when it is built (commented out in the shipped file: the
    # shipped description's content, and the calibrations made for it, stay as they were)
    "physics": frozenset(
        {
            "link_mass_kg",
            "payload_kg",
            "gravity_dir",
            "mu_kinetic",
            "static_ratio",
            "presliding_mm",
            "backlash_deg",
            "backlash_torque_Nmm",
        }
    ),
}
"""Tables of a robot description and the keys each may hold (``None``: its owner, the
rope layer, checks them).  Any other table or key is refused by :func:`robot_from_dict`."""


@dataclass(frozen=True, eq=False)
class RobotModel:
    """Immutable robot description (mm, rad).

    Attributes:
        name: free-form name of the arm.
        links: link lengths ``l_1 .. l_12`` (mm), shape (12,).
        outer_diameter: outer diameter of every link (mm), shape (12,).
        limit_alpha: |alpha_i| must stay below this (rad).
        limit_theta: |theta_i| must stay below this (rad).
        base_position: centre of joint 1 in the world frame (mm), shape (3,).
        base_rotation: world-from-base rotation, shape (3, 3); the arm's zero
            direction is ``base_rotation @ (1, 0, 0)``.
        base_fiducials: (k, 3) the base plate's reference nests in the base frame (mm):
            where an instrument (the laser tracker) measures the base to find its own frame.
        source: where the description came from (file path or resource name).
        tables: the raw TOML tables the planner does not interpret (``ropes``,
            ``motors`` and ``physics``, when present), read by the layers that own them.
    """

    name: str
    links: np.ndarray
    outer_diameter: np.ndarray
    limit_alpha: float
    limit_theta: float
    base_position: np.ndarray
    base_rotation: np.ndarray
    source: str
    tables: Mapping[str, Any] = field(default_factory=dict)
    base_fiducials: np.ndarray = field(default_factory=lambda: DEFAULT_FIDUCIALS_MM.copy())

    @property
    def n_joints(self) -> int:
        return int(self.links.shape[0])

    @property
    def length(self) -> float:
        """Total length L_sum (mm)."""
        return float(self.links.sum())

    @property
    def base_direction(self) -> np.ndarray:
        """Unit vector of the arm at zero angles (world frame)."""
        return self.base_rotation[:, 0].copy()

    def to_dict(self) -> dict[str, Any]:
        """The description as plain JSON-ready values (mm, degrees)."""
        return {
            "name": self.name,
            "links_mm": [float(v) for v in self.links],
            "outer_diameter_mm": [float(v) for v in self.outer_diameter],
            "joint_limits_deg": {
                "alpha": math.degrees(self.limit_alpha),
                "theta": math.degrees(self.limit_theta),
            },
            "base": {
                "position_mm": [float(v) for v in self.base_position],
                "rotation": self.base_rotation.tolist(),
                "fiducials_mm": self.base_fiducials.tolist(),
            },
            "source": self.source,
        }


MAX_LENGTH_MM = 1.0e5  # 100 m: anything larger is a typo, not an arm

_POSITIVE = Spec(lo=0.0, lo_open=True, hi=MAX_LENGTH_MM, unit="mm")
_COORDINATE = Spec(lo=-MAX_LENGTH_MM, hi=MAX_LENGTH_MM)
_LIMIT = Spec(lo=0.0, lo_open=True, hi=90.0, hi_open=True, unit="deg")

RANGES: Mapping[str, Spec] = {
    "links_mm": _POSITIVE,
    "outer_diameter_mm": _POSITIVE,
    "joint_limits.alpha_deg": _LIMIT,
    "joint_limits.theta_deg": _LIMIT,
    "base.position_mm": _COORDINATE,
    "base.yaw_deg": _COORDINATE,
    "base.pitch_deg": _COORDINATE,
    "base.fiducials_mm": _COORDINATE,
}
"""The range of every number of a robot description (each element of a list), by key
(:class:`hrm_ctrl.validate.Spec`); no magnitude beyond :data:`MAX_LENGTH_MM`."""


def _number(value: Any, where: str, key: str) -> float:
    """``value`` of ``key`` (at ``where``: file and key) as a float within its range."""
    x = float(number(value, where, RobotDescriptionError))
    s = RANGES[key]
    if s.contains(x):
        return x
    if x <= s.lo and s.lo_open:
        raise RobotDescriptionError(f"{where}: must be > {s.lo:g}, got {value!r}")
    if abs(x) > MAX_LENGTH_MM:
        raise RobotDescriptionError(
            f"{where}: {x:.6g} is out of range (|value| <= {MAX_LENGTH_MM:g})"
        )
    raise RobotDescriptionError(f"{where} must be < {s.hi:g}, got {x}")


def _table(doc: Mapping[str, Any], key: str, where: str) -> Mapping[str, Any]:
    if key not in doc:
        raise RobotDescriptionError(f"{where}: missing table [{key}]")
    value = doc[key]
    if not isinstance(value, Mapping):
        raise RobotDescriptionError(f"{where}: [{key}] must be a table")
    return value


def _require(doc: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in doc:
        raise RobotDescriptionError(f"{where}: missing key '{key}'")
    return doc[key]


def _check_keys(doc: Mapping[str, Any], where: str) -> None:
    """Refuse a table or key the description does not know, naming it and its table.

    >>> _check_keys({"ropess": {}}, "r.toml")
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.RobotDescriptionError: r.toml: unknown table [ropess] (did you mean [ropes]?)
    >>> _check_keys({"base": {"yaw": 1}}, "f")
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.RobotDescriptionError: f: [base]: unknown key 'yaw' (did you mean 'yaw_deg'?)
    """
    for key, value in doc.items():
        if key in PLAIN_KEYS:
            if isinstance(value, Mapping):
                raise RobotDescriptionError(f"{where}: '{key}' must be a value, not a table")
            continue
        if key not in TABLE_KEYS:
            kind = f"table [{key}]" if isinstance(value, Mapping) else f"key {key!r}"
            hint = unknown_key(key, PLAIN_KEYS | set(TABLE_KEYS), TABLE_KEYS)
            raise RobotDescriptionError(f"{where}: unknown {kind}{hint}")
        if not isinstance(value, Mapping):
            raise RobotDescriptionError(f"{where}: [{key}] must be a table")
        known = TABLE_KEYS[key]
        if known is None:
            continue
        for sub in value:
            if sub not in known:
                raise RobotDescriptionError(
                    f"{where}: [{key}]: unknown key {sub!r}{unknown_key(sub, known)}"
                )


def base_rotation_from(yaw: float, pitch: float) -> np.ndarray:
    """World-from-base rotation: yaw about z, then pitch up about the new y.

    >>> R = base_rotation_from(math.pi / 2, 0.0)
    >>> np.round(R[:, 0], 12).tolist()
    [0.0, 1.0, 0.0]
    """
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(-pitch), math.sin(-pitch)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return Rz @ Ry


def robot_from_dict(doc: Mapping[str, Any], source: str) -> RobotModel:
    """Validate a parsed robot description and build the model."""
    where = source
    _check_keys(doc, where)
    name = doc.get("name", "hrm")
    if not isinstance(name, str):
        raise RobotDescriptionError(f"{where}: 'name' must be a string")

    links_raw = _require(doc, "links_mm", where)
    if not isinstance(links_raw, list) or len(links_raw) != N_JOINTS:
        raise RobotDescriptionError(
            f"{where}: 'links_mm' must be a list of {N_JOINTS} lengths, got {links_raw!r}"
        )
    links = np.array(
        [_number(v, f"{where}: links_mm[{i}]", "links_mm") for i, v in enumerate(links_raw)]
    )

    od_raw = _require(doc, "outer_diameter_mm", where)
    if isinstance(od_raw, list):
        if len(od_raw) != N_JOINTS:
            raise RobotDescriptionError(
                f"{where}: 'outer_diameter_mm' list must have {N_JOINTS} values"
            )
        od = np.array(
            [
                _number(v, f"{where}: outer_diameter_mm[{i}]", "outer_diameter_mm")
                for i, v in enumerate(od_raw)
            ]
        )
    else:
        od = np.full(N_JOINTS, _number(od_raw, f"{where}: outer_diameter_mm", "outer_diameter_mm"))

    lim = _table(doc, "joint_limits", where)
    la, lt = (
        _number(_require(lim, k, where), f"{where}: joint_limits.{k}", f"joint_limits.{k}")
        for k in ("alpha_deg", "theta_deg")
    )

    base = _table(doc, "base", where)
    pos_raw = _require(base, "position_mm", where)
    if not isinstance(pos_raw, list) or len(pos_raw) != 3:
        raise RobotDescriptionError(f"{where}: base.position_mm must be [x, y, z]")
    pos = np.array(
        [
            _number(v, f"{where}: base.position_mm[{i}]", "base.position_mm")
            for i, v in enumerate(pos_raw)
        ]
    )
    yaw = _number(base.get("yaw_deg", 0.0), f"{where}: base.yaw_deg", "base.yaw_deg")
    pitch = _number(base.get("pitch_deg", 0.0), f"{where}: base.pitch_deg", "base.pitch_deg")
    fid = DEFAULT_FIDUCIALS_MM.copy()
    if "fiducials_mm" in base:
        raw = base["fiducials_mm"]
        if not isinstance(raw, list) or not 3 <= len(raw) <= MAX_FIDUCIALS:
            raise RobotDescriptionError(
                f"{where}: base.fiducials_mm must be a list of 3..{MAX_FIDUCIALS} points [x, y, z]"
            )
        rows = []
        for k, p in enumerate(raw):
            if not isinstance(p, list) or len(p) != 3:
                raise RobotDescriptionError(f"{where}: base.fiducials_mm[{k}] must be [x, y, z]")
            rows.append(
                [
                    _number(v, f"{where}: base.fiducials_mm[{k}][{i}]", "base.fiducials_mm")
                    for i, v in enumerate(p)
                ]
            )
        fid = np.array(rows)
        centred = fid - fid.mean(axis=0)
        if np.linalg.matrix_rank(centred, tol=1.0) < 2:
            raise RobotDescriptionError(
                f"{where}: base.fiducials_mm lie on one line: they cannot fix a frame"
            )

    tables = {k: doc[k] for k in ("ropes", "motors", "physics") if k in doc}
    for arr in (links, od, pos, fid):
        arr.setflags(write=False)
    R = base_rotation_from(math.radians(yaw), math.radians(pitch))
    R.setflags(write=False)
    return RobotModel(
        name=name,
        links=links,
        outer_diameter=od,
        limit_alpha=math.radians(la),
        limit_theta=math.radians(lt),
        base_position=pos,
        base_rotation=R,
        source=source,
        tables=tables,
        base_fiducials=fid,
    )


def load_robot(path: str | Path | None = None) -> RobotModel:
    """Load a robot description; ``None`` loads the one shipped with the package.

    Raises :class:`RobotDescriptionError` with a one-line message naming the
    file and the problem.
    """
    if path is None:
        default = resources.files("hrm_ctrl.data").joinpath(DEFAULT_ROBOT_RESOURCE)
        with resources.as_file(default) as p:
            doc, source = read_toml(
                p, RobotDescriptionError, "robot file", f"<default {DEFAULT_ROBOT_RESOURCE}>"
            )
    else:
        doc, source = read_toml(path, RobotDescriptionError, "robot file")
    return robot_from_dict(doc, source)


def default_robot() -> RobotModel:
    """The robot description shipped with the package (Table 1)."""
    return load_robot(None)
