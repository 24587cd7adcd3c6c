"""Kinematic calibration: link lengths and joint zero offsets from measured end points.

The model is the forward kinematics of Eqs. (1)-(4) (:mod:`hrm_ctrl.kinematics`) with
three groups of corrections, fitted by :func:`scipy.optimize.least_squares`:

- ``l_1 .. l_12``: link-length corrections (mm), added to ``model.links``;
- ``alpha_offset_1 .. 12``, ``theta_offset_1 .. 12``: joint zero offsets (rad); the true
  angle is the commanded one plus the joint's offset (issue 12);
- with ``estimate_frame``, the instrument's pose ``frame_rx, frame_ry, frame_rz`` (a rotation
  vector, rad) and ``frame_tx, frame_ty, frame_tz`` (mm): a measured point is
  ``p_instrument = R p_base + t``.  The rotation is fitted as a left correction of a
  closed-form (Kabsch) first guess, so its standard deviations are in the instrument's axes.

Every residual is the difference, in mm, between a measured end point and the predicted one;
the Jacobian is analytic (a link's column is its direction, an offset's the cross product of
its joint axis with the lever arm to the end point).

**What the end point can observe.**  Without a free instrument frame (points already in the
base frame) all 36 parameters are observable from well-spread poses: every joint axis is
perpendicular to its link, so no rotation moves the end point along its own axis, and the
last link's length and offsets act on the end point like any other (checked numerically: the
scaled Jacobian of 60 spread poses has full rank, condition ~100).  With a free frame exactly
one combination is not: ``alpha_1`` is the first rotation, about the base's fixed y axis
(Eq. 2), so an offset of joint 1's alpha turns the whole arm rigidly about that axis through
the base origin, which the instrument's rotation does as well.  :func:`fit_kinematics` fixes
``alpha_offset_1`` at 0 in that case and says so in :attr:`KinematicFit.fixed`: the fitted
frame then carries that rotation, and the calibrated arm with the fitted frame predicts the
instrument's points just as the true one does (``theta_offset_1`` stays observable: its axis
turns with ``alpha_1``).  Every other loss of observability comes from the data (too few
poses, poses too alike); it is found from the singular values of the Jacobian scaled by
:data:`STD_LIMIT` and refused (:class:`UnobservableError`) naming the parameters or
combinations: a direction is refused when the noise ``sigma_mm`` leaves it less well
determined than those limits (for a combination of unit length in those units).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import qmc

from hrm_ctrl.errors import CalibrationDataError, UnobservableError
from hrm_ctrl.files import read_text_file
from hrm_ctrl.kinematics import R_BASE_PAPER, frames
from hrm_ctrl.model import RobotModel

N_JOINTS = 12
COLUMNS = (
    tuple(f"alpha_{i}_rad" for i in range(1, N_JOINTS + 1))
    + tuple(f"theta_{i}_rad" for i in range(1, N_JOINTS + 1))
    + ("x_mm", "y_mm", "z_mm")
)
"""The header of a pose file, in order (issue 12)."""

MAX_POSE_BYTES = 16 * 2**20  # ~100 bytes a cell, 27 cells a pose: ~6,000 poses a MiB
MAX_POSES = 100_000
MAX_ANGLE_RAD = math.pi  # a commanded angle beyond half a turn is not a joint angle
MAX_COORDINATE_MM = 1.0e5  # 100 m from the base: a typo, not a measurement

LINK_NAMES = tuple(f"l_{i}" for i in range(1, N_JOINTS + 1))
ALPHA_NAMES = tuple(f"alpha_offset_{i}" for i in range(1, N_JOINTS + 1))
THETA_NAMES = tuple(f"theta_offset_{i}" for i in range(1, N_JOINTS + 1))
FRAME_NAMES = ("frame_rx", "frame_ry", "frame_rz", "frame_tx", "frame_ty", "frame_tz")

STD_LIMIT = {"mm": 0.25, "rad": math.radians(0.05)}
"""The largest standard deviation (at the caller's ``sigma_mm``) a fitted parameter, or a
unit combination of parameters in these units, may have: lengths in mm, angles in rad.
A well-spread set of 60 poses at sigma 0.05 mm gives about 0.014 mm and 0.01 deg at worst
(joint 12's offsets, on the shortest lever arm), so the limits refuse data at least five
times worse than that, and accept nothing that would not beat the description's own
tolerances (+-2 mm, +-1 deg) by far."""

EXACT_RCOND = 1e-9  # singular values below this fraction of the largest: not observable at all


@dataclass(frozen=True)
class PoseData:
    """The poses of a data file: commanded angles (rad, (N, 12) each), measured end points
    (mm, (N, 3)), and the file they came from."""

    alpha_rad: np.ndarray
    theta_rad: np.ndarray
    points_mm: np.ndarray
    source: str

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])


def _cell(cell: str) -> str:
    text = repr(cell.strip())
    return text if len(text) <= 40 else f"{text[:30]}...' ({len(cell.strip())} characters)"


def read_pose_csv(path: str | Path) -> PoseData:
    """Read a pose file: the header :data:`COLUMNS`, then one pose per line.

    Every problem raises :class:`CalibrationDataError` with one line naming the file, the
    line and the column (``poses.csv:7: column 27 (z_mm) is missing``); a file larger than
    :data:`MAX_POSE_BYTES` is refused unread, one of more than :data:`MAX_POSES` poses before
    its numbers are read.  Angles must lie within +-pi, coordinates within 100 m.
    """
    p = str(path)
    text = read_text_file(path, CalibrationDataError, "pose file", max_bytes=MAX_POSE_BYTES)
    lines = text.splitlines()
    if sum(bool(x.strip()) for x in lines) > MAX_POSES + 1:
        raise CalibrationDataError(
            f"{p}: pose file has more than the {MAX_POSES} poses it may have"
        )
    reader = csv.reader(lines)
    rows: list[list[str]] = []
    try:
        rows.extend(reader)
    except csv.Error as exc:  # a field longer than csv's limit, a NUL
        raise CalibrationDataError(f"{p}:{reader.line_num}: not a CSV line ({exc})") from None
    numbered = [(n, r) for n, r in enumerate(rows, start=1) if any(c.strip() for c in r)]
    if not numbered:
        raise CalibrationDataError(f"{p}: pose file is empty")
    n0, header = numbered[0]
    names = [c.strip() for c in header]
    for k, want in enumerate(COLUMNS):
        if k >= len(names):
            raise CalibrationDataError(f"{p}:{n0}: header column {k + 1} ({want}) is missing")
        if names[k] != want:
            raise CalibrationDataError(
                f"{p}:{n0}: header column {k + 1} is {_cell(names[k])}, expected {want!r}"
            )
    if len(names) > len(COLUMNS):
        raise CalibrationDataError(
            f"{p}:{n0}: header column {len(COLUMNS) + 1} {_cell(names[len(COLUMNS)])} is not "
            f"part of the format (it has {len(COLUMNS)} columns)"
        )
    if len(numbered) == 1:
        raise CalibrationDataError(f"{p}: pose file has a header but no poses")
    values = np.empty((len(numbered) - 1, len(COLUMNS)))
    for j, (n, row) in enumerate(numbered[1:]):
        if len(row) < len(COLUMNS):
            k = len(row)
            raise CalibrationDataError(f"{p}:{n}: column {k + 1} ({COLUMNS[k]}) is missing")
        if len(row) > len(COLUMNS):
            raise CalibrationDataError(
                f"{p}:{n}: column {len(COLUMNS) + 1} is one too many (a pose has "
                f"{len(COLUMNS)} columns)"
            )
        for k, (name, cell) in enumerate(zip(COLUMNS, row, strict=True)):
            where = f"{p}:{n}: column {k + 1} ({name})"
            try:
                v = float(cell)
            except ValueError:
                raise CalibrationDataError(f"{where} is not a number: {_cell(cell)}") from None
            bound = MAX_ANGLE_RAD if name.endswith("_rad") else MAX_COORDINATE_MM
            if math.isnan(v):
                raise CalibrationDataError(f"{where} is not a number: {_cell(cell)}")
            if not abs(v) <= bound:
                raise CalibrationDataError(
                    f"{where} = {_cell(cell)} is out of range (|value| <= {bound:.6g})"
                )
            values[j, k] = v
    n = N_JOINTS
    return PoseData(values[:, :n], values[:, n : 2 * n], values[:, 2 * n :], p)


def format_pose_csv(alpha_rad: np.ndarray, theta_rad: np.ndarray, points_mm: np.ndarray) -> str:
    """The text of a pose file (:data:`COLUMNS`), every number as Python writes it (the
    shortest text that reads back to the same float), what :func:`read_pose_csv` reads.

    >>> text = format_pose_csv(np.zeros((1, 12)), np.zeros((1, 12)), np.array([[1.5, 0, -2]]))
    >>> text.splitlines()[0].split(",")[-3:], text.splitlines()[1].split(",")[-3:]
    (['x_mm', 'y_mm', 'z_mm'], ['1.5', '0.0', '-2.0'])
    """
    a = np.asarray(alpha_rad, dtype=float)
    t = np.asarray(theta_rad, dtype=float)
    p = np.asarray(points_mm, dtype=float)
    if a.ndim != 2 or a.shape[1] != N_JOINTS or t.shape != a.shape or p.shape != (len(a), 3):
        raise CalibrationDataError(
            f"poses: alpha {a.shape}, theta {t.shape} and points {p.shape} do not make a pose "
            f"table of (N, {N_JOINTS}), (N, {N_JOINTS}), (N, 3)"
        )
    rows = [",".join(COLUMNS)]
    rows += [",".join(repr(float(v)) for v in row) for row in np.concatenate([a, t, p], axis=1)]
    return "\n".join(rows) + "\n"


def spread_configurations(model: RobotModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` well-spread configurations ``(alpha, theta)``, each of shape (n, 12), rad.

    A Latin hypercube over the 24 angles (each angle's range cut into ``n`` strata, one pose
    in each), within 90 % of the joint limits so that zero offsets of a few degrees keep the
    true angles inside; of a few candidate designs the one whose closest two poses are
    farthest apart.  Nothing here checks obstacles or the instrument's line of sight.

    >>> from hrm_ctrl.model import default_robot
    >>> a, t = spread_configurations(default_robot(), 5, np.random.default_rng(1))
    >>> a.shape, bool(np.all(np.abs(t) < np.radians(60)))
    ((5, 12), True)
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    nj = model.n_joints
    span = 0.9 * np.r_[np.full(nj, model.limit_alpha), np.full(nj, model.limit_theta)]
    best, best_d = None, -1.0
    for _ in range(8 if n <= 500 else 1):
        u = qmc.LatinHypercube(d=2 * nj, seed=rng).random(n)
        if n > 1 and n <= 500:
            diff = u[:, None, :] - u[None, :, :]
            d2 = np.einsum("ijk,ijk->ij", diff, diff)
            np.fill_diagonal(d2, np.inf)
            d = float(d2.min())
        else:
            d = 0.0
        if d > best_d:
            best, best_d = u, d
    assert best is not None
    q = (2.0 * best - 1.0) * span
    return q[:, :nj].copy(), q[:, nj:].copy()


@dataclass(frozen=True)
class KinematicFit:
    """The result of :func:`fit_kinematics`.

    ``params`` holds every parameter by name (:data:`LINK_NAMES`, :data:`ALPHA_NAMES`,
    :data:`THETA_NAMES`, and :data:`FRAME_NAMES` with a frame), ``std`` the standard deviation
    of each fitted one (``sigma^2 (J^T J)^-1`` with the residual-based ``sigma``); a parameter
    in ``fixed`` (name -> reason) was held at 0 and has no entry in ``std``.  Residuals are
    the distances between measured and predicted points (mm); "before" uses the robot
    description with zero offsets (and, with a frame, its best rigid fit to the points).
    """

    links_mm: np.ndarray
    link_corrections_mm: np.ndarray
    alpha_offset_rad: np.ndarray
    theta_offset_rad: np.ndarray
    frame_rotation: np.ndarray | None
    frame_translation_mm: np.ndarray | None
    params: dict[str, float]
    std: dict[str, float]
    fixed: dict[str, str]
    rms_before_mm: float
    max_before_mm: float
    rms_after_mm: float
    max_after_mm: float
    sigma_mm: float
    n_poses: int
    singular_values: np.ndarray = field(repr=False)

    def calibrated_model(self, model: RobotModel) -> RobotModel:
        """``model`` with the fitted link lengths (the offsets stay with the caller)."""
        return _with_links(model, self.links_mm)


def _with_links(model: RobotModel, links: np.ndarray) -> RobotModel:
    links = np.array(links, dtype=float)
    links.setflags(write=False)
    return dataclasses.replace(model, links=links)


def _skew(v: np.ndarray) -> np.ndarray:
    S = np.zeros((*v.shape[:-1], 3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _exp(r: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(r))
    K = _skew(r)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + math.sin(th) / th * K + (1.0 - math.cos(th)) / th**2 * K @ K


def _left_jacobian(r: np.ndarray) -> np.ndarray:
    """``d exp(r) / dr = [J_l(r) dr]x exp(r)``: the left Jacobian of SO(3)."""
    th = float(np.linalg.norm(r))
    K = _skew(r)
    if th < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return np.eye(3) + (1.0 - math.cos(th)) / th**2 * K + (th - math.sin(th)) / th**3 * K @ K


def _log(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R, t`` minimising ``|R p + t - q|`` over the rows."""
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    H = (p - pc).T @ (q - qc)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T))) or 1.0])
    R = Vt.T @ D @ U.T
    return R, qc - R @ pc


