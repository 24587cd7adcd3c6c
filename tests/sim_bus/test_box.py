"""The box's drives over every CAN backend: the frames a host sees on a real bus."""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import numpy as np
import pytest

import drivers.protocol.cia301 as cia301
import drivers.protocol.cia402 as cia
from drivers.config import box_config_from_dict
from sim_bus.box import SimBox

NODES = {"j01r0": 1, "j01r1": 2}
TIMEOUT_S = 1.0


class Host:
    """The test's end of the bus: sends frames and waits for the ones it expects."""

    def __init__(self, kwargs: dict[str, Any]) -> None:
        self.bus = can.Bus(**kwargs)
        self.sent: list[tuple[int, bytes]] = []

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def expect(
        self, want: Callable[[can.Message], bool], timeout_s: float = TIMEOUT_S
    ) -> can.Message:
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            m = self.bus.recv(left)
            if m is not None and want(m):
                return m
        raise AssertionError("expected frame did not arrive")

    def collect(self, duration_s: float, want: Callable[[can.Message], bool]) -> list[can.Message]:
        out = []
        deadline = time.monotonic() + duration_s
        while (left := deadline - time.monotonic()) > 0:
            m = self.bus.recv(left)
            if m is not None and want(m):
                out.append(m)
        return out

    def collect_until(
        self,
        want: Callable[[can.Message], bool],
        done: Callable[[list[can.Message]], bool],
        timeout_s: float = 5.0,
    ) -> list[can.Message]:
        """The frames ``want`` takes, until ``done`` of them holds (a wall-clock timeout only
        against a hang: the window itself is measured in frames)."""
        out: list[can.Message] = []
        deadline = time.monotonic() + timeout_s
        while not done(out):
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"not done after {timeout_s} s: {len(out)} frame(s)")
            m = self.bus.recv(left)
            if m is not None and want(m):
                out.append(m)
        return out

    def sdo(self, node: int, msg: can.Message) -> bytes:
        self.send(msg)
        return bytes(self.expect(lambda m: m.arbitration_id == 0x580 + node).data)


@pytest.fixture
def rig(can_backend: Callable[[], dict[str, Any]]) -> Iterator[tuple[Host, SimBox]]:
    kw = can_backend()
    cfg = box_config_from_dict(
        {
            "control": {"rate_hz": 100.0},
            "buses": {
                "can0": {
                    "interface": kw["interface"],
                    "channel": kw["channel"],
                    "bitrate": 1_000_000,
                    "options": {k: v for k, v in kw.items() if k not in ("interface", "channel")},
                    "nodes": NODES,
                }
            },
        },
        "test",
    )
    host = Host(kw)
    box = SimBox(cfg, tension_noise_N=0.0)
    try:
        box.start()
        yield host, box
    finally:
        box.stop()
        host.bus.shutdown()


def test_bootup_sdo_pdo_sync_heartbeat_emcy_on_the_bus(rig: tuple[Host, SimBox]) -> None:
    host, box = rig
    is_boot = lambda m: m.arbitration_id in (0x701, 0x702) and bytes(m.data) == b"\x00"  # noqa: E731
    host.send(cia301.make_nmt(cia301.NMT_RESET_NODE, 0))
    boots = {host.expect(is_boot).arbitration_id, host.expect(is_boot).arbitration_id}
    assert boots == {0x701, 0x702}
    # SDO: read statusword, bad object, write-protected object
    assert host.sdo(1, cia301.make_sdo_upload_request(1, cia.OD_STATUSWORD, 0)) == bytes.fromhex(
        "4b41600050020000"
    )
    assert host.sdo(2, cia301.make_sdo_upload_request(2, 0x2345, 1)) == bytes(
        cia301.make_sdo_abort(2, 0x2345, 1, cia301.SDO_ABORT_NO_OBJECT).data
    )
    # heartbeat producer: 20 ms
    host.sdo(1, cia301.make_sdo_download_expedited(1, 0x1017, 0, struct.pack("<H", 20)))
    beats = host.collect(0.2, lambda m: m.arbitration_id == 0x701)
    assert 6 <= len(beats) <= 12 and {bytes(m.data) for m in beats} == {b"\x7f"}
    # operational, enable node 1 over SDO, then RPDO + SYNC -> TPDO
    host.send(cia301.make_nmt(cia301.NMT_START_REMOTE_NODE, 0))
    host.sdo(1, cia301.make_sdo_download_expedited(1, cia.OD_MODES_OF_OPERATION, 0, b"\x08"))
    for cw in (cia.CW_SHUTDOWN, cia.CW_SWITCH_ON, cia.CW_ENABLE_OPERATION):
        host.sdo(
            1, cia301.make_sdo_download_expedited(1, cia.OD_CONTROLWORD, 0, struct.pack("<H", cw))
        )
    host.send(cia.make_rpdo_target(1, cia.CW_ENABLE_OPERATION, 800))
    host.send(cia301.make_sync())
    t1 = host.expect(lambda m: m.arbitration_id == 0x181)
    assert bytes(t1.data) == bytes(cia.make_tpdo_feedback(1, 0x1237, 0).data)
    host.send(cia301.make_sync())
    t2 = host.expect(lambda m: m.arbitration_id == 0x181)
    assert cia.parse_tpdo(t2.data) == (0x1237, 800)
    assert box.counts()[0] == 800
    # injected following-error fault -> EMCY 0x8611 on the bus
    box.fault_drive("j01r0")
    emcy = host.expect(lambda m: m.arbitration_id == 0x081)
    assert bytes(emcy.data)[:3] == b"\x11\x86\x01"


