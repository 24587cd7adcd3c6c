"""Byte-level conformance of one DriveSim, fed frames directly (no bus, simulated clock)."""

from __future__ import annotations

import itertools
import struct

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.protocol import cia301, cia402
from sim_bus.drive import DriveParams, DriveSim, object_table

NODE = 5
S = cia402.State402


class Rig:
    def __init__(self, **params: float) -> None:
        self.sent: list[can.Message] = []
        self.t = 0.0
        p = DriveParams(
            max_velocity_counts_per_s=params.get("vmax", 1.0e5),
            max_accel_counts_per_s2=params.get("amax", 1.0e7),
            quick_stop_decel_counts_per_s2=params.get("qs", 2.0e7),
            initial_position_counts=int(params.get("p0", 0)),
        )
        self.d = DriveSim(NODE, self.sent.append, p, now=0.0)

    def rx(self, msg: can.Message, dt: float = 0.0) -> list[can.Message]:
        n = len(self.sent)
        self.t += dt
        self.d.handle(msg, self.t)
        return self.sent[n:]

    def tick(self, dt: float) -> list[can.Message]:
        n = len(self.sent)
        self.t += dt
        self.d.tick(self.t)
        return self.sent[n:]

    def sdo(self, payload: bytes) -> bytes:
        out = self.rx(can.Message(arbitration_id=0x600 + NODE, data=payload, is_extended_id=False))
        sdo = [m for m in out if m.arbitration_id == 0x580 + NODE]
        assert len(sdo) == 1, out
        return bytes(sdo[0].data)

    def write(self, index: int, sub: int, value: bytes) -> bytes:
        return self.sdo(bytes(cia301.make_sdo_download_expedited(NODE, index, sub, value).data))

    def read(self, index: int, sub: int = 0) -> bytes:
        return self.sdo(bytes(cia301.make_sdo_upload_request(NODE, index, sub).data))

    def cw(self, word: int) -> None:
        assert self.write(cia402.OD_CONTROLWORD, 0, struct.pack("<H", word))[0] == 0x60

    def statusword(self) -> int:
        r = self.read(cia402.OD_STATUSWORD)
        return struct.unpack_from("<H", r, 4)[0]

    def state(self) -> S:
        return cia402.decode_state(self.statusword())

    def operational(self) -> None:
        self.rx(cia301.make_nmt(cia301.NMT_START_REMOTE_NODE, NODE))

    def sync(self, dt: float = 0.01) -> list[can.Message]:
        return self.rx(cia301.make_sync(), dt)

    def enable(self) -> None:
        self.write(cia402.OD_MODES_OF_OPERATION, 0, b"\x08")
        for w in (cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE_OPERATION):
            self.cw(w)
        assert self.state() == S.OPERATION_ENABLED


def abort_code(resp: bytes) -> int:
    assert resp[0] == 0x80, resp.hex()
    return struct.unpack_from("<I", resp, 4)[0]


def test_bootup_frame_and_reset_node() -> None:
    r = Rig()
    assert [(m.arbitration_id, bytes(m.data)) for m in r.sent] == [(0x705, b"\x00")]
    r.write(cia301.OD_PRODUCER_HEARTBEAT_TIME, 0, struct.pack("<H", 50))
    out = r.rx(cia301.make_nmt(cia301.NMT_RESET_NODE, 0))
    assert [(m.arbitration_id, bytes(m.data)) for m in out] == [(0x705, b"\x00")]
    assert r.read(cia301.OD_PRODUCER_HEARTBEAT_TIME)[4:6] == b"\x00\x00"  # back to default
    assert r.rx(cia301.make_nmt(cia301.NMT_RESET_NODE, 6)) == []  # another node
    bad = can.Message(arbitration_id=0, data=b"\x81", is_extended_id=False)
    assert r.rx(bad) == []  # wrong DLC ignored


