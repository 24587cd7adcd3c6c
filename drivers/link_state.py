"""A SocketCAN interface's link state, as ``ip -details -json link show DEV`` gives it.

The kernel's CAN drivers keep each controller's state (ERROR-ACTIVE, ERROR-WARNING,
ERROR-PASSIVE, BUS-OFF, STOPPED, SLEEPING: iproute2's names), its error counters, bitrate
and automatic restart; ``ip -details -json link show DEV`` reports them under
``linkinfo.info_data`` (iproute2's ``iplink_can.c``).  vcan has no controller and no
state ("no CAN state (virtual)").  ``hrm status`` and the console's ``status`` show one
line per SocketCAN bus (:func:`link_status_line`).

:func:`parse_ip_link_json` is pure (tested on recorded output); :func:`read_link_state`
runs ``ip`` once, bounded by a timeout; a missing ``ip``, a device that does not exist,
a timeout or output that is not iproute2's JSON is a one-line :class:`LinkStateError`.

>>> text = ('[{"ifname":"can0","flags":["NOARP","UP","LOWER_UP","ECHO"],"operstate":"UP",'
...         '"linkinfo":{"info_kind":"can","info_data":{"state":"ERROR-PASSIVE",'
...         '"berr_counter":{"tx":128,"rx":0},"restart_ms":100,'
...         '"bittiming":{"bitrate":1000000,"sample_point":0.875}}}}]')
>>> parse_ip_link_json(text, "can0").describe()
'can0 up, ERROR-PASSIVE (tx errors 128, rx errors 0), 1000 kbit/s, restart-ms 100'
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hrm_ctrl.errors import DriverError

#: iproute2's ``can_state_names`` (``enum can_state`` of linux/can/netlink.h, in order)
CAN_STATES = ("ERROR-ACTIVE", "ERROR-WARNING", "ERROR-PASSIVE", "BUS-OFF", "STOPPED", "SLEEPING")
#: states in which the controller does not take part in the bus as it should
TROUBLE_STATES = frozenset({"ERROR-PASSIVE", "BUS-OFF", "STOPPED"})
IP_TIMEOUT_S = 2.0  # ``ip`` answers in milliseconds; a process start in the vcan guest ~0.2 s
VIRTUAL_KINDS = frozenset({"vcan", "vxcan"})


class LinkStateError(DriverError):
    """The link state of a SocketCAN interface could not be read (one line)."""


@dataclass(frozen=True)
class LinkState:
    """One interface: its name, link kind (``can``, ``vcan``; None: not reported),
    operational state (``UP``, ``DOWN``, ``UNKNOWN``: vcan), whether it is set up, and,
    where the driver reports them, the controller's CAN state, error counters, bitrate
    (bit/s) and automatic restart (ms; 0: off)."""

    device: str
    kind: str | None
    operstate: str
    up: bool
    can_state: str | None = None
    tx_errors: int | None = None
    rx_errors: int | None = None
    bitrate: int | None = None
    restart_ms: int | None = None

    @property
    def trouble(self) -> bool:
        """The controller is error-passive, bus-off or stopped (or the link is down).

        >>> LinkState("can0", "can", "UP", True, "BUS-OFF").trouble
        True
        >>> LinkState("vcan0", "vcan", "UNKNOWN", True).trouble
        False
        """
        return not self.up or self.can_state in TROUBLE_STATES

    def describe(self) -> str:
        """One line: name, up or down, the CAN state and what goes with it.

        >>> LinkState("vcan0", "vcan", "UNKNOWN", True).describe()
        'vcan0 up, no CAN state (virtual)'
        >>> LinkState("can1", "can", "DOWN", False, "STOPPED", bitrate=500000).describe()
        'can1 DOWN, STOPPED, 500 kbit/s'
        """
        parts = [f"{self.device} {'up' if self.up else 'DOWN'}"]
        if self.can_state is None:
            virtual = self.kind in VIRTUAL_KINDS
            parts.append("no CAN state (virtual)" if virtual else "no CAN state reported")
        elif self.tx_errors is not None and self.rx_errors is not None:
            parts.append(
                f"{self.can_state} (tx errors {self.tx_errors}, rx errors {self.rx_errors})"
            )
        else:
            parts.append(self.can_state)
        if self.bitrate:
            parts.append(f"{self.bitrate / 1000:g} kbit/s")
        if self.restart_ms is not None:
            parts.append(f"restart-ms {self.restart_ms}" if self.restart_ms else "no auto-restart")
        return ", ".join(parts)


def _int_or_none(doc: dict[str, Any], key: str) -> int | None:
    value = doc.get(key)
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def parse_ip_link_json(text: str, device: str) -> LinkState:
    """The :class:`LinkState` of ``device`` in the output of ``ip -details -json link
    show DEV``; a :class:`LinkStateError` naming the device when it is not that.

    >>> parse_ip_link_json("state UP [", "can0")
    Traceback (most recent call last):
    ...
    drivers.link_state.LinkStateError: ip link show can0: output is not iproute2's JSON ...
    >>> parse_ip_link_json('[{"ifname": "can1"}]', "can0")
    Traceback (most recent call last):
    ...
    drivers.link_state.LinkStateError: ip link show can0: no entry for can0 in its output
    """
    where = f"ip link show {device}"
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise LinkStateError(
            f"{where}: output is not iproute2's JSON ({exc}; an older iproute2 printed "
            "the CAN state as text inside it)"
        ) from None
    entries = doc if isinstance(doc, list) else []
    entry = next((e for e in entries if isinstance(e, dict) and e.get("ifname") == device), None)
    if entry is None:
        raise LinkStateError(f"{where}: no entry for {device} in its output")
    flags = entry.get("flags")
    flags = [f for f in flags if isinstance(f, str)] if isinstance(flags, list) else []
    operstate = entry.get("operstate")
    linkinfo = entry.get("linkinfo")
    linkinfo = linkinfo if isinstance(linkinfo, dict) else {}
    kind = linkinfo.get("info_kind")
    data = linkinfo.get("info_data")
    data = data if isinstance(data, dict) else {}
    state = data.get("state")
    berr = data.get("berr_counter")
    berr = berr if isinstance(berr, dict) else {}
    timing = data.get("bittiming")
    timing = timing if isinstance(timing, dict) else {}
    bitrate = _int_or_none(timing, "bitrate")
    if bitrate is None:  # a controller with fixed bitrates reports it beside them
        bitrate = _int_or_none(data, "bittiming_bitrate")
    return LinkState(
        device=device,
        kind=kind if isinstance(kind, str) else None,
        operstate=operstate if isinstance(operstate, str) else "UNKNOWN",
        up="UP" in flags,
        can_state=state if isinstance(state, str) else None,
        tx_errors=_int_or_none(berr, "tx"),
        rx_errors=_int_or_none(berr, "rx"),
        bitrate=bitrate,
        restart_ms=_int_or_none(data, "restart_ms"),
    )


Runner = Callable[..., "subprocess.CompletedProcess[str]"]


def read_link_state(
    device: str, timeout_s: float = IP_TIMEOUT_S, run: Runner = subprocess.run
) -> LinkState:
    """Run ``ip -details -json link show DEVICE`` (at most ``timeout_s``) and parse it;
    a :class:`LinkStateError` in one line when ``ip`` is missing, fails or hangs.

    >>> def no_ip(*args, **kwargs):
    ...     raise FileNotFoundError(2, "No such file or directory", "ip")
    >>> read_link_state("can0", run=no_ip)
    Traceback (most recent call last):
    ...
    drivers.link_state.LinkStateError: ip not found (install iproute2): no link state of can0
    """
    argv = ["ip", "-details", "-json", "link", "show", "dev", device]
    try:
        done = run(argv, capture_output=True, text=True, timeout=timeout_s, check=False)
    except FileNotFoundError:
        raise LinkStateError(
            f"ip not found (install iproute2): no link state of {device}"
        ) from None
    except subprocess.TimeoutExpired:
        raise LinkStateError(f"ip link show {device}: no answer within {timeout_s:g} s") from None
    except OSError as exc:
        raise LinkStateError(f"ip link show {device}: cannot run ip ({exc})") from None
    if done.returncode != 0:
        lines = (done.stderr or "").strip().splitlines()
        why = lines[0] if lines else f"exit status {done.returncode}"
        raise LinkStateError(f"ip link show {device}: {why}")
    return parse_ip_link_json(done.stdout, device)


def link_status_line(device: str, run: Runner = subprocess.run) -> str:
    """What a status shows for a SocketCAN interface: its :meth:`LinkState.describe`, or
    why it could not be read (the :class:`LinkStateError`'s line).

    >>> def missing(*args, **kwargs):
    ...     return subprocess.CompletedProcess(args, 1, "", 'Device "can9" does not exist.\\n')
    >>> link_status_line("can9", run=missing)
    'ip link show can9: Device "can9" does not exist.'
    """
    try:
        return read_link_state(device, run=run).describe()
    except LinkStateError as exc:
        return str(exc)
