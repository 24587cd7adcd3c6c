"""Bring-up faults: missing nodes, SDO aborts, a drive stuck in a state, bus-load refusal."""

from __future__ import annotations

import copy
import dataclasses
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from drivers.bringup import BootupError, SdoError, StateTimeoutError
from drivers.busload import BusLoadError, highest_usable_rate
from drivers.protocol import cia402 as c
from drivers.safety.subset import ActuationSubset
from drivers.session import DriveSession, SessionState
from hrm_ctrl.errors import DriverError
from hrm_ctrl.ropes.actuation import Actuation
from sim_bus.box import SimBox
from tests.drivers.driver_rig import Rig, make_config, wait_until


def test_missing_nodes_are_listed(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory(
        buses=({"j01r0": 1, "j01r1": 2}, {"j07r0": 3, "j07r1": 4}),
        sim_buses=({"j01r0": 1, "j01r1": 2}, {"j07r0": 3}),
        bootup_timeout_s=0.3,
    )
    box = rig.open_box()
    t = time.monotonic()
    with pytest.raises(BootupError) as info:
        box.bring_up()
    assert time.monotonic() - t < 1.5
    msg = str(info.value)
    assert msg.endswith("1 node(s): j07r1 (bus bus1 node 4): never heard")
    # Nothing but NMT and heartbeats went out: no SDO, no PDO.
    sent = {m.arbitration_id for sn in rig.sniffers for m in sn.snapshot()}
    assert not any(0x600 < cid <= 0x67F or 0x200 < cid <= 0x27F for cid in sent)


def test_sdo_abort_names_node_object_and_code(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    # The configuration refuses 9 when it loads; set past that check, the drive's own
    # abort (it accepts 0..8 only) is what this test sees.
    control = dataclasses.replace(rig.config.control, quick_stop_option_code=9)
    rig.config = dataclasses.replace(rig.config, control=control)
    box = rig.open_box()
    with pytest.raises(SdoError) as info:
        box.bring_up()
    msg = str(info.value)
    assert "0x605A:00" in msg and "0x06090030" in msg and "node" in msg
    assert "\n" not in msg
    # No drive was enabled.
    assert c.State402.OPERATION_ENABLED not in {
        c.decode_state(sw) for sw in rig.sim.statuswords().values()
    }


def test_a_refused_mapping_entry_names_node_object_and_code(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    # a drive whose 0x607A cannot be mapped: it refuses the RPDO entry itself (CiA 301)
    drive = rig.sim.drives["j07r0"]
    drive.od.objects = dict(drive.od.objects)
    target = copy.copy(drive.od.objects[(c.OD_TARGET_POSITION, 0)])
    target.pdo_mappable = False
    drive.od.objects[(c.OD_TARGET_POSITION, 0)] = target
    box = rig.open_box()
    with pytest.raises(SdoError) as info:
        box.bring_up()
    msg = str(info.value)
    assert "\n" not in msg
    assert "j07r0" in msg and "node" in msg
    assert "RPDO1" in msg and "object 0x607A:00" in msg and "0x06040041" in msg
    assert c.State402.OPERATION_ENABLED not in {
        c.decode_state(sw) for sw in rig.sim.statuswords().values()
    }


def test_statusword_that_never_reaches_the_state_times_out(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory(state_timeout_s=0.1)
    stuck = rig.sim.drives["j07r0"]
    stuck._on_controlword = lambda cw, now: None  # type: ignore[method-assign]
    box = rig.open_box()
    t = time.monotonic()
    with pytest.raises(StateTimeoutError) as info:
        box.bring_up()
    assert time.monotonic() - t < 2.0
    msg = str(info.value)
    assert "j07r0" in msg and "SWITCH_ON_DISABLED" in msg and "expected READY_TO_SWITCH_ON" in msg
    # The drives that were enabled got a quick stop: none stays enabled.
    time.sleep(0.05)
    assert c.State402.OPERATION_ENABLED not in {
        c.decode_state(sw) for sw in rig.sim.statuswords().values()
    }


def test_bus_load_refusal_before_anything_is_opened(actuation: Actuation) -> None:
    nodes = {m: k + 1 for k, m in enumerate(actuation.motor_ids)}
    cfg = make_config([{"interface": "virtual", "channel": "never-opened"}], buses=(nodes,))
    with pytest.raises(BusLoadError) as info:
        DriveSession(cfg, actuation)
    msg = str(info.value)
    # 36 nodes: 36 * (115 + 115) + 55 bits per cycle, heartbeats 37 * 65 * 10 bit/s.
    per_cycle = 36 * 230 + 55
    expected = highest_usable_rate((0.7 * 1_000_000 - 37 * 65 * 10) / per_cycle)
    assert expected == 80  # 81 Hz fits the budget, but 0x60C2 cannot encode 1/81 s
    assert msg.startswith("bus bus0: worst-case load 85.8% at 100 Hz exceeds the 70% limit")
    assert msg.endswith(f"highest rate that fits: {expected:g} Hz")


def test_box_refuses_a_config_without_every_rope_motor(actuation: Actuation) -> None:
    cfg = make_config([{"interface": "virtual", "channel": "x"}], buses=({"j01r0": 1},))
    with pytest.raises(DriverError, match=r"no node id for rope motor\(s\) \['j01r1'"):
        DriveSession(cfg, actuation)
    sub = ActuationSubset(actuation, ("j01r0",))
    DriveSession(cfg, sub).close()


def test_unopenable_bus_is_a_one_line_error(actuation: Actuation) -> None:
    cfg = make_config(
        [{"interface": "socketcan", "channel": "hrm-no-such-if"}], buses=({"j01r0": 1},)
    )
    with pytest.raises(DriverError) as info:
        DriveSession(cfg, ActuationSubset(actuation, ("j01r0",)))
    assert "buses.bus0: cannot open socketcan channel 'hrm-no-such-if'" in str(info.value)


def test_unopenable_second_bus_leaves_no_file(actuation: Actuation, tmp_path: Path) -> None:
    cfg = make_config(
        [
            {"interface": "virtual", "channel": "fine"},
            {"interface": "socketcan", "channel": "hrm-no-such-if"},
        ],
        buses=({"j01r0": 1}, {"j07r0": 1}),
    )
    with pytest.raises(DriverError, match=r"buses\.bus1: cannot open"):
        DriveSession(cfg, ActuationSubset(actuation, ("j01r0", "j07r0")), log_dir=tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_a_second_box_on_the_bus_is_named_before_any_drive_moves(
    rig_factory: Callable[..., Rig], actuation: Actuation
) -> None:
    """Two boxes answer as the same nodes: every SDO request gets two answers.  The
    bring-up names the duplicate nodes instead of an SDO protocol error, and no drive is
    enabled."""
    rig = rig_factory()
    second = SimBox(rig.config, actuation=actuation)
    second.start()
    try:
        box = rig.open_box()
        with pytest.raises(BootupError) as info:
            box.bring_up()
        msg = str(info.value)
        assert msg.startswith("more than one device answers as the same node")
        assert "2 boot-ups" in msg and "\n" not in msg
        assert_no_drive_moved(rig, second)
    finally:
        second.stop()


def assert_no_drive_moved(rig: Rig, second: SimBox) -> None:
    """No drive of either box enabled, and no RPDO (setpoint) on the wire."""
    for sim in (rig.sim, second):
        assert c.State402.OPERATION_ENABLED not in {
            c.decode_state(sw) for sw in sim.statuswords().values()
        }
    sent = {m.arbitration_id for sn in rig.sniffers for m in sn.snapshot()}
    assert not any(0x200 < cid <= 0x27F for cid in sent)  # no RPDO


class _HeldBack:
    """A simulated box's frames held back (none reaches the bus) until :meth:`release`
    sends them, in order: a box whose thread ran late (the vcan guest, one CPU)."""

    def __init__(self, box: SimBox) -> None:
        self.frames: list[tuple[Callable[[can.Message], None], can.Message]] = []
        self.lock = threading.Lock()
        self.holding = True
        for drive in box.drives.values():
            send = drive._send_fn
            drive._send_fn = lambda msg, send=send: self._send(send, msg)  # type: ignore[method-assign]

    def _send(self, send: Callable[[can.Message], None], msg: can.Message) -> None:
        with self.lock:
            if self.holding:
                self.frames.append((send, msg))
                return
        send(msg)

    def release(self) -> None:
        with self.lock:
            self.holding = False
            frames, self.frames = self.frames, []
        for send, msg in frames:
            send(msg)


def test_a_second_box_heard_only_after_the_configuration_is_named_at_the_enable(
    rig_factory: Callable[..., Rig], actuation: Actuation
) -> None:
    """The second box's boot-ups (and its SDO answers) come after every node's first
    boot-up and the whole configuration (seen once in the vcan guest: the enable was then
    refused as 'rebooted since the drives were configured').  The enable names the
    duplicate nodes: each still answers one SDO request twice; no drive is enabled."""
    rig = rig_factory()
    second = SimBox(rig.config, actuation=actuation)
    second.start()
    late = _HeldBack(second)
    try:
        box = rig.open_box()
        box.configure()
        n_held = len(late.frames)
        late.release()
        assert n_held >= len(second.drives)  # at least its boot-ups after the reset
        assert wait_until(lambda: bool(box.monitor.rebooted.all()))
        with pytest.raises(BootupError) as info:
            box.enable()
        msg = str(info.value)
        assert msg.startswith("more than one device answers as the same node")
        assert "2 boot-ups" in msg and "answers to one SDO request" in msg
        assert "\n" not in msg
        assert box.state is SessionState.READY  # refused before anything but SDO reads
        assert_no_drive_moved(rig, second)
    finally:
        second.stop()
