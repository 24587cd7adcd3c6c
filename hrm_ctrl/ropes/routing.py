"""Rope routing: which ropes drive which joint and where their holes are.

Every joint k (1..12) is driven by ``n_k`` ropes (default 3 at 120 degrees; 4 works
too).  A rope of joint k leaves its motor in the box, runs parallel to the arm's
axis through a hole in the proximal and distal disk of every joint 1..k, and is
anchored on the distal disk of joint k.  Inside a link a rope keeps its angular
position, so one angle ``phi`` and the hole-circle radius ``r`` describe the
rope's hole in every disk it passes.  Around joint j the proximal disk sits at
``z = -d_p[j]`` in the frame before the joint and the distal disk at
``z = +d_d[j]`` in the frame after it.

The ``[ropes]`` table of the robot description (all optional, defaults below):

* ``per_joint``: ropes per joint, an int or a list of 12 ints (2..8); default 3.
* ``hole_radius_mm``: radius of the hole circle; default 12.0.
* ``hole_diameter_mm``: diameter of a hole; default 1.2.
* ``proximal_disk_mm`` / ``distal_disk_mm``: axial distances of the disks from
  the joint centre, a number or a list of 12; default 12.0 each.
* ``first_angle_deg`` and ``joint_step_deg``: rope m of joint k (0-based) sits at
  ``first + k * step + m * 360 / n_k`` degrees from the link's x axis towards y;
  defaults 0 and ``360 / (12 * max n_k)`` (10 degrees for 3 ropes), so the 36
  holes are evenly spread and no two ropes share a hole.
* ``angles_deg``: optional explicit list of 12 lists (one angle per rope),
  replacing the formula above.
* ``stiffness_EA_N``, ``box_length_mm``, ``pretension_N``: rope stiffness (axial
  rigidity EA), the free length of rope inside the box between drum and arm base,
  and the tension at which the zero (calibration) position is defined.
* ``command_tension_N``: ``[low, high]``, the rope tension the rope layer's model
  (:meth:`~hrm_ctrl.ropes.actuation.Actuation.tensions_from_counts`) may give a
  commanded move that is not a plan (a lead-in, a jog, a stop); default a third and
  four times the pretension (at least the pretension + 20 N): 10 and 120 N, inside the
  tension board's watch of 5 and 150 N.  Safe range: ``0 <= low <= pretension <= high
  <= 650`` N (the board saturates at 655 N; a pretension above that is its own top).

>>> from hrm_ctrl.model import default_robot
>>> rt = routing_from_model(default_robot())
>>> rt.n_ropes, rt.rope_ids[:4], rt.rope_ids[-1]
(36, ('j01r0', 'j01r1', 'j01r2', 'j02r0'), 'j12r2')
>>> [round(float(a), 1) for a in np.rad2deg(rt.hole_angle[:4])]
[0.0, 120.0, 240.0, 10.0]
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hrm_ctrl.errors import RopeError
from hrm_ctrl.model import RobotModel

DEFAULT_PER_JOINT = 3
DEFAULT_HOLE_RADIUS_MM = 12.0
DEFAULT_HOLE_DIAMETER_MM = 1.2
DEFAULT_DISK_MM = 12.0
DEFAULT_EA_N = 30_000.0
DEFAULT_BOX_LENGTH_MM = 500.0
DEFAULT_PRETENSION_N = 30.0
MAX_PER_JOINT = 8
MAX_COMMAND_TENSION_N = 650.0  # the tension board reads up to 655.34 N


class RoutingError(RopeError):
    """The ``[ropes]`` routing is malformed (shared hole, hole off the disk, ...)."""


@dataclass(frozen=True, eq=False)
class RopeRouting:
    """Validated rope routing; arrays are read-only, ropes ordered by joint.

    Attributes:
        rope_ids: ``"jKKrM"`` per rope (joint KK 1-based, rope M 0-based).
        joint_of_rope: (n,) 0-based joint each rope is anchored past.
        hole_angle: (n,) angular position of each rope's holes (rad).
        hole_radius: (n,) radius of each rope's hole circle (mm).
        hole_diameter: diameter of a hole (mm).
        proximal_disk: (12,) axial distance of joint j's proximal disk (mm).
        distal_disk: (12,) axial distance of joint j's distal disk (mm).
        stiffness_EA_N: (n,) axial rigidity EA of each rope (N).
        box_length: (n,) free rope length inside the box, drum to base (mm).
        pretension_N: tension at which the zero position is defined (N).
        in_link: (n,) length of each rope inside the links, from the distal disk of
            joint j to the proximal disk of joint j+1, summed over the links it
            passes: constant, ``sum_{j<k} (l_j - d_d[j] - d_p[j+1])`` (mm).
    """

    rope_ids: tuple[str, ...]
    joint_of_rope: np.ndarray
    hole_angle: np.ndarray
    hole_radius: np.ndarray
    hole_diameter: float
    proximal_disk: np.ndarray
    distal_disk: np.ndarray
    stiffness_EA_N: np.ndarray
    box_length: np.ndarray
    pretension_N: float
    in_link: np.ndarray  # (n,) rope length inside the links, between the joints' disks (mm)
    # (low, high) N: the modelled tension a lead-in, jog or stop may give a rope
    command_tension_N: tuple[float, float] = (10.0, 120.0)

    @property
    def n_ropes(self) -> int:
        return len(self.rope_ids)


def rope_id(joint: int, rope: int) -> str:
    """Id of rope ``rope`` (0-based) of joint ``joint`` (0-based).

    >>> rope_id(0, 2), rope_id(11, 0)
    ('j01r2', 'j12r0')
    """
    return f"j{joint + 1:02d}r{rope}"


#: upper bounds of the [ropes] numbers: far beyond any arm of this kind, far below what
#: would overflow the rope model (a typo, not a rope)
MAX_GEOMETRY_MM = 1.0e4  # hole circle, hole, disk thickness, box length: 10 m
MAX_EA_N = 1.0e9  # a 30 mm steel rod: 1.4e8 N
#: the softest rope taken: 1 % stretch under 10 N (a 1 mm Dyneema or steel rope is
#: 5e4-8e4 N; below this the rope model's stretch, not the geometry, sets the lengths)
MIN_EA_N = 1.0e3
MAX_PRETENSION_N = 1.0e5  # 10 t


def _num(
    value: Any,
    where: str,
    *,
    positive: bool = False,
    minimum: float | None = None,
    maximum: float | None = None,
) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RoutingError(f"{where}: expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise RoutingError(f"{where}: expected a finite number, got {value!r}")
    if positive and x <= 0.0:
        raise RoutingError(f"{where}: must be > 0, got {value!r}")
    if minimum is not None and x < minimum:
        raise RoutingError(f"{where}: must be >= {minimum}, got {value!r}")
    if maximum is not None and x > maximum:
        raise RoutingError(f"{where}: must be <= {maximum:g}, got {value!r}")
    return x


def _per_joint(value: Any, n: int, where: str, *, positive: bool = True) -> np.ndarray:
    top = MAX_GEOMETRY_MM
    if isinstance(value, list):
        if len(value) != n:
            raise RoutingError(f"{where}: list must have {n} values, got {len(value)}")
        return np.array(
            [_num(v, f"{where}[{i}]", positive=positive, maximum=top) for i, v in enumerate(value)]
        )
    return np.full(n, _num(value, where, positive=positive, maximum=top))


def _counts(value: Any, n: int, where: str) -> list[int]:
    raw = value if isinstance(value, list) else [value] * n
    if len(raw) != n:
        raise RoutingError(f"{where}: list must have {n} values, got {len(raw)}")
    out = []
    for i, v in enumerate(raw):
        if isinstance(v, bool) or not isinstance(v, int) or not 2 <= v <= MAX_PER_JOINT:
            raise RoutingError(f"{where}[{i}]: ropes per joint must be an int in 2..8, got {v!r}")
        out.append(v)
    return out


def default_spread(per_joint: Sequence[int], first_deg: float = 0.0) -> list[list[float]]:
    """Default hole angles (deg): all ropes on evenly spaced slots, each joint's ropes as
    close as the free slots allow to ``first + k * 360 / (12 n_max) + m * 360 / n_k``.

    With the same number of ropes on every joint this is exactly that formula
    (10 degree steps for 3 ropes, 7.5 for 4); with mixed numbers no slot is shared.

    >>> default_spread([3, 3], 0.0)
    [[0.0, 120.0, 240.0], [60.0, 180.0, 300.0]]
    """
    n_j, total = len(per_joint), sum(per_joint)
    slot = 360.0 / total
    step = 360.0 / (n_j * max(per_joint))
    free = np.ones(total, dtype=bool)
    out: list[list[float]] = []
    for k, n_k in enumerate(per_joint):
        row = []
        for m in range(n_k):
            ideal = (k * step + m * 360.0 / n_k) / slot
            dist = np.abs((np.arange(total) - ideal + total / 2.0) % total - total / 2.0)
            i = int(np.argmin(np.where(free, dist, np.inf)))
            free[i] = False
            row.append(first_deg + i * slot)
        out.append(row)
    return out


def routing_from_table(
    table: Mapping[str, Any],
    outer_diameter: np.ndarray,
    source: str = "[ropes]",
    links: np.ndarray | None = None,
) -> RopeRouting:
    """Validate a ``[ropes]`` table (may be empty: defaults) and build the routing."""
    where = f"{source}: [ropes]"
    if not isinstance(table, Mapping):
        raise RoutingError(f"{where} must be a table")
    known = {
        "per_joint",
        "hole_radius_mm",
        "hole_diameter_mm",
        "proximal_disk_mm",
        "distal_disk_mm",
        "first_angle_deg",
        "joint_step_deg",
        "angles_deg",
        "stiffness_EA_N",
        "box_length_mm",
        "pretension_N",
        "command_tension_N",
    }
    for key in table:
        if key not in known:
            raise RoutingError(f"{where}: unknown key {key!r}")
    n_j = int(outer_diameter.shape[0])
    per = _counts(table.get("per_joint", DEFAULT_PER_JOINT), n_j, f"{where}.per_joint")
    radius = _num(
        table.get("hole_radius_mm", DEFAULT_HOLE_RADIUS_MM),
        f"{where}.hole_radius_mm",
        positive=True,
        maximum=MAX_GEOMETRY_MM,
    )
    hole_d = _num(
        table.get("hole_diameter_mm", DEFAULT_HOLE_DIAMETER_MM),
        f"{where}.hole_diameter_mm",
        positive=True,
        maximum=MAX_GEOMETRY_MM,
    )
    d_p = _per_joint(
        table.get("proximal_disk_mm", DEFAULT_DISK_MM), n_j, f"{where}.proximal_disk_mm"
    )
    d_d = _per_joint(table.get("distal_disk_mm", DEFAULT_DISK_MM), n_j, f"{where}.distal_disk_mm")
    ea = _num(
        table.get("stiffness_EA_N", DEFAULT_EA_N),
        f"{where}.stiffness_EA_N",
        minimum=MIN_EA_N,
        maximum=MAX_EA_N,
    )
    box = _num(
        table.get("box_length_mm", DEFAULT_BOX_LENGTH_MM),
        f"{where}.box_length_mm",
        minimum=0.0,
        maximum=MAX_GEOMETRY_MM,
    )
    pre = _num(
        table.get("pretension_N", DEFAULT_PRETENSION_N),
        f"{where}.pretension_N",
        minimum=0.0,
        maximum=MAX_PRETENSION_N,
    )

    if "angles_deg" in table:
        raw = table["angles_deg"]
        if not isinstance(raw, list) or len(raw) != n_j:
            raise RoutingError(f"{where}.angles_deg: must be a list of {n_j} lists")
        angles: list[list[float]] = []
        for k, row in enumerate(raw):
            if not isinstance(row, list) or len(row) != per[k]:
                raise RoutingError(
                    f"{where}.angles_deg[{k}]: joint {k + 1} needs {per[k]} angles, got {row!r}"
                )
            angles.append([_num(v, f"{where}.angles_deg[{k}][{m}]") for m, v in enumerate(row)])
    else:
        first = _num(table.get("first_angle_deg", 0.0), f"{where}.first_angle_deg")
        if "joint_step_deg" in table:
            step = _num(table["joint_step_deg"], f"{where}.joint_step_deg")
            angles = [
                [first + k * step + m * 360.0 / per[k] for m in range(per[k])] for k in range(n_j)
            ]
        else:
            angles = default_spread(per, first)

    ids: list[str] = []
    joint: list[int] = []
    phi: list[float] = []
    for k in range(n_j):
        for m in range(per[k]):
            ids.append(rope_id(k, m))
            joint.append(k)
            phi.append(math.radians(angles[k][m]) % (2.0 * math.pi))
    phi_a = np.array(phi)
    joint_a = np.array(joint, dtype=np.int64)
    r_a = np.full(len(ids), radius)
    _check_holes(ids, joint_a, phi_a, r_a, hole_d, outer_diameter, where)
    inside = np.zeros(n_j)
    if links is not None:
        inside = np.asarray(links, dtype=float)[:-1] - d_d[:-1] - d_p[1:]
        if np.any(inside <= 0.0):
            j = int(np.flatnonzero(inside <= 0.0)[0])
            raise RoutingError(
                f"{where}: link {j + 1} ({float(links[j]):g} mm) is shorter than the disks "
                f"of joints {j + 1} and {j + 2} ({d_d[j]:g} + {d_p[j + 1]:g} mm)"
            )
    in_link = np.concatenate([[0.0], np.cumsum(inside)])[joint_a]

    arrays = {
        "joint_of_rope": joint_a,
        "hole_angle": phi_a,
        "hole_radius": r_a,
        "proximal_disk": d_p,
        "distal_disk": d_d,
        "stiffness_EA_N": np.full(len(ids), ea),
        "box_length": np.full(len(ids), box),
        "in_link": in_link,
    }
    for arr in arrays.values():
        arr.setflags(write=False)
    band = _command_tension(table.get("command_tension_N"), pre, f"{where}.command_tension_N")
    return RopeRouting(
        rope_ids=tuple(ids), hole_diameter=hole_d, pretension_N=pre, command_tension_N=band,
        **arrays,
    )  # fmt: skip


def default_command_tension(pretension_N: float) -> tuple[float, float]:
    """The ``command_tension_N`` of a rope layer that does not give one: a third and four
    times the pretension, the top at least 20 N above it.

    >>> default_command_tension(30.0)
    (10.0, 120.0)
    """
    high = min(max(4.0 * pretension_N, pretension_N + 20.0), MAX_COMMAND_TENSION_N)
    return pretension_N / 3.0, max(high, pretension_N)  # (a pretension above 650 N: itself)


def _command_tension(raw: Any, pretension_N: float, where: str) -> tuple[float, float]:
    """``[low, high]`` (N) checked against its safe range (module docstring)."""
    if raw is None:
        low, high = default_command_tension(pretension_N)
    else:
        if not isinstance(raw, list) or len(raw) != 2:
            raise RoutingError(f"{where}: must be [low, high] in N, got {raw!r}")
        top = max(MAX_COMMAND_TENSION_N, pretension_N)
        low = _num(raw[0], f"{where}[0]", minimum=0.0, maximum=top)
        high = _num(raw[1], f"{where}[1]", minimum=0.0, maximum=top)
    if not low <= pretension_N <= high:
        raise RoutingError(
            f"{where}: [{low:g}, {high:g}] N must hold the pretension of {pretension_N:g} N"
        )
    return float(low), float(high)


def _check_holes(
    ids: Sequence[str],
    joint: np.ndarray,
    phi: np.ndarray,
    r: np.ndarray,
    hole_d: float,
    outer_diameter: np.ndarray,
    where: str,
) -> None:
    """No hole off the disk; no two ropes through the same disk closer than a hole."""
    for i in range(len(ids)):
        # A rope of joint k passes the disks of joints 1..k; the tightest is the thinnest.
        od = float(outer_diameter[: joint[i] + 1].min())
        if r[i] + hole_d / 2.0 > od / 2.0:
            raise RoutingError(
                f"{where}: hole of rope {ids[i]} (radius {r[i]:g} mm + {hole_d / 2:g} mm) lies "
                f"outside the {od:g} mm disk"
            )
    xy = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)
    dist = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=-1)
    # Every pair of ropes meets in joint 1's disks (all ropes start at the base).
    close = np.argwhere(np.triu(dist < hole_d, k=1))
    if close.size:
        a, b = (int(v) for v in close[0])
        raise RoutingError(
            f"{where}: ropes {ids[a]} and {ids[b]} share a hole (centres {dist[a, b]:.3g} mm "
            f"apart, hole diameter {hole_d:g} mm)"
        )


def routing_from_model(model: RobotModel) -> RopeRouting:
    """The routing described by ``model.tables["ropes"]`` (defaults if absent)."""
    return routing_from_table(
        model.tables.get("ropes", {}), model.outer_diameter, model.source, model.links
    )
