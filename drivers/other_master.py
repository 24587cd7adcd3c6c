"""Another master, or another device, on the box's buses: what the session listens for
before it resets drives, refuses an enable on, and names beside a stop.

* Before the first NMT reset of drives this session has not brought up it listens
  (:func:`listen_for_other_masters`): heartbeats of nodes in NMT operational, a SYNC
  producer, RPDOs, node guarding.  Heard: :class:`OtherMasterError` (nothing is reset)
  unless the operator takes over.
* After the reset, host-direction frames this host did not send (:func:`foreign_frames`)
  refuse the enable.
* A node that boots more than once after one reset is two devices answering as one
  (:func:`duplicate_boot_text`); one whose second boot-up comes after the configuration
  began is when it also answers one SDO request twice
  (:meth:`drivers.drive_group.DriveGroup.refuse_late_duplicates`).
* A stopped stream's buses carrying at least a frame per cycle of nodes not in the
  configuration (:func:`unconfigured_traffic`): a babbling device is named beside the
  watchdog it tripped.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.cycle import EventLog
from drivers.receive import BusReceiver, wait_quiet_listen
from hrm_ctrl.errors import DriverError


class OtherMasterError(DriverError):
    """Another master is active on the box's buses: its drives are not reset.  ``heard``
    says what gave it away (per bus)."""

    def __init__(self, message: str, heard: str = "") -> None:
        super().__init__(message)
        self.heard = heard


def listen_for_other_masters(
    receivers: Sequence[BusReceiver], listen_s: float, take_over: bool, events: EventLog
) -> None:
    """Listen ``listen_s`` on every bus; another master heard raises
    :class:`OtherMasterError` unless ``take_over`` (logged either way)."""
    heard = wait_quiet_listen(list(receivers), listen_s)
    if heard is None:
        events.add("listen", f"no other master heard in {listen_s:g} s")
        return
    if take_over:
        events.add("take_over", f"another master heard, taken over: {heard}")
        return
    text = (
        f"another master is active: {heard}; not resetting its drives "
        "(take over explicitly to reset them anyway)"
    )
    events.add("error", text)
    raise OtherMasterError(text, heard)


def foreign_frames(receivers: Sequence[BusReceiver]) -> str | None:
    """The host-direction frames heard that this host did not send, per bus (COB-ID and
    count); None: none."""
    heard = [
        f"bus {r.port.name}: "
        + ", ".join(f"0x{cid:03X} x{n}" for cid, n in sorted(r.traffic.foreign.items()))
        for r in receivers
        if r.traffic.foreign
    ]
    return "; ".join(heard) if heard else None


def duplicate_boot_text(duplicates: Sequence[str]) -> str | None:
    """The refusal for nodes that booted more than once after one NMT reset (a second box,
    a simulator on the same bus, a node-id clash); None: none did.

    >>> duplicate_boot_text([]) is None
    True
    >>> duplicate_boot_text(["a", "b", "c", "d", "e"]).endswith("a; b; c; d (+1 more)")
    True
    """
    if not duplicates:
        return None
    more = f" (+{len(duplicates) - 4} more)" if len(duplicates) > 4 else ""
    return (
        f"more than one device answers as the same node ({len(duplicates)} node(s) booted "
        "more than once after one NMT reset: a second box or a node-id clash on "
        "the bus): " + "; ".join(duplicates[:4]) + more
    )


def unconfigured_counts(receivers: Sequence[BusReceiver]) -> list[dict[int, int]]:
    """Per bus, the frames counted so far of nodes not in the configuration, by COB-ID."""
    return [r.traffic.unconfigured_counts() for r in receivers]


def unconfigured_traffic(
    receivers: Sequence[BusReceiver], before: Sequence[dict[int, int]], cycles: int
) -> str | None:
    """What the buses carried since ``before`` (:func:`unconfigured_counts`) from nodes
    not in the configuration, when that was at least one frame per control cycle (of
    ``cycles``): the three busiest COB-IDs per bus.  None: no such traffic."""
    parts = []
    for r, was in zip(receivers, before, strict=True):
        now = r.traffic.unconfigured_counts()
        grown = {cid: n - was.get(cid, 0) for cid, n in now.items() if n > was.get(cid, 0)}
        total = sum(grown.values())
        if total and total >= max(1, cycles):
            top = sorted(grown.items(), key=lambda kv: -kv[1])[:3]
            parts.append(
                f"bus {r.traffic.bus} carried {total} frame(s) of nodes not in the "
                "configuration during the stream: "
                + ", ".join(f"0x{cid:03X} x{n}" for cid, n in top)
            )
    return "; ".join(parts) if parts else None
