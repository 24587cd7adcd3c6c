"""Red-team review of the lean receive path (issue 13, H9): each test pins one safety
property of the new path (the reader thread, the short TPDO/heartbeat path, the lean
heartbeat check) that a finding of the review showed broken or at risk."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace
from typing import Any

import can
import numpy as np

from drivers.protocol import cia301, cia402
from drivers.receive import BusReader
from drivers.safety.causes import StopKind
from drivers.safety.monitor import NodeMonitor
from tests.drivers.test_cycle_lean import rig

WAIT_S = 5.0  # generous bound on waits that normally take milliseconds
HB_TIMEOUT_S = 0.35


class Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class RacingStamps(np.ndarray):
    """``hb_time`` whose first element read lets the receive thread in: ``deliver`` runs
    (heartbeats processed, stamped after the check's ``now``) before the value is read,
    as when the reader thread takes the GIL in the middle of :meth:`NodeMonitor.check`."""

    deliver: Any = None

    def __getitem__(self, key: Any) -> Any:
        fn, type(self).deliver = type(self).deliver, None
        if fn is not None:
            fn()
        return super().__getitem__(key)


def racing_monitor(n: int) -> tuple[NodeMonitor, Clock]:
    clock = Clock(100.0)
    mon = NodeMonitor([f"m{i}" for i in range(n)], 3, HB_TIMEOUT_S, clock=clock)
    mon.hb_time = np.full(n, 100.0 - 0.4).view(RacingStamps)  # every one 400 ms old
    return mon, clock


def hb_causes(causes: list[Any]) -> list[str]:
    return [c.text for c in causes if c.kind is StopKind.HEARTBEAT]


def test_a_heartbeat_processed_during_the_check_is_not_reported_lost() -> None:
    # The reported symptom: "m7..m18: heartbeat lost (last -3 ms ago, timeout 350 ms)".
    # The check decided from one read of hb_time and named the age from another: the
    # heartbeats the reader stamped in between (3 ms after the check's now) were lost.
    mon, clock = racing_monitor(4)
    now = 100.0

    def reader_catches_up() -> None:
        clock.t = now + 0.003
        for i in (1, 2, 3):
            mon.on_heartbeat(i, b"\x05")

    RacingStamps.deliver = reader_catches_up
    texts = hb_causes(mon.check(now, -1, heartbeats_armed_at=0.0))
    assert not any("-" in t.split("last ")[-1].split(" ms")[0] for t in texts), texts
    # node 0 is really lost (nothing since 400 ms); 1-3 answered: stamped after now
    assert len(texts) == 1 and texts[0].startswith("m0: heartbeat lost (last 400 ms ago")


def test_every_reported_heartbeat_age_is_at_least_the_timeout() -> None:
    mon, clock = racing_monitor(3)
    mon.hb_time[:] = [99.5, 99.64, 99.70]  # 500, 360, 300 ms before now

    def late_arrival() -> None:
        clock.t = 100.002
        mon.on_heartbeat(0, b"\x05")  # node 0's heartbeat lands during the check

    RacingStamps.deliver = late_arrival
    texts = hb_causes(mon.check(100.0, -1, heartbeats_armed_at=0.0))
    assert texts == ["m1: heartbeat lost (last 360 ms ago, timeout 350 ms)"]
    RacingStamps.deliver = None
    clock.t = 100.3
    # at 100.3 node 0 (stamped 100.002) is in time, node 2 (99.70) is 600 ms late
    texts = hb_causes(mon.check(100.3, -1, heartbeats_armed_at=0.0))
    assert texts == [
        "m1: heartbeat lost (last 660 ms ago, timeout 350 ms)",
        "m2: heartbeat lost (last 600 ms ago, timeout 350 ms)",
    ]


def test_a_stamp_newer_than_the_checks_now_is_in_time() -> None:
    mon = NodeMonitor(["a", "b"], 3, HB_TIMEOUT_S, clock=Clock(0.0))
    mon.hb_time[:] = [10.004, 9.0]  # a: stamped after the check's now (10.0)
    assert hb_causes(mon.check(10.0, -1, heartbeats_armed_at=0.0)) == [
        "b: heartbeat lost (last 1000 ms ago, timeout 350 ms)"
    ]


class ScriptedBus(can.BusABC):
    """recv blocks until ``release`` is set, then delivers ``frames`` one per call."""

    def __init__(self, frames: list[can.Message]) -> None:
        super().__init__(channel="scripted")
        self.frames = list(frames)
        self.release = threading.Event()
        self.in_recv = threading.Event()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("scripted bus: no send")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self.in_recv.set()
        if not self.release.wait(WAIT_S):
            return None, False
        if self.frames:
            return self.frames.pop(0), False
        time.sleep(min(timeout or 0.0, 0.01))
        return None, False


def wait_dead(reader: BusReader) -> None:
    t_end = time.monotonic() + WAIT_S
    while reader.alive and time.monotonic() < t_end:
        time.sleep(0.005)
    assert not reader.alive


def test_a_frame_that_arrives_after_stop_is_not_handled() -> None:
    got: list[int] = []
    bus = ScriptedBus([cia402.make_tpdo_feedback(1, 0x0237, 5)])
    reader = BusReader(bus, SimpleNamespace(on_message_received=lambda m: got.append(1)), "late")
    assert bus.in_recv.wait(WAIT_S)
    reader.stop(0.01)  # the join times out: recv is still blocked
    bus.release.set()  # ... then hands over a frame
    wait_dead(reader)
    assert got == [] and reader.exception is None
    bus.shutdown()


def test_a_receive_thread_ended_by_a_base_exception_is_a_failure() -> None:
    # SystemExit (or any BaseException) raised in a handler ended the thread silently:
    # .exception stayed None, so the supervisor saw a live receive path.
    def boom(_msg: can.Message) -> None:
        raise SystemExit("handler called sys.exit")

    bus = ScriptedBus([cia402.make_tpdo_feedback(1, 0x0237, 5)])
    bus.release.set()
    reader = BusReader(bus, SimpleNamespace(on_message_received=boom), "exit")
    wait_dead(reader)
    assert reader.exception is not None and "sys.exit" in str(reader.exception)
    reader.stop(1.0)
    bus.shutdown()


def test_a_receive_thread_that_ended_unasked_is_a_failure() -> None:
    bus = ScriptedBus([])
    bus.release.set()
    reader = BusReader(bus, SimpleNamespace(on_message_received=print), "gone")
    assert bus.in_recv.wait(WAIT_S)
    reader._stopped = True  # the loop ends without stop(): as if it had returned
    wait_dead(reader)
    reader._stopped = False
    assert reader.exception is not None and "ended" in str(reader.exception)
    reader.stop(1.0)
    assert reader.exception is None  # asked to stop: not a failure
    bus.shutdown()


def bad_frames() -> list[can.Message]:
    std = {"is_extended_id": False}
    return [
        can.Message(arbitration_id=0x181, data=b"", **std),  # TPDO, empty
        can.Message(arbitration_id=0x181, data=b"\x37\x02\x00\x00\x00", **std),  # 5 bytes
        can.Message(arbitration_id=0x182, data=bytes(8), **std),  # 8 bytes
        can.Message(arbitration_id=0x181, data=bytes(64), is_fd=True, **std),  # FD
        can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=6, **std),
        can.Message(arbitration_id=0x181, data=bytes(6), is_extended_id=True),
        can.Message(arbitration_id=0x701, data=b"", **std),  # heartbeat, empty
        can.Message(arbitration_id=0x702, data=b"\x05\x00", **std),  # 2 bytes
        can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1, **std),  # guarding
        can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=True),
        can.Message(is_error_frame=True, arbitration_id=0x20000004, data=bytes(8)),
        can.Message(arbitration_id=0x000, data=b"", **std),  # NMT, short
        can.Message(arbitration_id=0x000, data=b"\x01", **std),
        can.Message(arbitration_id=0x7FF + 0x182, data=b"\x01", check=False, **std),  # >11 bit
        can.Message(arbitration_id=0x1FFFFFFF, data=bytes(8), is_extended_id=True),
    ]


def test_bad_frames_through_a_reader_leave_it_alive_and_stop_where_they_must() -> None:
    bus, _log, _port, mon, rx, _net, reports = rig()
    frames = bad_frames()
    src = ScriptedBus([*frames, cia301.make_heartbeat(1, cia301.NMT_STATE_OPERATIONAL)])
    src.release.set()
    reader = BusReader(src, rx, "bad")
    t_end = time.monotonic() + WAIT_S
    while mon.hb_state[0] != cia301.NMT_STATE_OPERATIONAL and time.monotonic() < t_end:
        time.sleep(0.005)
    assert reader.alive and reader.exception is None  # the last, good frame was handled
    kinds = [c.kind for c in mon.drain()]
    # 4 malformed TPDOs (empty, 5 bytes, 8 bytes, FD) and 2 malformed heartbeats
    assert kinds == [StopKind.BAD_FRAME] * 6, kinds
    assert [k for k, _t in reports] == [StopKind.FOREIGN, StopKind.FOREIGN]  # both NMTs
    assert mon.n_tpdo.tolist() == [0, 0]  # no bad frame counted as feedback
    t = rx.traffic
    assert (t.remote_frames, t.error_frames, len(t.extended)) == (2, 1, 3)
    reader.stop(1.0)
    src.shutdown()
    bus.shutdown()


def test_own_echoes_are_dropped_and_another_masters_frames_stop_as_before() -> None:
    bus, _log, port, mon, rx, net, reports = rig(echoes=True)
    ours = [
        can.Message(arbitration_id=0x201, data=b"\x0f\x00\x01\x00\x00\x00", is_extended_id=False),
        can.Message(arbitration_id=cia301.COB_SYNC, data=b"", is_extended_id=False),
    ]
    port.send_many(ours)
    for m in ours:  # udp_multicast hands our own frames back
        rx.on_message_received(can.Message(arbitration_id=m.arbitration_id, data=bytes(m.data),
                                           is_extended_id=False))  # fmt: skip
    assert rx.traffic.echoes_dropped == 2 and reports == []
    foreign = [
        can.Message(arbitration_id=0x201, data=b"\x0f\x00\x09\x00\x00\x00", is_extended_id=False),
        can.Message(arbitration_id=cia301.COB_SYNC, data=b"", is_extended_id=False),
        can.Message(arbitration_id=cia301.COB_NMT, data=b"\x02\x02", is_extended_id=False),
        cia301.make_heartbeat(cia301.HOST_HEARTBEAT_NODE_ID, cia301.NMT_STATE_OPERATIONAL),
    ]
    for m in foreign:
        rx.on_message_received(m)
    texts = [t for _k, t in reports]
    assert [k for k, _t in reports] == [StopKind.FOREIGN] * 4, texts
    assert "RPDO1 0x201" in texts[0] and "SYNC 0x080" in texts[1] and "m1 (node 2)" in texts[2]
    assert "0x77F" in texts[3] and "host heartbeat" in texts[3]  # the one our drives watch
    host_hb = cia301.COB_NMT_ERROR_CONTROL + cia301.HOST_HEARTBEAT_NODE_ID
    assert rx.traffic.foreign == {0x201: 1, 0x080: 1, 0x000: 1, host_hb: 1}
    assert rx.traffic.other_master() is not None and mon.n_tpdo.tolist() == [0, 0]
    assert net.notified == []
    bus.shutdown()


def test_a_receive_thread_killed_by_a_base_exception_stops_the_supervisor() -> None:
    from drivers.safety.supervisor import Mode
    from tests.drivers.safety import test_supervisor as ts

    def boom(_msg: can.Message) -> None:
        raise SystemExit("handler called sys.exit")

    clock = ts.FakeClock()
    sup, _mon, _port, stops = ts.armed(clock)
    bus = ScriptedBus([cia402.make_tpdo_feedback(1, 0x0237, 5)])
    bus.release.set()
    reader = BusReader(bus, SimpleNamespace(on_message_received=boom), "exit2")
    wait_dead(reader)
    sup.layouts[0].notifier = reader
    ts.run_until(sup, clock, clock.t + ts.T)  # the next deadline finds it
    assert sup.mode is Mode.STOPPING
    ts.run_until(sup, clock, clock.t + 0.2)
    assert stops and any(
        c.kind is StopKind.RECEIVE and "sys.exit" in c.text for c in stops[0].causes
    )
    bus.shutdown()


def test_a_statusword_from_before_the_due_sync_is_not_judged() -> None:
    # The reported symptom: after reset-fault and enable, a jog's first cycle stopped on
    # "j01r2 ...: statusword 0x0250 (SWITCH_ON_DISABLED), expected OPERATION_ENABLED
    # (+15 more)": words of the TPDOs from before the enable, the nodes' first TPDO of the
    # stream late.  A node is judged by its TPDO of the due SYNC; a late one is the
    # missing-TPDO watch's.
    mon = NodeMonitor(["a", "b"], 3, HB_TIMEOUT_S, clock=Clock(0.0))
    enabled, disabled = bytes.fromhex("370200000000"), bytes.fromhex("500200000000")
    mon.on_tpdo(0, disabled, seq=3)
    mon.on_tpdo(1, disabled, seq=3)
    mon.on_tpdo(0, enabled, seq=4)  # b's TPDO of SYNC 4 is late
    causes = mon.check(0.0, 4, None)
    assert causes == [] and mon.missing_run.tolist() == [0, 1]
    mon.on_tpdo(1, disabled, seq=5)  # b's TPDO of SYNC 5 says SWITCH_ON_DISABLED: a stop
    mon.on_tpdo(0, enabled, seq=5)
    causes = mon.check(0.0, 5, None)
    assert [(c.kind, c.text) for c in causes] == [
        (
            StopKind.STATE,
            "b: statusword 0x0250 (SWITCH_ON_DISABLED), expected OPERATION_ENABLED",
        )
    ]
