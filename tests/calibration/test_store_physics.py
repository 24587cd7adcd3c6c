"""The calibration format's physics member (``hrm-calibration/3``): a physics
calibration's link masses, payload and friction round-trip bit for bit; files of the
previous formats (``/2`` without ``physics``, ``/1`` without ``box`` either) still read,
with no physics calibration (the description's ``[physics]`` values apply); a wrong
physics member is one line naming the file and the key; the feed-forward takes the
calibrated values where the calibration has them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.apply import calibrated_actuation, nominal_calibration, updated
from calibration.store import (
    FORMAT,
    FORMAT_1,
    FORMAT_2,
    CalibrationStore,
    PhysicsConstants,
    Routine,
    checksum,
)
from hrm_ctrl.errors import CalibrationFileError
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.feedforward import DEFAULT_PHYSICS, Feedforward
from tests.calibration.test_store import _one_line_naming, _rewrite, make_cal

MASSES = np.linspace(0.014, 0.026, 12)
MU = np.linspace(0.07, 0.13, 12)


def physics_cal(seed: int = 0):
    import dataclasses

    ph = PhysicsConstants(MASSES + seed * 1e-4, 0.023, MU)
    return dataclasses.replace(make_cal(seed), physics=ph, routine=Routine.PHYSICS)


def test_physics_round_trips_bit_for_bit(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    cal = physics_cal(1)
    assert store.save(cal) == 1
    back = store.load(1)
    assert back == cal and back.physics is not None and back.routine is Routine.PHYSICS
    assert back.physics.link_mass_kg.tobytes() == cal.physics.link_mass_kg.tobytes()
    assert back.physics.mu_kinetic.tobytes() == MU.tobytes()
    assert back.physics.payload_kg == 0.023
    assert not back.physics.mu_kinetic.flags.writeable
    doc = json.loads((tmp_path / "v0001.json").read_text())
    assert doc["format"] == FORMAT == "hrm-calibration/3"
    assert doc["physics"]["payload_kg"] == 0.023
    # a calibration without one writes null
    store.save(make_cal(2))
    assert json.loads((tmp_path / "v0002.json").read_text())["physics"] is None
    assert store.load(2).physics is None


@pytest.mark.parametrize(
    ("fmt", "drop"),
    [(FORMAT_2, ("physics",)), (FORMAT_1, ("physics", "box"))],
)
def test_a_file_of_an_older_format_still_reads(
    tmp_path: Path, fmt: str, drop: tuple[str, ...]
) -> None:
    """An /2 file (no physics member) and an /1 file (no box either), as their writers
    made them: read, with no physics calibration and (for /1) the box unknown."""
    store = CalibrationStore(tmp_path)
    cal = make_cal(3)
    store.save(cal)
    path = tmp_path / "v0001.json"

    def older(doc: dict) -> None:
        doc["format"] = fmt
        for key in drop:
            del doc[key]

    _rewrite(path, older)
    back = store.load(1)
    assert back.physics is None and back.box is None
    assert back.links_mm.tobytes() == cal.links_mm.tobytes()
    # and the feed-forward of such a calibration takes the description's values
    m = default_robot()
    old = updated(nominal_calibration(m), routine="manual", residuals={})
    ff = Feedforward.of(calibrated_actuation(m, old))
    assert ff.physics.mu_kinetic.tolist() == [DEFAULT_PHYSICS["mu_kinetic"]] * 12
    assert ff.physics.payload_kg == DEFAULT_PHYSICS["payload_kg"]


def test_an_older_format_with_a_physics_member_is_refused(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save(physics_cal())
    path = tmp_path / "v0001.json"
    _rewrite(path, lambda d: d.update(format=FORMAT_2))
    with pytest.raises(CalibrationFileError, match=r"unknown \['physics'\]") as exc:
        store.load(1)
    _one_line_naming(exc, path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda p: p["link_mass_kg"].pop(), r"physics.link_mass_kg has 11 values, not 12"),
        (lambda p: p["link_mass_kg"].__setitem__(3, -0.01), r"link_mass_kg\[3\] is -0.01, not > 0"),
        (lambda p: p["link_mass_kg"].__setitem__(0, 0.0), r"link_mass_kg\[0\] is 0.0, not > 0"),
        (lambda p: p["mu_kinetic"].__setitem__(5, -0.1), r"mu_kinetic\[5\] is -0.1, not >= 0"),
        (lambda p: p["mu_kinetic"].__setitem__(1, "0.1"), r"mu_kinetic\[1\] is not a number"),
        (lambda p: p["mu_kinetic"].__setitem__(1, float("nan")), "NaN and infinity"),
        (lambda p: p.update(payload_kg=-1.0), "physics.payload_kg is -1.0, not >= 0"),
        (lambda p: p.update(payload_kg=True), r"physics.payload_kg is not a number"),
        (lambda p: p.pop("mu_kinetic"), r"physics: members missing \['mu_kinetic'\]"),
        (lambda p: p.update(static_ratio=1.5), r"physics: members missing \[\], unknown"),
    ],
)
def test_a_wrong_physics_member_is_one_line_naming_file_and_key(
    tmp_path: Path, change, message: str
) -> None:
    store = CalibrationStore(tmp_path)
    store.save(physics_cal())
    path = tmp_path / "v0001.json"
    _rewrite(path, lambda d: change(d["physics"]))
    with pytest.raises(CalibrationFileError, match=message) as exc:
        store.load(1)
    _one_line_naming(exc, path)


def test_a_physics_member_that_is_not_a_table_is_refused(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save(physics_cal())
    path = tmp_path / "v0001.json"
    _rewrite(path, lambda d: d.update(physics=[1, 2]))
    with pytest.raises(CalibrationFileError, match="physics must be a table") as exc:
        store.load(1)
    _one_line_naming(exc, path)


def test_an_edited_physics_value_fails_the_checksum(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.save(physics_cal())
    path = tmp_path / "v0001.json"
    doc = json.loads(path.read_text())
    doc["physics"]["mu_kinetic"][0] = 0.5
    path.write_text(json.dumps(doc))
    assert checksum(doc) != doc["sha256"]
    with pytest.raises(CalibrationFileError, match="checksum mismatch"):
        store.load(1)


def test_the_feedforward_takes_the_calibrated_values() -> None:
    m = default_robot()
    ph = PhysicsConstants(MASSES, 0.031, MU)
    cal = updated(nominal_calibration(m), routine="physics", residuals={}, physics=ph)
    ff = Feedforward.of(calibrated_actuation(m, cal))
    assert ff.physics.link_mass_kg.tolist() == MASSES.tolist()
    assert ff.physics.mu_kinetic.tolist() == MU.tolist() and ff.physics.payload_kg == 0.031
    # the rest of the [physics] table stays the description's
    assert ff.physics.static_ratio == DEFAULT_PHYSICS["static_ratio"]
    # the physics calibration is carried over by the next routine's version
    nxt = updated(cal, routine="stiffness", residuals={})
    assert nxt.physics is not None and nxt.physics.payload_kg == 0.031
