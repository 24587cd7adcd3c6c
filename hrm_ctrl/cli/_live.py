"""The live view of a drive session (``hrm view --live``, the console's ``view``): the arm
as the host estimates it from drive feedback, in the browser.

:func:`start_live_view` serves an :class:`hrm_ctrl.view.server.ArmView` and starts a feed
thread: every ``1 / rate_hz`` s it copies the actual positions the drives report
(``session.monitor.position``, counts), turns them into joint angles with the rope layer
(:meth:`hrm_ctrl.ropes.actuation.Actuation.angles_from_counts`, warm-started from the last
estimate, no slow fallback: one bounded solve per tick) and shows that pose.  Until every
drive has reported a position nothing is shown.  With ``trail`` (``hrm drive``: the
trail the tip has drawn, points (P, 3) mm) each tick also draws the trail as it is then
(:meth:`hrm_ctrl.view.server.ArmView.show_trail`; an unchanged trail sends nothing).
The thread stops when the session closes or the handle is closed; a tick whose counts do
not solve is skipped and counted.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hrm_ctrl.errors import DriverError, HrmError, RopeError
from hrm_ctrl.view.server import ArmView

LIVE_RATE_HZ = 20.0  # feed ticks a second (issue 11 asks for >= 10 Hz)
CLOSE_TIMEOUT_S = 5.0  # longest wait for the feed thread at close()

# The trail to draw, read once a tick: points (P, 3) mm (None or fewer than 2: none yet).
TrailFeed = Callable[[], np.ndarray | None]


class LiveView:
    """A served live view and its feed thread: ``url``, ``close()``, and what the feed
    did (``ticks``, ``shown``, ``skipped``, ``rate_hz()``)."""

    def __init__(
        self,
        session: Any,
        actuation: Any,
        view: ArmView,
        rate_hz: float = LIVE_RATE_HZ,
        trail: TrailFeed | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise DriverError(f"live view rate must be > 0 Hz, got {rate_hz}")
        self.session = session
        self.actuation = actuation
        self.view = view
        self.url = view.url
        self.period_s = 1.0 / rate_hz
        self.ticks = 0  # feed ticks with every drive's position known
        self.shown = 0  # poses handed to the view
        self.skipped = 0  # ticks whose counts did not solve
        self.last_error: str | None = None
        self.trail = trail
        self._t_first: float | None = None
        self._t_last: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._feed, name="hrm-live-view", daemon=True)
        self._thread.start()

    def _session_closed(self) -> bool:
        from drivers.session import SessionState

        return self.session.state is SessionState.CLOSED

    def _feed(self) -> None:
        monitor = self.session.monitor
        alpha = theta = None
        next_t = time.monotonic()
        while not self._stop.is_set():
            if self._session_closed():
                break
            if int(monitor.n_tpdo.min()) > 0:  # every drive has reported a position
                counts = np.array(monitor.position, dtype=np.int64)
                self.ticks += 1
                try:
                    alpha, theta, _ = self.actuation.angles_from_counts(
                        counts, alpha0=alpha, theta0=theta, robust=False
                    )
                    if not (np.isfinite(alpha).all() and np.isfinite(theta).all()):
                        raise RopeError("the estimate is not finite")
                    self.view.update(alpha, theta)
                    self.shown += 1
                    now = time.monotonic()
                    self._t_first = now if self._t_first is None else self._t_first
                    self._t_last = now
                except HrmError as exc:  # a pose the rope layer cannot explain: skip it
                    self.skipped += 1
                    self.last_error = str(exc)
                    alpha = theta = None
            self._show_trail()
            next_t += self.period_s
            now = time.monotonic()
            if next_t < now:  # late (a busy machine): no burst to catch up
                next_t = now
            self._stop.wait(next_t - now)
        self.view.flush()

    def set_trail(self, trail: TrailFeed | None) -> None:
        """Draw this trail from the next tick on (None: stop reading one; the trail drawn
        stays): the console's ``drive`` hands its trail to a ``view`` already running."""
        self.trail = trail

    def _show_trail(self) -> None:
        trail = self.trail  # read once: set_trail() may change it from another thread
        if trail is None:
            return
        points = trail()
        if points is None or len(points) < 2:
            return
        try:
            self.view.show_trail(np.array(points, dtype=float))  # a copy: the planner grows it
        except HrmError as exc:  # a malformed trail: not drawn, said why
            self.last_error = str(exc)

    def rate_hz(self) -> float:
        """Poses shown a second so far (0 before two were shown)."""
        if self._t_first is None or self._t_last is None or self.shown < 2:
            return 0.0
        dt = self._t_last - self._t_first
        return (self.shown - 1) / dt if dt > 0 else 0.0

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def close(self) -> None:
        """Stop the feed thread and the server (idempotent)."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(CLOSE_TIMEOUT_S)
        self.view.close()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_live_view(
    session: Any,
    actuation: Any,
    model: Any,
    environment: Any = None,
    port: int = 0,
    *,
    plan: Any = None,
    step: int = 0,
    rate_hz: float = LIVE_RATE_HZ,
    trail: TrailFeed | None = None,
) -> LiveView:
    """Serve the live view of ``session`` (an open :class:`drivers.session.DriveSession`)
    on 127.0.0.1:``port`` (0: a free one) and start its feed; returns the handle
    (``.url``, ``.close()``).  ``actuation`` is the session's rope layer, ``model`` the
    robot drawn (its links and diameters), ``environment`` the obstacles (None: none
    known), ``plan`` a plan drawn beside it (path, backbone, the planned arm at ``step``),
    ``trail`` the trail the tip has drawn (read every tick)."""
    from drivers.session import SessionState

    if session.state is SessionState.CLOSED:
        raise DriverError("live view: the drive session is not open")
    view = ArmView(model, environment, plan, port=port, step=step, live=True)
    try:
        return LiveView(session, actuation, view, rate_hz, trail)
    except BaseException:
        view.close()
        raise
