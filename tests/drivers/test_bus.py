"""Each run's CAN log reads back with the frames that were on the wire; the run record."""

from __future__ import annotations

import json
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
    # the log is under test, not the SDO timing: with both cores busy an in-process
    # drive once took more than the production 0.5 s to answer the finish's SDO read
    rig = rig_factory(sdo_timeout_s=2.0)
    box = rig.open_box(log_dir=tmp_path, log_suffix=suffix, run_name="t")
    box.bring_up()
    jog = JogSource(rig.limits, "j01r0", 30_000.0, 0.05)
    box.stream(jog)
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
    assert record["streams"][0]["stats"]["cycles"] == jog.n_cycles >= 15  # ramps: issue 10
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


class EchoBus(can.BusABC):
    """A bus that delivers every frame sent on it back to its sender (as udp_multicast
    does), and lets a test inject frames of other senders."""

    def __init__(self) -> None:
        self.inbox: list[can.Message] = []
        super().__init__(channel="echo")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inbox.append(
            can.Message(
                arbitration_id=msg.arbitration_id, data=msg.data, is_extended_id=msg.is_extended_id
            )
        )

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def receiver_for(port: BusPort, log: TrafficLog, reports: list[tuple[Any, str]], armed: bool):
    from drivers.receive import BusReceiver

    class Net:  # canopen's part: nothing to say about these frames
        def notify(self, *args: Any) -> None: ...

    return BusReceiver(
        port,
        Net(),
        log,
        {1: "m0 (node 1)"},  # type: ignore[arg-type]
        lambda kind, text: reports.append((kind, text)),
        lambda: armed,
    )


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_log_keeps_our_frames_once_and_every_other_frame_on_the_wire(
    tmp_path: Path, suffix: str
) -> None:
    """Our own frames come back (udp_multicast) and are dropped: they were logged when
    sent.  Everything else is logged, in particular another master's frames with
    host-direction COB-IDs, error frames, remote frames and 29-bit frames."""
    from drivers.bus import BusPort

    path = tmp_path / f"echo{suffix}"
    log = TrafficLog(path)
    bus = EchoBus()
    port = BusPort("bus0", bus, log, echoes=True)
    reports: list[tuple[Any, str]] = []
    rx = receiver_for(port, log, reports, armed=False)
    host = [
        (0x000, b"\x81\x00"),  # NMT reset
        (0x080, b""),  # SYNC
        (0x201, b"\x0f\x00\x10\x27\x00\x00"),  # RPDO1
        (0x601, b"\x40\x41\x60\x00\x00\x00\x00\x00"),  # SDO upload request
        (0x77F, b"\x05"),  # host heartbeat
    ]
    for cid, data in host:
        port.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))
    for echo in list(bus.inbox):
        rx.on_message_received(echo)  # the bus gives them back: dropped
    others = [
        can.Message(arbitration_id=0x201, data=b"\x0f\x00\xdc\x05\x00\x00", is_extended_id=False),
        can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),  # a second SYNC
        can.Message(arbitration_id=0x181, data=b"\x37\x02\x10\x27\x00\x00"),  # 29-bit
        can.Message(arbitration_id=0x701, is_remote_frame=True, is_extended_id=False),
        can.Message(is_error_frame=True),
        can.Message(arbitration_id=0x705, data=b"\x05", is_extended_id=False),  # node 5
    ]
    for m in others:
        rx.on_message_received(m)
    log.stop()
    back = list(can.LogReader(path))
    assert [(m.arbitration_id, bytes(m.data), m.is_rx) for m in back[: len(host)]] == [
        (cid, data, False) for cid, data in host
    ]
    assert len(back) == len(host) + len(others)
    assert [m.arbitration_id for m in back[len(host) :] if not m.is_error_frame] == [
        0x201,
        0x080,
        0x181,
        0x701,
        0x705,
    ]
    assert sum(m.is_error_frame for m in back) == 1
    t = rx.traffic
    assert t.echoes_dropped == len(host)
    assert t.foreign == {0x201: 1, 0x080: 1} and t.extended == {0x181: 1}
    assert t.unconfigured == {0x705: 1} and t.remote_frames == 1 and t.error_frames == 1
    assert reports == []  # not armed: counted, no stop cause


