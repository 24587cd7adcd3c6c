"""A gamepad as a steering device: Linux joystick events (evdev) ->
:class:`~hrm_ctrl.drive.command.SteerCommand`.

The device is read through python-evdev (the optional extra ``hrm[gamepad]``); the
mapping itself is pure and needs no device: :func:`next_pad_state` folds one
:class:`InputEvent` into an immutable :class:`PadState`, :func:`pad_command` reads the
command.  The codes are the kernel's (``linux/input-event-codes.h``, a stable ABI) and
named here, so the mapping and its tests run without evdev installed.

Mapping (:class:`PadMap`, the usual layout of an Xbox-style pad as Linux reports it):

====================  ==========================================================
left stick, across    tip yaw (stick left: yaw +, turn left)
left stick, up/down   tip pitch (stick up: pitch +)
right stick, up/down  advance (up) / retract (down)
LB / RB               speed cap down / up (tenths of the limits, as the keys)
A (south)             pause / resume (latched stop, as the keyboard's space)
Back (select)         abort (stop and end the drive)
====================  ==========================================================

Each stick axis is scaled to ``[-1, 1]`` about the centre of its range with a dead zone
(:func:`normalised`: the larger of :data:`DEAD_ZONE` and the device's own ``flat``), so
a stick let go -- which springs back to the centre -- asks for zero.  Hold-to-move needs
no timeout here: the sticks are absolute.  Lost events (``SYN_DROPPED``) centre every
axis until the device reports them again, and a device that disappears
(:class:`GamepadSteer`) stops every motion.

>>> ranges = {ABS_X: AxisRange(-32768, 32767), ABS_Y: AxisRange(-32768, 32767),
...           ABS_RY: AxisRange(-32768, 32767)}
>>> s = next_pad_state(PadState(), InputEvent(EV_ABS, ABS_RY, -32768, 0.0))
>>> pad_command(s, SteerLimits(), ranges)
SteerCommand(yaw_rate_rad_s=0.0, pitch_rate_rad_s=0.0, advance_mm_s=10.0)
"""

from __future__ import annotations

import math
import os
import select
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Protocol

from hrm_ctrl.drive.command import STOP, DriveError, SteerCommand, SteerLimits
from hrm_ctrl.drive.keymap import START_SPEED_FRACTION, step_speed_fraction

# linux/input-event-codes.h
EV_SYN, EV_KEY, EV_ABS = 0x00, 0x01, 0x03
SYN_REPORT, SYN_DROPPED = 0, 3
ABS_X, ABS_Y, ABS_Z, ABS_RX, ABS_RY, ABS_RZ = 0x00, 0x01, 0x02, 0x03, 0x04, 0x05
BTN_SOUTH, BTN_EAST, BTN_NORTH, BTN_WEST = 0x130, 0x131, 0x133, 0x134
BTN_TL, BTN_TR, BTN_SELECT, BTN_START = 0x136, 0x137, 0x13A, 0x13B

DEAD_ZONE = 0.12  # of the half range: a stick at rest reads within a few % of its centre
READ_TIMEOUT_S = 0.1  # the reader thread looks up from its wait this often


@dataclass(frozen=True, slots=True)
class InputEvent:
    """One evdev event: ``type`` (EV_*), ``code``, ``value`` and its time (s)."""

    type: int
    code: int
    value: int
    t_s: float


@dataclass(frozen=True, slots=True)
class AxisRange:
    """An absolute axis's range as the device reports it (``absinfo``)."""

    min: int
    max: int
    flat: int = 0

    def __post_init__(self) -> None:
        if not self.max > self.min:
            raise DriveError(f"gamepad axis range: max {self.max} must exceed min {self.min}")


@dataclass(frozen=True, slots=True)
class PadMap:
    """Which axes and buttons do what; ``*_sign``: +1 or -1 (the axis's raw direction
    that turns a positive command)."""

    yaw_axis: int = ABS_X
    yaw_sign: float = -1.0  # stick left (negative x) turns left (yaw +)
    pitch_axis: int = ABS_Y
    pitch_sign: float = -1.0  # stick up (negative y) pitches up
    advance_axis: int = ABS_RY
    advance_sign: float = -1.0  # stick up advances
    pause_button: int = BTN_SOUTH
    abort_button: int = BTN_SELECT
    speed_down_button: int = BTN_TL
    speed_up_button: int = BTN_TR

    @property
    def axes(self) -> tuple[int, int, int]:
        return (self.yaw_axis, self.pitch_axis, self.advance_axis)


