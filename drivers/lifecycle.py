"""The drive session's states and the one table of its transitions.

Modelled on ros2_control's hardware lifecycle: a session is in one primary state
(:class:`SessionState`); each call a caller makes (:class:`Call`) is allowed from some
states and leads to one state on success (:data:`TRANSITIONS`).  :func:`next_state` is
the one place a call is checked: a call the table does not list for the state raises
:class:`SessionStateError` (one line, before anything is sent).

.. code-block:: text

    CLOSED --open--> CONNECTED --configure--> READY --enable--> ENABLED
                        ^                        ^                | ^
                        |                        |          stream| |completed
                        |                        +--disable--+    v |
                        +-------finish---------- STOPPED <-- STREAMING
                                                 FAULT   (a stop that failed)

Besides the calls, two things move a session that are not in the table: the supervisor's
stop (any cause, in any state the drives are live in: -> STOPPED, or FAULT when the quick
stop itself could not be sent) and a call that fails half-way (-> FAULT where the drives'
state is then unknown, e.g. an enable or a disable that failed); a stream's end takes
STREAMING back to ENABLED.  :meth:`~drivers.session.DriveSession.close` is allowed in
every state (-> CLOSED).

>>> next_state(SessionState.READY, Call.ENABLE).name
'ENABLED'
>>> next_state(SessionState.CONNECTED, Call.STREAM)
Traceback (most recent call last):
...
drivers.lifecycle.SessionStateError: stream: not allowed in state CONNECTED (only from ENABLED)
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import Enum
from types import MappingProxyType
from typing import TYPE_CHECKING

from hrm_ctrl.errors import DriverError

if TYPE_CHECKING:
    from drivers.safety.supervisor import StopRecord


class SessionState(Enum):
    """Where a :class:`~drivers.session.DriveSession` is."""

    CLOSED = "closed"
    CONNECTED = "connected"  # buses open; drives pre-operational or unknown
    READY = "ready"  # every drive configured and operational, power stage off
    ENABLED = "enabled"  # every drive OPERATION_ENABLED, supervised, holding
    STREAMING = "streaming"
    STOPPED = "stopped"  # quick-stopped by a stop cause
    FAULT = "fault"  # a stop, bring-up or disable that could not be carried out


class SessionStateError(DriverError):
    """A session call refused in the session's current state.  ``state`` is the state it
    was refused in, ``call`` the call (None: refused for another reason in that state)."""

    def __init__(
        self, message: str, state: SessionState | None = None, call: Call | None = None
    ) -> None:
        super().__init__(message)
        self.state = state
        self.call = call


class Call(Enum):
    """A call a caller makes on a session; the value is how messages name it."""

    CONFIGURE = "configure"
    ENABLE = "enable"
    BRING_UP = "bring-up"
    STREAM = "stream"
    DISABLE = "disable"
    RESET_FAULT = "reset-fault"
    ACTUAL_POSITIONS = "actual positions"
    FINISH = "finish"


S = SessionState
_CONFIGURABLE = (S.CONNECTED, S.READY, S.ENABLED, S.STOPPED, S.FAULT)
_LIVE = tuple(s for s in S if s is not S.CLOSED)

#: (state, call) -> the state the call leads to when it succeeds.  A pair not listed is
#: refused.  Configure resets the drives (from ENABLED they are disabled first, never reset
#: while enabled); reset-fault and disable end power stage off (READY); finish leaves the
#: drives pre-operational (CONNECTED); reading the actual positions keeps the state.
TRANSITIONS: Mapping[tuple[SessionState, Call], SessionState] = MappingProxyType(
    {
        **{(s, Call.CONFIGURE): S.READY for s in _CONFIGURABLE},
        **{(s, Call.BRING_UP): S.ENABLED for s in _CONFIGURABLE},
        (S.READY, Call.ENABLE): S.ENABLED,
        (S.ENABLED, Call.STREAM): S.STREAMING,
        (S.ENABLED, Call.DISABLE): S.READY,
        (S.STOPPED, Call.DISABLE): S.READY,
        **{(s, Call.RESET_FAULT): S.READY for s in (S.STOPPED, S.FAULT, S.READY)},
        **{(s, Call.ACTUAL_POSITIONS): s for s in _CONFIGURABLE},
        **{(s, Call.FINISH): S.CONNECTED for s in _LIVE},
    }
)
del S


def allowed_from(call: Call) -> tuple[SessionState, ...]:
    """The states ``call`` is allowed in, in :class:`SessionState`'s order.

    >>> [s.name for s in allowed_from(Call.DISABLE)]
    ['ENABLED', 'STOPPED']
    """
    return tuple(s for s in SessionState if (s, call) in TRANSITIONS)


def next_state(state: SessionState, call: Call) -> SessionState:
    """The state ``call`` leads to from ``state``; :class:`SessionStateError` if the table
    does not allow it there.

    >>> next_state(SessionState.CLOSED, Call.FINISH)
    Traceback (most recent call last):
    ...
    drivers.lifecycle.SessionStateError: finish: the session is closed
    """
    target = TRANSITIONS.get((state, call))
    if target is not None:
        return target
    if state is SessionState.CLOSED:
        raise SessionStateError(f"{call.value}: the session is closed", state, call)
    names = ", ".join(s.name for s in allowed_from(call))
    raise SessionStateError(
        f"{call.value}: not allowed in state {state.name} (only from {names})", state, call
    )


def after_stop(stop: StopRecord) -> tuple[SessionState, str | None]:
    """The state the supervisor's stop leaves a session in, and why the quick stop failed
    (None: it did not): STOPPED, or FAULT when a quick stop could not be sent or a drive
    never confirmed it (still enabled for all the host knows: not a stop to recover from).

    >>> from types import SimpleNamespace as NS
    >>> after_stop(NS(failed=[], unconfirmed=[], while_streaming=True))
    (<SessionState.STOPPED: 'stopped'>, None)
    >>> after_stop(NS(failed=[], unconfirmed=["m0"], while_streaming=False))[1][:40]
    'quick stop while idle failed: not confir'
    """
    problems = [x.text for x in stop.failed]
    if stop.unconfirmed:
        problems.append(
            f"not confirmed by {', '.join(stop.unconfirmed)} (sent NMT pre-operational; "
            "bring the drives up again)"
        )
    if not problems:
        return SessionState.STOPPED, None
    where = "" if stop.while_streaming else " while idle"
    return SessionState.FAULT, f"quick stop{where} failed: " + "; ".join(problems)
