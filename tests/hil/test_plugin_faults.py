"""HIL fault tests at production settings: every fault stops every axis, and the host
detects it and stops the drives within the production watchdogs, measured on the wire
(the session's CAN logs: frames the host sent, frames it received, with their wire
timestamps) -- not on the test's clock.

The production watchdogs (``[control]`` of the drivers' ``box.toml``): a node's TPDO
missing ``missing_tpdo_cycles`` = 3 consecutive cycles, a heartbeat older than
``heartbeat_timeout_ms`` = 350 ms; an EMCY or a fault in a statusword at the next control
deadline; the tension watch at the ``[tension]`` defaults (``stale_s`` 0.1 s, bad data past
``garbage_per_s`` 5/s, a rope below ``slack_N`` 5 N).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any

import pytest

import drivers.protocol.cia402 as cia
from drivers.safety.causes import StopKind
from drivers.sources import HoldSource
from hrm_ctrl.hil.rig import BusKind, HilHost, HostRun
from hrm_ctrl.hil.wirelog import EMCY_BASE, HEARTBEAT_BASE, TPDO1_BASE, WireLog
from tests.hrm_ctrl.cli.cli_helpers import STALL_TOLERANT_PRODUCTION
from tests.vcan_guest import in_vcan_guest

# over the cross-process bus and udp_multicast (both hold at production settings here),
# SocketCAN where the kernel has vcan0/vcan1; --hrm-bus on the command line overrides
# A run stopped on its own is rerun only on a machine stall through a production window.
# Alone among the pytest-xdist workers (tests/conftest.py): beside the other worker's
# simulated boxes under SCHED_FIFO, a box here missed its TPDOs for the 3-cycle (30 ms)
# production window with no machine stall the probe saw.
pytestmark = [
    pytest.mark.hrm_buses("ipc", "udp_multicast", "socketcan"),
    STALL_TOLERANT_PRODUCTION,
    pytest.mark.exclusive,
]

#: The small box of the fault tests: few drives, light load, the motors the faults name.
FAULT_NODES: tuple[dict[str, int], ...] = (
    {"j01r0": 1, "j05r1": 2, "j03r1": 3},
    {"j08r0": 4, "j08r2": 5},
)
FAULT_AFTER_S = 0.4  # into the stream
#: Receive latency the wire-time bounds allow on top of a watchdog: a frame's log time
#: is its sender's (ipc) or the receiving socket's (udp) clock, the host's watchdog runs
#: on its control deadlines, after its receive thread handed the frame over (measured
#: 0.3-4 ms on the quiet machine).  Besides, every bound allows the host's own lag in
#: that run (:func:`host_lag_s`): a watchdog cannot act before the late deadline it runs at.
LATENCY_S = 0.015
#: the tension watch checks every 10 ms; the board sends every 10 ms (100 Hz)
TENSION_CHECK_S = 0.010
BOARD_PERIOD_S = 0.010
#: The quick stop confirmed: every node still answering shows it left OPERATION_ENABLED
#: (the supervisor repeats the quick stop each period up to 10 periods).
CONFIRM_PERIODS = 10
FIGURES = os.environ.get("HRM_HIL_FIGURES")  # a file: append each fault's measured times


#: In the vcan guest (``tools/vcan-guest``: one CPU for box and host, 30-40 us per system
#: call) the bring-up's SDO answers came later than 0.5 s, and at 100 Hz (and at 50 and
#: 40 Hz in most runs) the box's TPDOs went missing 3 cycles before the fault: over
#: SocketCAN there the box runs at 25 Hz (the watchdogs in cycles and the bounds in
#: periods as at production settings), the host waits 2 s for an SDO answer and runs its
#: threads under ``SCHED_FIFO`` 20.  The production-rate fault runs are the ``ipc`` ones.
#: At 25 Hz the quick stop's 10 periods are as long as the delay fault's 400 ms: the
#: delayed node's late TPDO falls inside them and counts as its confirmation, 0.5 s after
#: the stop (a strict xfail there: :func:`guest_rate_limits`).
GUEST_CONTROL: dict[str, Any] = {"rate_hz": 25, "sdo_timeout_s": 2.0, "realtime_priority": 20}


@pytest.fixture(scope="module")
def hrm_box_nodes() -> tuple[dict[str, int], ...]:
    return FAULT_NODES


@pytest.fixture(scope="module")
def hrm_control(hrm_bus_kind: BusKind) -> dict[str, Any]:
    """Production settings; over SocketCAN in the vcan guest :data:`GUEST_CONTROL`."""
    if hrm_bus_kind is BusKind.SOCKETCAN and in_vcan_guest():
        return dict(GUEST_CONTROL)
    return {}


@dataclass
class Measured:
    host: HilHost  # the session that ran it
    run: HostRun
    record: dict[str, Any]
    wire: WireLog
    quick_stop_s: float  # wire time of the host's first quick-stop RPDO
    confirmed_s: float | None  # ... every answering node left OPERATION_ENABLED
    silent: list[str]  # nodes with no TPDO after the quick stop


def play_with_fault(
    host: HilHost,
    spec: str,
    kinds: tuple[str, ...],
    names: str,
    n_cycles: int = 400,
    silenced: tuple[str, list[int]] | None = None,
) -> Measured:
    """Hold with ``spec`` injected ``FAULT_AFTER_S`` into the stream.  A run the host
    stopped on its own -- before the fault was sent, or on causes none of which is the
    fault's (``kinds`` naming ``names``) -- tested nothing of the fault: it is counted
    (``FIGURES``) and fails; the module's ``stall_tolerant`` marker reruns it only when the
    stall probe saw the machine stall through a production watchdog window.  So does a run
    whose quick stop came before the fault took effect on the wire: ``silenced`` (bus, node
    ids) are the nodes the fault silences, and one of them still sending a TPDO after the
    quick stop means the stop was not the fault's."""
    run = host.play(HoldSource(n_cycles=n_cycles), fault_spec=spec, fault_after_s=FAULT_AFTER_S)
    record = host.close()
    unrelated = run.error is not None and not any(
        c.kind in kinds and names in c.text for c in run.error.causes
    )
    m = None if run.stopped_before_fault() or unrelated else _measure(host, run, record, spec)
    if m is not None and not _answered_after_the_stop(m, silenced):
        return m
    why = run.describe() if m is None else f"{silenced} answered after the quick stop"
    figure(spec, spurious_stop=why)
    raise AssertionError(f"{spec}: the run stopped on its own: {why}")


