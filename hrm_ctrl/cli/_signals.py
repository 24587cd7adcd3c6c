"""SIGTERM and SIGHUP do what SIGINT does: an interrupt in the main thread.

Python turns SIGINT into :class:`KeyboardInterrupt`; every stop path of the stack
(a stream quick-stops every axis, the session finishes, the run record is written,
the CAN logs are closed) handles it.  :func:`signals_as_interrupts` makes SIGTERM
(``kill``, systemd, a container stop) and SIGHUP (the terminal went away) raise
:class:`~hrm_ctrl.errors.SignalInterrupt` the same way, for the time of a command.

>>> import os, signal
>>> with signals_as_interrupts():
...     try:
...         os.kill(os.getpid(), signal.SIGTERM)
...     except SignalInterrupt as exc:
...         print(exc.signal_name, exc.signal_number == signal.SIGTERM)
SIGTERM True
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

from drivers.interrupts import interrupt
from hrm_ctrl.errors import SignalInterrupt

HANDLED = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)


def _raise(signum: int, _frame: FrameType | None) -> None:
    """Raise the interrupt now, or when the critical section running ends
    (:func:`drivers.interrupts.deferred_interrupts`: enable, finish, close)."""
    if signum == signal.SIGINT:
        interrupt(KeyboardInterrupt())
    else:
        interrupt(SignalInterrupt(signal.Signals(signum).name, signum))


@contextmanager
def signals_as_interrupts() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise :class:`SignalInterrupt` in the main
    thread (SIGINT :class:`KeyboardInterrupt`, as usual), held until the end of a
    critical section; the previous handlers come back afterwards (no-op off the main
    thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in HANDLED}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
