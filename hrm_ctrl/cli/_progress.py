"""Progress bars for the console's long operations (refinement, time parameterisation,
bring-up, runs, calibration): rich's progress display on stderr, with an optional live
line after the bar (a run's travel, tip error, tension, bus load, late cycles).

Quiet (every call a no-op) when stdout is not a terminal, with ``--json``, or with
``HRM_PROGRESS=0`` in the environment (``HRM_PROGRESS=1`` forces it on: tests, and
``script``-recorded sessions).  The library side knows nothing of this: the planner, the
trajectory and the calibration take a ``progress(fraction)`` callback; the control loop's
thread never calls into this module (a run's display is fed by its own thread,
:mod:`hrm_ctrl.cli._runcontrol`).

>>> with ProgressBar("refining", enabled=False) as bar:
...     bar(0.5)
...     bar.line("step 3")
>>> bar.fraction
0.5
"""

from __future__ import annotations

import math
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

ProgressFn = Callable[[float], None]
ENV = "HRM_PROGRESS"


def wanted(json_output: bool = False, stream: Any = None) -> bool:
    """Whether to show progress: stdout is a terminal and no ``--json`` (``HRM_PROGRESS``
    overrides: ``0`` never, ``1`` always).

    >>> import io
    >>> os.environ.pop(ENV, None) and None
    >>> wanted(False, io.StringIO())
    False
    """
    env = os.environ.get(ENV)
    if env == "0":
        return False
    if env == "1":
        return True
    if json_output:
        return False
    out = sys.stdout if stream is None else stream
    try:
        return bool(out.isatty())
    except (AttributeError, ValueError):
        return False


class ProgressBar:
    """One progress bar (a context manager): call it with the fraction done (0..1),
    :meth:`line` sets the text shown after it.  Disabled: it only remembers the values.
    Thread-safe (rich's display refreshes from its own thread)."""

    def __init__(self, description: str, *, enabled: bool = True, transient: bool = True) -> None:
        self.description = description
        self.enabled = bool(enabled)
        self.transient = transient
        self.fraction = 0.0
        self.text = ""
        self._lock = threading.Lock()
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> ProgressBar:
        if self.enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                Progress,
                TaskProgressColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._progress = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TaskProgressColumn(),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                TextColumn("{task.fields[line]}"),
                console=Console(stderr=True),
                transient=self.transient,
                refresh_per_second=4,
            )
            self._progress.start()
            self._task = self._progress.add_task(self.description, total=1.0, line="")
        return self

    def __call__(self, fraction: float) -> None:
        f = float(fraction)
        if not math.isfinite(f):
            return
        with self._lock:
            self.fraction = min(1.0, max(0.0, f))
            if self._progress is not None:
                self._progress.update(self._task, completed=self.fraction)

    def line(self, text: str) -> None:
        with self._lock:
            self.text = str(text)
            if self._progress is not None:
                self._progress.update(self._task, line=self.text)

    def describe(self, description: str) -> None:
        """Change the bar's label (e.g. the phase of a bring-up)."""
        with self._lock:
            self.description = description
            if self._progress is not None:
                self._progress.update(self._task, description=description)

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            if self._progress is not None:
                self._progress.stop()
                self._progress = None


@contextmanager
def progress_bar(description: str, *, enabled: bool) -> Iterator[ProgressBar]:
    """``with progress_bar("time parameterisation", enabled=wanted(args.json)) as bar:``
    then pass ``bar`` as a ``progress`` callback."""
    with ProgressBar(description, enabled=enabled) as bar:
        yield bar


def bring_up_with_progress(box: Any, *, enabled: bool) -> Any:
    """``box.bring_up()`` (a :class:`drivers.session.DriveSession`) shown in two phases,
    configure (NMT reset, SDO configuration) and enable (CiA 402 to OPERATION_ENABLED),
    the same calls :meth:`~drivers.session.DriveSession.bring_up` makes (its calibration
    check first).  Returns the actual positions."""
    if not enabled:
        return box.bring_up()
    box._require_calibration("bring-up")
    with ProgressBar("bring-up: configure", enabled=True) as bar:
        box.configure()
        bar(0.5)
        bar.describe("bring-up: enable")
        actual = box.enable()
        bar(1.0)
    return actual
