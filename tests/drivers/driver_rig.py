"""Rigs for the driver tests: a few simulated drives (sim_bus) on every CAN backend.

The drivers talk to the simulated drives only through python-can buses; a
sniffer bus on every channel records what went over the wire.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from drivers.config import BoxConfig, box_config_from_dict
from drivers.safety.subset import ActuationSubset
from drivers.session import DriveSession
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.runtime.process_box import BoxProcess
from sim_bus.box import SimBox
from sim_bus.in_process import IN_PROCESS_MISSING_TPDO_CYCLES
from tests.vcan_guest import in_vcan_guest

# The rig's drives are fresh simulators (pre-operational, no other master): a short
# listen before the first reset keeps the suite fast; tests of the listen set their own.
RIG_LISTEN_S = 0.1
SMALL_BUSES: tuple[dict[str, int], ...] = ({"j01r0": 1, "j01r1": 2}, {"j07r0": 3})
#: In the vcan guest (``tools/vcan-guest``: one CPU shared by the rig's drives and host,
#: 30-40 us per system call) a simulated drive's SDO answer came later than the production
#: 0.5 s during a bring-up (``No SDO response received``): over SocketCAN there the rigs
#: wait this long for one unless the test sets its own; the SDO timeout is no watchdog.
GUEST_SDO_TIMEOUT_S = 2.0


@pytest.fixture(scope="session")
def actuation() -> Actuation:
    return load_actuation(default_robot())


class Sniffer(can.Listener):
    """Records every frame seen on a bus (with a receive time)."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()
        self._per_id: dict[int, int] = {}

    def on_message_received(self, msg: can.Message) -> None:
        msg.timestamp = time.time() if not msg.timestamp else msg.timestamp
        with self.lock:
            self.frames.append(msg)
            self._per_id[msg.arbitration_id] = self._per_id.get(msg.arbitration_id, 0) + 1

    def count(self, arbitration_id: int) -> int:
        """How many frames of ``arbitration_id`` it has recorded, without copying them: a
        condition counting them in a :meth:`snapshot` costs 3.3 ms at 5,000 frames (on
        the loaded host), so polled every 5 ms (:func:`wait_until`) through a 36-drive
        bring-up it takes about half a CPU, the vcan guest's only one beside the box and
        the host."""
        with self.lock:
            return self._per_id.get(arbitration_id, 0)

    def snapshot(self) -> list[can.Message]:
        with self.lock:
            return list(self.frames)

    def clear(self) -> None:
        with self.lock:
            self.frames.clear()
            self._per_id.clear()


@dataclass
class Rig:
    config: BoxConfig
    limits: ActuationSubset
    sim: SimBox
    sniffers: list[Sniffer]
    box: DriveSession | None = None
    cleanup: list[Callable[[], None]] = field(default_factory=list)

    def open_box(self, log_dir: Path | None = None, **kw: Any) -> DriveSession:
        kw.setdefault("listen_s", RIG_LISTEN_S)
        kw.setdefault("allow_uncalibrated", True)  # the rig tests the drivers, not calibration
        self.box = DriveSession(self.config, self.limits, log_dir=log_dir, **kw)
        return self.box

    def brought_up_box(self) -> DriveSession:
        """A box opened and brought up, the sniffers cleared: they hold what follows."""
        box = self.open_box()
        box.bring_up()
        for sn in self.sniffers:
            sn.clear()
        return box


RIG_BOOTUP_TIMEOUT_S = 2.0  # every node's boot-up within this of its bus's NMT reset