def _measure(host: HilHost, run: HostRun, record: dict[str, Any], spec: str) -> Measured:
    names = [b.name for b in host.config.buses]
    wire = WireLog.read(record["can_logs"], names)
    qs = wire.quick_stop()
    assert qs is not None, f"{spec}: no quick stop on the wire"
    nodes = {b.name: dict(b.nodes) for b in host.config.buses}
    confirmed, silent = wire.stop_confirmed(nodes, qs.t_s)
    return Measured(host, run, record, wire, qs.t_s, confirmed, silent)


def _answered_after_the_stop(m: Measured, silenced: tuple[str, list[int]] | None) -> bool:
    if silenced is None:
        return False
    bus, node_ids = silenced
    motors = [mtr for b in m.host.config.buses if b.name == bus
              for mtr, n in b.nodes.items() if n in node_ids]  # fmt: skip
    return any(mtr not in m.silent for mtr in motors)


def figure(spec: str, **values: Any) -> None:
    if FIGURES:
        with open(FIGURES, "a") as f:
            f.write(json.dumps({"fault": spec, **values}) + "\n")


def assert_stopped_and_logged(m: Measured, kinds: tuple[str, ...], names: str) -> None:
    """Every axis stopped, the cause named, the run record saying why, the stop confirmed
    on the wire within ``CONFIRM_PERIODS``."""
    err = m.run.error
    assert err is not None, "the host did not stop"
    assert any(c.kind in kinds and names in c.text for c in err.causes), m.run.describe()
    enabled = [
        mtr
        for mtr, sw in m.run.statuswords_after.items()
        if cia.decode_state(sw) == cia.State402.OPERATION_ENABLED
    ]
    assert enabled == [], f"still enabled: {enabled}"
    end = [e for e in m.record["events"] if e["kind"] == "stream_end"]
    assert end and "stopped" in end[-1]["text"] and names in end[-1]["text"]
    period = m.record["config"]["control"]["rate_hz"] ** -1
    assert m.confirmed_s is not None and m.confirmed_s != float("inf"), (m.silent, m.run.describe())
    assert m.confirmed_s - m.quick_stop_s <= CONFIRM_PERIODS * period


