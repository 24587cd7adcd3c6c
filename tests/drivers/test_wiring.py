"""drivers/wiring.py: the motor -> slot map, computed once per session."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from drivers.wiring import MotorSlots
from tests.drivers.driver_rig import Rig


def test_the_slots_follow_the_rope_layer_order_across_buses(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    slots = MotorSlots.of(rig.config, rig.limits.motor_ids)
    assert slots.motor_ids == tuple(rig.limits.motor_ids)
    for b in rig.config.buses:
        for motor, nid in b.nodes.items():
            i = slots.slot[motor]
            assert (slots.bus[i], slots.node_id[i]) == (b.name, nid)
            assert slots.labels[i] == f"{motor} (bus {b.name} node {nid})"
        assert [slots.motor_ids[i] for i in slots.on_bus(b)] == list(b.nodes)
    box = rig.open_box()
    assert [link.motor for link in box.links] == list(slots.motor_ids)  # slot order
    assert box.slots == slots
    idx = np.concatenate([lay.index for lay in box.wiring.layouts])
    assert sorted(idx.tolist()) == list(range(slots.n))
