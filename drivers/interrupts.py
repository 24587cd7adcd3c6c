"""Interrupts (Ctrl-C, SIGTERM, SIGHUP) that wait for the end of a critical section.

The console turns signals into exceptions raised in the main thread
(:mod:`hrm_ctrl.cli._signals`).  Some sequences must not be cut in the middle: a
drive enable (a half-enabled box is aborted by its own error path), the finish
(disable, NMT pre-operational, host heartbeat last), closing the logs and writing the
run record.  Inside :func:`deferred_interrupts` an interrupt is held and raised when
the outermost section ends; outside, :func:`interrupt` raises it at once.  Every
section is bounded in time (its SDO and state waits have timeouts).

>>> try:
...     with deferred_interrupts():
...         interrupt(RuntimeError("SIGTERM"))     # held ...
...         print("section done")
... except RuntimeError as exc:
...     print("raised after it:", exc)             # ... and raised when it ends
section done
raised after it: SIGTERM
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

_state = threading.local()


def _depth() -> int:
    return getattr(_state, "depth", 0)


def interrupt(exc: BaseException) -> None:
    """Raise ``exc`` now, or (inside a critical section of this thread) when it ends."""
    if _depth() > 0:
        if getattr(_state, "pending", None) is None:
            _state.pending = exc  # the first one counts; repeats add nothing
        return
    raise exc


@contextmanager
def deferred_interrupts() -> Iterator[None]:
    """A critical section: interrupts arriving inside it are raised at its end."""
    _state.depth = _depth() + 1
    try:
        yield
    finally:
        _state.depth -= 1
        pending = getattr(_state, "pending", None)
        if _state.depth == 0 and pending is not None:
            _state.pending = None
            raise pending
