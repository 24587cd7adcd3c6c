"""The arm as URDF, so other robotics tools (viewers, pinocchio, MoveIt) can load it.

Each universal joint i becomes two revolute joints, exactly as Eq. (1) composes
them: ``j{i}_alpha`` turns about the joint's y axis (the first rotation),
then ``j{i}_theta`` about the new x axis (the second).  Between them sits a
small dummy link ``cross{i}`` (the cross of the universal joint).  Link
``link{i}``'s frame is the paper's frame i (``kinematics.frames``): origin at the
joint centre O_i, z along the link.  The fixed part of Eq. (2),
``Rot_y(-pi/2) Rot_x(pi)``, is the origin of ``j1_alpha``; the base mounting
(``model.base_rotation``, ``model.base_position``) is the fixed joint
``base_mount`` from the root link ``world``.  A fixed joint puts the frame
``end_effector`` at the end point O_13.

URDF units are SI: lengths in metres (the model's mm / 1000), angles in rad.
Numbers are written with full double precision, so the file reproduces the
kinematics to rounding error.  The robot description carries no masses: each
link's inertial block is a solid cylinder of ``link_mass_kg_per_m`` (a nominal
placeholder, not a measured value) so that tools that require inertia accept
the file; effort and velocity limits are placeholders for the same reason.

>>> from hrm_ctrl.model import default_robot
>>> text = robot_urdf(default_robot())
>>> text.count('type="revolute"'), text.count("<link ")
(24, 27)
>>> '<joint name="j1_alpha" type="revolute">' in text
True
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from hrm_ctrl.errors import HrmError
from hrm_ctrl.files import write_atomic
from hrm_ctrl.model import RobotModel

MM_PER_M = 1000.0


class UrdfWriteError(HrmError):
    """The URDF file cannot be written."""


#: characters XML 1.0 does not allow in a document (control characters but tab and the
#: line ends, lone surrogates, U+FFFE and U+FFFF)
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


# Rot_y(-pi/2) Rot_x(pi) as URDF roll-pitch-yaw (R = Rz(yaw) Ry(pitch) Rx(roll)).
RPY_BASE_PAPER = (math.pi, -math.pi / 2, 0.0)

# Placeholders (the robot description has no masses, torques or speeds).
DEFAULT_LINK_MASS_KG_PER_M = 1.0
CROSS_MASS_KG = 1e-3
CROSS_INERTIA_KG_M2 = 1e-9
EFFORT_LIMIT_NM = 100.0
VELOCITY_LIMIT_RAD_PER_S = 1.0


def rotation_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw of a rotation matrix: ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Yaw and pitch come from the first column; roll from what is left once they
    are undone, which stays accurate near and at pitch = +-90 deg (gimbal lock).

    >>> from hrm_ctrl.kinematics import R_BASE_PAPER
    >>> r, p, y = rotation_rpy(R_BASE_PAPER)
    >>> bool(np.allclose(rpy_rotation(r, p, y), R_BASE_PAPER, atol=1e-15))
    True
    >>> [round(v, 6) for v in rotation_rpy(rpy_rotation(0.1, -0.2, 0.3))]
    [0.1, -0.2, 0.3]
    """
    R = np.asarray(R, dtype=float)
    c = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], c)
    yaw = math.atan2(R[1, 0], R[0, 0]) if c > 1e-12 else 0.0
    rest = _rot_y(pitch).T @ _rot_z(yaw).T @ R  # = Rot_x(roll)
    roll = math.atan2(rest[2, 1], rest[1, 1])
    return roll, pitch, yaw