FIDUCIAL_RMS_LIMIT_MM = 0.5  # nests measured further from their drawing: the wrong nests


@dataclass(frozen=True)
class InstrumentFrame:
    """An instrument's frame found from the base plate's nests: ``p_instrument = R p_base +
    t``; ``rms_mm`` how well the measured nests fit the drawn ones after the transform."""

    rotation: np.ndarray  # (3, 3)
    translation_mm: np.ndarray  # (3,)
    rms_mm: float
    max_mm: float

    def to_base(self, points_mm: np.ndarray) -> np.ndarray:
        """Points (n, 3) in the instrument's frame -> the base frame."""
        return (np.asarray(points_mm, dtype=float) - self.translation_mm) @ self.rotation


def instrument_frame(model: RobotModel, measured_mm: np.ndarray) -> InstrumentFrame:
    """The instrument's frame from its readings ``measured_mm`` (k, 3) of the base plate's
    nests ``model.base_fiducials`` (k, 3), by the least-squares rigid fit (Kabsch).  With
    the frame known, every joint offset is observable, ``alpha_offset_1`` too (a free
    frame carries a rotation of the whole arm about the base's first axis).  Refuses
    (:class:`CalibrationDataError`, one line) readings that fit the drawing worse than
    :data:`FIDUCIAL_RMS_LIMIT_MM` (the wrong nests, or nests moved).

    >>> from hrm_ctrl.model import default_robot
    >>> m = default_robot()
    >>> R = _exp(np.array([0.1, -0.2, 1.2])); t = np.array([-1000.0, 1200.0, 200.0])
    >>> f = instrument_frame(m, m.base_fiducials @ R.T + t)
    >>> bool(np.allclose(f.rotation, R) and np.allclose(f.translation_mm, t)), f.rms_mm < 1e-9
    (True, True)
    """
    q = np.asarray(measured_mm, dtype=float)
    p = np.asarray(model.base_fiducials, dtype=float)
    if q.shape != p.shape or not np.isfinite(q).all():
        raise CalibrationDataError(
            f"instrument frame: {p.shape[0]} base nests drawn, readings of shape {q.shape}"
        )
    R, t = _kabsch(p, q)
    d = np.linalg.norm(p @ R.T + t - q, axis=1)
    rms, worst = float(np.sqrt(np.mean(d**2))), float(d.max())
    if rms > FIDUCIAL_RMS_LIMIT_MM:
        raise CalibrationDataError(
            f"instrument frame: the base nests fit their drawing to {rms:.3f} mm rms (nest "
            f"{int(np.argmax(d)) + 1} {worst:.3f} mm off), more than {FIDUCIAL_RMS_LIMIT_MM} mm: "
            "wrong nests, or the base moved"
        )
    return InstrumentFrame(R, t, rms, worst)


