"""The supervisor on a fake bus port with an injected clock: idle and streaming
watchdogs, the host heartbeat, and the one-period stop, step by step (no thread)."""

from __future__ import annotations

from typing import Any

import can
import numpy as np
import pytest

from drivers.cycle import BusLayout, EventLog
from drivers.protocol import cia301, cia402
from drivers.protocol.batch import to_messages
from drivers.safety.causes import StopKind
from drivers.safety.monitor import NodeMonitor
from drivers.safety.supervisor import Mode, StopRecord, Supervisor, SupervisorModeError
from drivers.sources import HoldSource

T = 0.01
HB_PERIOD_S = 0.1
HB_TIMEOUT_S = 0.35
HOST = 0x7F
SYNC = 0x080


class FakePort:
    """Records what the supervisor sends (the BusPort interface it uses)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.log = None  # no CAN log
        self.sent: list[tuple[float, can.Message]] = []
        self.clock: FakeClock | None = None

    def send(self, msg: can.Message, timeout_s: float = 0.05) -> None:
        self.sent.append((self.clock() if self.clock else 0.0, msg))

    def send_many(
        self, msgs: list[can.Message], timeout_s: float = 0.05, keep_going: bool = False
    ) -> None:
        for m in msgs:
            self.send(m, timeout_s)

    def send_batch(
        self, frames: np.ndarray, timeout_s: float = 0.05, keep_going: bool = False
    ) -> None:
        self.send_many(to_messages(frames, is_rx=False), timeout_s)

    def ids_since(self, t: float) -> list[int]:
        return [m.arbitration_id for ts, m in self.sent if ts >= t]


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Limits:
    """Every setpoint is within limits unless it exceeds ``max_counts``."""

    motor_ids = ("m0", "m1")
    counts_min = np.array([-(10**6)] * 2)
    counts_max = np.array([10**6] * 2)
    max_rate_counts_per_s = np.array([1e6] * 2)
    max_accel_counts_per_s2: np.ndarray | None = None  # none: the stop ramp holds
    max_jerk_counts_per_s3: np.ndarray | None = None

    def motor_label(self, i: int) -> str:
        return self.motor_ids[i]

    def check_counts(self, counts: object, previous: object = None, dt_s: object = None) -> None:
        from drivers.safety.limits import SetpointError

        if np.any(np.abs(np.asarray(counts)) > 10**6):
            raise SetpointError("motor m0: setpoint beyond the drum travel")

    def counts_from_angles(self, alpha: object, theta: object, tension_N: object = None):
        return np.zeros(2, np.int64)


def make(clock: FakeClock) -> tuple[Supervisor, NodeMonitor, FakePort, list[StopRecord]]:
    port = FakePort("bus0")
    port.clock = clock
    mon = NodeMonitor(["m0", "m1"], missing_tpdo_cycles=3, heartbeat_timeout_s=HB_TIMEOUT_S,
                      clock=clock)  # fmt: skip
    layout = BusLayout(port, np.array([0, 1]), np.array([1, 2]))  # type: ignore[arg-type]
    stops: list[StopRecord] = []
    sup = Supervisor([layout], mon, Limits(), T, HB_PERIOD_S, HOST, EventLog(),
                     on_stop=stops.append, clock=clock, sleep=lambda s: None)  # fmt: skip
    return sup, mon, port, stops


def armed(
    clock: FakeClock, targets: tuple[int, int] = (0, 0)
) -> tuple[Supervisor, NodeMonitor, FakePort, list[StopRecord]]:
    """A supervisor with the heartbeat on, both nodes just heard, armed at ``targets``."""
    sup, mon, port, stops = make(clock)
    sup.set_heartbeat(True)
    heartbeat(mon, 0), heartbeat(mon, 1)
    sup.arm(np.array(targets))
    return sup, mon, port, stops


def heartbeat(mon: NodeMonitor, idx: int) -> None:
    mon.on_heartbeat(idx, b"\x05")  # operational


def tpdo(mon: NodeMonitor, idx: int, sw: int = 0x0237, pos: int = 0) -> None:
    mon.on_tpdo(idx, sw.to_bytes(2, "little") + pos.to_bytes(4, "little", signed=True))


def quick_stop_rpdos(port: FakePort, since: float) -> list[can.Message]:
    return [
        m
        for ts, m in port.sent
        if ts >= since and 0x200 < m.arbitration_id <= 0x27F and m.data[:2] == b"\x02\x00"
    ]


def syncs_before(port: FakePort, t: float) -> list[float]:
    return [ts for ts, m in port.sent if m.arbitration_id == SYNC and ts < t]


def run_until(sup: Supervisor, clock: FakeClock, t_end: float, each=None) -> None:
    while clock.t < t_end - 1e-12:
        clock.t = round(clock.t + T, 9)
        if each is not None:
            each()
        sup.step(clock.t)


def test_heartbeat_is_sent_every_period_and_stops_when_off() -> None:
    clock = FakeClock()
    sup, _mon, port, _ = make(clock)
    sup.set_heartbeat(True)
    sup.step(clock.t)
    run_until(sup, clock, clock.t + 1.0)
    hb = [ts for ts, m in port.sent if m.arbitration_id == 0x700 + HOST]
    assert len(hb) == 11 and np.allclose(np.diff(hb), HB_PERIOD_S)
    sup.set_heartbeat(False)
    n = len(port.sent)
    run_until(sup, clock, clock.t + 1.0)
    assert len(port.sent) == n and sup.mode is Mode.OFF


def test_idle_heartbeat_loss_stops_every_axis_at_the_deadline_it_is_seen() -> None:
    clock = FakeClock()
    sup, mon, port, stops = armed(clock, (10, 20))
    t_last = clock.t
    # m0 keeps beating, m1 falls silent.
    run_until(sup, clock, t_last + HB_TIMEOUT_S - T / 2, each=lambda: heartbeat(mon, 0))
    assert sup.mode is Mode.ARMED and not quick_stop_rpdos(port, 0.0)
    clock.t = round(clock.t + T, 9)
    heartbeat(mon, 0)
    sup.step(clock.t)  # the first deadline past the timeout: stop now
    qs = quick_stop_rpdos(port, clock.t)
    assert sorted(m.arbitration_id for m in qs) == [0x201, 0x202]
    assert [int.from_bytes(m.data[2:6], "little", signed=True) for m in qs] == [10, 20]
    ids = port.ids_since(clock.t)
    assert ids.index(SYNC) > ids.index(0x202)  # the SYNC that applies them comes after
    assert sup.mode is Mode.STOPPING
    # Confirmed once every node's fresh feedback left OPERATION_ENABLED.
    clock.t = round(clock.t + T, 9)
    tpdo(mon, 0, sw=0x0217), tpdo(mon, 1, sw=0x0217)  # QUICK_STOP_ACTIVE
    mon.rx_seq[:] = sup.seq
    sup.step(clock.t)
    assert sup.mode is Mode.HEARTBEAT and len(stops) == 1
    stop = stops[0]
    assert stop.confirmed and not stop.while_streaming
    assert [(x.kind, x.motor) for x in stop.causes] == [(StopKind.HEARTBEAT, "m1")]
    assert stop.latency_s <= T


def test_a_cause_between_deadlines_stops_at_once() -> None:
    """An EMCY reported by a receive callback wakes the supervisor: the quick stop goes
    out at that moment, not at the next deadline."""
    clock = FakeClock()
    sup, mon, port, _ = armed(clock)
    sup.step(clock.t)
    clock.t = round(clock.t + 0.003, 9)  # 3 ms after a deadline
    mon.on_emcy(1, 2, bytes.fromhex("1186110000000000"))
    assert mon.wake.is_set()
    sup.wake(clock.t)
    assert len(quick_stop_rpdos(port, clock.t)) == 2
    assert sup.mode is Mode.STOPPING


@pytest.mark.parametrize(
    ("payload", "stops"),
    [
        ("0000000000000000", False),  # error reset, no error left
        ("0000010000000000", True),  # 'error reset' with the generic error bit still set
        ("0000800000000000", True),  # ... a manufacturer-specific one
    ],
)
def test_an_error_reset_emcy_stops_only_when_an_error_remains(payload: str, stops: bool) -> None:
    clock = FakeClock()
    sup, mon, port, _ = armed(clock)
    sup.step(clock.t)
    clock.t = round(clock.t + 0.003, 9)
    mon.on_emcy(1, 2, bytes.fromhex(payload))
    sup.wake(clock.t)
    assert (len(quick_stop_rpdos(port, clock.t)) == 2) is stops
    assert (sup.mode is Mode.STOPPING) is stops


def test_a_heartbeat_that_names_no_state_is_a_bad_frame() -> None:
    """Bit 7 set (a node-guarding toggle) or an unknown state: a bad frame, never read as
    OPERATIONAL."""
    clock = FakeClock()
    sup, mon, _port, _ = armed(clock)
    sup.step(clock.t)
    mon.on_heartbeat(1, b"\x85")
    assert [(c.kind, c.motor) for c in mon.queued()] == [(StopKind.BAD_FRAME, "m1")]
    assert "0x85" in mon.queued()[0].text


def test_streaming_missing_feedback_stops_within_one_period() -> None:
    clock = FakeClock()
    sup, mon, port, stops = armed(clock)
    src = HoldSource(n_cycles=1000)
    src.start(np.array([0, 0]), T)
    stream = sup.begin(src)
    assert sup.mode is Mode.STREAMING
    # Setpoint 0's RPDOs went out at once; the first SYNC on the grid after them.
    assert port.ids_since(clock.t)[:2] == [0x201, 0x202]

    def feedback() -> None:
        heartbeat(mon, 0), heartbeat(mon, 1)
        tpdo(mon, 0)
        mon.rx_seq[0] = sup.seq  # m0 answers every SYNC; m1 stops answering after 5
        if sup.seq < 5:
            tpdo(mon, 1)
            mon.rx_seq[1] = sup.seq

    run_until(sup, clock, clock.t + 0.2, each=feedback)
    assert sup.mode is not Mode.STREAMING
    syncs = [ts for ts, m in port.sent if m.arbitration_id == SYNC]
    qs = quick_stop_rpdos(port, 0.0)
    assert qs, "no quick stop"
    t_stop = next(ts for ts, m in port.sent if m in qs)
    # m1 answered SYNCs 0..4; SYNCs 5, 6, 7 get nothing: the deadline that finds the
    # third missing answer (the one after SYNC 7) sends the quick stop, and no SYNC 8.
    assert len(syncs_before(port, t_stop)) == 8
    assert t_stop == pytest.approx(syncs[7] + T, abs=1e-9)
    run_until(
        sup,
        clock,
        clock.t + 0.05,
        each=lambda: (tpdo(mon, 0, sw=0x0217), tpdo(mon, 1, sw=0x0217),
                      mon.rx_seq.__setitem__(slice(None), sup.seq)),
    )  # fmt: skip
    assert stream.done.is_set() and stream.result is not None
    kinds = {(x.kind, x.motor) for x in stream.result.causes}
    assert (StopKind.TPDO_MISSING, "m1") in kinds
    assert stops and stops[0].while_streaming


def test_a_setpoint_beyond_the_limits_is_never_sent() -> None:
    clock = FakeClock()
    sup, _mon, port, _ = armed(clock)
    src = HoldSource(n_cycles=5, counts=np.array([0, 2 * 10**6]))
    src.start(np.array([0, 0]), T)
    stream = sup.begin(src)
    assert stream.error is not None and "drum travel" in str(stream.error)
    sent_targets = [
        int.from_bytes(m.data[2:6], "little", signed=True)
        for _, m in port.sent
        if 0x200 < m.arbitration_id <= 0x27F
    ]
    assert sent_targets and max(sent_targets) == 0  # only the quick stop, at the hold


def test_mode_rules() -> None:
    clock = FakeClock()
    sup, _mon, _port, _ = make(clock)
    src = HoldSource(n_cycles=3)
    src.start(np.array([0, 0]), T)
    with pytest.raises(SupervisorModeError, match="cannot stream in mode OFF"):
        sup.begin(src)
    with pytest.raises(SupervisorModeError, match="cannot arm in mode OFF"):
        sup.arm(np.array([0, 0]))
    sup.set_heartbeat(True)
    sup.arm(np.array([0, 0]))
    sup.begin(src)
    with pytest.raises(SupervisorModeError, match="cannot disarm in mode STREAMING"):
        sup.disarm()


def test_quick_stop_keeps_repeating_until_confirmed_then_gives_up() -> None:
    clock = FakeClock()
    sup, _mon, port, stops = armed(clock)
    sup.request_stop()
    sup.step(clock.t)
    run_until(sup, clock, clock.t + 0.2)  # no feedback at all
    assert stops and stops[0].confirmed is False
    assert stops[0].causes[0].kind is StopKind.OPERATOR
    assert len(quick_stop_rpdos(port, 0.0)) == 2 * 10  # STOP_CONFIRM_CYCLES times, per node
    assert cia402.CW_QUICK_STOP == 0x0002
    # then every node that did not confirm is sent NMT enter pre-operational, named
    assert stops[0].unconfirmed == ["m0", "m1"]
    nmt = [bytes(m.data) for _ts, m in port.sent if m.arbitration_id == cia301.COB_NMT]
    assert nmt == [bytes([cia301.NMT_ENTER_PRE_OPERATIONAL, n]) for n in (1, 2)]


def _stopped_stream(detect_late_by_periods: float | None) -> Any:
    """A 2-node stream on the fake clock, stopped after 5 cycles: by a cause reported
    ``detect_late_by_periods`` periods before the supervisor sees it, or (None) by m1's
    TPDOs ceasing (found at a deadline).  Returns the stream's result."""
    from drivers.safety.causes import StopCause

    clock = FakeClock()
    sup, mon, _port, _stops = armed(clock)
    src = HoldSource(n_cycles=1000)
    src.start(np.array([0, 0]), T)
    stream = sup.begin(src)

    def feedback() -> None:
        heartbeat(mon, 0), heartbeat(mon, 1)
        for i in (0, 1):
            if detect_late_by_periods is not None or i == 0 or sup.seq < 5:
                tpdo(mon, i)
                mon.rx_seq[i] = sup.seq

    run_until(sup, clock, clock.t + (0.055 if detect_late_by_periods is not None else 0.2),
              each=feedback)  # fmt: skip
    if detect_late_by_periods is not None:
        assert sup.mode is Mode.STREAMING
        t_detect = round(clock.t - detect_late_by_periods * T, 9)
        cause = StopCause(StopKind.TENSION, "m0: rope snapped", "m0", t_detect)
        sup._begin_stop([cause], clock.t)
    run_until(
        sup, clock, clock.t + 0.1,
        each=lambda: (tpdo(mon, 0, sw=0x0217), tpdo(mon, 1, sw=0x0217),
                      mon.rx_seq.__setitem__(slice(None), sup.seq)),
    )  # fmt: skip
    assert stream.done.is_set() and stream.result is not None
    return stream.result


