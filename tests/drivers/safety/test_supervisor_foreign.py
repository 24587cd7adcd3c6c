"""A controlled bus is ours: another master's frames stop every axis, a second host does
not reset drives someone else operates, CANopen is 11-bit, malformed frames of any
service are one-line stop causes, and after a safety stop the session still finishes
(NMT pre-operational, host heartbeat last).  Over every bus backend."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import can
import pytest

from drivers.protocol import cia301, cia402
from drivers.safety.causes import StopKind
from drivers.session import OtherMasterError, SafetyStopError, SessionState
from drivers.sources import HoldSource
from tests.drivers.driver_rig import Rig, send_from_outside, sending_from_outside, wait_until
from tests.vcan_guest import GUEST_RATE_HZ

T = 0.01


def frames(rig: Rig, bus: int) -> list[can.Message]:
    return rig.sniffers[bus].snapshot()


def test_a_second_master_streaming_to_our_node_stops_every_axis(
    rig_factory: Callable[..., Rig],
) -> None:
    # over SocketCAN in the vcan guest at 25 Hz, as the stop tests there (at 100 Hz the
    # quick stop took 16.2 ms on one bus there), the rig's TPDO tolerance at the same blind
    # time (6 cycles, 240 ms); the stop still within one period
    rig = rig_factory(guest_control={"rate_hz": GUEST_RATE_HZ, "missing_tpdo_cycles": 6})
    period = rig.config.control.period_s
    box = rig.open_box()
    actual = box.bring_up()
    target = int(actual[0]) + 1500
    foreign = can.Message(
        arbitration_id=0x201,
        data=cia402.RPDO_TARGET_LAYOUT.pack(cia402.CW_ENABLE_OPERATION, target),
        is_extended_id=False,
    )
    threading.Timer(0.1, send_from_outside, args=(rig, 0, foreign)).start()
    with pytest.raises(SafetyStopError, match=r"RPDO1 0x201 .*another master") as info:
        box.stream(HoldSource(n_cycles=300))
    kinds = [x.kind for x in info.value.causes]
    assert kinds[0] is StopKind.FOREIGN
    # The quick stop went out on every bus within one control period of the foreign
    # frame (wire timestamps of the sniffers).
    wire0 = frames(rig, 0)
    t_foreign = next(
        m.timestamp
        for m in wire0
        if m.arbitration_id == 0x201 and bytes(m.data[2:6]) == bytes(foreign.data[2:6])
    )
    for k in range(len(rig.sniffers)):
        t_qs = next(
            m.timestamp
            for m in frames(rig, k)
            if 0x200 < m.arbitration_id <= 0x27F
            and bytes(m.data[:2]) == b"\x02\x00"
            and m.timestamp >= t_foreign
        )
        assert t_qs - t_foreign <= period + 0.005, f"bus{k}: {1e3 * (t_qs - t_foreign):.1f} ms"
    record = box.record()
    assert any(t["foreign_frames"].get("0x201") for t in record["bus_traffic"])


def test_another_sender_of_the_host_heartbeat_stops_every_axis(
    rig_factory: Callable[..., Rig],
) -> None:
    """A heartbeat on the host's own COB-ID (0x77F) that this process did not send: the
    drives' heartbeat consumer (0x1016) would take it for this host's, so it is another
    master, a stop cause while the drives are enabled (before: counted only)."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    host_hb = cia301.make_heartbeat(box.control.host_node_id, cia301.NMT_STATE_OPERATIONAL)
    send_from_outside(rig, 1, host_hb)
    assert wait_until(lambda: box.state is SessionState.STOPPED)
    assert [x.kind for x in box.idle_causes][:1] == [StopKind.FOREIGN]
    assert "0x77F" in box.idle_causes[0].text and "host heartbeat" in box.idle_causes[0].text
    box.finish()


