"""Every drive of the box at once: each bring-up step of :mod:`drivers.bringup` carried
out on all the session's drives in parallel (:mod:`drivers.parallel`), bounded in time.

The session (:mod:`drivers.session`) decides which step comes when; a
:class:`DriveGroup` carries each one out on every drive and says what it found:

- after an NMT reset, every node's boot-up within the boot-up timeout (the error lists
  the missing ones), and no node that booted twice (two devices answering as one; a
  second boot-up that comes after the configuration began is a second device when the
  node answers one SDO request twice: :meth:`DriveGroup.refuse_late_duplicates`);
- the SDO configuration (:meth:`DriveGroup.configure`, :func:`drivers.bringup.configure_drive`
  per drive: PDO mappings, heartbeat times, software limits 0x607D from the rope layer,
  interpolation period, CSP);
- the CiA 402 state machine to OPERATION_ENABLED (:meth:`DriveGroup.enable`: the actual
  positions inside the limits, returned in the rope layer's order);
- the checks before an enable (drives in FAULT) and before a stream (every drive
  OPERATION_ENABLED), the controlled disable, the quick stop after a failed enable, the
  fault reset and the read-outs (statusword, actual position).

Each step's time bound is its count of SDO transfers and CiA 402 transitions per drive
(:func:`drivers.parallel.budget_s`): a drive still busy after it is named, and the first
failure is raised as itself (its class and fields kept), logged in the event log first.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar

import numpy as np

from drivers.bringup import (
    FAULTY,
    BootupError,
    DriveLink,
    DriveSettings,
    DriveSetup,
    check_identity,
    configure_drive,
    disable_unless_faulty,
    enable_operation,
    quick_stop,
    read_state,
    read_status,
    reset_to_ready,
    sdo_answers,
    sdo_read,
)
from drivers.config import ControlConfig
from drivers.cycle import EventLog
from drivers.identity import BoxIdentity
from drivers.other_master import duplicate_boot_text
from drivers.parallel import budget_s, run_parallel, sdo_transfer_s
from drivers.protocol import cia402
from drivers.rope_model import MotorLimits
from drivers.safety.monitor import NodeMonitor
from drivers.wiring import MotorSlots
from hrm_ctrl.errors import DriverError

__all__ = [
    "CONFIG_SDO_TRANSFERS",
    "ENABLE_SDO_TRANSFERS",
    "ENABLE_TRANSITIONS",
    "DriveGroup",
]

# Upper bounds of the parallel SDO work, in SDO transfers / CiA 402 transitions per drive
# (each transfer may take (1 + retries) SDO timeouts; each transition the state timeout).
CONFIG_SDO_TRANSFERS = 48
ENABLE_TRANSITIONS = 7
ENABLE_SDO_TRANSFERS = 12
_T = TypeVar("_T")


class DriveGroup:
    """The drives of a session: their SDO ``links`` in slot order (the rope layer's
    motor order, ``slots``), the limits ``actuation`` gives each, the session's
    ``control`` settings, its node ``monitor`` (boot-ups) and its event log."""

    def __init__(
        self,
        links: Sequence[DriveLink],
        slots: MotorSlots,
        actuation: MotorLimits,
        control: ControlConfig,
        monitor: NodeMonitor,
        events: EventLog,
        setups: Mapping[str, DriveSetup] | None = None,
    ) -> None:
        self.setups = {} if setups is None else dict(setups)  # per motor, from its device file
        self.links = links
        self.slots = slots
        self.actuation = actuation
        self.control = control
        self.monitor = monitor
        self.events = events

    @property
    def sdo_transfer_s(self) -> float:
        """Longest one SDO transfer can take (timeout x (1 + canopen's retries))."""
        return sdo_transfer_s(self.control.sdo_timeout_s)

    def budget_s(self, transfers: int, transitions: int = 0) -> float:
        """Time bound of parallel work of ``transfers`` SDO transfers and ``transitions``
        CiA 402 transitions per drive."""
        ctl = self.control
        return budget_s(ctl.sdo_timeout_s, ctl.state_timeout_s, transfers, transitions)

    def parallel(self, what: str, fn: Callable[[DriveLink], _T], timeout_s: float) -> list[_T]:
        """``fn`` for every drive at once, in slot order (:func:`run_parallel`: the first
        error raised as itself, or the drives still busy after ``timeout_s`` named)."""
        return run_parallel(
            what,
            fn,
            self.links,
            timeout_s,
            label=lambda link: link.label,
            on_error=lambda text: self.events.add("error", text),
        )

    def settings(self, link: DriveLink) -> DriveSettings:
        """What the configuration writes to ``link``'s drive (its limits: the rope
        layer's, read now)."""
        ctl = self.control
        act = self.actuation
        slot = self.slots.slot[link.motor]
        return DriveSettings(
            period_s=ctl.period_s,
            host_node_id=ctl.host_node_id,
            host_heartbeat_timeout_ms=ctl.heartbeat_timeout_ms,
            node_heartbeat_ms=ctl.node_heartbeat_ms,
            counts_min=int(act.counts_min[slot]),
            counts_max=int(act.counts_max[slot]),
            following_error_window_counts=ctl.following_error_window_counts,
            quick_stop_option_code=ctl.quick_stop_option_code,
            setup=self.setups.get(link.motor, DriveSetup()),
        )

    def check_identities(self, box: BoxIdentity) -> None:
        """Every drive's identity (read at boot, ``box``) against the one its box
        configuration expects (:func:`check_identity`), before anything is written; the
        first mismatch raised (and logged)."""
        for link in self.links:
            expected = self.setups.get(link.motor, DriveSetup()).identity
            found = box.drives[link.motor]
            values = (found.vendor_id, found.product_code, found.revision, found.serial)
            try:
                check_identity(link, expected, values, box.simulated)
            except DriverError as exc:
                self.events.add("error", str(exc))
                raise

    # ------------------------------------------------------------------ bring-up
    def await_bootup(self, reset_at: float, t_start: float) -> None:
        """Every node's boot-up after the NMT reset sent at ``reset_at`` (the monitor's
        clock), within the boot-up timeout; else :class:`BootupError` naming the missing
        nodes.  Then :meth:`refuse_duplicate_nodes`."""
        timeout_s = self.control.bootup_timeout_s
        if not self.monitor.boot_event.wait(timeout_s):
            missing = self.monitor.describe_missing_boot(reset_at)
            raise BootupError(
                f"no boot-up within {timeout_s:g} s from {len(missing)} node(s): "
                + "; ".join(missing)
            )
        self.events.add("bootup", f"every node booted ({time.monotonic() - t_start:.3f} s)")
        self.refuse_duplicate_nodes()

    def refuse_duplicate_nodes(self) -> None:
        """:class:`BootupError` if a node booted more than once after the one NMT reset:
        two devices answer as that node (a second box, or a simulator, on the same bus; a
        node-id clash), and each SDO request would get two answers."""
        text = duplicate_boot_text(self.monitor.describe_duplicate_boot())
        if text is not None:
            self.events.add("error", text)
            raise BootupError(text)

    def refuse_late_duplicates(self) -> None:
        """:class:`BootupError` (logged) naming the nodes that booted again after every
        node's first boot-up (:attr:`NodeMonitor.rebooted`: since the configuration
        began) and answer one SDO request more than once (:func:`sdo_answers`, waiting
        ``sdo_timeout_s``): a second device's boot-ups, late (a second box whose
        answers came after the boot-up window), while the configured device keeps
        answering.  A node that answers once rebooted by itself (a brown-out): left to
        the enable's refusal, which names it so."""
        mon = self.monitor
        slot = self.slots.slot
        suspects = [link for link in self.links if mon.rebooted[slot[link.motor]]]
        if not suspects:
            return
        wait_s = self.control.sdo_timeout_s
        answers = run_parallel(
            "second-device check",
            lambda link: sdo_answers(link, wait_s),
            suspects,
            wait_s + self.budget_s(1),
            label=lambda link: link.label,
            on_error=lambda text: self.events.add("error", text),
        )
        twice = [
            f"{mon.labels[slot[link.motor]]}: {int(mon.bootups[slot[link.motor]])} boot-ups, "
            f"{n} answers to one SDO request"
            for link, n in zip(suspects, answers, strict=True)
            if n > 1
        ]
        text = duplicate_boot_text(twice)
        if text is not None:
            self.events.add("error", text)
            raise BootupError(text)

    def configure(self) -> None:
        """The SDO configuration of every drive (:func:`configure_drive` with
        :meth:`settings`).  A failure is first checked for a node that booted twice
        (a second device's boot-up may come after every node's first: two answers to
        each SDO request fail the configuration, and that is then the error)."""
        try:
            self.parallel(
                "configuration",
                lambda link: configure_drive(link, self.settings(link)),
                self.budget_s(CONFIG_SDO_TRANSFERS),
            )
        except DriverError:
            self.refuse_duplicate_nodes()
            raise
        self.events.add("configured", "every drive configured by SDO (CSP, PDOs, limits)")

    def enable(self) -> np.ndarray:
        """Every drive to OPERATION_ENABLED (:func:`enable_operation`, its actual position
        checked against its limits); the actual positions (counts, slot order)."""
        timeout_s = self.control.state_timeout_s

        def enable_one(link: DriveLink) -> int:
            s = self.settings(link)
            return enable_operation(
                link, timeout_s, counts_min=s.counts_min, counts_max=s.counts_max
            )

        actual = self.parallel(
            "enable", enable_one, self.budget_s(ENABLE_SDO_TRANSFERS, ENABLE_TRANSITIONS)
        )
        return np.array(actual, dtype=np.int64)  # (the links are in slot order)

    def in_fault(self) -> list[str]:
        """The drives in FAULT (or on their way into it), read by SDO: each's label and
        statusword."""
        states = self.parallel("state check", read_state, self.budget_s(1))
        return [
            f"{link.label} (statusword 0x{sw:04X})"
            for link, (state, sw) in zip(self.links, states, strict=True)
            if state in FAULTY
        ]

    def check_operation_enabled(self) -> None:
        """Before the first RPDO of a stream: every drive's statusword (SDO upload of
        0x6041, in parallel, with timeouts) must show OPERATION_ENABLED; else
        :class:`DriverError` naming the motors and their states (nothing is sent)."""
        states = self.parallel("statusword check", read_state, self.budget_s(1))
        bad = [
            f"{link.label} statusword 0x{sw:04X} ({state.name})"
            for link, (state, sw) in zip(self.links, states, strict=True)
            if state is not cia402.State402.OPERATION_ENABLED
        ]
        if bad:
            text = f"stream refused: not OPERATION_ENABLED: {', '.join(bad)}"
            self.events.add("error", text)
            raise DriverError(text)

    # ------------------------------------------------------------------ stopping
    def disable(self, what: str) -> None:
        """Controlled disable of every drive by SDO along the CiA 402 transition table
        (:func:`drivers.bringup.disable`): from OPERATION_ENABLED *disable operation*
        then *shutdown*; from QUICK_STOP_ACTIVE or SWITCH_ON_DISABLED (after a quick stop)
        to READY_TO_SWITCH_ON (power stage off), each step confirmed by the statusword.
        No target position is sent.  A drive in FAULT is left there (a fault is reset
        only on purpose).  Raises naming the drives that failed (the others are still
        disabled)."""
        timeout_s = self.control.state_timeout_s
        self.parallel(
            what, lambda link: disable_unless_faulty(link, timeout_s), self.budget_s(1, 3)
        )

    def quick_stop(self, what: str) -> None:
        """The quick-stop controlword by SDO to every drive (no target is written)."""
        self.parallel(what, quick_stop, self.budget_s(1))

    def reset_faults(self) -> list[str]:
        """The fault reset of every drive in FAULT, then every drive to
        READY_TO_SWITCH_ON (:func:`reset_to_ready`); the labels of the drives that were
        in FAULT."""
        timeout_s = self.control.state_timeout_s
        was_faulty = self.parallel(
            "fault reset", lambda link: reset_to_ready(link, timeout_s), self.budget_s(2, 4)
        )
        return [link.label for link, f in zip(self.links, was_faulty, strict=True) if f]

    # ------------------------------------------------------------------ read-outs
    def statuses(self) -> list[tuple[int, int] | None]:
        """Every drive's (statusword, actual position) by SDO; None for a drive that does
        not answer."""
        return self.parallel("status", read_status, self.budget_s(2))

    def actual_positions(self) -> np.ndarray:
        """Every drive's actual position (0x6064, counts, slot order) by SDO; a drive that
        does not answer raises :class:`DriverError`."""
        values = self.parallel(
            "actual positions",
            lambda link: int(sdo_read(link, cia402.OD_POSITION_ACTUAL_VALUE)),
            self.budget_s(1),
        )
        return np.array(values, dtype=np.int64)