def make_config(
    bus_kwargs: list[dict[str, Any]],
    buses: tuple[dict[str, int], ...] = SMALL_BUSES,
    **control: Any,
) -> BoxConfig:
    # the rigs' simulated drives share this interpreter: the in-process TPDO tolerance
    # unless the test sets its own (CI saw a 3-node rig's TPDOs 3 cycles late at 3, and an
    # 18-drive one under load)
    control.setdefault("missing_tpdo_cycles", IN_PROCESS_MISSING_TPDO_CYCLES)
    doc: dict[str, Any] = {
        "control": {"bootup_timeout_s": RIG_BOOTUP_TIMEOUT_S, **control},
        "buses": {},
    }
    for k, (kw, nodes) in enumerate(zip(bus_kwargs, buses, strict=True)):
        kw = dict(kw)
        kw.pop("bitrate", None)
        doc["buses"][f"bus{k}"] = {
            "interface": kw.pop("interface"),
            "channel": kw.pop("channel"),
            "bitrate": 1_000_000,
            "options": kw,
            "nodes": dict(nodes),
        }
    return box_config_from_dict(doc, "<test rig>")


@pytest.fixture(params=["shared", "hrm_sim"])
def bus_backend(request: pytest.FixtureRequest) -> Callable[[], dict[str, Any]]:
    """The shared ``can_backend`` (virtual, udp_multicast, socketcan) plus the project's
    own ``hrm_sim`` interface: a simulated wire at 1 Mbit/s that delivers frames after
    their wire time, in identifier order (so frame ordering and bus time are real).
    ``can_backend`` is set up only for ``shared``: an ``hrm_sim`` item of another
    ``can_backend`` skips for that reason, not for want of that backend (``rig_factory``
    names ``can_backend`` after this fixture, which parametrises its items over it)."""
    if request.param == "hrm_sim":
        if request.node.callspec.params.get("can_backend") != "virtual":
            pytest.skip("hrm_sim runs once (with the virtual parametrisation)")
        return lambda: {
            "interface": "hrm_sim",
            "channel": f"hrm-drv-{uuid.uuid4().hex[:12]}",
            "bitrate": 1_000_000,
        }
    factory: Callable[[], dict[str, Any]] = request.getfixturevalue("can_backend")
    return factory


@pytest.fixture
def rig_factory(
    bus_backend: Callable[[], dict[str, Any]],
    can_backend: Callable[[], dict[str, Any]],
    actuation: Actuation,
) -> Iterator[Callable[..., Rig]]:
    """``make(buses, sim_buses, sim_counts, guest_control, **control)``: a rig of simulated
    drives on ``buses`` (``[control]`` keys ``control``); over SocketCAN in the vcan guest
    ``guest_control`` overrides them (a rig sized for the guest) and the SDO timeout is
    :data:`GUEST_SDO_TIMEOUT_S` unless set."""
    rigs: list[Rig] = []
    opened: list[Any] = []

    def make(
        buses: tuple[dict[str, int], ...] = SMALL_BUSES,
        sim_buses: tuple[dict[str, int], ...] | None = None,
        sim_counts: dict[str, int] | None = None,
        guest_control: dict[str, Any] | None = None,
        **control: Any,
    ) -> Rig:
        kwargs = [bus_backend() for _ in buses]
        if in_vcan_guest() and kwargs[0]["interface"] == "socketcan":
            # a test sized for the guest says why beside its ``guest_control``
            control = {**control, **(guest_control or {})}
            control.setdefault("sdo_timeout_s", GUEST_SDO_TIMEOUT_S)
        config = make_config(kwargs, buses, **control)
        sim_cfg = make_config(kwargs, sim_buses or buses, **control)
        initial = np.zeros(actuation.n_motors, dtype=np.int64)
        for motor, counts in (sim_counts or {}).items():
            initial[actuation.motor_ids.index(motor)] = counts
        sim = SimBox(
            sim_cfg,
            actuation=actuation,
            initial_counts=initial,
        )
        sim.start()
        opened.append(sim.stop)
        sniffers = []
        for kw in kwargs:
            bus = can.Bus(**kw)
            sn = Sniffer()
            notifier = can.Notifier(bus, [sn], 0.05)
            opened.append(bus.shutdown)
            opened.append(lambda n=notifier: n.stop(1.0))
            sniffers.append(sn)
        motors = tuple(m for nodes in buses for m in nodes)
        rig = Rig(config, ActuationSubset(actuation, motors), sim, sniffers)
        rigs.append(rig)
        return rig

    yield make
    for rig in rigs:
        if rig.box is not None:
            try:
                rig.box.__exit__(None, None, None)
            except Exception:
                pass
    for fn in reversed(opened):
        try:
            fn()
        except Exception:
            pass


