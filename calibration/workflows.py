"""The calibration workflows: what a routine's result makes of the calibration, and the
zero -> kinematic sequence of a fresh arm.

These are library code for ``hrm calibrate``, the console's ``calibrate`` and ``hrm demo``:
they take an opened drive session (or a way to open one, ``open_session``) and readers as
parameters, and open no box themselves (the runtime layer, ``hrm_ctrl.runtime.box``,
does; calibration imports neither it nor the simulator).

* :func:`kinematic_calibration`: the next calibration with a kinematic fit's links and
  offsets; :func:`zero_calibration`, :func:`stiffness_calibration` the same for the
  rope-tension routines' results, :func:`physics_calibration` for the link masses and
  friction (``calibration.physics``);
* :func:`save_calibration`: into the store (made active when loading would accept it) or
  one file;
* :func:`tracker_frame` and :func:`collect_in_base_frame`: the laser tracker's frame from
  the base plate's nests, and poses collected and put into the base frame;
* :func:`zero_then_kinematic`: pretension and zero in the fixture, then the kinematic
  calibration out of it, each saved as a version.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from hrm_ctrl.errors import CalibrationFileError

if TYPE_CHECKING:
    import numpy as np

    from calibration.kinematic import InstrumentFrame, KinematicFit, PoseData
    from calibration.physics import PhysicsFit
    from calibration.stiffness import StiffnessResult
    from calibration.store import Calibration, CalibrationStore
    from calibration.zero import ZeroResult
    from drivers.identity import BoxIdentity
    from drivers.session import CalibrationRef, DriveSession
    from hrm_ctrl.model import RobotModel
    from hrm_ctrl.ropes.actuation import Actuation

# Readings averaged per base nest: the frame's error reaches the tip over the arm's 2 m, so
# the nests get more than a pose (0.05 mm / sqrt(200) = 3.5 um a nest; 0.2 ms a reading)
NEST_READINGS = 200


def fit_residuals(fit: KinematicFit) -> dict[str, float]:
    """What a kinematic calibration keeps of its fit: residuals before and after, the
    largest standard deviations, the instrument frame's parameters."""
    from calibration.kinematic import ALPHA_NAMES, LINK_NAMES, THETA_NAMES

    links = [fit.std[n] for n in LINK_NAMES if n in fit.std]
    offsets = [fit.std[n] for n in (*ALPHA_NAMES, *THETA_NAMES) if n in fit.std]
    out = {
        "n_poses": float(fit.n_poses),
        "rms_before_mm": fit.rms_before_mm,
        "max_before_mm": fit.max_before_mm,
        "rms_after_mm": fit.rms_after_mm,
        "max_after_mm": fit.max_after_mm,
        "sigma_mm": fit.sigma_mm,
        "max_std_link_mm": max(links),
        "max_std_offset_rad": max(offsets),
    }
    for name, value in fit.params.items():
        if name.startswith("frame_"):
            out[name] = value
    return out


def kinematic_calibration(base: Calibration, fit: KinematicFit) -> Calibration:
    """The next calibration from ``base`` with the fit's links and offsets; a parameter the
    fit held fixed (``alpha_offset_1`` with a free instrument frame) keeps ``base``'s."""
    import numpy as np

    from calibration.apply import updated
    from calibration.kinematic import ALPHA_NAMES, THETA_NAMES
    from calibration.store import Routine

    alpha = np.array(fit.alpha_offset_rad, dtype=float)
    theta = np.array(fit.theta_offset_rad, dtype=float)
    for j, name in enumerate(ALPHA_NAMES):
        if name in fit.fixed:
            alpha[j] = base.alpha_offset_rad[j]
    for j, name in enumerate(THETA_NAMES):
        if name in fit.fixed:
            theta[j] = base.theta_offset_rad[j]
    return updated(
        base,
        routine=Routine.KINEMATIC,
        residuals=fit_residuals(fit),
        links_mm=np.array(fit.links_mm, dtype=float),
        alpha_offset_rad=alpha,
        theta_offset_rad=theta,
    )


def zero_calibration(
    base: Calibration,
    result: ZeroResult,
    residuals: dict[str, float] | None = None,
    box: BoxIdentity | None = None,
) -> Calibration:
    """The next calibration from ``base`` with the zero routine's motor zeros
    (``residuals``: what it keeps of the routine; default the result's own), made on
    ``box`` (the session's :attr:`~drivers.session.DriveSession.box_identity`; None:
    ``base``'s)."""
    from calibration.apply import updated
    from calibration.store import Routine

    zeros = {m: int(v) for m, v in zip(result.motor_ids, result.zero_counts, strict=True)}
    kept = result.residuals() if residuals is None else residuals
    made_on = {} if box is None else {"box": box}
    return updated(base, routine=Routine.ZERO, residuals=kept, motor_zero_counts=zeros, **made_on)


