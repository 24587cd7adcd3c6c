"""One exception root for the whole stack, with a subclass per layer.

Every error the stack raises on bad input or an unsafe state derives from
:class:`HrmError`; the console turns it into a one-line message and a non-zero
exit.  Layers subclass their own branch (``PlanningError`` for the planner,
``RopeError`` for the rope layer, ``DriverError`` for the CAN drivers,
``SimError`` for the simulated box, ``CalibrationError`` for calibration).
"""

from __future__ import annotations


class HrmError(Exception):
    """Root of every error the hrm stack raises on purpose."""


class RobotDescriptionError(HrmError):
    """The robot description (TOML) is missing, malformed or out of range."""


class PlanningError(HrmError):
    """The planner cannot produce a valid plan."""


class PathFileError(PlanningError):
    """A path file (CSV) is missing or malformed."""


class UnreachableError(PlanningError):
    """The backbone solver cannot reach a target with the given length and angles."""


class JointLimitError(PlanningError):
    """A plan breaks a joint limit."""


class PlanFileError(HrmError):
    """A plan file is missing or is not ``hrm-plan/1``."""


class RopeError(HrmError):
    """Rope layer: routing, limits or inverse failures."""


class DriverError(HrmError):
    """CAN drivers: configuration, bring-up, streaming or safety stops."""


class SimError(HrmError):
    """The simulated manipulator box."""


class CalibrationError(HrmError):
    """Calibration input or fit failures."""