def _chain(model, dl, da, dt, alpha, theta):
    """End points (N, 3) and their Jacobian (N, 3, 36) w.r.t. (dl, da, dt)."""
    m = _with_links(model, model.links + dl)
    R, O = frames(m, alpha + da, theta + dt)
    p = O[:, -1, :]
    n = alpha.shape[0]
    R0 = np.broadcast_to(model.base_rotation @ R_BASE_PAPER, (n, 1, 3, 3))
    Rprev = np.concatenate([R0, R[:, :-1]], axis=1)
    lever = p[:, None, :] - O[:, :-1, :]
    J = np.concatenate(
        [R[..., :, 2], np.cross(Rprev[..., :, 1], lever), np.cross(R[..., :, 0], lever)], axis=1
    )  # (N, 36, 3)
    return p, J.transpose(0, 2, 1)


def _compress(names: list[str]) -> str:
    """``l_1-3, alpha_offset_5`` for a list of parameter names."""
    groups: dict[str, list[int]] = {}
    out: list[str] = []
    for name in names:
        m = re.fullmatch(r"(.*_)(\d+)", name)
        if m is None:
            out.append(name)
        else:
            groups.setdefault(m.group(1), []).append(int(m.group(2)))
    parts = []
    for prefix, idx in groups.items():
        idx.sort()
        runs, start = [], idx[0]
        for a, b in zip(idx, [*idx[1:], None], strict=True):
            if b != a + 1:
                runs.append(f"{start}" if start == a else f"{start}-{a}")
                start = b
        parts.append(prefix + ",".join(runs))
    return ", ".join(parts + out)


