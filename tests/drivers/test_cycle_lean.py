"""The lean control cycle (issue 13 item 1): the short receive path, the bus reader, the
BLF log, batched sends, RPDO frames, the lean watchdog check.  Each is checked
against the slower path it replaces: same bytes, same frames, same causes."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import can
import numpy as np
import pytest

from drivers.bus import BusPort, BusSendError, TrafficLog
from drivers.cycle import BusLayout
from drivers.protocol import cia301, cia402
from drivers.receive import BusReader, BusReceiver
from drivers.safety.causes import StopKind
from drivers.safety.monitor import NodeMonitor
from drivers.safety.supervisor import Mode
from drivers.sources import HoldSource

WAIT_S = 5.0  # generous: only a bound on a wait that normally takes microseconds


def test_a_blf_log_reads_back_every_frame_with_its_direction(tmp_path: Path) -> None:
    path = tmp_path / "log.blf"
    log = TrafficLog(path)
    sent = [can.Message(arbitration_id=0x201 + k, data=bytes([k] * 6), is_extended_id=False)
            for k in range(50)]  # fmt: skip
    for m in sent:
        m.timestamp, m.is_rx = time.time(), False
        log.log_sent(m)
        log.on_message_received(
            can.Message(timestamp=time.time(), arbitration_id=0x181 + m.arbitration_id % 64,
                        data=bytes(m.data), is_extended_id=False)
        )  # fmt: skip
    log.stop()
    back = list(can.LogReader(path))
    assert len(back) == 100 and log.n_frames == 100
    assert [m.arbitration_id for m in back[::2]] == [m.arbitration_id for m in sent]
    assert [m.is_rx for m in back[:4]] == [False, True, False, True]
    assert all(m.channel == 0 for m in back)  # python-can's 0-based number again


def rig(tmp_path: Path | None = None, echoes: bool = False) -> tuple[Any, ...]:
    class Net:
        def __init__(self) -> None:
            self.notified: list[int] = []

        def notify(self, cid: int, data: Any, ts: float) -> None:
            self.notified.append(cid)

    bus = can.Bus(interface="virtual", channel=f"lean-{time.monotonic_ns()}")
    log = TrafficLog(tmp_path / "rx.blf") if tmp_path is not None else None
    port = BusPort("bus0", bus, log, echoes=echoes)
    mon = NodeMonitor(["m0 (node 1)", "m1 (node 2)"], missing_tpdo_cycles=3,
                      heartbeat_timeout_s=1.0)  # fmt: skip
    reports: list[tuple[StopKind, str]] = []
    net = Net()
    rx = BusReceiver(port, net, log, {1: "m0 (node 1)", 2: "m1 (node 2)"},  # type: ignore[arg-type]
                     lambda kind, text: reports.append((kind, text)), lambda: True)  # fmt: skip
    for i, nid in enumerate((1, 2)):
        rx.tpdo[cia301.COB_TPDO1 + nid] = (mon, i)
        rx.heartbeat[cia301.COB_NMT_ERROR_CONTROL + nid] = (mon, i)
    return bus, log, port, mon, rx, net, reports


def test_tpdos_go_straight_into_the_monitor_and_the_log(tmp_path: Path) -> None:
    bus, log, _port, mon, rx, net, _reports = rig(tmp_path)
    mon.seq = 7
    rx.on_message_received(cia402.make_tpdo_feedback(2, 0x0237, -12345))
    rx.on_message_received(cia402.make_tpdo_feedback(1, 0x0218, 99))
    assert mon.statusword.tolist() == [0x0218, 0x0237]
    assert mon.position.tolist() == [99, -12345]
    assert mon.rx_seq.tolist() == [7, 7] and mon.n_tpdo.tolist() == [1, 1]
    # a 29-bit 0x181 is not node 1's TPDO; a short TPDO is a malformed frame
    rx.on_message_received(can.Message(arbitration_id=0x181, data=b"\x00" * 6, is_extended_id=True))
    assert mon.n_tpdo.tolist() == [1, 1] and rx.traffic.extended == {0x181: 1}
    rx.on_message_received(
        can.Message(arbitration_id=0x181, data=b"\x37\x02", is_extended_id=False)
    )
    causes = mon.drain()
    assert [c.kind for c in causes] == [StopKind.BAD_FRAME] and "m0" in causes[0].text
    assert net.notified == []  # canopen was not asked about any of these
    log.stop()
    bus.shutdown()
    assert [m.arbitration_id for m in can.LogReader(tmp_path / "rx.blf")] == [
        0x182,
        0x181,
        0x181,
        0x181,
    ]


def test_while_listening_tpdos_and_heartbeats_are_evidence_of_another_master() -> None:
    bus, _log, _port, mon, rx, net, _reports = rig()
    rx.traffic.listening = True
    rx.on_message_received(cia402.make_tpdo_feedback(2, 0x0237, 1))
    rx.on_message_received(cia301.make_heartbeat(1, cia301.NMT_STATE_OPERATIONAL))
    rx.traffic.listening = False
    assert rx.traffic.pdo_nodes == {2} and rx.traffic.operational_nodes == {1}
    assert net.notified == [0x701]  # heard by canopen too, on the full path
    assert mon.n_tpdo.tolist() == [0, 1]
    bus.shutdown()


def test_heartbeats_take_the_short_path_and_a_reboot_while_armed_stops() -> None:
    bus, _log, _port, mon, rx, net, _reports = rig()
    rx.on_message_received(cia301.make_heartbeat(2, cia301.NMT_STATE_OPERATIONAL))
    assert mon.hb_state.tolist() == [-1, cia301.NMT_STATE_OPERATIONAL] and net.notified == []
    mon.armed = True
    rx.on_message_received(cia301.make_heartbeat(1, cia301.NMT_STATE_BOOTUP))
    causes = mon.drain()
    assert [c.kind for c in causes] == [StopKind.BOOTUP] and "m0" in causes[0].text
    bus.shutdown()


class FailingBus(can.BusABC):
    """Delivers ``n`` frames, then fails as a bus that went away."""

    def __init__(self, n: int) -> None:
        super().__init__(channel="failing")
        self.left = n

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("no bus")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.left <= 0:
            raise can.CanOperationError("interface gone")
        self.left -= 1
        return can.Message(arbitration_id=0x181, data=b"\x37\x02\x00\x00\x00\x00"), False


def test_a_bus_reader_keeps_the_failure_for_the_supervisor_and_ends() -> None:
    got: list[int] = []
    sink = SimpleNamespace(on_message_received=lambda m: got.append(m.arbitration_id))
    bus = FailingBus(3)
    reader = BusReader(bus, sink, name="failing")
    t_end = time.monotonic() + WAIT_S
    while reader.alive and time.monotonic() < t_end:
        time.sleep(0.005)
    assert not reader.alive
    assert isinstance(reader.exception, can.CanOperationError) and got == [0x181] * 3
    assert reader.n_frames == 3
    reader.stop(1.0)
    bus.shutdown()


def test_a_bus_with_filters_is_read_through_recv_and_its_filters_hold() -> None:
    name = f"lean-filter-{time.monotonic_ns()}"
    bus = can.Bus(interface="virtual", channel=name,
                  can_filters=[{"can_id": 0x181, "can_mask": 0x7FF}])  # fmt: skip
    other = can.Bus(interface="virtual", channel=name)
    got: list[int] = []
    done = threading.Event()

    def take(m: can.Message) -> None:
        got.append(m.arbitration_id)
        if m.arbitration_id == 0x181:
            done.set()

    reader = BusReader(bus, SimpleNamespace(on_message_received=take), name="filter")
    assert reader._recv() == bus.recv  # filters: python-can's recv, which applies them
    other.send(can.Message(arbitration_id=0x182, is_extended_id=False))
    other.send(can.Message(arbitration_id=0x181, is_extended_id=False))
    assert done.wait(WAIT_S)
    reader.stop(1.0)
    other.shutdown()
    bus.shutdown()
    assert got == [0x181]


class BatchBus(can.BusABC):
    def __init__(self, fail: bool = False) -> None:
        super().__init__(channel="batch")
        self.batches: list[list[tuple[int, bytes]]] = []
        self.single = 0
        self.fail = fail

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.single += 1

    def send_many(self, msgs: list[can.Message], timeout: float | None = None) -> None:
        if self.fail:
            raise can.CanOperationError("peer gone")
        self.batches.append([(m.arbitration_id, bytes(m.data)) for m in msgs])

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def test_send_many_goes_through_the_bus_batch_and_logs_every_frame(tmp_path: Path) -> None:
    log = TrafficLog(tmp_path / "tx.blf")
    bus = BatchBus()
    port = BusPort("bus0", bus, log, echoes=True)
    lay = BusLayout(port, np.arange(3), np.array([1, 2, 3]))
    port.send_many(lay.rpdo_frames(cia402.CW_ENABLE_OPERATION, np.array([10, -20, 30])))
    assert bus.single == 0 and len(bus.batches) == 1
    assert [cid for cid, _ in bus.batches[0]] == [0x201, 0x202, 0x203] and port.n_sent == 3
    for m in lay.rpdo_frames(cia402.CW_ENABLE_OPERATION, np.array([10, -20, 30])):
        assert port.is_own_echo(m)  # the ledger knows every frame of the batch
    failing = BusPort("bus1", BatchBus(fail=True), None, echoes=True)
    frames = lay.rpdo_frames(2, np.array([1, 2, 3]))
    with pytest.raises(BusSendError, match="bus bus1: send failed"):
        failing.send_many(frames)
    assert failing.n_sent == 0 and not any(failing.is_own_echo(m) for m in frames)
    log.stop()
    assert [m.arbitration_id for m in can.LogReader(tmp_path / "tx.blf")] == [0x201, 0x202, 0x203]


def test_rpdo_frames_are_the_protocol_frames() -> None:
    rng = np.random.default_rng(13)
    targets = rng.integers(cia402.INT32_MIN, cia402.INT32_MAX, size=36, endpoint=True)
    index = rng.permutation(36)[:18]
    nodes = np.arange(1, 19)
    lay = BusLayout(BusPort("b", None), index, nodes)  # type: ignore[arg-type]
    for cw in (cia402.CW_ENABLE_OPERATION, cia402.CW_QUICK_STOP):
        got = lay.rpdo_frames(cw, targets)
        want = [
            cia402.make_rpdo_target(int(n), cw, int(targets[i]))
            for n, i in zip(nodes, index, strict=True)
        ]
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [
            (m.arbitration_id, bytes(m.data)) for m in want
        ]
    too_far = targets.copy()
    too_far[index[5]] = cia402.INT32_MAX + 1
    with pytest.raises(cia402.FrameError, match="outside INTEGER32"):
        lay.rpdo_frames(cia402.CW_ENABLE_OPERATION, too_far)


def test_the_lean_check_names_exactly_the_nodes_the_full_decode_rejects() -> None:
    rng = np.random.default_rng(7)
    n = 36
    mon = NodeMonitor([f"m{i}" for i in range(n)], missing_tpdo_cycles=25, heartbeat_timeout_s=9)
    for trial in range(200):
        sw = rng.integers(0, 0x10000, size=n)
        sw[rng.random(n) < 0.8] = 0x0237  # mostly enabled, as in a stream
        for i in range(n):
            mon.on_tpdo(i, cia402.make_tpdo_feedback(i + 1, int(sw[i]), 0).data, seq=trial)
        causes = mon.check(now=1.0, last_seq=trial, heartbeats_armed_at=None)
        states = cia402.decode_states(sw)
        want = {f"m{i}" for i in np.flatnonzero(states != int(cia402.State402.OPERATION_ENABLED))}
        assert {c.motor for c in causes} == want
        assert all(
            (c.kind is StopKind.FAULT) == bool(int(sw[int(c.motor[1:])]) & cia402.SW_FAULT)
            for c in causes
        )
    assert mon.missing_total == 0


def test_missing_tpdos_are_counted_and_stop_after_the_tolerance() -> None:
    mon = NodeMonitor(["a", "b"], missing_tpdo_cycles=3, heartbeat_timeout_s=9)
    ok = cia402.make_tpdo_feedback(1, 0x0237, 0).data
    texts = []
    for seq in range(4):
        mon.on_tpdo(0, ok, seq=seq)  # node b stays silent
        texts.append([c.text for c in mon.check(now=1.0, last_seq=seq, heartbeats_armed_at=None)])
    assert texts[:2] == [[], []] and texts[2] == ["b: no TPDO for 3 cycle(s)"]
    assert mon.missing_total == 4 and mon.missing_run.tolist() == [0, 4]
    mon.on_tpdo(1, ok, seq=4)
    mon.on_tpdo(0, ok, seq=4)
    assert mon.check(now=1.0, last_seq=4, heartbeats_armed_at=None) == []
    assert mon.missing_run.tolist() == [0, 0]


def test_the_lean_check_names_exactly_the_late_heartbeats() -> None:
    rng = np.random.default_rng(3)
    mon = NodeMonitor(
        [f"m{i}" for i in range(36)], missing_tpdo_cycles=25, heartbeat_timeout_s=0.35
    )
    for _ in range(300):
        mon.hb_time[:] = rng.uniform(0.0, 1.0, size=36)
        mon.hb_time[rng.random(36) < 0.05] = -np.inf  # never heard
        armed = float(rng.uniform(0.0, 1.0))
        now = float(rng.uniform(0.5, 1.6))
        causes = mon.check(now=now, last_seq=-1, heartbeats_armed_at=armed)
        want = {f"m{i}" for i in np.flatnonzero(now - np.maximum(mon.hb_time, armed) > 0.35)}
        assert {c.motor for c in causes} == want
        assert all(c.kind is StopKind.HEARTBEAT for c in causes)


def test_each_cycle_sends_the_sync_then_the_next_rpdos_in_one_batch() -> None:
    from tests.drivers.safety import test_supervisor as ts

    clock = ts.FakeClock()
    sup, mon, port, _stops = ts.armed(clock)
    batches: list[tuple[float, list[int]]] = []

    def send_many(msgs: list[can.Message], timeout_s: float = 0.05) -> None:
        batches.append((clock.t, [m.arbitration_id for m in msgs]))
        for m in msgs:
            port.send(m, timeout_s)

    port.send_many = send_many  # type: ignore[method-assign]
    src = HoldSource(n_cycles=6, counts=np.array([10, -10]))
    src.start(np.array([0, 0]), ts.T)
    t_begin = clock.t
    stream = sup.begin(src)

    def feedback() -> None:
        ts.heartbeat(mon, 0), ts.heartbeat(mon, 1)
        ts.tpdo(mon, 0), ts.tpdo(mon, 1)
        mon.rx_seq[:] = sup.seq

    ts.run_until(sup, clock, clock.t + 0.2, each=feedback)
    assert stream.done.is_set() and stream.result is not None and stream.result.completed
    # every setpoint's RPDOs in one batch (begin: setpoint 0), each SYNC followed by the
    # RPDOs that the next SYNC applies; the last SYNC alone (no setpoint left); the SYNC
    # goes out on its own, never in the RPDOs' batch
    assert [ids for _t, ids in batches] == (
        [[0x201, 0x202]] + [[ts.SYNC], [0x201, 0x202]] * 5 + [[ts.SYNC]]
    )
    batches = [(t, ids) for t, ids in batches if ids != [ts.SYNC]]
    stream_ids = [
        m.arbitration_id for t, m in port.sent if t >= t_begin and m.arbitration_id < 0x700
    ]
    assert stream_ids == [0x201, 0x202] + [ts.SYNC, 0x201, 0x202] * 5 + [ts.SYNC]
    assert [t for t, _ids in batches[1:]] == pytest.approx(
        [batches[1][0] + k * ts.T for k in range(5)], abs=1e-9
    )  # one batch per period, on the grid


def test_a_dead_receive_thread_is_a_stop_cause_of_the_supervisor() -> None:
    from tests.drivers.safety import test_supervisor as ts

    clock = ts.FakeClock()
    sup, _mon, _port, stops = ts.armed(clock)
    bus = FailingBus(0)
    reader = BusReader(bus, SimpleNamespace(on_message_received=print), name="dead")
    t_end = time.monotonic() + WAIT_S
    while reader.alive and time.monotonic() < t_end:
        time.sleep(0.005)
    bus.shutdown()
    sup.layouts[0].notifier = reader
    ts.run_until(sup, clock, clock.t + ts.T)  # the next deadline finds it
    assert sup.mode is Mode.STOPPING
    ts.run_until(sup, clock, clock.t + 0.2)  # no feedback: unconfirmed after 10 periods
    assert stops and any(
        c.kind is StopKind.RECEIVE and "interface gone" in c.text for c in stops[0].causes
    )
