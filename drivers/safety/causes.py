"""Why the box stopped: the kinds of stop cause (an enum) and one cause.

Every stop of the box (a quick stop of every axis on every bus) carries one or
more :class:`StopCause`: a :class:`StopKind`, a one-line text naming the motor,
bus or node, the motor's label when one motor is to blame, and the monotonic time
it was detected.

>>> cause = StopCause(StopKind.EMCY, "j07r0 (bus bus1 node 3): EMCY 0x8611", "j07r0", 1.5)
>>> cause.to_dict()["kind"], cause.kind == "emcy"
('emcy', True)
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any


class StopKind(StrEnum):
    """What stopped the box (the run record keeps the value)."""

    HEARTBEAT = "heartbeat"  # a drive's heartbeat lost, or it reports a wrong NMT state
    EMCY = "emcy"  # a drive sent an emergency
    FAULT = "fault"  # a statusword with the fault bit
    STATE = "state"  # a drive left OPERATION_ENABLED
    TPDO_MISSING = "tpdo_missing"  # no feedback for the configured number of cycles
    BAD_FRAME = "bad_frame"  # a malformed frame of a CANopen service
    BOOTUP = "bootup"  # a drive rebooted while enabled
    LIMIT = "limit"  # a setpoint refused by the rope or joint limits
    TENSION = "tension"  # a rope's tension out of range, or the tension sensor failing
    ROPE = "rope"  # a rope whose length stops fitting the others (slipped or broken)
    FOREIGN = "foreign"  # traffic of another master for our nodes (RPDO, SYNC, NMT)
    SIGNAL = "signal"  # SIGTERM / SIGHUP / SIGINT
    SEND = "send"  # a frame could not be sent
    RECEIVE = "receive"  # a bus's receive thread failed
    BUS_ERROR = "bus_error"  # an error frame: a bus's controller bus-off or error-passive
    OPERATOR = "operator"  # stop requested (console, Ctrl-C)
    INTERNAL = "internal"  # the control loop itself failed (a bug)


@dataclass(frozen=True)
class StopCause:
    """One reason to stop: kind, one-line text, the motor to blame (if one), when."""

    kind: StopKind
    text: str
    motor: str | None = None
    time_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind.value,
            "text": self.text,
            "motor": self.motor,
            "time_s": self.time_s,
        }


def unique_causes(causes: list[StopCause]) -> list[StopCause]:
    """The first cause of each (kind, motor or text), in order.

    >>> a = StopCause(StopKind.HEARTBEAT, "m0: lost", "m0")
    >>> [x.text for x in unique_causes([a, a, StopCause(StopKind.EMCY, "m0: emcy", "m0")])]
    ['m0: lost', 'm0: emcy']
    """
    unique: dict[tuple[StopKind, str], StopCause] = {}
    for x in causes:
        unique.setdefault((x.kind, x.motor or x.text), x)
    return list(unique.values())
