"""Every safety trigger stops every node of every bus within one control cycle."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import numpy as np
import pytest

from drivers.protocol import cia402 as c
from drivers.session import DriveSession, SafetyStopError
from drivers.sources import HoldSource, TableSource
from hrm_ctrl.errors import DriverError, SignalInterrupt
from tests.drivers.driver_rig import RIG_LISTEN_S, Rig, first_time, wait_until
from tests.vcan_guest import GUEST_RATE_HZ, in_vcan_guest

PERIOD_S = 0.01
# Wire-level timing (frame on the bus -> quick-stop SYNC on the bus) includes the receive
# thread's scheduling; on the shared 2-core development machine, with the simulated drives
# in the same interpreter, that alone can take several ms.  The host's own reaction (from
# detection to the quick-stop SYNC) is asserted strictly against one period.
RECEIVE_SLACK_S = 0.010
NODES = ([1, 2], [3])
#: over SocketCAN in the vcan guest (one CPU, system calls of 33-41 us) the timing tests run
#: at 25 Hz: at 100 Hz the host's reaction there took up to 23 ms beside other work
#: (tools/vcan-guest/README.md); the stop is still asserted within one period
GUEST_CONTROL: dict[str, Any] = {"rate_hz": 25, "missing_tpdo_cycles": 6}


def quick_stop_sync_time(rig: Rig) -> float:
    """Wall time of the first SYNC after every node of a bus got a quick-stop RPDO,
    the latest over all buses (NaN if some node never got one)."""
    latest = 0.0
    for sn, nodes in zip(rig.sniffers, NODES, strict=True):
        stopped: set[int] = set()
        t_sync = float("nan")
        for m in sn.snapshot():
            cid = m.arbitration_id
            if 0x200 < cid <= 0x27F and bytes(m.data[:2]) == c.CW_QUICK_STOP.to_bytes(2, "little"):
                stopped.add(cid - 0x200)
            elif cid == 0x80 and stopped >= set(nodes):
                t_sync = float(m.timestamp)
                break
        latest = max(latest, t_sync) if t_sync == t_sync else float("nan")
        if latest != latest:
            return latest
    return latest


def stream_with(rig: Rig, action: Callable[[], Any], after_s: float = 0.1) -> SafetyStopError:
    box = rig.open_box()
    box.bring_up()
    timer = threading.Timer(after_s, action)
    timer.start()
    try:
        with pytest.raises(SafetyStopError) as info:
            box.stream(HoldSource(n_cycles=300))
    finally:
        timer.cancel()
    return info.value


def assert_only_quick_stops_sent(rig: Rig) -> None:
    """Since the sniffers were cleared: no setpoint went out, only quick-stop RPDOs and
    their SYNC, and every drive left operation enabled."""
    frames = [m for sn in rig.sniffers for m in sn.snapshot()]
    rpdo_cws = {bytes(m.data[:2]) for m in frames if 0x200 < m.arbitration_id <= 0x27F}
    assert rpdo_cws == {c.CW_QUICK_STOP.to_bytes(2, "little")}
    assert not np.isnan(quick_stop_sync_time(rig))
    assert wait_until(lambda: all_left_operation_enabled(rig))


def all_left_operation_enabled(rig: Rig) -> bool:
    states = {c.decode_state(sw) for sw in rig.sim.statuswords().values()}
    return c.State402.OPERATION_ENABLED not in states


def test_emcy_and_fault_stop_every_node_within_one_cycle(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory(guest_control=GUEST_CONTROL)
    period_s = 1.0 / rig.config.control.rate_hz
    err = stream_with(rig, lambda: rig.sim.fault_drive("j07r0"))
    kinds = {x.kind for x in err.causes}
    assert "emcy" in kinds, err.causes
    assert "j07r0" in str(err)
    frames = rig.sniffers[1].snapshot()
    t_emcy = first_time(frames, lambda m: m.arbitration_id == 0x83 and any(m.data[:2]))
    t_stop = quick_stop_sync_time(rig)
    # Host side (EMCY callback -> quick-stop SYNC sent) strictly within one period; on the
    # wire (EMCY frame -> quick-stop SYNC frame) also the receive thread's latency counts.
    assert err.result.stop_latency_s is not None and err.result.stop_latency_s <= period_s
    assert err.result.stop_syncs_after_detection in (0, 1)
    assert 0.0 < t_stop - t_emcy <= period_s + 2 * RECEIVE_SLACK_S, t_stop - t_emcy
    assert wait_until(lambda: all_left_operation_enabled(rig))
    assert any(e["kind"] == "quick_stop" for e in rig.box.events.to_list())


def test_lost_heartbeat_stops_every_node(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory(guest_control=GUEST_CONTROL)
    period_s = 1.0 / rig.config.control.rate_hz
    err = stream_with(rig, lambda: rig.sim.stop_heartbeat("j01r1"))
    assert [x.kind for x in err.causes] == ["heartbeat"], err.causes
    assert "j01r1" in err.causes[0].text
    # Host side: detected at the first deadline after the timeout expired (+ wake-up
    # latency), and the quick stop was on its way within one period of detection.
    last_hb = float(rig.box.monitor.hb_time[1])
    detected = err.causes[0].time_s
    assert 0.350 <= detected - last_hb <= 0.350 + period_s + RECEIVE_SLACK_S
    assert err.result.stop_latency_s is not None and err.result.stop_latency_s <= period_s
    assert err.result.stop_syncs_after_detection in (0, 1)
    # On the wire: the quick-stop SYNC follows the last heartbeat frame by about the timeout.
    frames = rig.sniffers[0].snapshot()
    hb = [m.timestamp for m in frames if m.arbitration_id == 0x702]
    t_stop = quick_stop_sync_time(rig)
    assert 0.350 <= t_stop - hb[-1] <= 0.350 + 2 * period_s + 3 * RECEIVE_SLACK_S
    assert wait_until(lambda: all_left_operation_enabled(rig))


# At 2 missing cycles a stall of the machine can make another node miss its TPDOs first
# (a true missing-feedback stop): such a run is rerun only when the stall probe saw it;
# in the vcan guest, at 25 Hz, 2 cycles are 80 ms.
@pytest.mark.stall_tolerant(
    window_s=2 / GUEST_RATE_HZ if in_vcan_guest() else 2 * PERIOD_S,
    watchdog="2 cycles without a TPDO",
)
def test_missing_tpdo_stops_every_node(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory(missing_tpdo_cycles=2, guest_control={"rate_hz": GUEST_RATE_HZ})
    sim = rig.sim
    err = stream_with(
        rig,
        lambda s=sim: s.drop_frames("bus0", lambda m: m.arbitration_id == 0x181, count=None),
    )
    assert {x.kind for x in err.causes} == {"tpdo_missing"}, err.causes
    assert "j01r0" in err.causes[0].text and "2 cycle" in err.causes[0].text, err.causes
    assert not np.isnan(quick_stop_sync_time(rig))
    assert wait_until(lambda: all_left_operation_enabled(rig))


class RefusingSource(TableSource):
    """Holds, then asks for a setpoint beyond the software limit at slot 5."""

    name = "refusing"

    def __init__(self, bad: int) -> None:
        super().__init__()
        self.bad = bad

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.table = np.repeat(actual_counts[None, :], 20, axis=0)
        self.table[5:, 0] = self.bad


def test_setpoint_outside_limits_is_never_sent(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    bad = int(rig.limits.counts_max[0]) + 1
    with pytest.raises(SafetyStopError) as info:
        box.stream(RefusingSource(bad))
    assert info.value.causes[0].kind == "limit"
    assert "j01r0" in str(info.value) and str(bad) in str(info.value)
    targets = [
        int.from_bytes(bytes(m.data[2:6]), "little", signed=True)
        for m in rig.sniffers[0].snapshot()
        if m.arbitration_id == 0x201
    ]
    assert targets and bad not in targets
    assert not np.isnan(quick_stop_sync_time(rig))


def test_operator_stop(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    threading.Timer(0.05, box.request_stop).start()
    with pytest.raises(SafetyStopError, match="stop requested"):
        box.stream(HoldSource(n_cycles=300))
    assert wait_until(lambda: all_left_operation_enabled(rig))


class FlakyBus(can.BusABC):
    """Delegates to a real bus; ``fail`` makes every send raise like a bus-off."""

    def __init__(self, inner: can.BusABC) -> None:
        self.inner = inner
        self.fail = False
        self.fail_if: Callable[[can.Message], bool] | None = None  # fail only these frames
        super().__init__(channel="flaky")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail or (self.fail_if is not None and self.fail_if(msg)):
            raise can.CanOperationError("bus off")
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


@contextlib.contextmanager
def flaky_box(rig: Rig) -> Iterator[tuple[DriveSession, list[FlakyBus]]]:
    """A DriveSession on :class:`FlakyBus` wrappers of the rig's buses; on leaving, the
    failures are cleared, the box closed and the buses shut down."""
    buses = [FlakyBus(can.Bus(**b.bus_kwargs())) for b in rig.config.buses]
    box = DriveSession(  # fresh simulators: the rig's short listen (driver_rig.RIG_LISTEN_S)
        rig.config, rig.limits, buses=buses, allow_uncalibrated=True, listen_s=RIG_LISTEN_S
    )
    rig.box = box
    try:
        yield box, buses
    finally:
        for b in buses:
            b.fail, b.fail_if = False, None
        box.__exit__(None, None, None)
        rig.box = None
        for b in buses:
            b.shutdown()


def test_bus_failing_on_send_stops_the_other_buses(
    rig_factory: Callable[..., Rig], can_backend: Callable[[], dict[str, Any]]
) -> None:
    rig = rig_factory()
    with flaky_box(rig) as (box, buses):
        box.bring_up()

        def fail() -> None:
            buses[1].fail = True

        threading.Timer(0.05, fail).start()
        with pytest.raises(SafetyStopError, match="bus bus1") as info:
            box.stream(HoldSource(n_cycles=300))
        assert {x.kind for x in info.value.causes} <= {"send", "tpdo_missing", "heartbeat"}
        # bus0 still got its quick stop.
        frames = rig.sniffers[0].snapshot()
        assert any(m.arbitration_id == 0x201 and bytes(m.data[:2]) == b"\x02\x00" for m in frames)
        assert wait_until(
            lambda: c.decode_state(rig.sim.statuswords()["j01r0"]) != c.State402.OPERATION_ENABLED
        )
    time.sleep(0.01)


class CrashingSource(TableSource):
    """Holds, then fails like a bug (or Ctrl-C) in the middle of the stream."""

    name = "crashing"

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.table = np.repeat(actual_counts[None, :], 20, axis=0)

    def setpoint(self, k: int) -> np.ndarray | None:
        if k == 5:
            raise RuntimeError("boom")
        return super().setpoint(k)


def test_control_loop_crash_still_stops_every_node(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    with pytest.raises(RuntimeError, match="boom"):
        box.stream(CrashingSource())
    assert not np.isnan(quick_stop_sync_time(rig))
    assert wait_until(lambda: all_left_operation_enabled(rig))
    assert any("control loop interrupted" in e["text"] for e in box.events.to_list())


def test_lost_heartbeat_while_idle_stops_every_node(rig_factory: Callable[..., Rig]) -> None:
    """Between bring-up and a stream the supervisor watches the drives."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    rig.sim.stop_heartbeat("j07r0")
    assert wait_until(lambda: box.idle_causes != [], timeout_s=2.0)
    assert box.idle_causes[0].kind == "heartbeat" and "j07r0" in box.idle_causes[0].text
    assert wait_until(lambda: all_left_operation_enabled(rig))
    with pytest.raises(SafetyStopError, match="stopped while idle: j07r0"):
        box.stream(HoldSource(n_cycles=10))


