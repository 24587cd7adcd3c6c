"""Bring-up and cyclic streaming against simulated drives, over every CAN backend."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable

import can
import numpy as np
import pytest

from drivers.bringup import sdo_read
from drivers.protocol import cia301
from drivers.protocol import cia402 as c
from drivers.safety.subset import ActuationSubset
from drivers.session import DriveSession
from drivers.sources import HoldSource, JogSource
from hrm_ctrl.errors import DriverError
from hrm_ctrl.ropes.actuation import Actuation
from sim_bus.box import SimBox
from tests.drivers.driver_rig import (
    RIG_BOOTUP_TIMEOUT_S,
    RIG_LISTEN_S,
    Rig,
    Sniffer,
    make_config,
    rpdo_targets_per_sync,
    set_sim_state,
    wait_until,
)
from tests.vcan_guest import GUEST_RATE_HZ

NODES = ([1, 2], [3])
#: over SocketCAN in the vcan guest (one CPU, system calls of 30-40 us) the per-SYNC test
#: runs at the guest's rate, as the other timing tests there: at 100 Hz it once saw 39
#: node-cycles without feedback in 33 cycles there (docs/hil.md); the rig's TPDO tolerance
#: at about the same blind time (6 cycles, 240 ms)
GUEST_CONTROL = {"rate_hz": GUEST_RATE_HZ, "missing_tpdo_cycles": 6}


def sdo_controlword_times(rig: Rig, controlword: int) -> list[dict[int, float]]:
    """Per bus: {node: wire time of its first SDO download of 0x6040 = controlword}."""
    want = bytes([0x2B, 0x40, 0x60, 0x00]) + controlword.to_bytes(2, "little")
    out = []
    for sn, nodes in zip(rig.sniffers, NODES, strict=True):
        seen: dict[int, float] = {}
        for m in sn.snapshot():
            n = m.arbitration_id - 0x600
            if n in nodes and bytes(m.data[:6]) == want:
                seen.setdefault(n, float(m.timestamp))
        out.append(seen)
    return out


def test_bring_up_configures_and_enables_every_drive(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    actual = box.bring_up()
    assert actual.tolist() == [0, 0, 0]
    states = {m: c.decode_state(sw) for m, sw in rig.sim.statuswords().items()}
    assert set(states.values()) == {c.State402.OPERATION_ENABLED}
    for k, link in enumerate(box.links):
        assert link is not None
        assert sdo_read(link, c.OD_MODES_OF_OPERATION_DISPLAY) == c.MODE_CSP
        assert sdo_read(link, c.OD_SOFTWARE_POSITION_LIMIT, 1) == int(rig.limits.counts_min[k])
        assert sdo_read(link, c.OD_SOFTWARE_POSITION_LIMIT, 2) == int(rig.limits.counts_max[k])
        assert sdo_read(link, c.OD_INTERPOLATION_TIME_PERIOD, 1) == 10
        assert sdo_read(link, c.OD_INTERPOLATION_TIME_PERIOD, 2) == -3
        assert sdo_read(link, cia301.OD_CONSUMER_HEARTBEAT_TIME, 1) == (127 << 16) | 350
        assert sdo_read(link, cia301.OD_PRODUCER_HEARTBEAT_TIME) == 100
        assert sdo_read(link, cia301.OD_RPDO1_MAPPING, 1) == c.RPDO_TARGET_MAPPING[0]
        assert sdo_read(link, cia301.OD_TPDO1_MAPPING, 2) == c.TPDO_FEEDBACK_MAPPING[1]
    kinds = [e["kind"] for e in box.events.to_list()]
    assert kinds.index("bootup") < kinds.index("configured") < kinds.index("enabled")


def test_each_node_receives_the_setpoints_in_order_one_per_sync(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory(guest_control=GUEST_CONTROL)
    box = rig.brought_up_box()
    src = JogSource(rig.limits, "j01r1", velocity_counts_per_s=50_000.0, duration_s=0.15)
    result = box.stream(src)
    assert result.completed and result.cycles == src.n_cycles
    assert result.stats["missing_feedback_node_cycles"] <= result.cycles  # tolerated, counted
    table = src.table
    for b, (sn, nodes) in enumerate(zip(rig.sniffers, [[1, 2], [3]], strict=True)):
        assert wait_until(
            lambda sn=sn: sum(m.arbitration_id == 0x80 for m in sn.snapshot()) >= result.cycles
        )
        per_sync = rpdo_targets_per_sync(sn.snapshot(), nodes)[: result.cycles]
        assert len(per_sync) == result.cycles
        for k, got in enumerate(per_sync):
            assert sorted(got) == nodes, f"bus {b} SYNC {k}: RPDOs from {sorted(got)}"
            for n, (cw, target) in got.items():
                col = {1: 0, 2: 1, 3: 2}[n]
                assert cw == c.CW_ENABLE_OPERATION
                assert target == table[k, col]
    # The jogged drive followed its setpoints; the others held.
    idx = [rig.sim.actuation.motor_ids.index(m) for m in rig.limits.motor_ids]
    assert wait_until(lambda: abs(int(rig.sim.counts()[idx[1]]) - int(table[-1, 1])) <= 2)
    assert rig.sim.counts()[idx[0]] == 0 and rig.sim.counts()[idx[2]] == 0


def test_streams_chain_and_finish_disables(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    box.stream(JogSource(rig.limits, "j07r0", -20_000.0, 0.05, hold_s=0.0))
    second = box.stream(HoldSource(n_cycles=5))
    assert second.completed
    held = second.last_targets
    assert held[2] == -1000  # the hold starts where the jog ended
    box.finish()
    # Disabled and shut down (power stage off), confirmed by SDO before finish returns
    # (and stops the host heartbeat): READY_TO_SWITCH_ON at once, and still so after the
    # drives' heartbeat timeout (no fault, no quick stop).
    ready = {c.State402.READY_TO_SWITCH_ON}
    assert {c.decode_state(sw) for sw in rig.sim.statuswords().values()} == ready
    shut = sdo_controlword_times(rig, c.CW_SHUTDOWN)
    assert [sorted(x) for x in shut] == [sorted(n) for n in NODES]
    time.sleep(0.5)  # > heartbeat_timeout_ms
    assert {c.decode_state(sw) for sw in rig.sim.statuswords().values()} == ready
    assert np.all(second.stats["cycles"] == 5)


def test_rpdos_reach_the_wire_before_their_sync_on_a_priority_arbitrated_bus(
    actuation: Actuation,
) -> None:
    """On the simulated wire (hrm_sim, 1 Mbit/s) pending frames leave in identifier
    order, so a SYNC (0x080) queued behind RPDOs (0x2xx) would overtake them; the
    supervisor sends each cycle's RPDOs a period ahead of their SYNC."""
    motors = actuation.motor_ids[:18]
    kw = [{"interface": "hrm_sim", "channel": f"prio-{uuid.uuid4().hex[:8]}"}]
    cfg = make_config(kw, ({m: k + 1 for k, m in enumerate(motors)},))
    sub = ActuationSubset(actuation, motors)
    with SimBox(cfg, actuation=actuation):
        sniffer_bus = can.Bus(**kw[0])
        sniffer = Sniffer()
        notifier = can.Notifier(sniffer_bus, [sniffer], 0.05)
        try:
            # a fresh simulator: the rig's short listen (driver_rig.RIG_LISTEN_S)
            with DriveSession(cfg, sub, allow_uncalibrated=True, listen_s=RIG_LISTEN_S) as box:
                box.bring_up()
                sniffer.clear()
                src = JogSource(sub, "j01r0", 50_000.0, 0.1, hold_s=0.0)
                result = box.stream(src)
            assert result.completed
            assert wait_until(
                lambda: sum(m.arbitration_id == 0x80 for m in sniffer.snapshot()) >= 10
            )
            per_sync = rpdo_targets_per_sync(sniffer.snapshot(), list(range(1, 19)))
            assert [len(p) for p in per_sync[:10]] == [18] * 10
            assert [p[1][1] for p in per_sync[:10]] == src.table[:10, 0].tolist()
        finally:
            notifier.stop(1.0)
            sniffer_bus.shutdown()


