"""CAN error frames (SocketCAN's ``CAN_ERR_*`` classes) reach the stop path and the log:
bus-off and error-passive stop every axis naming the bus and the class; the other
classes are counted and logged; every error frame is in the run's CAN log."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.canlog import TrafficLog, log_formats
from drivers.lifecycle import SessionStateError
from drivers.protocol import can_error as ce
from drivers.safety.causes import StopKind
from drivers.session import SafetyStopError
from drivers.sources import HoldSource
from tests.drivers.driver_rig import Rig, send_from_outside, wait_until
from tests.drivers.safety.test_supervisor_stops import (
    GUEST_CONTROL,
    all_left_operation_enabled,
    quick_stop_sync_time,
)
from tests.drivers.test_cycle_lean import rig as receiver_rig


def error_frame(classes: int, data1: int = 0) -> can.Message:
    """An error frame as python-can's socketcan gives one (11-bit, the class in the id)."""
    data = bytes([0, data1, 0, 0, 0, 0, 0, 0])
    return can.Message(arbitration_id=classes, data=data, is_error_frame=True, is_extended_id=False)


BUS_OFF = error_frame(ce.CAN_ERR_BUSOFF)
RX_PASSIVE = error_frame(ce.CAN_ERR_CRTL, ce.CAN_ERR_CRTL_RX_PASSIVE)
TX_PASSIVE = error_frame(ce.CAN_ERR_CRTL, ce.CAN_ERR_CRTL_TX_PASSIVE)
TX_WARNING = error_frame(ce.CAN_ERR_CRTL, ce.CAN_ERR_CRTL_TX_WARNING)


@given(classes=st.integers(0, 0x3FF), data=st.binary(max_size=8))
def test_a_verdict_stops_exactly_on_bus_off_and_error_passive_and_names_every_class(
    classes: int, data: bytes
) -> None:
    v = ce.error_frame_verdict(classes | 0x20000000, data)  # the error flag still set
    d1 = data[1] if len(data) > 1 else 0
    passive = bool(classes & ce.CAN_ERR_CRTL) and bool(d1 & ce.CAN_ERR_CRTL_PASSIVE)
    assert v.stops == (bool(classes & ce.CAN_ERR_BUSOFF) or passive)
    assert v.classes == classes
    for bit, name, _what in ce.ERROR_CLASSES:
        assert (name in v.text) == bool(classes & bit), (hex(classes), v.text)
    assert "\n" not in v.text and v.text


@pytest.mark.parametrize(
    ("frame", "named"),
    [
        (BUS_OFF, "bus-off (CAN_ERR_BUSOFF)"),
        (RX_PASSIVE, "rx error-passive"),
        (TX_PASSIVE, "tx error-passive"),
        (error_frame(ce.CAN_ERR_BUSOFF | ce.CAN_ERR_RESTARTED), "CAN_ERR_BUSOFF"),
    ],
)
def test_bus_off_and_error_passive_are_a_stop_cause_naming_the_bus_and_the_class(
    frame: can.Message, named: str, tmp_path: Path
) -> None:
    bus, log, _port, _mon, rx, _net, reports = receiver_rig(tmp_path)
    rx.on_message_received(frame)
    assert [k for k, _t in reports] == [StopKind.BUS_ERROR]
    text = reports[0][1]
    assert text.startswith(f"bus bus0: CAN error frame 0x{frame.arbitration_id:03X}: ")
    assert named in text
    assert rx.traffic.error_frames == 1
    assert rx.traffic.to_dict()["error_frame_classes"] == {f"0x{frame.arbitration_id:03X}": 1}
    log.stop()
    bus.shutdown()


