"""NMT slave and heartbeat of a simulated drive (CiA 301 7.2.8 / 7.2.8.3).

Node control (start, stop, pre-operational, reset node, reset communication),
the boot-up frame, the heartbeat producer (0x1017) and the heartbeat consumer
(0x1016): after the first heartbeat of a monitored node, silence longer than
its time raises EMCY 0x8130 (error register bits 0 and 4, statusword warning)
and a quick stop; the next heartbeat clears it (EMCY 0x0000).  Leaving NMT
operational while operation is enabled quick-stops the drive too.

Node guarding (CiA 301 7.2.8.3.1), on a drive whose file has 0x100C (guard time) and
0x100D (life time factor): a remote frame on 0x700 + node id is answered with one byte,
the NMT state and the toggle bit (bit 7: 0 in the first answer after a reset of
communication, then alternating); once guarded (the first request), no request within
guard time x life time factor is a life-guarding event, raised as a lost heartbeat
(EMCY 0x8130, quick stop) and cleared by the next request.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import can

from drivers.protocol import cia301, cia402
from sim_bus.drive.objects import SdoAbort

if TYPE_CHECKING:
    from sim_bus.drive import DriveSim

State = cia402.State402
OD_GUARD_TIME = 0x100C
OD_LIFE_TIME_FACTOR = 0x100D


class NmtSlave:
    """The NMT state machine and the heartbeat producer/consumer of one drive."""

    def __init__(self, drive: DriveSim) -> None:
        self._drive = drive
        self._od = drive.od
        self.state = cia301.NMT_STATE_PRE_OPERATIONAL
        self.heartbeat_enabled = True  # fault injection: False silences the producer
        self._hb_next = math.inf
        self._hb_seen: dict[int, float] = {}
        self._hb_lost: set[int] = set()
        self._monitored: dict[int, float] = {}
        self._monitored_at = -1  # the OD generation _monitored was read at
        self.guarding_enabled = True  # fault injection: False: requests heard, not answered
        self._toggle = 0  # the toggle bit of the next node-guarding answer
        self._guarded_at: float | None = None  # the last guarding request (None: not guarded)
        self._life_lost = False

    @property
    def guardable(self) -> bool:
        """Whether the drive's file offers node guarding (0x100C and 0x100D)."""
        values = self._od.values
        return (OD_GUARD_TIME, 0) in values and (OD_LIFE_TIME_FACTOR, 0) in values

    def life_time_s(self) -> float:
        """Guard time x life time factor (0: life guarding off)."""
        if not self.guardable:
            return 0.0
        return self._od.int_value(OD_GUARD_TIME) * self._od.int_value(OD_LIFE_TIME_FACTOR) / 1e3

    @property
    def operational(self) -> bool:
        return self.state == cia301.NMT_STATE_OPERATIONAL

    @property
    def stopped(self) -> bool:
        return self.state == cia301.NMT_STATE_STOPPED

    @property
    def lost(self) -> frozenset[int]:
        """Monitored nodes whose heartbeat is missing now."""
        return frozenset(self._hb_lost)

    def reset_communication(self, now: float) -> None:
        """Back to pre-operational with fresh heartbeat watches; sends the boot-up frame."""
        self.state = cia301.NMT_STATE_PRE_OPERATIONAL
        self._hb_next = now
        self._hb_seen = {}
        self._hb_lost = set()
        self._toggle = 0
        self._guarded_at = None
        self._life_lost = False
        self._drive.transmit(cia301.make_heartbeat(self._drive.node_id, cia301.NMT_STATE_BOOTUP))
        self.schedule_heartbeat(now)

    def schedule_heartbeat(self, now: float) -> None:
        period_ms = self._od.int_value(cia301.OD_PRODUCER_HEARTBEAT_TIME)
        self._hb_next = now + period_ms / 1000.0 if period_ms else math.inf

    def monitored(self) -> dict[int, float]:
        """{node id: timeout s} of the 0x1016 consumer entries that are on (read again only
        when the object dictionary changed; the caller must not modify it)."""
        od = self._od
        if self._monitored_at != od.generation:
            self._monitored = self._read_monitored()
            self._monitored_at = od.generation
        return self._monitored

    def _read_monitored(self) -> dict[int, float]:
        out: dict[int, float] = {}
        values = self._od.values
        n = int(values.get((cia301.OD_CONSUMER_HEARTBEAT_TIME, 0), 0))  # type: ignore[arg-type]
        for sub in range(1, n + 1):
            v = int(values.get((cia301.OD_CONSUMER_HEARTBEAT_TIME, sub), 0))  # type: ignore[arg-type]
            node, ms = (v >> 16) & 0xFF, v & 0xFFFF
            if cia301.NODE_ID_MIN <= node <= cia301.NODE_ID_MAX and ms:
                out[node] = ms / 1000.0
        return out

    # ---------------------------------------------------------------- frames in
    def on_nmt(self, data: bytes, now: float) -> None:
        """An NMT node-control frame (other lengths and other nodes' commands ignored)."""
        if len(data) != 2 or data[1] not in (0, self._drive.node_id):
            return
        cmd = data[0]
        if cmd == cia301.NMT_START_REMOTE_NODE:
            self.state = cia301.NMT_STATE_OPERATIONAL
        elif cmd == cia301.NMT_STOP_REMOTE_NODE:
            self._leave_operational(now)
            self.state = cia301.NMT_STATE_STOPPED
        elif cmd == cia301.NMT_ENTER_PRE_OPERATIONAL:
            self._leave_operational(now)
            self.state = cia301.NMT_STATE_PRE_OPERATIONAL
        elif cmd == cia301.NMT_RESET_NODE:
            self._drive.log("NMT reset node")
            self._drive.reset_node(now)
        elif cmd == cia301.NMT_RESET_COMMUNICATION:
            self._drive.log("NMT reset communication")
            self._drive.reset_communication(now)

    def _leave_operational(self, now: float) -> None:
        sm = self._drive.state_machine
        if self.operational and sm.state == State.OPERATION_ENABLED:
            self._drive.log("left NMT operational while enabled: quick stop")
            sm.quick_stop(now)

    def on_heartbeat(self, node: int, data: bytes, now: float) -> None:
        """A heartbeat of a monitored node: restarts its watch, clears a loss."""
        if len(data) != 1:
            return
        self._hb_seen[node] = now
        if node in self._hb_lost:
            self._hb_lost.discard(node)
            self._clear_loss()

    def on_guarding_request(self, now: float) -> None:
        """A node-guarding request (remote frame on 0x700 + node id): the answer, NMT state
        and toggle bit; restarts the life guarding, clears a life-guarding event."""
        if not self.guardable:
            return
        drive = self._drive
        if self.guarding_enabled:
            drive.transmit(
                can.Message(
                    arbitration_id=cia301.COB_NMT_ERROR_CONTROL + drive.node_id,
                    data=bytes((self.state & 0x7F | self._toggle << 7,)),
                    is_extended_id=False,
                )
            )
            self._toggle ^= 1
        self._guarded_at = now
        if self._life_lost:
            self._life_lost = False
            self._clear_loss()

    def _clear_loss(self) -> None:
        """The last watch lost is back: warning and communication error cleared (EMCY 0)."""
        if self._hb_lost or self._life_lost:
            return
        drive = self._drive
        drive.warning = False
        drive.error_register &= ~cia301.ERR_REG_COMMUNICATION
        if drive.state_machine.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            if drive.error_register == cia301.ERR_REG_GENERIC:  # no error left
                drive.error_register = 0
            drive.emcy(cia301.EMCY_NO_ERROR)

    def _lose(self, now: float, why: str, node: int) -> None:
        drive = self._drive
        drive.warning = True
        drive.error_register |= cia301.ERR_REG_COMMUNICATION | cia301.ERR_REG_GENERIC
        drive.error_code = cia301.EMCY_HEARTBEAT
        drive.log(f"{why}: quick stop")
        drive.emcy(cia301.EMCY_HEARTBEAT, bytes((node,)))
        if drive.state_machine.state == State.OPERATION_ENABLED:
            drive.state_machine.quick_stop(now)

    # ---------------------------------------------------------------- timers
    def tick(self, now: float, heartbeat_early_s: float = 0.0) -> None:
        """Heartbeat production and consumption; a heartbeat due within
        ``heartbeat_early_s`` goes out now (the next stays on the producer's grid)."""
        drive = self._drive
        if now + heartbeat_early_s >= self._hb_next and self.heartbeat_enabled:
            drive.transmit(cia301.make_heartbeat(drive.node_id, self.state))
            period_s = self._od.int_value(cia301.OD_PRODUCER_HEARTBEAT_TIME) / 1000.0
            self._hb_next = self._hb_next + period_s if period_s else math.inf
            if self._hb_next <= now:
                self._hb_next = now + period_s
        elif now >= self._hb_next:
            self.schedule_heartbeat(now)
        monitored = self.monitored()
        for node, last in list(self._hb_seen.items()):
            timeout = monitored.get(node)
            if timeout is None:
                del self._hb_seen[node]
                continue
            if node not in self._hb_lost and now - last > timeout:
                self._hb_lost.add(node)
                self._lose(now, f"heartbeat of node {node} lost ({timeout * 1000:.0f} ms)", node)
        life_s = self._life_time_if_guarded()
        if life_s and not self._life_lost and now - self._guarded_at > life_s:  # type: ignore[operator]
            self._life_lost = True
            self._lose(now, f"life guarding: no guarding request in {life_s * 1000:.0f} ms", 0)

    def _life_time_if_guarded(self) -> float:
        """The life time while guarded (a request seen), else 0."""
        return 0.0 if self._guarded_at is None else self.life_time_s()

    def deadline(self) -> float:
        """Earliest time :meth:`tick` has something to do."""
        t = self._hb_next if self.heartbeat_enabled else math.inf
        monitored = self.monitored()
        for node, last in self._hb_seen.items():
            if node in monitored and node not in self._hb_lost:
                t = min(t, last + monitored[node] + 1e-4)
        life_s = self._life_time_if_guarded()
        if life_s and not self._life_lost and self._guarded_at is not None:
            t = min(t, self._guarded_at + life_s + 1e-4)
        return t

    # ---------------------------------------------------------------- objects
    def check_write(self, index: int, sub: int, value: int) -> None:
        """0x1016 entries: bits 24..31 are reserved; the drive cannot watch itself."""
        if index == cia301.OD_CONSUMER_HEARTBEAT_TIME and sub >= 1:
            node = (value >> 16) & 0xFF
            if value >> 24 or (node == self._drive.node_id and value & 0xFFFF):
                raise SdoAbort(cia301.SDO_ABORT_INVALID_VALUE)

    def after_write(self, index: int, now: float) -> None:
        if index == cia301.OD_PRODUCER_HEARTBEAT_TIME:
            self.schedule_heartbeat(now)
        elif index == cia301.OD_CONSUMER_HEARTBEAT_TIME:
            self._hb_seen.clear()
            self._hb_lost.clear()
