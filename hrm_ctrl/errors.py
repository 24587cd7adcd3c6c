"""One exception root for the whole stack, with a subclass per layer.

Every error the stack raises on bad input or an unsafe state derives from
:class:`HrmError`; the console turns it into a one-line message and a non-zero
exit.  Layers subclass their own branch (``PlanningError`` for the planner,
``RopeError`` for the rope layer, ``DriverError`` for the CAN drivers,
``SimError`` for the simulated box, ``CalibrationError`` for calibration).

The whole tree, each class with the module that defines it::

    Exception (Python standard library)
     +-- HrmError                           hrm_ctrl.errors
     |    +-- RobotDescriptionError         hrm_ctrl.errors
     |    +-- PlanningError                 hrm_ctrl.errors
     |    |    +-- PathFileError            hrm_ctrl.errors
     |    |    +-- UnreachableError         hrm_ctrl.errors
     |    |    +-- JointLimitError          hrm_ctrl.errors
     |    |    +-- CollisionError           hrm_ctrl.errors
     |    |    +-- SceneFileError           hrm_ctrl.formats.scene
     |    |    +-- PointCloudError          hrm_ctrl.formats.pointcloud
     |    |    +-- ScanFitError             hrm_ctrl.planning.scan
     |    |    +-- DriveError               hrm_ctrl.drive.command
     |    +-- PlanFileError                 hrm_ctrl.errors
     |    +-- OverwriteInputError           hrm_ctrl.errors
     |    +-- PlotError                     hrm_ctrl.formats.plots
     |    +-- UrdfWriteError                hrm_ctrl.formats.urdf
     |    +-- RunLogError                   hrm_ctrl.formats.runlog
     |    +-- ViewError                     hrm_ctrl.view.server
     |    +-- ConsoleError                  hrm_ctrl.cli._console.table
     |    +-- RopeError                     hrm_ctrl.errors
     |    |    +-- RoutingError             hrm_ctrl.ropes.routing
     |    |    +-- MotorConfigError         hrm_ctrl.ropes.motor_map
     |    |    +-- RopeInverseError         hrm_ctrl.ropes.inverse
     |    |    +-- RopeLimitError           hrm_ctrl.ropes.actuation
     |    |    +-- JogError                 hrm_ctrl.ropes.jog
     |    |    +-- FeedforwardError         hrm_ctrl.ropes.feedforward
     |    +-- DriverError                   hrm_ctrl.errors
     |    |    +-- FrameError               drivers.protocol.cia301
     |    |    +-- TransitionError          drivers.protocol.cia402
     |    |    +-- BusConfigError           drivers.config
     |    |    +-- BusLoadError             drivers.busload
     |    |    +-- BusSendError             drivers.bus
     |    |    +-- SdoError                 drivers.bringup
     |    |    +-- StateTimeoutError        drivers.bringup
     |    |    +-- BootupError              drivers.bringup
     |    |    +-- IdentityMismatchError    drivers.bringup
     |    |    +-- SetpointError            drivers.safety.limits
     |    |    +-- SupervisorModeError      drivers.safety.supervisor
     |    |    +-- SessionStateError        drivers.lifecycle
     |    |    +-- OtherMasterError         drivers.other_master
     |    |    +-- SafetyStopError          drivers.safety.stops
     |    |    +-- ProcessSettingsError     drivers.realtime
     |    |    +-- TrackerLineError         drivers.protocol.tracker
     |    |    +-- DeviceFileError          drivers.protocol.cia306
     |    |    +-- DeviceCheckError         drivers.device_check
     |    |    +-- BoxIdentityError         drivers.identity
     |    |    +-- LinkStateError           drivers.link_state
     |    |    +-- TrackerError             drivers.tracker
     |    |    |    +-- TrackerTargetLostError drivers.tracker
     |    |    +-- TensionSensorError       drivers.tension_sensor
     |    |         +-- StaleTensionError   drivers.tension_sensor
     |    +-- SimError                      hrm_ctrl.errors
     |    |    +-- DriveSimError            sim_bus.drive
     |    |    +-- WireConfigError          sim_bus.wire
     |    |    +-- FaultSpecError           sim_bus.faults
     |    |    +-- TruthFileError           sim_bus.truth
     |    |    +-- PhysicsSpecError         sim_bus.physics
     |    +-- CalibrationError              hrm_ctrl.errors
     |         +-- CalibrationDataError     hrm_ctrl.errors
     |         +-- UnobservableError        hrm_ctrl.errors
     |         +-- CalibrationFileError     hrm_ctrl.errors
     |         +-- RopeTensionError         calibration.zero
     +-- SdoAbort                           sim_bus.drive.objects
    BaseException (Python standard library)
     +-- SignalInterrupt                    hrm_ctrl.errors
    UserWarning (Python standard library)
     +-- DuplicatePointsWarning             hrm_ctrl.planning.known_path

Some classes are not errors of the stack and stay outside :class:`HrmError`:
``SdoAbort`` carries a CiA 301 abort code inside the simulated drive, whose SDO
server answers it with an abort frame (it never reaches a caller), and
``DuplicatePointsWarning`` is a warning.  :class:`SignalInterrupt` (SIGTERM,
SIGHUP) derives from ``BaseException``, as ``KeyboardInterrupt`` does.  A new
exception derives from its layer's branch and gets its line here:
``tests/hrm_ctrl/test_errors.py`` compares this drawing (names, parents, modules)
with the classes the packages define.
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


class CollisionError(PlanningError):
    """A plan's arm meets an obstacle of its environment (negative clearance)."""


class PlanFileError(HrmError):
    """A plan file is missing or is not ``hrm-plan/1``."""


class OverwriteInputError(HrmError):
    """An output path names a file the command reads (``--out`` naming the plan, ...)."""


class RopeError(HrmError):
    """Rope layer: routing, limits or inverse failures."""


class DriverError(HrmError):
    """CAN drivers: configuration, bring-up, streaming or safety stops."""


class SimError(HrmError):
    """The simulated manipulator box."""


class CalibrationError(HrmError):
    """Calibration input or fit failures."""


class CalibrationDataError(CalibrationError):
    """A calibration data file (or array) is missing, malformed or out of range."""


class UnobservableError(CalibrationError):
    """The data leave a calibration fit ill-conditioned: some parameters are not observable."""


class CalibrationFileError(CalibrationError):
    """A calibration file or store (``calibration.store``) is missing, damaged, of
    another format or robot, or cannot be written."""


class SignalInterrupt(BaseException):
    """SIGTERM or SIGHUP, raised in the main thread like :class:`KeyboardInterrupt` is
    for SIGINT, so every stop path that handles Ctrl-C handles them the same way."""

    def __init__(self, signal_name: str, signal_number: int = 0) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name
        self.signal_number = signal_number


def interrupting_signal(exc: BaseException | None) -> str | None:
    """The name of the signal ``exc`` stands for (Ctrl-C is SIGINT), else ``None``.

    >>> interrupting_signal(KeyboardInterrupt()), interrupting_signal(SignalInterrupt("SIGTERM"))
    ('SIGINT', 'SIGTERM')
    >>> interrupting_signal(RuntimeError("boom")) is None
    True
    """
    if isinstance(exc, SignalInterrupt):
        return exc.signal_name
    return "SIGINT" if isinstance(exc, KeyboardInterrupt) else None