def test_a_second_host_does_not_reset_drives_another_master_operates(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    first = rig.open_box()
    first.bring_up()
    assert first.stream(HoldSource(n_cycles=5)).completed
    second = type(first)(rig.config, rig.limits, listen_s=0.3)
    try:
        with pytest.raises(OtherMasterError, match=r"another master is active: bus bus0: "):
            second.configure()
        assert second.state is SessionState.CONNECTED
        # Nothing was reset: one NMT reset per bus (the first host's).
        for k in range(len(rig.sniffers)):
            resets = [
                m
                for m in frames(rig, k)
                if m.arbitration_id == cia301.COB_NMT and m.data[0] == cia301.NMT_RESET_NODE
            ]
            assert len(resets) == 1
        assert all(
            cia402.decode_state(sw) is cia402.State402.OPERATION_ENABLED
            for sw in rig.sim.statuswords().values()
        )
        with pytest.raises(OtherMasterError) as again:  # still refused
            second.configure()
        assert "NMT operational" in str(again.value) and "\n" not in str(again.value)
    finally:
        second.close()
    first.finish()
    # An explicit take-over resets them.
    third = type(first)(
        rig.config, rig.limits, listen_s=0.2, take_over=True, allow_uncalibrated=True
    )
    try:
        third.bring_up()
        assert third.state is SessionState.ENABLED
    finally:
        third.__exit__(None, None, None)


def test_a_29_bit_frame_is_never_taken_for_a_tpdo(rig_factory: Callable[..., Rig]) -> None:
    """Node 1's real TPDOs are lost; 29-bit frames with identifier 0x181 keep coming:
    feedback is still missing, and the run record counts them."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    rig.sim.drop_frames(
        "bus0", lambda m: m.arbitration_id == 0x181 and not m.is_extended_id, count=None
    )
    impostor = can.Message(arbitration_id=0x181, data=b"\x37\x02\x00\x00\x00\x00",
                           is_extended_id=True)  # fmt: skip
    with sending_from_outside(rig, 0, impostor, 0.005), pytest.raises(SafetyStopError) as info:
        box.stream(HoldSource(n_cycles=300))
    missing = [x for x in info.value.causes if x.kind is StopKind.TPDO_MISSING]
    assert missing and "j01r0" in missing[0].text
    traffic = box.record()["bus_traffic"][0]
    assert traffic["extended_id_frames"].get("0x00000181", 0) > 0


def test_frames_of_an_unconfigured_node_are_recorded(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    send_from_outside(rig, 1, can.Message(arbitration_id=0x72A, data=b"\x05",
                                          is_extended_id=False))  # fmt: skip
    assert wait_until(lambda: box.record()["bus_traffic"][1]["unconfigured_node_frames"] != {})
    assert box.record()["bus_traffic"][1]["unconfigured_node_frames"] == {"0x72A": 1}
    assert box.stream(HoldSource(n_cycles=5)).completed  # a stranger's heartbeat is no stop


@pytest.mark.parametrize(
    ("cob_id", "data", "service"),
    [
        (0x081, b"\x10\x81\x11\x00\x00", "EMCY"),  # 5 bytes
        (0x701, b"\x05\x05", "heartbeat"),  # 2 bytes
        (0x181, b"\x37\x02", "TPDO"),  # short TPDO
    ],
)
def test_malformed_frames_are_a_one_line_stop_cause(
    rig_factory: Callable[..., Rig],
    capfd: pytest.CaptureFixture[str],
    cob_id: int,
    data: bytes,
    service: str,
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    bad = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
    threading.Timer(0.1, send_from_outside, args=(rig, 0, bad)).start()
    with pytest.raises(SafetyStopError) as info:
        box.stream(HoldSource(n_cycles=300))
    cause = next(x for x in info.value.causes if x.kind is StopKind.BAD_FRAME)
    assert "j01r0" in cause.text and service in cause.text and "\n" not in cause.text
    assert "Traceback" not in capfd.readouterr().err


def test_after_a_safety_stop_the_session_still_finishes(rig_factory: Callable[..., Rig]) -> None:
    """NMT pre-operational after the quick stop, and the host heartbeat is the last of
    the host's frames."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    threading.Timer(0.05, rig.sim.fault_drive, args=("j07r0",)).start()
    with pytest.raises(SafetyStopError):
        box.stream(HoldSource(n_cycles=300))
    assert box.state is SessionState.STOPPED
    box.__exit__(None, None, None)
    rig.box = None
    assert box.state is SessionState.CLOSED

    def pre_op_seen() -> bool:  # the sniffers' threads may lag behind a loaded machine
        return all(
            any(
                m.arbitration_id == cia301.COB_NMT and m.data[0] == cia301.NMT_ENTER_PRE_OPERATIONAL
                for m in frames(rig, k)
            )
            for k in range(len(rig.sniffers))
        )

    wait_until(pre_op_seen, timeout_s=3.0)
    for k in range(len(rig.sniffers)):
        host = [
            m
            for m in frames(rig, k)
            if m.arbitration_id in (cia301.COB_NMT, 0x77F) or 0x200 < m.arbitration_id < 0x280
        ]
        qs = max(
            i for i, m in enumerate(host) if 0x200 < m.arbitration_id and m.data[:2] == b"\x02\x00"
        )
        pre_op = [
            i
            for i, m in enumerate(host)
            if m.arbitration_id == cia301.COB_NMT and m.data[0] == cia301.NMT_ENTER_PRE_OPERATIONAL
        ]
        assert pre_op and pre_op[-1] > qs, f"bus{k}: no NMT pre-operational after the stop"
        after = host[pre_op[-1] + 1 :]
        assert all(m.arbitration_id == 0x77F for m in after)  # only heartbeats follow it
        t_pre = host[pre_op[-1]].timestamp
        assert all(m.timestamp - t_pre < 0.15 for m in after)  # and they stop at once
    n0 = len(frames(rig, 0))
    threading.Event().wait(0.3)
    assert not [m for m in frames(rig, 0)[n0:] if m.arbitration_id == 0x77F]  # heartbeat off


def quick_stops_after(rig: Rig, bus: int, t: float) -> list[float]:
    """Wire times of the quick-stop RPDOs on ``bus`` after ``t``."""
    return [
        m.timestamp
        for m in frames(rig, bus)
        if 0x200 < m.arbitration_id <= 0x27F
        and bytes(m.data[:2]) == b"\x02\x00"
        and m.timestamp >= t
    ]


def test_another_master_during_the_enable_stops_every_axis_once_enabled(
    rig_factory: Callable[..., Rig], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another master sends node 1 a target and SYNCs while the other drives are still
    being enabled (found by a red-team helper: only counted, the session went ENABLED
    holding where node 1 no longer was): the enable raises naming the foreign frame and
    every axis is quick-stopped."""
    import drivers.drive_group as drive_group

    rig = rig_factory()
    box = rig.open_box()
    box.configure()
    real = drive_group.enable_operation
    first = rig.limits.motor_ids[0]

    def enable_then_foreign(link: Any, *args: Any, **kw: Any) -> int:
        actual = real(link, *args, **kw)
        if link.motor == first:
            rpdo = cia402.RPDO_TARGET_LAYOUT.pack(cia402.CW_ENABLE_OPERATION, actual + 3000)
            send_from_outside(rig, 0, can.Message(arbitration_id=0x200 + link.node_id,
                                                  data=rpdo, is_extended_id=False))  # fmt: skip
            send_from_outside(rig, 0, cia301.make_sync())
            time.sleep(0.1)  # the other drives are being enabled meanwhile
        return actual

    monkeypatch.setattr(drive_group, "enable_operation", enable_then_foreign)
    with pytest.raises(SafetyStopError, match=r"0x20\d .*another master"):
        box.enable()
    assert box.state is SessionState.STOPPED
    assert wait_until(
        lambda: all(
            cia402.decode_state(sw) is not cia402.State402.OPERATION_ENABLED
            for sw in rig.sim.statuswords().values()
        )
    )
    box.finish()


def test_another_master_after_a_stop_is_quick_stopped_again_and_logged(
    rig_factory: Callable[..., Rig],
) -> None:
    """After a stop nothing is enabled by this host; another master walking a drive back
    to OPERATION_ENABLED and moving it (found by a red-team helper: nothing logged, the
    drive moved 2800 counts) gets a quick stop on every bus within a period of each of
    its frames, each logged with its cause; the drive does not move."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    box.request_stop()
    assert wait_until(lambda: box.state is SessionState.STOPPED)
    node = rig.config.buses[0].nodes[rig.limits.motor_ids[0]]
    motor = rig.limits.motor_ids[0]
    drive = rig.sim.drives[motor]
    before = drive.position_counts
    t0 = time.time()
    for k in range(5):
        cw = cia402.CW_ENABLE_OPERATION if k else cia402.CW_SWITCH_ON
        rpdo = cia402.RPDO_TARGET_LAYOUT.pack(cw, before + 100 * (k + 1))
        send_from_outside(rig, 0, can.Message(arbitration_id=0x200 + node, data=rpdo,
                                              is_extended_id=False))  # fmt: skip
        send_from_outside(rig, 0, cia301.make_sync())
        time.sleep(3 * T)
    foreign = [m.timestamp for m in frames(rig, 0)
               if m.arbitration_id == 0x200 + node and m.timestamp >= t0
               and bytes(m.data[:2]) != b"\x02\x00"]  # fmt: skip
    assert len(foreign) == 5
    for k in range(len(rig.sniffers)):  # a quick stop after the first foreign frame
        stops = quick_stops_after(rig, k, foreign[0])
        assert stops and stops[0] - foreign[0] <= T + 0.005, f"bus{k}"
    assert abs(drive.position_counts - before) <= 1
    causes = [e for e in box.record()["events"]
              if e["kind"] == "stop_cause" and e.get("cause") == "foreign"]  # fmt: skip
    assert causes and "another master" in causes[0]["text"]
    box.finish()


@pytest.mark.parametrize("during", ["disable", "reset_fault"])
def test_another_master_during_a_disable_or_fault_reset_is_not_hidden_by_ready(
    rig_factory: Callable[..., Rig], during: str
) -> None:
    """Found by a review helper: the idle guard's quick stop in the middle of a disable
    or a fault reset was overwritten by their READY (and the reset cleared its cause), so
    with take-over the next enable went ahead.  The guard waits for the SDO walk and
    stops every node right after it: STOPPED, the cause logged, the enable refused."""
    from drivers.session import SessionStateError

    rig = rig_factory()
    box = rig.open_box(take_over=True)
    box.bring_up()
    if during == "reset_fault":
        box.request_stop()
        assert wait_until(lambda: box.state is SessionState.STOPPED)
    real = box.drives.parallel

    def with_foreign(what: str, fn: Any, timeout_s: float) -> Any:
        if what in ("disable", "fault reset"):
            send_from_outside(rig, 0, cia301.make_sync())  # while our SDOs walk the drives
            time.sleep(3 * T)
        return real(what, fn, timeout_s)

    box.drives.parallel = with_foreign  # type: ignore[method-assign]
    getattr(box, during)()
    box.drives.parallel = real  # type: ignore[method-assign]
    assert wait_until(lambda: box.state is SessionState.STOPPED)
    assert any(e["kind"] == "stop_cause" and e.get("cause") == "foreign"
               for e in box.record()["events"])  # fmt: skip
    with pytest.raises(SessionStateError, match="not allowed in state STOPPED"):
        box.enable()
    box.finish()


@pytest.mark.xfail(
    strict=False,
    reason="the flood of one Python thread leaves gaps on hrm_sim's wire that the "
    "heartbeats pass through: the watchdog it tripped was the interpreter's own pauses "
    "(a GC pass, a scipy import in the box), now gone; a flood that fills the wire is to do",
)
def test_a_babbling_unconfigured_node_is_named_beside_the_watchdog_it_trips(
    rig_factory: Callable[..., Rig], request: pytest.FixtureRequest
) -> None:
    """A device not in the configuration floods bus 0 with 0x1A5: on a real wire it wins
    arbitration over the drives' heartbeats (0x701..), so a watchdog stops every axis; the
    stop names the flooding node beside it.  Only ``hrm_sim`` models arbitration and wire
    time (on python-can's virtual bus or udp_multicast nothing is starved)."""
    if request.node.callspec.params.get("bus_backend") != "hrm_sim":
        pytest.skip("arbitration and wire time are modelled only by hrm_sim")
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    stop = threading.Event()

    def babble() -> None:
        other = can.Bus(**rig.config.buses[0].bus_kwargs())
        msg = can.Message(arbitration_id=0x1A5, data=bytes(8), is_extended_id=False)
        try:
            time.sleep(0.1)
            while not stop.is_set():
                try:
                    other.send(msg)
                except can.CanOperationError:  # its transmit queue is full
                    time.sleep(0.001)
        finally:
            other.shutdown()

    flood = threading.Thread(target=babble, daemon=True)
    flood.start()
    try:
        with pytest.raises(SafetyStopError) as info:
            box.stream(HoldSource(n_cycles=500))  # 5 s
    finally:
        stop.set()
        flood.join(10.0)
    msg = str(info.value)
    assert "bus bus0 carried" in msg and "nodes not in the configuration" in msg
    assert "0x1A5 x" in msg and "\n" not in msg
    # what the flood starves first: the drives' heartbeats (0x701..), the host's own
    # (0x77F: a drive's EMCY 0x8130, seen in a loaded run) or the host's RPDOs (0x201..:
    # its transmit queue full, a send cause)
    starved = (StopKind.HEARTBEAT, StopKind.TPDO_MISSING, StopKind.EMCY, StopKind.SEND)
    assert info.value.causes[0].kind in starved, info.value.causes[0]
    events = [e for e in box.record()["events"] if e["kind"] == "traffic"]
    assert len(events) == 1 and "0x1A5" in events[0]["text"]


def test_a_few_frames_of_an_unconfigured_node_are_no_stop_and_no_note(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    msg = can.Message(arbitration_id=0x1A5, data=bytes(8), is_extended_id=False)
    threading.Timer(0.1, send_from_outside, args=(rig, 0, msg)).start()
    result = box.stream(HoldSource(n_cycles=30))
    assert result.completed
    assert not [e for e in box.record()["events"] if e["kind"] == "traffic"]
    assert any(t["unconfigured_node_frames"].get("0x1A5") for t in box.record()["bus_traffic"])
