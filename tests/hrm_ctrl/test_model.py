"""The robot description: every table and key is known, an unknown one is refused by name."""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.errors import HrmError, RobotDescriptionError
from hrm_ctrl.formats.planfile import write_plan
from hrm_ctrl.model import PLAIN_KEYS, TABLE_KEYS, default_robot, load_robot
from hrm_ctrl.ropes.actuation import load_actuation
from tests.hrm_ctrl.cli.cli_helpers import small_plan
from tests.hrm_ctrl.cli.test_bad_input import refused

SHIPPED = resources.files("hrm_ctrl.data").joinpath("robot.toml").read_text()


def shipped_keys() -> list[tuple[str | None, str]]:
    """(table or None for the top level, key) of every key the shipped file sets."""
    doc = tomllib.loads(SHIPPED)
    out: list[tuple[str | None, str]] = []
    for key, value in doc.items():
        out.append((None, key))
        if isinstance(value, dict):
            out += [(key, sub) for sub in value]
    return out


def test_every_table_and_key_of_the_shipped_file_is_known() -> None:
    keys = shipped_keys()
    top = {k for t, k in keys if t is None}
    # the shipped file sets every table but the optional [physics] (commented out there)
    assert top == PLAIN_KEYS | (set(TABLE_KEYS) - {"physics"})
    for table, key in keys:
        known = TABLE_KEYS.get(table) if table is not None else None
        if known is not None:
            assert key in known, (table, key)
    assert sorted(default_robot().tables) == ["motors", "ropes"]
    load_actuation(default_robot())  # the rope layer takes its tables' keys


@pytest.mark.parametrize(("table", "key"), shipped_keys())
def test_a_misspelt_key_is_refused_naming_key_and_table(
    tmp_path: Path, table: str | None, key: str
) -> None:
    """Each table and key of the shipped file, misspelt, fails in one line naming it and
    its table: when the description loads, or for [ropes] / [motors] (the rope layer's)
    when the rope layer is built from it."""
    doc = tomllib.loads(SHIPPED)
    typo = key + "x"
    if table is None:
        doc[typo] = doc.pop(key)
    else:
        doc[table][typo] = doc[table].pop(key)
    p = tmp_path / "robot.toml"
    p.write_text(_toml(doc))
    with pytest.raises(HrmError) as info:
        load_actuation(load_robot(p))
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{p}: "), msg
    if table is None:
        kind = f"unknown table [{typo}]" if isinstance(doc[typo], dict) else f"key '{typo}'"
        assert kind in msg, msg
        assert f"'{key}'" in msg or f"[{key}]" in msg, msg  # the near miss is named
    else:
        assert f"[{table}]: unknown key '{typo}'" in msg, msg
    if TABLE_KEYS.get(table or "") is None and table is not None:
        return  # the rope layer's table: refused by its owner
    assert isinstance(info.value, RobotDescriptionError)


def test_the_reported_typo_ropess_is_refused_by_every_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``[ropess]`` used to fall back to the default ropes; now ``hrm urdf`` (which never
    builds the rope layer) refuses the file with exit 2 and one line, like the rest."""
    p = tmp_path / "robot.toml"
    p.write_text(SHIPPED.replace("[ropes]", "[ropess]", 1))
    out = tmp_path / "arm.urdf"
    rc = main(["urdf", "--robot", str(p), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert err == f"hrm urdf: error: {p}: unknown table [ropess] (did you mean [ropes]?)\n"
    assert "Traceback" not in err and not out.exists()


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        ({"name": {"x": 1}}, "'name' must be a value, not a table"),
        ({"base": [1, 2]}, "[base] must be a table"),
        ({"ropes": 3}, "[ropes] must be a table"),
        ({"motors": {"direction": {"j01r0": -1}, "gear_ratio": 33.0}}, None),  # motor ids: ok
    ],
)
def test_tables_and_plain_keys_keep_their_kind(edit: dict[str, Any], expected: str | None) -> None:
    from hrm_ctrl.model import robot_from_dict

    doc = {**tomllib.loads(SHIPPED), **edit}
    if expected is None:
        assert robot_from_dict(doc, "r").tables["motors"]["direction"] == {"j01r0": -1}
        return
    with pytest.raises(RobotDescriptionError) as info:
        robot_from_dict(doc, "r")
    assert expected in str(info.value)


def _toml(doc: dict[str, Any]) -> str:
    """A small TOML writer for the description's shapes (values, lists, one level)."""

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        return repr(v)

    lines = [f"{k} = {value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"[{k}]")
            lines += [f"{s} = {value(x)}" for s, x in v.items()]
    return "\n".join(lines) + "\n"


# ---- every [motors] number has a range (a red team's 1e300 rpm) ----------------------------

MOTOR_LINES = {
    "drum_radius_mm": "drum_radius_mm = 10.0",
    "gear_ratio": "gear_ratio = 33.0",
    "counts_per_turn": "counts_per_turn = 4096.0",
    "max_speed_rpm": "max_speed_rpm = 6000.0",
    "max_accel_rpm_per_s": "max_accel_rpm_per_s = 30000.0",
    "max_jerk_rpm_per_s2": "max_jerk_rpm_per_s2 = 600000.0",
    "travel_in_mm": "travel_in_mm = 200.0",
    "travel_out_mm": "travel_out_mm = 200.0",
}


def _robot_with(tmp_path: Path, key: str, value: str) -> Path:
    line = MOTOR_LINES[key]
    assert line in SHIPPED
    p = tmp_path / "robot.toml"
    p.write_text(SHIPPED.replace(line, f"{key} = {value}", 1))
    return p


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("key", sorted(MOTOR_LINES))
def test_an_absurd_motor_number_is_refused_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str
) -> None:
    """``max_speed_rpm = 1e300`` used to give a setpoint table, and ``hrm run --sim``
    enabled the drives before stopping with RuntimeWarnings."""
    robot = _robot_with(tmp_path, key, "1e300")
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    refused(
        capsys, tmp_path,
        ["ropes", str(plan), "--robot", str(robot), "--out", str(tmp_path / "sp.csv")],
        f"{robot}: [motors].{key}: 1e+300 is out of range",
    )  # fmt: skip


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_run_sim_refuses_1e300_rpm_before_any_drive_is_enabled(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    robot = _robot_with(tmp_path, "max_speed_rpm", "1e300")
    plan = tmp_path / "plan.json"
    write_plan(plan, small_plan())
    argv = ["run", str(plan), "--sim", "--robot", str(robot)]
    argv += ["--calibrations", str(tmp_path / "cal")]
    refused(capsys, tmp_path, argv, "[motors].max_speed_rpm: 1e+300 is out of range")


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("max_speed_rpm", "100000.0"),
        ("max_accel_rpm_per_s", "1e6"),
        ("max_jerk_rpm_per_s2", "1e9"),
        ("max_jerk_rpm_per_s2", "1000.0"),
        ("gear_ratio", "1e4"),
        ("drum_radius_mm", "1000.0"),
    ],
)
def test_motor_numbers_at_the_ends_of_their_ranges_load(tmp_path: Path, key: str, value: str):
    act = load_actuation(load_robot(_robot_with(tmp_path, key, value)))
    assert act.n_motors == 36
