"""The simulated box (``--sim``): the physical arm it simulates, the box in this process,
and what the entry points do with a running box, wherever it runs (:class:`SimControl`;
:func:`start_simulated_box` starts it in its own process, the default, or in this one).

The drivers only ever see buses: here the configured interfaces are replaced by
in-process buses (python-can ``virtual``, or ``hrm_sim``, the simulated wire at the
configured bitrate) and a :class:`sim_bus.box.SimBox` is started on the other end,
with its tension-sensor board on a pseudo-terminal, which becomes the configuration's
``[tension]`` port (thresholds from the file's table if it has one, else the defaults).
With ``tracker`` the box's laser tracker is started too and its pseudo-terminal becomes
the ``[tracker]`` port.  ``truth`` is how the simulated arm differs from its description
(:class:`sim_bus.truth.TrueArm`; None: it does not), ``fixture`` starts it in its zero
fixture (``box.set_straight_fixture(False)`` frees it).
Host and box take the same :class:`drivers.config.BoxConfig`: the one configuration.

:func:`simulated_arm` is the one choice of what a simulated box simulates: the robot
description's arm (links too, not a calibration's), perturbed or read from a truth file
when asked, its motors standing where the active calibration zeroed them.

>>> sim_listen(True), sim_listen(False)
({'listen_s': 0.1}, {})
"""

from __future__ import annotations

import sys
import uuid
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from hrm_ctrl.errors import DriverError
from sim_bus.in_process import (
    IN_PROCESS_HEARTBEAT_TIMEOUT_MS,
    IN_PROCESS_MISSING_TPDO_CYCLES,
    IN_PROCESS_SDO_TIMEOUT_S,
    IN_PROCESS_SWITCH_INTERVAL_S,
    IN_PROCESS_TENSION_STALE_S,
)

if TYPE_CHECKING:
    import numpy as np

    from calibration.store import Calibration
    from drivers.config import BoxConfig
    from hrm_ctrl.ropes.actuation import Actuation
    from hrm_ctrl.runtime.arm import Arm
    from sim_bus.box import SimBox
    from sim_bus.physics import Physics
    from sim_bus.truth import TrueArm

# the tolerances and why: sim_bus/in_process.py
SIM_MISSING_TPDO_CYCLES = IN_PROCESS_MISSING_TPDO_CYCLES
SIM_SWITCH_INTERVAL_S = IN_PROCESS_SWITCH_INTERVAL_S
SIM_TENSION_STALE_S = IN_PROCESS_TENSION_STALE_S
SIM_HEARTBEAT_TIMEOUT_MS = IN_PROCESS_HEARTBEAT_TIMEOUT_MS
SIM_WIRES = ("virtual", "hrm_sim")  # the buses of a simulated box in this interpreter
#: the buses of a simulated box in its own process (``hrm sim --control``; ``--sim``'s
#: default: :func:`hrm_ctrl.runtime.process_box.simulated_box_process`)
PROCESS_WIRE = "hrm_ipc"
#: SCHED_FIFO priority of the simulated box's threads and of the session's on it, where the
#: process may (best effort, :func:`drivers.realtime.realtime_permitted`; the real box's
#: ``realtime_priority`` stays the configuration's, 0 as shipped).  Low: below the
#: kernel's interrupt threads (50) and below a real-time session's usual priorities.  Beside
#: two CPU burners on the 2-core development machine (load 13-15 from other work besides)
#: ``hrm run --sim`` of the bent-pipe plan with the box in its own process stopped on a
#: missing TPDO or heartbeat in 2 of 2 runs under normal scheduling, 1 of 2 with only the
#: box under FIFO, and 0 of 2 with box and session under FIFO (jitter p99 3-4 ms).
SIM_REALTIME_PRIORITY = 10
# How long a session on the in-process box listens for another master before its first NMT
# reset: the box's buses are private channels of this process (a fresh name each time), so
# no other master can be on them; the listen still runs, shorter than a real bus's 1.1 s.
SIM_LISTEN_S = 0.1


