"""The simulated arm's truth: how the real arm differs from its robot description.

A real arm differs from its drawing.  :class:`TrueArm` holds what the simulated box
uses instead of the description (issue 12), and what the calibration routines try to
find:

* ``links_mm`` (12,): the true link lengths ``l_1 .. l_12`` (the description's +- 2 mm
  when perturbed);
* ``alpha_offset_rad``, ``theta_offset_rad`` (12,): joint zero offsets (+- 1 deg).  The
  kinematic calibration's convention: true joint angle = commanded angle + offset.  In
  the simulator the ropes fix the rope-geometric angle phi (the rope layer's inverse of the
  rope lengths) and the physical angle is phi + offset;
* ``rope_EA_N`` (n,): each rope's axial rigidity EA (the description's +- 20 %);
* ``motor_zero_counts`` (n,) int: the true encoder count at which rope m is at its
  pretension with the rope geometry straight (the joint's rope disks coaxial, as the zero
  fixture holds them; the links then stand at the joint offsets); the description's is 0
  for every motor (+- 5000 counts);
* ``slack_mm`` (n,): rope that must be taken up before the rope carries any tension
  (default 0: none);
* ``tracker_rotation`` (3, 3), ``tracker_translation_mm`` (3,): the laser tracker's frame,
  ``p_tracker = R p_base + t`` (the kinematic calibration's convention), and its noise
  ``tracker_noise_mm`` (sigma per axis, 0.05 mm).

Because the motor zeros are defined with the rope geometry straight, a host with the true
zeros and the true joint offsets puts the physical joints exactly where it commands them
(``docs/sim.md``, "Joint offsets and motor zeros"); :meth:`TrueArm.host_zero_counts` gives
the zeros in the host rope layer's convention (the slack taken up) and
:meth:`TrueArm.ideal_actuation` the rope layer a perfect calibration gives.

Every array is in the rope layer's motor order (``Actuation.motor_ids``).
:meth:`TrueArm.nominal` is the description itself (the simulator's default);
:meth:`TrueArm.perturbed` draws a truth from a seed; :func:`read_truth` reads a truth
file (``hrm-sim-truth/1``, TOML, format in ``docs/sim.md``) and :func:`write_truth`
writes one (what ``hrm sim --write-truth`` does), :meth:`TrueArm.to_dict` being its
content.

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> t = TrueArm.perturbed(act, seed=7)
>>> bool(np.abs(t.links_mm - act.robot.links).max() <= 2.0)
True
>>> bool(np.abs(t.motor_zero_counts).max() <= 5000), t.motor_zero_counts.dtype.name
(True, 'int64')
>>> t2 = truth_from_dict(t.to_dict(), act, "<round trip>")
>>> bool(np.array_equal(t2.rope_EA_N, t.rope_EA_N) and np.array_equal(t2.links_mm, t.links_mm))
True
>>> TrueArm.nominal(act).is_nominal(act), t.is_nominal(act)
(True, False)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.errors import SimError
from hrm_ctrl.files import read_toml, write_atomic
from hrm_ctrl.model import RobotModel
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.validate import Spec, number, unknown_key

TRUTH_FORMAT = "hrm-sim-truth/1"
N_JOINTS = 12

# What TrueArm.perturbed draws (uniformly, either side of the description): issue 12.
PERTURB_LINK_MM = 2.0
PERTURB_OFFSET_RAD = math.radians(1.0)
PERTURB_EA_FRACTION = 0.20
PERTURB_ZERO_COUNTS = 5000

# What a truth file may say (wider than the perturbation, so a test can ask for a worse arm;
# beyond these it is a typo, not an arm).
TRUTH_LINK_MAX_DEVIATION_MM = 10.0  # from the description's link length
TRUTH_OFFSET_MAX_RAD = math.radians(5.0)
TRUTH_EA_RATIO_RANGE = (0.5, 2.0)  # of the description's EA
TRUTH_ZERO_MAX_COUNTS = 50_000  # ~23 mm of rope with the shipped motor map
TRUTH_SLACK_MAX_MM = 20.0
TRUTH_TRACKER_MAX_DISTANCE_MM = 50_000.0  # |t|: the tracker within 50 m
TRUTH_TRACKER_NOISE_MAX_MM = 1.0
ROTATION_TOLERANCE = 1e-6  # |R^T R - I| and |det R - 1|

_EA_LO, _EA_HI = TRUTH_EA_RATIO_RANGE
_OFFSET_DEG = math.degrees(TRUTH_OFFSET_MAX_RAD)
# fmt: off
RANGES: Mapping[str, Spec] = {
    # of the deviation from the description's link length (and the length > 0)
    "links_mm": Spec(
        -TRUTH_LINK_MAX_DEVIATION_MM, TRUTH_LINK_MAX_DEVIATION_MM, unit="mm",
        why=f"mm is more than {TRUTH_LINK_MAX_DEVIATION_MM:g} mm from the description's link",
    ),
    "alpha_offset_rad": Spec(
        -TRUTH_OFFSET_MAX_RAD, TRUTH_OFFSET_MAX_RAD, unit="rad",
        why=f"rad is beyond +-{_OFFSET_DEG:g} deg",
    ),
    "theta_offset_rad": Spec(
        -TRUTH_OFFSET_MAX_RAD, TRUTH_OFFSET_MAX_RAD, unit="rad",
        why=f"rad is beyond +-{_OFFSET_DEG:g} deg",
    ),
    "motor_zero_counts": Spec(
        -TRUTH_ZERO_MAX_COUNTS, TRUTH_ZERO_MAX_COUNTS, unit="counts",
        why=f"is beyond +-{TRUTH_ZERO_MAX_COUNTS} counts",
    ),
    # of the ratio to the description's EA
    "rope_EA_N": Spec(
        _EA_LO, _EA_HI, why=f"N is outside {_EA_LO:g}..{_EA_HI:g} x the description's EA"
    ),
    "slack_mm": Spec(
        0.0, TRUTH_SLACK_MAX_MM, unit="mm", why=f"mm is outside [0, {TRUTH_SLACK_MAX_MM:g}] mm"
    ),
    # of |t|
    "tracker.translation_mm": Spec(
        0.0, TRUTH_TRACKER_MAX_DISTANCE_MM, unit="mm",
        why=f"mm is beyond {TRUTH_TRACKER_MAX_DISTANCE_MM:g} mm",
    ),
    "tracker.noise_mm": Spec(
        0.0, TRUTH_TRACKER_NOISE_MAX_MM, unit="mm",
        why=f"outside [0, {TRUTH_TRACKER_NOISE_MAX_MM:g}] mm",
    ),
}
# fmt: on
"""The range of every number of a truth file, by key (:class:`hrm_ctrl.validate.Spec`;
for ``links_mm`` of the deviation from the description, for ``rope_EA_N`` of the ratio to
it, for ``tracker.translation_mm`` of ``|t|``); ``why`` follows the value in a message."""

TRACKER_NOISE_MM = 0.05
# The default tracker placement: standing 2.5 m from the base, to the side of the arm's
# straight direction (+x0), level, turned 30 deg about the vertical.
DEFAULT_TRACKER_POSITION_MM = (1000.0, -2300.0, -300.0)  # its origin in the base frame
DEFAULT_TRACKER_YAW_RAD = math.radians(30.0)

_TOP_KEYS = frozenset(
    {
        "format",
        "links_mm",
        "alpha_offset_rad",
        "theta_offset_rad",
        "motor_zero_counts",
        "rope_EA_N",
        "slack_mm",
        "tracker",
    }
)
_TRACKER_KEYS = frozenset({"rotation", "translation_mm", "noise_mm"})


class TruthFileError(SimError):
    """A truth file (``--truth``) is missing, malformed or out of range."""


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def tracker_frame(
    position_mm: Any, yaw_rad: float, tilt_rad: tuple[float, float] = (0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of a tracker standing at ``position_mm`` (its origin, base frame), its
    axes the base's turned by ``yaw_rad`` about the vertical (then tilted about x, y):
    ``p_tracker = R p_base + t`` with ``R = Rot^T``, ``t = -R position``.

    >>> R, t = tracker_frame([1000.0, 0.0, 0.0], 0.0)
    >>> (R @ np.array([1000.0, 0.0, 0.0]) + t).tolist()     # its own origin
    [0.0, 0.0, 0.0]
    """
    rot = _rot_z(yaw_rad) @ _rot_x(tilt_rad[0]) @ _rot_y(tilt_rad[1])  # tracker axes in base
    R = rot.T
    return R, -R @ np.asarray(position_mm, dtype=float)