def test_heartbeat_producer_period_and_state() -> None:
    r = Rig()
    assert r.write(cia301.OD_PRODUCER_HEARTBEAT_TIME, 0, struct.pack("<H", 20)) == bytes.fromhex(
        "6017100000000000"
    )
    beats: list[tuple[float, bytes]] = []
    for _ in range(100):
        for m in r.tick(0.001):
            beats.append((r.t, bytes(m.data)))
    assert len(beats) == 5
    assert {b for _t, b in beats} == {b"\x7f"}
    r.operational()
    beats = [bytes(m.data) for _ in range(25) for m in r.tick(0.001)]
    assert beats == [b"\x05"]


def test_a_heartbeat_due_within_the_early_window_goes_out_now_and_the_next_stays_on_grid() -> None:
    """What the box does after a SYNC (a heartbeat due before the next SYNC rides with the
    TPDOs): sent up to ``heartbeat_early_s`` early, the producer's 100 ms grid unchanged."""
    r = Rig()
    r.write(cia301.OD_PRODUCER_HEARTBEAT_TIME, 0, struct.pack("<H", 100))  # at t = 0: due 0.1
    hb = 0x700 + NODE
    n = len(r.sent)  # after the boot-up frame
    r.t = 0.085
    r.d.tick(r.t, heartbeat_early_s=0.01)  # due in 15 ms: not yet
    assert r.sent[n:] == []
    r.t = 0.095
    n = len(r.sent)
    r.d.tick(r.t, heartbeat_early_s=0.01)  # due in 5 ms: now
    assert [m.arbitration_id for m in r.sent[n:]] == [hb]
    assert r.d.next_deadline() == pytest.approx(0.2)  # on the grid, not 0.195
    r.t = 0.19
    n = len(r.sent)
    r.d.tick(r.t)  # without the window: not before it is due
    assert r.sent[n:] == []
    r.t = 0.2
    r.d.tick(r.t)
    assert [m.arbitration_id for m in r.sent[n:]] == [hb]


def test_sdo_expedited_upload_of_every_readable_object() -> None:
    r = Rig()
    for (index, sub), var in object_table().items():
        resp = r.read(index, sub)
        if var.access_type == "wo":
            assert abort_code(resp) == cia301.SDO_ABORT_WRITE_ONLY
            continue
        size = len(var) // 8 if var.fixed_size else None
        if size is not None and size <= 4:
            assert resp[0] == 0x43 | ((4 - size) << 2), (hex(index), sub, resp.hex())
            assert resp[1:4] == struct.pack("<HB", index, sub)
        else:
            assert resp[0] == 0x41


def test_sdo_segmented_upload_of_device_name() -> None:
    r = Rig()
    resp = r.read(cia301.OD_MANUFACTURER_DEVICE_NAME)
    assert resp[0] == 0x41
    size = struct.unpack_from("<I", resp, 4)[0]
    data, toggle = b"", 0
    while True:
        seg = r.sdo(bytes((0x60 | (toggle << 4),)) + bytes(7))
        assert (seg[0] >> 4) & 1 == toggle
        n = 7 - ((seg[0] >> 1) & 7)
        data += seg[1 : 1 + n]
        toggle ^= 1
        if seg[0] & 1:
            break
    assert len(data) == size and data == b"HRM rope drive"
    # a wrong toggle bit aborts with 0x05030000
    r.read(cia301.OD_MANUFACTURER_DEVICE_NAME)
    assert abort_code(r.sdo(bytes((0x70,)) + bytes(7))) == cia301.SDO_ABORT_TOGGLE_BIT


def test_sdo_segmented_download() -> None:
    r = Rig()
    # initiate segmented download of 4 bytes to 0x607A (allowed: size given)
    init = bytes((0x21,)) + struct.pack("<HBI", cia402.OD_TARGET_POSITION, 0, 4)
    assert r.sdo(init) == bytes.fromhex("607a600000000000")
    seg = bytes((0x00 | (3 << 1) | 1,)) + struct.pack("<i", -77) + bytes(3)
    assert r.sdo(seg) == bytes.fromhex("2000000000000000")
    assert r.read(cia402.OD_TARGET_POSITION)[4:8] == struct.pack("<i", -77)


