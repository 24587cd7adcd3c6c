"""Bus configuration validation and the bus-load budget."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.busload import BusLoadError, bus_load, check_bus_load
from drivers.config import (
    CONTROL_RANGES,
    RATE_MAX_HZ,
    RATE_MIN_HZ,
    UDP_MULTICAST_HOP_LIMIT,
    BusConfigError,
    ControlConfig,
    box_config_from_dict,
    load_box_config,
    rate_problem,
)
from drivers.protocol.cia301 import FrameError
from drivers.protocol.cia402 import interpolation_time_period
from drivers.protocol.frames import worst_case_frame_bits
from hrm_ctrl.ropes.actuation import Actuation

GOOD = """
[control]
rate_hz = 100

[buses.a]
interface = "virtual"
channel = "x"
bitrate = 1000000

[buses.a.nodes]
j01r0 = 1
j01r1 = 2
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "box.toml"
    p.write_text(text)
    return p


def test_default_config_matches_the_rope_layer(actuation: Actuation) -> None:
    cfg = load_box_config(None)
    cfg.check_motors(actuation.motor_ids)
    assert [len(b.nodes) for b in cfg.buses] == [18, 18]
    assert {b.bitrate for b in cfg.buses} == {1_000_000}
    assert cfg.control.rate_hz == 100.0 and cfg.control.bus_load_limit == 0.7
    loads = check_bus_load(cfg)
    assert all(0.4 < bl.load < 0.5 for bl in loads)


def test_good_file_loads(tmp_path: Path) -> None:
    cfg = load_box_config(write(tmp_path, GOOD))
    assert cfg.motor_ids == ("j01r0", "j01r1")
    assert cfg.buses[0].bus_kwargs() == {"interface": "virtual", "channel": "x", "bitrate": 1000000}


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (('"virtual"', '"nosuch"'), "a.interface: unknown python-can interface 'nosuch'"),
        (("j01r1 = 2", "j01r1 = 1"), "buses.a.nodes.j01r1: duplicate node id 1 (also j01r0)"),
        (("j01r1 = 2", "j01r1 = 0"), "buses.a.nodes.j01r1: node id 0 outside 1..127"),
        (("j01r1 = 2", "j01r1 = 128"), "buses.a.nodes.j01r1: node id 128 outside 1..127"),
        (("j01r1 = 2", "j01r1 = 127"), "nodes.j01r1: node id 127 is the host's heartbeat id"),
        (("j01r1 = 2", 'j01r1 = "2"'), "buses.a.nodes.j01r1: node id must be an integer"),
        (("bitrate = 1000000", "bitrate = 2000000"), "buses.a.bitrate: expected an integer in 1.."),
        (("bitrate = 1000000\n", ""), "buses.a: missing key 'bitrate'"),
        (("rate_hz = 100", "rate_hz = -1"), "control.rate_hz = -1 outside 10..1000 Hz; "),
        (("rate_hz = 100", "rate_hz = 100\nbogus = 1"), "control.bogus: unknown key"),
        (("rate_hz = 100", "heartbeat_timeout_ms = 50"), "heartbeat_timeout_ms = 50 must be at"),
        (("[control]", "[controls]"), "unknown table(s) ['controls']"),
        (("rate_hz = 100", "rate_hz = = 1"), "not valid TOML"),
        (("rate_hz = 100", "rate_hz = 7"), "control.rate_hz = 7 outside 10..1000 Hz"),
        (("rate_hz = 100", "rate_hz = 70"), "control.rate_hz must give a period 0x60C2 can"),
        (("rate_hz = 100", "rate_hz = 30"), "control.rate_hz must give a period 0x60C2 can"),
        (("rate_hz = 100", "rate_hz = 300"), "rate_hz must give a period 0x60C2 can encode"),
        (("[buses.a", '[buses."a/b"'), "buses.'a/b': bus name may only use letters"),
        (("[buses.a", '[buses."../a"'), "buses.'../a': bus name may only use letters"),
        (("[buses.a", '[buses."a b"'), "buses.'a b': bus name may only use letters"),
    ],
)  # fmt: skip
def test_bad_config_is_one_line_naming_file_and_key(
    tmp_path: Path, edit: tuple[str, str], expected: str
) -> None:
    p = write(tmp_path, GOOD.replace(*edit))
    with pytest.raises(BusConfigError) as info:
        load_box_config(p)
    msg = str(info.value)
    assert msg.startswith(str(p)), msg
    assert expected in msg, msg
    assert "\n" not in msg


