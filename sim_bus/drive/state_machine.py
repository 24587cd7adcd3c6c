"""CiA 402 device control of a simulated drive: the state machine and the statusword.

A controlword (written by SDO or carried by the RPDO) is decoded to a command
(:func:`drivers.protocol.cia402.decode_command`) and applied through the one
transition table, :data:`drivers.protocol.cia402.TRANSITIONS`; the fault reset
is the 0→1 edge of bit 7.  A command without a transition from the present
state leaves the drive where it is, as a drive does with a controlword it holds
(the RPDO repeats it every cycle).  Transition 16 (quick stop active →
operation enabled) needs a quick stop option code 5..8 and a standing motor.

Quick stop (11, and the host-heartbeat or NMT reactions) follows 0x605A: 0
coasts to switch on disabled at once; 1..4 ramp down then switch on disabled
(12); 5..8 ramp down and stay in quick stop active.  A fault (13) enters fault
reaction active, sends the EMCY, ramps down, then FAULT (14).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.protocol import cia301, cia402
from sim_bus.drive.objects import SdoAbort

if TYPE_CHECKING:
    from sim_bus.drive import DriveSim

State = cia402.State402
Command = cia402.Command402

QUICK_STOP_OPTION_RANGE = range(0, 9)  # the option codes this drive implements (0..8)


class StateMachine402:
    """Power drive system state of one drive (CiA 402 figure 13)."""

    def __init__(self, drive: DriveSim) -> None:
        self._drive = drive
        self._od = drive.od
        self.state = State.SWITCH_ON_DISABLED
        self._last_cw = 0

    def reset(self) -> None:
        """Power-on: switch on disabled (transitions 0 and 1 done), no controlword seen."""
        self.state = State.SWITCH_ON_DISABLED
        self._last_cw = 0

    @property
    def quick_stop_option(self) -> int:
        return self._od.int_value(cia402.OD_QUICK_STOP_OPTION_CODE)

    @property
    def decelerating(self) -> bool:
        """True in the states that ramp the motor down by themselves."""
        return self.state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)

    @property
    def statusword(self) -> int:
        drive = self._drive
        motion = drive.motion
        sw = cia402.STATUSWORD_OF_STATE[self.state] | cia402.SW_REMOTE
        if self.state != State.NOT_READY_TO_SWITCH_ON:
            sw |= cia402.SW_VOLTAGE_ENABLED
        if drive.warning:
            sw |= cia402.SW_WARNING
        if motion.limit_active:
            sw |= cia402.SW_INTERNAL_LIMIT_ACTIVE
        if self.state == State.OPERATION_ENABLED and motion.mode == cia402.MODE_CSP:
            sw |= cia402.SW_CSP_DRIVE_FOLLOWS_COMMAND
        if motion.following_error:
            sw |= cia402.SW_CSP_FOLLOWING_ERROR
        return sw

    # ---------------------------------------------------------------- device control
    def on_controlword(self, cw: int, now: float) -> None:
        """Device control (CiA 402 table 31): apply one controlword."""
        rising_reset = bool(cw & cia402.CW_BIT_FAULT_RESET) and not (
            self._last_cw & cia402.CW_BIT_FAULT_RESET
        )
        self._last_cw = cw
        command = cia402.decode_command(cw)
        if command is Command.FAULT_RESET and not rising_reset:
            return  # bit 7 held high: only its 0→1 edge is a fault reset
        if not cia402.has_transition(self.state, command):
            return  # no transition from this state on this command: the drive stays
        transition = cia402.transition(self.state, command)
        if transition.numbers == (16,) and not (
            self.quick_stop_option in cia402.QUICK_STOP_OPTIONS_STAY
            and self._drive.motion.velocity == 0.0
        ):
            return  # 16 only after a stop that stays in quick stop active
        self._take(transition, now)

    def _take(self, transition: cia402.Transition, now: float) -> None:
        if transition.target == State.OPERATION_ENABLED:  # 4, 3+4, 16
            self.enable_operation()
        elif transition.target == State.QUICK_STOP_ACTIVE:  # 11
            self._drive.log("quick stop commanded")
            self.quick_stop(now)
        elif transition.source == State.FAULT:  # 15
            self._fault_reset()
        else:
            if transition.source in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
                self._drive.motion.velocity = 0.0  # 5, 8, 9, 12: the brake holds
            self.state = transition.target

    def enable_operation(self) -> None:
        """Enter operation enabled with the target set to the actual position: nothing moves
        until a new target arrives (an RPDO buffered before is dropped)."""
        motion = self._drive.motion
        self.state = State.OPERATION_ENABLED
        self._od.write((cia402.OD_TARGET_POSITION, 0), motion.position_counts)
        motion.velocity = 0.0
        self._drive.pdo.discard_buffered()

    def quick_stop(self, now: float) -> None:
        """Transition 11 (operation enabled → quick stop active) and the 0x605A reaction."""
        self.state = cia402.next_state(self.state, Command.QUICK_STOP)
        if self.quick_stop_option == cia402.QUICK_STOP_OPTION_DISABLE_DRIVE:
            self._drive.motion.velocity = 0.0
            self.state = State.SWITCH_ON_DISABLED
            return
        if self._drive.motion.velocity == 0.0:
            self.stopped()

    def stopped(self) -> None:
        """The motor came to a standstill while decelerating: the automatic transitions."""
        if self.state == State.FAULT_REACTION_ACTIVE:
            self.state = cia402.AUTOMATIC_SUCCESSOR[self.state]  # 14
        elif self.state == State.QUICK_STOP_ACTIVE:
            if self.quick_stop_option in cia402.QUICK_STOP_OPTIONS_THEN_DISABLED:
                self.state = State.SWITCH_ON_DISABLED  # 12

    def fault(self, code: int, now: float, why: str, extra: bytes = b"") -> None:
        """Enter fault reaction active (transition 13) and send the EMCY."""
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        drive = self._drive
        drive.log(f"fault 0x{code:04X}: {why}")
        drive.error_code = code
        drive.error_register |= cia301.ERR_REG_GENERIC | (
            cia301.ERR_REG_MANUFACTURER if code >= 0xFF00 else 0
        )
        self.state = State.FAULT_REACTION_ACTIVE
        drive.emcy(code, extra)
        if drive.motion.velocity == 0.0:
            self.state = State.FAULT

    def _fault_reset(self) -> None:
        """Transition 15: errors cleared (a heartbeat still missing keeps the warning)."""
        drive = self._drive
        self.state = State.SWITCH_ON_DISABLED
        drive.error_code = 0
        drive.warning = bool(drive.nmt.lost)
        # a heartbeat still lost is an error still present (its register bits stay)
        lost = cia301.ERR_REG_COMMUNICATION | cia301.ERR_REG_GENERIC
        drive.error_register = lost if drive.warning else 0
        drive.motion.following_error = False
        drive.emcy(cia301.EMCY_NO_ERROR)

    # ---------------------------------------------------------------- objects
    def check_write(self, index: int, sub: int, value: int) -> None:
        if index == cia402.OD_QUICK_STOP_OPTION_CODE and value not in QUICK_STOP_OPTION_RANGE:
            raise SdoAbort(cia301.SDO_ABORT_INVALID_VALUE)