BEATS = 5  # a fault is watched for this many heartbeats of the other drive (10 ms apart)


def beats_after(t: float) -> Callable[[can.Message], bool]:
    return lambda m: m.arbitration_id in (0x701, 0x702) and m.timestamp > t


def test_heartbeat_stop_and_frame_drop_faults(rig: tuple[Host, SimBox]) -> None:
    """Judged on the frames' own timestamps and counted in the other drive's beats: a beat
    sent before the fault may still wait in the host's receive queue, and with the other
    core busy the box can be descheduled for longer than any fixed wall-clock window, so
    only frames stamped after the fault call returned count, and a window is BEATS beats.
    The box sends under the lock the fault calls take, and both backends stamp a frame when
    it is sent (``virtual``: the sender's ``time.time()``; ``udp_multicast``: the kernel's
    arrival stamp on loopback)."""
    host, box = rig
    n_of = lambda cob: lambda ms: sum(m.arbitration_id == cob for m in ms) >= BEATS  # noqa: E731
    for node in (1, 2):
        host.sdo(node, cia301.make_sdo_download_expedited(node, 0x1017, 0, struct.pack("<H", 10)))
    box.stop_heartbeat("j01r1")
    t_stop = time.time()
    beats = host.collect_until(beats_after(t_stop), n_of(0x701))
    assert {m.arbitration_id for m in beats} == {0x701}
    box.stop_heartbeat("j01r1", stopped=False)  # its beats time the next window
    box.drop_frames("can0", lambda m: m.arbitration_id == 0x701, count=None)
    t_drop = time.time()
    beats = host.collect_until(beats_after(t_drop), n_of(0x702))
    assert {m.arbitration_id for m in beats} == {0x702}
    box.clear_frame_faults()
    t_clear = time.time()
    host.collect_until(beats_after(t_clear), lambda ms: any(m.arbitration_id == 0x701 for m in ms))


def test_arm_state_follows_the_drives(rig: tuple[Host, SimBox]) -> None:
    _host, box = rig
    s = box.arm_state()
    assert np.allclose(s.centres[-1], [2007.0, 0.0, 0.0], atol=0.05)
    box.snap_rope("j01r0")
    time.sleep(0.05)
    s2 = box.arm_state()
    assert s2.tension_N[0] == 0.0
    assert abs(s2.alpha[0]) + abs(s2.theta[0]) > 0.0


def test_receive_buffer_enlarged_on_socket_buses(can_backend: Callable[[], dict[str, Any]]) -> None:
    from sim_bus.box import enlarge_receive_buffer

    kw = can_backend()
    bus = can.Bus(**kw)
    try:
        size = enlarge_receive_buffer(bus, 4 * 1024 * 1024)
        if kw["interface"] == "virtual":
            assert size is None
        else:
            assert size is not None and size >= 1024 * 1024
    finally:
        bus.shutdown()