def test_same_motor_on_two_buses(tmp_path: Path) -> None:
    text = GOOD + '\n[buses.b]\ninterface = "virtual"\nchannel = "y"\nbitrate = 500000\n'
    text += "[buses.b.nodes]\nj01r0 = 1\n"
    with pytest.raises(
        BusConfigError, match=r"buses\.b\.nodes\.j01r0: motor 'j01r0' is also on bus a"
    ):
        load_box_config(write(tmp_path, text))


@pytest.mark.parametrize("rate_hz", [70.0, 30.0, 60.0, 300.0, 163.0])
def test_rates_whose_period_0x60C2_cannot_encode_are_refused(rate_hz: float) -> None:
    with pytest.raises(BusConfigError, match=r"control\.rate_hz must give a period 0x60C2"):
        load_box_config(None).with_control(rate_hz=rate_hz)


@settings(max_examples=60, deadline=None)
@given(rate_hz=st.floats(0.01, 10_000.0))
def test_every_accepted_rate_has_an_0x60C2_encoding(rate_hz: float) -> None:
    try:
        cfg = load_box_config(None).with_control(rate_hz=rate_hz)
    except BusConfigError as exc:
        if not RATE_MIN_HZ <= rate_hz <= RATE_MAX_HZ:
            assert f"control.rate_hz = {rate_hz!r} outside 10..1000 Hz" in str(exc)
            return
        assert "control.rate_hz must give a period 0x60C2 can encode" in str(exc)
        with pytest.raises(FrameError):
            interpolation_time_period(1.0 / rate_hz)
        return
    value, index = interpolation_time_period(cfg.control.period_s)
    assert value * 10.0**index == pytest.approx(1.0 / rate_hz, rel=1e-9)


@pytest.mark.parametrize("rate_hz", [10.0, 20.0, 25.0, 40.0, 50.0, 100.0, 125.0, 200.0, 1000.0])
def test_encodable_rates_are_accepted(rate_hz: float) -> None:
    assert load_box_config(None).with_control(rate_hz=rate_hz).control.rate_hz == rate_hz