def host_lag_s(m: Measured) -> float:
    """How late the host's control loop ran in this stream at worst: its largest SYNC
    lateness plus every grid slot it skipped (each a period), from the stream's statistics."""
    res = m.run.result if m.run.result is not None else m.run.error.result
    st = res.stats
    period = st["period_s"]
    return float(st.get("lateness_max_s", 0.0)) + st.get("skipped_slots", 0) * period


def tpdo_gap(m: Measured, bus: str, nodes: list[int]) -> tuple[float, int]:
    """(wire time of the last TPDO of ``nodes`` on ``bus`` before the quick stop, SYNCs the
    host sent on ``bus`` from then to the quick stop)."""
    last = [m.wire.last_received(bus, TPDO1_BASE + n, before_s=m.quick_stop_s) for n in nodes]
    assert all(f is not None for f in last), f"no TPDO of {nodes} on {bus}"
    t = max(f.t_s for f in last if f is not None)
    return t, m.wire.syncs_sent(bus, t, m.quick_stop_s)


# ------------------------------------------------------------------ CAN-side watchdogs


def test_heartbeat_loss_detected_at_the_production_timeout(hrm_host: HilHost) -> None:
    spec = "heartbeat-stop:j05r1"  # can0 node 2
    m = play_with_fault(hrm_host, spec, ("heartbeat",), "j05r1")
    assert_stopped_and_logged(m, ("heartbeat",), "j05r1")
    control = m.record["config"]["control"]
    timeout_s = control["heartbeat_timeout_ms"] / 1000.0
    period = 1.0 / control["rate_hz"]
    last_hb = m.wire.last_received("can0", HEARTBEAT_BASE + 2, before_s=m.quick_stop_s)
    assert last_hb is not None
    detect_s = m.quick_stop_s - last_hb.t_s
    lag = host_lag_s(m)
    figure(spec, detect_s=detect_s, host_lag_s=lag, confirm_s=m.confirmed_s - m.quick_stop_s)
    # not before the timeout (the watchdog, not something else), within a period after it
    assert timeout_s <= detect_s <= timeout_s + period + LATENCY_S + lag, (detect_s, lag)


def test_drive_fault_emcy_stops_within_one_period(hrm_host: HilHost) -> None:
    spec = "drive-fault:j03r1"  # can0 node 3
    m = play_with_fault(hrm_host, spec, ("emcy", "fault", "state"), "j03r1")
    assert_stopped_and_logged(m, ("emcy", "fault", "state"), "j03r1")
    period = 1.0 / m.record["config"]["control"]["rate_hz"]
    # the EMCY that stopped it: the last one before the quick stop, a non-zero error code
    emcy = m.wire.last_received("can0", EMCY_BASE + 3, before_s=m.quick_stop_s)
    assert emcy is not None and int.from_bytes(emcy.data[:2], "little") != 0, emcy
    detect_s = m.quick_stop_s - emcy.t_s
    lag = host_lag_s(m)
    figure(spec, detect_s=detect_s, host_lag_s=lag, confirm_s=m.confirmed_s - m.quick_stop_s)
    assert detect_s <= period + LATENCY_S + lag, (detect_s, lag)


TPDO_FAULTS = [
    ("drop:can1:0x184:all", "can1", [4], "j08r0"),
    ("delay:can0:400:0x181:all", "can0", [1], "j01r0"),
    ("bus-off:can1", "can1", [4, 5], "bus can1"),
]


