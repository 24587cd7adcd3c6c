"""The drive session's states: refused transitions raise, and one bring-up serves
several sources one after another (jog, hold, table, hold) without a new NMT reset."""

from __future__ import annotations

import ast
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.protocol import cia301, cia402
from drivers.session import SessionState, SessionStateError
from drivers.sources import HoldSource, JogSource, TableSource
from tests.drivers.driver_rig import Rig, wait_until


class RampSource(TableSource):
    """A short ramp of every motor away from where it is, and back."""

    name = "ramp"

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        up = actual_counts[None, :] + np.arange(1, 21)[:, None] * 200
        self.table = np.concatenate([up, up[::-1], actual_counts[None, :]]).astype(np.int64)


def nmt_resets(rig: Rig) -> list[int]:
    """NMT reset-node commands seen on each bus."""
    return [
        sum(
            1
            for m in sn.snapshot()
            if m.arbitration_id == cia301.COB_NMT and m.data[0] == cia301.NMT_RESET_NODE
        )
        for sn in rig.sniffers
    ]


def test_refused_transitions_raise(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    box = rig.open_box()
    assert box.state is SessionState.CONNECTED
    with pytest.raises(SessionStateError, match=r"stream: not allowed in state CONNECTED"):
        box.stream(HoldSource(n_cycles=3))
    with pytest.raises(SessionStateError, match=r"enable: not allowed in state CONNECTED"):
        box.enable()
    with pytest.raises(SessionStateError, match=r"disable: not allowed in state CONNECTED"):
        box.disable()
    assert nmt_resets(rig) == [0, 0]  # nothing refused sent anything
    box.configure()
    assert box.state is SessionState.READY
    with pytest.raises(SessionStateError, match=r"stream: not allowed in state READY"):
        box.stream(HoldSource(n_cycles=3))
    box.enable()
    assert box.state is SessionState.ENABLED and box.enabled
    with pytest.raises(SessionStateError, match=r"enable: not allowed in state ENABLED"):
        box.enable()
    box.disable()
    assert box.state is SessionState.READY
    assert wait_until(
        lambda: all(
            cia402.decode_state(sw) is cia402.State402.READY_TO_SWITCH_ON
            for sw in rig.sim.statuswords().values()
        )
    )
    box.enable()
    assert box.stream(HoldSource(n_cycles=5)).completed
    box.finish()
    assert box.state is SessionState.CONNECTED
    box.close()
    rig.box = None
    assert box.state is SessionState.CLOSED
    with pytest.raises(SessionStateError, match="closed"):
        box.finish()
    assert nmt_resets(rig) == [1, 1]


def test_several_sources_one_after_another_without_a_new_reset(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    box = rig.open_box()
    actual = box.bring_up()
    results = [
        box.stream(JogSource(rig.limits, "j01r0", 20_000.0, 0.1)),
        box.stream(HoldSource(n_cycles=10)),
        box.stream(RampSource()),
        box.stream(HoldSource(n_cycles=10)),
    ]
    assert all(r.completed for r in results)
    assert box.state is SessionState.ENABLED
    assert nmt_resets(rig) == [1, 1]
    # Each source started where the previous one left the drives.
    jogged = results[0].last_targets
    assert jogged[0] == actual[0] + 2000 and np.array_equal(jogged[1:], actual[1:])
    assert np.array_equal(results[1].last_targets, jogged)
    assert np.array_equal(results[3].last_targets, jogged)
    # The simulated drives followed: j01r0 is where the jog left it.
    i = rig.limits.full.motor_ids.index("j01r0")
    assert wait_until(lambda: abs(int(rig.sim.counts()[i]) - int(jogged[0])) < 50)
    box.finish()


def test_after_a_stop_disable_and_enable_recover_without_a_reset(
    rig_factory: Callable[..., Rig],
) -> None:
    """An operator's stop quick-stops every drive; ``disable`` walks them to
    READY_TO_SWITCH_ON along the transition table, ``enable`` brings them back, and a
    stream runs again: one NMT reset in all."""
    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    box.request_stop()
    assert wait_until(lambda: box.state is SessionState.STOPPED)
    assert [x.kind.value for x in box.idle_causes] == ["operator"]
    box.disable()
    assert box.state is SessionState.READY
    assert all(
        cia402.decode_state(sw) is cia402.State402.READY_TO_SWITCH_ON
        for sw in rig.sim.statuswords().values()
    )
    box.enable()
    assert box.stream(HoldSource(n_cycles=5)).completed
    assert nmt_resets(rig) == [1, 1]
    box.finish()


# --- calibration (issue 12): no drive is enabled without one, unless overridden ------------


def test_enable_is_refused_without_a_calibration_and_sends_nothing(
    rig_factory: Callable[..., Rig], tmp_path: Path
) -> None:
    rig = rig_factory()
    box = rig.open_box(log_dir=tmp_path, allow_uncalibrated=False)
    with pytest.raises(SessionStateError, match=r"^bring-up refused: no calibration") as exc:
        box.bring_up()
    assert "\n" not in str(exc.value)
    assert nmt_resets(rig) == [0, 0]  # refused before the NMT reset
    assert box.state is SessionState.CONNECTED
    box.configure()  # configuring powers nothing; enabling is what the gate refuses
    time.sleep(0.3)  # let the sniffers take the configuration's last frames
    for sn in rig.sniffers:
        sn.clear()
    with pytest.raises(SessionStateError, match=r"^enable refused: no calibration"):
        box.enable()
    assert box.state is SessionState.READY and not box.enabled
    sdo_requests = [
        m for sn in rig.sniffers for m in sn.snapshot() if 0x600 < m.arbitration_id < 0x680
    ]
    assert sdo_requests == []  # no controlword written: nothing sent for the refused enable
    assert all(
        cia402.decode_state(sw) is not cia402.State402.OPERATION_ENABLED
        for sw in rig.sim.statuswords().values()
    )
    box.finish()
    record = json.loads(box.close().read_text())  # type: ignore[union-attr]
    rig.box = None
    assert record["calibration"] == "none (enable refused)"
    assert any("enable refused: no calibration" in e["text"] for e in record["events"])


def operation_enabled(rig: Rig) -> list[str]:
    """The simulated drives in OPERATION_ENABLED."""
    return [
        m
        for m, sw in rig.sim.statuswords().items()
        if cia402.decode_state(sw) is cia402.State402.OPERATION_ENABLED
    ]


def quick_stop_rpdos(rig: Rig) -> int:
    """RPDOs on the wire with the quick-stop controlword."""
    return sum(
        1
        for sn in rig.sniffers
        for m in sn.snapshot()
        if 0x200 < m.arbitration_id <= 0x27F
        and int.from_bytes(bytes(m.data[:2]), "little") == cia402.CW_QUICK_STOP
    )


def test_a_fault_while_ready_refuses_enable_until_the_fault_is_reset(
    rig_factory: Callable[..., Rig],
) -> None:
    """A drive that faults after the configuration (its EMCY queued, the drive in FAULT):
    ``enable`` refuses, naming it, before a drive is enabled (no fault reset behind the
    operator's back); ``reset_fault`` clears it and ``enable`` then works."""
    rig = rig_factory()
    box = rig.open_box()
    box.configure()
    rig.sim.fault_drive("j01r0")
    assert wait_until(lambda: bool(box.monitor.emergencies))
    with pytest.raises(SessionStateError, match=r"enable refused: .*j01r0.*EMCY"):
        box.enable()
    assert box.state is SessionState.READY and operation_enabled(rig) == []
    # the EMCY taken, the drive itself is still in FAULT: refused on its statusword
    with pytest.raises(SessionStateError, match=r"enable refused: .*j01r0.* in FAULT"):
        box.enable()
    assert box.state is SessionState.READY and operation_enabled(rig) == []
    assert box.reset_fault() == [next(lb for lb in box.monitor.labels if "j01r0" in lb)]
    box.enable()
    assert box.state is SessionState.ENABLED and len(operation_enabled(rig)) == box.monitor.n
    box.finish()


@pytest.mark.parametrize("what", ["emcy", "operator"])
def test_a_stop_cause_during_the_enable_stops_every_axis_once_enabled(
    rig_factory: Callable[..., Rig], monkeypatch: pytest.MonkeyPatch, what: str
) -> None:
    """A drive that faults right after its own enable (its EMCY arriving while the others
    are still being enabled), or an operator's stop asked for meanwhile: as soon as every
    drive is enabled the supervisor quick-stops them all and ``enable`` raises naming the
    cause (before, the EMCY was filed as a bring-up event and the stop request cleared)."""
    import drivers.drive_group as drive_group
    from drivers.session import SafetyStopError

    rig = rig_factory()
    box = rig.open_box()
    box.configure()
    real = drive_group.enable_operation
    first = rig.limits.motor_ids[0]

    def enable_then_cause(link: Any, *args: Any, **kw: Any) -> int:
        actual = real(link, *args, **kw)
        if link.motor == first:
            if what == "emcy":
                rig.sim.fault_drive(first)
            else:
                box.request_stop()
            time.sleep(0.2)  # the other drives are being enabled meanwhile
        return actual

    monkeypatch.setattr(drive_group, "enable_operation", enable_then_cause)
    with pytest.raises(SafetyStopError, match="EMCY" if what == "emcy" else "stop requested"):
        box.enable()
    assert box.state is SessionState.STOPPED
    assert quick_stop_rpdos(rig) >= box.monitor.n  # every node got the quick stop
    assert wait_until(lambda: operation_enabled(rig) == [])
    if what == "emcy":  # the faulted drive stays in FAULT until reset on purpose
        box.reset_fault()
    box.finish()


def test_a_quick_stop_a_drive_never_confirms_leaves_the_session_in_fault(
    rig_factory: Callable[..., Rig],
) -> None:
    """One drive's RPDOs are lost: it never gets the quick stop, so its feedback never
    confirms it.  After the supervisor gives up the session is FAULT (not STOPPED, as if
    every drive had stopped), the error names the drive, and that drive was sent NMT
    enter pre-operational (it no longer takes PDOs; CiA 402 drives react to leaving
    operational)."""
    from drivers.session import SafetyStopError

    rig = rig_factory()
    box = rig.open_box()
    box.bring_up()
    bus = rig.config.buses[0]
    motor, node = next(iter(bus.nodes.items()))
    rig.sim.drop_frames(bus.name, lambda m: m.arbitration_id == 0x200 + node, count=None)
    try:
        box.request_stop()
        with pytest.raises(SafetyStopError):
            box.stream(HoldSource(n_cycles=50))
        assert wait_until(lambda: box.state is SessionState.FAULT)
        assert box.stop_error is not None and motor in box.stop_error
        assert "not confirmed" in box.stop_error

        def pre_operational_sent() -> bool:  # the sniffer hears it on its own thread
            nmt = [
                bytes(m.data)
                for m in rig.sniffers[0].snapshot()
                if m.arbitration_id == cia301.COB_NMT
            ]
            return bytes([cia301.NMT_ENTER_PRE_OPERATIONAL, node]) in nmt

        assert wait_until(pre_operational_sent)
    finally:
        rig.sim.clear_frame_faults()


def test_a_drive_that_rebooted_since_its_configuration_is_not_enabled(
    rig_factory: Callable[..., Rig],
) -> None:
    """A drive resets itself between configure and enable (a brown-out): it lost its SDO
    configuration (heartbeats, limits, PDO maps, CSP).  Found by a red-team helper: it
    was enabled anyway.  ``enable`` refuses naming it, nothing is enabled, and a new
    bring-up configures it again."""
    rig = rig_factory()
    box = rig.open_box()
    box.configure()
    motor = rig.limits.motor_ids[1]
    with rig.sim._lock:
        rig.sim.drives[motor].reset_node(time.monotonic())  # its boot-up goes on the bus
    assert wait_until(lambda: bool(box.monitor.rebooted.any()))
    with pytest.raises(SessionStateError, match=rf"enable refused: {motor} .*rebooted since"):
        box.enable()
    assert box.state is SessionState.READY and operation_enabled(rig) == []
    box.bring_up()  # configured again: enabled
    assert box.state is SessionState.ENABLED
    box.finish()


def test_a_stop_asked_for_during_the_configuration_refuses_the_enable(
    rig_factory: Callable[..., Rig], monkeypatch: pytest.MonkeyPatch
) -> None:
    """An operator's stop while the drives are being configured (found by a red-team
    helper: ``enable`` cleared it and enabled every drive): ``enable`` refuses naming it,
    logged; the next ``enable`` works.  A stop asked for while already stopped is done
    with by ``disable``."""
    import drivers.drive_group as drive_group

    rig = rig_factory()
    box = rig.open_box()
    real = drive_group.configure_drive

    def configure_then_stop(link: Any, *args: Any, **kw: Any) -> None:
        real(link, *args, **kw)
        box.request_stop(text="stop (operator)")

    monkeypatch.setattr(drive_group, "configure_drive", configure_then_stop)
    box.configure()
    with pytest.raises(SessionStateError, match=r"enable refused: stop \(operator\) before"):
        box.enable()
    assert box.state is SessionState.READY and operation_enabled(rig) == []
    assert any(e["kind"] == "stop_cause" and e["text"] == "stop (operator)"
               for e in box.record()["events"])  # fmt: skip
    box.enable()
    box.request_stop()
    assert wait_until(lambda: box.state is SessionState.STOPPED)
    box.request_stop(text="again while stopped")
    box.disable()
    box.enable()
    assert box.state is SessionState.ENABLED
    box.finish()


class FractionSource(TableSource):
    """A user's source whose table is float counts (0.9 would be sent as 0)."""

    name = "fractions"

    def start(self, actual_counts: np.ndarray, period_s: float) -> None:
        self.table = actual_counts[None, :] + np.array([0.9, 206.6, 412.0])[:, None]


def test_a_setpoint_that_is_not_whole_counts_is_refused_and_never_sent(
    rig_factory: Callable[..., Rig],
) -> None:
    """Setpoints go out as int32: a float table was checked as floats and sent truncated
    (found by a red-team helper: a second difference of 206 counts against a limit of
    204.8 reached the wire).  Refused as a limit stop before its RPDO."""
    rig = rig_factory()
    box = rig.open_box()
    actual = box.bring_up()
    for sn in rig.sniffers:
        sn.clear()
    result = box.stream(FractionSource(), raise_on_stop=False)
    assert not result.completed
    assert "is not whole counts (dtype float64)" in result.causes[0].text
    targets = [
        int.from_bytes(bytes(m.data[2:6]), "little", signed=True)
        for sn in rig.sniffers
        for m in sn.snapshot()
        if 0x200 < m.arbitration_id <= 0x27F
    ]
    assert set(targets) <= {int(x) for x in actual}  # only the holds and the quick stop
    box.finish()


def test_a_boot_up_just_before_the_arming_stops_every_axis(
    rig_factory: Callable[..., Rig],
) -> None:
    """Found by a review helper: a boot-up handled between the enable's reboot check and
    the arming was judged by nobody (the session stayed ENABLED)."""
    from drivers.session import SafetyStopError

    rig = rig_factory()
    box = rig.open_box()
    box.configure()
    real = box.supervisor.arm

    def boot_then_arm(targets: np.ndarray) -> None:
        box.monitor.on_heartbeat(0, b"\x00")  # the first node's boot-up, handled now
        real(targets)

    box.supervisor.arm = boot_then_arm  # type: ignore[method-assign]
    with pytest.raises(SafetyStopError, match=r"rebooted .*during the enable"):
        box.enable()
    assert box.state is SessionState.STOPPED
    box.finish()


def _eventfds() -> int:
    """This process's open eventfd descriptors."""
    import os

    names = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            names.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # the listing's own descriptor, closed meanwhile
            continue
    return sum(1 for n in names if n == "anon_inode:[eventfd]")


def test_a_closed_session_holds_no_descriptor_until_a_garbage_collection(
    rig_factory: Callable[..., Rig],
) -> None:
    import gc

    rig = rig_factory()
    gc.disable()  # the collector must not be what releases them
    try:
        before = _eventfds()
        for _ in range(3):
            box = rig.open_box()
            assert _eventfds() == before + 1  # the supervisor's wake-up descriptor
            box.close()
            assert box.monitor.wake.fileno() == -1
            assert _eventfds() == before
    finally:
        gc.enable()


def _session_sources() -> list[tuple[str, ast.AST]]:
    import drivers

    root = Path(drivers.__file__).parent
    names = ["session.py", "wiring.py", "parallel.py", "other_master.py", "run_record.py"]
    return [(n, ast.parse((root / n).read_text())) for n in names]


def test_the_session_moves_the_monitor_only_through_the_supervisor() -> None:
    """No attribute of the node monitor is assigned, and none of its state-changing
    methods called, outside the supervisor (the receivers only get its feed callbacks)."""
    writers = {"drain", "reset_boot", "configured", "report", "take"}
    found = []
    for name, tree in _session_sources():
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else []
            if isinstance(node, ast.AugAssign | ast.AnnAssign):
                targets = [node.target]
            for t in targets:
                if isinstance(t, ast.Attribute) and "monitor" in ast.unparse(t.value):
                    found.append(f"{name}:{node.lineno} {ast.unparse(t)} =")
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr in writers
                and ast.unparse(node.func.value).endswith("monitor")
            ):
                found.append(f"{name}:{node.lineno} {ast.unparse(node.func)}()")
    assert found == []


def test_the_session_probes_no_attribute() -> None:
    probes = [
        f"{name}:{node.lineno}"
        for name, tree in _session_sources()
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id in ("getattr", "hasattr")
    ]
    assert probes == []