@pytest.mark.parametrize("channel_b", ['"x"', '"x"\noptions = {rx_queue_size = 5}'])
def test_two_buses_on_the_same_interface_and_channel_are_refused(
    tmp_path: Path, channel_b: str
) -> None:
    text = GOOD + f'\n[buses.b]\ninterface = "virtual"\nchannel = {channel_b}\nbitrate = 500000\n'
    text += "[buses.b.nodes]\nj02r0 = 1\n"
    p = write(tmp_path, text)
    with pytest.raises(BusConfigError) as info:
        load_box_config(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: buses.b.channel: virtual channel 'x' is already bus a"), msg
    assert "\n" not in msg
    # The same channel on another interface is another bus.
    other = text.replace('[buses.b]\ninterface = "virtual"', '[buses.b]\ninterface = "hrm_sim"')
    assert [b.interface for b in load_box_config(write(tmp_path, other)).buses] == [
        "virtual",
        "hrm_sim",
    ]


def test_rewiring_onto_one_channel_is_refused() -> None:
    cfg = load_box_config(None)
    with pytest.raises(BusConfigError, match=r"buses\.can1\.channel: virtual channel 'v' is"):
        cfg.with_bus_kwargs([{"interface": "virtual", "channel": "v"}] * 2)
    two = cfg.with_bus_kwargs([{"interface": "virtual", "channel": f"v{k}"} for k in range(2)])
    assert [b.channel for b in two.buses] == ["v0", "v1"]


def test_bus_names_with_letters_digits_dash_underscore_load(tmp_path: Path) -> None:
    cfg = load_box_config(write(tmp_path, GOOD.replace("[buses.a", "[buses.Left_bus-2")))
    assert cfg.buses[0].name == "Left_bus-2"


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(BusConfigError, match="bus configuration not found"):
        load_box_config(tmp_path / "nope.toml")


def test_entry_point_interface_is_known(tmp_path: Path) -> None:
    cfg = load_box_config(write(tmp_path, GOOD.replace('"virtual"', '"hrm_sim"')))
    assert cfg.buses[0].interface == "hrm_sim"


def test_udp_multicast_stays_on_this_host_unless_the_file_says_otherwise(tmp_path: Path) -> None:
    """One hop_limit default (0) for host and simulator: both open buses from bus_kwargs()."""
    udp = GOOD.replace('"virtual"', '"udp_multicast"').replace('"x"', '"239.74.1.1"')
    cfg = load_box_config(write(tmp_path, udp))
    assert UDP_MULTICAST_HOP_LIMIT == 0
    assert cfg.buses[0].bus_kwargs()["hop_limit"] == 0
    assert cfg.buses[0].options == {}  # a default of bus_kwargs, not written into the file's
    explicit = udp.replace("bitrate = 1000000", "bitrate = 1000000\noptions = {hop_limit = 1}")
    assert load_box_config(write(tmp_path, explicit)).buses[0].bus_kwargs()["hop_limit"] == 1
    rewired = load_box_config(None).with_bus_kwargs(
        [{"interface": "udp_multicast", "channel": f"239.74.1.{k}"} for k in (1, 2)]
    )
    assert [b.bus_kwargs()["hop_limit"] for b in rewired.buses] == [0, 0]
    assert "hop_limit" not in load_box_config(write(tmp_path, GOOD)).buses[0].bus_kwargs()


def test_config_errors_name_the_key() -> None:
    """(Was the simulator's own parser test: the simulator now reads this configuration.)"""
    with pytest.raises(BusConfigError, match=r"buses.b.nodes.m: node id 0 outside 1..127"):
        box_config_from_dict(
            {
                "buses": {
                    "b": {"interface": "virtual", "channel": "x", "bitrate": 1, "nodes": {"m": 0}}
                }
            },
            "t",
        )
    with pytest.raises(BusConfigError, match="duplicate node id"):
        box_config_from_dict(
            {
                "buses": {
                    "b": {
                        "interface": "virtual",
                        "channel": "x",
                        "bitrate": 1,
                        "nodes": {"m": 1, "n": 1},
                    }
                }
            },
            "t",
        )


def test_worst_case_frame_bits() -> None:
    assert worst_case_frame_bits(8) == 135
    assert worst_case_frame_bits(0) == 55
    assert [worst_case_frame_bits(n) for n in range(9)] == sorted(
        worst_case_frame_bits(n) for n in range(9)
    )
    with pytest.raises(Exception, match=r"0\.\.8"):
        worst_case_frame_bits(9)


def test_one_bus_is_over_budget_two_fit() -> None:
    cfg = load_box_config(None)
    both = cfg.buses[0].nodes | {f"x{k}": k + 19 for k in range(18)}
    from dataclasses import replace

    one = replace(cfg.buses[0], nodes=both)
    assert bus_load(one, cfg.control).load > 0.7
    assert all(bus_load(b, cfg.control).fits for b in cfg.buses)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 120),
    bitrate=st.sampled_from([125_000, 250_000, 500_000, 1_000_000]),
    limit=st.floats(0.2, 1.0),
)
def test_highest_rate_that_fits_is_tight(n: int, bitrate: int, limit: float) -> None:
    cfg = load_box_config(None)
    from dataclasses import replace

    bus = replace(cfg.buses[0], nodes={f"m{k}": k + 1 for k in range(n)}, bitrate=bitrate)
    control = replace(cfg.control, bus_load_limit=limit)
    bl = bus_load(bus, control)
    if bl.max_rate_hz >= 1:
        assert bus_load(bus, replace(control, rate_hz=bl.max_rate_hz)).fits
    # the next rate the drives could take (0x60C2-encodable) no longer fits
    nxt = next(
        (r for r in range(int(bl.max_rate_hz) + 1, 10_001) if rate_problem(float(r)) is None),
        None,
    )
    if nxt is not None:
        assert not bus_load(bus, replace(control, rate_hz=float(nxt))).fits
    assert math.isclose(
        bl.load * bitrate,
        bl.bits_per_cycle * control.rate_hz + bl.heartbeat_bits_per_s,
    )


