"""Each run's CAN log reads back with the frames that were on the wire; the run record."""

from __future__ import annotations

import json
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from drivers.bus import BusPort, BusSendError, TrafficLog
from drivers.sources import JogSource
from hrm_ctrl.errors import DriverError
from tests.drivers.driver_rig import Rig, Sniffer, wait_until

HOST_IDS = {0x000, 0x080} | set(range(0x201, 0x280)) | set(range(0x601, 0x680)) | {0x77F}
DRIVE_IDS = set(range(0x081, 0x100)) | set(range(0x181, 0x200)) | set(range(0x581, 0x600))
DRIVE_IDS |= set(range(0x701, 0x77F))


def by_id(frames: list[can.Message], ids: set[int]) -> dict[int, list[bytes]]:
    out: dict[int, list[bytes]] = defaultdict(list)
    for m in frames:
        if m.arbitration_id in ids:
            out[m.arbitration_id].append(bytes(m.data))
    return out


def since_first_host_frame(
    frames: list[can.Message], is_host: Callable[[can.Message], bool]
) -> list[can.Message]:
    """Frames from the host's first one on (before it only the drives' power-on boot-ups,
    which may predate the box's receive thread)."""
    for k, m in enumerate(frames):
        if is_host(m):
            return frames[k:]
    return []


def wait_for_quiet(sniffers: list[Sniffer], quiet_s: float = 0.3, timeout_s: float = 5.0) -> None:
    """Wait until no sniffer has seen a new frame for ``quiet_s``."""
    t_end = time.monotonic() + timeout_s
    counts = [len(sn.snapshot()) for sn in sniffers]
    while time.monotonic() < t_end:
        time.sleep(quiet_s)
        now = [len(sn.snapshot()) for sn in sniffers]
        if now == counts:
            return
        counts = now
    raise AssertionError("the wire did not go quiet")


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_log_reads_back_with_the_same_frames(
    rig_factory: Callable[..., Rig], tmp_path: Path, suffix: str
) -> None:
    """Every frame the host sent is in the log once (as sent, ``is_rx`` False), every
    frame a drive sent once (received); nothing else: in particular no echo of the
    host's own frames (udp_multicast delivers them back to the sender)."""
    rig = rig_factory()
    box = rig.open_box(log_dir=tmp_path, log_suffix=suffix, run_name="t")
    box.bring_up()
    box.stream(JogSource(rig.limits, "j01r0", 30_000.0, 0.05))
    box.finish()
    rig.sim.stop()  # the drives fall silent (no more heartbeats): the wire's end is known
    wait_for_quiet(rig.sniffers)
    record_path = box.close()
    rig.box = None
    assert record_path == tmp_path / "t.json"
    for k, sn in enumerate(rig.sniffers):
        path = tmp_path / f"t_bus{k}{suffix}"
        logged = since_first_host_frame(list(can.LogReader(path)), lambda m: not m.is_rx)
        wire = since_first_host_frame(sn.snapshot(), lambda m: m.arbitration_id in HOST_IDS)
        assert logged, path
        assert {m.arbitration_id for m in wire} <= HOST_IDS | DRIVE_IDS
        echoes = [hex(m.arbitration_id) for m in logged if m.is_rx and m.arbitration_id in HOST_IDS]
        assert echoes == [], f"host frames logged as received: {echoes[:5]}"
        assert not [m for m in logged if not m.is_rx and m.arbitration_id in DRIVE_IDS]
        sent_log = by_id([m for m in logged if not m.is_rx], HOST_IDS)
        recv_log = by_id([m for m in logged if m.is_rx], DRIVE_IDS)
        sent_wire = by_id(wire, HOST_IDS)
        recv_wire = by_id(wire, DRIVE_IDS)
        # Exactly the same frames, in the same order per COB-ID: none missing, none twice.
        assert sent_log == sent_wire
        assert recv_log == recv_wire
        assert len(logged) == len(wire)
        # Streaming traffic is all there: every RPDO and TPDO of every node.
        nodes = [1, 2] if k == 0 else [3]
        assert len(sent_log[0x080]) >= 15  # the stream's (finish may add one)
        for n in nodes:
            assert len(sent_log[0x200 + n]) >= 15
            assert len(recv_log[0x180 + n]) >= 15
    record = json.loads(record_path.read_text())
    assert record["format"] == "hrm-run/1"
    assert record["motor_ids"] == ["j01r0", "j01r1", "j07r0"]
    assert record["streams"][0]["completed"] is True
    assert record["streams"][0]["stats"]["cycles"] == 15
    kinds = [e["kind"] for e in record["events"]]
    for kind in ("open", "bootup", "configured", "enabled", "stream_start", "stream_end"):
        assert kind in kinds
    assert [Path(p).name for p in record["can_logs"]] == [f"t_bus0{suffix}", f"t_bus1{suffix}"]
    assert record["can_log_errors"] == [] and min(record["can_log_frames"]) > 100
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_traffic_log_numbers_channels_whatever_the_interface_calls_them(
    tmp_path: Path, suffix: str
) -> None:
    path = tmp_path / f"x{suffix}"
    log = TrafficLog(path, channel=2)
    for k in range(3):
        msg = can.Message(arbitration_id=0x181 + k, data=bytes([k]), timestamp=1.0 + k)
        msg.channel = "hrm-drv-2fa1c93b77019999"  # trailing digits overflow a BLF channel
        log.on_message_received(msg)
    log.stop()
    back = list(can.LogReader(path))
    assert [m.arbitration_id for m in back] == [0x181, 0x182, 0x183]
    assert log.write_errors == 0


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_traffic_log_keeps_host_frames_once_and_drops_their_echo(
    tmp_path: Path, suffix: str
) -> None:
    path = tmp_path / f"echo{suffix}"
    log = TrafficLog(path)
    host = [
        (0x000, b"\x81\x00"),  # NMT reset
        (0x080, b""),  # SYNC
        (0x201, b"\x0f\x00\x10\x27\x00\x00"),  # RPDO1
        (0x305, b"\x01"),  # RPDO2
        (0x57F, b"\x01"),  # RPDO4
        (0x601, b"\x40\x41\x60\x00\x00\x00\x00\x00"),  # SDO upload request
        (0x77F, b"\x05"),  # host heartbeat
    ]
    drive = [
        (0x081, b"\x00\x00\x00\x00\x00\x00\x00\x00"),  # EMCY
        (0x181, b"\x37\x02\x10\x27\x00\x00"),  # TPDO1
        (0x281, b"\x01"),  # TPDO2
        (0x581, b"\x4b\x41\x60\x00\x37\x02\x00\x00"),  # SDO response
        (0x701, b"\x05"),  # drive heartbeat
    ]
    t = 1.0
    for cid, data in host:
        t += 0.001
        log.log_sent(
            can.Message(
                arbitration_id=cid, data=data, is_extended_id=False, timestamp=t, is_rx=False
            )
        )
        echo = can.Message(arbitration_id=cid, data=data, is_extended_id=False, timestamp=t)
        log.on_message_received(echo)  # udp_multicast: the frame comes back
    for cid, data in drive:
        t += 0.001
        log.on_message_received(
            can.Message(arbitration_id=cid, data=data, is_extended_id=False, timestamp=t)
        )
    log.stop()
    back = list(can.LogReader(path))
    assert [(m.arbitration_id, bytes(m.data), m.is_rx) for m in back] == [
        (cid, data, False) for cid, data in host
    ] + [(cid, data, True) for cid, data in drive]
    assert log.n_echoes == len(host) and log.n_frames == len(host) + len(drive)