def rpy_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix of URDF roll, pitch, yaw: ``Rz(yaw) Ry(pitch) Rx(roll)``.

    >>> from hrm_ctrl.kinematics import R_BASE_PAPER
    >>> bool(np.allclose(rpy_rotation(*RPY_BASE_PAPER), R_BASE_PAPER))
    True
    """
    return _rot_z(yaw) @ _rot_y(pitch) @ _rot_x(roll)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _num(x: float) -> str:
    """Shortest text that reads back as the same double; integers without ``.0``."""
    x = float(x)
    if x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


def _vec(v: tuple[float, ...] | np.ndarray) -> str:
    return " ".join(_num(x) for x in v)


def _origin(xyz: tuple[float, ...] | np.ndarray, rpy: tuple[float, ...] | np.ndarray) -> str:
    return f'<origin xyz="{_vec(xyz)}" rpy="{_vec(rpy)}"/>'


def _inertial(mass_kg: float, ixx: float, iyy: float, izz: float, z_m: float) -> list[str]:
    return [
        "    <inertial>",
        f"      {_origin((0.0, 0.0, z_m), (0.0, 0.0, 0.0))}",
        f'      <mass value="{_num(mass_kg)}"/>',
        f'      <inertia ixx="{_num(ixx)}" ixy="0" ixz="0" iyy="{_num(iyy)}" iyz="0"'
        f' izz="{_num(izz)}"/>',
        "    </inertial>",
    ]


def _cylinder_link(name: str, length_m: float, radius_m: float, mass_kg: float) -> list[str]:
    """A link whose body is a cylinder from its frame origin along +z."""
    ixx = mass_kg * (3.0 * radius_m**2 + length_m**2) / 12.0
    izz = mass_kg * radius_m**2 / 2.0
    geometry = (
        f'<geometry><cylinder radius="{_num(radius_m)}" length="{_num(length_m)}"/></geometry>'
    )
    centre = _origin((0.0, 0.0, length_m / 2.0), (0.0, 0.0, 0.0))
    return [
        f"  <link name={quoteattr(name)}>",
        *_inertial(mass_kg, ixx, ixx, izz, length_m / 2.0),
        "    <visual>",
        f"      {centre}",
        f"      {geometry}",
        '      <material name="link_grey"/>',
        "    </visual>",
        "    <collision>",
        f"      {centre}",
        f"      {geometry}",
        "    </collision>",
        "  </link>",
    ]


def _small_link(name: str) -> list[str]:
    return [
        f"  <link name={quoteattr(name)}>",
        *_inertial(CROSS_MASS_KG, *(CROSS_INERTIA_KG_M2,) * 3, 0.0),
        "  </link>",
    ]


def _joint(
    name: str,
    kind: str,
    parent: str,
    child: str,
    xyz: tuple[float, ...] | np.ndarray = (0.0, 0.0, 0.0),
    rpy: tuple[float, ...] | np.ndarray = (0.0, 0.0, 0.0),
    axis: tuple[float, float, float] | None = None,
    limit_rad: float | None = None,
) -> list[str]:
    lines = [
        f"  <joint name={quoteattr(name)} type={quoteattr(kind)}>",
        f"    <parent link={quoteattr(parent)}/>",
        f"    <child link={quoteattr(child)}/>",
        f"    {_origin(xyz, rpy)}",
    ]
    if axis is not None:
        lines.append(f'    <axis xyz="{_vec(axis)}"/>')
    if limit_rad is not None:
        lines.append(
            f'    <limit lower="{_num(-limit_rad)}" upper="{_num(limit_rad)}"'
            f' effort="{_num(EFFORT_LIMIT_NM)}" velocity="{_num(VELOCITY_LIMIT_RAD_PER_S)}"/>'
        )
    lines.append("  </joint>")
    return lines


def link_names(model: RobotModel) -> list[str]:
    """Names of the links whose frames are the paper's frames 1..12, then the end point.

    >>> from hrm_ctrl.model import default_robot
    >>> link_names(default_robot())[:2], link_names(default_robot())[-1]
    (['link1', 'link2'], 'end_effector')
    """
    return [f"link{i + 1}" for i in range(model.n_joints)] + ["end_effector"]


def joint_names(model: RobotModel) -> list[str]:
    """Names of the revolute joints in order: ``j1_alpha, j1_theta, j2_alpha, ...``.

    >>> from hrm_ctrl.model import default_robot
    >>> joint_names(default_robot())[:3]
    ['j1_alpha', 'j1_theta', 'j2_alpha']
    """
    return [f"j{i + 1}_{a}" for i in range(model.n_joints) for a in ("alpha", "theta")]


def robot_urdf(model: RobotModel, link_mass_kg_per_m: float = DEFAULT_LINK_MASS_KG_PER_M) -> str:
    """The URDF text of the arm (see the module docstring for the frame layout).

    ``link_mass_kg_per_m`` sets the placeholder link masses (the description
    has none); it only affects the ``<inertial>`` blocks.
    """
    if not (math.isfinite(link_mass_kg_per_m) and link_mass_kg_per_m > 0.0):
        raise ValueError(f"link_mass_kg_per_m must be > 0, got {link_mass_kg_per_m!r}")
    for what, text in (("robot name", model.name), ("description path", str(model.source))):
        bad = _NOT_XML.search(text)
        if bad is not None:
            raise UrdfWriteError(
                f"{model.source}: the {what} {text!r} holds a character XML cannot carry "
                f"(U+{ord(bad.group()):04X})"
            )
    n = model.n_joints
    links_m = np.asarray(model.links, dtype=float) / MM_PER_M
    radii_m = np.asarray(model.outer_diameter, dtype=float) / MM_PER_M / 2.0
    comment = (
        f"{model.name}: {n} universal joints as {2 * n} revolute joints"
        f" (alpha about y, then theta about the new x); lengths in m."
        f" Generated by hrm urdf from {model.source}."
    )
    while "--" in comment:  # "--" may not appear inside an XML comment
        comment = comment.replace("--", "- -")
    lines = [
        '<?xml version="1.0"?>',
        f"<!-- {comment} -->",
        f"<robot name={quoteattr(model.name)}>",
        '  <material name="link_grey"><color rgba="0.6 0.6 0.65 1"/></material>',
        '  <link name="world"/>',
        *_small_link("base"),
        *_joint(
            "base_mount",
            "fixed",
            "world",
            "base",
            xyz=np.asarray(model.base_position, dtype=float) / MM_PER_M,
            rpy=rotation_rpy(model.base_rotation),
        ),
    ]
    parent = "base"
    for i in range(n):
        k = i + 1
        cross, link = f"cross{k}", f"link{k}"
        lines += _small_link(cross)
        lines += _cylinder_link(
            link, float(links_m[i]), float(radii_m[i]), link_mass_kg_per_m * float(links_m[i])
        )
        if i == 0:
            xyz: tuple[float, ...] = (0.0, 0.0, 0.0)
            rpy: tuple[float, ...] = RPY_BASE_PAPER
        else:
            xyz, rpy = (0.0, 0.0, float(links_m[i - 1])), (0.0, 0.0, 0.0)
        lines += _joint(
            f"j{k}_alpha",
            "revolute",
            parent,
            cross,
            xyz,
            rpy,
            axis=(0.0, 1.0, 0.0),
            limit_rad=model.limit_alpha,
        )
        lines += _joint(
            f"j{k}_theta",
            "revolute",
            cross,
            link,
            axis=(1.0, 0.0, 0.0),
            limit_rad=model.limit_theta,
        )
        parent = link
    lines += _small_link("end_effector")
    lines += _joint(
        "end_effector_mount", "fixed", parent, "end_effector", xyz=(0.0, 0.0, float(links_m[n - 1]))
    )
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def write_robot_urdf(
    model: RobotModel, path: str | Path, link_mass_kg_per_m: float = DEFAULT_LINK_MASS_KG_PER_M
) -> Path:
    """Write :func:`robot_urdf` to ``path`` atomically (temp file + ``os.replace``).

    Raises :class:`UrdfWriteError` naming the file if it cannot be written; no
    partial file is left behind.
    """
    path = Path(path)
    text = robot_urdf(model, link_mass_kg_per_m)
    try:
        write_atomic(path, text, make_parents=False)
    except OSError as exc:
        raise UrdfWriteError(f"{path}: cannot write URDF ({exc.strerror or exc})") from None
    return path