def test_check_bus_load_names_the_bus_and_rate() -> None:
    cfg = load_box_config(None).with_control(rate_hz=1000.0)
    with pytest.raises(BusLoadError, match=r"^bus can0: .* highest rate that fits: 125 Hz$"):
        check_bus_load(cfg)


def test_control_defaults_are_consistent() -> None:
    c = ControlConfig()
    assert c.period_s == pytest.approx(0.01)
    assert c.heartbeat_timeout_ms > max(c.host_heartbeat_ms, c.node_heartbeat_ms)
    # the defaults are a valid [control] table, and so is the shipped box.toml's
    assert (
        box_config_from_dict(
            {"control": {k: getattr(c, k) for k in ControlConfig.__dataclass_fields__}, **ONE_BUS},
            "t",
        ).control
        == c
    )
    assert load_box_config(None).control == c


# ---------------------------------------------------------------- safe ranges of [control]
ONE_BUS: dict[str, Any] = {
    "buses": {
        "a": {"interface": "virtual", "channel": "x", "bitrate": 1_000_000, "nodes": {"m": 1}}
    }
}

#: Values the other keys need for a key's bound to satisfy the relations between keys.
COMPANIONS: dict[tuple[str, str], dict[str, Any]] = {
    ("host_heartbeat_ms", "lo"): {"rate_hz": 100.0},
    ("host_heartbeat_ms", "hi"): {"heartbeat_timeout_ms": 1500},
    ("node_heartbeat_ms", "hi"): {"heartbeat_timeout_ms": 1500},
    ("heartbeat_timeout_ms", "lo"): {"host_heartbeat_ms": 10, "node_heartbeat_ms": 10},
    ("rate_hz", "hi"): {},
}


def control_error(tmp_path: Path, control: dict[str, Any]) -> str:
    """The one-line message of a box.toml whose [control] table is ``control``, or ''."""
    body = "\n".join(f"{k} = {v!r}" for k, v in control.items())
    text = GOOD.replace("rate_hz = 100", body or "rate_hz = 100")
    p = write(tmp_path, text.replace("j01r0 = 1\nj01r1 = 2", "j01r0 = 50\nj01r1 = 51"))
    try:
        load_box_config(p)
    except BusConfigError as exc:
        msg = str(exc)
        assert "\n" not in msg and msg.startswith(f"{p}: "), msg
        return msg
    return ""


def test_every_control_key_has_a_documented_range() -> None:
    assert set(CONTROL_RANGES) == set(ControlConfig.__dataclass_fields__)
    for key, rng in CONTROL_RANGES.items():
        assert rng.lo < rng.hi and len(rng.why) > 40, key
        default = getattr(ControlConfig(), key)
        assert rng.lo <= default <= rng.hi, key


@pytest.mark.parametrize("key", sorted(CONTROL_RANGES))
def test_each_bound_is_accepted_and_beyond_it_refused(tmp_path: Path, key: str) -> None:
    rng = CONTROL_RANGES[key]
    kind = int if isinstance(getattr(ControlConfig(), key), int) else float
    step = 1 if kind is int else 1e-6 * max(1.0, abs(rng.hi))
    for end, inside, outside in (("lo", rng.lo, rng.lo - step), ("hi", rng.hi, rng.hi + step)):
        others = COMPANIONS.get((key, end), {})
        value = kind(inside)
        if key == "rate_hz" and end == "lo":
            value = 10.0  # 0x60C2: 100 ms
        assert control_error(tmp_path, {**others, key: value}) == "", (key, end)
        msg = control_error(tmp_path, {**others, key: kind(outside)})
        assert f"control.{key} = {kind(outside)!r} outside {rng.text()}; " in msg, msg


