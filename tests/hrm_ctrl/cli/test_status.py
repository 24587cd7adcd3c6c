"""``hrm status`` waits for every drive's next heartbeat before its snapshot."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np

from hrm_ctrl.cli.status import FRESH_HEARTBEAT_PERIODS, await_fresh_heartbeats


def _session(n: int, node_heartbeat_ms: int = 20) -> SimpleNamespace:
    mon = SimpleNamespace(clock=time.monotonic, hb_time=np.full(n, time.monotonic()))
    return SimpleNamespace(
        monitor=mon, control=SimpleNamespace(node_heartbeat_ms=node_heartbeat_ms)
    )


def test_returns_once_every_drive_has_sent_a_heartbeat_since_the_call() -> None:
    s = _session(3)

    def heartbeats() -> None:
        for i in range(3):
            time.sleep(0.005)
            s.monitor.hb_time[i] = time.monotonic()

    t = threading.Thread(target=heartbeats)
    t.start()
    assert await_fresh_heartbeats(s)
    t.join()
    assert (s.monitor.hb_time > 0).all()


def test_a_silent_drive_ends_the_wait_after_its_bound() -> None:
    s = _session(2, node_heartbeat_ms=20)
    t0 = time.monotonic()
    assert not await_fresh_heartbeats(s)
    waited = time.monotonic() - t0
    assert FRESH_HEARTBEAT_PERIODS * 0.020 <= waited < 5.0