def _check_observable(
    Js: np.ndarray, names: list[str], sigma_mm: float, n_poses: int
) -> np.ndarray:
    """Refuse when the scaled Jacobian ``Js`` leaves a direction undetermined; return its
    singular values."""
    _, s, Vt = np.linalg.svd(Js, full_matrices=Js.shape[0] < Js.shape[1])
    n = Js.shape[1]
    s_full = np.zeros(n)
    s_full[: len(s)] = s
    smax = float(s_full.max()) if n else 0.0
    bad = np.flatnonzero((s_full <= EXACT_RCOND * smax) | (s_full < sigma_mm))
    few = 3 * n_poses <= n
    if len(bad) == 0 and not few:
        return s_full
    null = Vt[bad]  # rows: the undetermined directions, in STD_LIMIT units
    if len(bad) <= 3:
        combos = []
        for v in null:
            order = [j for j in np.argsort(-np.abs(v)) if abs(v[j]) >= 0.2]
            sign = 1.0 if v[order[0]] > 0 else -1.0
            combos.append(" ".join(f"{sign * v[j]:+.2f}*{names[j]}" for j in order).lstrip("+"))
        what = "; ".join(combos)
        kind = "combination" if len(bad) == 1 else "combinations"
    else:
        weight = np.sum(null**2, axis=0)
        what = _compress([names[j] for j in range(n) if weight[j] >= 0.25])
        kind = "directions, involving"
    head = (
        f"too few poses ({n_poses} give {3 * n_poses} equations for {n} parameters; need more "
        f"than {n // 3}, well spread)"
        if few
        else "the poses do not determine every parameter"
    )
    worst = float(s_full[bad].min()) if len(bad) else 0.0
    ratio = "inf" if worst == 0.0 else f"{sigma_mm / worst:.3g}"
    raise UnobservableError(
        f"kinematic fit refused: {head}; not observable ({len(bad)} {kind}): {what} "
        f"(std {ratio} x the limit, in units of {STD_LIMIT['mm']:g} mm and "
        f"{math.degrees(STD_LIMIT['rad']):g} deg)"
    )


