"""drivers/other_master.py: what the session says about another master or device on its
buses (the session's refusals on them: tests/drivers/safety/test_supervisor_foreign.py)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from drivers.cycle import EventLog
from drivers.other_master import (
    OtherMasterError,
    duplicate_boot_text,
    foreign_frames,
    listen_for_other_masters,
    unconfigured_counts,
    unconfigured_traffic,
)
from drivers.receive import BusTraffic


def receiver(name: str) -> Any:
    return SimpleNamespace(port=SimpleNamespace(name=name), traffic=BusTraffic(name))


def test_foreign_frames_are_named_per_bus_by_cob_id() -> None:
    a, b = receiver("can0"), receiver("can1")
    assert foreign_frames([a, b]) is None
    b.traffic.foreign.update({0x080: 3, 0x201: 1})
    assert foreign_frames([a, b]) == "bus can1: 0x080 x3, 0x201 x1"


def test_traffic_of_unknown_nodes_is_named_only_at_a_frame_per_cycle() -> None:
    r = receiver("can0")
    r.traffic.unconfigured.update({0x1A5: 2})
    before = unconfigured_counts([r])
    r.traffic.unconfigured.update({0x1A5: 12, 0x725: 4, 0x1A6: 1, 0x1A7: 9})
    assert unconfigured_traffic([r], before, cycles=30) is None  # 23 frames in 30 cycles
    text = unconfigured_traffic([r], before, cycles=20)
    assert text == (
        "bus can0 carried 24 frame(s) of nodes not in the configuration during the stream: "
        "0x1A5 x10, 0x1A7 x9, 0x725 x4"
    )


def test_duplicate_boot_ups_name_at_most_four_nodes() -> None:
    assert duplicate_boot_text([]) is None
    text = duplicate_boot_text([f"n{k}" for k in range(6)])
    assert text is not None and "(6 node(s) booted more than once" in text
    assert text.endswith(": n0; n1; n2; n3 (+2 more)")


def test_another_master_heard_is_refused_unless_taken_over(monkeypatch: Any) -> None:
    import drivers.other_master as om

    heard = "bus can0: node 3 operational"
    monkeypatch.setattr(om, "wait_quiet_listen", lambda receivers, listen_s: heard)
    events = EventLog()
    with pytest.raises(OtherMasterError, match="another master is active") as info:
        listen_for_other_masters([], 0.0, take_over=False, events=events)
    assert info.value.heard == heard  # the error keeps what gave it away
    listen_for_other_masters([], 0.0, take_over=True, events=events)
    assert [e["kind"] for e in events.to_list()] == ["error", "take_over"]
    monkeypatch.setattr(om, "wait_quiet_listen", lambda receivers, listen_s: None)
    listen_for_other_masters([], 1.1, take_over=False, events=events)
    assert events.to_list()[-1]["text"] == "no other master heard in 1.1 s"