def guest_rate_limits(request: pytest.FixtureRequest, spec: str) -> None:
    """The delay fault in the vcan guest's 25 Hz run (:data:`GUEST_CONTROL`) is a strict
    xfail: its 400 ms delay is no longer than the quick stop's 10 periods there."""
    if spec.startswith("delay") and in_vcan_guest():
        request.applymarker(
            pytest.mark.xfail(
                strict=True,
                reason="vcan guest at 25 Hz: the delayed node's TPDO inside the quick "
                "stop's 10 periods confirms it late (a 400 ms delay is sized for 100 Hz)",
            )
        )


@pytest.mark.parametrize(
    ("spec", "bus", "nodes", "names"), TPDO_FAULTS, ids=[f[0] for f in TPDO_FAULTS]
)
def test_missing_tpdos_detected_after_the_production_cycles(
    request: pytest.FixtureRequest,
    hrm_host: HilHost,
    spec: str,
    bus: str,
    nodes: list[int],
    names: str,
) -> None:
    guest_rate_limits(request, spec)
    kinds = ("tpdo_missing", "heartbeat") if spec.startswith("bus-off") else ("tpdo_missing",)
    # the faults that silence their nodes (all but the delay): none answers after the stop
    silenced = None if spec.startswith("delay") else (bus, nodes)
    m = play_with_fault(hrm_host, spec, kinds, names, silenced=silenced)
    assert_stopped_and_logged(m, kinds, names)
    cycles = m.record["config"]["control"]["missing_tpdo_cycles"]
    last_t, syncs = tpdo_gap(m, bus, nodes)
    figure(
        spec,
        syncs_without_tpdo=syncs,
        detect_s=m.quick_stop_s - last_t,
        confirm_s=m.confirmed_s - m.quick_stop_s,
        silent=m.silent,
    )
    # the quick stop follows the 3rd SYNC left unanswered (the check runs at the next
    # deadline, before its SYNC); a TPDO late past its deadline adds a cycle at most
    assert cycles <= syncs <= cycles + 1, (syncs, m.run.describe())


# ------------------------------------------------------------------ tension watch

TENSION_FAULTS = [
    ("rope-snap:j08r2", "j08r2"),
    ("sensor-silent", "tension sensor"),
    ("sensor-corrupt:100000", "tension sensor"),
]


@pytest.mark.parametrize(("spec", "names"), TENSION_FAULTS, ids=[f[0] for f in TENSION_FAULTS])
def test_tension_faults_stop_every_axis(hrm_host: HilHost, spec: str, names: str) -> None:
    """The tension board is a serial line, not on the CAN wire: detection is measured from
    the fault command to the stop cause (host monotonic clock), the stop on the wire."""
    m = play_with_fault(hrm_host, spec, ("tension",), names)
    assert_stopped_and_logged(m, ("tension",), names)
    cause = next(c for c in m.run.error.causes if c.kind is StopKind.TENSION)
    stale_s = m.host.tension.stale_s
    assert m.run.fault_sent_s is not None
    detect_s = cause.time_s - m.run.fault_sent_s
    assert m.run.fault_applied_s is not None
    command_s = m.run.fault_applied_s - m.run.fault_sent_s  # the box's reply round trip
    lag = host_lag_s(m)
    figure(
        spec,
        detect_s=detect_s,
        command_s=command_s,
        host_lag_s=lag,
        confirm_s=m.confirmed_s - m.quick_stop_s,
    )
    # a silent or corrupt board goes stale after stale_s (its newest frame up to one
    # board period old when it fell silent); a snapped rope reads slack at the board's
    # next frame; then the watch's next check
    bound = stale_s + BOARD_PERIOD_S + TENSION_CHECK_S + command_s + LATENCY_S + lag
    assert 0.0 < detect_s <= bound, (detect_s, command_s, lag)


def test_sensor_garbage_past_its_rate_stops_the_host(hrm_host: HilHost) -> None:
    """Garbage before every frame (100 runs/s, far past the 5/s a healthy board never
    reaches) stops every axis naming the sensor; the valid frames between still parse."""
    m = play_with_fault(hrm_host, "sensor-garbage:300", ("tension",), "tension sensor")
    assert_stopped_and_logged(m, ("tension",), "tension sensor")
    assert m.run.tension_fault is not None and "garbage" in m.run.tension_fault