@pytest.mark.parametrize(
    ("payload", "code"),
    [
        (cia301.make_sdo_upload_request(NODE, 0x2000, 0).data, cia301.SDO_ABORT_NO_OBJECT),
        (cia301.make_sdo_upload_request(NODE, 0x607D, 5).data, cia301.SDO_ABORT_NO_SUBINDEX),
        (
            cia301.make_sdo_download_expedited(NODE, cia402.OD_STATUSWORD, 0, b"\x00\x00").data,
            cia301.SDO_ABORT_READ_ONLY,
        ),
        (
            cia301.make_sdo_download_expedited(NODE, cia301.OD_DEVICE_TYPE, 0, b"\x00" * 4).data,
            cia301.SDO_ABORT_READ_ONLY,
        ),
        (
            cia301.make_sdo_download_expedited(
                NODE, cia402.OD_TARGET_POSITION, 0, b"\x01\x02"
            ).data,
            cia301.SDO_ABORT_LENGTH_TOO_LOW,
        ),
        (
            cia301.make_sdo_download_expedited(
                NODE, cia402.OD_MODES_OF_OPERATION, 0, b"\x01\x00"
            ).data,
            cia301.SDO_ABORT_LENGTH_TOO_HIGH,
        ),
        (
            cia301.make_sdo_download_expedited(NODE, cia402.OD_MODES_OF_OPERATION, 0, b"\x03").data,
            cia301.SDO_ABORT_INVALID_VALUE,
        ),
        (
            cia301.make_sdo_download_expedited(
                NODE, cia402.OD_QUICK_STOP_OPTION_CODE, 0, b"\x09\x00"
            ).data,
            cia301.SDO_ABORT_INVALID_VALUE,
        ),
        (
            cia301.make_sdo_download_expedited(NODE, 0x1400, 2, b"\xf5").data,
            cia301.SDO_ABORT_INVALID_VALUE,
        ),
        (
            cia301.make_sdo_download_expedited(NODE, 0x1600, 1, b"\x20\x00\x7a\x60").data,
            cia301.SDO_ABORT_UNSUPPORTED_ACCESS,
        ),
        (bytes((0xE0,)) + bytes(7), cia301.SDO_ABORT_COMMAND_SPECIFIER),
        (bytes((0xC0,)) + bytes(7), cia301.SDO_ABORT_COMMAND_SPECIFIER),  # block download
        (bytes((0x00,)) + bytes(7), cia301.SDO_ABORT_COMMAND_SPECIFIER),  # segment, no transfer
    ],
)
def test_sdo_abort_codes(payload: bytes, code: int) -> None:
    r = Rig()
    resp = r.sdo(bytes(payload))
    assert abort_code(resp) == code
    if payload[0] >> 5 in (1, 2):
        assert resp[1:4] == bytes(payload)[1:4]  # index and sub-index echoed


def test_sdo_frame_of_wrong_length_is_ignored() -> None:
    r = Rig()
    short = can.Message(arbitration_id=0x600 + NODE, data=b"\x40\x41\x60", is_extended_id=False)
    assert r.rx(short) == []
    assert r.state() == S.SWITCH_ON_DISABLED  # still answers afterwards


