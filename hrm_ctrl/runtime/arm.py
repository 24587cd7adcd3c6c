"""The arm a command works with: robot description, calibrated model and rope layer.

:func:`load_arm` takes explicit parameters (the robot description as loaded, the
calibration store's folder, ``uncalibrated``, ``simulated``, the command's name for its
messages); the CLI turns its arguments into them.

>>> import os
>>> calibrations_folder("store")
PosixPath('store')
>>> os.environ[CALIBRATIONS_ENV] = "/tmp/cal"; calibrations_folder(None)
PosixPath('/tmp/cal')
>>> del os.environ[CALIBRATIONS_ENV]
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # heavy imports only where used (the CLI's start)
    from calibration.apply import ActiveCalibration
    from drivers.identity import BoxIdentity
    from drivers.session import CalibrationRef
    from hrm_ctrl.model import RobotModel
    from hrm_ctrl.ropes.actuation import Actuation

CALIBRATIONS_ENV = "HRM_CALIBRATIONS"
DEFAULT_CALIBRATIONS = Path(".local", "share", "hrm", "calibrations")  # under the home folder


def calibrations_folder(given: Path | str | None) -> Path:
    """The calibration store: ``given``, else ``$HRM_CALIBRATIONS``, else
    ``~/.local/share/hrm/calibrations``."""
    if given is not None:
        return Path(given)
    env = os.environ.get(CALIBRATIONS_ENV)
    if env:  # set but empty: as if unset
        return Path(env)
    return Path.home() / DEFAULT_CALIBRATIONS


@dataclass(frozen=True)
class Arm:
    """The arm a command works with: the robot description as loaded, the model with the
    calibration's links, the active calibration used (None: the description's values),
    a line for stderr saying why there is none (``note``: the command prints it once its
    own checks have passed, see :meth:`say_note`), and its rope layer (:attr:`actuation`:
    ``rope_layer`` when given, else built from the description and the active calibration
    on first use, so that a command that only plans never builds it)."""

    description: RobotModel
    robot: RobotModel  # calibrated links
    active: ActiveCalibration | None
    note: str | None = None
    rope_layer: Actuation | None = None

    @cached_property
    def actuation(self) -> Actuation:
        """The rope layer: ``rope_layer``, else the description's with the active
        calibration (its values where there is none)."""
        if self.rope_layer is not None:
            return self.rope_layer
        if self.active is None:
            from hrm_ctrl.ropes.actuation import load_actuation

            return load_actuation(self.description)
        from calibration.apply import calibrated_actuation

        return calibrated_actuation(self.description, self.active.calibration)

    def say_note(self) -> None:
        """Print :attr:`note` on stderr (if any)."""
        if self.note is not None:
            print(self.note, file=sys.stderr)

    def say_calibration(self, prog: str) -> None:
        """Print :attr:`note` (if any) and, when a calibration is used, :meth:`version_line`
        on stderr: which calibration a command uses (``plan``, ``ropes``, ``run``)."""
        self.say_note()
        if self.active is not None:
            print(self.version_line(prog), file=sys.stderr)

    def calibration_ref(self) -> CalibrationRef | None:
        """The :class:`drivers.session.CalibrationRef` of the calibration used, or None."""
        if self.active is None:
            return None
        from drivers.session import CalibrationRef

        a = self.active
        return CalibrationRef(a.version, a.sha256, a.path, box=a.calibration.box)

    def version_line(self, prog: str) -> str:
        """What a command says of the calibration it uses: ``prog: calibration v0003
        (path; zero, made on a real box, 36 drives, …)``, or that it uses none."""
        a = self.active
        if a is None:
            return f"{prog}: calibration: none (the robot description's values)"
        cal = a.calibration
        box = "box unknown" if cal.box is None else f"made on a {cal.box.describe()}"
        return f"{prog}: calibration v{a.version:04d} ({a.path}; {cal.routine.value}, {box})"


def simulated_box_identity(
    description: RobotModel, *, perturb: int | None = None, truth_file: Path | None = None
) -> BoxIdentity:
    """The box a simulated arm of ``description`` (``perturb``, ``truth_file``: as
    :func:`hrm_ctrl.runtime.simulated.simulated_arm`) is, known before it starts: every
    drive's identity object as the simulated drives answer it (the EDS's vendor, product
    code and revision; serials from the truth, :func:`sim_bus.truth.drive_serials`)."""
    from drivers.identity import BoxIdentity, DriveIdentity
    from drivers.protocol.cia301 import OD_IDENTITY
    from hrm_ctrl.ropes.actuation import load_actuation
    from sim_bus.drive.objects import object_table
    from sim_bus.truth import TrueArm, drive_serials, read_truth

    physical = load_actuation(description)
    if perturb is not None:
        truth = TrueArm.perturbed(physical, perturb)
    elif truth_file is not None:
        truth = read_truth(truth_file, physical)
    else:
        truth = TrueArm.nominal(physical)
    table = object_table()
    vendor, product, revision = (int(table[(OD_IDENTITY, k)].default) for k in (1, 2, 3))
    return BoxIdentity.of(
        {m: DriveIdentity(vendor, product, revision, s) for m, s in drive_serials(truth).items()}
    )


def load_arm(
    description: RobotModel,
    *,
    calibrations: Path | str | None = None,
    uncalibrated: bool = False,
    simulated: bool = False,
    perturb: int | None = None,
    truth_file: Path | None = None,
    prog: str = "hrm",
) -> Arm:
    """The arm of ``description`` with the active calibration of the store
    ``calibrations`` (:func:`calibrations_folder`) for it.

    A damaged calibration, or one for another robot description, is refused
    (:class:`~hrm_ctrl.errors.CalibrationFileError`, one line).  ``uncalibrated`` uses the
    description's values, and the ``note`` says so; so does a ``simulated`` arm's when the
    store has no calibration, or none made on this simulated arm (``perturb``,
    ``truth_file``: :func:`simulated_box_identity`): a calibration of another truth, of a
    real box or of an unknown box is not used on it.  Otherwise no calibration means the
    description's values, and ``active`` None (a drive session refuses to enable).  On a
    real box the drive session checks at the bring-up that the calibration was made on it
    (:mod:`drivers.identity`).
    """
    from calibration.apply import active_for, calibrated_model
    from calibration.store import CalibrationStore

    folder = calibrations_folder(calibrations)
    if uncalibrated:
        note = (
            f"{prog}: --uncalibrated: the robot description's values, not the calibration "
            f"store ({folder})"
        )
        return Arm(description, description, None, note)
    active = active_for(CalibrationStore(folder), description)
    if active is not None and simulated:
        from drivers.identity import box_problems

        box = simulated_box_identity(description, perturb=perturb, truth_file=truth_file)
        problems = box_problems(active.calibration.box, box, active.path)
        if problems:
            made = active.calibration.box
            why = (
                "box unknown (made before calibrations named their box)"
                if made is None
                else "made on another simulated arm"
                if made.simulated
                else "made on a real box"
            )
            note = (
                f"{prog}: --sim: {active.path}: {why}: not used on this simulated arm: the "
                "robot description's values"
            )
            return Arm(description, description, None, note)
    if active is None:
        note = None
        if simulated:
            note = (
                f"{prog}: --sim: no calibration in {folder}: the robot description's values "
                "(a simulated arm; real drives are not enabled without a calibration)"
            )
        return Arm(description, description, None, note)
    return Arm(description, calibrated_model(description, active.calibration), active)
