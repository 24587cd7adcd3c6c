"""python-can's bus contract, checked on ``hrm_sim`` and ``hrm_ipc``.

The checks of python-can's own back-to-back tests (``test/back2back_test.py`` of python-can
4.6: ``Back2BackTestCase`` and ``TestThreadSafeBus``), written here for our two interfaces
(the installed python-can does not ship its tests): two buses of one channel opened as
generic python-can code opens them (``fd=True``, ``single_handle=True``), frames both ways
with every field kept, no frame when none was sent, absolute sub-second timestamps,
``fileno``, ``send_periodic`` stopping after its duration, 1,000 concurrent sends through
``can.ThreadSafeBus`` all received, and filters.  Where the two interfaces differ from
python-can's virtual bus on purpose: both carry classical CAN only, so an FD frame is
refused at send (python-can's FD cases), and the timestamp checks bound a frame's stamp
between the send and the receive instead of by wall-clock tolerances (the machine is
loaded)."""

from __future__ import annotations

import random
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from multiprocessing.dummy import Pool as ThreadPool
from pathlib import Path
from typing import Any

import can
import pytest

INTERFACES = ("hrm_sim", "hrm_ipc")
BITRATE = 500_000
TIMEOUT_S = 2.0  # a frame's receive wait (python-can's is 0.1 s on an idle machine)


@dataclass
class Opener:
    """Opens ends of one fresh channel of an interface, as generic python-can code does."""

    interface: str
    channel: str
    extra: dict[str, Any]
    opened: list[can.BusABC] = field(default_factory=list)

    def __call__(self, bus_class: Any = can.Bus, **kwargs: Any) -> can.BusABC:
        bus = bus_class(
            channel=self.channel,
            interface=self.interface,
            bitrate=BITRATE,
            fd=True,
            single_handle=True,
            **self.extra,
            **kwargs,
        )
        self.opened.append(bus)
        return bus


@pytest.fixture(params=INTERFACES)
def opener(request: pytest.FixtureRequest, ipc_dir: Path) -> Iterator[Opener]:
    interface = request.param
    extra: dict[str, Any] = {"directory": str(ipc_dir)} if interface == "hrm_ipc" else {}
    open_bus = Opener(interface, f"b2b-{uuid.uuid4().hex[:8]}", extra)
    yield open_bus
    for bus in open_bus.opened:
        bus.shutdown()


@pytest.fixture
def buses(opener: Opener) -> tuple[can.BusABC, can.BusABC]:
    return opener(), opener()


def check_received(recv: can.Message | None, sent: can.Message) -> None:
    assert recv is not None, "no message was received"
    assert recv.arbitration_id == sent.arbitration_id
    assert recv.is_extended_id == sent.is_extended_id
    assert recv.is_remote_frame == sent.is_remote_frame
    assert recv.is_error_frame == sent.is_error_frame
    assert recv.is_fd == sent.is_fd
    assert recv.bitrate_switch == sent.bitrate_switch
    assert recv.dlc == sent.dlc
    if not sent.is_remote_frame:
        assert bytes(recv.data) == bytes(sent.data)


def send_and_receive(bus1: can.BusABC, bus2: can.BusABC, msg: can.Message) -> None:
    """python-can's ``_send_and_receive``: 1 -> 2, then the same object with id + 1, 2 -> 1."""
    bus1.send(msg)
    check_received(bus2.recv(TIMEOUT_S), msg)
    bus1.recv(0)  # a bus that receives its own frames: take it off the queue
    msg.arbitration_id += 1
    bus2.send(msg)
    bus2.recv(0)
    check_received(bus1.recv(TIMEOUT_S), msg)


def test_no_message(buses: tuple[can.BusABC, can.BusABC]) -> None:
    assert buses[0].recv(0.1) is None


def test_multiple_shutdown(buses: tuple[can.BusABC, can.BusABC]) -> None:
    buses[0].shutdown()
    buses[0].shutdown()


@pytest.mark.parametrize(
    "make",
    [
        lambda: can.Message(
            is_extended_id=False, arbitration_id=0x100, data=[1, 2, 3, 4, 5, 6, 7, 8]
        ),
        lambda: can.Message(
            is_extended_id=True, arbitration_id=0x123456, data=[10, 11, 12, 13, 14, 15, 16, 17]
        ),
        lambda: can.Message(
            is_extended_id=False, arbitration_id=0x200, is_remote_frame=True, dlc=4
        ),
        lambda: can.Message(is_extended_id=False, arbitration_id=0x300, data=[4, 5, 6]),
    ],
    ids=["standard", "extended", "remote", "dlc_less_than_eight"],
)
def test_frames_both_ways_keep_every_field(
    buses: tuple[can.BusABC, can.BusABC], make: Callable[[], can.Message]
) -> None:
    send_and_receive(*buses, make())