def test_a_stop_counts_the_setpoint_syncs_sent_after_its_cause_was_detected() -> None:
    """Counted in cycles (load does not change it): a cause the supervisor sees only
    after it already sent SYNCs (its detection earlier) counts those SYNCs."""
    # the supervisor has just sent the SYNC of the current deadline: seen 0.5 periods
    # late the cause counts that one, 1.5 periods late the one before it too
    assert _stopped_stream(0.5).stop_syncs_after_detection == 1
    assert _stopped_stream(1.5).stop_syncs_after_detection == 2
    assert _stopped_stream(0.0).stop_syncs_after_detection == 0  # at that SYNC: not after


def test_a_cause_found_at_the_deadline_stops_before_that_cycles_sync() -> None:
    result = _stopped_stream(None)
    assert any(c.kind is StopKind.TPDO_MISSING for c in result.causes)
    assert result.stop_syncs_after_detection == 0
    assert result.to_dict()["stop_syncs_after_detection"] == 0


class SteppedTime:
    """A clock that moves only when slept on (the wait's polls, counted)."""

    def __init__(self) -> None:
        self.t = 0.0
        self.sleeps = 0

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.sleeps += 1
        self.t += s


def test_the_wait_for_the_supervisor_gives_up_at_its_timeout() -> None:
    from drivers.safety.supervisor import wait_while

    t = SteppedTime()
    mode = wait_while(lambda: Mode.STOPPING, frozenset({Mode.STOPPING}), 0.5, T, t, t.sleep)
    assert mode is Mode.STOPPING  # still stopping: timed out
    assert t.t == pytest.approx(0.5, abs=T) and t.t >= 0.5
    assert t.sleeps == pytest.approx(0.5 / T, abs=1)