@pytest.mark.parametrize(
    ("control", "expected"),
    [
        ({"missing_tpdo_cycles": 100000000}, "missing_tpdo_cycles = 100000000 outside 1..25"),
        ({"missing_tpdo_cycles": 1e8}, "missing_tpdo_cycles = 100000000.0 outside 1..25 cycles"),
        ({"missing_tpdo_cycles": 0}, "missing_tpdo_cycles = 0 outside 1..25"),
        ({"heartbeat_timeout_ms": 60000}, "heartbeat_timeout_ms = 60000 outside 30..2000 ms"),
        ({"sdo_timeout_s": 3600.0}, "sdo_timeout_s = 3600.0 outside 0.05..2 s"),
        ({"state_timeout_s": 0.0}, "state_timeout_s = 0.0 outside 0.05..5 s"),
        ({"bootup_timeout_s": 1e9}, "bootup_timeout_s = 1000000000.0 outside 0.1..30 s"),
        ({"quick_stop_option_code": 9}, "quick_stop_option_code = 9 outside 1..8; 0x605A"),
        ({"quick_stop_option_code": -1}, "quick_stop_option_code = -1 outside 1..8"),
        ({"quick_stop_option_code": 0}, "quick_stop_option_code = 0 outside 1..8; 0x605A"),
        (
            {"following_error_window_counts": 0xFFFFFFFF},
            "following_error_window_counts = 4294967295 outside 1..65536 counts; 0x6065",
        ),
        ({"following_error_window_counts": 0}, "following_error_window_counts = 0 outside"),
        ({"bus_load_limit": 1.0}, "bus_load_limit = 1.0 outside 0.05..0.9"),
        ({"realtime_priority": 99}, "realtime_priority = 99 outside 0..49"),
        ({"host_node_id": 0}, "host_node_id = 0 outside 1..127"),
        ({"rate_hz": 5}, "rate_hz = 5 outside 10..1000 Hz"),
        ({"rate_hz": 1e6}, "rate_hz = 1000000.0 outside 10..1000 Hz"),
        # relations: a watchdog cannot be stretched by combining values either
        (
            {"heartbeat_timeout_ms": 250},
            "heartbeat_timeout_ms = 250 must be at least 3 x host_heartbeat_ms (3 x 100 = 300",
        ),
        (
            {"node_heartbeat_ms": 200, "heartbeat_timeout_ms": 400},
            "heartbeat_timeout_ms = 400 must be at least 3 x node_heartbeat_ms (3 x 200 = 600",
        ),
        (
            {"rate_hz": 25, "missing_tpdo_cycles": 25},
            "missing_tpdo_cycles = 25 must keep the arm at most 0.5 s without feedback "
            "(25 cycles at 25 Hz are 1 s)",
        ),
        (
            {"rate_hz": 10, "host_heartbeat_ms": 50},
            "host_heartbeat_ms = 50 must be at least one control period (100 ms at 10 Hz)",
        ),
    ],
)  # fmt: skip
def test_unsafe_control_values_are_refused_in_one_line(
    tmp_path: Path, control: dict[str, Any], expected: str
) -> None:
    msg = control_error(tmp_path, control)
    assert expected in msg, msg


def test_an_integer_of_many_digits_is_refused_in_a_short_line() -> None:
    with pytest.raises(BusConfigError) as info:
        box_config_from_dict({"control": {"missing_tpdo_cycles": 10**400}, **ONE_BUS}, "t")
    msg = str(info.value)
    assert msg.startswith("t: control.missing_tpdo_cycles = 1000000000000000000... (401 digits)")
    assert len(msg) < 400 and "\n" not in msg


