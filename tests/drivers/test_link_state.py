"""A SocketCAN interface's link state from ``ip -details -json link show DEV``: the pure
parser on recorded and written samples (``tests/drivers/ip_link/``), the bounded call of
``ip`` and its one-line errors, and the line ``hrm status`` and the console show."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.busload import bus_loads
from drivers.config import box_config_from_dict
from drivers.link_state import (
    CAN_STATES,
    LinkState,
    LinkStateError,
    link_status_line,
    parse_ip_link_json,
    read_link_state,
)
from drivers.status import BusStatus, SessionStatus, bus_statuses

SAMPLES = Path(__file__).parent / "ip_link"


@pytest.mark.parametrize(
    ("sample", "device", "want", "line"),
    [
        (
            "vcan0.json", "vcan0",
            LinkState("vcan0", "vcan", "UNKNOWN", True),
            "vcan0 up, no CAN state (virtual)",
        ),
        (
            "can0_gs_usb_error_active.json", "can0",
            LinkState("can0", "can", "UP", True, "ERROR-ACTIVE", 0, 0, 1_000_000, 100),
            "can0 up, ERROR-ACTIVE (tx errors 0, rx errors 0), 1000 kbit/s, restart-ms 100",
        ),
        (
            "can1_peak_usb_error_passive.json", "can1",
            LinkState("can1", "can", "UP", True, "ERROR-PASSIVE", 128, 0, 1_000_000, 0),
            "can1 up, ERROR-PASSIVE (tx errors 128, rx errors 0), 1000 kbit/s, no auto-restart",
        ),
        (
            "can0_mcp251x_bus_off.json", "can0",
            LinkState("can0", "can", "UP", True, "BUS-OFF", 248, 0, 500_000, 0),
            "can0 up, BUS-OFF (tx errors 248, rx errors 0), 500 kbit/s, no auto-restart",
        ),
        (
            "can0_down_stopped.json", "can0",
            LinkState("can0", "can", "DOWN", False, "STOPPED", None, None, 1_000_000, 0),
            "can0 DOWN, STOPPED, 1000 kbit/s, no auto-restart",
        ),
    ],
)  # fmt: skip
def test_samples_parse_to_their_state_and_line(
    sample: str, device: str, want: LinkState, line: str
) -> None:
    got = parse_ip_link_json((SAMPLES / sample).read_text(), device)
    assert got == want
    assert got.describe() == line
    assert got.trouble == (want.can_state in ("ERROR-PASSIVE", "BUS-OFF", "STOPPED") or not got.up)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "not iproute2's JSON"),
        ('[{"ifname":"can0","linkinfo":{"info_data":{"state"', "not iproute2's JSON"),
        ('{"ifname": "can0"}', "no entry for can0"),
        ("[]", "no entry for can0"),
        ('[{"ifname": "can1"}]', "no entry for can0"),
    ],
)
def test_output_that_is_not_a_link_of_the_device_is_a_one_line_error(
    text: str, message: str
) -> None:
    with pytest.raises(LinkStateError) as info:
        parse_ip_link_json(text, "can0")
    assert message in str(info.value) and "\n" not in str(info.value)
    assert str(info.value).startswith("ip link show can0: ")


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.text(max_size=5),
    lambda kids: (
        st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=8), kids, max_size=3)
    ),
    max_leaves=12,
)


@given(
    entry=st.fixed_dictionaries(
        {"ifname": st.just("can0")},
        optional={
            "flags": json_values,
            "operstate": json_values,
            "linkinfo": st.fixed_dictionaries(
                {},
                optional={
                    "info_kind": json_values,
                    "info_data": st.fixed_dictionaries(
                        {},
                        optional={
                            "state": st.sampled_from(CAN_STATES) | json_values,
                            "berr_counter": json_values,
                            "restart_ms": json_values,
                            "bittiming": json_values,
                        },
                    )
                    | json_values,
                },
            )
            | json_values,
        },
    )
)
def test_any_json_entry_of_the_device_parses_or_is_a_one_line_error(entry: dict[str, Any]) -> None:
    """Fields of any JSON type where iproute2 puts its own: a state, never a crash."""
    got = parse_ip_link_json(json.dumps([entry]), "can0")
    assert got.device == "can0" and "\n" not in got.describe()
    assert got.can_state is None or isinstance(got.can_state, str)


def runner(code: int = 0, out: str = "", err: str = "", raises: Exception | None = None) -> Any:
    calls: list[dict[str, Any]] = []

    def run(argv: list[str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
        calls.append({"argv": argv, **kwargs})
        if raises is not None:
            raise raises
        return subprocess.CompletedProcess(argv, code, out, err)

    run.calls = calls  # type: ignore[attr-defined]
    return run


def test_ip_is_run_once_bounded_by_a_timeout() -> None:
    run = runner(out=(SAMPLES / "vcan0.json").read_text())
    assert read_link_state("vcan0", timeout_s=0.5, run=run).kind == "vcan"
    (call,) = run.calls
    assert call["argv"] == ["ip", "-details", "-json", "link", "show", "dev", "vcan0"]
    assert call["timeout"] == 0.5 and call["check"] is False


@pytest.mark.parametrize(
    ("run", "line"),
    [
        (
            runner(raises=FileNotFoundError(2, "No such file or directory", "ip")),
            "ip not found (install iproute2): no link state of can0",
        ),
        (
            runner(raises=subprocess.TimeoutExpired(["ip"], 2.0)),
            "ip link show can0: no answer within 2 s",
        ),
        (
            runner(code=1, err='Device "can0" does not exist.\n'),
            'ip link show can0: Device "can0" does not exist.',
        ),
        (runner(code=255), "ip link show can0: exit status 255"),
        (runner(raises=PermissionError(13, "Permission denied")), "cannot run ip"),
    ],
)
def test_a_failing_ip_is_a_one_line_status(run: Any, line: str) -> None:
    got = link_status_line("can0", run=run)
    assert line in got and "\n" not in got


def test_a_socketcan_bus_status_carries_its_link_line_and_others_none() -> None:
    cfg = box_config_from_dict(
        {
            "buses": {
                "bus0": {
                    "interface": "socketcan",
                    "channel": "hrmnosuch0",
                    "bitrate": 1000000,
                    "nodes": {"j01r0": 1},
                },
                "bus1": {
                    "interface": "virtual",
                    "channel": "x",
                    "bitrate": 1000000,
                    "nodes": {"j01r1": 2},
                },
            }
        },
        "<test>",
    )
    st_ = bus_statuses(cfg.buses, bus_loads(cfg), [], [], [])
    assert st_[1].link is None
    line = st_[0].link
    assert line is not None and "\n" not in line
    if shutil.which("ip") is None:
        assert line == "ip not found (install iproute2): no link state of hrmnosuch0"
    else:
        assert line.startswith("ip link show hrmnosuch0: ")  # no such device


@pytest.mark.parametrize("can_backend", ["socketcan"], indirect=True)
def test_a_vcan_bus_reads_as_virtual(can_backend: Any) -> None:
    """The real ``ip`` on a real vcan (here: in the vcan guest)."""
    channel = can_backend()["channel"]
    assert link_status_line(channel) == f"{channel} up, no CAN state (virtual)"


def test_the_consoles_bus_line_ends_with_the_link_state() -> None:
    from hrm_ctrl.cli._console.commands_session import format_status

    bus = BusStatus("bus0", 1_000_000, 0.4, 0.7, 12, 0, 0, 0, None, "can0 up, BUS-OFF")
    st_ = SessionStatus(
        "READY", "none", (), (), (bus, dataclasses.replace(bus, link=None)), 0.0, False
    )
    lines = [line for line in format_status(st_, None) if line.startswith("bus ")]
    assert lines[0].endswith(
        ", error frames 0, foreign frames 0, log lost 0; link can0 up, BUS-OFF"
    )
    assert lines[1].endswith("log lost 0")