def test_finish_without_stream_disables_by_sdo(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.brought_up_box()
    box.finish()
    assert wait_until(
        lambda: (
            {c.decode_state(sw) for sw in rig.sim.statuswords().values()}
            == {c.State402.READY_TO_SWITCH_ON}
        )
    )
    # No target position went out: no RPDO at all.
    frames = [m for sn in rig.sniffers for m in sn.snapshot()]
    assert not any(0x200 < m.arbitration_id <= 0x27F for m in frames)


# A loaded suite run had one bus's boot-ups miss the rig's boot-up timeout here (the
# in-process box's thread or the host's receiver starved): rerun only on a machine stall
# through that window.
@pytest.mark.stall_tolerant(window_s=RIG_BOOTUP_TIMEOUT_S, watchdog="the rig's boot-up timeout")
def test_second_bring_up_is_not_a_fault(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.brought_up_box()
    box.bring_up()  # the drives are enabled: disabled (confirmed) first, then reset
    assert box.idle_causes == []
    # Every node got *disable operation* by SDO before the NMT reset of its bus, and was
    # seen SWITCHED_ON (statusword read) before it.
    disabled = sdo_controlword_times(rig, c.CW_DISABLE_OPERATION)
    for sn, nodes, dis in zip(rig.sniffers, NODES, disabled, strict=True):
        frames = sn.snapshot()
        t_reset = min(
            m.timestamp
            for m in frames
            if m.arbitration_id == 0 and bytes(m.data[:1]) == bytes([cia301.NMT_RESET_NODE])
        )
        assert sorted(dis) == nodes and max(dis.values()) < t_reset
    kinds = [e["kind"] for e in box.events.to_list()]
    assert "disable" in kinds[kinds.index("enabled") :]
    assert box.stream(HoldSource(n_cycles=5)).completed


def test_stream_refused_unless_every_drive_is_operation_enabled(
    rig_factory: Callable[..., Rig],
) -> None:
    """A drive that left OPERATION_ENABLED silently (no EMCY, no SYNC while idle so no
    TPDO) is found by the statusword check before the first RPDO: nothing is sent."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    set_sim_state(rig, "j07r0", c.State402.SWITCHED_ON)
    for sn in rig.sniffers:
        sn.clear()
    with pytest.raises(DriverError, match=r"not OPERATION_ENABLED: j07r0 .*SWITCHED_ON"):
        box.stream(HoldSource(n_cycles=20))
    time.sleep(0.05)
    frames = [m for sn in rig.sniffers for m in sn.snapshot()]
    assert not any(0x200 < m.arbitration_id <= 0x27F or m.arbitration_id == 0x80 for m in frames)
    assert c.decode_state(rig.sim.statuswords()["j07r0"]) == c.State402.SWITCHED_ON
