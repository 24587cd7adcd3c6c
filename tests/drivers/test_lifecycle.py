"""drivers/lifecycle.py: the session's transition table, state by call."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import pytest

from drivers.lifecycle import (
    TRANSITIONS,
    Call,
    SessionState,
    SessionStateError,
    after_stop,
    allowed_from,
    next_state,
)
from tests.drivers.driver_rig import Rig

S = SessionState
LIVE = [s for s in S if s is not S.CLOSED]
CONFIGURABLE = [S.CONNECTED, S.READY, S.ENABLED, S.STOPPED, S.FAULT]

# What each call may do, written out from the session's documented behaviour (not read
# back from the table): state allowed in -> state on success.
EXPECTED: dict[Call, dict[SessionState, SessionState]] = {
    Call.CONFIGURE: {s: S.READY for s in CONFIGURABLE},
    Call.BRING_UP: {s: S.ENABLED for s in CONFIGURABLE},
    Call.ENABLE: {S.READY: S.ENABLED},
    Call.STREAM: {S.ENABLED: S.STREAMING},
    Call.DISABLE: {S.ENABLED: S.READY, S.STOPPED: S.READY},
    Call.RESET_FAULT: {S.STOPPED: S.READY, S.FAULT: S.READY, S.READY: S.READY},
    Call.ACTUAL_POSITIONS: {s: s for s in CONFIGURABLE},
    Call.FINISH: {s: S.CONNECTED for s in LIVE},
}


def test_every_call_is_in_the_expectations() -> None:
    assert set(EXPECTED) == set(Call)


@pytest.mark.parametrize(
    ("state", "call"), list(itertools.product(SessionState, Call)), ids=lambda x: x.name
)
def test_every_state_and_call_is_allowed_or_refused_as_expected(
    state: SessionState, call: Call
) -> None:
    target = EXPECTED[call].get(state)
    if target is not None:
        assert next_state(state, call) is target
        assert state in allowed_from(call)
        return
    with pytest.raises(SessionStateError) as info:
        next_state(state, call)
    err = info.value
    assert (err.state, err.call) == (state, call)  # the error keeps its fields
    assert str(err).startswith(f"{call.value}: ")
    if state is S.CLOSED:
        assert str(err) == f"{call.value}: the session is closed"
    else:
        names = ", ".join(s.name for s in SessionState if s in EXPECTED[call])
        assert str(err) == f"{call.value}: not allowed in state {state.name} (only from {names})"


def test_the_table_lists_nothing_else() -> None:
    assert dict(TRANSITIONS) == {
        (s, call): target for call, by_state in EXPECTED.items() for s, target in by_state.items()
    }
    with pytest.raises(TypeError):
        TRANSITIONS[(S.CLOSED, Call.ENABLE)] = S.ENABLED  # type: ignore[index]


class _Stop:
    def __init__(self, failed: list[Any], unconfirmed: list[str], while_streaming: bool) -> None:
        self.failed, self.unconfirmed, self.while_streaming = failed, unconfirmed, while_streaming


class _Cause:
    text = "bus0: send failed"


@pytest.mark.parametrize(
    ("stop", "state", "error"),
    [
        (_Stop([], [], True), S.STOPPED, None),
        (_Stop([], [], False), S.STOPPED, None),
        (_Stop([_Cause()], [], True), S.FAULT, "quick stop failed: bus0: send failed"),
        (
            _Stop([], ["j01r0"], False),
            S.FAULT,
            "quick stop while idle failed: not confirmed by j01r0 (sent NMT pre-operational; "
            "bring the drives up again)",
        ),
    ],
)
def test_a_stop_leaves_stopped_or_fault(
    stop: _Stop, state: SessionState, error: str | None
) -> None:
    assert after_stop(stop) == (state, error)  # type: ignore[arg-type]


def test_the_session_refuses_through_the_table(rig_factory: Callable[..., Rig]) -> None:
    """Every call of a closed session is refused by the table, sending nothing."""
    rig = rig_factory()
    box = rig.open_box()
    box.close()
    rig.box = None
    calls: dict[Call, Callable[[], Any]] = {
        Call.CONFIGURE: box.configure,
        Call.ENABLE: box.enable,
        Call.BRING_UP: box.bring_up,
        Call.DISABLE: box.disable,
        Call.RESET_FAULT: box.reset_fault,
        Call.ACTUAL_POSITIONS: box.actual_positions,
        Call.FINISH: box.finish,
    }
    box.allow_uncalibrated = True  # (the calibration is checked before the state)
    for call, fn in calls.items():
        with pytest.raises(SessionStateError, match=f"^{call.value}: the session is closed$"):
            fn()
