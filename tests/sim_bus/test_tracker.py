"""The box's laser tracker, the straight fixture and the truth through ``SimBox``,
``hrm sim`` and the in-process wiring (``--sim``)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.config import box_config_from_dict, load_box_config
from drivers.tracker import TrackerError, TrackerReader, TrackerTargetLostError
from hrm_ctrl.cli import main
from hrm_ctrl.cli._simwire import start_in_process_sim
from hrm_ctrl.errors import SimError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from sim_bus.box import SimBox
from sim_bus.runner import run_box_process
from sim_bus.truth import TrueArm, read_truth, write_truth

REPO = Path(__file__).resolve().parents[2]
ACT = load_actuation(default_robot())
TRUTH = TrueArm.perturbed(ACT, 12)


def _config():
    tag = uuid.uuid4().hex[:8]
    kw = [{"interface": "hrm_sim", "channel": f"trk-{tag}-{k}"} for k in range(2)]
    return load_box_config(None).with_bus_kwargs(kw)


@pytest.fixture
def box() -> Iterator[SimBox]:
    b = SimBox(_config(), truth=TRUTH, tension_noise_N=0.0, initial_counts=TRUTH.motor_zero_counts)
    with b:
        yield b


def test_tracker_measures_the_true_end_point_in_its_frame(box: SimBox) -> None:
    assert box.truth is TRUTH
    tracker = box.start_tracker()
    assert box.start_tracker() is tracker  # once
    with TrackerReader(tracker.port, timeout_s=2.0) as reader:
        p = reader.measure(100)
        want = TRUTH.to_tracker(box.end_point_mm())
        assert np.abs(p - want).max() < 0.03  # sigma 0.005 mm for the mean of 100
        # the tracker's frame is not the base's: the raw point is metres away from O_13
        assert np.linalg.norm(p - box.end_point_mm()) > 500.0
        # in the fixture the rope geometry is straight: the links at their offsets
        box.set_straight_fixture(True)
        held = joint_centres(
            TRUTH.model(ACT.robot), TRUTH.alpha_offset_rad, TRUTH.theta_offset_rad
        )[-1]
        assert np.allclose(box.end_point_mm(), held)
        assert np.abs(reader.measure(100) - TRUTH.to_tracker(held)).max() < 0.03
        # the base plate's nests, in the tracker's frame: the frame is found from them
        fid = ACT.robot.base_fiducials
        for k in range(len(fid)):
            got = reader.measure(50, fiducial=k + 1)
            assert np.abs(got - TRUTH.to_tracker(fid[k])).max() < 0.04
        with pytest.raises(TrackerError, match="NONEST"):
            reader.measure(1, fiducial=len(fid) + 1)
        box.tracker_lose_target(True)
        with pytest.raises(TrackerTargetLostError):
            reader.measure()
        box.tracker_lose_target(False)
        assert reader.measure().shape == (3,)
    assert any("tracker target lost" in e for e in box.events)


def test_fixture_tensions_at_the_true_zero_and_freed(box: SimBox) -> None:
    pre = float(ACT.routing.pretension_N)
    box.set_straight_fixture(True)
    assert np.allclose(box.tension_N(), pre, atol=1e-6)  # at the true zero counts
    s = box.arm_state()
    assert s.fixture and not s.rope_alpha.any() and np.allclose(s.alpha, TRUTH.alpha_offset_rad)
    box.set_straight_fixture(False)
    free = box.arm_state()
    assert not free.fixture
    # off the fixture the arm at its true zeros keeps its rope geometry straight (phi = 0):
    # the links stand at the joint offsets
    assert np.abs(free.rope_alpha).max() < 1e-4 and np.abs(free.rope_theta).max() < 1e-4
    assert np.allclose(free.alpha, TRUTH.alpha_offset_rad, atol=1e-4)


def test_tracker_stops_with_the_box_and_needs_starting() -> None:
    b = SimBox(_config(), truth=TRUTH).start()
    try:
        with pytest.raises(SimError, match="not started"):
            b.tracker_lose_target(True)
        t = b.start_tracker()
        port = t.port
    finally:
        b.stop()
    assert b.tracker is None and not t._thread.is_alive()  # type: ignore[union-attr]
    with pytest.raises(TrackerError):
        TrackerReader(port, timeout_s=0.05).measure()


def test_runner_with_truth_fixture_and_tracker() -> None:
    tag = uuid.uuid4().hex[:8]
    doc = {
        "buses": {
            "can0": {
                "interface": "hrm_sim",
                "channel": f"rt-{tag}",
                "bitrate": 1_000_000,
                "nodes": {"j01r0": 1},
            }
        }
    }
    cfg = box_config_from_dict(doc, "test")
    out = io.StringIO()
    r_in = io.StringIO(
        "state\nfixture off\ntracker-lost on\ntracker-lost maybe\ntruth\nstate\nquit\n"
    )
    t = threading.Thread(
        target=run_box_process,
        args=(cfg,),
        kwargs={
            "control": True,
            "out": out,
            "inp": r_in,
            "truth": TRUTH,
            "fixture": True,
            "tracker": True,
        },
    )
    t.start()
    t.join(20.0)
    assert not t.is_alive()
    events = [json.loads(line) for line in out.getvalue().splitlines()]
    kinds = [e["event"] for e in events]
    assert kinds == ["ready", "state", "fixture", "tracker", "error", "truth", "state", "stopped"]
    ready = events[0]
    assert Path(ready["tracker_port"]).name.isdigit() and ready["fixture"] is True
    assert ready["truth"] == TRUTH.source
    assert events[1]["fixture"] is True and events[6]["fixture"] is False
    assert np.allclose(events[1]["alpha"], TRUTH.alpha_offset_rad)  # rope geometry straight
    assert "on|off" in events[4]["error"]
    truth = {k: v for k, v in events[5].items() if k not in ("event", "source")}
    assert truth == TRUTH.to_dict()


def test_in_process_wiring_carries_truth_fixture_and_tracker_port() -> None:
    cfg = load_box_config(None)
    config, sim = start_in_process_sim(cfg, ACT, "hrm_sim", truth=TRUTH, tracker=True, fixture=True)
    try:
        assert config.tracker is not None and config.tracker.port == sim.tracker.port
        assert sim.truth is TRUTH and sim.arm.fixture
        with TrackerReader(config.tracker.port, config.tracker.timeout_s) as reader:
            assert reader.measure(5).shape == (3,)
    finally:
        sim.stop()
    config, sim = start_in_process_sim(cfg, ACT, "virtual")  # the old call still works
    try:
        assert config.tracker is None and sim.truth.is_nominal(ACT) and not sim.arm.fixture
    finally:
        sim.stop()


def test_hrm_sim_perturb_tracker_and_write_truth(tmp_path: Path) -> None:
    cfg = tmp_path / "box.toml"
    cfg.write_text(
        "[buses.can0]\ninterface = 'virtual'\nchannel = 'trk'\nbitrate = 1000000\n"
        "[buses.can0.nodes]\nj01r0 = 1\n"
    )
    out = tmp_path / "truth.toml"
    argv = ["sim", "--config", str(cfg), "--perturb", "5", "--max-slack", "1.5", "--tracker"]
    argv += ["--fixture", "--write-truth", str(out), "--duration", "0.3"]
    proc = subprocess.run(
        [sys.executable, "-m", "hrm_ctrl.cli", *argv],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    ready = json.loads(proc.stdout.splitlines()[0])
    assert ready["event"] == "ready" and ready["tracker_port"].startswith("/dev/")
    assert ready["fixture"] is True and ready["truth"] == "<perturbed seed 5>"
    want = TrueArm.perturbed(ACT, 5, max_slack_mm=1.5)
    assert read_truth(out, ACT).to_dict() == want.to_dict()


def test_hrm_sim_truth_arguments_refused_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = tmp_path / "t.toml"
    write_truth(truth, TRUTH)
    bad = tmp_path / "bad.toml"
    bad.write_text("[slack_mm]\nj01r0 = -1.0\n")
    for argv, match in [
        (["sim", "--truth", str(truth), "--write-truth", str(truth)], "would overwrite"),
        (["sim", "--max-slack", "2"], "--max-slack needs --perturb"),
        (["sim", "--perturb", "1", "--max-slack", "-1"], "--max-slack must be in"),
        (["sim", "--perturb", "-1"], "seed must be an integer >= 0"),
        (["sim", "--truth", str(bad)], "slack_mm.j01r0"),
        (["sim", "--truth", str(tmp_path / "none.toml")], "not found"),
    ]:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and match in err, err
    with pytest.raises(SystemExit):  # argparse: not both
        main(["sim", "--truth", str(truth), "--perturb", "3"])
    assert "not allowed with" in capsys.readouterr().err