def test_emcy_between_streams_stops_every_node(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    assert box.stream(HoldSource(n_cycles=5)).completed
    rig.sim.fault_drive("j01r0")
    assert wait_until(lambda: box.idle_causes != [], timeout_s=2.0)
    assert {x.kind for x in box.idle_causes} >= {"emcy"}
    assert wait_until(lambda: all_left_operation_enabled(rig))


class FaultOnStart(HoldSource):
    """Holds; while being started (after the statusword check, before the first
    RPDO) a drive faults and its EMCY reaches the host."""

    def __init__(self, rig: Rig, motor: str) -> None:
        super().__init__(n_cycles=50)
        self.rig = rig
        self.motor = motor

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        super().start(actual_counts, period_s)
        box = self.rig.box
        assert box is not None
        n_emcy = len(box.monitor.emergencies)
        self.rig.sim.fault_drive(self.motor)
        assert wait_until(lambda: len(box.monitor.emergencies) > n_emcy)


def test_emcy_at_stream_start_stops_every_node_and_streams_nothing(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    box = rig.brought_up_box()
    with pytest.raises(SafetyStopError, match="j07r0") as info:
        box.stream(FaultOnStart(rig, "j07r0"))
    assert "emcy" in {x.kind for x in info.value.causes}
    assert info.value.result.cycles == 0
    assert_only_quick_stops_sent(rig)
    assert not any(e["kind"] == "before_stream" for e in box.events.to_list())


def test_heartbeat_timeout_is_not_restarted_by_a_stream(rig_factory: Callable[..., Rig]) -> None:
    """Heartbeat supervision stays armed from bring-up: a heartbeat lost while idle is
    detected one timeout after the last heartbeat, even when a stream starts meanwhile."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    rig.sim.stop_heartbeat("j01r1")
    time.sleep(0.2)
    with pytest.raises(SafetyStopError) as info:
        box.stream(HoldSource(n_cycles=300))
    hb = [x for x in info.value.causes if x.kind == "heartbeat"]
    assert hb and "j01r1" in hb[0].text
    last_hb = float(box.monitor.hb_time[1])
    # Armed at the stream's start it would be >= 0.2 + 0.35 s; allow load-induced latency.
    assert hb[0].time_s - last_hb <= 0.350 + 0.15
    assert wait_until(lambda: all_left_operation_enabled(rig))


def test_bring_up_refuses_an_actual_position_outside_the_limits(
    rig_factory: Callable[..., Rig], actuation: Any
) -> None:
    i = actuation.motor_ids.index("j07r0")
    beyond = int(actuation.counts_max[i]) + 5000
    rig = rig_factory(sim_counts={"j07r0": beyond})
    box = rig.open_box()
    with pytest.raises(DriverError, match=rf"j07r0 .*actual position {beyond} counts is outside"):
        box.bring_up()
    assert not box.enabled
    # No target position was written to it and no drive is left enabled.
    frames = rig.sniffers[1].snapshot()
    target_writes = [
        m for m in frames if m.arbitration_id == 0x603 and bytes(m.data[1:3]) == b"\x7a\x60"
    ]
    assert target_writes == []
    assert wait_until(lambda: all_left_operation_enabled(rig))


def test_idle_quick_stop_failure_is_reported(rig_factory: Callable[..., Rig]) -> None:
    """The idle quick stop fails on one bus: the failure is a stop cause, the
    run record says so, and the next stream names it."""
    rig = rig_factory()
    with flaky_box(rig) as (box, buses):
        box.bring_up()
        assert box.stream(HoldSource(n_cycles=5)).completed
        buses[1].fail_if = lambda m: 0x200 < m.arbitration_id <= 0x27F  # RPDOs lost
        rig.sim.fault_drive("j01r0")
        assert wait_until(lambda: box.idle_causes != [], timeout_s=2.0)
        assert wait_until(lambda: box.stop_error is not None)
        sent = [x for x in box.idle_causes if x.kind == "send"]
        assert sent and "bus1" in sent[0].text
        events = box.events.to_list()
        assert any(e["kind"] == "error" and "bus1" in e["text"] for e in events)
        assert not any(e["kind"] == "quick_stop" and "while idle" in e["text"] for e in events)
        with pytest.raises(SafetyStopError, match="quick stop while idle failed"):
            box.stream(HoldSource(n_cycles=5))


def test_finish_reports_drives_it_could_not_disable(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    with flaky_box(rig) as (box, buses):
        box.bring_up()
        assert box.stream(HoldSource(n_cycles=5)).completed
        buses[1].fail_if = lambda m: 0x600 < m.arbitration_id <= 0x67F  # SDO requests lost
        with pytest.raises(DriverError, match=r"finish: .*j07r0"):
            box.finish()
        assert not box.enabled
        # bus0's drives were still disabled and shut down.
        sw = rig.sim.statuswords()
        assert c.decode_state(sw["j01r0"]) == c.State402.READY_TO_SWITCH_ON
        assert c.decode_state(sw["j01r1"]) == c.State402.READY_TO_SWITCH_ON


def test_bus_whose_interface_library_is_missing(
    rig_factory: Callable[..., Rig], monkeypatch: pytest.MonkeyPatch
) -> None:
    rig = rig_factory()

    def broken(**kwargs: Any) -> can.BusABC:
        raise NameError("name 'PCANBasic' is not defined")

    monkeypatch.setattr(can, "Bus", broken)
    iface = rig.config.buses[0].interface
    with pytest.raises(DriverError, match=rf"buses.bus0: cannot open {iface} .*NameError"):
        DriveSession(rig.config, rig.limits)


class SignalledOnStart(HoldSource):
    """Holds; SIGTERM arrives (as the console raises it) while setpoint 0 is computed,
    after the supervisor entered STREAMING, before any RPDO."""

    def setpoint(self, k: int) -> np.ndarray | None:
        if k == 0:
            raise SignalInterrupt("SIGTERM", 15)
        return super().setpoint(k)


def test_signal_at_stream_start_stops_every_node_with_its_cause(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    box = rig.brought_up_box()
    with pytest.raises(SignalInterrupt):
        box.stream(SignalledOnStart(n_cycles=50))
    causes = [e for e in box.events.to_list() if e["kind"] == "stop_cause"]
    assert [(e["cause"], e["text"]) for e in causes] == [
        ("signal", "stream start interrupted: SIGTERM")
    ]
    assert_only_quick_stops_sent(rig)


@pytest.mark.parametrize("exc", [SignalInterrupt("SIGTERM", 15), KeyboardInterrupt()])
def test_signal_while_enabled_and_idle_quick_stops_before_the_finish(
    rig_factory: Callable[..., Rig], exc: BaseException
) -> None:
    """A signal leaving a ``with DriveSession`` block between streams (drives enabled,
    holding) quick-stops every axis with the signal as its cause, then finishes."""
    rig = rig_factory()
    box = rig.brought_up_box()
    box.__exit__(type(exc), exc, None)
    causes = [(e["cause"], e["text"]) for e in box.events.to_list() if e["kind"] == "stop_cause"]
    name = "SIGTERM" if isinstance(exc, SignalInterrupt) else "SIGINT"
    assert causes == [("signal", f"{name}: stop requested")]
    assert not np.isnan(quick_stop_sync_time(rig))
    assert any(e["kind"] == "disable" for e in box.events.to_list())
    assert wait_until(lambda: all_left_operation_enabled(rig))