def test_traffic_log_knows_the_hosts_heartbeat_id(tmp_path: Path) -> None:
    path = tmp_path / "hb.asc"
    log = TrafficLog(path, host_node_id=100)
    log.on_message_received(can.Message(arbitration_id=0x764, data=b"\x05", is_extended_id=False))
    log.on_message_received(can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False))
    log.stop()
    assert [m.arbitration_id for m in can.LogReader(path)] == [0x77F]  # node 127 is a drive here
    # A log not told the host id learns it from the heartbeats the host sends.
    path = tmp_path / "hb2.asc"
    log = TrafficLog(path)
    log.log_sent(can.Message(arbitration_id=0x764, data=b"\x05", is_extended_id=False, is_rx=False))
    log.on_message_received(can.Message(arbitration_id=0x764, data=b"\x05", is_extended_id=False))
    log.stop()
    assert [(m.arbitration_id, m.is_rx) for m in can.LogReader(path)] == [(0x764, False)]


@pytest.mark.parametrize("where", ["file", "under_file", "proc"])
def test_bad_log_directory_is_one_line_naming_it(tmp_path: Path, where: str) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("")
    bad = {"file": blocker, "under_file": blocker / "sub", "proc": Path("/proc/nope")}[where]
    with pytest.raises(DriverError) as info:
        TrafficLog(bad / "x.blf")
    msg = str(info.value)
    assert msg.startswith(f"log directory {bad}: ") and "\n" not in msg, msg


def test_writer_failure_is_counted_and_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = can.Logger

    class Failing:
        def __init__(self, path: str) -> None:
            self.inner = real(path)
            self.n = 0

        def on_message_received(self, msg: can.Message) -> None:
            self.n += 1
            if self.n > 2:
                raise OSError(28, "No space left on device")
            self.inner.on_message_received(msg)

        def stop(self) -> None:
            self.inner.stop()
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(can, "Logger", Failing)
    log = TrafficLog(tmp_path / "full.asc")
    for k in range(4):
        log.on_message_received(can.Message(arbitration_id=0x181, data=bytes([k])))
    log.stop()
    assert log.n_frames == 2 and log.write_errors == 3  # two frames and the close
    assert log.first_error is not None and log.first_error.startswith("full.asc: cannot log")
    assert "No space left on device" in log.first_error


def test_traffic_log_rejects_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(Exception, match=r"must end in \.asc or \.blf"):
        TrafficLog(tmp_path / "x.txt")


def test_bus_port_send_failure_names_the_bus() -> None:
    bus = can.Bus(interface="virtual", channel="port-fail")
    port = BusPort("can7", bus)
    bus.shutdown()
    with pytest.raises(BusSendError, match=r"^bus can7: send of 0x080 failed"):
        port.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    assert wait_until(lambda: True)
