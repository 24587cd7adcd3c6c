"""The gamepad's steering: evdev events -> steer command, with a fake event source and,
where /dev/uinput can be written, a synthetic device the kernel makes."""

from __future__ import annotations

import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.drive.command import DriveError, SteerLimits
from hrm_ctrl.drive.gamepad import (
    ABS_RY,
    ABS_X,
    ABS_Y,
    BTN_SELECT,
    BTN_SOUTH,
    BTN_TL,
    BTN_TR,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    SYN_DROPPED,
    AxisRange,
    GamepadSteer,
    InputEvent,
    PadState,
    next_pad_state,
    normalised,
    pad_command,
    uinput_available,
)

LIM = SteerLimits()
STICK = AxisRange(-32768, 32767, flat=128)
RANGES = {ABS_X: STICK, ABS_Y: STICK, ABS_RY: STICK}


class FakePad:
    """An :class:`~hrm_ctrl.drive.gamepad.EventSource` playing a script of event batches;
    an ``OSError`` in the script is raised (the device unplugged)."""

    name = "fake pad"

    def __init__(self, script: list[list[InputEvent] | OSError]) -> None:
        self.script = list(script)
        self.closed = False

    def axis_ranges(self) -> dict[int, AxisRange]:
        return dict(RANGES)

    def read(self, timeout_s: float) -> list[InputEvent]:
        if not self.script:
            return []
        batch = self.script.pop(0)
        if isinstance(batch, OSError):
            raise batch
        return batch

    def close(self) -> None:
        self.closed = True


def _abs(code: int, v: int, t: float = 0.0) -> InputEvent:
    return InputEvent(EV_ABS, code, v, t)


def _btn(code: int, v: int = 1, t: float = 0.0) -> InputEvent:
    return InputEvent(EV_KEY, code, v, t)


def test_sticks_map_to_yaw_pitch_and_advance_at_the_speed_cap() -> None:
    pad = GamepadSteer(FakePad([[_abs(ABS_X, -32768), _abs(ABS_Y, 32767), _abs(ABS_RY, 0)]]), LIM)
    pad.poll()
    c = pad.command()
    assert c.yaw_rate_rad_s == pytest.approx(0.5 * LIM.yaw_rate_rad_s)  # left: yaw +
    assert c.pitch_rate_rad_s == pytest.approx(-0.5 * LIM.pitch_rate_rad_s)  # down: pitch -
    assert c.advance_mm_s == 0.0  # the right stick at rest


def test_a_stick_let_go_inside_the_dead_zone_asks_for_nothing() -> None:
    s = PadState()
    for code, v in ((ABS_X, 3000), (ABS_Y, -3000), (ABS_RY, 2500)):  # 9 % of the half range
        s = next_pad_state(s, _abs(code, v))
    assert pad_command(s, LIM, RANGES).is_stop


def test_buttons_pause_abort_and_the_speed_cap() -> None:
    s = next_pad_state(PadState(), _abs(ABS_RY, -32768))
    for _ in range(9):
        s = next_pad_state(s, _btn(BTN_TR))
    assert s.speed_fraction == 1.0
    assert pad_command(s, LIM, RANGES).advance_mm_s == LIM.advance_mm_s
    s = next_pad_state(s, _btn(BTN_TL))
    assert pad_command(s, LIM, RANGES).advance_mm_s == pytest.approx(0.9 * LIM.advance_mm_s)
    s = next_pad_state(s, _btn(BTN_TL, 0))  # a release does nothing
    assert s.speed_fraction == pytest.approx(0.9)
    p = next_pad_state(s, _btn(BTN_SOUTH))
    assert p.paused and pad_command(p, LIM, RANGES).is_stop
    assert not next_pad_state(p, _btn(BTN_SOUTH)).paused
    a = next_pad_state(s, _btn(BTN_SELECT))
    assert a.aborted and pad_command(a, LIM, RANGES).is_stop


def test_lost_events_centre_the_sticks() -> None:
    s = next_pad_state(PadState(), _abs(ABS_RY, -32768))
    s = next_pad_state(s, InputEvent(EV_SYN, SYN_DROPPED, 0, 0.0))
    assert pad_command(s, LIM, RANGES).is_stop


