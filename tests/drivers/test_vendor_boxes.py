"""Boxes of vendor drives on the simulator: each simulated drive has its device file's
object dictionary; the bring-up writes the SDO overlay first, remaps the PDOs in CiA 301's
order within the file's limits, writes 0x60C2 in the drive's encoding and refuses a drive
whose identity is not the configuration's before anything is written; a jog streams."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import can
import pytest

from drivers.bringup import IdentityMismatchError
from drivers.config import BoxConfig, box_config_from_dict
from drivers.protocol import cia301
from drivers.safety.subset import ActuationSubset
from drivers.session import DriveSession
from drivers.sources import HoldSource, JogSource
from hrm_ctrl.ropes.actuation import Actuation
from sim_bus.box import SimBox
from sim_bus.drive import DriveSim
from sim_bus.in_process import IN_PROCESS_MISSING_TPDO_CYCLES
from tests.drivers.driver_rig import RIG_LISTEN_S, Sniffer

VENDOR = Path(__file__).parent / "vendor_eds"
EPOS4 = VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"
C5E = VENDOR / "C5-E-2-09.eds"
FAULHABER = VENDOR / "605.3150.68-B-EK-2-60.eds"
NODES = {"j01r0": 1, "j01r1": 2, "j01r2": 3}
UNIT_INCREMENTS = {"sdo": {"0x60A8": 0x00B50000}}  # the C5-E counts in 0.1 deg by default

#: The CSP-capable files: (device file, the rest of the [drives] table)
CSP_BOXES: dict[str, dict[str, Any]] = {
    "hrm_drive.eds": {},
    "epos4": {"device_file": str(EPOS4)},
    "c5-e": {"device_file": str(C5E), **UNIT_INCREMENTS},
}

#: 0x6085 units per count/s^2 on each: hrm's EDS counts; the C5-E's acceleration is its
#: velocity unit (rpm) per second at 2000 counts a revolution (0x608F); the EPOS4's 0x60AA
#: unit is not converted (not written)
QUICK_STOP_PER_COUNT_S2: dict[str, float | None] = {
    "hrm_drive.eds": 1.0,
    "epos4": None,
    "c5-e": 60 / 2000,
}


@dataclass
class VendorRig:
    config: BoxConfig
    sim: SimBox
    sniffer: Sniffer
    limits: ActuationSubset

    def session(self) -> DriveSession:
        return DriveSession(
            self.config, self.limits, listen_s=RIG_LISTEN_S, allow_uncalibrated=True
        )

    def sdo_downloads(self, node: int) -> list[tuple[int, int, int]]:
        """(index, sub, value) of every expedited SDO download request to ``node``."""
        return [
            (m.data[1] | m.data[2] << 8, m.data[3], int.from_bytes(m.data[4:8], "little"))
            for m in self.sniffer.snapshot()
            if m.arbitration_id == cia301.COB_SDO_RX + node and m.data[0] & 0xE0 == 0x20
        ]


@pytest.fixture
def vendor_rig(actuation: Actuation) -> Iterator[Any]:
    opened: list[Any] = []

    def make(drives: dict[str, Any]) -> VendorRig:
        channel = f"hrm-vendor-{uuid.uuid4().hex[:12]}"
        doc: dict[str, Any] = {
            "control": {
                "bootup_timeout_s": 2.0,
                "missing_tpdo_cycles": IN_PROCESS_MISSING_TPDO_CYCLES,
            },
            "buses": {
                "bus0": {
                    "interface": "virtual",
                    "channel": channel,
                    "bitrate": 1_000_000,
                    "nodes": dict(NODES),
                }
            },
        }
        if drives:
            doc["drives"] = drives
        config = box_config_from_dict(doc, "<vendor rig>")
        sim = SimBox(config, actuation=actuation)
        sim.start()
        opened.append(sim.stop)
        bus = can.Bus(interface="virtual", channel=channel)
        sniffer = Sniffer()
        notifier = can.Notifier(bus, [sniffer], 0.05)
        opened.extend([bus.shutdown, lambda: notifier.stop(1.0)])
        return VendorRig(config, sim, sniffer, ActuationSubset(actuation, tuple(NODES)))

    yield make
    for fn in reversed(opened):
        fn()


def _remap(comm: int, cob: int, entries: tuple[int, ...]) -> list[tuple[int, int, int]]:
    """CiA 301's remapping sequence: COB-ID invalid, transmission type, number of entries
    0, the entries, their number, COB-ID valid."""
    mapping = comm + 0x200
    return [
        (comm, 1, cob | 0x80000000), (comm, 2, 1), (mapping, 0, 0),
        *[(mapping, k, e) for k, e in enumerate(entries, start=1)],
        (mapping, 0, len(entries)), (comm, 1, cob),
    ]  # fmt: skip


@pytest.mark.parametrize("name", list(CSP_BOXES))
def test_a_box_of_csp_drives_brings_up_by_its_file_and_streams(vendor_rig: Any, name: str) -> None:
    rig: VendorRig = vendor_rig(CSP_BOXES[name])
    drive: DriveSim = rig.sim.drives["j01r1"]
    start = drive.position_counts
    with rig.session() as box:
        box.bring_up()  # configured and enabled
        result = box.stream(JogSource(rig.limits, "j01r1", 20_000.0, 0.2))
        assert result.completed
        box.finish()
    assert drive.position_counts - start == pytest.approx(4000, abs=200)  # 20000/s x 0.2 s
    writes = rig.sdo_downloads(2)
    overlay = [(0x60A8, 0, 0x00B50000)] if name == "c5-e" else []
    assert writes[: len(overlay)] == overlay  # the overlay first
    pdo = [w for w in writes if w[0] in (0x1400, 0x1600, 0x1800, 0x1A00)]
    assert pdo == _remap(0x1400, 0x202, (0x60400010, 0x607A0020)) + _remap(
        0x1800, 0x182, (0x60410010, 0x60640020)
    )
    assert [w for w in writes if w[0] == 0x60C2] == [(0x60C2, 1, 10), (0x60C2, 2, 0xFD)]
    assert drive.interpolation_period_s == pytest.approx(0.01)
    # 0x6085 from the motor's acceleration limit, in the drive's unit, after 0x605A
    accel = float(rig.limits.max_accel_counts_per_s2[1])
    per_count_s2 = QUICK_STOP_PER_COUNT_S2[name]
    expected = [] if per_count_s2 is None else [(0x6085, 0, round(accel * per_count_s2))]
    assert [w for w in writes if w[0] == 0x6085] == expected
    if expected:
        indices = [w[0] for w in writes]
        assert indices.index(0x6085) == indices.index(0x605A) + 1


def test_0x60c2_is_written_in_the_encoding_the_device_file_allows(vendor_rig: Any) -> None:
    """The bring-up writes the setup's 0x60C2 (the check's, from the drive's limits), not
    hrm's own encoding: 1 x 10^-2 s here, which the simulated drive reads as 10 ms."""
    rig: VendorRig = vendor_rig({"device_file": str(EPOS4)})
    with rig.session() as box:
        box.drives.setups = {
            m: replace(s, interpolation=(1, -2)) for m, s in box.drives.setups.items()
        }
        box.bring_up()
    assert [w for w in rig.sdo_downloads(1) if w[0] == 0x60C2] == [
        (0x60C2, 1, 1), (0x60C2, 2, 0xFE)
    ]  # fmt: skip
    assert rig.sim.drives["j01r0"].interpolation_period_s == pytest.approx(0.01)


