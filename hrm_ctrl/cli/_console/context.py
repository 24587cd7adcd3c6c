"""What every console command works on: :class:`ConsoleContext`.

One context per console process: the bus configuration, the arm (robot model with the
calibration's links, its rope layer, the calibration used), the live drive session once
``connect`` has opened it (None before), the simulated box's controls with ``--sim``, the
output functions, and where runs and their CAN logs go.

>>> lines = []
>>> ctx = ConsoleContext(config=None, description=None, model=None, actuation=None,
...                      out=lines.append, err=lines.append)
>>> ctx.out("hello"); lines
['hello']
>>> ctx.connected
False
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

Writer = Callable[[str], None]


@dataclass
class ConsoleContext:
    """The console's state.  ``config`` is the :class:`drivers.config.BoxConfig` (rewritten
    onto the simulated box's buses with ``--sim``), ``description`` the robot description as loaded,
    ``model`` the robot model with the calibration's links, ``actuation`` its rope layer,
    ``calibration`` the :class:`drivers.session.CalibrationRef` used (None: the
    description's values), ``active`` the ``calibration.apply.ActiveCalibration`` (or None).
    ``session`` is the :class:`drivers.session.DriveSession` after ``connect`` (None
    before and after ``disconnect``), ``sim`` the simulated box's controls with ``--sim``
    (``hrm_ctrl.runtime.simulated.SimControl``: the box in its own process, or with an
    in-process ``--wire`` an ``InProcessSim``).  ``out``/``err`` print one line each.
    ``runs_dir`` is where each session's CAN logs and run record go, ``last_run`` the
    last run record written (or None).
    ``stop_requested`` is set (by another thread: a progress display's ``stop``) to end a
    move early (:func:`hrm_ctrl.cli._console.streaming.play` stops every axis).
    ``extra`` keeps commands' own state by key (``tension_reader``: the tension board's
    reader, open while connected)."""

    config: Any
    description: Any
    model: Any
    actuation: Any
    out: Writer = print
    err: Writer = print
    calibration: Any = None
    active: Any = None
    allow_uncalibrated: bool = False
    session: Any = None
    sim: Any = None
    simulated: bool = False
    runs_dir: Path = Path("runs")
    log_suffix: str = ".blf"
    last_run: Path | None = None
    take_over: bool = False
    prog: str = "hrm console"
    stop_requested: threading.Event = field(default_factory=threading.Event)
    interactive: bool = False  # the shell at a terminal (not a script, not one-shot)
    quit_requested: bool = False  # `quit` ran: the shell ends after this command
    watches: Any = None  # the feedback watches (tension, ropes) of the session, once enabled
    extra: dict[str, Any] = field(default_factory=dict)  # commands' own state, by key
    script_path: Path | None = None  # the script file being run: no command writes over it

    @property
    def connected(self) -> bool:
        """A drive session is open (``connect`` done, not yet ``disconnect``)."""
        return self.session is not None

    @property
    def enabled(self) -> bool:
        """The session's drives are enabled (ENABLED or STREAMING)."""
        return self.session is not None and bool(self.session.enabled)