def start_in_process_sim(
    config: BoxConfig,
    actuation: Actuation,
    wire: str = "virtual",
    prog: str = "hrm",
    *,
    truth: TrueArm | None = None,
    tracker: bool = False,
    fixture: bool = False,
    initial_counts: np.ndarray | None = None,
    physics: Physics | None = None,
) -> tuple[BoxConfig, SimBox]:
    """Return the configuration rewritten onto in-process buses and the started box.

    ``actuation`` is the host's rope layer; the box takes the motors and the robot
    description from it, nothing of a calibration it carries (``sim_bus.arm``).  Pass the
    arm's ``truth`` explicitly when the host's actuation is calibrated: the default truth
    (None) is the nominal arm of ``actuation.robot``, whose links may be calibrated ones.
    ``initial_counts`` (n motor counts, the rope layer's order) is where the simulated
    motors stand at power-on (default 0): a simulated box remembers nothing between
    processes, so a command that follows a calibration starts it where the calibration
    left the motors (:func:`calibration_counts`).  ``physics``: the arm's physics
    (``sim_bus.physics``; None: none).

    The simulated drives and tension board run in this interpreter and share its CPU,
    so their TPDOs get ``SIM_MISSING_TPDO_CYCLES`` cycles before the host calls them
    missing, their heartbeats ``SIM_HEARTBEAT_TIMEOUT_MS`` (seen 379-860 ms apart with
    both cores busy), each SDO transfer ``IN_PROCESS_SDO_TIMEOUT_S`` and the tension samples
    ``SIM_TENSION_STALE_S`` before they are stale (a line
    on stderr says so, and the run record keeps the configuration used).
    """
    from drivers.realtime import process_settings
    from sim_bus.box import SimBox

    if wire not in SIM_WIRES:
        raise DriverError(f"--wire must be one of {', '.join(SIM_WIRES)}, got {wire!r}")
    config, raised, tension = sim_tolerances(config)
    tag = uuid.uuid4().hex[:8]
    config = config.with_bus_kwargs(
        [{"interface": wire, "channel": f"hrm-sim-{tag}-{b.name}"} for b in config.buses]
    )
    sim = SimBox(
        config, actuation=actuation, truth=truth, initial_counts=initial_counts, physics=physics
    )
    if fixture:
        sim.set_straight_fixture(True)
    # the box's threads inherit the policy of the thread that starts them
    with process_settings(switch_interval_s=None, realtime_priority=sim_realtime_priority(config)):
        sim.start()
        try:
            config = config.with_tension(port=sim.start_tension_board().port, **tension)
            if tracker:
                config = config.with_tracker(port=sim.start_tracker().port)
        except BaseException:
            sim.stop()
            raise
    if raised:
        print(
            f"{prog}: --sim: {', '.join(raised)} (the simulated box shares this interpreter)",
            file=sys.stderr,
        )
    return config, sim


def sim_tolerances(config: BoxConfig) -> tuple[BoxConfig, list[str], dict[str, Any]]:
    """``config`` with the simulated box's watchdog tolerances (``sim_bus.in_process``)
    where its own are tighter, what was raised (for the stderr line), and the ``[tension]``
    values to take with the simulated board's port.

    Where the process may, the session's threads run under ``SCHED_FIFO`` at
    :data:`SIM_REALTIME_PRIORITY` (the configuration's ``realtime_priority``, unless it
    has one of its own) and so do the box's (:func:`sim_realtime_priority`).

    >>> from drivers.config import load_box_config
    >>> cfg, raised, tension = sim_tolerances(load_box_config(None))
    >>> cfg.control.missing_tpdo_cycles, raised[:2], tension
    (25, ['TPDO tolerance raised to 25 cycles', 'heartbeat timeout to 1000 ms'], {'stale_s': 0.5})
    """
    from drivers.realtime import realtime_permitted

    raised = []
    if config.control.missing_tpdo_cycles < SIM_MISSING_TPDO_CYCLES:
        config = config.with_control(missing_tpdo_cycles=SIM_MISSING_TPDO_CYCLES)
        raised.append(f"TPDO tolerance raised to {SIM_MISSING_TPDO_CYCLES} cycles")
    if config.control.heartbeat_timeout_ms < SIM_HEARTBEAT_TIMEOUT_MS:
        config = config.with_control(heartbeat_timeout_ms=SIM_HEARTBEAT_TIMEOUT_MS)
        raised.append(f"heartbeat timeout to {SIM_HEARTBEAT_TIMEOUT_MS} ms")
    if config.control.sdo_timeout_s < IN_PROCESS_SDO_TIMEOUT_S:
        config = config.with_control(sdo_timeout_s=IN_PROCESS_SDO_TIMEOUT_S)
        raised.append(f"SDO timeout to {IN_PROCESS_SDO_TIMEOUT_S:g} s")
    tension: dict[str, Any] = {}
    if config.tension is None or config.tension.stale_s < SIM_TENSION_STALE_S:
        tension["stale_s"] = SIM_TENSION_STALE_S
        raised.append(f"tension staleness to {SIM_TENSION_STALE_S * 1000:.0f} ms")
    if config.control.realtime_priority == 0 and realtime_permitted(SIM_REALTIME_PRIORITY):
        config = config.with_control(realtime_priority=SIM_REALTIME_PRIORITY)
        raised.append(f"threads under SCHED_FIFO {SIM_REALTIME_PRIORITY}")
    return config, raised, tension