def rpdo_targets_per_sync(
    frames: list[can.Message], node_ids: list[int], start_after: float = 0.0
) -> list[dict[int, tuple[int, int]]]:
    """Group the wire's RPDOs by SYNC: for each SYNC, {node: (controlword, target)}
    of the RPDOs seen since the previous SYNC (a node sending twice raises)."""
    out: list[dict[int, tuple[int, int]]] = []
    current: dict[int, tuple[int, int]] = {}
    for m in frames:
        if m.timestamp < start_after:
            continue
        cid = m.arbitration_id
        if cid == 0x080:
            out.append(current)
            current = {}
        elif 0x200 < cid <= 0x27F and (cid - 0x200) in node_ids:
            n = cid - 0x200
            if n in current:
                raise AssertionError(f"node {n}: two RPDOs before one SYNC")
            data = bytes(m.data)
            current[n] = (
                int.from_bytes(data[:2], "little"),
                int.from_bytes(data[2:6], "little", signed=True),
            )
    return out


def first_time(frames: list[can.Message], pred: Callable[[can.Message], bool]) -> float:
    for m in frames:
        if pred(m):
            return float(m.timestamp)
    return float("nan")


def set_sim_state(rig: Rig, motor: str, state: Any) -> None:
    """Put one simulated drive into a CiA 402 state silently (no EMCY, no frame): a drive
    that changed state without telling the host (e.g. a local stop input)."""
    with rig.sim._lock:
        rig.sim.drives[motor].state = state


def wait_until(pred: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.005)
    return pred()


__all__ = ["Rig", "Sniffer", "first_time", "make_config", "np", "rpdo_targets_per_sync"]


def send_from_outside(rig: Rig, bus: int, msg: can.Message) -> None:
    """A frame from another device on bus ``bus`` (its own python-can bus object)."""
    other = can.Bus(**rig.config.buses[bus].bus_kwargs())
    try:
        other.send(msg)
    finally:
        other.shutdown()


@contextmanager
def sending_from_outside(
    rig: Rig, bus: int, msg: can.Message, period_s: float
) -> Iterator[threading.Thread]:
    """Another device on bus ``bus`` (its own python-can bus object) sending ``msg`` every
    ``period_s`` for the length of the block; stopped (and its bus shut down) on leaving."""
    stop = threading.Event()

    def send() -> None:
        other = can.Bus(**rig.config.buses[bus].bus_kwargs())
        try:
            while not stop.is_set():
                other.send(msg)
                stop.wait(period_s)
        finally:
            other.shutdown()

    thread = threading.Thread(target=send, name="outside-sender", daemon=True)
    thread.start()
    try:
        yield thread
    finally:
        stop.set()
        thread.join(2.0)


@dataclass(frozen=True)
class BoxView:
    """What a test reads of a simulated box in its own process
    (:class:`~hrm_ctrl.runtime.process_box.BoxProcess`, over its ``state`` and ``fault``
    control commands), under the names :class:`sim_bus.box.SimBox` gives them."""

    process: BoxProcess

    def counts(self) -> np.ndarray:
        """Every drive's actual position, the rope layer's order."""
        return np.asarray(self.process.command("state", "state")["counts"], dtype=np.int64)

    def statuswords(self) -> dict[str, int]:
        """Every drive's statusword, by motor."""
        words = self.process.command("state", "state")["statuswords"]
        return {m: int(sw) for m, sw in words.items()}

    def snap_rope(self, motor: str) -> None:
        """Snap ``motor``'s rope (the ``rope-snap`` fault)."""
        self.process.fault(f"rope-snap:{motor}")