@dataclass(frozen=True, slots=True)
class PadState:
    """The pad's state: the last raw value of each axis seen, the speed cap (a fraction
    of the limits), pause (latched) and abort."""

    axes: dict[int, int] = field(default_factory=dict)
    speed_fraction: float = START_SPEED_FRACTION
    paused: bool = False
    aborted: bool = False


def normalised(value: int, rng: AxisRange, dead_zone: float = DEAD_ZONE) -> float:
    """A raw axis value -> ``[-1, 1]`` about the centre of ``rng``, zero within the dead
    zone (the larger of ``dead_zone`` and the device's ``flat``) and rescaled beyond it
    so the output is continuous.

    >>> r = AxisRange(0, 255)
    >>> normalised(128, r), normalised(255, r), normalised(0, r)
    (0.0, 1.0, -1.0)
    >>> round(normalised(192, AxisRange(0, 256), 0.5), 3)
    0.0
    >>> round(normalised(224, AxisRange(0, 256), 0.5), 3)
    0.5
    """
    centre = 0.5 * (rng.min + rng.max)
    half = 0.5 * (rng.max - rng.min)
    x = max(-1.0, min(1.0, (value - centre) / half))
    dz = min(0.95, max(dead_zone, rng.flat / half))
    if abs(x) <= dz:
        return 0.0
    return math.copysign((abs(x) - dz) / (1.0 - dz), x)


def next_pad_state(state: PadState, event: InputEvent, pad: PadMap = PadMap()) -> PadState:
    """``state`` after ``event``: an axis of the map takes its value; a button press
    (value 1; 0 is its release, 2 a repeat) pauses, aborts or moves the speed cap; lost
    events centre every axis (:data:`SYN_DROPPED`)."""
    if event.type == EV_ABS and event.code in pad.axes:
        return replace(state, axes={**state.axes, event.code: event.value})
    if event.type == EV_SYN and event.code == SYN_DROPPED:
        return replace(state, axes={})
    if event.type != EV_KEY or event.value != 1:
        return state
    if event.code == pad.pause_button:
        return replace(state, paused=not state.paused)
    if event.code == pad.abort_button:
        return replace(state, aborted=True)
    if event.code == pad.speed_up_button:
        return replace(state, speed_fraction=step_speed_fraction(state.speed_fraction, 1))
    if event.code == pad.speed_down_button:
        return replace(state, speed_fraction=step_speed_fraction(state.speed_fraction, -1))
    return state


def pad_command(
    state: PadState,
    limits: SteerLimits,
    ranges: Mapping[int, AxisRange],
    pad: PadMap = PadMap(),
    dead_zone: float = DEAD_ZONE,
) -> SteerCommand:
    """The steer command the pad asks for: each mapped axis normalised (an axis not seen
    yet, or without a range, is at rest), times its sign and the speed cap, never above
    ``limits``; paused or aborted: :data:`~hrm_ctrl.drive.command.STOP`."""
    if state.paused or state.aborted:
        return STOP
    f = min(1.0, max(0.0, state.speed_fraction))

    def axis(code: int, sign: float) -> float:
        v, rng = state.axes.get(code), ranges.get(code)
        return 0.0 if v is None or rng is None else sign * normalised(v, rng, dead_zone) * f

    return SteerCommand.from_axes(
        axis(pad.yaw_axis, pad.yaw_sign),
        axis(pad.pitch_axis, pad.pitch_sign),
        axis(pad.advance_axis, pad.advance_sign),
        limits,
    )


class EventSource(Protocol):
    """Where a pad's events come from (an evdev device, or a test's script)."""

    name: str

    def axis_ranges(self) -> dict[int, AxisRange]:
        """The range of every absolute axis the device has."""
        ...

    def read(self, timeout_s: float) -> list[InputEvent]:
        """The events that arrived, waiting at most ``timeout_s`` for the first; raises
        :class:`OSError` when the device is gone."""
        ...

    def close(self) -> None: ...


