"""Applying a calibration: which robot it belongs to, the calibrated model and rope layer,
and a new calibration carrying the others' results.

**Which robot.**  :func:`robot_sha256` is the SHA-256 of the robot description's
*content*, not of its file's bytes: the canonical JSON (sorted keys, floats written as
Python writes them, so bit for bit) of every value the description holds: name, link
lengths, outer diameters, joint limits, base position and rotation, and the raw
``[ropes]`` and ``[motors]`` tables.  The shipped default and a ``--robot FILE`` are
treated alike, the file's path, comments and layout do not count, and any value that
changes makes another robot (whose calibrations are refused).  It is always taken of the
description as loaded, never of a calibrated model (whose links differ).

**How far from the description.**  The store keeps any finite value; :func:`check_belongs`
(every command that applies a calibration, or makes one active, calls it) refuses a
calibration whose values could not be this arm's, one line naming the file and the key
(:func:`check_ranges`): a link length more than :data:`LINK_MAX_DEVIATION_MM` (20 mm) or
:data:`LINK_MAX_DEVIATION_FRACTION` (10 %), whichever is more, from the description's; a
joint zero offset beyond :data:`MAX_OFFSET_RAD` (10 deg) either way; a rope's EA outside
:data:`EA_RATIO_RANGE` (0.25 .. 4) times the description's; a motor zero more than
:data:`ZERO_MAX_ROPE_MM` (50 mm) of rope from the description's count 0.  The simulated
arm's perturbations (links +-2 mm, offsets +-1 deg, EA +-20 %, zeros +-5000 counts: 2.3 mm
of rope) and its truth files' limits (10 mm, 5 deg, 0.5 .. 2 times, 50 000 counts) are well
inside, with room for the routines' errors; 1e300 is far outside.

**Applying.**  :func:`calibrated_model` replaces the link lengths (and, with a physics
calibration, the ``[physics]`` table's link masses, payload and friction coefficients,
which the feed-forward reads); :func:`calibrated_actuation`
builds the rope layer from that model with the calibration's motor zero counts, per-rope
axial rigidity and joint zero offsets (:func:`hrm_ctrl.ropes.actuation.load_actuation`:
true angle = commanded angle + offset).

**A new version.**  Every routine estimates some of the fields; :func:`updated` makes the
next calibration from the active one with those fields replaced, so each routine's new
version carries the other routines' results (:func:`starting_point` is the active one for
this robot, or the description's own values).

>>> from hrm_ctrl.model import default_robot
>>> m = default_robot()
>>> cal = nominal_calibration(m)
>>> cal.robot_sha256 == robot_sha256(m), len(cal.motor_ids), cal.routine.value
(True, 36, 'manual')
>>> new = updated(cal, routine="kinematic", residuals={"rms_after_mm": 0.05},
...               links_mm=m.links + 0.5)
>>> float(calibrated_model(m, new).links[0]), new.routine.value, dict(new.rope_EA_N) == dict(
...     cal.rope_EA_N)
(179.5, 'kinematic', True)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.store import Calibration, CalibrationStore, Routine, checksum
from drivers.identity import BoxIdentity, box_problems, same_box
from hrm_ctrl.errors import CalibrationFileError
from hrm_ctrl.model import RobotModel
from hrm_ctrl.ropes.motor_map import motor_map_from_table
from hrm_ctrl.ropes.routing import routing_from_model

if TYPE_CHECKING:  # the rope layer is imported where one is built (slow to import)
    from hrm_ctrl.ropes.actuation import Actuation

UPDATABLE = frozenset(
    {
        "links_mm",
        "alpha_offset_rad",
        "theta_offset_rad",
        "motor_zero_counts",
        "rope_EA_N",
        "box",
        "physics",
    }
)
"""The fields a routine may replace (:func:`updated`)."""

# How far a calibration may be from its robot description (module docstring).
LINK_MAX_DEVIATION_MM = 20.0
LINK_MAX_DEVIATION_FRACTION = 0.10
MAX_OFFSET_RAD = math.radians(10.0)
EA_RATIO_RANGE = (0.25, 4.0)
ZERO_MAX_ROPE_MM = 50.0


def _plain(value: Any) -> Any:
    """Plain JSON types (numpy arrays and scalars, tuples, mappings)."""
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def robot_content(model: RobotModel) -> dict[str, Any]:
    """The values of a robot description that :func:`robot_sha256` covers."""
    return {
        "name": model.name,
        "links_mm": _plain(model.links),
        "outer_diameter_mm": _plain(model.outer_diameter),
        "limit_alpha_rad": float(model.limit_alpha),
        "limit_theta_rad": float(model.limit_theta),
        "base_position_mm": _plain(model.base_position),
        "base_rotation": _plain(model.base_rotation),
        "base_fiducials_mm": _plain(model.base_fiducials),
        "tables": _plain(model.tables),
    }


def robot_sha256(model: RobotModel) -> str:
    """SHA-256 (64 lower-case hex digits) of the description's content (module docstring).

    >>> import dataclasses
    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> robot_sha256(m) == robot_sha256(dataclasses.replace(m, source="elsewhere.toml"))
    True
    >>> robot_sha256(m) == robot_sha256(dataclasses.replace(m, name="other"))
    False
    """
    text = json.dumps(
        robot_content(model),
        sort_keys=True,
        separators=(",", ":"),
        ensure_ascii=True,
        allow_nan=True,
        default=str,  # a TOML date or time in a raw table
    )
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def nominal_calibration(model: RobotModel, routine: Routine = Routine.MANUAL) -> Calibration:
    """The description's own values as a calibration: its links, zero offsets, zero motor
    counts and the routing's axial rigidity per rope."""
    routing = routing_from_model(model)
    return Calibration.nominal(
        links_mm=model.links,
        motor_ids=routing.rope_ids,
        rope_EA_N=dict(zip(routing.rope_ids, routing.stiffness_EA_N.tolist(), strict=True)),
        robot_sha256=robot_sha256(model),
        routine=routine,
    )


