"""A simulated serial instrument on a pseudo-terminal: the life cycle the tension board and
the laser tracker share.

The device thread owns the master side; the host opens the slave path (:attr:`port`) with
pyserial as it would a USB serial adapter.  A subclass gives :attr:`THREAD_NAME` and
``_run`` (its loop, ending when :attr:`_stop` is set).

>>> class Quiet(PtyDevice):
...     THREAD_NAME = "quiet"
...     def _run(self) -> None:
...         self._stop.wait(5.0)
>>> with Quiet() as dev:
...     dev.port.startswith("/dev/pts/")
True
>>> dev._thread.is_alive(), dev._master
(False, -1)
"""

from __future__ import annotations

import os
import threading
import tty
from typing import Self

JOIN_TIMEOUT_S = 2.0


class PtyDevice:
    """Start, stop and context management of a device thread on a pseudo-terminal."""

    THREAD_NAME = "pty-device"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self.port = ""

    def start(self) -> Self:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        self._thread = threading.Thread(target=self._run, name=self.THREAD_NAME, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=JOIN_TIMEOUT_S)
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:  # pragma: no cover - every device has its own
        raise NotImplementedError