@pytest.mark.parametrize(
    ("identity", "expected"),
    [
        ({"product_code": 0x12345678}, "0x1018:02 (product code) expected 0x12345678, found"),
        ({"revision": 1}, "0x1018:03 (revision) expected 0x00000001, found 0x07F70000"),
    ],
)
def test_an_identity_other_than_the_configuration_is_refused_before_any_write(
    vendor_rig: Any, identity: dict[str, int], expected: str
) -> None:
    rig: VendorRig = vendor_rig({"device_file": str(C5E), **UNIT_INCREMENTS, "identity": identity})
    with rig.session() as box, pytest.raises(IdentityMismatchError) as info:
        box.bring_up()
    text = str(info.value)
    assert text.startswith("j01r0 (bus bus0 node 1): identity ") and expected in text
    assert text.endswith(": not the drive the box configuration names; nothing written")
    assert all(rig.sdo_downloads(n) == [] for n in NODES.values())  # no SDO write at all


def test_the_identity_the_file_gives_passes(vendor_rig: Any) -> None:
    """The C5-E's product code and revision (the simulated drive answers its file's); the
    vendor-ID is not compared on a simulated box (its drives answer 0)."""
    identity = {"vendor_id": 0x26C, "product_code": 17, "revision": 133627904}
    rig: VendorRig = vendor_rig({"device_file": str(C5E), **UNIT_INCREMENTS, "identity": identity})
    with rig.session() as box:
        box.bring_up()
    assert rig.sdo_downloads(1)[0] == (0x60A8, 0, 0x00B50000)


