"""python-can's conventions in the bus configuration (issue 11): a bus without an
``interface`` takes python-can's configuration (``~/can.conf``, ``CAN_*`` variables),
``--bus NAME=INTERFACE:CHANNEL[@BITRATE]`` replaces one bus, ``box_udp.toml`` ships.

Every test points ``HOME`` at a temporary folder and clears the ``CAN_*`` variables, so
the machine's own python-can configuration never enters.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import can
import pytest

from drivers import default_box_path
from drivers.config import (
    UDP_MULTICAST_HOP_LIMIT,
    BusConfigError,
    box_config_from_dict,
    load_box_config,
    parse_bus_override,
)
from tests.hrm_ctrl.cli.cli_helpers import run_cli

BOX_UDP = default_box_path().with_name("box_udp.toml")

# Two buses without an interface; can1 gives its own channel.
NO_INTERFACE = """
[buses.can0.nodes]
j01r0 = 1

[buses.can1]
channel = "from-the-file"

[buses.can1.nodes]
j07r0 = 1
"""


@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A home folder of its own, no CAN_* variable, no can.rc, no system-wide can.conf."""
    if Path("/etc/can.conf").exists():  # python-can reads it after ~/can.conf
        pytest.skip("/etc/can.conf exists on this machine")
    folder = tmp_path / "home"
    folder.mkdir()
    monkeypatch.setenv("HOME", str(folder))
    for name in list(os.environ):
        if name.startswith("CAN_"):
            monkeypatch.delenv(name)
    monkeypatch.setattr(can, "rc", {})
    return folder


@pytest.fixture
def no_bus(monkeypatch: pytest.MonkeyPatch) -> list[dict]:
    """Every attempt to open a CAN bus, recorded and refused."""
    opened: list[dict] = []

    def refuse(*args: object, **kwargs: object) -> None:
        opened.append(dict(kwargs))
        raise AssertionError(f"a bus was opened: {kwargs}")

    monkeypatch.setattr(can, "Bus", refuse)
    return opened


def write(tmp_path: Path, text: str, name: str = "box.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_can_conf_default_section_fills_a_bus_without_interface(home: Path, tmp_path: Path) -> None:
    (home / "can.conf").write_text(
        "[default]\ninterface = virtual\nchannel = conf-ch\nbitrate = 500000\n"
        "receive_own_messages = False\n"
    )
    cfg = load_box_config(write(tmp_path, NO_INTERFACE))
    can0, can1 = cfg.buses
    assert (can0.interface, can0.channel, can0.bitrate) == ("virtual", "conf-ch", 500_000)
    assert can1.channel == "from-the-file" and can1.bitrate == 500_000  # the file's wins
    # other keys of python-can's configuration become can.Bus keyword arguments
    assert can0.options == {"receive_own_messages": False}
    assert can0.bus_kwargs()["receive_own_messages"] is False


def test_can_conf_section_named_after_the_bus_wins_over_default(home: Path, tmp_path: Path) -> None:
    (home / "can.conf").write_text(
        "[default]\ninterface = virtual\nchannel = d\nbitrate = 500000\n"
        "[can1]\ninterface = udp_multicast\nbitrate = 250000\n"
    )
    cfg = load_box_config(write(tmp_path, NO_INTERFACE.replace('"from-the-file"', '"239.74.9.1"')))
    assert [b.interface for b in cfg.buses] == ["virtual", "udp_multicast"]
    assert [b.bitrate for b in cfg.buses] == [500_000, 250_000]
    # a udp_multicast bus from python-can's configuration stays on this host too
    assert cfg.buses[1].bus_kwargs()["hop_limit"] == UDP_MULTICAST_HOP_LIMIT == 0


def test_can_variables_are_honoured_and_win_over_can_conf(
    home: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (home / "can.conf").write_text("[default]\ninterface = socketcan\nchannel = conf\n")
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "env-ch")
    monkeypatch.setenv("CAN_BITRATE", "125000")
    monkeypatch.setenv("CAN_CHANNEL_can1", "env-can1")  # per bus: the bus name as context
    text = NO_INTERFACE.replace('channel = "from-the-file"\n', "")
    cfg = load_box_config(write(tmp_path, text))
    assert [(b.interface, b.channel, b.bitrate) for b in cfg.buses] == [
        ("virtual", "env-ch", 125_000),
        ("virtual", "env-can1", 125_000),
    ]


def test_a_bus_with_an_interface_ignores_python_cans_configuration(
    home: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "socketcan")
    monkeypatch.setenv("CAN_CHANNEL", "can9")
    cfg = load_box_config(None)
    assert [(b.interface, b.channel) for b in cfg.buses] == [
        ("socketcan", "can0"),
        ("socketcan", "can1"),
    ]


@pytest.mark.parametrize(
    ("conf", "env", "expected"),
    [
        ("", {}, "buses.can0: no interface in the file and none python-can can use"),
        ("[default]\ninterface = nosuch\n", {}, 'Unknown interface type "nosuch"'),
        ("[default]\ninterface = virtual\n", {}, "buses.can0: interface 'virtual' from python"),
        ("", {"CAN_CONFIG": "{not json"}, "buses.can0: python-can's configuration: JSONDecode"),
    ],
    ids=["nothing", "unknown", "no-channel", "bad-json"],
)
def test_python_cans_configuration_missing_or_bad_is_one_line(
    home: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    conf: str,
    env: dict[str, str],
    expected: str,
) -> None:
    if conf:
        (home / "can.conf").write_text(conf)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    path = write(tmp_path, NO_INTERFACE)
    with pytest.raises(BusConfigError, match=r"buses\.can0") as info:
        load_box_config(path)
    assert expected in str(info.value) and "\n" not in str(info.value)
    rc, out, err = run_cli(["busload", "--config", str(path)], capsys)
    assert rc == 2 and out == "" and err.count("\n") == 1 and expected in err, err
    if expected.startswith("buses.can0: no interface"):
        assert "CAN_INTERFACE_can0 or CAN_INTERFACE" in err and "~/can.conf" in err


@pytest.mark.parametrize(
    ("text", "name", "interface", "channel", "bitrate"),
    [
        ("can0=socketcan:vcan3", "can0", "socketcan", "vcan3", None),
        ("can1=virtual:left@500000", "can1", "virtual", "left", 500_000),
        ("can0=kvaser:0@1000000", "can0", "kvaser", 0, 1_000_000),
        ("b-2=udp_multicast:ff15:7079::1", "b-2", "udp_multicast", "ff15:7079::1", None),
        ("can0=slcan:/dev/ttyACM0@115200@500000", "can0", "slcan", "/dev/ttyACM0@115200", 500_000),
    ],
)
def test_bus_override_good_forms(
    text: str, name: str, interface: str, channel: str | int, bitrate: int | None
) -> None:
    o = parse_bus_override(text)
    assert (o.name, o.interface, o.channel, o.bitrate) == (name, interface, channel, bitrate)


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("can0", "expected NAME=INTERFACE:CHANNEL[@BITRATE]"),
        ("can0=socketcan", "expected NAME=INTERFACE:CHANNEL[@BITRATE]"),
        ("=socketcan:can0", "expected NAME=INTERFACE:CHANNEL[@BITRATE]"),
        ("can0=:can0", "expected NAME=INTERFACE:CHANNEL[@BITRATE]"),
        ("can 0=virtual:x", "bus name 'can 0' may only use"),
        ("can0=virtual:x@fast", "bitrate 'fast' after '@' must be an integer"),
        ("can0=virtual:x@0", "bitrate 0 outside 1..1000000"),
        ("can0=virtual:x@2000000", "bitrate 2000000 outside 1..1000000"),
        ("can0=virtual:x@" + "9" * 5000, "outside 1..1000000"),
        ("can0=virtual:@500000", "must be an integer"),
        ("can7=virtual:x", "--bus can7=virtual:x: no bus 'can7' in <default box.toml>"),
        ("can0=nosuch:x", "--bus can0=nosuch:x: unknown python-can interface 'nosuch'"),
        ("can0=socketcan:can1", "channel 'can1' is already bus can0"),
    ],
)
def test_bad_bus_override_is_one_line_exit_2_naming_the_option(
    home: Path, capsys: pytest.CaptureFixture[str], no_bus: list, value: str, expected: str
) -> None:
    rc, out, err = run_cli(["busload", "--bus", value], capsys)
    assert rc == 2 and out == "", err
    assert err.count("\n") == 1 and "--bus" in err and expected in err, err
    assert "Traceback" not in err and no_bus == []


