"""Process-wide settings: one opt-in context sets and restores them; buses change none."""

from __future__ import annotations

import gc
import os
import sys
import time
import uuid
from typing import Any

import can
import pytest

import drivers.realtime as rt
from drivers.realtime import (
    CPU_LATENCY_DEVICE,
    SWITCH_INTERVAL_S,
    AppliedSettings,
    CpuLatencyRequest,
    GcHold,
    ProcessSettingsError,
    process_settings,
)
from drivers.receive import BusPoller
from drivers.sources import HoldSource
from hrm_ctrl.errors import DriverError


def test_the_context_sets_and_restores_the_switch_interval() -> None:
    before = sys.getswitchinterval()
    with process_settings(switch_interval_s=0.003) as s:
        assert sys.getswitchinterval() == pytest.approx(0.003)
        assert s.switch_interval_s == pytest.approx(0.003)
        assert s.previous_switch_interval_s == before
        with process_settings() as inner:  # nested: the stack's value, then back to 3 ms
            assert sys.getswitchinterval() == pytest.approx(SWITCH_INTERVAL_S)
            assert inner.previous_switch_interval_s == pytest.approx(0.003)
        assert sys.getswitchinterval() == pytest.approx(0.003)
    assert sys.getswitchinterval() == before


def test_the_switch_interval_is_restored_when_the_body_raises() -> None:
    before = sys.getswitchinterval()
    with pytest.raises(KeyError), process_settings(switch_interval_s=0.004):
        raise KeyError("boom")
    assert sys.getswitchinterval() == before


def test_none_leaves_the_switch_interval_alone() -> None:
    before = sys.getswitchinterval()
    with process_settings(switch_interval_s=None) as s:
        assert sys.getswitchinterval() == before == s.switch_interval_s
    assert sys.getswitchinterval() == before


def test_the_switch_interval_constant_is_below_a_frame_budget() -> None:
    # 0.2 ms: well under a 10 ms control period, CPython's default is 5 ms
    assert SWITCH_INTERVAL_S == pytest.approx(2e-4)


def test_constructing_an_hrm_sim_wire_bus_changes_no_interpreter_setting() -> None:
    ch = f"rt-{uuid.uuid4().hex[:8]}"
    with process_settings(switch_interval_s=0.005):  # CPython's default, whatever pytest has
        before = sys.getswitchinterval()
        a = can.Bus(interface="hrm_sim", channel=ch, bitrate=1_000_000)
        b = can.Bus(interface="hrm_sim", channel=ch, bitrate=1_000_000)
        try:
            assert sys.getswitchinterval() == before
            a.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
            assert b.recv(timeout=1.0) is not None
            assert sys.getswitchinterval() == before
        finally:
            a.shutdown()
            b.shutdown()
        assert sys.getswitchinterval() == before


