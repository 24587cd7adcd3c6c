"""The simulated laser tracker: end-point measurements on a pseudo-terminal.

The instrument serves the master side of a pseudo-terminal; the host opens the slave
path (:attr:`Tracker.port`) with pyserial as it would a USB serial adapter.  For each
request line ``MEAS`` it measures ``source()`` (the true end point O_13, base frame,
mm) and answers ``$PT,...`` (:mod:`drivers.protocol.tracker`) with the point in its own
frame, ``R p + t`` (the truth's ``tracker_rotation``, ``tracker_translation_mm``), plus
N(0, ``noise_mm``) per axis from a seeded generator.  An unknown request gets ``$ER,
<seq>,BADCMD``.  Fault hooks: :meth:`Tracker.lose_target` (replies flag the target
lost, no coordinates), :meth:`Tracker.set_silent` (requests are read, never answered),
:meth:`Tracker.inject_garbage` (random bytes instead of the next replies).

>>> import numpy as np, os
>>> t = Tracker(lambda: np.array([2007.0, 0.0, 0.0]), np.eye(3), np.zeros(3), noise_mm=0.0)
>>> t.reply(b"MEAS\\n")
b'$PT,0,2007.0000,0.0000,0.0000,00*33\\r\\n'
>>> t.lose_target(True); t.reply(b"MEAS\\n")
b'$PT,1,,,,01*18\\r\\n'
"""

from __future__ import annotations

import os
import select
import threading
from collections.abc import Callable

import numpy as np

from drivers.protocol.tracker import (
    MAX_REQUEST_BYTES,
    STATUS_OK,
    STATUS_TARGET_LOST,
    make_error_line,
    make_point_line,
    parse_request_target,
)
from hrm_ctrl.errors import SimError
from sim_bus.pty_device import PtyDevice

POLL_S = 0.05  # the thread checks for stop this often


class Tracker(PtyDevice):
    """A laser tracker thread answering requests on a pseudo-terminal (see module doc)."""

    THREAD_NAME = "sim-tracker"

    def __init__(
        self,
        source: Callable[[], np.ndarray],
        rotation: np.ndarray,
        translation_mm: np.ndarray,
        *,
        noise_mm: float = 0.05,
        seed: int = 0,
        fiducials_mm: np.ndarray | None = None,
    ) -> None:
        if not (0.0 <= noise_mm <= 1.0):
            raise SimError(f"tracker noise must be in [0, 1] mm, got {noise_mm!r}")
        super().__init__()
        self.source = source
        self.rotation = np.array(rotation, dtype=float)
        self.translation_mm = np.array(translation_mm, dtype=float)
        self.noise_mm = float(noise_mm)
        self.fiducials_mm = (  # the base plate's nests, base frame (request "MEAS F<k>")
            np.zeros((0, 3)) if fiducials_mm is None else np.array(fiducials_mm, dtype=float)
        )
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._lost = False
        self._silent = False
        self._garbage = 0  # replies still to be replaced by garbage
        self._seq = 0
        self.requests = 0
        self.replies = 0
        self.errors: list[str] = []

    # ------------------------------------------------------------ faults
    def lose_target(self, lost: bool = True) -> None:
        """The beam is broken (or restored): replies flag the target lost."""
        with self._lock:
            self._lost = bool(lost)

    def set_silent(self, silent: bool = True) -> None:
        """The instrument stops answering (or answers again)."""
        with self._lock:
            self._silent = bool(silent)

    def inject_garbage(self, replies: int = 1) -> None:
        """The next ``replies`` replies are random bytes ending in ``\\r\\n``."""
        with self._lock:
            self._garbage = int(replies)

    # ------------------------------------------------------------ engine
    def measured_point(self, fiducial: int = 0) -> np.ndarray:
        """One reading (tracker frame, mm): ``R p + t`` plus the noise, of the end point or
        (``fiducial`` k >= 1) of base nest k."""
        p = (
            np.asarray(self.source(), dtype=float)
            if fiducial == 0
            else self.fiducials_mm[fiducial - 1]
        )
        q = self.rotation @ p + self.translation_mm
        if self.noise_mm > 0:
            q = q + self._rng.normal(0.0, self.noise_mm, 3)
        return q

    def reply(self, request: bytes) -> bytes | None:
        """The reply to one request line (None: silent); pure but for the counters."""
        with self._lock:
            lost, silent = self._lost, self._silent
            garbage = self._garbage > 0
            self._garbage = max(0, self._garbage - 1)
            seq = self._seq
            if not silent:
                self._seq = (self._seq + 1) % 65536
        self.requests += 1
        if silent:
            return None
        if garbage:
            n = int(self._rng.integers(8, 40))
            return self._rng.integers(0x21, 0x7F, n, dtype=np.uint8).tobytes() + b"\r\n"
        target = parse_request_target(request)
        if target is None:
            return make_error_line(seq, "BADCMD")
        if target > len(self.fiducials_mm):
            return make_error_line(seq, "NONEST")
        if lost and target == 0:
            return make_point_line(seq, None, STATUS_TARGET_LOST)
        return make_point_line(seq, self.measured_point(target), STATUS_OK)

    def _run(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], POLL_S)
            except (OSError, ValueError):
                return
            if not ready:
                continue
            try:
                data = os.read(self._master, 256)
            except BlockingIOError:
                continue
            except OSError:  # the host side closed: nothing to read until it reopens
                if self._stop.wait(POLL_S):
                    return
                continue
            buf += data
            while b"\n" in buf:
                line, _, rest = bytes(buf).partition(b"\n")
                buf = bytearray(rest)
                self._answer(line + b"\n")
            if len(buf) > MAX_REQUEST_BYTES:  # no end of line: not a request, drop it
                self._answer(bytes(buf))
                buf.clear()

    def _answer(self, line: bytes) -> None:
        try:
            out = self.reply(line)
        except Exception as exc:  # the instrument keeps running; the host sees silence
            if len(self.errors) < 100:
                self.errors.append(repr(exc))
            return
        if out is None:
            return
        try:
            os.write(self._master, out)
            self.replies += 1
        except OSError as exc:
            if len(self.errors) < 100:
                self.errors.append(repr(exc))
