"""What a red team found in the session's edges: an interrupt inside finish, finish or
close from another thread while a stream plays, a second stream, a master that only
streams PDOs.  Each must still stop every axis or refuse without side effects."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import can
import pytest

from drivers.interrupts import interrupt
from drivers.protocol import cia301, cia402
from drivers.safety.causes import StopKind
from drivers.session import OtherMasterError, SessionState, SessionStateError
from drivers.sources import HoldSource
from hrm_ctrl.errors import SignalInterrupt
from tests.drivers.driver_rig import Rig, sending_from_outside, wait_until


def quick_stops(rig: Rig) -> list[can.Message]:
    return [
        m
        for sn in rig.sniffers
        for m in sn.snapshot()
        if 0x200 < m.arbitration_id <= 0x27F and bytes(m.data[:2]) == b"\x02\x00"
    ]


def pre_operational_sent(rig: Rig) -> bool:
    return all(
        any(
            m.arbitration_id == cia301.COB_NMT and m.data[0] == cia301.NMT_ENTER_PRE_OPERATIONAL
            for m in sn.snapshot()
        )
        for sn in rig.sniffers
    )


def test_a_signal_inside_finish_waits_for_its_end(
    rig_factory: Callable[..., Rig], monkeypatch: pytest.MonkeyPatch
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    real = box.drives.disable

    def disable_then_signal(what: str) -> None:
        interrupt(SignalInterrupt("SIGTERM", 15))  # arrives in the middle of finish
        real(what)

    monkeypatch.setattr(box.drives, "disable", disable_then_signal)
    with pytest.raises(SignalInterrupt):
        box.finish()
    # finish ran to its end first: drives disabled, NMT pre-operational, heartbeat off
    assert box.state is SessionState.CONNECTED
    assert wait_until(lambda: pre_operational_sent(rig))
    assert all(
        cia402.decode_state(sw) is cia402.State402.READY_TO_SWITCH_ON
        for sw in rig.sim.statuswords().values()
    )


@pytest.mark.parametrize("how", ["finish", "close"])
def test_finish_or_close_from_another_thread_stops_a_running_stream(
    rig_factory: Callable[..., Rig], how: str
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    outcome: dict[str, Any] = {}

    def play() -> None:
        try:
            outcome["result"] = box.stream(HoldSource(n_cycles=3000), raise_on_stop=False)
        except BaseException as exc:
            outcome["error"] = exc

    thread = threading.Thread(target=play)
    thread.start()
    assert wait_until(lambda: box.state is SessionState.STREAMING)
    threading.Event().wait(0.1)
    getattr(box, how)()
    thread.join(10.0)
    assert not thread.is_alive(), "the stream's caller is still blocked"
    assert quick_stops(rig), "no quick stop was sent"
    result = outcome.get("result")
    if result is not None:
        assert not result.completed and result.causes
        assert result.causes[0].kind is StopKind.OPERATOR
    assert wait_until(
        lambda: all(
            cia402.decode_state(sw) is not cia402.State402.OPERATION_ENABLED
            for sw in rig.sim.statuswords().values()
        )
    )
    if how == "close":
        rig.box = None


def test_a_second_stream_is_refused_and_leaves_the_first_alone(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    results: list[Any] = []
    thread = threading.Thread(target=lambda: results.append(box.stream(HoldSource(n_cycles=50))))
    thread.start()
    assert wait_until(lambda: box.state is SessionState.STREAMING)
    with pytest.raises(SessionStateError, match="stream: not allowed in state STREAMING"):
        box.stream(HoldSource(n_cycles=5))
    with pytest.raises(SessionStateError, match="configure: not allowed in state STREAMING"):
        box.configure()
    thread.join(10.0)
    assert results and results[0].completed
    assert box.state is SessionState.ENABLED


def test_a_master_heard_only_by_its_pdos_is_not_reset(rig_factory: Callable[..., Rig]) -> None:
    """Another master drives node 1 with SYNCs on its own bus object: its TPDOs (and the
    SYNCs) are heard while listening; nothing is reset."""
    rig = rig_factory()
    tpdo = can.Message(arbitration_id=0x181, data=cia402.TPDO_FEEDBACK_LAYOUT.pack(0x1237, 0),
                       is_extended_id=False)  # fmt: skip
    with sending_from_outside(rig, 0, tpdo, 0.01):  # the other master
        box = rig.open_box(listen_s=0.3)
        with pytest.raises(OtherMasterError, match=r"PDOs from 1 node\(s\) \(1\)"):
            box.configure()
    resets = [
        m
        for sn in rig.sniffers
        for m in sn.snapshot()
        if m.arbitration_id == cia301.COB_NMT and m.data[0] == cia301.NMT_RESET_NODE
    ]
    assert resets == []
    assert box.state is SessionState.CONNECTED