def test_the_quick_stop_range_is_what_the_eds_and_the_drive_allow() -> None:
    import canopen

    from drivers import eds_path
    from sim_bus.drive.state_machine import QUICK_STOP_OPTION_RANGE

    od = canopen.import_od(str(eds_path()), 1)
    rng = CONTROL_RANGES["quick_stop_option_code"]
    # the drive's codes but 0, which lets every motor coast
    assert range(int(rng.lo), int(rng.hi) + 1) == range(1, QUICK_STOP_OPTION_RANGE.stop)
    assert QUICK_STOP_OPTION_RANGE.start == 0
    qs = od[0x605A]
    assert qs.data_type == canopen.objectdictionary.INTEGER16
    lo = -(2**15) if qs.min is None else qs.min
    hi = 2**15 - 1 if qs.max is None else qs.max
    assert lo <= rng.lo and rng.hi <= hi
    fe = od[0x6065]
    assert fe.data_type == canopen.objectdictionary.UNSIGNED32
    fe_rng = CONTROL_RANGES["following_error_window_counts"]
    assert 0 < fe_rng.lo and fe_rng.hi < 0xFFFFFFFF  # 0xFFFFFFFF: the check switched off
    # the heartbeat values fit 0x1016 (UNSIGNED16 ms in its low word) and 0x1017
    assert CONTROL_RANGES["heartbeat_timeout_ms"].hi <= 0xFFFF
    assert od[0x1017].data_type == canopen.objectdictionary.UNSIGNED16
    assert CONTROL_RANGES["node_heartbeat_ms"].hi <= 0xFFFF


def test_rates_in_range_are_all_0x60C2_checked() -> None:
    accepted = [r for r in range(1, 2001) if rate_problem(float(r)) is None]
    assert min(accepted) == RATE_MIN_HZ and max(accepted) == RATE_MAX_HZ
    for r in accepted:
        value, _ = interpolation_time_period(1.0 / r)
        assert 1 <= value <= 255


def test_the_rigs_and_the_simulator_fit_the_ranges() -> None:
    """The kill -9 log test's relaxed watchdogs, the --sim TPDO tolerance and the watch
    benchmark's settings are all within the safe ranges (none needs a value this module
    refuses)."""
    from hrm_ctrl.cli._simwire import SIM_MISSING_TPDO_CYCLES
    from tests.drivers.test_canlog_durability import KILL_TEST_CONTROL

    cfg = load_box_config(None)
    assert cfg.with_control(**KILL_TEST_CONTROL).control.missing_tpdo_cycles == 25
    assert cfg.with_control(missing_tpdo_cycles=SIM_MISSING_TPDO_CYCLES)
    assert cfg.with_control(missing_tpdo_cycles=25, heartbeat_timeout_ms=1000)


def test_busload_and_run_refuse_the_same_file_before_any_bus_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import can

    from drivers import default_box_path
    from hrm_ctrl.cli import main

    opened: list[Any] = []

    def refuse(*args: Any, **kwargs: Any) -> None:
        opened.append(kwargs)
        raise AssertionError("a bus was opened")

    monkeypatch.setattr(can, "Bus", refuse)
    box = tmp_path / "box.toml"
    text = default_box_path().read_text()
    box.write_text(text.replace("missing_tpdo_cycles = 3 ", "missing_tpdo_cycles = 100000000 ", 1))
    assert "missing_tpdo_cycles = 100000000" in box.read_text()
    expected = f"{box}: control.missing_tpdo_cycles = 100000000 outside 1..25 cycles; "
    logs = tmp_path / "runs"
    for argv in (
        ["busload", "--config", str(box)],
        ["run", "--hold", "0.1", "--sim", "--config", str(box), "--log-dir", str(logs)],
        ["run", "--hold", "0.1", "--config", str(box), "--log-dir", str(logs)],
    ):
        rc = main(argv)
        err = capsys.readouterr().err
        assert rc == 2, (argv, err)
        assert expected in err and err.count("\n") == 1, err
    assert opened == [] and not logs.exists()