def test_priority_zero_leaves_the_scheduling_policy_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[Any] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a), raising=False)
    with process_settings(realtime_priority=0) as s:
        assert (s.realtime_priority, s.realtime_granted, s.realtime_refusal) == (0, False, None)
    assert calls == []


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="no SCHED_FIFO on this platform")
def test_a_granted_priority_is_reported_and_restored(monkeypatch: pytest.MonkeyPatch) -> None:
    """The right is simulated: the shared machine's real policy is never changed here."""
    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: os.SCHED_OTHER)
    monkeypatch.setattr(os, "sched_getparam", lambda pid: os.sched_param(0))
    monkeypatch.setattr(
        os, "sched_setscheduler", lambda pid, pol, par: calls.append((pid, pol, par.sched_priority))
    )
    with process_settings(realtime_priority=20) as s:
        assert s.realtime_granted and s.realtime_refusal is None
        assert calls == [(0, os.SCHED_FIFO, 20)]
    assert calls[-1] == (0, os.SCHED_OTHER, 0)
    assert s.to_dict()["realtime_granted"] is True


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="no SCHED_FIFO on this platform")
def test_a_refused_priority_carries_on_and_says_why(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(pid: int, policy: int, param: Any) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    before = sys.getswitchinterval()
    with caplog.at_level("WARNING", logger="drivers.realtime"):
        with process_settings(switch_interval_s=0.002, realtime_priority=10) as s:
            assert sys.getswitchinterval() == pytest.approx(0.002)  # the rest still applies
    assert not s.realtime_granted
    assert s.realtime_refusal == "SCHED_FIFO priority 10 refused (Operation not permitted)"
    assert "running under normal scheduling" in caplog.text
    assert sys.getswitchinterval() == before


def test_no_sched_fifo_on_the_platform_is_a_refusal(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delattr(os, "sched_setscheduler", raising=False)
    with process_settings(switch_interval_s=None, realtime_priority=5) as s:
        assert not s.realtime_granted
        assert s.realtime_refusal is not None and "not available" in s.realtime_refusal


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"switch_interval_s": 0.0}, r"^switch_interval_s: must be a finite number > 0 s, got 0.0"),
        ({"switch_interval_s": float("nan")}, "switch_interval_s: must be a finite number"),
        ({"switch_interval_s": True}, "switch_interval_s: must be a finite number"),
        ({"realtime_priority": -1}, r"^realtime_priority: must be an integer in 0..99, got -1$"),
        ({"realtime_priority": 100}, "realtime_priority: must be an integer in 0..99"),
        ({"realtime_priority": 1.5}, "realtime_priority: must be an integer in 0..99"),
    ],
)  # fmt: skip
def test_bad_settings_are_refused_before_anything_changes(
    kwargs: dict[str, Any], match: str
) -> None:
    before = sys.getswitchinterval()
    with pytest.raises(ProcessSettingsError, match=match), process_settings(**kwargs):
        pass  # pragma: no cover
    assert sys.getswitchinterval() == before
    assert issubclass(ProcessSettingsError, DriverError)


def test_the_console_runs_every_command_under_the_context(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """hrm_ctrl.cli.main is the process entry of hrm (host commands and hrm sim)."""
    from hrm_ctrl import cli

    seen: list[float] = []
    monkeypatch.setattr(
        cli, "build_parser", lambda: _parser_running(lambda: seen.append(sys.getswitchinterval()))
    )
    with process_settings(switch_interval_s=0.005):
        assert cli.main(["x"]) == 0
        assert sys.getswitchinterval() == pytest.approx(0.005)
    assert seen == [pytest.approx(SWITCH_INTERVAL_S)]


def _parser_running(body: Any) -> Any:
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("command")
    p.set_defaults(_run=lambda args: body() and 0)
    return p


def test_applied_settings_is_a_plain_record() -> None:
    s = AppliedSettings(2e-4, 5e-3, 0, False)
    assert s.to_dict() == {
        "switch_interval_s": 2e-4,
        "previous_switch_interval_s": 5e-3,
        "realtime_priority": 0,
        "realtime_granted": False,
        "realtime_refusal": None,
        "cpus": None,
    }
    assert rt.NORMAL_PRIORITY == 0 and rt.REALTIME_PRIORITY_MAX == 99


def test_cpus_keep_the_threads_started_inside_on_them_and_come_back() -> None:
    import threading

    cpus = rt.available_cpus()
    one = frozenset({max(cpus)})
    seen: list[set[int]] = []
    with rt.process_settings(switch_interval_s=None, cpus=one) as applied:
        t = threading.Thread(target=lambda: seen.append(os.sched_getaffinity(0)))
        t.start()
        t.join(5.0)
        assert applied.cpus == one and os.sched_getaffinity(0) == one
    assert seen == [set(one)] and os.sched_getaffinity(0) == set(cpus)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("x", "'x' is not a CPU list"),
        ("3-1", "'3-1' is not a CPU list"),
        ("-1", "'-1' is not a CPU list"),
        ("4096", "'4096' is not a CPU list"),
        ("4095", "CPU 4095 is not available to this process"),
    ],
)
def test_a_bad_cpu_list_is_one_line_naming_it(text: str, message: str) -> None:
    with pytest.raises(rt.ProcessSettingsError, match=r"^--cpus: ") as err:
        rt.parse_cpus(text)
    assert message in str(err.value) and "\n" not in str(err.value)