def _as_array(x, shape_tail: tuple[int, ...], what: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 2 or a.shape[1:] != shape_tail:
        raise CalibrationDataError(f"{what} must have shape (N, {shape_tail[0]}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        i = int(np.argwhere(~np.isfinite(a))[0][0])
        raise CalibrationDataError(f"{what}: pose {i + 1} has a value that is not finite")
    return a


def fit_kinematics(
    model: RobotModel,
    alpha_cmd: np.ndarray,
    theta_cmd: np.ndarray,
    points_mm: np.ndarray,
    *,
    estimate_frame: bool = False,
    sigma_mm: float = 0.05,
) -> KinematicFit:
    """Fit link-length corrections and joint zero offsets (and, with ``estimate_frame``, the
    instrument's pose) to measured end points; see the module's docstring for what is
    observable.  ``sigma_mm`` is the instrument's noise, used only to decide whether the
    data determine the parameters (:data:`STD_LIMIT`); the reported standard deviations use
    the residuals' own sigma.

    Raises :class:`UnobservableError` (one line naming the parameters or combinations) when
    the data leave the fit ill-conditioned, :class:`CalibrationDataError` for arrays of the
    wrong shape or with values that are not finite.
    """
    nj = model.n_joints
    alpha = _as_array(alpha_cmd, (nj,), "alpha_cmd")
    theta = _as_array(theta_cmd, (nj,), "theta_cmd")
    pts = _as_array(points_mm, (3,), "points_mm")
    if not (alpha.shape[0] == theta.shape[0] == pts.shape[0]):
        raise CalibrationDataError(
            f"alpha_cmd, theta_cmd and points_mm have {alpha.shape[0]}, {theta.shape[0]} and "
            f"{pts.shape[0]} poses"
        )
    if not (math.isfinite(sigma_mm) and sigma_mm > 0.0):
        raise ValueError(f"sigma_mm must be a positive number, got {sigma_mm!r}")
    n_poses = pts.shape[0]

    names = [*LINK_NAMES[:nj], *ALPHA_NAMES[:nj], *THETA_NAMES[:nj]]
    scale = [STD_LIMIT["mm"]] * nj + [STD_LIMIT["rad"]] * (2 * nj)
    fixed: dict[str, str] = {}
    R0, t0 = np.eye(3), np.zeros(3)
    p_nom = frames(model, alpha, theta)[1][:, -1, :] if n_poses else np.zeros((0, 3))
    if estimate_frame:
        names += list(FRAME_NAMES)
        scale += [STD_LIMIT["rad"]] * 3 + [STD_LIMIT["mm"]] * 3
        fixed[ALPHA_NAMES[0]] = (
            "a rotation of the whole arm about the base's first axis is also a rotation of the "
            "instrument: fixed at 0, the fitted frame carries it"
        )
        if n_poses:
            R0, t0 = _kabsch(p_nom, pts)
    free = np.array([nm not in fixed for nm in names])
    free_names = [nm for nm, f in zip(names, free, strict=True) if f]
    D = np.array(scale)[free]

    def unpack(x: np.ndarray) -> np.ndarray:
        full = np.zeros(len(names))
        full[free] = x * D
        return full

    def model_eval(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        full = unpack(x)
        p, Jc = _chain(model, full[:nj], full[nj : 2 * nj], full[2 * nj : 3 * nj], alpha, theta)
        if not estimate_frame:
            return p, Jc
        dr, dtr = full[3 * nj : 3 * nj + 3], full[3 * nj + 3 :]
        Rf = _exp(dr) @ R0
        q = p @ Rf.T + t0 + dtr
        Jq = np.einsum("ij,njk->nik", Rf, Jc)
        Jr = -_skew(q - t0 - dtr) @ _left_jacobian(dr)  # (N, 3, 3)
        Jt = np.broadcast_to(np.eye(3), (n_poses, 3, 3))
        return q, np.concatenate([Jq, Jr, Jt], axis=2)

    def jac(x: np.ndarray) -> np.ndarray:
        return model_eval(x)[1][:, :, free].reshape(3 * n_poses, -1) * D

    x0 = np.zeros(len(free_names))
    dist_before = np.linalg.norm(model_eval(x0)[0] - pts, axis=1)
    _check_observable(jac(x0) if n_poses else np.zeros((0, len(x0))), free_names, sigma_mm, n_poses)

    sol = least_squares(
        lambda x: (model_eval(x)[0] - pts).ravel(),
        x0,
        jac=jac,
        method="lm",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    J = jac(sol.x)
    s = _check_observable(J, free_names, sigma_mm, n_poses)
    q_fit = model_eval(sol.x)[0]
    dist_after = np.linalg.norm(q_fit - pts, axis=1)
    dof = 3 * n_poses - len(free_names)
    sigma = math.sqrt(float(np.sum((q_fit - pts) ** 2)) / dof)
    cov = np.linalg.inv(J.T @ J) * sigma**2 * np.outer(D, D)
    std = dict(zip(free_names, np.sqrt(np.diag(cov)).tolist(), strict=True))

    full = unpack(sol.x)
    params = dict(zip(names, full.tolist(), strict=True))
    frame_R = frame_t = None
    if estimate_frame:
        frame_R = _exp(full[3 * nj : 3 * nj + 3]) @ R0
        frame_t = t0 + full[3 * nj + 3 :]
        rv, tv = _log(frame_R), frame_t
        params.update(zip(FRAME_NAMES, [*rv.tolist(), *tv.tolist()], strict=True))
    dl = full[:nj].copy()
    return KinematicFit(
        links_mm=model.links + dl,
        link_corrections_mm=dl,
        alpha_offset_rad=full[nj : 2 * nj].copy(),
        theta_offset_rad=full[2 * nj : 3 * nj].copy(),
        frame_rotation=frame_R,
        frame_translation_mm=frame_t,
        params=params,
        std=std,
        fixed=fixed,
        rms_before_mm=float(np.sqrt(np.mean(dist_before**2))),
        max_before_mm=float(dist_before.max()),
        rms_after_mm=float(np.sqrt(np.mean(dist_after**2))),
        max_after_mm=float(dist_after.max()),
        sigma_mm=sigma,
        n_poses=n_poses,
        singular_values=s,
    )