def stiffness_calibration(
    base: Calibration, result: StiffnessResult, residuals: dict[str, float] | None = None
) -> Calibration:
    """The next calibration from ``base`` with the stiffness routine's rope EA."""
    from calibration.apply import updated
    from calibration.store import Routine

    ea = {m: float(v) for m, v in zip(result.motor_ids, result.EA_N, strict=True)}
    kept = result.residuals() if residuals is None else residuals
    return updated(base, routine=Routine.STIFFNESS, residuals=kept, rope_EA_N=ea)


def physics_calibration(
    base: Calibration, fit: PhysicsFit, residuals: dict[str, float] | None = None
) -> Calibration:
    """The next calibration from ``base`` with the physics routine's link masses, payload
    (the one it was given) and friction coefficients."""
    from calibration.apply import updated
    from calibration.store import PhysicsConstants, Routine

    constants = PhysicsConstants(fit.link_mass_kg, fit.payload_kg, fit.mu_kinetic)
    kept = fit.residuals() if residuals is None else residuals
    return updated(base, routine=Routine.PHYSICS, residuals=kept, physics=constants)


class Saved(NamedTuple):
    """Where :func:`save_calibration` put a routine's result: its ``version``, ``where``
    (one line for the user) and ``usable``: whether loading would accept it (False: a
    value out of :func:`calibration.apply.check_ranges`, kept but not made active)."""

    version: int
    where: str
    usable: bool


def save_calibration(
    store: CalibrationStore,
    new: Calibration,
    description: RobotModel,
    *,
    out: Path | None = None,
    write: Callable[[Path, str], None] | None = None,
) -> tuple[Saved, str | None]:
    """Save ``new`` as the store's next version (active), or with ``out`` write that one
    file (numbered as the store's next; ``write(path, text)``, default an atomic write);
    returns where it went and, for a result loading would refuse, why (else None).

    A result that loading would refuse (a value out of
    :func:`calibration.apply.check_ranges`) is still kept, the routine's work is not lost,
    but not made active: the active version stays what it was."""
    from calibration.apply import check_belongs
    from calibration.store import to_json

    try:
        check_belongs(description, new, "the new calibration")
        problem = None
    except CalibrationFileError as exc:
        problem = str(exc)
    if out is not None:
        version = max(store.versions(), default=0) + 1  # the number it would have in the store
        if write is None:
            from hrm_ctrl.files import write_atomic as write
        write(out, to_json(new, version))
        if problem is not None:
            return Saved(
                version, f"written to {out} (not in the store; out of range)", False
            ), problem
        return Saved(version, f"written to {out} (not in the store)", True), None
    if problem is not None:
        version = store.save(new, activate=False)
        where = f"saved as v{version:04d} in {store.folder} (NOT active: out of range)"
        return Saved(version, where, False), problem
    version = store.save(new)
    return Saved(version, f"saved as v{version:04d} in {store.folder} (active)", True), None


def calibration_ref(store: CalibrationStore, version: int) -> CalibrationRef:
    """The drive session's reference to version ``version`` of ``store``."""
    from calibration.apply import file_sha256
    from drivers.session import CalibrationRef

    cal = store.load(version)
    path = str(store.path_of(version))
    return CalibrationRef(version, file_sha256(cal, version), path, box=cal.box)


def tracker_frame(
    tracker: Any, description: RobotModel, readings: int = NEST_READINGS
) -> InstrumentFrame:
    """The laser tracker's frame from ``readings`` averaged readings of each of the base
    plate's nests (``description.base_fiducials``; the tracker's ``measure(n,
    fiducial=k)``)."""
    import numpy as np

    from calibration.kinematic import instrument_frame

    measured = [
        tracker.measure(readings, fiducial=k + 1) for k in range(len(description.base_fiducials))
    ]
    return instrument_frame(description, np.array(measured))


def collect_in_base_frame(
    session: DriveSession,
    actuation: Actuation,
    tracker: Any,
    description: RobotModel,
    alpha: np.ndarray,
    theta: np.ndarray,
    *,
    period_s: float,
    frame: InstrumentFrame | None = None,
    **collect: Any,
) -> tuple[PoseData, InstrumentFrame]:
    """Poses collected on ``session`` (:func:`calibration.collect.collect_poses`, its
    keywords in ``collect``) with the tracker's points put into the base frame (``frame``;
    None: :func:`tracker_frame` first); returns the poses and the frame."""
    from calibration.collect import collect_poses

    if frame is None:
        frame = tracker_frame(tracker, description)
    data = collect_poses(session, actuation, tracker, alpha, theta, period_s=period_s, **collect)
    return dataclasses.replace(data, points_mm=frame.to_base(data.points_mm)), frame


