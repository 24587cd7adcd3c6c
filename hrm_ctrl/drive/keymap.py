"""The keyboard as a steering device: keys -> :class:`~hrm_ctrl.drive.command.SteerCommand`.

Keys (a terminal in cbreak mode, as ``hrm run`` reads its keys):

=====================  =============================================================
Left / Right, ``h``/``l``   tip yaw + / - (turn left / right), held
Up / Down, ``k``/``j``      tip pitch + / - (turn up / down), held
``w`` / ``s``               advance / retract along the trail, held
``+`` (``=``) / ``-``       speed cap up / down, in steps of :data:`SPEED_STEP`
space, ``p``                pause: every motion stops and stays stopped (latched);
                            ``p``, space or ``r`` resumes
``a``                       abort: stop and end the drive (as ``hrm run``'s ``a``)
Ctrl-C                      not a key here: the terminal sends SIGINT, which stops every
                            axis at once (the runtime's signal handling, as ``hrm run``)
=====================  =============================================================

Hold-to-move without key-up events: a terminal only sends a key when it is pressed and
then, while it is held, the keyboard's auto-repeat (after an initial delay of typically
250-600 ms, then 25-40 repeats a second).  A motion key therefore counts as held

* for :attr:`HoldTiming.first_hold_s` after its first press (long enough to bridge the
  auto-repeat's initial delay, so a held key does not stutter), and
* for :attr:`HoldTiming.repeat_hold_s` after each later press (a repeat: the key is
  released at most that long after its last repeat).

A device with real key-up events (a :class:`KeyInput` with ``down=False``) ends the hold
at once.  The
command is zero at the latest ``first_hold_s`` after the last event of a key
(:func:`release_deadline_s`); the planner then ramps the advance down within the motors'
deceleration.  A terminal repeats only the key pressed last: two motion keys at once are
not held together (the gamepad does that).

The motion keys are the key scripts' (:class:`~hrm_ctrl.drive.script.SteerKey`, one
command of the keys held: :func:`~hrm_ctrl.drive.script.command_of_keys`).  Everything
here is a pure function of the events and the time: :func:`next_state`
folds one event into an immutable :class:`KeyState`, :func:`command_at` reads the
command at a time.  :class:`KeyboardSteer` wraps them for two threads (the key reader
feeds, the control loop reads).

>>> st = KeyState()
>>> st = next_state(st, KeyInput(SteerKey.ADVANCE, 10.0))
>>> command_at(st, 10.1, SteerLimits())
SteerCommand(yaw_rate_rad_s=0.0, pitch_rate_rad_s=0.0, advance_mm_s=10.0)
>>> command_at(st, 10.0 + HoldTiming().first_hold_s, SteerLimits()).is_stop
True
>>> [k.value for k in decode_terminal("\\x1b[Aw+ ")[0]]
['pitch_up', 'advance', 'speed_up', 'pause']
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import StrEnum

from hrm_ctrl.drive.command import DriveError, SteerCommand, SteerLimits
from hrm_ctrl.drive.script import SteerKey, command_of_keys

SPEED_STEP = 0.1  # the speed cap moves in tenths of the limits
MIN_SPEED_FRACTION = 0.1
START_SPEED_FRACTION = 0.5  # a drive starts at half the limits


class ControlKey(StrEnum):
    """The keys besides the motion keys (:class:`~hrm_ctrl.drive.script.SteerKey`)."""

    SPEED_UP = "speed_up"
    SPEED_DOWN = "speed_down"
    PAUSE = "pause"  # toggles: pause / resume
    RESUME = "resume"
    ABORT = "abort"


Key = SteerKey | ControlKey  # what a key means to the drive


# Terminal input -> key.  Arrows come as ESC [ X (or ESC O X in application mode).
TERMINAL_KEYS: dict[str, Key] = {
    "\x1b[D": SteerKey.YAW_LEFT,
    "\x1bOD": SteerKey.YAW_LEFT,
    "h": SteerKey.YAW_LEFT,
    "\x1b[C": SteerKey.YAW_RIGHT,
    "\x1bOC": SteerKey.YAW_RIGHT,
    "l": SteerKey.YAW_RIGHT,
    "\x1b[A": SteerKey.PITCH_UP,
    "\x1bOA": SteerKey.PITCH_UP,
    "k": SteerKey.PITCH_UP,
    "\x1b[B": SteerKey.PITCH_DOWN,
    "\x1bOB": SteerKey.PITCH_DOWN,
    "j": SteerKey.PITCH_DOWN,
    "w": SteerKey.ADVANCE,
    "s": SteerKey.RETRACT,
    "+": ControlKey.SPEED_UP,
    "=": ControlKey.SPEED_UP,
    "-": ControlKey.SPEED_DOWN,
    "_": ControlKey.SPEED_DOWN,
    " ": ControlKey.PAUSE,
    "p": ControlKey.PAUSE,
    "r": ControlKey.RESUME,
    "a": ControlKey.ABORT,
}
_ESC = "\x1b"
_ESC_LEN = 3  # every escape sequence above is three characters


@dataclass(frozen=True, slots=True)
class KeyInput:
    """One key at ``t_s`` (s, the reader's monotonic clock): pressed (``down``; a
    terminal's every key, auto-repeats included) or released."""

    key: Key
    t_s: float
    down: bool = True


@dataclass(frozen=True, slots=True)
class HoldTiming:
    """How long a motion key counts as held after a press without a release (s)."""

    first_hold_s: float = 0.55
    repeat_hold_s: float = 0.2

    def __post_init__(self) -> None:
        for name in ("first_hold_s", "repeat_hold_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise DriveError(f"key hold timing: {name}: expected a number > 0, got {v!r}")


@dataclass(frozen=True, slots=True)
class Held:
    """A motion key held: its first press and its last press (s)."""

    first_s: float
    last_s: float


@dataclass(frozen=True, slots=True)
class KeyState:
    """The keyboard's state: the motion keys held, the speed cap (a fraction of the
    limits), whether paused (latched) and whether the operator aborted."""

    held: dict[SteerKey, Held] = field(default_factory=dict)
    speed_fraction: float = START_SPEED_FRACTION
    paused: bool = False
    aborted: bool = False


def step_speed_fraction(f: float, sign: int) -> float:
    """The speed fraction one step up or down, kept to whole tenths in [0.1, 1].

    >>> step_speed_fraction(0.5, 1), step_speed_fraction(1.0, 1), step_speed_fraction(0.1, -1)
    (0.6, 1.0, 0.1)
    """
    n = round(f / SPEED_STEP) + sign
    return min(1.0, max(MIN_SPEED_FRACTION, round(n * SPEED_STEP, 10)))


def next_state(state: KeyState, event: KeyInput) -> KeyState:
    """``state`` after ``event`` (events come in time order).

    A press of a motion key starts or extends its hold, a release ends it; pause
    toggles the latch (and drops every hold: a resume needs a fresh press), resume
    clears it, abort latches the abort and drops every hold."""
    k = event.key
    if isinstance(k, SteerKey):
        held = dict(state.held)
        if not event.down:
            held.pop(k, None)
        else:
            h = held.get(k)
            held[k] = Held(event.t_s, event.t_s) if h is None else Held(h.first_s, event.t_s)
        return replace(state, held=held)
    if not event.down:
        return state
    if k is ControlKey.SPEED_UP:
        return replace(state, speed_fraction=step_speed_fraction(state.speed_fraction, 1))
    if k is ControlKey.SPEED_DOWN:
        return replace(state, speed_fraction=step_speed_fraction(state.speed_fraction, -1))
    if k is ControlKey.PAUSE:
        return replace(state, paused=not state.paused, held={})
    if k is ControlKey.RESUME:
        return replace(state, paused=False, held={})
    return replace(state, aborted=True, held={})  # ControlKey.ABORT


def is_held(h: Held, t_s: float, timing: HoldTiming) -> bool:
    """Whether a key pressed as ``h`` still counts as held at ``t_s`` (module doc).

    >>> tm = HoldTiming(first_hold_s=0.5, repeat_hold_s=0.2)
    >>> is_held(Held(0.0, 0.0), 0.4, tm), is_held(Held(0.0, 0.6), 0.75, tm)
    (True, True)
    >>> is_held(Held(0.0, 0.0), 0.5, tm), is_held(Held(0.0, 0.6), 0.8, tm)
    (False, False)
    """
    window = timing.first_hold_s if h.last_s == h.first_s else timing.repeat_hold_s
    return t_s < h.last_s + window


def release_deadline_s(state: KeyState, timing: HoldTiming) -> float:
    """The time by which every motion key held is released if no further event comes
    (``-inf`` when none is held)."""
    return max(
        (
            h.last_s + (timing.first_hold_s if h.last_s == h.first_s else timing.repeat_hold_s)
            for h in state.held.values()
        ),
        default=-math.inf,
    )


def held_at(state: KeyState, t_s: float, timing: HoldTiming) -> frozenset[SteerKey]:
    """The motion keys held at ``t_s`` (none while paused or aborted)."""
    if state.paused or state.aborted:
        return frozenset()
    return frozenset(k for k, h in state.held.items() if is_held(h, t_s, timing))


def command_at(
    state: KeyState, t_s: float, limits: SteerLimits, timing: HoldTiming = HoldTiming()
) -> SteerCommand:
    """The steer command the keys ask for at ``t_s``: the keys held
    (:func:`~hrm_ctrl.drive.script.command_of_keys`, as a key script's) scaled by the
    speed cap (``speed_fraction`` of ``limits``), never above ``limits``."""
    c = command_of_keys(held_at(state, t_s, timing), limits)
    f = min(1.0, max(0.0, state.speed_fraction))
    return SteerCommand(c.yaw_rate_rad_s * f, c.pitch_rate_rad_s * f, c.advance_mm_s * f)


def decode_terminal(text: str) -> tuple[list[Key], str]:
    """The keys in terminal input ``text`` and what is left of an escape sequence cut
    off at its end (to be put before the next read).  Other input is ignored.

    >>> decode_terminal("\\x1b[Dxs\\x1b[")
    ([<SteerKey.YAW_LEFT: 'yaw_left'>, <SteerKey.RETRACT: 'retract'>], '\\x1b[')
    """
    keys: list[Key] = []
    i = 0
    while i < len(text):
        if text[i] == _ESC:
            seq = text[i : i + _ESC_LEN]
            if len(seq) < _ESC_LEN:
                return keys, seq
            k = TERMINAL_KEYS.get(seq)
            if k is not None:
                keys.append(k)
                i += _ESC_LEN
                continue
            i += 1  # a lone ESC or a sequence not ours: skip the ESC
            continue
        k = TERMINAL_KEYS.get(text[i].lower() if text[i].isalpha() else text[i])
        if k is not None:
            keys.append(k)
        i += 1
    return keys, ""


class KeyboardSteer:
    """The keyboard for two threads: the key reader calls :meth:`feed` (or
    :meth:`feed_terminal`), the control loop calls :meth:`command`.  The state is an
    immutable :class:`KeyState` swapped whole, so the reader never blocks the loop."""

    def __init__(self, limits: SteerLimits, timing: HoldTiming = HoldTiming()) -> None:
        self.limits = limits
        self.timing = timing
        self.state = KeyState()
        self._rest = ""

    def feed(self, event: KeyInput) -> None:
        self.state = next_state(self.state, event)

    def feed_terminal(self, text: str, t_s: float) -> list[Key]:
        """Feed what was read from the terminal at ``t_s``; returns the keys found."""
        keys, self._rest = decode_terminal(self._rest + text)
        for k in keys:
            self.feed(KeyInput(k, t_s))
        return keys

    def command(self, t_s: float) -> SteerCommand:
        return command_at(self.state, t_s, self.limits, self.timing)

    @property
    def aborted(self) -> bool:
        return self.state.aborted

    @property
    def paused(self) -> bool:
        return self.state.paused

    @property
    def speed_fraction(self) -> float:
        return self.state.speed_fraction
