"""The keyboard's steering: hold-to-move from key presses and the time, the speed cap,
the stop keys, the terminal's escape sequences."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.drive.command import DriveError, SteerLimits
from hrm_ctrl.drive.keymap import (
    ControlKey,
    HoldTiming,
    KeyboardSteer,
    KeyInput,
    KeyState,
    command_at,
    decode_terminal,
    next_state,
    release_deadline_s,
)
from hrm_ctrl.drive.script import SteerKey

LIM = SteerLimits()
TIMING = HoldTiming(first_hold_s=0.5, repeat_hold_s=0.2)


def _fold(events: list[KeyInput]) -> KeyState:
    s = KeyState()
    for e in events:
        s = next_state(s, e)
    return s


def test_a_held_key_auto_repeating_moves_without_a_gap_and_stops_after_its_last_repeat() -> None:
    # the terminal's auto-repeat: first press, 0.45 s initial delay, then every 33 ms
    presses = [0.0] + [0.45 + 0.033 * i for i in range(30)]
    s = KeyState()
    seen = []
    t = 0.0
    events = iter(presses)
    nxt = next(events)
    while t < 2.0:
        while nxt is not None and nxt <= t:
            s = next_state(s, KeyInput(SteerKey.ADVANCE, nxt))
            nxt = next(events, None)
        seen.append((t, command_at(s, t, LIM, TIMING).advance_mm_s))
        t = round(t + 0.01, 10)
    last = presses[-1]
    moving = [v for t, v in seen if t <= last]
    assert moving and all(v == pytest.approx(0.5 * LIM.advance_mm_s) for v in moving)
    stopped = [v for t, v in seen if t >= last + TIMING.repeat_hold_s]
    assert stopped and all(v == 0.0 for v in stopped)


def test_a_tap_moves_for_the_first_hold_only() -> None:
    s = next_state(KeyState(), KeyInput(SteerKey.YAW_LEFT, 1.0))
    assert command_at(s, 1.49, LIM, TIMING).yaw_rate_rad_s > 0
    assert command_at(s, 1.5, LIM, TIMING).is_stop


def test_a_release_event_stops_at_once_and_opposite_keys_cancel() -> None:
    s = _fold([KeyInput(SteerKey.PITCH_UP, 0.0), KeyInput(SteerKey.PITCH_UP, 0.1, down=False)])
    assert command_at(s, 0.1, LIM, TIMING).is_stop
    s = _fold([KeyInput(SteerKey.ADVANCE, 0.0), KeyInput(SteerKey.RETRACT, 0.01)])
    assert command_at(s, 0.02, LIM, TIMING).advance_mm_s == 0.0


def test_yaw_pitch_and_advance_held_together_from_key_down_events() -> None:
    s = _fold(
        [
            KeyInput(SteerKey.YAW_RIGHT, 0.0),
            KeyInput(SteerKey.PITCH_DOWN, 0.0),
            KeyInput(SteerKey.RETRACT, 0),
        ]
    )
    c = command_at(s, 0.1, LIM, TIMING)
    assert c.yaw_rate_rad_s < 0 and c.pitch_rate_rad_s < 0 and c.advance_mm_s < 0


def test_pause_latches_a_stop_until_resumed_and_abort_latches() -> None:
    s = _fold(
        [
            KeyInput(SteerKey.ADVANCE, 0.0),
            KeyInput(ControlKey.PAUSE, 0.1),
            KeyInput(SteerKey.ADVANCE, 0.2),
        ]
    )
    assert s.paused and command_at(s, 0.25, LIM, TIMING).is_stop
    s = _fold(
        [
            KeyInput(ControlKey.PAUSE, 0.0),
            KeyInput(ControlKey.PAUSE, 0.1),
            KeyInput(SteerKey.ADVANCE, 0.2),
        ]
    )
    assert not s.paused and command_at(s, 0.25, LIM, TIMING).advance_mm_s > 0
    s = _fold([KeyInput(ControlKey.PAUSE, 0.0), KeyInput(ControlKey.RESUME, 0.1)])
    assert not s.paused
    s = _fold(
        [
            KeyInput(SteerKey.ADVANCE, 0.0),
            KeyInput(ControlKey.ABORT, 0.1),
            KeyInput(SteerKey.ADVANCE, 0.2),
        ]
    )
    assert s.aborted and command_at(s, 0.25, LIM, TIMING).is_stop


def test_the_speed_cap_steps_in_tenths_between_a_tenth_and_the_limits() -> None:
    s = _fold([KeyInput(ControlKey.SPEED_UP, 0.01 * i) for i in range(20)])
    assert s.speed_fraction == 1.0
    s = next_state(s, KeyInput(SteerKey.ADVANCE, 1.0))
    assert command_at(s, 1.0, LIM, TIMING).advance_mm_s == LIM.advance_mm_s
    s = _fold([KeyInput(ControlKey.SPEED_DOWN, 0.01 * i) for i in range(20)])
    assert s.speed_fraction == pytest.approx(0.1)


def test_the_console_stop_keys_and_the_arrows_decode() -> None:
    keys, rest = decode_terminal("\x1b[A\x1b[B\x1bOC\x1b[Dhjklws+-=_ pra")
    assert rest == ""
    assert [k.value for k in keys] == [
        "pitch_up", "pitch_down", "yaw_right", "yaw_left", "yaw_left", "pitch_down",
        "pitch_up", "yaw_right", "advance", "retract", "speed_up", "speed_down", "speed_up",
        "speed_down", "pause", "pause", "resume", "abort",
    ]  # fmt: skip
    assert decode_terminal("W")[0] == [SteerKey.ADVANCE]  # caps lock on
    assert decode_terminal("\x1b[5~x")[0] == []  # keys not ours are ignored


def test_an_escape_sequence_cut_between_two_reads_is_kept() -> None:
    kb = KeyboardSteer(LIM, TIMING)
    assert kb.feed_terminal("\x1b", 0.0) == []
    assert kb.feed_terminal("[A", 0.01) == [SteerKey.PITCH_UP]
    assert kb.command(0.02).pitch_rate_rad_s > 0


def test_bad_hold_timing_is_one_error() -> None:
    with pytest.raises(DriveError, match="first_hold_s"):
        HoldTiming(first_hold_s=math.nan)


_events = st.lists(
    st.tuples(
        st.sampled_from([*SteerKey, *ControlKey]),
        st.floats(0.0, 0.3),  # time since the previous event
        st.booleans(),  # down or up
    ),
    max_size=60,
)


@settings(max_examples=300, deadline=None)
@given(
    events=_events,
    first=st.floats(0.05, 1.0),
    repeat=st.floats(0.05, 1.0),
    cap=st.floats(0.1, 100.0),
    probe=st.floats(0.0, 2.0),
)
def test_never_above_the_cap_and_always_zero_after_the_release_timeout(
    events: list[tuple[SteerKey | ControlKey, float, bool]],
    first: float,
    repeat: float,
    cap: float,
    probe: float,
) -> None:
    timing = HoldTiming(first_hold_s=first, repeat_hold_s=repeat)
    lim = SteerLimits(yaw_rate_rad_s=cap / 50, pitch_rate_rad_s=cap / 70, advance_mm_s=cap)
    s = KeyState()
    t = 0.0
    for key, dt, down in events:
        t += dt
        s = next_state(s, KeyInput(key, t, down))
        for u in (t, t + probe * first):
            c = command_at(s, u, lim, timing)
            f = s.speed_fraction
            assert abs(c.yaw_rate_rad_s) <= f * lim.yaw_rate_rad_s + 1e-12
            assert abs(c.pitch_rate_rad_s) <= f * lim.pitch_rate_rad_s + 1e-12
            assert abs(c.advance_mm_s) <= f * lim.advance_mm_s + 1e-12
            assert f <= 1.0
    # released: no event after t -> zero by the deadline, and never later than first_hold_s
    deadline = release_deadline_s(s, timing)
    assert deadline <= t + max(first, repeat)
    assert command_at(s, max(deadline, t), lim, timing).is_stop
    assert command_at(s, t + max(first, repeat) + probe, lim, timing).is_stop