def file_sha256(cal: Calibration, version: int) -> str:
    """The ``sha256`` member of version ``version``'s file (its checksum)."""
    return checksum({**cal.content(), "version": version})


def check_belongs(model: RobotModel, cal: Calibration, where: str = "calibration") -> None:
    """Refuse (:class:`CalibrationFileError`, one line) a calibration for another robot
    description, or one whose motors and ropes are not the description's."""
    sha = robot_sha256(model)
    if cal.robot_sha256 != sha:
        raise CalibrationFileError(
            f"{where}: belongs to robot description {cal.robot_sha256[:12]}…, not to this one "
            f"({model.source}, {sha[:12]}…)"
        )
    ids = routing_from_model(model).rope_ids
    for what, have in (("motor_zero_counts", cal.motor_ids), ("rope_EA_N", cal.rope_ids)):
        if set(have) != set(ids):
            extra = sorted(set(have) - set(ids))[:4]
            missing = [i for i in ids if i not in have][:4]
            raise CalibrationFileError(
                f"{where}: {what} does not name the description's ropes (unknown {extra}, "
                f"missing {missing})"
            )
    check_ranges(model, cal, where)


def check_ranges(model: RobotModel, cal: Calibration, where: str = "calibration") -> None:
    """Refuse (:class:`CalibrationFileError`, one line naming ``where`` and the key) a
    calibration of ``model``'s ropes with a value too far from the description's (module
    docstring).

    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> cal = nominal_calibration(m)
    >>> check_ranges(m, updated(cal, routine="manual", residuals={}, links_mm=m.links + 19.0))
    >>> too_long = updated(cal, routine="manual", residuals={}, links_mm=m.links * 1.2)
    >>> check_ranges(m, too_long)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.CalibrationFileError: calibration: links_mm[0] is 214.8 mm, more than 20 mm...
    """
    desc = np.asarray(model.links, dtype=float)
    if cal.links_mm.shape != desc.shape:
        raise CalibrationFileError(
            f"{where}: links_mm has {cal.links_mm.shape[0]} values, the description {desc.shape[0]}"
        )
    allowed = np.maximum(LINK_MAX_DEVIATION_MM, LINK_MAX_DEVIATION_FRACTION * desc)
    rows = zip(cal.links_mm.tolist(), desc.tolist(), allowed.tolist(), strict=True)
    for j, (v, d, a) in enumerate(rows):
        if not abs(v - d) <= a:
            raise CalibrationFileError(
                f"{where}: links_mm[{j}] is {v:.6g} mm, more than {a:.6g} mm from the "
                f"description's {d:.6g} mm"
            )
    for key in ("alpha_offset_rad", "theta_offset_rad"):
        for j, v in enumerate(getattr(cal, key).tolist()):
            if not abs(v) <= MAX_OFFSET_RAD:
                raise CalibrationFileError(
                    f"{where}: {key}[{j}] is {v:.6g} rad ({math.degrees(v):.4g} deg), beyond "
                    f"the {math.degrees(MAX_OFFSET_RAD):g} deg a joint zero offset may be"
                )
    routing = routing_from_model(model)
    lo, hi = EA_RATIO_RANGE
    for rope, ea0 in zip(routing.rope_ids, routing.stiffness_EA_N.tolist(), strict=True):
        ea = cal.rope_EA_N[rope]
        if not lo * ea0 <= ea <= hi * ea0:
            raise CalibrationFileError(
                f"{where}: rope_EA_N.{rope} is {ea:.6g} N, not within {lo:g} .. {hi:g} times "
                f"the description's {ea0:.6g} N"
            )
    ids = routing.rope_ids
    motors = motor_map_from_table(
        model.tables.get("motors", {}), ids, np.zeros(len(ids)), None, model.source
    )
    for motor, cpm in zip(ids, motors.counts_per_mm.tolist(), strict=True):
        z = cal.motor_zero_counts[motor]
        if not abs(z) <= ZERO_MAX_ROPE_MM * cpm:
            raise CalibrationFileError(
                f"{where}: motor_zero_counts.{motor} is {z} counts, {abs(z) / cpm:.4g} mm of "
                f"rope from the description's zero (at most {ZERO_MAX_ROPE_MM:g} mm, "
                f"{math.floor(ZERO_MAX_ROPE_MM * cpm)} counts)"
            )


