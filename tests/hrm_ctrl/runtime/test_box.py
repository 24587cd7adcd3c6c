"""``hrm_ctrl.runtime.box.open_box`` on the in-process simulated box: whatever ends the block
(its end, an exception raised in it, SIGTERM delivered in it), the box closes in order:
the watches stop, every drive is disabled, the run record is written, the simulated box
stops.  The order is observed by wrapping the session's and the box's own methods."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from drivers.config import load_box_config
from hrm_ctrl.cli._signals import signals_as_interrupts
from hrm_ctrl.errors import SignalInterrupt
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.runtime.arm import Arm
from hrm_ctrl.runtime.box import OpenBox, SessionOptions, open_box
from hrm_ctrl.runtime.process_box import BoxProcess
from hrm_ctrl.runtime.simulated import SimulatedBox, simulated_arm

CLOSING = ["watches stopped", "drives disabled", "run record written", "box stopped"]


@pytest.fixture(scope="module")
def actuation() -> Actuation:
    return load_actuation(default_robot())


def _after(events: list[str], name: str, call: Callable[..., Any], check: Callable[[], None]):
    def wrapped(*args: Any, **kw: Any) -> Any:
        try:
            return call(*args, **kw)
        finally:
            check()
            events.append(name)

    return wrapped


class Observed:
    """``open_box`` on a fresh simulated box (:meth:`__call__`; in its own process, the
    default), and the closing steps as
    they complete (:attr:`events`, filled once :meth:`observe` has wrapped the box)."""

    def __init__(self, actuation: Actuation, log_dir: Path) -> None:
        self.events: list[str] = []
        self.actuation = actuation
        self.log_dir = log_dir

    def __call__(self) -> Any:
        arm = Arm(self.actuation.robot, self.actuation.robot, None, rope_layer=self.actuation)
        options = SessionOptions(log_dir=self.log_dir, run_name="box", allow_uncalibrated=True)
        return open_box(
            load_box_config(None),
            self.actuation,
            options,
            sim=SimulatedBox(simulated_arm(arm)),
            prog="test",
        )

    def observe(self, box: OpenBox) -> None:
        session, sim, watches, events = box.session, box.sim, box.watches, self.events
        assert sim is not None and session.enabled  # brought up: the drives are enabled

        def disabled() -> None:
            assert not session.enabled

        def written() -> None:
            assert (self.log_dir / "box.json").is_file()

        watches.stop = _after(events, "watches stopped", watches.stop, lambda: None)
        session.finish = _after(events, "drives disabled", session.finish, disabled)
        session.close = _after(events, "run record written", session.close, written)
        if isinstance(sim, BoxProcess):  # a box in its own process: closed
            sim.close = _after(events, "box stopped", sim.close, lambda: None)
        else:
            sim.stop = _after(events, "box stopped", sim.stop, lambda: None)

    def record(self) -> dict[str, Any]:
        return json.loads((self.log_dir / "box.json").read_text())


@pytest.fixture
def opened(actuation: Actuation, tmp_path: Path) -> Observed:
    return Observed(actuation, tmp_path)


def test_a_normal_exit_closes_in_order(opened: Observed) -> None:
    with opened() as box:
        opened.observe(box)
        assert opened.events == []
    assert opened.events == CLOSING
    record = opened.record()
    assert set(record["watches"]) == {"tension", "rope_consistency"}  # summaries kept
    assert record["session_state"] == "closed"
    assert any(e["kind"] == "disable" for e in record["events"]), record["events"]


def test_an_exception_inside_closes_in_order_and_is_raised(opened: Observed) -> None:
    class BoomError(Exception):
        pass

    with pytest.raises(BoomError), opened() as box:
        opened.observe(box)
        raise BoomError("inside the block")
    assert opened.events == CLOSING
    assert any(e["kind"] == "disable" for e in opened.record()["events"])


def test_sigterm_inside_stops_every_axis_and_closes_in_order(opened: Observed) -> None:
    with pytest.raises(SignalInterrupt) as caught, signals_as_interrupts(), opened() as box:
        opened.observe(box)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(10.0)  # the interrupt comes in here
        pytest.fail("SIGTERM did not interrupt the block")
    assert caught.value.signal_name == "SIGTERM"
    assert opened.events == CLOSING
    record = opened.record()
    causes = [c["text"] for c in record["idle_stop_causes"]]
    assert any("SIGTERM" in c for c in causes), causes  # every axis quick-stopped first
    assert any(e["kind"] == "disable" for e in record["events"])


def test_a_box_process_started_for_the_block_closes_last(
    actuation: Actuation, tmp_path: Path
) -> None:
    """``sim=ProcessBox(...)``: ``hrm sim --control`` started for the block, the session on
    its buses (here the cross-process ``hrm_ipc``), the box process gone after the record."""
    from hrm_ctrl.hil.rig import BusKind, default_nodes, ipc_available, write_box_toml
    from hrm_ctrl.runtime.box import WatchOptions
    from hrm_ctrl.runtime.process_box import ProcessBox

    if not ipc_available():
        pytest.skip("python-can has no hrm_ipc interface here")
    # watchdogs relaxed: this is about the closing order, not about a loaded machine
    relaxed = {"missing_tpdo_cycles": 25, "heartbeat_timeout_ms": 1000}
    path = write_box_toml(tmp_path / "box.toml", BusKind.IPC, default_nodes(), relaxed)
    observed = Observed(actuation, tmp_path)
    options = SessionOptions(log_dir=tmp_path, run_name="box", allow_uncalibrated=True)
    watches = WatchOptions(ropes=False, grace_s=0.5)
    box_config = load_box_config(path)
    with open_box(
        box_config, actuation, options, sim=ProcessBox(path, cpus=False), watches=watches
    ) as box:
        process = box.sim
        assert process is not None and process.proc.poll() is None  # running
        assert box.config.tension is not None  # the box's board
        observed.observe(box)
    assert observed.events == CLOSING
    assert process.proc.poll() is not None  # the box process has exited
    assert set(observed.record()["watches"]) == {"tension"}