def test_a_simulated_drive_refuses_the_modes_its_file_does_not_declare() -> None:
    from sim_bus.drive.objects import SdoAbort

    faulhaber = DriveSim(5, lambda m: None, eds=FAULHABER)
    with pytest.raises(SdoAbort) as info:
        faulhaber.check_write(0x6060, 0, 8)  # CSP: not in its 0x6502 (PP, PV, HM)
    assert info.value.code == cia301.SDO_ABORT_INVALID_VALUE
    faulhaber.check_write(0x6060, 0, 1)  # PP: declared
    epos4 = DriveSim(5, lambda m: None, eds=EPOS4)
    epos4.check_write(0x6060, 0, 8)
    with pytest.raises(SdoAbort):
        epos4.check_write(0x6060, 0, 7)  # IP: the EPOS4 declares PP, PV, HM, CSP, CSV, CST


def test_a_simulated_drive_maps_no_more_entries_than_its_file_has() -> None:
    from sim_bus.drive.objects import SdoAbort

    faulhaber = DriveSim(5, lambda m: None, eds=FAULHABER)  # 4 entries a PDO
    faulhaber.od.write((0x1400, 1), 0x80000205)
    for k in range(1, 5):
        faulhaber.od.write((0x1600, k), 0x60400010)
    faulhaber.od.write((0x1600, 0), 0)
    with pytest.raises(SdoAbort) as info:
        faulhaber.check_write(0x1600, 0, 5)
    assert info.value.code == cia301.SDO_ABORT_PDO_LENGTH
    with pytest.raises(SdoAbort):
        faulhaber.od.lookup(0x1600, 5)


def guarded_eds(folder: Path) -> Path:
    """hrm's EDS without a heartbeat consumer 0x1016, with node guarding 0x100C/0x100D (as
    the Technosoft iPOS offers, which hrm refuses anyway for want of CSP)."""
    from drivers import eds_path

    text = eds_path().read_text()
    start, end = text.index("[1016]\n"), text.index("[1017]\n")
    guarding = (
        "[100C]\nParameterName=Guard time\nObjectType=0x7\nDataType=0x0006\nAccessType=rw\n"
        "DefaultValue=0\nPDOMapping=0\n\n[100D]\nParameterName=Life time factor\n"
        "ObjectType=0x7\nDataType=0x0005\nAccessType=rw\nDefaultValue=0\nPDOMapping=0\n\n"
    )
    text = text[:start] + guarding + text[end:]
    text = text.replace("4=0x1016\n", "4=0x100C\n").replace("23=0x6085\n", "23=0x6085\n24=0x100D\n")
    text = text.replace(
        "[OptionalObjects]\nSupportedObjects=23", "[OptionalObjects]\nSupportedObjects=24"
    )
    path = folder / "guarded.eds"
    path.write_text(text)
    return path