def sim_realtime_priority(config: BoxConfig) -> int:
    """The ``SCHED_FIFO`` priority the simulated box's threads run at: the session's
    (``config`` as :func:`sim_tolerances` left it) where the process may, else 0."""
    from drivers.realtime import realtime_permitted

    priority = config.control.realtime_priority
    return priority if priority and realtime_permitted(priority) else 0


def sim_thread_scheduling(config: BoxConfig) -> AbstractContextManager[Any]:
    """A context in which the caller starts a thread that works beside a session on the
    simulated box before that session exists (a sensor's reader opened first): the
    scheduling the session's threads get there (``SCHED_FIFO`` at
    :func:`sim_realtime_priority` where the process may); the caller's own back on
    leaving."""
    from drivers.realtime import process_settings

    return process_settings(switch_interval_s=None, realtime_priority=sim_realtime_priority(config))


def calibration_counts(calibration: Calibration | None, actuation: Actuation) -> np.ndarray | None:
    """The motor zero counts of a calibration (``calibration.store.Calibration``, or None:
    all 0) in ``actuation``'s motor order: where the motors of a box a calibration has just
    zeroed stand (its ropes at pretension, the arm straight)."""
    import numpy as np

    if calibration is None:
        return None
    zeros = calibration.motor_zero_counts
    return np.array([int(zeros.get(m, 0)) for m in actuation.motor_ids], dtype=np.int64)


def sim_listen(simulated: bool) -> dict[str, float]:
    """The drive session's ``listen_s`` for a session on the in-process box (else none:
    the session's own default)."""
    return {"listen_s": SIM_LISTEN_S} if simulated else {}


@dataclass(frozen=True)
class SimulatedArm:
    """What a simulated box simulates: the ``physical`` rope layer (the robot
    description's), how the arm differs from it (``truth``; None: it does not) and where
    its motors stand at power-on (``initial_counts``; None: 0), and its ``physics``
    (:class:`sim_bus.physics.Physics`; None: none, the arm goes where its ropes' lengths
    put it)."""

    physical: Actuation
    truth: TrueArm | None = None
    initial_counts: np.ndarray | None = None
    physics: Physics | None = None


def simulated_arm(
    arm: Arm,
    *,
    perturb: int | None = None,
    truth_file: Path | None = None,
    physics: Physics | None = None,
) -> SimulatedArm:
    """The simulated arm under ``arm``: the robot description's (links too, not the
    calibration's), or one that differs from it (``perturb``: a seeded
    :meth:`sim_bus.truth.TrueArm.perturbed`; ``truth_file``: :func:`sim_bus.truth.read_truth`),
    its motors at the active calibration's zeros (a box that calibration zeroed), with
    ``physics`` (:class:`sim_bus.physics.Physics`; None: none)."""
    from hrm_ctrl.ropes.actuation import load_actuation
    from sim_bus.truth import TrueArm, read_truth

    physical = load_actuation(arm.description)  # not arm.actuation: its model may be calibrated
    truth = None
    if perturb is not None:
        truth = TrueArm.perturbed(physical, perturb)
    elif truth_file is not None:
        truth = read_truth(truth_file, physical)
    counts = calibration_counts(None if arm.active is None else arm.active.calibration, physical)
    return SimulatedArm(physical, truth, counts, physics)