# ---- a drive session's threads ---------------------------------------------------------------


def _policies(prefixes: tuple[str, ...]) -> dict[str, int]:
    import threading

    return {
        t.name: os.sched_getscheduler(t.native_id)
        for t in threading.enumerate()
        if t.name.startswith(prefixes) and t.native_id is not None
    }


SESSION_THREADS = ("hrm-rx-", "hrm-supervisor", "canlog-")


def fifo_or_skip(priority: int) -> int:
    """The calling thread's policy, after checking SCHED_FIFO at ``priority`` is allowed
    (the test skips, saying why, where it is not)."""
    before = os.sched_getscheduler(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        os.sched_setscheduler(0, before, os.sched_param(0))
    except PermissionError:
        pytest.skip("SCHED_FIFO needs CAP_SYS_NICE or an RLIMIT_RTPRIO this account lacks")
    return before


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="no SCHED_FIFO on this platform")
def test_every_thread_of_a_session_runs_at_its_realtime_priority(
    rig_factory: Any, tmp_path: Any
) -> None:
    """The readers, the log writers and the supervisor all start under SCHED_FIFO (one of
    them at normal priority holding the GIL would keep the others waiting); the thread
    that opened the session keeps its own policy.  Priority 1, the lowest FIFO one."""
    before = fifo_or_skip(1)
    rig = rig_factory(realtime_priority=1)
    box = rig.open_box(log_dir=tmp_path, log_suffix=".asc", run_name="rt")
    assert box.realtime_granted
    seen = _policies(SESSION_THREADS)
    # a bus with a descriptor is read by the supervisor's thread: no reader thread of its own
    readers = [
        p for p in box._networks if not isinstance(p.notifier, BusPoller)
    ]  # fmt: skip
    expected = SESSION_THREADS if readers else SESSION_THREADS[1:]
    assert all(any(n.startswith(p) for n in seen) for p in expected), seen
    assert len([n for n in seen if n.startswith("hrm-rx-")]) == len(readers), seen
    assert set(seen.values()) == {os.SCHED_FIFO}, seen
    assert os.sched_getscheduler(0) == before
    with box.thread_scheduling() as applied:  # a watch's thread started for the session
        assert applied.realtime_granted and os.sched_getscheduler(0) == os.SCHED_FIFO
    assert os.sched_getscheduler(0) == before
    assert any(
        e["kind"] == "realtime" and "SCHED_FIFO 1" in e["text"] for e in box.events.to_list()
    )


@pytest.mark.skipif(not hasattr(os, "SCHED_FIFO"), reason="no SCHED_FIFO on this platform")
def test_the_log_writers_run_one_priority_below_the_supervisor(
    rig_factory: Any, tmp_path: Any
) -> None:
    """Under FIFO the CAN log writers step one priority below the session's, so that the
    supervisor, woken at its deadline, preempts a writer packing a batch on its CPU."""
    import threading

    fifo_or_skip(3)
    rig = rig_factory(realtime_priority=3)
    box = rig.open_box(log_dir=tmp_path, log_suffix=".asc", run_name="rt3")
    assert box.realtime_granted
    deadline = time.monotonic() + 5.0
    prio: dict[str, int] = {}
    while time.monotonic() < deadline:  # a writer steps down as its thread starts
        prio = {
            t.name: os.sched_getparam(t.native_id).sched_priority
            for t in threading.enumerate()
            if t.name.startswith(SESSION_THREADS) and t.native_id is not None
        }
        if all(v == 2 for n, v in prio.items() if n.startswith("canlog-")):
            break
        time.sleep(0.01)
    writers = {n: v for n, v in prio.items() if n.startswith("canlog-")}
    others = {n: v for n, v in prio.items() if not n.startswith("canlog-")}
    assert writers and set(writers.values()) == {2}, prio
    assert others.get("hrm-supervisor") == 3 and set(others.values()) == {3}, prio
    assert _policies(SESSION_THREADS) and set(_policies(SESSION_THREADS).values()) == {
        os.SCHED_FIFO
    }


