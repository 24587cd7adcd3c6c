"""The batch receive path (``BusReceiver.on_batch``, ``NodeMonitor.on_tpdo_batch``,
``BusPoller`` on ``hrm_ipc``'s ``recv_batches``) against the per-frame one: the same
monitor state, the same stop causes, the same traffic counts and the same CAN log, for any
mix of our nodes' TPDOs, heartbeats, EMCYs, bad frames and other masters' frames."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from drivers.protocol import cia301, cia402
from drivers.protocol.batch import from_messages, to_messages
from drivers.receive import BusPoller, pollable
from sim_bus.ipc import open_ends
from tests.drivers.test_cycle_lean import rig

FAULT_SW = 0x0237 | cia402.SW_FAULT


def frame(kind: str, node: int, value: int) -> can.Message:
    """One frame of a kind the receive path treats in its own way."""
    if kind == "tpdo":
        return cia402.make_tpdo_feedback(node, 0x0237, value)
    if kind == "tpdo_fault":
        return cia402.make_tpdo_feedback(node, FAULT_SW, value)
    if kind == "tpdo_short":
        return can.Message(arbitration_id=0x180 + node, data=b"\x37\x02", is_extended_id=False)
    if kind == "heartbeat":
        return cia301.make_heartbeat(node, cia301.NMT_STATE_OPERATIONAL)
    if kind == "bootup":
        return cia301.make_heartbeat(node, cia301.NMT_STATE_BOOTUP)
    if kind == "emcy":
        return can.Message(arbitration_id=0x80 + node, data=bytes(8), is_extended_id=False)
    if kind == "foreign_rpdo":
        return can.Message(arbitration_id=0x200 + node, data=bytes(6), is_extended_id=False)
    if kind == "extended":
        return can.Message(arbitration_id=0x180 + node, data=bytes(6), is_extended_id=True)
    if kind == "unknown_node":
        return cia402.make_tpdo_feedback(9, 0x0237, value)
    raise ValueError(kind)


KINDS = (
    "tpdo", "tpdo_fault", "tpdo_short", "heartbeat", "bootup", "emcy", "foreign_rpdo",
    "extended", "unknown_node",
)  # fmt: skip
frames_st = st.lists(
    st.tuples(st.sampled_from(KINDS), st.sampled_from((1, 2)), st.integers(-(2**31), 2**31 - 1)),
    min_size=0,
    max_size=40,
)


def feed(msgs: list[can.Message], as_batch: bool, tmp: Path, armed: bool) -> dict[str, Any]:
    """Hand ``msgs`` to a fresh receiver frame by frame or as one batch; what it did."""
    tmp = Path(tempfile.mkdtemp(dir=tmp))
    bus, log, _port, mon, rx, net, reports = rig(tmp)
    mon.seq = 3
    mon.armed = armed
    t0 = time.time()
    stamped = [
        can.Message(
            timestamp=t0 + k * 1e-4,
            arbitration_id=m.arbitration_id,
            is_extended_id=m.is_extended_id,
            data=bytes(m.data),
        )
        for k, m in enumerate(msgs)
    ]
    if as_batch:
        rx.on_batch(from_messages(stamped))
    else:
        for m in stamped:
            rx.on_message_received(m)
    log.stop()
    bus.shutdown()
    logged = [
        (m.arbitration_id, m.is_extended_id, bytes(m.data), round(m.timestamp - t0, 5))
        for m in can.LogReader(tmp / "rx.blf")
    ]
    return {
        "statusword": mon.statusword.tolist(),
        "position": mon.position.tolist(),
        "rx_seq": mon.rx_seq.tolist(),
        "seen": (mon.n_tpdo > 0).tolist(),
        "hb_state": mon.hb_state.tolist(),
        "booted": mon.booted.tolist(),
        "causes": sorted((c.kind.value, c.text) for c in mon.drain()),
        "reports": sorted((k.value, t) for k, t in reports),
        "traffic": rx.traffic.to_dict(),
        "canopen": sorted(net.notified),
        "logged": sorted(logged, key=lambda x: x[3]),
    }


@settings(max_examples=60, deadline=None, derandomize=True)
@given(frames_st, st.booleans())
@example([("tpdo", 1, 5), ("tpdo", 2, -7)], True)  # the usual cycle: a whole batch of TPDOs
@example([("tpdo", 1, 5), ("tpdo", 1, 6), ("heartbeat", 2, 0)], True)  # a node twice
@example([("tpdo_fault", 2, 1), ("tpdo_short", 1, 0), ("extended", 1, 0)], True)
def test_a_batch_does_what_its_frames_do_one_by_one(
    spec: list[tuple[str, int, int]], armed: bool
) -> None:
    msgs = [frame(k, n, v) for k, n, v in spec]
    with tempfile.TemporaryDirectory() as d:
        one = feed(msgs, False, Path(d), armed)
        many = feed(msgs, True, Path(d), armed)
    assert many == one


def test_a_poller_reads_hrm_ipc_in_batches_into_the_monitor(tmp_path: Path, ipc_dir: Path) -> None:
    """The supervisor's poller on an ``hrm_ipc`` end: whole datagrams into the batch path,
    every frame logged once, frames of our own end (``receive_own_messages``) taken as
    echoes, a closed bus a kept exception instead of a raise."""
    box, host = open_ends("batch-poll", 2, ipc_dir)
    bus, log, port, mon, rx, _net, _reports = rig(tmp_path)
    assert pollable(host)
    poller = BusPoller(host, rx, "bus0")
    assert poller._recv_batch is not None  # hrm_ipc's recv_batches
    mon.seq = 11
    box.send_many([cia402.make_tpdo_feedback(n, 0x0237, 100 * n) for n in (1, 2)])
    box.send(cia301.make_heartbeat(2, cia301.NMT_STATE_OPERATIONAL))
    deadline = time.monotonic() + 5.0
    got = 0
    while got < 3 and time.monotonic() < deadline:
        got += poller.poll()
        time.sleep(0.001)
    assert got == 3 and poller.n_frames == 3 and poller.exception is None
    assert mon.position.tolist() == [100, 200] and mon.rx_seq.tolist() == [11, 11]
    assert mon.hb_state.tolist() == [-1, cia301.NMT_STATE_OPERATIONAL]
    host.shutdown()
    assert poller.poll() == 0 and poller.exception is not None and not poller.alive
    box.shutdown()
    bus.shutdown()
    log.stop()
    assert len(list(can.LogReader(tmp_path / "rx.blf"))) == 3
    assert port.name == "bus0"


def test_hrm_ipc_refuses_a_batch_it_cannot_carry(ipc_dir: Path) -> None:
    a, b = open_ends("batch-refuse", 2, ipc_dir)
    try:
        good = from_messages([cia301.make_sync()] * 6)
        bad = good.copy()
        bad["id"][3] = 0x800  # an 11-bit id out of range
        with pytest.raises(can.CanOperationError, match="id out of range"):
            a.send_batch(bad)
        with pytest.raises(can.CanOperationError, match="FRAME_DTYPE"):
            a.send_batch(np.zeros(3, dtype=np.int64))
        a.send_batch(good)
        got = b.recv_batches(2.0)
        assert [len(f) for f, _rx in got] == [6] and got[0][1] is True
        assert [m.arbitration_id for m in to_messages(got[0][0])] == [0x080] * 6
        assert a.stats()["frames_sent"] == 6
    finally:
        a.shutdown()
        b.shutdown()


def test_the_supervisor_reads_its_buses_and_a_dead_one_is_a_stop_cause_not_a_spin(
    tmp_path: Path, ipc_dir: Path
) -> None:
    """The supervisor's own thread waits on an hrm_ipc end (BusPoller): frames reach the
    monitor between deadlines; a bus that dies under it is reported as a receive failure
    at the next deadline, and the thread goes on waiting instead of spinning on it."""
    import os
    import threading

    from drivers.bus import BusPort
    from drivers.cycle import BusLayout, EventLog
    from drivers.safety.supervisor import Supervisor
    from tests.drivers.safety.test_supervisor import HB_PERIOD_S, HOST, Limits, T

    box, host = open_ends("sup-poll", 2, ipc_dir)
    bus, log, _port, mon, rx, _net, _reports = rig(tmp_path)
    poller = BusPoller(host, rx, "bus0")
    layout = BusLayout(BusPort("bus0", host), np.array([0, 1]), np.array([1, 2]), poller)
    sup = Supervisor([layout], mon, Limits(), T, HB_PERIOD_S, HOST, EventLog())
    sup.start()
    try:
        box.send(cia301.make_heartbeat(2, cia301.NMT_STATE_OPERATIONAL))
        deadline = time.monotonic() + 5.0
        while mon.hb_state[1] != cia301.NMT_STATE_OPERATIONAL and time.monotonic() < deadline:
            time.sleep(0.005)
        assert mon.hb_state.tolist() == [-1, cia301.NMT_STATE_OPERATIONAL]
        host.shutdown()  # the bus dies under the waiting thread
        box.send(cia301.make_heartbeat(1, cia301.NMT_STATE_OPERATIONAL))
        deadline = time.monotonic() + 5.0
        while poller.exception is None and time.monotonic() < deadline:
            time.sleep(0.005)
        assert poller.exception is not None
        causes = sup._watchdogs(time.monotonic(), -1, None)
        assert [c.kind.value for c in causes] == ["receive"], causes
        tid = next(t.native_id for t in threading.enumerate() if t.name == "hrm-supervisor")

        def cpu_s() -> float:
            with open(f"/proc/self/task/{tid}/stat", encoding="ascii") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

        c0 = cpu_s()
        time.sleep(0.5)
        assert cpu_s() - c0 < 0.05  # waiting on its deadline, not spinning on the dead bus
    finally:
        sup.close()
        box.shutdown()
        bus.shutdown()
        log.stop()


def test_a_supervisor_woken_late_reads_what_arrived_before_it_judges_the_cycle(
    tmp_path: Path, ipc_dir: Path
) -> None:
    """A supervisor held off the CPU past its deadline (here: a step that takes 3 periods)
    reads the frames that arrived meanwhile before the next step: a TPDO waiting in the
    socket is not a missing one (the watchdogs judge each cycle at its step)."""
    import threading

    from drivers.bus import BusPort
    from drivers.cycle import BusLayout, EventLog
    from drivers.safety.supervisor import Supervisor
    from tests.drivers.safety.test_supervisor import HB_PERIOD_S, HOST, Limits, T

    box, host = open_ends("sup-late", 2, ipc_dir)
    bus, log, _port, mon, rx, _net, _reports = rig(tmp_path)
    poller = BusPoller(host, rx, "bus0")
    layout = BusLayout(BusPort("bus0", host), np.array([0, 1]), np.array([1, 2]), poller)
    stall = threading.Event()
    at_steps: list[list[int]] = []  # node 1's position as each step began

    class HeldOff(Supervisor):
        def step(self, now: float, deadline: float | None = None) -> None:
            at_steps.append(mon.position.tolist())
            if stall.is_set():
                stall.clear()
                box.send(cia402.make_tpdo_feedback(1, 0x0237, 4242))  # arrives meanwhile
                time.sleep(3 * T)  # held off the CPU past the next deadline
                at_steps.append([])  # marks the stall's end
            super().step(now, deadline)

    sup = HeldOff([layout], mon, Limits(), T, HB_PERIOD_S, HOST, EventLog())
    sup.start()
    try:
        deadline = time.monotonic() + 5.0
        while len(at_steps) < 3 and time.monotonic() < deadline:
            time.sleep(0.005)
        stall.set()
        while [] not in at_steps[:-1] and time.monotonic() < deadline:
            time.sleep(0.005)
        after = at_steps[at_steps.index([]) + 1]  # the first step after the stall
        assert after[0] == 4242, at_steps[-4:]
    finally:
        sup.close()
        box.shutdown()
        bus.shutdown()
        log.stop()


def test_the_batch_paths_are_taken_by_what_the_bus_and_receiver_are(
    tmp_path: Path, ipc_dir: Path
) -> None:
    """The kinds of bus and receiver that move batches are Protocols (no probing):
    ``hrm_ipc`` sends and receives batches, python-can's virtual bus does neither; the
    port hands records to a bus that takes them unless it must tell echoes apart; the
    poller takes the batch path only with a filterless batch bus and a batch receiver."""
    from drivers.bus import BatchSendingBus, BusPort, RecordSendingBus
    from drivers.receive import BatchReceivingBus, BatchSink, FrameSink

    a, b = open_ends("batch-kinds", 2, ipc_dir)
    virtual = can.Bus(interface="virtual", channel="batch-kinds")
    try:
        assert isinstance(a, RecordSendingBus) and isinstance(a, BatchReceivingBus)
        assert not isinstance(virtual, BatchSendingBus | BatchReceivingBus)
        assert BusPort("p", a)._records is a and BusPort("p", a, echoes=True)._records is None
        assert BusPort("p", a, echoes=True)._many is a and BusPort("p", virtual)._many is None
        _bus, log, _port, _mon, rx, _net, _reports = rig(tmp_path)
        assert isinstance(rx, BatchSink)

        class Frames:
            def on_message_received(self, msg: can.Message) -> None: ...

        sink: FrameSink = Frames()
        assert BusPoller(b, rx, "b")._recv_batch is not None
        assert BusPoller(b, sink, "b")._recv_batch is None
        b.set_filters([{"can_id": 0x181, "can_mask": 0x7FF}])
        assert BusPoller(b, rx, "b")._recv_batch is None
        _bus.shutdown()
        log.stop()
    finally:
        for bus in (a, b, virtual):
            bus.shutdown()