class EvdevSource:
    """A Linux input device (``/dev/input/eventN``) through python-evdev."""

    def __init__(self, path: str) -> None:
        try:
            import evdev
        except ImportError:
            raise DriveError("the gamepad needs python-evdev: pip install 'hrm[gamepad]'") from None
        try:
            self._dev = evdev.InputDevice(path)
        except OSError as exc:
            raise DriveError(f"gamepad {path}: cannot open ({exc.strerror or exc})") from None
        self.name = f"{self._dev.name} ({path})"

    def axis_ranges(self) -> dict[int, AxisRange]:
        caps = self._dev.capabilities(absinfo=True)
        out: dict[int, AxisRange] = {}
        for code, info in caps.get(EV_ABS, []):
            if info.max > info.min:
                out[int(code)] = AxisRange(int(info.min), int(info.max), int(info.flat))
        return out

    def read(self, timeout_s: float) -> list[InputEvent]:
        r, _, _ = select.select([self._dev.fd], [], [], timeout_s)
        if not r:
            return []
        try:
            events = list(self._dev.read())
        except BlockingIOError:
            return []
        return [InputEvent(e.type, e.code, e.value, e.timestamp()) for e in events]

    def close(self) -> None:
        self._dev.close()


def find_gamepads() -> list[str]:
    """The ``/dev/input/event*`` devices with a stick and a south button (empty where
    python-evdev is missing or no device can be read)."""
    try:
        import evdev
    except ImportError:
        return []
    found = []
    for path in evdev.list_devices():
        try:
            dev = evdev.InputDevice(path)
        except OSError:
            continue
        try:
            caps = dev.capabilities()
            abs_codes = {c if isinstance(c, int) else c[0] for c in caps.get(EV_ABS, [])}
            if ABS_X in abs_codes and BTN_SOUTH in caps.get(EV_KEY, []):
                found.append(path)
        finally:
            dev.close()
    return sorted(found)


class GamepadSteer:
    """A pad read on its own thread; :meth:`command` is what the control loop calls.

    The state is an immutable :class:`PadState` swapped whole.  When the device fails
    (unplugged: ``read`` raises :class:`OSError`) the pad is ``lost``: the command is
    :data:`~hrm_ctrl.drive.command.STOP` from then on and ``error`` says why."""

    def __init__(
        self,
        source: EventSource,
        limits: SteerLimits,
        pad: PadMap = PadMap(),
        dead_zone: float = DEAD_ZONE,
    ) -> None:
        if not (math.isfinite(dead_zone) and 0.0 <= dead_zone < 0.95):
            raise DriveError(f"gamepad dead zone must be in [0, 0.95), got {dead_zone!r}")
        self.source = source
        self.limits = limits
        self.pad = pad
        self.dead_zone = dead_zone
        self.ranges = source.axis_ranges()
        missing = [c for c in pad.axes if c not in self.ranges]
        if missing:
            raise DriveError(
                f"gamepad {source.name}: no axis {missing} (has {sorted(self.ranges)})"
            )
        self.state = PadState()
        self.events = 0
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def feed(self, event: InputEvent) -> None:
        self.state = next_pad_state(self.state, event, self.pad)
        self.events += 1

    def poll(self, timeout_s: float = 0.0) -> int:
        """Read what the device has (waiting at most ``timeout_s``); the events read."""
        try:
            events = self.source.read(timeout_s)
        except OSError as exc:
            self.error = f"gamepad {self.source.name} lost: {exc.strerror or exc}"
            return 0
        for e in events:
            self.feed(e)
        return len(events)

    @property
    def lost(self) -> bool:
        return self.error is not None

    def command(self, t_s: float | None = None) -> SteerCommand:
        """The command now (``t_s`` is accepted for the keyboard's signature; the pad's
        axes are absolute and need no time)."""
        if self.lost:
            return STOP
        return pad_command(self.state, self.limits, self.ranges, self.pad, self.dead_zone)

    @property
    def aborted(self) -> bool:
        return self.state.aborted

    def start(self) -> GamepadSteer:
        """Read the device on a daemon thread until :meth:`close` or the device is lost."""

        def run() -> None:
            while not self._stop.is_set() and not self.lost:
                self.poll(READ_TIMEOUT_S)

        self._thread = threading.Thread(target=run, name="hrm-gamepad", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        self.source.close()


def uinput_available() -> tuple[bool, str]:
    """Whether a synthetic input device can be made here, and if not, why."""
    try:
        import evdev  # noqa: F401
    except ImportError:
        return False, "python-evdev is not installed (pip install 'hrm[gamepad]')"
    if not os.path.exists("/dev/uinput"):
        return False, "/dev/uinput does not exist here (no uinput module in this kernel/container)"
    if not os.access("/dev/uinput", os.W_OK):
        return False, "/dev/uinput is not writable by this user"
    return True, ""