def test_a_refused_priority_is_asked_once_per_session_and_recorded(
    rig_factory: Any, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(pid: int, policy: int, param: Any) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse, raising=False)
    rig = rig_factory(realtime_priority=5)
    with caplog.at_level("WARNING", logger="drivers.realtime"):
        box = rig.open_box()
        box.bring_up()
        with box.thread_scheduling() as applied:
            assert not applied.realtime_granted
    assert not box.realtime_granted and box.supervisor.realtime_priority == 0
    assert caplog.text.count("SCHED_FIFO priority 5 refused") == 1
    texts = [e["text"] for e in box.events.to_list() if e["kind"] == "realtime"]
    assert texts == ["SCHED_FIFO priority 5 refused (Operation not permitted); normal scheduling"]


def _cpu_latency_now() -> int | None:
    try:
        fd = os.open(CPU_LATENCY_DEVICE, os.O_RDONLY)
    except OSError:
        return None
    try:
        return int.from_bytes(os.read(fd, 4), sys.byteorder, signed=True)
    finally:
        os.close(fd)


def test_a_session_holds_its_cpu_latency_request_while_open(
    rig_factory: Any, tmp_path: Any
) -> None:
    """``cpu_wakeup_latency_us = 0``: the kernel's CPU latency target is 0 while the session
    is open and back where it was after; the run record's events say so.  Without access
    to the device the session runs on, one event naming the refusal."""
    before = _cpu_latency_now()
    rig = rig_factory(cpu_wakeup_latency_us=0)
    box = rig.open_box(log_dir=tmp_path, log_suffix=".asc", run_name="lat")
    events = [e for e in box.events.to_list() if e["kind"] == "cpu-latency"]
    assert len(events) == 1, events
    if box.cpu_latency.held:
        assert _cpu_latency_now() == 0
        assert "at most 0 us held" in events[0]["text"]
    else:
        assert box.cpu_latency.refusal and "refused" in events[0]["text"]
    box.close()
    assert not box.cpu_latency.held
    assert _cpu_latency_now() == before


def test_no_cpu_latency_request_by_default(rig_factory: Any, tmp_path: Any) -> None:
    box = rig_factory().open_box(log_dir=tmp_path, log_suffix=".asc", run_name="nolat")
    assert not box.cpu_latency.held and box.cpu_latency.refusal is None
    assert all(e["kind"] != "cpu-latency" for e in box.events.to_list())
    box.close()


def test_a_refused_cpu_latency_request_is_one_reason(tmp_path: Any) -> None:
    r = CpuLatencyRequest(0, str(tmp_path / "no-such-device"))
    assert not r.held and r.refusal is not None and "no-such-device" in r.refusal
    r.close()


def test_a_session_keeps_the_heap_out_of_the_collector_while_drives_depend_on_it(
    rig_factory: Any,
) -> None:
    """From the bring-up to the end of finish() the heap is frozen (a full collection
    walks only what was allocated since: no pause of the whole heap while the heartbeat
    watchdogs run), through a stream, until finish()."""
    rig = rig_factory()
    box = rig.open_box()
    holders = GcHold.holders()
    if holders == 0:
        gc.unfreeze()  # undo tests/conftest.py's freeze: what is frozen below is the session's
    ballast = [[i] for i in range(50_000)]  # tracked objects, allocated before the hold
    box.bring_up()
    assert GcHold.holders() == holders + 1
    assert gc.get_freeze_count() >= len(ballast)
    assert box.stream(HoldSource(n_cycles=3)).completed
    assert GcHold.holders() == holders + 1
    assert gc.get_freeze_count() >= len(ballast)
    box.finish()
    assert GcHold.holders() == holders
    if holders == 0:
        assert gc.get_freeze_count() == 0
    box.finish()  # a second finish releases nothing more
    assert GcHold.holders() == holders