@dataclass(frozen=True)
class ZeroKinematic:
    """What :func:`zero_then_kinematic` made: the zero routine's result and calibration
    (``zero``, ``zero_calibration``, version ``zero_version``, ``zero_s`` seconds), the
    kinematic fit, its poses (base frame) and calibration (``calibration``, version
    ``version``, ``kinematic_s`` seconds)."""

    zero: ZeroResult
    zero_calibration: Calibration
    zero_version: int
    zero_s: float
    fit: KinematicFit
    poses: PoseData
    calibration: Calibration
    version: int
    kinematic_s: float


OpenSession = Callable[
    ["Actuation", str, "CalibrationRef | None", bool], AbstractContextManager["DriveSession"]
]


def zero_then_kinematic(
    description: RobotModel,
    store: CalibrationStore,
    open_session: OpenSession,
    tension: Callable[[], AbstractContextManager[Any]],
    tracker: Callable[[], AbstractContextManager[Any]],
    *,
    leave_fixture: Callable[[], None],
    poses: int,
    period_s: float,
    samples: int = 4,
    sigma_mm: float = 0.05,
    seed: int = 7,
    say: Callable[[str], None] = print,
    on_zero: Callable[[ZeroResult, int, float], None] | None = None,
    **collect: Any,
) -> ZeroKinematic:
    """Pretension and zero in the fixture (the arm lies in it), then ``leave_fixture()``
    and the kinematic calibration out of it on ``poses`` well-spread configurations; each
    saved as a version of ``store`` (the kinematic one active).

    ``open_session(actuation, name, calibration, watch)`` opens a brought-up drive session
    for the rope layer ``actuation`` (its run named ``name``; ``watch``: with the tension
    watch, the rope-consistency watch left out as ``hrm calibrate kinematic`` does);
    ``tension()`` and ``tracker()`` open the tension board's and the laser tracker's
    readers (each for its step: the kinematic session's tension watch opens the board's
    port itself);
    ``collect`` goes to :func:`calibration.collect.collect_poses` (``settle_s``,
    ``rate_fraction``); ``say`` gets a line per step, ``on_zero(result, version, seconds)``
    the zero routine's outcome once it is saved."""
    import numpy as np

    from calibration.apply import calibrated_actuation, nominal_calibration
    from calibration.collect import travel_order
    from calibration.kinematic import fit_kinematics, spread_configurations
    from calibration.zero import pretension_and_zero

    store.check_can_save()  # before the first move: both results have a place to go
    base = nominal_calibration(description)
    act0 = calibrated_actuation(description, base)
    t0 = time.monotonic()
    say("calibration 1/2: pretension and zero, the arm in its zero fixture")
    with tension() as reader, open_session(act0, "zero", None, False) as session:
        zr = pretension_and_zero(session, reader, act0)
        box = session.box_identity  # the box the zeros belong to
    cal_zero = zero_calibration(base, zr, box=box)
    v_zero = store.save(cal_zero)
    t_zero = time.monotonic() - t0
    if on_zero is not None:
        on_zero(zr, v_zero, t_zero)

    leave_fixture()  # the technician takes the arm out of the tube
    t1 = time.monotonic()
    act1 = calibrated_actuation(description, cal_zero)
    alpha, theta = spread_configurations(description, poses, np.random.default_rng(seed))
    order = travel_order(alpha, theta)  # short moves: the same poses
    alpha, theta = alpha[order], theta[order]
    say(f"calibration 2/2: kinematic, {poses} poses read on the laser tracker")
    ref = calibration_ref(store, v_zero)
    with tracker() as points, open_session(act1, "kinematic", ref, True) as session:
        data, _frame = collect_in_base_frame(
            session,
            act1,
            points,
            description,
            alpha,
            theta,
            period_s=period_s,
            samples=samples,
            **collect,
        )
    fit = fit_kinematics(
        description,
        data.alpha_rad,
        data.theta_rad,
        data.points_mm,
        sigma_mm=sigma_mm / math.sqrt(samples),
    )
    cal = kinematic_calibration(cal_zero, fit)
    version = store.save(cal)
    return ZeroKinematic(
        zr, cal_zero, v_zero, t_zero, fit, data, cal, version, time.monotonic() - t1
    )