def test_a_drive_without_heartbeat_consumer_is_guarded_by_the_host(
    vendor_rig: Any, tmp_path: Path
) -> None:
    """No 0x1016: the bring-up writes the guard time and life time factor (0x1017 = 0, no
    0x1016); the host sends a guarding request to each drive with every host heartbeat,
    each drive answers its NMT state with the toggle bit alternating from 0; a jog
    streams; then a drive whose answers stop is a lost heartbeat that stops every axis."""
    from drivers.safety.stops import SafetyStopError

    rig: VendorRig = vendor_rig({"device_file": str(guarded_eds(tmp_path))})
    with rig.session() as box:
        box.bring_up()
        result = box.stream(JogSource(rig.limits, "j01r1", 20_000.0, 0.3))
        assert result.completed
        rig.sim.drives["j01r2"].nmt.guarding_enabled = False  # answers stop
        with pytest.raises(SafetyStopError) as info:
            box.stream(HoldSource(n_cycles=300))  # 3 s
        assert str(info.value).startswith("stopped: j01r2 (bus bus0 node 3): heartbeat lost")
    writes = rig.sdo_downloads(2)
    assert [w for w in writes if w[0] in (0x1016, 0x1017, 0x100C, 0x100D)] == [
        (0x1017, 0, 0), (0x100C, 0, 100), (0x100D, 0, 3)
    ]  # fmt: skip
    frames = rig.sniffer.snapshot()
    requests = [m for m in frames if m.arbitration_id == 0x702 and m.is_remote_frame]
    answers = [m.data[0] for m in frames if m.arbitration_id == 0x702 and not m.is_remote_frame]
    boot = answers.index(0x00)  # the boot-up after the NMT reset, then the answers
    assert len(requests) >= 3 and all(a != 0x00 for a in answers[boot + 1 :])
    toggles = [a >> 7 for a in answers[boot + 1 :]]
    assert toggles == [k % 2 for k in range(len(toggles))] and len(toggles) >= 3
    assert {a & 0x7F for a in answers[boot + 1 :]} <= {0x05, 0x7F}  # operational, pre-op


def test_a_simulated_drive_answers_guarding_as_cia_301_says(tmp_path: Path) -> None:
    """A remote frame on 0x700 + node id: one byte, the NMT state with the toggle bit, 0
    first after a reset of communication, then alternating; once guarded, no request
    within guard time x life time factor: EMCY 0x8130 (life guarding), cleared (EMCY 0)
    by the next request.  A drive with a heartbeat consumer (hrm's EDS) does not guard."""
    sent: list[can.Message] = []
    drive = DriveSim(5, sent.append, eds=guarded_eds(tmp_path), now=0.0)
    assert 0x705 in drive.cob_ids()
    drive.od.write((0x100C, 0), 100)
    drive.od.write((0x100D, 0), 3)
    request = cia301.make_guarding_request(5)
    sent.clear()
    for k in range(3):
        drive.handle(request, 0.1 * k)
    assert [(m.arbitration_id, m.data[0]) for m in sent] == [
        (0x705, 0x7F),
        (0x705, 0xFF),
        (0x705, 0x7F),
    ]
    sent.clear()
    drive.tick(0.2 + 0.29)
    assert sent == []  # within the life time (300 ms)
    drive.tick(0.2 + 0.31)
    assert [(m.arbitration_id, m.data[:2].hex()) for m in sent] == [(0x85, "3081")]  # 0x8130
    sent.clear()
    drive.handle(request, 0.6)
    assert [(m.arbitration_id, m.data[:2].hex()) for m in sent] == [(0x705, "ff"), (0x85, "0000")]
    drive.reset_communication(1.0)
    sent.clear()
    drive.handle(request, 1.1)
    assert [m.data[0] for m in sent] == [0x7F]  # toggle 0 again
    assert 0x705 not in DriveSim(5, sent.append, now=0.0).cob_ids()
