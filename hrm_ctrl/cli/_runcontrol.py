"""Pause, resume and abort of a plan being played, and its live display (``hrm run``, the
console's ``run``).

The plan is played by a :class:`drivers.sources.PausableSource`; three things may drive
it, each from its own thread (never the control loop's):

* the keyboard, when stdin is a terminal: ``p`` or space pauses / resumes, ``a`` aborts
  (stops on the path, then ends the run), Ctrl-C stops every axis at once;
* a script of the run's own arguments (``--pause-at 30% --resume-after 1s``,
  ``--abort-at 60%``): what tests and unattended runs use;
* the console's other thread (``ctx``).

:class:`RunDisplay` feeds the progress bar and the live line (travel, tip error against
the plan from the feedback, worst tension, bus load, late cycles) four times a second.

>>> parse_fraction("30%"), parse_fraction("0.25"), parse_seconds("1.5s"), parse_seconds("2")
(0.3, 0.25, 1.5, 2.0)
>>> parse_fraction("130%")
Traceback (most recent call last):
...
hrm_ctrl.errors.DriverError: --pause-at '130%': a fraction of the run, 0..100 %
"""

from __future__ import annotations

import math
import select
import sys
import threading
import time
from typing import Any

import numpy as np

from hrm_ctrl.errors import DriverError

DISPLAY_PERIOD_S = 0.25
TIP_EVERY_S = 1.0  # the tip error (two rope-layer inverses) at most this often
KEY_POLL_S = 0.1
SAMPLE_PERIOD_S = 0.1  # the samples a run keeps for its figures and tension file
MAX_SAMPLES = 36_000  # at most (an hour at 10 Hz)
MAX_SCRIPT_WAIT_S = 3600.0


def parse_fraction(text: str, what: str = "--pause-at") -> float:
    s = str(text).strip()
    try:
        f = float(s[:-1]) / 100.0 if s.endswith("%") else float(s)
    except ValueError:
        raise DriverError(f"{what} {text!r}: a fraction of the run, 0..100 %") from None
    if not (math.isfinite(f) and 0.0 <= f <= 1.0):
        raise DriverError(f"{what} {text!r}: a fraction of the run, 0..100 %")
    return f


def parse_seconds(text: str, what: str = "--resume-after") -> float:
    s = str(text).strip()
    try:
        v = float(s[:-1] if s.endswith("s") else s)
    except ValueError:
        raise DriverError(f"{what} {text!r}: seconds, e.g. 1.5s") from None
    if not (math.isfinite(v) and 0.0 <= v <= MAX_SCRIPT_WAIT_S):
        raise DriverError(f"{what} {text!r}: seconds from 0 to {MAX_SCRIPT_WAIT_S:g}")
    return v


class RunScript:
    """What ``--pause-at`` / ``--resume-after`` / ``--abort-at`` ask for (checked before
    anything is sent: :meth:`from_args`)."""

    def __init__(
        self, pause_at: float | None, resume_after_s: float | None, abort_at: float | None
    ) -> None:
        if resume_after_s is not None and pause_at is None:
            raise DriverError("--resume-after goes with --pause-at")
        self.pause_at = pause_at
        self.resume_after_s = resume_after_s
        self.abort_at = abort_at

    @classmethod
    def from_args(cls, args: Any) -> RunScript:
        g = getattr
        return cls(
            None if g(args, "pause_at", None) is None else parse_fraction(args.pause_at),
            None if g(args, "resume_after", None) is None else parse_seconds(args.resume_after),
            None
            if g(args, "abort_at", None) is None
            else parse_fraction(args.abort_at, "--abort-at"),
        )

    @property
    def empty(self) -> bool:
        return self.pause_at is None and self.abort_at is None


def fraction_done(source: Any) -> float:
    n = int(getattr(source, "n_rows", 0))
    return 0.0 if n <= 1 else min(1.0, float(source.position) / (n - 1))


