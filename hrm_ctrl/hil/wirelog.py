"""Detection and stop times of a HIL run, read off its CAN logs (wire timestamps).

A session logs every frame on each bus (``<run>_<bus>.blf``, ``docs/drivers.md``): what
the host sent (SYNC, RPDOs, the quick stop) and what it received (TPDOs, heartbeats,
EMCYs).  From them:

* :meth:`WireLog.quick_stop` -- the host's first quick-stop RPDO (controlword 0x0002),
  the moment the fault was detected and acted on;
* :meth:`WireLog.last_received` -- e.g. a node's last heartbeat or TPDO before the stop
  (a fault's onset on the wire);
* :meth:`WireLog.syncs_sent` -- SYNCs on a bus between two moments (cycles without a TPDO);
* :meth:`WireLog.stop_confirmed` -- when every node that still answered showed (TPDO
  statusword) that it left OPERATION_ENABLED.

>>> import can
>>> qs = can.Message(arbitration_id=0x201, data=bytes([2, 0, 0, 0, 0, 0]), timestamp=2.0,
...                  is_rx=False)
>>> tp = can.Message(arbitration_id=0x181, data=bytes([0x37, 0x02, 0, 0, 0, 0]), timestamp=1.0)
>>> log = WireLog.from_frames({"can0": [tp, qs]})
>>> log.quick_stop().t_s, log.last_received("can0", 0x181, before_s=2.0).t_s
(2.0, 1.0)
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SYNC_COB_ID = 0x080
RPDO1_BASE = 0x200
TPDO1_BASE = 0x180
EMCY_BASE = 0x080
HEARTBEAT_BASE = 0x700
MAX_WIRE_FRAMES = 2_000_000  # frames of one run read at most (~4 min of the 36-drive arm at 100 Hz)


@dataclass(frozen=True, slots=True)
class WireFrame:
    """One frame of a CAN log: wire time (s, the log's clock), bus, COB-ID, data, direction."""

    t_s: float
    bus: str
    cob_id: int
    data: bytes
    sent: bool  # sent by the host (else received)


class WireLog:
    """The frames of every bus of one run, in time order."""

    def __init__(self, frames: Iterable[WireFrame]) -> None:
        self.frames = sorted(frames, key=lambda f: f.t_s)

    @classmethod
    def from_frames(cls, by_bus: Mapping[str, Iterable[Any]]) -> WireLog:
        """From python-can messages per bus name."""
        return cls(
            WireFrame(
                float(m.timestamp),
                bus,
                int(m.arbitration_id),
                bytes(m.data),
                not m.is_rx,
            )
            for bus, msgs in by_bus.items()
            for m in msgs
            if not m.is_error_frame
        )

    @classmethod
    def read(
        cls,
        paths: Sequence[str | Path],
        bus_names: Sequence[str],
        max_frames: int = MAX_WIRE_FRAMES,
    ) -> WireLog:
        """Read a run's logs (``record["can_logs"]``, in the configuration's bus order),
        at most ``max_frames`` frames in all; a log that cannot be read (damaged, not a
        regular file, too long) is one :class:`~hrm_ctrl.formats.runlog.RunLogError`."""
        from hrm_ctrl.errors import SimError
        from hrm_ctrl.formats.runlog import RunLogError, iter_can_log

        if len(paths) != len(bus_names):
            raise SimError(f"{len(paths)} CAN logs for {len(bus_names)} buses")
        count = 0

        def counted(path: str | Path) -> Iterator[Any]:
            nonlocal count
            for msg in iter_can_log(path, max_frames):
                count += 1
                if count > max_frames:
                    raise RunLogError(f"{path}: more than {max_frames} frames in all")
                yield msg

        frames: list[WireFrame] = []
        for path, bus in zip(paths, bus_names, strict=True):
            frames.extend(cls.from_frames({bus: counted(path)}).frames)
        return cls(frames)

    def quick_stop(self, after_s: float = float("-inf")) -> WireFrame | None:
        """The host's first quick-stop RPDO after ``after_s``."""
        from drivers.protocol.cia402 import Command402

        for f in self.frames:
            if (
                f.sent
                and f.t_s > after_s
                and RPDO1_BASE < f.cob_id <= RPDO1_BASE + 0x7F
                and len(f.data) >= 2
                and Command402.QUICK_STOP.matches(f.data[0] | f.data[1] << 8)
            ):
                return f
        return None

    def last_received(
        self, bus: str, cob_id: int, before_s: float, after_s: float = float("-inf")
    ) -> WireFrame | None:
        """The last frame ``cob_id`` received on ``bus`` in (``after_s``, ``before_s``)."""
        last = None
        for f in self.frames:
            if f.t_s >= before_s:
                break
            if not f.sent and f.bus == bus and f.cob_id == cob_id and f.t_s > after_s:
                last = f
        return last

    def syncs_sent(self, bus: str, after_s: float, until_s: float) -> int:
        """SYNCs the host sent on ``bus`` in (``after_s``, ``until_s``)."""
        return sum(
            1
            for f in self.frames
            if f.sent and f.bus == bus and f.cob_id == SYNC_COB_ID and after_s < f.t_s < until_s
        )

    def stop_confirmed(
        self, nodes: Mapping[str, Mapping[str, int]], after_s: float
    ) -> tuple[float | None, list[str]]:
        """When every node (``{bus: {motor: node}}``) that sent a TPDO after ``after_s``
        showed in one that it left OPERATION_ENABLED: (the latest such time, or None if
        no node answered; the motors that sent no TPDO after ``after_s``)."""
        from drivers.protocol.cia402 import State402, decode_state

        first: dict[str, float] = {}
        silent: list[str] = []
        for bus, bus_nodes in nodes.items():
            for motor, node in bus_nodes.items():
                seen = False
                for f in self.frames:
                    if (
                        f.t_s > after_s
                        and not f.sent
                        and f.bus == bus
                        and f.cob_id == TPDO1_BASE + node
                        and len(f.data) >= 2
                    ):
                        seen = True
                        state = decode_state(f.data[0] | f.data[1] << 8)
                        if state is not State402.OPERATION_ENABLED:
                            first[motor] = f.t_s
                            break
                if not seen:
                    silent.append(motor)
                elif motor not in first:
                    first[motor] = float("inf")  # answered, never left OPERATION_ENABLED
        return (max(first.values()) if first else None), silent