def calibrated_model(model: RobotModel, cal: Calibration) -> RobotModel:
    """``model`` with the calibration's link lengths and, where the calibration has a
    physics calibration, its link masses, payload and friction coefficients in the
    ``[physics]`` table (the rest of it, and everything else, as described): the
    feed-forward (:meth:`hrm_ctrl.ropes.feedforward.Feedforward.of`) reads them there.

    >>> from hrm_ctrl.model import default_robot
    >>> from calibration.store import PhysicsConstants
    >>> m = default_robot()
    >>> ph = PhysicsConstants(np.full(12, 0.025), 0.03, np.full(12, 0.08))
    >>> cal = updated(nominal_calibration(m), routine="physics", residuals={}, physics=ph)
    >>> t = calibrated_model(m, cal).tables["physics"]
    >>> t["payload_kg"], t["mu_kinetic"][0], "physics" in m.tables
    (0.03, 0.08, False)
    """
    if cal.links_mm.shape != model.links.shape:
        raise CalibrationFileError(
            f"calibration has {cal.links_mm.shape[0]} links, the description {model.n_joints}"
        )
    links = np.array(cal.links_mm, dtype=float)
    links.setflags(write=False)
    if cal.physics is None:
        return dataclasses.replace(model, links=links)
    raw = model.tables.get("physics", {})
    table = {**(raw if isinstance(raw, Mapping) else {}), **cal.physics.to_dict()}
    return dataclasses.replace(model, links=links, tables={**model.tables, "physics": table})