def test_an_unplugged_pad_stops_and_says_why() -> None:
    src = FakePad([[_abs(ABS_RY, -32768)], OSError(19, "No such device")])
    pad = GamepadSteer(src, LIM)
    pad.poll()
    assert pad.command().advance_mm_s > 0
    pad.poll()
    assert pad.lost and pad.command().is_stop
    assert pad.error == "gamepad fake pad lost: No such device"
    pad.close()
    assert src.closed


def test_the_reader_thread_feeds_the_command() -> None:
    pad = GamepadSteer(FakePad([[_abs(ABS_X, 32767)]]), LIM).start()
    try:
        deadline = time.monotonic() + 5.0
        while pad.events == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pad.command().yaw_rate_rad_s < 0
    finally:
        pad.close()


def test_a_pad_without_the_mapped_axes_is_refused_in_one_line() -> None:
    class NoRightStick(FakePad):
        def axis_ranges(self) -> dict[int, AxisRange]:
            return {ABS_X: STICK, ABS_Y: STICK}

    with pytest.raises(DriveError, match=r"gamepad fake pad: no axis \[4\]"):
        GamepadSteer(NoRightStick([]), LIM)
    with pytest.raises(DriveError, match="max 0 must exceed min 0"):
        AxisRange(0, 0)


@settings(max_examples=300, deadline=None)
@given(
    lo=st.integers(-40000, 0),
    span=st.integers(2, 80000),
    value=st.integers(-100000, 100000),
    dz=st.floats(0.0, 0.9),
)
def test_normalised_is_within_one_and_zero_in_the_dead_zone(
    lo: int, span: int, value: int, dz: float
) -> None:
    rng = AxisRange(lo, lo + span)
    x = normalised(value, rng, dz)
    assert -1.0 <= x <= 1.0
    centre, half = lo + 0.5 * span, 0.5 * span
    if abs(value - centre) <= dz * half:
        assert x == 0.0


@settings(max_examples=200, deadline=None)
@given(
    events=st.lists(
        st.tuples(
            st.sampled_from([EV_ABS, EV_KEY, EV_SYN]),
            st.sampled_from([ABS_X, ABS_Y, ABS_RY, BTN_SOUTH, BTN_TL, BTN_TR, SYN_DROPPED]),
            st.integers(-70000, 70000),
        ),
        max_size=40,
    )
)
def test_never_above_the_speed_cap(events: list[tuple[int, int, int]]) -> None:
    s = PadState()
    for t, code, v in events:
        s = next_pad_state(s, InputEvent(t, code, v, 0.0))
        c = pad_command(s, LIM, RANGES)
        f = s.speed_fraction
        assert abs(c.yaw_rate_rad_s) <= f * LIM.yaw_rate_rad_s + 1e-12
        assert abs(c.pitch_rate_rad_s) <= f * LIM.pitch_rate_rad_s + 1e-12
        assert abs(c.advance_mm_s) <= f * LIM.advance_mm_s + 1e-12


_UINPUT_OK, _UINPUT_WHY = uinput_available()


@pytest.mark.skipif(not _UINPUT_OK, reason=f"no synthetic input device: {_UINPUT_WHY}")
def test_a_synthetic_uinput_pad_steers() -> None:  # pragma: no cover - needs /dev/uinput
    from evdev import AbsInfo, UInput
    from evdev import ecodes as e

    info = AbsInfo(value=0, min=-32768, max=32767, fuzz=16, flat=128, resolution=0)
    caps = {
        e.EV_KEY: [e.BTN_SOUTH, e.BTN_SELECT, e.BTN_TL, e.BTN_TR],
        e.EV_ABS: [(e.ABS_X, info), (e.ABS_Y, info), (e.ABS_RY, info)],
    }
    from hrm_ctrl.drive.gamepad import EvdevSource

    with UInput(caps, name="hrm test pad") as ui:
        time.sleep(0.3)  # udev makes the node
        src = EvdevSource(ui.device.path)
        pad = GamepadSteer(src, LIM).start()
        try:
            ui.write(e.EV_ABS, e.ABS_RY, -32768)
            ui.syn()
            deadline = time.monotonic() + 5.0
            while pad.command().advance_mm_s <= 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert pad.command().advance_mm_s == pytest.approx(0.5 * LIM.advance_mm_s)
        finally:
            pad.close()