@dataclass(frozen=True, eq=False)
class TrueArm:
    """The simulated arm's truth (see the module docstring); arrays read-only."""

    motor_ids: tuple[str, ...]
    links_mm: np.ndarray  # (12,)
    alpha_offset_rad: np.ndarray  # (12,)
    theta_offset_rad: np.ndarray  # (12,)
    rope_EA_N: np.ndarray  # (n,)
    motor_zero_counts: np.ndarray  # (n,) int64
    slack_mm: np.ndarray  # (n,)
    tracker_rotation: np.ndarray  # (3, 3)
    tracker_translation_mm: np.ndarray  # (3,)
    tracker_noise_mm: float = TRACKER_NOISE_MM
    source: str = "<nominal>"

    def __post_init__(self) -> None:
        n = len(self.motor_ids)
        put = object.__setattr__
        put(self, "motor_ids", tuple(self.motor_ids))
        for key, shape, dtype in (
            ("links_mm", (N_JOINTS,), float),
            ("alpha_offset_rad", (N_JOINTS,), float),
            ("theta_offset_rad", (N_JOINTS,), float),
            ("rope_EA_N", (n,), float),
            ("motor_zero_counts", (n,), np.int64),
            ("slack_mm", (n,), float),
            ("tracker_rotation", (3, 3), float),
            ("tracker_translation_mm", (3,), float),
        ):
            arr = np.array(getattr(self, key), dtype=dtype)
            if arr.shape != shape:
                raise SimError(f"{self.source}: {key} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise SimError(f"{self.source}: {key} must be finite")
            arr.setflags(write=False)
            put(self, key, arr)
        put(self, "tracker_noise_mm", float(self.tracker_noise_mm))

    @property
    def n_motors(self) -> int:
        return len(self.motor_ids)

    # ---- constructors ---------------------------------------------------------------------

    @classmethod
    def nominal(cls, actuation: Actuation) -> TrueArm:
        """The robot description itself: the arm the simulator had before issue 12 (the
        tracker at its default placement)."""
        n = actuation.n_motors
        R, t = tracker_frame(DEFAULT_TRACKER_POSITION_MM, DEFAULT_TRACKER_YAW_RAD)
        return cls(
            motor_ids=actuation.motor_ids,
            links_mm=np.asarray(actuation.robot.links, dtype=float),
            alpha_offset_rad=np.zeros(N_JOINTS),
            theta_offset_rad=np.zeros(N_JOINTS),
            rope_EA_N=_description_EA(actuation),
            motor_zero_counts=np.zeros(n, dtype=np.int64),
            slack_mm=np.zeros(n),
            tracker_rotation=R,
            tracker_translation_mm=t,
        )

    @classmethod
    def perturbed(cls, actuation: Actuation, seed: int, *, max_slack_mm: float = 0.0) -> TrueArm:
        """A truth drawn from ``seed`` (``numpy.random.default_rng``), uniformly within
        :data:`PERTURB_LINK_MM`, :data:`PERTURB_OFFSET_RAD`, :data:`PERTURB_EA_FRACTION` and
        :data:`PERTURB_ZERO_COUNTS` of the description; slack uniform in
        ``[0, max_slack_mm]`` per rope (default none); the tracker 2-3 m from the base at
        a random bearing and height +- 0.5 m, turned at random about the vertical and
        tilted up to 2 deg.  The same seed and actuation give the same truth."""
        if not (math.isfinite(max_slack_mm) and 0.0 <= max_slack_mm <= TRUTH_SLACK_MAX_MM):
            raise SimError(
                f"max_slack_mm must be in [0, {TRUTH_SLACK_MAX_MM:g}], got {max_slack_mm}"
            )
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise SimError(f"a perturbation seed must be an integer >= 0, got {seed!r}")
        rng = np.random.default_rng(seed)
        n = actuation.n_motors
        links = np.asarray(actuation.robot.links, float) + rng.uniform(
            -PERTURB_LINK_MM, PERTURB_LINK_MM, N_JOINTS
        )
        da = rng.uniform(-PERTURB_OFFSET_RAD, PERTURB_OFFSET_RAD, N_JOINTS)
        dt = rng.uniform(-PERTURB_OFFSET_RAD, PERTURB_OFFSET_RAD, N_JOINTS)
        ea = _description_EA(actuation) * (
            1.0 + rng.uniform(-PERTURB_EA_FRACTION, PERTURB_EA_FRACTION, n)
        )
        zero = rng.integers(-PERTURB_ZERO_COUNTS, PERTURB_ZERO_COUNTS, n, endpoint=True)
        slack = rng.uniform(0.0, 1.0, n) * max_slack_mm
        bearing = rng.uniform(-math.pi, math.pi)
        distance = rng.uniform(2000.0, 3000.0)
        centre = np.array([0.5 * float(actuation.robot.length), 0.0, 0.0])
        pos = centre + np.array([distance * math.cos(bearing), distance * math.sin(bearing), 0.0])
        pos[2] = rng.uniform(-500.0, 500.0)
        yaw = rng.uniform(-math.pi, math.pi)
        tilt = rng.uniform(-math.radians(2.0), math.radians(2.0), 2)
        R, t = tracker_frame(pos, yaw, (float(tilt[0]), float(tilt[1])))
        return cls(
            motor_ids=actuation.motor_ids,
            links_mm=links,
            alpha_offset_rad=da,
            theta_offset_rad=dt,
            rope_EA_N=ea,
            motor_zero_counts=zero.astype(np.int64),
            slack_mm=slack,
            tracker_rotation=R,
            tracker_translation_mm=t,
            source=f"<perturbed seed {seed}>",
        )

    def replace(self, **changes: Any) -> TrueArm:
        """A copy with some fields changed (checked again), e.g. ``slack_mm=...``."""
        return dataclasses.replace(self, **changes)

    # ---- uses ----------------------------------------------------------------------------

    def model(self, robot: RobotModel) -> RobotModel:
        """``robot`` with the true link lengths (what the simulator's FK uses)."""
        return dataclasses.replace(robot, links=self.links_mm)

    def to_tracker(self, points_mm: Any) -> np.ndarray:
        """Base-frame points (..., 3) in the tracker's frame, ``R p + t`` (no noise).

        >>> from hrm_ctrl.model import default_robot
        >>> from hrm_ctrl.ropes.actuation import load_actuation
        >>> t = TrueArm.nominal(load_actuation(default_robot()))
        >>> bool(np.allclose(t.to_tracker(DEFAULT_TRACKER_POSITION_MM), 0.0))   # its origin
        True
        >>> 2000.0 < float(np.linalg.norm(t.to_tracker([0.0, 0.0, 0.0]))) < 3000.0
        True
        """
        p = np.asarray(points_mm, dtype=float)
        return p @ self.tracker_rotation.T + self.tracker_translation_mm

    def host_zero_counts(self, actuation: Actuation) -> np.ndarray:
        """The motor zeros (n,) int64 in the host rope layer's convention: the count at
        which rope m is at its pretension with the rope geometry straight (phi = 0; the
        physical angle is then the joint's offset), with the slack taken up.

        ``motor_zero_counts`` is defined at that same pose (``sim_bus.arm``: the zero
        fixture clamps the rope disks coaxial), so the two differ only by the slack,
        ``direction counts_per_mm slack``.  ``actuation``: the rope layer of the true arm,
        ``load_actuation(truth.model(robot))``, no calibration in it.
        """
        m = actuation.motors
        z = self.motor_zero_counts + m.direction * m.counts_per_mm * self.slack_mm
        return np.rint(z).astype(np.int64)

    def ideal_actuation(self, robot: RobotModel) -> Actuation:
        """The rope layer a perfect calibration would give the host: the true EAs, joint
        offsets, link lengths and motor zeros (:meth:`host_zero_counts`) in
        ``load_actuation`` (as ``calibration.apply.calibrated_actuation`` builds it).  Its
        ``counts_from_angles(q)`` puts the simulated arm's physical joints at ``q`` (to the
        counts' quantisation)."""
        true_robot = self.model(robot)
        zero = self.host_zero_counts(load_actuation(true_robot))
        return load_actuation(
            true_robot,
            {m: int(z) for m, z in zip(self.motor_ids, zero, strict=True)},
            rope_EA_N=self.rope_EA_N,
            alpha_offset_rad=self.alpha_offset_rad,
            theta_offset_rad=self.theta_offset_rad,
        )

    def is_nominal(self, actuation: Actuation) -> bool:
        """Whether the arm is its description (the tracker's frame not considered)."""
        return bool(
            np.array_equal(self.links_mm, np.asarray(actuation.robot.links, float))
            and not self.alpha_offset_rad.any()
            and not self.theta_offset_rad.any()
            and np.array_equal(self.rope_EA_N, _description_EA(actuation))
            and not self.motor_zero_counts.any()
            and not self.slack_mm.any()
        )

    def to_dict(self) -> dict[str, Any]:
        """The truth as a truth file's content (plain TOML/JSON types, floats exact)."""
        ids = self.motor_ids
        return {
            "format": TRUTH_FORMAT,
            "links_mm": self.links_mm.tolist(),
            "alpha_offset_rad": self.alpha_offset_rad.tolist(),
            "theta_offset_rad": self.theta_offset_rad.tolist(),
            "motor_zero_counts": {
                m: int(v) for m, v in zip(ids, self.motor_zero_counts, strict=True)
            },
            "rope_EA_N": {m: float(v) for m, v in zip(ids, self.rope_EA_N, strict=True)},
            "slack_mm": {m: float(v) for m, v in zip(ids, self.slack_mm, strict=True)},
            "tracker": {
                "rotation": self.tracker_rotation.tolist(),
                "translation_mm": self.tracker_translation_mm.tolist(),
                "noise_mm": self.tracker_noise_mm,
            },
        }


def drive_serials(truth: TrueArm) -> dict[str, int]:
    """The serial number (0x1018:4) each simulated drive of ``truth``'s arm reports: from
    the SHA-256 of the arm's truth (all of it but the laser tracker's frame, which is not
    the box) and the motor id, so that another truth (a perturbed arm) is another box.
    Never 0 (the EDS's default).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.actuation import load_actuation
    >>> act = load_actuation(default_robot())
    >>> a, b = drive_serials(TrueArm.nominal(act)), drive_serials(TrueArm.perturbed(act, 3))
    >>> len(a), a == drive_serials(TrueArm.nominal(act)), a["j01r0"] == b["j01r0"]
    (36, True, False)
    """
    doc = truth.to_dict()
    del doc["tracker"]
    arm = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode("ascii")
    out = {}
    for motor in truth.motor_ids:
        digest = hashlib.sha256(arm + b"\0" + motor.encode("ascii")).digest()
        out[motor] = int.from_bytes(digest[:4], "big") or 1
    return out


def _description_EA(actuation: Actuation) -> np.ndarray:
    return np.broadcast_to(
        np.asarray(actuation.routing.stiffness_EA_N, dtype=float), (actuation.n_motors,)
    ).copy()


# ---- the truth file --------------------------------------------------------------------------


def _fail(source: str, key: str, why: str) -> TruthFileError:
    return TruthFileError(f"{source}: {key}: {why}")


def _number(v: Any, source: str, key: str) -> float:
    return number(v, f"{source}: {key}", TruthFileError)


def _vector(v: Any, n: int, source: str, key: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        got = f"{len(v)} values" if isinstance(v, list) else repr(v)
        raise _fail(source, key, f"expected a list of {n} numbers, got {got}")
    return np.array([float(_number(x, source, f"{key}[{i}]")) for i, x in enumerate(v)])


def _per_motor(
    v: Any, ids: tuple[str, ...], default: np.ndarray, source: str, key: str
) -> np.ndarray:
    if not isinstance(v, Mapping):
        raise _fail(source, key, "expected a table of motor id = value")
    out = default.copy()
    for m, x in v.items():
        if m not in ids:
            raise _fail(source, f"{key}.{m}", f"unknown rope motor (have {ids[0]} .. {ids[-1]})")
        where = f"{key}.{m}"
        if out.dtype.kind == "i" and (isinstance(x, bool) or not isinstance(x, int)):
            raise _fail(source, where, f"expected an integer count, got {x!r}")
        out[ids.index(m)] = _number(x, source, where)
    return out


def _check_range(
    key: str, values: np.ndarray, measure: np.ndarray, source: str, names: Any = None
) -> None:
    """Every ``measure`` (of ``values``: the values themselves, their deviation or ratio)
    within ``RANGES[key]``; else the first value outside, named by motor or index."""
    s = RANGES[key]
    bad = np.flatnonzero(~s.inside(measure))
    if bad.size:
        i = int(bad[0])
        where = f"{key}.{names[i]}" if names else f"{key}[{i}]"
        raise _fail(source, where, f"{values[i]!r} {s.why}")


def truth_from_dict(doc: Mapping[str, Any], actuation: Actuation, source: str) -> TrueArm:
    """A :class:`TrueArm` from a truth file's content; every key optional (missing: the
    description's value, the default tracker), per-motor tables may name some motors only.
    Any problem raises :class:`TruthFileError` naming ``source`` and the key."""
    if not isinstance(doc, Mapping):
        raise TruthFileError(f"{source}: a truth file must be a TOML table")
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise _fail(source, unknown[0], f"unknown key{unknown_key(unknown[0], _TOP_KEYS)}")
    if "format" in doc and doc["format"] != TRUTH_FORMAT:
        raise _fail(source, "format", f"expected {TRUTH_FORMAT!r}, got {doc['format']!r}")
    nom = TrueArm.nominal(actuation)
    ids = nom.motor_ids
    desc_links = np.asarray(actuation.robot.links, dtype=float)
    links = (
        _vector(doc["links_mm"], N_JOINTS, source, "links_mm")
        if "links_mm" in doc
        else (desc_links.copy())
    )
    # a length must stay > 0 whatever its deviation: a length <= 0 measures as outside
    _check_range("links_mm", links, np.where(links > 0, links - desc_links, np.nan), source)
    offsets = {}
    for key in ("alpha_offset_rad", "theta_offset_rad"):
        v = _vector(doc[key], N_JOINTS, source, key) if key in doc else np.zeros(N_JOINTS)
        _check_range(key, v, v, source)
        offsets[key] = v
    per_motor = {}
    for key in ("motor_zero_counts", "rope_EA_N", "slack_mm"):
        v = getattr(nom, key)
        per_motor[key] = _per_motor(doc[key], ids, v, source, key) if key in doc else v.copy()
    zero, ea, slack = per_motor["motor_zero_counts"], per_motor["rope_EA_N"], per_motor["slack_mm"]
    _check_range("motor_zero_counts", zero, zero, source, ids)
    _check_range("rope_EA_N", ea, ea / nom.rope_EA_N, source, ids)
    _check_range("slack_mm", slack, slack, source, ids)
    R, t, noise = nom.tracker_rotation, nom.tracker_translation_mm, nom.tracker_noise_mm
    if "tracker" in doc:
        R, t, noise = _tracker_from(doc["tracker"], (R, t, noise), source)
    return TrueArm(
        motor_ids=ids,
        links_mm=links,
        alpha_offset_rad=offsets["alpha_offset_rad"],
        theta_offset_rad=offsets["theta_offset_rad"],
        rope_EA_N=ea,
        motor_zero_counts=zero,
        slack_mm=slack,
        tracker_rotation=R,
        tracker_translation_mm=t,
        tracker_noise_mm=noise,
        source=source,
    )


def _tracker_from(doc: Any, default: tuple, source: str) -> tuple[np.ndarray, np.ndarray, float]:
    if not isinstance(doc, Mapping):
        raise _fail(source, "tracker", "expected a table")
    unknown = sorted(set(doc) - _TRACKER_KEYS)
    if unknown:
        hint = unknown_key(unknown[0], _TRACKER_KEYS)
        raise _fail(source, f"tracker.{unknown[0]}", f"unknown key{hint}")
    R, t, noise = default
    if "rotation" in doc:
        rows = doc["rotation"]
        if not isinstance(rows, list) or len(rows) != 3:
            raise _fail(source, "tracker.rotation", "expected 3 rows of 3 numbers")
        R = np.stack([_vector(r, 3, source, f"tracker.rotation[{i}]") for i, r in enumerate(rows)])
        with np.errstate(all="ignore"):  # entries of 1e300: off by inf, no warning
            err = max(float(np.abs(R.T @ R - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1))
        if not err <= ROTATION_TOLERANCE:  # NaN too
            raise _fail(
                source,
                "tracker.rotation",
                f"not a rotation (orthonormal, det +1) within {ROTATION_TOLERANCE:g} "
                f"(off by {err:.3g})",
            )
    if "translation_mm" in doc:
        key = "tracker.translation_mm"
        t = _vector(doc["translation_mm"], 3, source, key)
        with np.errstate(over="ignore"):  # |t| of 1e300 entries: inf, refused below
            distance = float(np.linalg.norm(t))
        if not RANGES[key].inside(distance):
            raise _fail(source, key, f"|t| = {distance:.6g} {RANGES[key].why}")
    if "noise_mm" in doc:
        key = "tracker.noise_mm"
        noise = float(_number(doc["noise_mm"], source, key))
        if not RANGES[key].inside(noise):
            raise _fail(source, key, f"{noise!r} {RANGES[key].why}")
    return R, t, noise


def read_truth(path: str | Path, actuation: Actuation) -> TrueArm:
    """Read a truth file (``hrm-sim-truth/1``, TOML; ``docs/sim.md``) for ``actuation``'s
    arm.  Unknown keys, wrong lengths, non-numbers, NaN and values outside the
    ranges (:data:`RANGES`) raise :class:`TruthFileError` naming the file and the key."""
    doc, source = read_toml(path, TruthFileError, "truth file")
    return truth_from_dict(doc, actuation, source)


# ---- writing ---------------------------------------------------------------------------------


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)  # the shortest text that reads back to the same float
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise SimError(f"cannot write {v!r} to TOML")


def truth_to_toml(truth: TrueArm) -> str:
    """The truth file's text (floats written so that they read back bit for bit)."""
    doc = truth.to_dict()
    lines = [
        # the source escaped as in a JSON string: a newline in a path stays in the comment
        f"# simulated arm truth ({json.dumps(truth.source, ensure_ascii=False)[1:-1]}); "
        "the format is in docs/sim.md",
    ]
    tables = []
    for key, v in doc.items():
        if isinstance(v, Mapping):
            tables.append((key, v))
        else:
            lines.append(f"{key} = {_toml_value(v)}")
    for key, table in tables:
        lines += ["", f"[{key}]"]
        lines += [f"{k} = {_toml_value(x)}" for k, x in table.items()]
    return "\n".join(lines) + "\n"


def write_truth(path: str | Path, truth: TrueArm) -> None:
    """Write ``truth`` as a truth file, atomically (a reader sees the old file or the new
    one).  Raises :class:`TruthFileError` if it cannot be written."""
    try:
        write_atomic(path, truth_to_toml(truth))
    except OSError as exc:
        raise TruthFileError(f"{path}: cannot write truth file ({exc})") from None
