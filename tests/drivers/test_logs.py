"""Each run's CAN log reads back with the frames that were on the wire; the run record."""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from drivers.setpoints import JogSource
from drivers.traffic import BusPort, BusSendError, TrafficLog
from tests.drivers.driver_rig import Rig, wait_until

HOST_IDS = {0x000, 0x080} | set(range(0x201, 0x280)) | set(range(0x601, 0x680)) | {0x77F}
DRIVE_IDS = set(range(0x081, 0x100)) | set(range(0x181, 0x200)) | set(range(0x581, 0x600))
DRIVE_IDS |= set(range(0x701, 0x77F))


def by_id(frames: list[can.Message], ids: set[int]) -> dict[int, list[bytes]]:
    out: dict[int, list[bytes]] = defaultdict(list)
    for m in frames:
        if m.arbitration_id in ids:
            out[m.arbitration_id].append(bytes(m.data))
    return out


def contiguous_in(part: list[bytes], whole: list[bytes]) -> bool:
    n = len(part)
    return any(whole[i : i + n] == part for i in range(len(whole) - n + 1))


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_log_reads_back_with_the_same_frames(
    rig_factory: Callable[..., Rig], tmp_path: Path, suffix: str
) -> None:
    rig = rig_factory()
    box = rig.open_box(log_dir=tmp_path, log_suffix=suffix, run_name="t")
    box.bring_up()
    box.stream(JogSource(rig.limits, "j01r0", 30_000.0, 0.05))
    box.finish()
    record_path = box.close()
    rig.box = None
    assert record_path == tmp_path / "t.json"
    for k, sn in enumerate(rig.sniffers):
        path = tmp_path / f"t_bus{k}{suffix}"
        logged = list(can.LogReader(path))
        assert logged, path
        wire = sn.snapshot()
        sent_log = by_id([m for m in logged if not m.is_rx], HOST_IDS)
        recv_log = by_id([m for m in logged if m.is_rx], DRIVE_IDS)
        sent_wire = by_id(wire, HOST_IDS)
        recv_wire = by_id(wire, DRIVE_IDS)
        assert set(sent_log) == set(sent_wire)
        for cid, seq in sent_log.items():
            assert seq == sent_wire[cid][: len(seq)] or contiguous_in(seq, sent_wire[cid]), hex(cid)
            assert len(seq) >= len(sent_wire[cid]) - 1, hex(cid)
        assert set(recv_log) <= set(recv_wire)
        for cid, seq in recv_log.items():
            assert contiguous_in(seq, recv_wire[cid]), hex(cid)
            assert len(seq) >= len(recv_wire[cid]) - 3, hex(cid)
        # Streaming traffic is all there: every RPDO and TPDO of every node.
        nodes = [1, 2] if k == 0 else [3]
        assert len(sent_log[0x080]) == 15 + 1  # stream + disable operation
        for n in nodes:
            assert len(sent_log[0x200 + n]) >= 16
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
