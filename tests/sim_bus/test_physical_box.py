"""The box with every physical effect on: the tension watch on its board raises nothing
while the arm sags under gravity and still catches a snapped rope (the rope it names
may be a neighbour the snap unloaded); ``hrm sim``'s runner says which physics it runs."""

from __future__ import annotations

import io
import json
import threading
import time
import uuid
from typing import Any

import numpy as np

from drivers.config import box_config_from_dict, load_box_config
from drivers.tension_sensor import TensionSensorReader, TensionWatch
from sim_bus.box import SimBox
from sim_bus.physics import Physics
from sim_bus.runner import run_box_process
from sim_bus.tension_board import TensionBoard

SLACK_N, LIMIT_N = 5.0, 150.0  # the shipped [tension] watch
STALE_S = 0.5  # the loosest the [tension] table allows: this machine is shared


def test_the_tension_watch_catches_a_snapped_rope_on_the_physical_box() -> None:
    box = SimBox(load_box_config(None), physics=Physics.of("all"))  # motors at rest
    faults: list[str] = []
    got = threading.Event()

    def on_fault(text: str) -> None:
        faults.append(text)
        got.set()

    ids = box.actuation.motor_ids
    before = box.arm_state()  # the arm settled under gravity (the first state's solve)
    assert float(before.centres[-1, 2]) < -10.0  # it does sag
    with (
        TensionBoard(box.tension_N, rate_hz=100.0) as board,
        TensionSensorReader(board.port, len(ids), stale_after_s=STALE_S) as reader,
    ):
        watch = TensionWatch(reader, ids, on_fault, min_N=SLACK_N, max_N=LIMIT_N).start()
        try:
            time.sleep(0.5)
            assert faults == []  # sagging under gravity, no rope leaves [5, 150] N
            box.snap_rope("j05r2")
            got.wait(5.0)
        finally:
            watch.stop()
    # caught; the rope named is the first of joint 5's below the slack limit: the joint
    # turning away from its broken rope unloads a neighbour too (j05r1 here)
    assert len(faults) == 1 and faults[0].startswith("rope j05r"), faults
    assert faults[0].endswith("N below 5 N (slack or broken)"), faults
    after = box.arm_state()
    assert after.tension_N[ids.index("j05r2")] == 0.0
    turned = np.hypot(after.alpha[4] - before.alpha[4], after.theta[4] - before.theta[4])
    assert turned > 0.01  # joint 5 turns away from its broken rope


def test_the_runner_says_which_physics_it_runs() -> None:
    doc = {"buses": {"can0": {"interface": "hrm_sim", "channel": f"p-{uuid.uuid4().hex[:8]}",
                              "bitrate": 1_000_000, "nodes": {"j01r0": 1}}}}  # fmt: skip
    out = io.StringIO()
    kwargs: dict[str, Any] = {
        "control": True,
        "out": out,
        "inp": io.StringIO("state\nquit\n"),
        "physics": Physics.of("gravity,capstan"),
    }
    t = threading.Thread(
        target=run_box_process, args=(box_config_from_dict(doc, "test"),), kwargs=kwargs
    )
    t.start()
    t.join(30.0)
    assert not t.is_alive()
    events = [json.loads(line) for line in out.getvalue().splitlines()]
    assert events[0]["event"] == "ready" and events[0]["physics"] == "gravity,capstan"
    assert events[1]["event"] == "state" and events[1]["centres"][-1][2] < -10.0  # it sags