def calibrated_actuation(model: RobotModel, cal: Calibration) -> Actuation:
    """The rope layer of the calibrated arm: calibrated links, the motor zero counts, the
    per-rope axial rigidity and the joint zero offsets of ``cal``."""
    from hrm_ctrl.ropes.actuation import load_actuation

    return load_actuation(
        calibrated_model(model, cal),
        dict(cal.motor_zero_counts),
        rope_EA_N=dict(cal.rope_EA_N),
        alpha_offset_rad=cal.alpha_offset_rad,
        theta_offset_rad=cal.theta_offset_rad,
    )


def updated(
    base: Calibration,
    *,
    routine: Routine | str,
    residuals: Mapping[str, float],
    **fields: Any,
) -> Calibration:
    """A new calibration from ``base``: the routine's ``fields`` (of :data:`UPDATABLE`)
    replaced, its ``routine`` and ``residuals``, created now; every other field, and the
    robot it belongs to, carried over.  A field not in :data:`UPDATABLE` is a TypeError."""
    unknown = sorted(set(fields) - UPDATABLE)
    if unknown:
        raise TypeError(f"updated(): {unknown} are not fields a routine replaces")
    return dataclasses.replace(
        base,
        routine=Routine(routine),
        residuals=dict(residuals),
        created_utc=datetime.now(UTC),
        **fields,
    )


@dataclasses.dataclass(frozen=True)
class ActiveCalibration:
    """The active calibration of a store for one robot, or None when there is none."""

    calibration: Calibration
    version: int
    path: str
    sha256: str  # the file's checksum


def active_for(store: CalibrationStore, model: RobotModel) -> ActiveCalibration | None:
    """The store's active calibration, checked and refused unless it belongs to ``model``
    (:class:`CalibrationFileError`, one line); None when no version is active."""
    version = store.active()
    if version is None:
        return None
    cal = store.load(version)
    path = str(store.path_of(version))
    check_belongs(model, cal, path)
    return ActiveCalibration(cal, version, path, file_sha256(cal, version))


def starting_point(
    store: CalibrationStore, model: RobotModel, box: BoxIdentity | None = None
) -> tuple[Calibration, ActiveCalibration | None, str | None]:
    """What a routine's new version starts from: the active calibration for ``model`` (and,
    when ``box`` is given, made on that box: a simulated box's, known before it starts), or
    the description's values.  Returns ``(base, active, note)``: ``note`` says why the
    description's values are used (no active version, the active one belongs to another
    robot description or another box).  A damaged active file is refused."""
    version = store.active()
    if version is None:
        return nominal_calibration(model), None, "no active calibration: the description's values"
    cal = store.load(version)  # a damaged file is refused here
    path = str(store.path_of(version))
    if cal.robot_sha256 != robot_sha256(model):
        return (
            nominal_calibration(model),
            None,
            f"{path} (active) belongs to robot description {cal.robot_sha256[:12]}…: "
            "starting from this description's values",
        )
    check_belongs(model, cal, path)
    if box is not None:
        problems = box_problems(cal.box, box, f"{path} (active)")
        if problems:
            return (
                nominal_calibration(model),
                None,
                f"{problems[0]}: starting from the description's values",
            )
    return cal, ActiveCalibration(cal, version, path, file_sha256(cal, version)), None


def for_box(
    base: Calibration, box: BoxIdentity | None, model: RobotModel
) -> tuple[Calibration, str | None]:
    """What the zero routine, which measures every motor zero anew on ``box``, keeps of
    ``base``: all of it when ``base`` was made on that box (drives replaced since or not),
    else the description's values (a calibration of a simulated arm, or of another box,
    or one whose box is unknown, lends none of its links, offsets or EA to this box's new
    version); the note says why.  ``box`` None (not known): ``base``."""
    if box is None or same_box(base.box, box):
        return base, None
    nominal = nominal_calibration(model)
    lent = ("links_mm", "alpha_offset_rad", "theta_offset_rad", "rope_EA_N")
    if all(base.content()[k] == nominal.content()[k] for k in lent):
        return base, None  # the description's values already
    why = box_problems(base.box, box, "the active calibration")
    return nominal, f"{why[0]}: the new version starts from the description's values"