class RunDriver(threading.Thread):
    """One thread that plays a :class:`RunScript` and reads the keyboard (when stdin is a
    terminal and ``keys``) against a :class:`~drivers.sources.PausableSource`, and feeds
    a progress bar with :class:`RunDisplay` text.  ``stop()`` ends it (and restores the
    terminal)."""

    def __init__(
        self,
        source: Any,
        script: RunScript | None = None,
        *,
        keys: bool = False,
        display: RunDisplay | None = None,
        bar: Any = None,
    ) -> None:
        super().__init__(name="hrm-run-control", daemon=True)
        self.source = source
        self.script = script or RunScript(None, None, None)
        self.keys = bool(keys) and _stdin_is_terminal()
        self.display = display
        self.bar = bar
        self.events: list[tuple[str, float]] = []  # (what, fraction done) as it happened
        # (unix time, targets applied, positions reported, tensions N or None), 10 Hz
        self.samples: list[tuple[float, Any, Any, Any]] = []
        self._quit = threading.Event()
        self._paused_at: float | None = None
        self._resumed = False
        self._aborted = False

    def stop(self) -> None:
        self._quit.set()
        if self.is_alive():
            self.join(2.0)

    def _act(self, what: str) -> None:
        getattr(self.source, what)()
        self.events.append((what, fraction_done(self.source)))

    def _script_step(self) -> None:
        from drivers.sources import PlayState

        s, f = self.script, fraction_done(self.source)
        if s.abort_at is not None and not self._aborted and f >= s.abort_at:
            self._aborted = True
            self._act("abort")
        if s.pause_at is not None and self._paused_at is None and f >= s.pause_at:
            self._paused_at = math.inf
            self._act("pause")
        if self._paused_at == math.inf and self.source.state is PlayState.PAUSED:
            self._paused_at = time.monotonic()
        if (
            s.resume_after_s is not None
            and not self._resumed
            and self._paused_at is not None
            and self._paused_at != math.inf
            and time.monotonic() - self._paused_at >= s.resume_after_s
        ):
            self._resumed = True
            self._act("resume")

    def _key(self, ch: str) -> None:
        if ch in ("p", " "):
            self._act("resume" if self.source.requested == "pause" else "pause")
        elif ch == "r":
            self._act("resume")
        elif ch == "a":
            self._act("abort")

    def run(self) -> None:
        old = _cbreak() if self.keys else None
        try:
            last = 0.0
            last_sample = 0.0
            while not self._quit.is_set():
                now = time.monotonic()
                if self.display is not None and now - last_sample >= SAMPLE_PERIOD_S:
                    last_sample = now
                    if len(self.samples) < MAX_SAMPLES:
                        self.samples.append(self.display.sample())
                self._script_step()
                if self.keys and _key_ready(KEY_POLL_S / 2):
                    self._key(sys.stdin.read(1).lower())
                now = time.monotonic()
                shown = self.bar is not None and getattr(self.bar, "enabled", True)
                if shown and now - last >= DISPLAY_PERIOD_S:
                    last = now
                    self.bar(fraction_done(self.source))
                    if self.display is not None:
                        self.bar.line(self.display.text())
                self._quit.wait(KEY_POLL_S / 2)
        finally:
            if old is not None:
                _restore(old)


def _stdin_is_terminal() -> bool:
    try:
        return bool(sys.stdin.isatty())
    except (AttributeError, ValueError):
        return False


def _cbreak() -> Any:
    import termios
    import tty

    try:
        old = termios.tcgetattr(sys.stdin.fileno())
        tty.setcbreak(sys.stdin.fileno())  # keys one by one; Ctrl-C still SIGINT
    except (termios.error, OSError, ValueError):
        return None
    return old


def _restore(old: Any) -> None:
    import termios

    try:
        termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, old)
    except (termios.error, OSError, ValueError):
        pass


def _key_ready(timeout_s: float) -> bool:
    try:
        r, _, _ = select.select([sys.stdin], [], [], timeout_s)
    except (OSError, ValueError):
        return False
    return bool(r)


