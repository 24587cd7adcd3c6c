"""What a node flooding the bus can make the host keep is bounded: EMCYs, queued stop
causes, run events."""

from __future__ import annotations

from drivers.cycle import MAX_EVENTS, EventLog
from drivers.protocol import cia301
from drivers.safety.monitor import MAX_EMERGENCIES, MAX_QUEUED_CAUSES, NodeMonitor


def test_an_emcy_flood_keeps_the_first_emergencies_and_causes_and_counts_the_rest() -> None:
    mon = NodeMonitor(["m0"], missing_tpdo_cycles=3, heartbeat_timeout_s=0.35)
    n = MAX_EMERGENCIES + MAX_QUEUED_CAUSES + 5
    for k in range(n):
        mon.on_emcy(0, 1, bytes(cia301.make_emcy(1, 0x2310 + k % 7, 0x01).data))
    assert len(mon.emergencies) == MAX_EMERGENCIES
    assert mon.emergencies_dropped == n - MAX_EMERGENCIES
    assert mon.emergencies[0].error_code == 0x2310
    causes = mon.drain()
    assert len(causes) == MAX_QUEUED_CAUSES and mon.causes_dropped == n - MAX_QUEUED_CAUSES
    assert "0x2310" in causes[0].text  # the first kept: what started it


def test_a_run_keeps_its_first_events_and_says_how_many_more_came() -> None:
    log = EventLog()
    for k in range(MAX_EVENTS + 3):
        log.add("stop_cause", f"cause {k}")
    events = log.to_list()
    assert len(events) == MAX_EVENTS + 1
    assert events[0]["text"] == "cause 0" and events[-2]["text"] == f"cause {MAX_EVENTS - 1}"
    assert events[-1]["kind"] == "events_dropped" and events[-1]["text"].startswith("3 more")