def test_a_reused_message_object_is_delivered_as_sent(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    """Changing the object right after send() does not change the frame on the wire."""
    bus1, bus2 = buses
    msg = can.Message(is_extended_id=False, arbitration_id=0x100, data=[1, 2, 3])
    for k in range(10):
        msg.arbitration_id, msg.data[0] = 0x100 + k, k
        bus1.send(msg)
    msg.arbitration_id, msg.data[0] = 0x7FF, 0xFF
    got = [bus2.recv(TIMEOUT_S) for _ in range(10)]
    assert [(m.arbitration_id, m.data[0]) for m in got if m] == [(0x100 + k, k) for k in range(10)]


def test_unique_message_instances(opener: Opener, buses: tuple[can.BusABC, can.BusABC]) -> None:
    bus1, bus2 = buses
    bus3 = opener(receive_own_messages=True)
    bus3.send(can.Message(is_extended_id=False, arbitration_id=0x300, data=[2, 1, 3]))
    m1, m2, m3 = bus1.recv(TIMEOUT_S), bus2.recv(TIMEOUT_S), bus3.recv(TIMEOUT_S)
    assert m1 is not None and m2 is not None and m3 is not None
    check_received(m1, m2)
    check_received(m2, m3)
    m1.data[0] = 4
    assert m1.data != m2.data
    assert m2.data == m3.data
    assert m1.is_rx and m2.is_rx and not m3.is_rx  # our own frame comes back as sent


def test_fd_frames_are_refused_at_send(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """Both interfaces carry classical CAN: python-can's FD cases are refused, not garbled."""
    bus1, bus2 = buses
    for msg in (
        can.Message(is_fd=True, is_extended_id=True, arbitration_id=0x56789, data=[0xFF] * 64),
        can.Message(
            is_fd=True,
            bitrate_switch=True,
            is_extended_id=True,
            arbitration_id=0x98765,
            data=[0xFF] * 48,
        ),
    ):
        with pytest.raises(can.CanOperationError, match="FD"):
            bus1.send(msg)
    assert bus2.recv(0.05) is None


def test_fileno(buses: tuple[can.BusABC, can.BusABC]) -> None:
    try:
        fileno = buses[0].fileno()
    except NotImplementedError:
        return  # python-can allows it to be left unimplemented (hrm_sim)
    assert fileno == -1 or fileno > 0


def test_timestamps_are_absolute_with_sub_second_resolution(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    """A received frame is stamped on the ``time.time()`` scale, between its send and its
    receive (python-can: within 0.1 s of ``time()``), with sub-second resolution."""
    bus1, bus2 = buses
    before = time.time()
    bus2.send(can.Message())
    time.sleep(0.01)
    bus2.send(can.Message())
    m1, m2 = bus1.recv(TIMEOUT_S), bus1.recv(TIMEOUT_S)
    after = time.time()
    assert m1 is not None and m2 is not None
    assert before <= m1.timestamp <= m2.timestamp <= after
    assert m2.timestamp - m1.timestamp >= 0.01
    assert (m1.timestamp % 1) + (m2.timestamp % 1) > 0


def test_send_periodic_stops_after_its_duration(buses: tuple[can.BusABC, can.BusABC]) -> None:
    bus1, bus2 = buses
    for duration, period in [(0.01, 0.003), (0.1, 0.011)]:
        start = time.time()
        bus2.send_periodic(can.Message(), period, duration)
        got = []
        while (msg := bus1.recv(period + 0.5)) is not None:
            got.append(msg)
        assert got, (duration, period)
        assert len(got) <= duration / period + 2  # the task does not go on sending
        assert all(m.timestamp >= start for m in got)
        assert bus1.recv(0.2) is None


@pytest.mark.timeout(120)
def test_thread_safe_bus_concurrent_writes(opener: Opener) -> None:
    """python-can's ``TestThreadSafeBus.test_concurrent_writes``: 1,000 sends of one message
    object from 100 threads, 1,000 receives in 100 threads, every frame received (each
    receive waits up to 30 s instead of forever: a lost frame fails instead of hanging)."""
    bus1 = opener(can.ThreadSafeBus)
    bus2 = opener(can.ThreadSafeBus)
    message = can.Message(
        arbitration_id=0x123,
        channel=opener.channel,
        is_extended_id=True,
        timestamp=121334.365,
        data=[254, 255, 1, 2],
    )
    workload = 1000 * [message]
    senders, receivers = ThreadPool(100), ThreadPool(100)
    try:
        sent = senders.map_async(bus1.send, workload)
        got = receivers.map(lambda _: bus2.recv(30.0), len(workload) * [None])
        sent.get(timeout=60.0)  # every send returned, none raised
    finally:
        for pool in (senders, receivers):
            pool.close()
            pool.join()
    assert all(m is not None for m in got)
    assert all(message.equals(m, timestamp_delta=None) for m in got)
    assert bus2.recv(0.05) is None


@pytest.mark.timeout(120)
def test_thread_safe_bus_filtered(opener: Opener) -> None:
    """python-can's ``TestThreadSafeBus.test_filtered_bus``: 500 frames pass the receiver's
    filter, 500 do not, sent in random order from 100 threads."""
    bus1 = opener(can.ThreadSafeBus)
    bus2 = opener(can.ThreadSafeBus)
    ch = opener.channel
    included = can.Message(
        arbitration_id=0x123, channel=ch, is_extended_id=True, data=[254, 255, 1, 2]
    )
    excluded = can.Message(arbitration_id=0x02, channel=ch, is_extended_id=True, data=[1, 2, 3])
    workload = 500 * [included] + 500 * [excluded]
    random.Random(34).shuffle(workload)
    bus2.set_filters([{"can_id": 0x123, "can_mask": 0xFF, "extended": True}])
    senders, receivers = ThreadPool(100), ThreadPool(100)
    try:
        sent = senders.map_async(bus1.send, workload)
        got = receivers.map(lambda _: bus2.recv(30.0), 500 * [None])
        sent.get(timeout=60.0)
    finally:
        for pool in (senders, receivers):
            pool.close()
            pool.join()
    assert len(got) == 500 and all(m is not None for m in got)
    assert all(included.equals(m, timestamp_delta=None) for m in got)
    assert bus2.recv(0.2) is None  # the excluded ones never come
