"""Moving the arm from the console: one setpoint source played on the live session, with
Ctrl-C (or SIGTERM/SIGHUP) as the stop.

:func:`play` runs :meth:`DriveSession.stream` on a worker thread and waits for it in
the main thread (bounded: the stream's own timeout plus a margin), so an interrupt
there quick-stops every axis through :meth:`DriveSession.request_stop` instead of
cutting the stream off half-way: the session goes STOPPED, the operator sees why, and
``disable`` / ``reset-fault`` / ``enable`` continue from there.  ``ctx.stop_requested``
set by another thread (a ``stop`` from a progress display) stops it the same way.

The feedback watches (tension board, rope consistency) run while the drives are enabled:
:func:`start_watches` after ``enable``, :func:`stop_watches` before ``disable``.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError
from hrm_ctrl.errors import HrmError, SignalInterrupt

WAIT_SLICE_S = 0.05  # the main thread looks at stop requests this often while moving
EXTRA_WAIT_S = 10.0  # beyond the stream's own timeout: its stop and last checks


def play(ctx: ConsoleContext, source: Any, what: str) -> Any:
    """Stream ``source`` (started by the session from the held positions); return its
    :class:`drivers.cycle.StreamResult`.  A stop (a watchdog, a limit, Ctrl-C, ``stop``)
    raises :class:`ConsoleError` naming why; Ctrl-C is not raised further (the console
    goes on), a SIGTERM/SIGHUP is, after the stop."""
    from drivers.safety.causes import StopKind

    session = ctx.session
    if session is None:
        raise ConsoleError("not connected (connect first)")
    done = threading.Event()
    box: dict[str, Any] = {}

    def worker() -> None:
        try:
            box["result"] = session.stream(source)
        except BaseException as exc:  # handed to the main thread
            box["error"] = exc
        finally:
            done.set()

    ctx.stop_requested.clear()
    thread = threading.Thread(target=worker, name=f"console-{what}", daemon=True)
    # until the stream moves, the source may not know its length yet (a table source
    # makes its table when the session starts it): the deadline then counts from the
    # first setpoint, the source's whole length plus the margins
    limit_s = session._stream_timeout_s(source) + EXTRA_WAIT_S
    deadline = time.monotonic() + limit_s
    interrupted: BaseException | None = None
    announced = False
    thread.start()
    while not done.is_set():
        try:
            done.wait(WAIT_SLICE_S)
            moving = session.supervisor.mode.name == "STREAMING"  # the first setpoint is out
            if not announced and moving and not done.is_set():
                announced = True
                limit_s = session._stream_timeout_s(source) + EXTRA_WAIT_S
                deadline = time.monotonic() + limit_s
                # a pausable source's n_cycles allows for its longest pause (the wait for
                # its end): what it plays is its table, n_rows cycles at full rate
                n = getattr(source, "n_rows", None) or getattr(source, "n_cycles", 0)
                period_s = ctx.config.control.period_s
                ctx.out(f"{what}: moving, {n} cycles ({n * period_s:.2f} s); Ctrl-C stops")
            if ctx.stop_requested.is_set():
                session.request_stop(StopKind.OPERATOR, f"{what}: stop requested (console)")
                ctx.stop_requested.clear()
            if time.monotonic() > deadline:
                session.request_stop(StopKind.INTERNAL, f"{what}: no end within {limit_s:g} s")
                deadline = time.monotonic() + EXTRA_WAIT_S
        except (KeyboardInterrupt, SignalInterrupt) as exc:
            interrupted = exc
            name = "Ctrl-C" if isinstance(exc, KeyboardInterrupt) else exc.signal_name
            kind = StopKind.OPERATOR if isinstance(exc, KeyboardInterrupt) else StopKind.SIGNAL
            session.request_stop(kind, f"{what}: stopped by {name}")
    thread.join(EXTRA_WAIT_S)
    if isinstance(interrupted, SignalInterrupt):
        raise interrupted
    if not done.is_set():
        raise ConsoleError(f"{what}: the stream did not end {EXTRA_WAIT_S:g} s after its stop")
    err = box.get("error")
    if err is None:
        return box["result"]
    if isinstance(err, HrmError):
        hint = _after_stop_hint(ctx)
        raise ConsoleError(f"{err}{hint}") from None
    raise err


def _after_stop_hint(ctx: ConsoleContext) -> str:
    session = ctx.session
    if session is None:
        return ""
    state = session.state.name
    if state == "STOPPED":
        return " (every axis quick-stopped: reset-fault or disable, then enable)"
    if state == "FAULT":
        return " (session FAULT: reset-fault, then enable)"
    return ""


def tension_sample(ctx: ConsoleContext) -> Any:
    """The tension board's newest sample (N per rope, the rope layer's order), or None
    when there is no board or no fresh sample."""
    from drivers.tension_sensor import TensionSensorError

    reader = ctx.extra.get("tension_reader")
    if reader is None:
        return None
    try:
        return reader.latest().tensions_N
    except TensionSensorError:
        return None


def start_watches(ctx: ConsoleContext) -> None:
    """The feedback watches of the enabled drives (:func:`hrm_ctrl.runtime.watches.watches_of`):
    the tension board (over the reader the session keeps open) and the rope layer's
    consistency check; either stops every axis through the session's monitor, naming the
    rope."""
    from hrm_ctrl.runtime.watches import watches_of

    stop_watches(ctx)
    reader = ctx.extra.get("tension_reader")
    watches = watches_of(
        ctx.config,
        ctx.actuation,
        ctx.session,
        reader=reader,
        tension=reader is not None,
        grace_s=0.0,  # the reader has been open since connect
    )
    watches.start()
    ctx.watches = watches


def stop_watches(ctx: ConsoleContext) -> None:
    """Stop the feedback watches (if running); their summaries go into the run record."""
    watches = ctx.watches
    if watches is None:
        return
    ctx.watches = None
    watches.stop()
    if ctx.session is not None:
        kept = ctx.session.record_extra.setdefault("watches", [])
        kept.append(watches.summary())