def test_warnings_and_bus_errors_are_counted_and_logged_once_per_class(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bus, _log, _port, mon, rx, _net, reports = receiver_rig()
    frames = [TX_WARNING, TX_WARNING, error_frame(ce.CAN_ERR_PROT | ce.CAN_ERR_BUSERROR)] * 50
    frames += [error_frame(ce.CAN_ERR_CRTL, ce.CAN_ERR_CRTL_ACTIVE), error_frame(ce.CAN_ERR_ACK)]
    with caplog.at_level(logging.WARNING, logger="drivers.receive"):
        for m in frames:
            rx.on_message_received(m)
    assert reports == [] and mon.drain() == []
    assert rx.traffic.error_frames == len(frames)
    assert rx.traffic.error_classes == {0x004: 101, 0x088: 50, 0x020: 1}
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 3, warned  # one per class combination (0x004 twice: its first)
    assert "bus bus0" in warned[0] and "tx error-warning (CAN_ERR_CRTL data[1]=0x08)" in warned[0]
    bus.shutdown()


@pytest.mark.parametrize("fmt", log_formats())
def test_an_error_frame_reads_back_from_the_can_log_as_one(tmp_path: Path, fmt: str) -> None:
    """Written as the receiver hands it over: BLF keeps the class and the data, ASC and
    candump mark an error frame (python-can's writers keep no class there; candump keeps
    the data under ``CAN_ERR_BUSERROR``), TRC leaves it out (python-can's writer: see
    :data:`drivers.canlog.LOG_FORMAT_DURABILITY`)."""
    path = tmp_path / f"bus.{fmt}"
    log = TrafficLog(path)
    t0 = time.time()
    for k, m in enumerate((BUS_OFF, TX_PASSIVE)):
        m = can.Message(
            timestamp=t0 + k * 0.001, arbitration_id=m.arbitration_id, data=m.data,
            is_error_frame=True, is_extended_id=False,
        )  # fmt: skip
        log.on_message_received(m)
    log.on_message_received(
        can.Message(timestamp=t0 + 0.002, arbitration_id=0x181, data=b"\x01", is_extended_id=False)
    )
    log.stop()
    assert (log.n_frames, log.write_errors) == (3, 0)
    back = list(can.LogReader(path))
    errors = [m for m in back if m.is_error_frame]
    assert [m.arbitration_id for m in back if not m.is_error_frame] == [0x181]
    if fmt == "trc":
        assert errors == []
        return
    assert len(errors) == 2
    if fmt == "blf":
        assert [(m.arbitration_id, bytes(m.data)) for m in errors] == [
            (0x040, bytes(BUS_OFF.data)),
            (0x004, bytes(TX_PASSIVE.data)),
        ]


def test_a_bus_off_error_frame_stops_every_axis_and_is_in_the_can_log(
    rig_factory: Callable[..., Rig], tmp_path: Path
) -> None:
    """A bus-off error frame on bus1 (from another socket on the bus: what a SocketCAN
    adapter's driver hands every socket with the error filter set, python-can's default)
    while streaming: every node of both buses quick-stopped within a period of it, the
    cause naming the bus and the class, the frame in bus1's CAN log.  Over SocketCAN in
    the vcan guest at 25 Hz (as the other stop tests there)."""
    rig = rig_factory(guest_control=GUEST_CONTROL)
    period_s = 1.0 / rig.config.control.rate_hz
    box = rig.open_box(log_dir=tmp_path, run_name="err")
    box.bring_up()
    for sn in rig.sniffers:
        sn.clear()
    err = stream_err(rig, box, lambda: send_from_outside(rig, 1, BUS_OFF))
    assert [x.kind for x in err.causes] == [StopKind.BUS_ERROR], err.causes
    assert err.causes[0].text == "bus bus1: CAN error frame 0x040: bus-off (CAN_ERR_BUSOFF)"
    assert "bus bus1" in str(err) and "CAN_ERR_BUSOFF" in str(err)
    assert err.result.stop_latency_s is not None and err.result.stop_latency_s <= period_s
    assert err.result.stop_syncs_after_detection in (0, 1)
    t_stop = quick_stop_sync_time(rig)  # every node of both buses got its quick stop
    assert t_stop == t_stop, "a node never got a quick stop"
    assert wait_until(lambda: all_left_operation_enabled(rig))
    box.finish()
    box.close()
    rig.box = None
    with can.LogReader(str(tmp_path / "err_bus1.blf")) as reader:
        logged = [(m.arbitration_id, bytes(m.data)) for m in reader if m.is_error_frame]
    assert logged == [(0x040, bytes(BUS_OFF.data))]


def stream_err(rig: Rig, box: Any, action: Callable[[], Any]) -> SafetyStopError:
    """A hold stream on a box brought up, ``action`` 0.1 s into it; the stop's error."""
    timer = threading.Timer(0.1, action)
    timer.start()
    try:
        with pytest.raises(SafetyStopError) as info:
            box.stream(HoldSource(n_cycles=300))
    finally:
        timer.cancel()
    return info.value


@pytest.mark.parametrize("can_backend", ["virtual"], indirect=True)
def test_an_error_passive_frame_while_idle_refuses_the_next_enable(
    rig_factory: Callable[..., Rig],
) -> None:
    """Drives configured, not enabled: an error-passive frame stops nothing (nothing
    moves) but the enable after it is refused naming the bus and the class, until a
    reset-fault (as an EMCY since the configuration)."""
    rig = rig_factory()
    box = rig.open_box()
    box.configure()
    send_from_outside(rig, 0, TX_PASSIVE)
    assert wait_until(lambda: box._receivers[0].traffic.error_frames == 1)
    with pytest.raises(SessionStateError, match=r"enable refused: bus bus0: CAN error frame "
                       r"0x004: controller: tx error-passive .*reset-fault clears it"):  # fmt: skip
        box.enable()
    assert box.state.name == "READY"
    box.reset_fault()
    box.enable()  # the cause was taken: enabled now
    assert box.state.name == "ENABLED"
