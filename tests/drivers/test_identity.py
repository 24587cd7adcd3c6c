"""drivers/identity.py: each drive's identity object read at the bring-up, and the check
that the calibration in use was made on this box (issue 34, item 1)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.identity import (
    SIMULATOR_VENDOR_ID,
    BoxIdentity,
    BoxIdentityError,
    DriveIdentity,
    box_problems,
    same_box,
)
from drivers.lifecycle import SessionState
from drivers.run_record import CalibrationRef
from tests.drivers.driver_rig import Rig

MOTORS = ("j01r0", "j01r1", "j01r2", "j02r0")
u32 = st.integers(0, 0xFFFFFFFF)


def _box(vendor: int, serials: list[int]) -> BoxIdentity:
    return BoxIdentity.of(
        {m: DriveIdentity(vendor, 0x402, 0x10000, s) for m, s in zip(MOTORS, serials, strict=True)}
    )


@given(st.lists(u32, min_size=4, max_size=4, unique=True), st.sampled_from([0, 0x9A]))
def test_the_box_it_was_made_on_passes(serials: list[int], vendor: int) -> None:
    box = _box(vendor, serials)
    assert box_problems(box, box, "v1") == [] and same_box(box, box)
    assert box.simulated == (vendor == SIMULATOR_VENDOR_ID)
    # a firmware update (revision) keeps the drive
    newer = BoxIdentity.of({m: dataclasses.replace(d, revision=2) for m, d in box.drives.items()})
    assert box_problems(box, newer, "v1") == []
    # the record round-trips
    assert BoxIdentity.from_dict(box.to_dict(), ValueError) == box


@given(st.lists(u32, min_size=4, max_size=4, unique=True), st.sets(st.sampled_from(MOTORS)))
def test_each_replaced_drive_is_named(serials: list[int], replaced: set[str]) -> None:
    made = _box(0x9A, serials)
    live = BoxIdentity.of(
        {
            m: dataclasses.replace(d, serial=(d.serial + 1) & 0xFFFFFFFF) if m in replaced else d
            for m, d in made.drives.items()
        }
    )
    problems = box_problems(made, live, "v1")
    if len(replaced) == len(MOTORS):  # none left: another box
        assert len(problems) == 1 and "made on another box" in problems[0]
        assert not same_box(made, live)
        return
    assert same_box(made, live)
    assert [p.split(":")[0] for p in problems] == [m for m in MOTORS if m in replaced]
    for p in problems:
        m = p.split(":")[0]
        assert p == (
            f"{m}: drive serial 0x{live.drives[m].serial:08X} is not the one calibrated "
            f"(0x{made.drives[m].serial:08X}): run calibrate zero for it"
        )


def test_the_simulator_and_the_check_agree_on_its_vendor() -> None:
    import sim_bus.drive

    assert sim_bus.drive.SIMULATOR_VENDOR_ID == SIMULATOR_VENDOR_ID == 0
    # two simulated drives are the same by their serial (their truth's), whatever the
    # device file's product code
    a = DriveIdentity(0, 0x402, 1, 77)
    assert a.same_drive(DriveIdentity(0, 0x60500, 7, 77))
    assert not a.same_drive(DriveIdentity(0, 0x402, 1, 78))
    assert not DriveIdentity(9, 0x402, 1, 77).same_drive(DriveIdentity(9, 0x403, 1, 77))


def test_unknown_simulated_and_real_boxes_are_told_apart() -> None:
    sim, real = _box(0, [1, 2, 3, 4]), _box(0x9A, [1, 2, 3, 4])
    assert "box unknown" in box_problems(None, real, "v1")[0]
    assert "--box" in box_problems(None, real, "v1")[0]
    assert "a real box never uses it" in box_problems(sim, real, "v1")[0]
    assert "made on a real box" in box_problems(real, sim, "v1")[0]
    other = dataclasses.replace(real.drives["j01r0"], product_code=0x403)
    live = BoxIdentity.of({**real.drives, "j01r0": other})
    (p,) = box_problems(real, live, "v1")
    assert p.startswith("j01r0: drive identity vendor 0x0000009A product 0x00000403")


@pytest.mark.parametrize(
    ("doc", "why"),
    [
        ([], "box must be a table"),
        ({"simulated": 1, "drives": {}}, "box.simulated must be true or false"),
        ({"simulated": True, "drives": {}}, "box.drives must be a table of 1 to 128"),
        ({"simulated": True, "drives": {"a b": {}}}, "id 'a b'"),
        ({"simulated": True, "drives": {"m": {"serial": 1}}}, "box.drives.m must have"),
        (
            {"simulated": True, "drives": {"m": dict.fromkeys(
                ("vendor_id", "product_code", "revision", "serial"), -1)}},
            "UNSIGNED32",
        ),
        (
            {"simulated": True, "drives": {"m": dict.fromkeys(
                ("vendor_id", "product_code", "revision", "serial"), 7)}},
            "does not match the drives' vendor-IDs",
        ),
    ],
)  # fmt: skip
def test_a_bad_box_record_is_refused(doc: object, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        BoxIdentity.from_dict(doc, ValueError)


def test_the_session_reads_every_drive_and_refuses_another_box_before_configuring(
    rig_factory: Callable[..., Rig], tmp_path: Path
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    live = box.box_identity
    assert live is not None and live.simulated
    assert sorted(live.drives) == sorted(rig.limits.motor_ids)
    serials = {m: rig.sim.drives[m].params.serial_number for m in live.drives}
    assert {m: d.serial for m, d in live.drives.items()} == serials
    assert len(set(serials.values())) == len(serials)  # a serial per drive
    box.finish()
    box.close()
    rig.box = None
    # one drive's serial changed in the calibration: that drive is named, nothing configured
    m0 = next(iter(live.drives))
    other = dataclasses.replace(live.drives[m0], serial=live.drives[m0].serial ^ 1)
    made = BoxIdentity.of({**live.drives, m0: other})
    ref = CalibrationRef(3, "ab" * 32, "/store/v0003.json", box=made)
    box = rig.open_box(log_dir=tmp_path, calibration=ref, allow_uncalibrated=False)
    with pytest.raises(BoxIdentityError, match=f"calibration refused: {m0}: drive serial"):
        box.bring_up()
    assert box.state is not SessionState.READY
    assert not any(e["kind"] == "configured" for e in box.events.to_list())
    # the same without the check (the zero routine makes every zero anew): brought up
    box.close()
    rig.box = None
    box = rig.open_box(calibration=dataclasses.replace(ref, check_box=False))
    box.bring_up()
    assert box.state is SessionState.ENABLED