class RunDisplay:
    """The live line of a plan run: plan step and travel, the tip's distance from where
    the plan puts it (the rope layer's inverse of the feedback and of the setpoint played,
    every :data:`TIP_EVERY_S`), the worst rope tension (when a tension board is read), the
    worst bus load (the configured worst case), the late cycles so far, and the play state.
    Reads the session's state from the display thread (numbers the loop publishes)."""

    def __init__(
        self, source: Any, setpoints: Any, session: Any, model: Any, watches: Any = None
    ) -> None:
        self.source = source
        self.watches = watches
        self.sp = setpoints
        self.session = session
        self.model = model
        self._tip_t = 0.0
        self._tip_mm: float | None = None
        self._travel: np.ndarray | None = None  # each row's travel (mm), once

    def where(self) -> tuple[int | None, float | None]:
        """(plan step, travel mm) at the playback position (None: in the lead-in)."""
        inner = getattr(self.source, "inner", self.source)
        row = math.floor(float(getattr(self.source, "position", 0.0)))
        body = row - int(getattr(inner, "n_lead_in", 0))
        sp = self.sp
        if sp is None or body < 0:
            return None, None
        body = min(body, len(sp.step_of_row) - 1)
        step = int(sp.step_of_row[body])
        if self._travel is None:
            rows = getattr(sp, "row_travel_mm", None)
            self._travel = np.asarray(rows()) if callable(rows) else None
        if self._travel is not None:
            return step, float(self._travel[body])
        return step, float(sp.travel_mm[step])

    def where_text(self) -> str:
        step, travel = self.where()
        pct = 100.0 * fraction_done(self.source)
        if self.sp is None:
            return f"{pct:.0f} % of the way"
        if step is None:
            return f"the lead-in to the plan's first step ({pct:.0f} % of the run)"
        return f"plan step {step}, travel {travel:.1f} mm ({pct:.0f} % of the run)"

    def _tip(self) -> float | None:
        now = time.monotonic()
        if now - self._tip_t < TIP_EVERY_S:
            return self._tip_mm
        self._tip_t = now
        try:
            from hrm_ctrl.kinematics import end_point

            act = self.session.actuation
            actual = np.asarray(self.session.monitor.position, dtype=np.int64).copy()
            target = self.session.supervisor.targets
            if target is None:
                return self._tip_mm
            a1, t1, _ = act.angles_from_counts(actual, robust=False)
            a0, t0, _ = act.angles_from_counts(np.asarray(target), robust=False)
            d = end_point(self.model, a1, t1) - end_point(self.model, a0, t0)
            self._tip_mm = float(np.linalg.norm(d))
        except Exception:  # a display figure, never a reason to stop
            self._tip_mm = None
        return self._tip_mm

    def tensions(self) -> np.ndarray | None:
        """The newest tension sample (N per motor), or None (no board, stale)."""
        w = self.watches
        tw = None if w is None else w.watches.get("tension")
        reader = getattr(tw, "reader", None)
        if reader is None:
            return None
        try:
            return np.asarray(reader.latest().tensions_N, dtype=np.float64).copy()
        except Exception:
            return None

    def sample(self) -> tuple[float, Any, Any, Any]:
        """(unix time, targets applied, positions reported, tensions or None) now."""
        sup = self.session.supervisor
        target = sup.targets
        return (
            time.time(),
            None if target is None else np.asarray(target, dtype=np.int64).copy(),
            np.asarray(self.session.monitor.position, dtype=np.int64).copy(),
            self.tensions(),
        )

    def _tension(self) -> str:
        w = self.watches
        tw = None if w is None else w.watches.get("tension")
        if getattr(tw, "reader", None) is None:
            return ""
        t = self.tensions()
        if t is None:
            return "  tension: stale"
        if not np.isfinite(t).any():
            return "  tension: invalid"
        i = int(np.nanargmax(t))
        return f"  max tension {t[i]:.0f} N ({self.session.actuation.motor_ids[i]})"

    def _late(self) -> int:
        stream = getattr(self.session.supervisor, "_stream", None)
        if stream is None:
            return 0
        return int(stream.stats.late_cycles)

    def text(self) -> str:
        step, travel = self.where()
        parts = []
        if step is not None:
            parts.append(f"step {step} {travel:.1f} mm")
        tip = self._tip()
        if tip is not None:
            parts.append(f"tip {tip:.2f} mm")
        loads = getattr(self.session, "loads", [])
        if loads:
            parts.append(f"bus {100 * max(bl.load for bl in loads):.0f} %")
        parts.append(f"late {self._late()}")
        state = getattr(self.source, "state", None)
        if state is not None and state.value != "playing":
            parts.append(state.value.upper())
        return "  ".join(parts) + self._tension()


def write_run_tensions(driver: RunDriver | None, record_path: Any, motor_ids: Any) -> Any:
    """Write the tensions a run's driver sampled as ``<run>_tension.csv`` beside its run
    record (atomically, bounded); None when there were none (no tension board)."""
    if driver is None or record_path is None:
        return None
    from hrm_ctrl.formats.runlog import tension_path, write_tension_csv

    rows = [(t, n) for t, _tg, _pos, n in driver.samples if n is not None]
    if not rows:
        return None
    t = [r[0] for r in rows]
    tn = np.array([r[1] for r in rows], dtype=np.float64)
    return write_tension_csv(tension_path(record_path), t, tn, list(motor_ids))