@dataclass(frozen=True)
class SimulatedBox:
    """A simulated box to start: the arm it simulates, its bus kind (``wire``:
    :data:`PROCESS_WIRE`, the box in its own process; one of :data:`SIM_WIRES`, the box in
    this interpreter), with a laser ``tracker``, its arm in the zero ``fixture``."""

    arm: SimulatedArm
    wire: str = PROCESS_WIRE
    tracker: bool = False
    fixture: bool = False


class SimControl(Protocol):
    """A running simulated box as the entry points command it, in this interpreter
    (:class:`InProcessSim`) or in its own process
    (:class:`~hrm_ctrl.runtime.process_box.BoxProcess`, over its control commands)."""

    def set_straight_fixture(self, on: bool) -> None:
        """Lay the arm into its zero fixture (``on``) or take it out."""
        ...

    def record_trace(self, enabled: bool = True) -> None:
        """Start (clearing) or stop recording every drive's position at each SYNC."""
        ...

    def trace(self) -> tuple[np.ndarray, np.ndarray]:
        """The recorded SYNC times (k,) and motor positions (k, n), the rope layer's order."""
        ...

    def fault(self, spec: str) -> str:
        """Apply the fault ``spec`` (``sim_bus.faults``) now; what was applied."""
        ...

    def stop(self) -> None:
        """Stop the box (its drives, tension board and tracker)."""
        ...


@dataclass(frozen=True)
class InProcessSim:
    """The controls of a simulated box in this interpreter (``box``: the
    :class:`sim_bus.box.SimBox` itself, for what a test inspects)."""

    box: SimBox

    def set_straight_fixture(self, on: bool) -> None:
        self.box.set_straight_fixture(on)

    def record_trace(self, enabled: bool = True) -> None:
        self.box.record_trace(enabled)

    def trace(self) -> tuple[np.ndarray, np.ndarray]:
        return self.box.trace()

    def fault(self, spec: str) -> str:
        from sim_bus.faults import apply_fault, parse_fault

        return apply_fault(parse_fault(spec), self.box, self.box.tension_board)

    def stop(self) -> None:
        self.box.stop()


@dataclass(frozen=True)
class RunningSim:
    """A started simulated box: the configuration rewritten onto its buses, and the box's
    controls (in this interpreter, or a box process)."""

    config: BoxConfig
    sim: SimControl


def start_simulated_box(config: BoxConfig, box: SimulatedBox, prog: str = "hrm") -> RunningSim:
    """Start the simulated box of ``box`` on ``config``'s buses (rewritten): in its own
    process (``wire`` :data:`PROCESS_WIRE`,
    :func:`hrm_ctrl.runtime.process_box.start_box_process`) or in this interpreter (one of
    :data:`SIM_WIRES`); the caller stops it (``.sim.stop()``; :func:`running_box` does
    for a block)."""
    if box.wire == PROCESS_WIRE:
        from hrm_ctrl.runtime.process_box import start_box_process

        new, process = start_box_process(config, box, prog)
        return RunningSim(new, process)
    a = box.arm
    new, sim = start_in_process_sim(
        config,
        a.physical,
        box.wire,
        prog,
        truth=a.truth,
        tracker=box.tracker,
        fixture=box.fixture,
        initial_counts=a.initial_counts,
        physics=a.physics,
    )
    return RunningSim(new, InProcessSim(sim))


@contextmanager
def running_box(config: BoxConfig, box: SimulatedBox, prog: str = "hrm") -> Iterator[RunningSim]:
    """The simulated box of ``box`` on ``config``'s buses (rewritten), started (in its own
    process or this one, :func:`start_simulated_box`); stopped on leaving, whatever ends
    the block."""
    running = start_simulated_box(config, box, prog)
    try:
        yield running
    finally:
        running.sim.stop()