def test_the_wait_for_the_supervisor_ends_when_the_mode_changes() -> None:
    from drivers.safety.supervisor import wait_while

    t = SteppedTime()
    modes = iter([Mode.STREAMING, Mode.STOPPING, Mode.STOPPING, Mode.HEARTBEAT])
    busy = frozenset({Mode.STREAMING, Mode.STOPPING})
    assert wait_while(lambda: next(modes), busy, 2.0, T, t, t.sleep) is Mode.HEARTBEAT
    assert t.sleeps == 3
    assert wait_while(lambda: Mode.ARMED, busy, 2.0, T, t, t.sleep) is Mode.ARMED
    assert t.sleeps == 3  # not busy: no wait at all


def test_the_session_writes_the_monitor_only_through_the_supervisor() -> None:
    clock = FakeClock()
    sup, mon, _port, _stops = make(clock)
    sup.set_guard(True)
    assert mon.guarding and sup.guard_idle and sup.guarding
    mon.hb_armed_at = 1.0
    assert sup.prepare_reset() == clock.t and mon.hb_armed_at is None
    sup.report(StopKind.OPERATOR, "one")
    assert [c.text for c in sup.drain_causes()] == ["one"] and sup.drain_causes() == []
    sup.set_guard(False)
    assert not mon.guarding and not sup.guard_idle