@settings(max_examples=60, deadline=None)
@given(st.binary(min_size=0, max_size=8), st.sampled_from([0x000, 0x080, 0x205, 0x605, 0x77F]))
def test_garbage_frames_never_crash(data: bytes, cob: int) -> None:
    r = Rig()
    r.write(cia301.OD_CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", 0x7F0064))
    r.operational()
    r.rx(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
    r.sync()
    r.tick(0.5)
    assert r.state() in set(S)


# ---------------------------------------------------------------- CiA 402 state machine
TRANSITIONS = [
    # (start-up commands, command, expected state)
    ([], cia402.CW_SHUTDOWN, S.READY_TO_SWITCH_ON),  # 2
    ([cia402.CW_SHUTDOWN], cia402.CW_SWITCH_ON, S.SWITCHED_ON),  # 3
    (
        [cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON],
        cia402.CW_ENABLE_OPERATION,
        S.OPERATION_ENABLED,
    ),  # 4
    ([cia402.CW_SHUTDOWN], cia402.CW_ENABLE_OPERATION, S.OPERATION_ENABLED),  # 3 + 4
    (
        [cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE_OPERATION],
        cia402.CW_DISABLE_OPERATION,
        S.SWITCHED_ON,
    ),  # 5
    ([cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON], cia402.CW_SHUTDOWN, S.READY_TO_SWITCH_ON),  # 6
    ([cia402.CW_SHUTDOWN], cia402.CW_DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),  # 7
    ([cia402.CW_SHUTDOWN], cia402.CW_QUICK_STOP, S.SWITCH_ON_DISABLED),  # 7
    (
        [cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE_OPERATION],
        cia402.CW_SHUTDOWN,
        S.READY_TO_SWITCH_ON,
    ),  # 8
    (
        [cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON, cia402.CW_ENABLE_OPERATION],
        cia402.CW_DISABLE_VOLTAGE,
        S.SWITCH_ON_DISABLED,
    ),  # 9
    (
        [cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON],
        cia402.CW_DISABLE_VOLTAGE,
        S.SWITCH_ON_DISABLED,
    ),  # 10
    ([cia402.CW_SHUTDOWN, cia402.CW_SWITCH_ON], cia402.CW_QUICK_STOP, S.SWITCH_ON_DISABLED),  # 10
    ([], cia402.CW_SWITCH_ON, S.SWITCH_ON_DISABLED),  # no transition
    ([], cia402.CW_ENABLE_OPERATION, S.SWITCH_ON_DISABLED),  # no transition
]


@pytest.mark.parametrize(("setup", "command", "expected"), TRANSITIONS)
def test_state_machine_transitions(setup: list[int], command: int, expected: S) -> None:
    r = Rig()
    r.write(cia402.OD_MODES_OF_OPERATION, 0, b"\x08")
    for w in setup:
        r.cw(w)
    r.cw(command)
    sw = r.statusword()
    assert cia402.decode_state(sw) == expected
    assert sw & 0x006F == cia402.STATUSWORD_OF_STATE[expected] & 0x006F


@pytest.mark.parametrize(
    ("option", "after_stop"),
    [(0, S.SWITCH_ON_DISABLED), (2, S.SWITCH_ON_DISABLED), (6, S.QUICK_STOP_ACTIVE)],
)
def test_quick_stop_per_option_code(option: int, after_stop: S) -> None:
    r = Rig(vmax=1e5, amax=1e7, qs=1e6)
    r.write(cia402.OD_QUICK_STOP_OPTION_CODE, 0, struct.pack("<h", option))
    r.write(cia402.OD_FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", 0xFFFFFFFF))
    r.operational()
    r.enable()
    r.write(cia402.OD_TARGET_POSITION, 0, struct.pack("<i", 50_000))
    for _ in range(5):
        r.sync()
    assert r.d.velocity > 0
    r.cw(cia402.CW_QUICK_STOP)  # 11
    if option == 0:
        assert r.state() == S.SWITCH_ON_DISABLED
        return
    assert r.state() == S.QUICK_STOP_ACTIVE
    assert r.statusword() & cia402.SW_QUICK_STOP == 0
    for _ in range(30):
        r.sync()
    assert r.d.velocity == 0.0
    assert r.state() == after_stop  # 12 for options 1..4
    if option == 6:
        r.cw(cia402.CW_ENABLE_OPERATION)  # 16
        assert r.state() == S.OPERATION_ENABLED


def test_csp_following_on_sync_with_tpdo_bytes() -> None:
    r = Rig(vmax=1e6, amax=1e9, p0=100)
    r.operational()
    r.enable()
    # RPDO (controlword + target) takes effect on the next SYNC; TPDO follows each SYNC
    r.rx(cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, 600))
    out = r.sync()
    tpdo = [m for m in out if m.arbitration_id == 0x185]
    assert (
        len(tpdo) == 1 and bytes(tpdo[0].data) == cia402.make_tpdo_feedback(NODE, 0x1237, 100).data
    )
    out = r.sync()
    tpdo = [m for m in out if m.arbitration_id == 0x185]
    assert cia402.parse_tpdo(tpdo[0].data) == (0x1237, 600)


def test_velocity_limit_and_software_position_limit() -> None:
    r = Rig(vmax=1e5, amax=1e9)
    r.write(cia402.OD_SOFTWARE_POSITION_LIMIT, 2, struct.pack("<i", 3000))
    r.write(cia402.OD_FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", 0xFFFFFFFF))
    r.operational()
    r.enable()
    r.rx(cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, 10_000))
    r.sync()
    positions = []
    for _ in range(6):
        out = r.sync()
        positions.append(cia402.parse_tpdo(next(m for m in out if m.arbitration_id == 0x185).data))
    steps = [b[1] - a[1] for a, b in itertools.pairwise(positions)]
    assert max(steps) <= 1000  # 1e5 counts/s * 10 ms
    assert positions[-1][1] == 3000  # clamped at the max limit
    assert positions[-1][0] & cia402.SW_INTERNAL_LIMIT_ACTIVE


def test_following_error_faults_with_emcy_and_fault_reset() -> None:
    r = Rig(vmax=1e5, amax=1e9)
    r.write(cia402.OD_FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", 500))
    r.operational()
    r.enable()
    r.rx(cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, 100_000))
    r.sync()
    out = r.sync()
    emcy = [m for m in out if m.arbitration_id == 0x085]
    assert [bytes(m.data) for m in emcy] == [bytes.fromhex("1186010000000000")]
    sw = cia402.parse_tpdo(next(m for m in out if m.arbitration_id == 0x185).data)[0]
    assert cia402.decode_state(sw) in (S.FAULT_REACTION_ACTIVE, S.FAULT)
    for _ in range(5):
        r.sync()
    assert r.state() == S.FAULT
    assert r.read(cia402.OD_ERROR_CODE)[4:6] == b"\x11\x86"
    # fault reset on the rising edge of bit 7 (transition 15), EMCY 0x0000
    n = len(r.sent)
    r.cw(cia402.CW_FAULT_RESET)
    assert r.state() == S.SWITCH_ON_DISABLED
    assert any(m.arbitration_id == 0x085 and bytes(m.data) == bytes(8) for m in r.sent[n:])
    assert r.read(cia301.OD_ERROR_REGISTER)[4] == 0


def test_host_heartbeat_loss_quick_stops_with_emcy() -> None:
    r = Rig(vmax=1e5, amax=1e7, qs=1e7)
    r.write(cia301.OD_CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", 0x7F0064))  # node 127, 100 ms
    r.operational()
    r.enable()
    hb = cia301.make_heartbeat(0x7F, cia301.NMT_STATE_OPERATIONAL)
    for _ in range(10):  # host alive: nothing happens
        r.rx(hb, 0.05)
        r.tick(0.0)
    assert r.state() == S.OPERATION_ENABLED
    out: list[can.Message] = []
    for _ in range(30):
        out += r.tick(0.005)
    emcy = [bytes(m.data) for m in out if m.arbitration_id == 0x085]
    assert emcy and emcy[0][:2] == b"\x30\x81" and emcy[0][2] & 0x10
    assert r.state() in (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED)
    for _ in range(20):
        r.tick(0.02)
    assert r.state() == S.SWITCH_ON_DISABLED


def test_rpdo_too_short_gives_emcy_8210_and_is_not_applied() -> None:
    r = Rig()
    r.operational()
    r.enable()
    out = r.rx(can.Message(arbitration_id=0x205, data=b"\x0f\x00\x01", is_extended_id=False))
    assert [bytes(m.data) for m in out if m.arbitration_id == 0x085] == [
        bytes.fromhex("1082000000000000")
    ]
    r.sync()
    assert r.state() == S.OPERATION_ENABLED


def test_pdo_remapping() -> None:
    r = Rig(vmax=1e7, amax=1e10)
    # mapping while the PDO is valid: refused
    assert abort_code(r.write(0x1600, 0, b"\x00")) == cia301.SDO_ABORT_UNSUPPORTED_ACCESS
    assert r.write(0x1400, 1, struct.pack("<I", 0x80000205))[0] == 0x60
    assert r.write(0x1600, 0, b"\x00")[0] == 0x60
    assert r.write(0x1600, 1, struct.pack("<I", 0x607A0020))[0] == 0x60
    # an unmappable object is refused as the entry is written (test_pdo.py: every kind)
    assert abort_code(r.write(0x1600, 2, struct.pack("<I", 0x10170010))) == (
        cia301.SDO_ABORT_NOT_MAPPABLE
    )
    assert r.write(0x1600, 0, b"\x01")[0] == 0x60
    assert r.write(0x1400, 1, struct.pack("<I", 0x305))[0] == 0x60  # new COB-ID, valid
    r.operational()
    r.enable()
    r.rx(can.Message(arbitration_id=0x305, data=struct.pack("<i", 4321), is_extended_id=False))
    r.sync()
    out = r.sync()
    assert cia402.parse_tpdo(next(m for m in out if m.arbitration_id == 0x185).data)[1] == 4321
    # the old COB-ID no longer reaches the drive
    assert 0x205 not in r.d.cob_ids() and 0x305 in r.d.cob_ids()


def test_tpdo_every_second_sync_and_no_pdo_when_preoperational() -> None:
    r = Rig()
    assert [m for m in r.sync() if m.arbitration_id == 0x185] == []  # pre-operational
    r.write(0x1800, 2, b"\x02")
    r.operational()
    counts = [len([m for m in r.sync() if m.arbitration_id == 0x185]) for _ in range(6)]
    assert counts == [0, 1, 0, 1, 0, 1]


def test_jammed_motor_faults_by_following_error_once_the_target_moves() -> None:
    r = Rig(vmax=1e6, amax=1e10)
    r.write(cia402.OD_FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", 2000))
    r.operational()
    r.enable()
    r.d.jammed = True
    target = 0
    faulted_at = None
    for k in range(10):
        target += 500
        r.rx(cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, target))
        out = r.sync()
        if any(m.arbitration_id == 0x085 for m in out):
            faulted_at = k
            break
    assert faulted_at is not None and 3 <= faulted_at <= 5  # 2000-count window, 500 per cycle
    assert r.d.position_counts == 0


def test_parameters_written_while_streaming_take_effect_at_the_next_frame() -> None:
    """The drive keeps what it derives from its parameters between writes (the object
    dictionary's generation): every SDO write and reset must still act at once."""
    r = Rig(vmax=1e6, amax=1e10)
    r.operational()
    r.enable()
    target = 0
    for _ in range(3):  # warm every cache: TPDO each SYNC, steps of one 10 ms period
        target += 100
        r.rx(cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, target))
        assert len([m for m in r.sync() if m.arbitration_id == 0x185]) == 1
    # transmission type 2: a TPDO every second SYNC from now on
    assert r.write(0x1800, 2, b"\x02")[0] == 0x60
    assert [len([m for m in r.sync() if m.arbitration_id == 0x185]) for _ in range(4)] in (
        [0, 1, 0, 1],
        [1, 0, 1, 0],
    )
    assert r.write(0x1800, 2, b"\x01")[0] == 0x60
    # a new SYNC COB-ID: the old one no longer triggers a TPDO, the new one does
    assert r.write(cia301.OD_COB_ID_SYNC, 0, struct.pack("<I", 0x81))[0] == 0x60
    assert [m for m in r.sync() if m.arbitration_id == 0x185] == []
    sync_81 = can.Message(arbitration_id=0x81, data=b"", is_extended_id=False)
    assert len([m for m in r.rx(sync_81, 0.01) if m.arbitration_id == 0x185]) == 1
    assert 0x81 in r.d.cob_ids() and 0x80 not in r.d.cob_ids()
    # a heartbeat consumer added now is watched from now on
    assert 127 not in r.d.monitored_heartbeats()
    r.write(cia301.OD_CONSUMER_HEARTBEAT_TIME, 1, struct.pack("<I", 0x7F0064))
    assert r.d.monitored_heartbeats() == {127: 0.1}
    r.rx(cia301.make_heartbeat(0x7F, cia301.NMT_STATE_OPERATIONAL))
    out: list[can.Message] = []
    for _ in range(30):
        out += r.tick(0.005)
    assert any(bytes(m.data)[:2] == b"\x30\x81" for m in out if m.arbitration_id == 0x085)
    # reset communication: the defaults again (SYNC 0x80, no consumer)
    r.rx(cia301.make_nmt(cia301.NMT_RESET_COMMUNICATION, NODE))
    assert 0x80 in r.d.cob_ids() and r.d.monitored_heartbeats() == {}


def test_interpolation_period_and_following_window_written_while_streaming() -> None:
    r = Rig(vmax=1e5, amax=1e10)
    r.write(cia402.OD_FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", 0xFFFFFFFF))
    r.operational()
    r.enable()
    r.rx(cia402.make_rpdo_target(NODE, cia402.CW_ENABLE_OPERATION, 100_000))
    r.sync()
    p0 = cia402.parse_tpdo(next(m for m in r.sync() if m.arbitration_id == 0x185).data)[1]
    p1 = cia402.parse_tpdo(next(m for m in r.sync() if m.arbitration_id == 0x185).data)[1]
    assert p1 - p0 == 1000  # 1e5 counts/s for 10 ms
    assert r.write(cia402.OD_INTERPOLATION_TIME_PERIOD, 1, b"\x05")[0] == 0x60  # 5 ms
    p2 = cia402.parse_tpdo(next(m for m in r.sync() if m.arbitration_id == 0x185).data)[1]
    assert p2 - p1 == 500
    assert r.d.interpolation_period_s == pytest.approx(0.005)
    # a following-error window tighter than the error already there: fault at the next SYNC
    assert r.write(cia402.OD_FOLLOWING_ERROR_WINDOW, 0, struct.pack("<I", 10))[0] == 0x60
    out = r.sync()
    assert [bytes(m.data)[:2] for m in out if m.arbitration_id == 0x085] == [b"\x11\x86"]


def test_a_host_heartbeat_regained_during_a_fault_reaction_sends_no_error_reset() -> None:
    """A drive still reacting to its fault keeps its error register and sends no 'error
    reset' EMCY when the host's heartbeat comes back (the host would read it as clear)."""
    sent: list[can.Message] = []
    d = DriveSim(5, sent.append)
    d.od.values[(cia301.OD_CONSUMER_HEARTBEAT_TIME, 1)] = (0x7F << 16) | 100
    d.od.generation += 1
    d.nmt.on_heartbeat(0x7F, b"\x05", 0.0)
    d.state_machine.state = cia402.State402.OPERATION_ENABLED
    d.motion.velocity = 1000.0
    d.state_machine.fault(0x8611, 0.05, "following error")
    assert d.state_machine.state is cia402.State402.FAULT_REACTION_ACTIVE
    d.nmt.tick(0.2)  # the host's heartbeat lost during the reaction
    d.nmt.on_heartbeat(0x7F, b"\x05", 0.25)  # and back, still decelerating
    emcys = [cia301.parse_emcy(5, m.data) for m in sent if 0x80 < m.arbitration_id < 0x100]
    assert [(e.error_code, e.error_register) for e in emcys] == [(0x8611, 0x01), (0x8130, 0x11)]
    assert d.error_register == cia301.ERR_REG_GENERIC