def test_a_foreign_rpdo_for_our_node_is_a_stop_cause_naming_the_cob_id(tmp_path: Path) -> None:
    from drivers.bus import BusPort
    from drivers.safety.causes import StopKind

    log = TrafficLog(tmp_path / "f.asc")
    port = BusPort("bus0", EchoBus(), log, echoes=True)
    reports: list[tuple[Any, str]] = []
    rx = receiver_for(port, log, reports, armed=True)
    port.send(
        can.Message(arbitration_id=0x201, data=b"\x0f\x00\x00\x00\x00\x00", is_extended_id=False)
    )
    rx.on_message_received(port.bus.inbox[0])  # our own echo: fine
    rx.on_message_received(
        can.Message(arbitration_id=0x201, data=b"\x0f\x00\xdc\x05\x00\x00", is_extended_id=False)
    )
    rx.on_message_received(
        can.Message(arbitration_id=0x209, data=b"\x0f\x00", is_extended_id=False)
    )  # not our node
    rx.on_message_received(
        can.Message(arbitration_id=0x27F, data=b"\x0f\x00", is_extended_id=False)
    )  # node 127 is not ours either (it was taken for the host heartbeat, 0x77F)
    log.stop()
    assert len(reports) == 1
    kind, text = reports[0]
    assert kind is StopKind.FOREIGN
    assert "RPDO1 0x201" in text and "m0 (node 1)" in text and "another master" in text


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
    with pytest.raises(Exception, match=r"must end in \.blf, \.asc, \.log, \.trc"):
        TrafficLog(tmp_path / "x.txt")


def test_bus_port_send_failure_names_the_bus() -> None:
    bus = can.Bus(interface="virtual", channel="port-fail")
    port = BusPort("can7", bus)
    bus.shutdown()
    with pytest.raises(BusSendError, match=r"^bus can7: send of 0x080 failed"):
        port.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    assert wait_until(lambda: True)


class FullQueueBus(can.BusABC):
    """A bus whose transmit queue refuses the frames of ``full_ids`` (after waiting their
    timeout, as socketcan does when its queue stays full) and takes the others."""

    def __init__(self, full_ids: set[int]) -> None:
        super().__init__(channel="full-queue")
        self.full_ids = full_ids
        self.sent: list[int] = []
        self.waited_s = 0.0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id in self.full_ids:
            self.waited_s += timeout or 0.0  # the time it was allowed to wait, and waits
            time.sleep(timeout or 0.0)
            raise can.CanOperationError("Transmit buffer full")
        self.sent.append(msg.arbitration_id)

    def _recv_internal(self, timeout: float | None) -> tuple[None, bool]:
        return None, False


def test_a_quick_stop_burst_keeps_going_past_a_failed_frame_within_its_budget() -> None:
    """``keep_going`` (the quick stop's burst): a frame the bus refuses does not keep the
    frames after it from going out, the whole batch waits at most ``timeout_s``, and the
    failures are raised together naming the first (found by a red-team helper: the rest
    of the bus was left without its quick stop for two periods)."""
    from drivers.protocol.batch import from_messages

    bus = FullQueueBus({0x202, 0x203})
    port = BusPort("can0", bus)
    ids = [0x201, 0x202, 0x203, 0x204]
    frames = from_messages([can.Message(arbitration_id=i, data=b"\x02\x00", is_extended_id=False)
                            for i in ids])  # fmt: skip
    with pytest.raises(BusSendError, match=r"^bus can0: send of 0x202 .* failed \(\+1 more\)$"):
        port.send_batch(frames, 0.002, keep_going=True)
    assert bus.sent == [0x201, 0x204] and port.n_sent == 2
    assert bus.waited_s <= 0.002  # the second refused frame got what was left of it
    bus.sent.clear()
    with pytest.raises(BusSendError):  # without it, the first failure ends the batch
        port.send_batch(frames, 0.002)
    assert bus.sent == [0x201]
    bus.shutdown()
