"""Scripted keys: a key sequence file played against the drive's clock (``hrm drive --keys``).

One event a line, ``T_S KEY down|up``: the time in seconds from the drive's start, a
logical key (:class:`SteerKey`) and whether it is pressed or released; blank lines and
``#`` comments are skipped, times never go back.  A held key is +1 or -1 on its axis
(:meth:`~hrm_ctrl.drive.command.SteerCommand.from_axes`); opposite keys held together
cancel.  ``T_S end`` ends the drive at that time.

>>> ks = KeyScript.parse("0 advance down\\n1.5 pitch_down down\\n2 advance up\\n3 end\\n", "k.txt")
>>> lim = SteerLimits()
>>> ks.command_at(1.0, lim), ks.command_at(1.6, lim).pitch_rate_rad_s, ks.end_s
(SteerCommand(yaw_rate_rad_s=0.0, pitch_rate_rad_s=0.0, advance_mm_s=20.0), -0.3, 3.0)
>>> KeyScript.parse("0 jump down\\n", "k.txt")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
hrm_ctrl.drive.command.DriveError: k.txt:1: unknown key 'jump' (keys: advance, ...)
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from hrm_ctrl.drive.command import DriveError, SteerCommand, SteerLimits
from hrm_ctrl.files import read_text_file

MAX_SCRIPT_BYTES = 1 << 20
MAX_SCRIPT_S = 24 * 3600.0


class SteerKey(StrEnum):
    """The logical keys of driving (a keyboard or gamepad maps its own onto these)."""

    ADVANCE = "advance"
    RETRACT = "retract"
    YAW_LEFT = "yaw_left"
    YAW_RIGHT = "yaw_right"
    PITCH_UP = "pitch_up"
    PITCH_DOWN = "pitch_down"


def command_of_keys(held: frozenset[SteerKey], limits: SteerLimits) -> SteerCommand:
    """The command of the keys held.

    >>> command_of_keys(frozenset({SteerKey.RETRACT, SteerKey.YAW_LEFT}), SteerLimits())
    SteerCommand(yaw_rate_rad_s=0.3, pitch_rate_rad_s=0.0, advance_mm_s=-20.0)
    """

    def axis(plus: SteerKey, minus: SteerKey) -> float:
        return float(plus in held) - float(minus in held)

    return SteerCommand.from_axes(
        axis(SteerKey.YAW_LEFT, SteerKey.YAW_RIGHT),
        axis(SteerKey.PITCH_UP, SteerKey.PITCH_DOWN),
        axis(SteerKey.ADVANCE, SteerKey.RETRACT),
        limits,
    )


@dataclass(frozen=True)
class KeyEvent:
    t_s: float
    key: SteerKey
    down: bool


@dataclass(frozen=True)
class KeyScript:
    """A parsed key sequence: its events in time order and its end (inf if none).

    The keys held after each event are kept with the events' times: the keys at a time
    are a bisection away (a control cycle asks every period)."""

    events: tuple[KeyEvent, ...]
    end_s: float
    source: str
    _times: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _held: tuple[frozenset[SteerKey], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        held: set[SteerKey] = set()
        after: list[frozenset[SteerKey]] = []
        for e in self.events:
            (held.add if e.down else held.discard)(e.key)
            after.append(frozenset(held))
        object.__setattr__(self, "_times", tuple(e.t_s for e in self.events))
        object.__setattr__(self, "_held", tuple(after))

    @classmethod
    def read(cls, path: str | Path) -> KeyScript:
        text = read_text_file(Path(path), DriveError, "key script", max_bytes=MAX_SCRIPT_BYTES)
        return cls.parse(text, str(path))

    @classmethod
    def parse(cls, text: str, source: str) -> KeyScript:
        events: list[KeyEvent] = []
        end = math.inf
        last = 0.0
        names = ", ".join(k.value for k in SteerKey)
        for n, raw in enumerate(text.splitlines(), start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            where = f"{source}:{n}"
            try:
                t = float(parts[0])
            except ValueError:
                raise DriveError(f"{where}: time is not a number: {parts[0]!r}") from None
            if not (math.isfinite(t) and 0.0 <= t <= MAX_SCRIPT_S):
                raise DriveError(f"{where}: time must be in [0, {MAX_SCRIPT_S:g}] s, got {t}")
            if t < last:
                raise DriveError(f"{where}: time {t:g} s goes back (last {last:g} s)")
            if end < math.inf:
                raise DriveError(f"{where}: an event after 'end'")
            last = t
            if len(parts) == 2 and parts[1] == "end":
                end = t
                continue
            if len(parts) != 3:
                raise DriveError(f"{where}: expected 'T_S KEY down|up' or 'T_S end', got {line!r}")
            try:
                key = SteerKey(parts[1])
            except ValueError:
                raise DriveError(f"{where}: unknown key {parts[1]!r} (keys: {names})") from None
            if parts[2] not in ("down", "up"):
                raise DriveError(f"{where}: expected down or up, got {parts[2]!r}")
            events.append(KeyEvent(t, key, parts[2] == "down"))
        return cls(tuple(events), end, source)

    def held_at(self, t_s: float) -> frozenset[SteerKey]:
        """The keys held at ``t_s`` (events at or before it applied).

        >>> ks = KeyScript.parse("1 advance down\\n1 yaw_left down\\n2 advance up\\n", "k")
        >>> [sorted(k.value for k in ks.held_at(t)) for t in (0.5, 1.0, 2.0)]
        [[], ['advance', 'yaw_left'], ['yaw_left']]
        """
        k = bisect_right(self._times, t_s)
        return self._held[k - 1] if k else frozenset()

    def command_at(self, t_s: float, limits: SteerLimits) -> SteerCommand:
        return command_of_keys(self.held_at(t_s), limits)


def bent_pipe_keys(limits: SteerLimits, *, period_s: float = 0.01) -> str:
    """The key sequence that steers the tip along the bent pipe of the paper (``NOTES.md``:
    158.579 mm straight, 45 deg down on a radius of 100 mm, 200 mm, 45 deg back up, 158.579
    mm) from its entry, advancing at ``limits.advance_mm_s`` with the pitch rate the radius
    asks (``limits.pitch_rate_rad_s`` must be ``advance / 100``), each event on a control
    cycle (``period_s``) and the advance released where the ramp down ends at the pipe's end.

    >>> print(bent_pipe_keys(SteerLimits(pitch_rate_rad_s=0.2)), end="")
    0 advance down
    8.18 pitch_down down
    12.11 pitch_down up
    22.11 pitch_up down
    26.03 pitch_up up
    33.71 advance up
    34.21 end
    """
    v, a = limits.advance_mm_s, limits.accel_mm_s2
    if abs(limits.pitch_rate_rad_s - v / 100.0) > 1e-9:
        raise DriveError("bent pipe keys: the pitch rate must be advance / 100 mm (radius 100)")
    ramp_s, ramp_mm = v / a, 0.5 * v * v / a
    arc = 100.0 * math.pi / 4.0
    marks = [158.579, 158.579 + arc, 358.579 + arc, 358.579 + 2 * arc]
    length = 674.237  # the pipe axis (NOTES.md)

    def at(mm: float) -> float:  # the time the tip reaches mm, on a control cycle
        return round((ramp_s + (mm - ramp_mm) / v) / period_s) * period_s

    release = at(length - ramp_mm)
    lines = [
        "0 advance down",
        f"{at(marks[0]):.10g} pitch_down down",
        f"{at(marks[1]):.10g} pitch_down up",
        f"{at(marks[2]):.10g} pitch_up down",
        f"{at(marks[3]):.10g} pitch_up up",
        f"{release:.10g} advance up",
        f"{release + ramp_s:.10g} end",
    ]
    return "\n".join(lines) + "\n"