def test_bus_overrides_keep_the_nodes_swap_channels_and_refuse_a_bus_twice() -> None:
    cfg = load_box_config(None)
    swapped = cfg.with_bus_overrides(
        [parse_bus_override("can0=socketcan:can1"), parse_bus_override("can1=socketcan:can0")]
    )
    assert [b.channel for b in swapped.buses] == ["can1", "can0"]
    assert [b.nodes for b in swapped.buses] == [b.nodes for b in cfg.buses]
    assert swapped.location("j07r0") == cfg.location("j07r0") == (1, 1)
    with pytest.raises(BusConfigError, match="bus can0 is already given as can0=virtual:a"):
        cfg.with_bus_overrides(
            [parse_bus_override("can0=virtual:a"), parse_bus_override("can0=virtual:b")]
        )


def test_an_override_on_another_interface_drops_the_files_options() -> None:
    udp = load_box_config(BOX_UDP)
    same = udp.with_bus_overrides([parse_bus_override("can0=udp_multicast:239.74.163.9")])
    assert same.buses[0].options == {"hop_limit": 0, "port": 43113}  # same interface: kept
    other = udp.with_bus_overrides([parse_bus_override("can0=virtual:v0@500000")])
    assert other.buses[0].options == {} and other.buses[0].bitrate == 500_000
    assert other.buses[0].bus_kwargs() == {
        "interface": "virtual",
        "channel": "v0",
        "bitrate": 500_000,
    }
    assert other.buses[1] == udp.buses[1]


def test_box_udp_ships_with_hop_limit_0_a_group_and_a_port_per_bus() -> None:
    cfg = load_box_config(BOX_UDP)
    default = load_box_config(None)
    assert [b.nodes for b in cfg.buses] == [b.nodes for b in default.buses]  # the same box
    assert {b.interface for b in cfg.buses} == {"udp_multicast"}
    kwargs = [b.bus_kwargs() for b in cfg.buses]
    assert [kw["hop_limit"] for kw in kwargs] == [0, 0]
    assert len({kw["channel"] for kw in kwargs}) == 2 and len({kw["port"] for kw in kwargs}) == 2
    # without hop_limit in the file the host's default is the same 0
    doc = tomllib.loads(BOX_UDP.read_text())
    for bus in doc["buses"].values():
        del bus["options"]["hop_limit"]
    bare = box_config_from_dict(doc, "box_udp.toml without hop_limit")
    assert [b.bus_kwargs()["hop_limit"] for b in bare.buses] == [0, 0]
    assert [b.options for b in bare.buses] == [{"port": 43113}, {"port": 43114}]
